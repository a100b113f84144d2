//! The layers' input gradients against PyTorch autograd (tests/fixtures/grad_expected.safetensors,
//! written by tools/reference/grad.py); here because the layers are crate-private.

use crate::checkpoint::ModelFile;
use crate::kernels::WeightType;
use crate::models::layers::{Conv1d, Linear};

fn fixture() -> ModelFile {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/grad_expected.safetensors");
    ModelFile::open(&path).unwrap()
}

fn tensor(f: &ModelFile, name: &str) -> (Vec<usize>, Vec<f32>) {
    let t = f.tensor_any_shape(name).unwrap();
    (t.shape().to_vec(), t.data().to_vec())
}

/// Largest difference relative to max(1, |reference|).
fn rel_diff(got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() / w.abs().max(1.0))
        .fold(0.0, f32::max)
}

#[test]
fn conv1d_input_gradient_matches_autograd() {
    let f = fixture();
    for (k, d) in [(3, 1), (3, 3), (3, 9), (1, 1)] {
        let name = format!("conv_k{k}_d{d}");
        let (ws, _) = tensor(&f, &format!("{name}.weight"));
        let (n_out, n_in) = (ws[0], ws[1]);
        let conv = Conv1d::load(&f, &name, n_in, n_out, k, d, true, WeightType::F32).unwrap();
        let (xs, _) = tensor(&f, &format!("{name}.x"));
        let (_, dy) = tensor(&f, &format!("{name}.dy"));
        let (_, want) = tensor(&f, &format!("{name}.dx"));
        let frames = xs[0];
        // Stale scratch of the wrong size: the call must resize and overwrite both.
        let (mut dx, mut cols) = (vec![7.0; 3], vec![7.0; 5]);
        conv.backward_input(&dy, frames, &mut dx, &mut cols);
        let diff = rel_diff(&dx, &want);
        assert!(diff <= 1e-5, "{name}: {diff:e}");
        assert!(
            want.iter().all(|v| v.abs() > 1e-3),
            "{name}: a zero reference"
        );
    }
}

#[test]
fn linear_input_gradient_matches_autograd_in_every_weight_type() {
    let f = fixture();
    let (ws, w) = tensor(&f, "linear.weight");
    let (n_out, n_in) = (ws[0], ws[1]);
    let (_, b) = tensor(&f, "linear.bias");
    let (_, dy) = tensor(&f, "linear.dy");
    let (_, want) = tensor(&f, "linear.dx");
    let rows = dy.len() / n_out;
    let layer = Linear::from_weight(&w, Some(&b), n_in, n_out, WeightType::F32);
    let mut dx = vec![f32::NAN; rows * n_in];
    layer.backward_input(&dy, rows, &mut dx);
    let diff = rel_diff(&dx, &want);
    assert!(diff <= 1e-5, "f32: {diff:e}");
    // Half weights: the gradient of the layer as stored, `dy · narrowed(W)` written out in f64.
    for ty in [WeightType::F16, WeightType::Bf16] {
        let layer = Linear::from_weight(&w, Some(&b), n_in, n_out, ty);
        layer.backward_input(&dy, rows, &mut dx);
        let narrowed: Vec<f64> = w
            .iter()
            .map(|&v| match ty {
                WeightType::F16 => half::f16::from_f32(v).to_f64(),
                _ => half::bf16::from_f32(v).to_f64(),
            })
            .collect();
        let want: Vec<f32> = (0..rows * n_in)
            .map(|i| {
                let (r, c) = (i / n_in, i % n_in);
                (0..n_out)
                    .map(|o| dy[r * n_out + o] as f64 * narrowed[o * n_in + c])
                    .sum::<f64>() as f32
            })
            .collect();
        let diff = rel_diff(&dx, &want);
        assert!(diff <= 1e-5, "{ty:?}: {diff:e}");
    }
}
