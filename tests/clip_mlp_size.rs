//! A CLIP text tower whose MLP is not 4 × its width loads from `intermediate_size`, and gives
//! what the same function at 4 × width gives. Built from the tiny CLIP fixture (width 32, MLP
//! 128, checked against Hugging Face in tests/text_clip.rs):
//! - `wide`: MLP 160 = 5 × width, the extra hidden units' `fc2` columns zero: the fixture's
//!   function exactly, so its outputs must equal the fixture's;
//! - `zeroed`: MLP 128 with the last 32 units' `fc2` columns zero, and `narrow`: MLP 96 =
//!   3 × width without those units: the same function, so equal outputs.
//!
//! A file whose configuration does not match its MLP is refused naming the tensor.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::text::{ClipConfig, ClipTextEncoder};
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

const W: usize = 32;
const MLP: usize = 4 * W;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

type Tensors = Vec<(String, Vec<usize>, Vec<f32>)>;

fn read_fixture() -> Tensors {
    let bytes = std::fs::read(fixture("clip_tiny.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut out: Tensors = st
        .tensors()
        .into_iter()
        .map(|(name, t)| {
            // Stored as f32 or f16; written back as f32 (the same values).
            let data = match t.dtype() {
                Dtype::F32 => t
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
                Dtype::F16 => t
                    .data()
                    .chunks_exact(2)
                    .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
                    .collect(),
                other => panic!("{name}: {other:?}"),
            };
            (name, t.shape().to_vec(), data)
        })
        .collect();
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

fn serialize(tensors: &Tensors) -> Vec<u8> {
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .iter()
        .map(|(n, s, d)| {
            let b = d.iter().flat_map(|x| x.to_le_bytes()).collect();
            (n.clone(), s.clone(), b)
        })
        .collect();
    let views: Vec<(String, TensorView)> = bytes
        .iter()
        .map(|(n, s, b)| {
            (
                n.clone(),
                TensorView::new(Dtype::F32, s.clone(), b).unwrap(),
            )
        })
        .collect();
    safetensors::serialize(views, &None::<HashMap<String, String>>).unwrap()
}

/// Every block's MLP resized to `size` hidden units: fc1 rows and fc2 columns beyond the
/// fixture's are zero-padded, those beyond `size` dropped, and fc2 columns from `keep` on
/// zeroed.
fn with_mlp(base: &Tensors, size: usize, keep: usize) -> Tensors {
    base.iter()
        .map(|(n, s, d)| {
            if n.ends_with("mlp.fc1.weight") {
                let mut v = vec![0.0; size * W];
                let rows = size.min(MLP);
                v[..rows * W].copy_from_slice(&d[..rows * W]);
                (n.clone(), vec![size, W], v)
            } else if n.ends_with("mlp.fc1.bias") {
                let mut v = vec![0.0; size];
                let rows = size.min(MLP);
                v[..rows].copy_from_slice(&d[..rows]);
                (n.clone(), vec![size], v)
            } else if n.ends_with("mlp.fc2.weight") {
                let mut v = vec![0.0; W * size];
                for r in 0..W {
                    for c in 0..size.min(MLP).min(keep) {
                        v[r * size + c] = d[r * MLP + c];
                    }
                }
                (n.clone(), vec![W, size], v)
            } else {
                (n.clone(), s.clone(), d.clone())
            }
        })
        .collect()
}

fn config(intermediate: Option<usize>) -> ClipConfig {
    let text = std::fs::read_to_string(fixture("clip_cases.json")).unwrap();
    let cases: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut cfg = cases["config"].clone();
    if let Some(i) = intermediate {
        cfg["intermediate_size"] = i.into();
    }
    serde_json::from_value(cfg).unwrap()
}

fn tokenizer() -> String {
    std::fs::read_to_string(fixture("clip_tokenizer/tokenizer.json")).unwrap()
}

fn load(tensors: &Tensors, intermediate: Option<usize>) -> flame::Result<ClipTextEncoder> {
    let file = ModelFile::from_bytes(&serialize(tensors)).unwrap();
    ClipTextEncoder::load(&file, "", &config(intermediate), &tokenizer())
}

const TEXTS: [&str; 3] = [
    "a person walks forward and waves.",
    "someone jumps twice, then sits down",
    "",
];

fn outputs(enc: &ClipTextEncoder) -> Vec<Vec<f32>> {
    TEXTS
        .iter()
        .flat_map(|t| {
            let o = enc.encode(t, 77).unwrap();
            [o.tokens, o.projected]
        })
        .collect()
}

fn max_diff(a: &[Vec<f32>], b: &[Vec<f32>]) -> f32 {
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| {
            assert_eq!(x.len(), y.len());
            x.iter().zip(y).map(|(p, q)| (p - q).abs())
        })
        .fold(0.0, f32::max)
}

#[test]
fn mlp_size_comes_from_the_configuration() {
    let base = read_fixture();
    let reference = outputs(&load(&base, None).unwrap());

    // 5 × width whose extra units contribute nothing: the fixture's function.
    let wide = load(&with_mlp(&base, 5 * W, MLP), Some(5 * W)).unwrap();
    assert_eq!(wide.config().mlp_size(), 160);
    let d = max_diff(&outputs(&wide), &reference);
    assert!(d <= 1e-5, "5 × width: {d:e}");

    // 3 × width against 4 × width with the same 96 units live.
    let zeroed = outputs(&load(&with_mlp(&base, MLP, 3 * W), None).unwrap());
    let narrow = load(&with_mlp(&base, 3 * W, 3 * W), Some(3 * W)).unwrap();
    assert_eq!(narrow.config().mlp_size(), 96);
    let d = max_diff(&outputs(&narrow), &zeroed);
    assert!(d <= 1e-5, "3 × width: {d:e}");
    // Dropping the units does change the function (the comparison above is not vacuous).
    assert!(max_diff(&zeroed, &reference) > 1e-3);

    // A configuration that does not describe the MLP is refused, naming the tensor.
    let e = load(&with_mlp(&base, 3 * W, 3 * W), None)
        .err()
        .unwrap()
        .to_string();
    assert_eq!(
        e,
        "bad model file: tensor `text_model.encoder.layers.0.mlp.fc1.weight` has shape [96, 32], \
         expected [128, 32] (from config text_encoder.width: no intermediate_size, so 4 × width)"
    );
    let e = load(&base, Some(3 * W)).err().unwrap().to_string();
    assert!(
        e.contains("mlp.fc1.weight` has shape [128, 32], expected [96, 32]"),
        "{e}"
    );
}
