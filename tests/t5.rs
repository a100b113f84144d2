//! T5 encoder parity: `flame::text::t5` against transformers' own `T5EncoderModel` with the
//! sentence-transformers head sentence-t5 has (mean pooling with the mask, Dense without bias,
//! L2 normalisation), on a tiny random T5 v1.0 and a small Unigram tokenizer built for the test.
//!
//! Fixtures: tests/fixtures/t5_tiny.safetensors (the weights as `T5EncoderModel` names them,
//! plus `dense.weight`), t5_tiny_tokenizer.json and t5_expected.safetensors, written by
//! tools/make_t5_fixtures.py (deterministic; needs torch, transformers, tokenizers, safetensors).
//! Asserted: the tokenizer's ids through the crate's tokenizer.json reader, `last_hidden_state`
//! within 1e-5 of its largest value (measured: at most 1.0e-5 at values up to 4.3) and the
//! sentence vector within 1e-5 (measured: 4.8e-7), for four sentences, one of 265 tokens
//! (relative distances past 128, the clamped last bucket).

use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::kernels::WeightType;
use flame::text::t5::{T5Encoder, T5_MAX_DISTANCE};
use flame::text::TextTokenizer;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn encoder(file: &ModelFile) -> T5Encoder {
    T5Encoder::load(file, "", Some("dense"), T5_MAX_DISTANCE, WeightType::F32).unwrap()
}

#[test]
fn hidden_states_and_sentence_vectors_match_transformers() {
    let file = ModelFile::open(&fixture("t5_tiny.safetensors")).unwrap();
    let t5 = encoder(&file);
    let d = t5.dims();
    assert_eq!(
        (d.d_model, d.heads, d.d_kv, d.d_ff, d.layers, d.buckets, d.out),
        (32, 4, 8, 64, 3, 32, 24)
    );
    let json = std::fs::read_to_string(fixture("t5_tiny_tokenizer.json")).unwrap();
    let tok = TextTokenizer::from_json(&json, d.vocab, 0).unwrap();
    let expected = ModelFile::open(&fixture("t5_expected.safetensors")).unwrap();
    let sentences: Vec<String> =
        serde_json::from_str(expected.metadata("sentences").unwrap()).unwrap();
    let mut longest = 0;
    for (i, text) in sentences.iter().enumerate() {
        let tokens = tok.encode(text, 512, false).unwrap();
        let want_ids = expected.tensor_any_shape(&format!("s{i}.ids")).unwrap();
        let want_ids: Vec<u32> = want_ids.data().iter().map(|&v| v as u32).collect();
        assert_eq!(tokens.ids, want_ids, "sentence {i}: ids");
        longest = longest.max(tokens.ids.len());

        let hidden = t5.hidden(&tokens.ids).unwrap();
        let want = expected.tensor_any_shape(&format!("s{i}.hidden")).unwrap();
        let diff = max_abs_diff(&hidden, want.data());
        let scale = want.data().iter().fold(0f32, |m, v| m.max(v.abs()));
        assert!(
            diff <= 1e-5 * scale.max(1.0),
            "sentence {i}: hidden off by {diff} (of {scale})"
        );

        // Padding does not change the vector.
        let mut ids = tokens.ids.clone();
        let mut mask = tokens.mask.clone();
        ids.extend([0, 0, 0]);
        mask.extend([0, 0, 0]);
        let v = t5.sentence_embedding(&ids, &mask).unwrap();
        let want = expected
            .tensor_any_shape(&format!("s{i}.embedding"))
            .unwrap();
        let diff = max_abs_diff(&v, want.data());
        assert!(diff <= 1e-5, "sentence {i}: vector off by {diff}");
        let norm: f32 = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5);
    }
    assert!(
        longest > 2 * T5_MAX_DISTANCE,
        "the long sentence has {longest} tokens"
    );
}

#[test]
fn bad_input_is_refused() {
    let file = ModelFile::open(&fixture("t5_tiny.safetensors")).unwrap();
    let t5 = encoder(&file);
    let vocab = t5.dims().vocab as u32;
    let msg = t5.hidden(&[1, vocab]).unwrap_err().to_string();
    assert!(msg.contains("outside the T5 vocabulary"), "{msg}");
    assert!(t5.hidden(&[]).is_err());
    let long = vec![1u32; flame::text::t5::T5_MAX_TOKENS + 1];
    assert!(t5
        .hidden(&long)
        .unwrap_err()
        .to_string()
        .contains("1 to 4096 tokens"));
    assert!(t5.sentence_embedding(&[1, 2], &[1]).is_err());
    // A missing Dense head, a max distance inside the exact buckets.
    assert!(T5Encoder::load(&file, "", Some("nope"), 128, WeightType::F32).is_err());
    let msg = T5Encoder::load(&file, "", None, 4, WeightType::F32)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("max_distance"), "{msg}");
    // A tokenizer whose ids do not fit the embedding table.
    let json = std::fs::read_to_string(fixture("t5_tiny_tokenizer.json")).unwrap();
    let msg = TextTokenizer::from_json(&json, 10, 0)
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains("vocab_size is 10"), "{msg}");
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()))
}
