//! Parity of the CLIP text tower and tokenizer: ids against the official OpenAI tokenizer
//! (clip-anytorch 2.6.0's simple_tokenizer.py), hidden states, pooled and projected vectors
//! against Hugging Face `CLIPTextModelWithProjection` on tiny random weights (MDM semantics:
//! context 22 with truncation, zero-padded to 77; a few at the full 77).
//!
//! Reference: tools/make_clip_fixtures.py; fixtures: tests/fixtures/clip_tokenizer/tokenizer.json,
//! tests/fixtures/clip_tiny.safetensors (HF names, token embedding stored as f16),
//! tests/fixtures/clip_cases.json, tests/fixtures/clip_expected.safetensors.

use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::text::{ClipConfig, ClipTextEncoder};
use safetensors::{Dtype, SafeTensors};

const TOL: f32 = 1e-4;
const MDM_CONTEXT: usize = 22;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn cases() -> serde_json::Value {
    let text = std::fs::read_to_string(fixture("clip_cases.json")).expect("clip_cases.json");
    serde_json::from_str(&text).expect("clip_cases.json is JSON")
}

fn load(prefix: &str, file: &ModelFile) -> ClipTextEncoder {
    let cfg: ClipConfig = serde_json::from_value(cases()["config"].clone()).expect("config");
    let tok = std::fs::read_to_string(fixture("clip_tokenizer/tokenizer.json")).expect("tok");
    ClipTextEncoder::load(file, prefix, &cfg, &tok).expect("tiny CLIP loads")
}

fn tiny() -> ClipTextEncoder {
    load(
        "",
        &ModelFile::open(&fixture("clip_tiny.safetensors")).expect("weights"),
    )
}

fn id_list(v: &serde_json::Value) -> Vec<u32> {
    v.as_array()
        .expect("id list")
        .iter()
        .map(|x| x.as_u64().expect("id") as u32)
        .collect()
}

fn f32s(st: &SafeTensors, name: &str) -> Vec<f32> {
    let t = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e:?}"));
    assert_eq!(t.dtype(), Dtype::F32, "{name}");
    t.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn i64s(st: &SafeTensors, name: &str) -> Vec<u32> {
    let t = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e:?}"));
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
fn tokenizer_matches_official_clip() {
    let enc = tiny();
    let cases = cases();
    let sentences = cases["sentences"].as_array().unwrap();
    assert!(sentences.len() >= 30);
    let mut with_fast_difference = 0;
    for s in sentences {
        let text = s["text"].as_str().unwrap();
        let ids22 = enc.tokenize(text, MDM_CONTEXT).unwrap();
        let ids77 = enc.tokenize(text, 77).unwrap();
        assert_eq!(
            &ids22[..MDM_CONTEXT],
            id_list(&s["ids22"]),
            "{text:?} at 22"
        );
        assert!(ids22[MDM_CONTEXT..].iter().all(|&i| i == 0), "{text:?}");
        assert_eq!(ids77, id_list(&s["ids77"]), "{text:?} at 77");
        // Texts the bare tokenizer.json gets wrong are right only thanks to clean_text.
        if s.get("fast_ids77").is_some() {
            with_fast_difference += 1;
        }
    }
    assert_eq!(with_fast_difference, 4, "known tokenizer.json differences");
}

#[test]
fn matches_hf_clip_text_model() {
    let enc = tiny();
    let cases = cases();
    let sentences = cases["sentences"].as_array().unwrap();
    let bytes = std::fs::read(fixture("clip_expected.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (mut eh, mut ep, mut ej) = (0f32, 0f32, 0f32);
    let runs = cases["cases"].as_array().unwrap();
    assert!(runs.len() >= 36);
    for (k, run) in runs.iter().enumerate() {
        let s = run["sentence"].as_u64().unwrap() as usize;
        let context = run["context_length"].as_u64().unwrap() as usize;
        let text = sentences[s]["text"].as_str().unwrap();
        let out = enc.encode(text, context).unwrap();
        assert_eq!(out.ids, i64s(&st, &format!("c{k}.ids")), "{text:?}");
        let (h, p, j) = (
            max_abs(&out.tokens, &f32s(&st, &format!("c{k}.hidden"))),
            max_abs(&out.pooled, &f32s(&st, &format!("c{k}.pooled"))),
            max_abs(&out.projected, &f32s(&st, &format!("c{k}.projected"))),
        );
        assert!(
            h <= TOL && p <= TOL && j <= TOL,
            "{text:?} ({context}): {h} {p} {j}"
        );
        (eh, ep, ej) = (eh.max(h), ep.max(p), ej.max(j));
    }
    eprintln!("clip max abs error: hidden {eh:e}, pooled {ep:e}, projected {ej:e}");
}

#[test]
fn pooling_takes_the_first_end_token_and_padding_is_inert() {
    let enc = tiny();
    let out = enc.encode("a person walks", MDM_CONTEXT).unwrap();
    let end = out.ids.iter().position(|&i| i == 49407).unwrap();
    assert_eq!(out.pooled_index, end);
    // Causal: the unpadded prefix gives the same rows, bit for bit (every kernel's result for
    // a row is independent of the rows after it).
    let short = enc.encode_ids(&out.ids[..=end]).unwrap();
    assert_eq!(short.pooled_index, end);
    assert_eq!(short.pooled, out.pooled);
    assert_eq!(short.tokens, out.tokens[..short.tokens.len()]);
    // encode_through_end runs that prefix: same rows and vectors, bit for bit, for short,
    // empty and over-long (cut, the end token last in the context) texts.
    let long = "a person walks forward and turns around ".repeat(20);
    for text in ["a person walks", "", long.as_str()] {
        for c in [2, MDM_CONTEXT, 77] {
            let all = enc.encode(text, c).unwrap();
            let end = all.pooled_index;
            assert!(end < c, "{text:?} ({c})");
            let fast = enc.encode_through_end(text, c).unwrap();
            assert_eq!(fast.ids, all.ids[..=end], "{text:?} ({c})");
            assert_eq!(fast.pooled_index, end);
            assert_eq!(fast.tokens, all.tokens[..(end + 1) * enc.width()]);
            assert_eq!(fast.pooled, all.pooled);
            assert_eq!(fast.projected, all.projected);
        }
    }
    assert_eq!(enc.encode_through_end(&long, 77).unwrap().ids.len(), 77);
    // A literal end token inside the text is the first one.
    let lit = enc.encode("a <|endoftext|> b", 77).unwrap();
    assert_eq!(lit.pooled_index, 2);
}

#[test]
fn any_text_encodes_and_bad_arguments_are_errors() {
    let enc = tiny();
    let long = "walks ".repeat(50_000);
    for text in [
        "",
        " ",
        "\u{0}\u{200b}\u{feff}",
        "🙂🙂🙂",
        "&&&&;;#x;&#xFFFFFFFF;&#55296;",
        "<|startoftext|><|endoftext|>",
        &long,
    ] {
        for c in [2, 3, MDM_CONTEXT, 77] {
            let out = enc.encode(text, c).unwrap();
            assert_eq!(out.ids.len(), 77);
            assert_eq!(out.tokens.len(), 77 * enc.width());
            assert_eq!(out.projected.len(), enc.projection_dim());
            assert!(out.projected.iter().all(|v| v.is_finite()), "{text:?}");
        }
    }
    for c in [0, 1, 78] {
        assert!(enc.encode("a", c).is_err());
    }
    assert!(enc.encode_ids(&[]).is_err());
    assert!(enc.encode_ids(&[49408]).is_err());
    assert!(enc.encode_ids(&[0; 78]).is_err());
}

#[test]
fn prefixed_file_and_missing_tensors() {
    // The same weights under a prefix load and agree.
    let bytes = std::fs::read(fixture("clip_tiny.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let named: Vec<(String, safetensors::tensor::TensorView)> = st
        .tensors()
        .into_iter()
        .map(|(n, t)| (format!("clip.{n}"), t))
        .collect();
    let prefixed = safetensors::serialize(named.clone(), &None).unwrap();
    let enc = load("clip.", &ModelFile::from_bytes(&prefixed).unwrap());
    let a = enc.encode("a person jumps", MDM_CONTEXT).unwrap();
    let b = tiny().encode("a person jumps", MDM_CONTEXT).unwrap();
    assert_eq!(a.projected, b.projected);

    let without: Vec<_> = named
        .into_iter()
        .filter(|(n, _)| n != "clip.text_model.encoder.layers.1.mlp.fc2.bias")
        .collect();
    let file = ModelFile::from_bytes(&safetensors::serialize(without, &None).unwrap()).unwrap();
    let cfg: ClipConfig = serde_json::from_value(cases()["config"].clone()).unwrap();
    let tok = std::fs::read_to_string(fixture("clip_tokenizer/tokenizer.json")).unwrap();
    let e = ClipTextEncoder::load(&file, "clip.", &cfg, &tok).unwrap_err();
    assert_eq!(
        e.to_string(),
        "bad model file: tensor `clip.text_model.encoder.layers.1.mlp.fc2.bias` is missing"
    );
    let mut bad = cfg.clone();
    bad.heads = 5;
    assert!(ClipTextEncoder::load(&file, "clip.", &bad, &tok)
        .unwrap_err()
        .to_string()
        .contains("not divisible"));
}
