//! Parity of the RoBERTa encoder and byte-level BPE tokenizer with Hugging Face on a tiny random
//! RobertaModel (FLAME semantics: padding and truncation to 20, pad-aware position ids).
//!
//! Reference: tools/make_text_fixtures.py (transformers RobertaModel, eager attention, float32);
//! fixtures: tests/fixtures/text_roberta_tiny.safetensors (weights, no prefix),
//! tests/fixtures/text_roberta_expected.safetensors, tests/fixtures/text_roberta_sentences.json,
//! tests/fixtures/tiny_roberta/{config,tokenizer}.json.

use std::path::{Path, PathBuf};

use flame::checkpoint::{ModelFile, TOKENIZER_KEY};
use flame::config::{Config, TextEncoderConfig};
use flame::text::{TextEncoder, Tokens};
use safetensors::{Dtype, SafeTensors};

const TOL: f32 = 1e-4;
const FLAME_MAX_LENGTH: usize = 20;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The encoder configuration from the Hugging Face config.json of the tiny model.
fn config_from_hf(path: &Path) -> TextEncoderConfig {
    let text = std::fs::read_to_string(path).expect("config.json");
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
        max_length: FLAME_MAX_LENGTH,
        hidden_act: v["hidden_act"].as_str().expect("hidden_act").to_string(),
    }
}

fn load_tiny() -> TextEncoder {
    let file = ModelFile::open(&fixture("text_roberta_tiny.safetensors")).expect("weights open");
    let cfg = config_from_hf(&fixture("tiny_roberta/config.json"));
    let tok =
        std::fs::read_to_string(fixture("tiny_roberta/tokenizer.json")).expect("tokenizer.json");
    TextEncoder::load(&file, "", &cfg, &tok).expect("tiny RoBERTa loads")
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

#[test]
fn tiny_roberta_matches_transformers() {
    let enc = load_tiny();
    let doc: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture("text_roberta_sentences.json")).unwrap(),
    )
    .unwrap();
    let full_max = doc["full_max_length"].as_u64().unwrap() as usize;
    assert_eq!(full_max, enc.max_sequence_length());
    let bytes = std::fs::read(fixture("text_roberta_expected.safetensors")).expect("fixture");
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let texts: Vec<&str> = doc["sentences"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["text"].as_str().unwrap())
        .collect();
    assert!(texts.len() >= 24);
    let (mut worst_h, mut worst_p) = (0f32, 0f32);
    let mut failures = Vec::new();
    for (i, text) in texts.iter().enumerate() {
        // FLAME: padded to 20 through `encode`.
        let tokens = enc.tokenize(text, FLAME_MAX_LENGTH, true).unwrap();
        assert_eq!(
            tokens.ids,
            ids(&st, &format!("pad.{i}.ids")),
            "padded ids of sentence {i} {text:?}"
        );
        let mask: Vec<u8> = ids(&st, &format!("pad.{i}.mask"))
            .iter()
            .map(|&m| m as u8)
            .collect();
        assert_eq!(tokens.mask, mask, "mask of sentence {i}");
        let padded = enc.encode(text).unwrap();
        assert_eq!(
            (padded.len, padded.hidden.len()),
            (20, 20 * enc.hidden_size())
        );
        // Unpadded, up to every position the model has.
        let tokens = enc.tokenize(text, full_max, false).unwrap();
        assert_eq!(
            tokens.ids,
            ids(&st, &format!("full.{i}.ids")),
            "unpadded ids of sentence {i} {text:?}"
        );
        let full = enc.encode_tokens(&tokens).unwrap();
        for (what, out) in [("pad", &padded), ("full", &full)] {
            let h = max_abs(&out.hidden, &f32s(&st, &format!("{what}.{i}.hidden")));
            let p = max_abs(&out.pooled, &f32s(&st, &format!("{what}.{i}.pooled")));
            (worst_h, worst_p) = (worst_h.max(h), worst_p.max(p));
            if h > TOL || p > TOL {
                failures.push(format!(
                    "{what} sentence {i} {text:?}: hidden {h:.2e} pooled {p:.2e}"
                ));
            }
        }
    }
    println!(
        "tiny roberta, {} sentences: max abs error hidden {worst_h:.2e}, pooled {worst_p:.2e}",
        texts.len()
    );
    assert!(
        failures.is_empty(),
        "beyond {TOL}:\n{}",
        failures.join("\n")
    );
}

#[test]
fn flame_prompt_format_and_limits() {
    let enc = load_tiny();
    // "" → <s> </s> then 18 pads (docs/official/flame.md#roberta-prompt-encoding).
    let empty = enc.tokenize("", 20, true).unwrap();
    assert_eq!(empty.ids, [&[0u32, 2][..], &[1; 18]].concat());
    assert_eq!(empty.mask, [&[1u8, 1][..], &[0; 18]].concat());
    // Truncation keeps both special tokens.
    let long = enc.tokenize(&"walk forward ".repeat(50), 20, true).unwrap();
    assert_eq!(
        (
            long.ids[0],
            long.ids[19],
            long.mask.iter().filter(|&&m| m == 1).count()
        ),
        (0, 2, 20)
    );
    let unpadded = enc.tokenize("a person walks.", 20, false).unwrap();
    assert!(unpadded.ids.len() < 20 && unpadded.mask.iter().all(|&m| m == 1));

    let too_long = Tokens {
        ids: vec![5; enc.max_sequence_length() + 1],
        mask: vec![1; enc.max_sequence_length() + 1],
    };
    let e = enc.encode_tokens(&too_long).unwrap_err().to_string();
    assert!(e.contains("positions allow"), "{e}");
    let bad_id = Tokens {
        ids: vec![0, 5000, 2],
        mask: vec![1; 3],
    };
    let e = enc.encode_tokens(&bad_id).unwrap_err().to_string();
    assert!(e.contains("id 5000 at index 1"), "{e}");
    let e = enc
        .encode_tokens(&Tokens {
            ids: vec![0, 2],
            mask: vec![1],
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("2 ids but 1 mask"), "{e}");
    let e = enc.tokenize("x", 1, false).unwrap_err().to_string();
    assert!(e.contains("no room"), "{e}");
}

#[test]
fn encodes_the_same_from_many_threads() {
    let enc = load_tiny();
    let want = enc.encode("a person walks forward and waves.").unwrap();
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..4)
            .map(|_| s.spawn(|| enc.encode("a person walks forward and waves.").unwrap()))
            .collect();
        for h in handles {
            let got = h.join().unwrap();
            assert_eq!(got.hidden, want.hidden);
            assert_eq!(got.pooled, want.pooled);
        }
    });
}

/// The libflame fixture model (text encoder under prefix "text.", config and tokenizer in the
/// metadata) against transformers' output for FLAME's conditional and empty prompt.
/// Fixtures: tests/fixtures/flame_tiny.safetensors, tests/fixtures/flame_tiny_expected.safetensors.
#[test]
fn flame_tiny_text_encoder_matches_transformers() {
    let file = ModelFile::open(&fixture("flame_tiny.safetensors")).unwrap();
    let cfg = Config::from_file(&file).unwrap();
    let tok = file
        .metadata(TOKENIZER_KEY)
        .expect("flame.tokenizer metadata");
    let flame::config::TextConfig::Bert(tcfg) = &cfg.text_encoder else {
        panic!("the FLAME fixture uses a RoBERTa text encoder")
    };
    let enc = TextEncoder::load(&file, "text.", tcfg, tok).unwrap();
    let bytes = std::fs::read(fixture("flame_tiny_expected.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    for (name, text) in [
        ("cond", "a person walks forward and waves."),
        ("uncond", ""),
    ] {
        let out = enc.encode(text).unwrap();
        let h = max_abs(&out.hidden, &f32s(&st, &format!("text_{name}_hidden")));
        let p = max_abs(&out.pooled, &f32s(&st, &format!("text_{name}_pooled")));
        println!("flame_tiny {name}: max abs error hidden {h:.2e}, pooled {p:.2e}");
        assert!(
            h <= TOL && p <= TOL,
            "{name} {text:?}: hidden {h:.2e} pooled {p:.2e}"
        );
    }
}
