//! Half-precision weights chosen at load (`LoadOptions::weights`): the f16/bf16 kernels against
//! f32 runs of the same models.
//!
//! Fixtures: tests/fixtures/flame_tiny.safetensors (f32), flame_tiny_f16.safetensors (the same
//! network stored in f16) and mdm_tiny.safetensors, all written by tools/make_fixtures.py /
//! tools/make_mdm_fixtures.py.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::models::{LoadOptions, Model, WeightType};
use flame::session::{Sampler, Session, SessionParams};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn load(name: &str, weights: WeightType) -> Arc<Model> {
    Arc::new(Model::load_with(fixture(name), &LoadOptions { weights }).unwrap())
}

/// The features after a whole seeded 10-step DDIM generation with guidance.
fn generate(model: &Arc<Model>, threads: usize) -> Vec<f32> {
    let params = SessionParams {
        frames: Some(40),
        steps: Some(10),
        sampler: Some(Sampler::Ddim),
        eta: Some(0.0),
        guidance: None,
        clip_denoised: None,
        seed: 7,
        threads,
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt("a person jumps over an obstacle").unwrap();
    s.run().unwrap().to_vec()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
#[ignore = "the tiny random FLAME fixture amplifies f16 weight rounding over 10 steps to ~1 \
            (the f16-stored fixture, widened to f32, diverges from the f32 one by as much); \
            needs the FLAME-base model or a trained fixture"]
fn half_weights_stay_within_1e_2_of_f32_after_10_steps() {
    for name in ["flame_tiny.safetensors", "mdm_tiny.safetensors"] {
        let f32_model = load(name, WeightType::F32);
        let want = generate(&f32_model, 2);
        for ty in [WeightType::F16, WeightType::Bf16] {
            let m = load(name, ty);
            assert_eq!(m.weight_type(), ty);
            assert_eq!(
                m.linear_weight_bytes() * 2,
                f32_model.linear_weight_bytes(),
                "{name}: {ty:?} halves the linear weights"
            );
            let got = generate(&m, 2);
            let d = max_abs_diff(&got, &want);
            let stored_f16 = if name.starts_with("flame") {
                let f16_file = load("flame_tiny_f16.safetensors", WeightType::F32);
                max_abs_diff(&generate(&f16_file, 2), &want)
            } else {
                f32::NAN
            };
            assert!(
                d < 1e-2,
                "{name} {ty:?}: features differ by {d:e} (f16-stored file as f32: {stored_f16:e})"
            );
            assert!(d > 0.0, "{name} {ty:?}: weights were not narrowed");
        }
    }
}

#[test]
fn f16_kernels_equal_f32_kernels_on_f16_rounded_weights() {
    // The f16 file's weights are exactly representable in f16, so the f16 kernel (widening in
    // registers) and the f32 kernel (widened at load) must agree bit for bit.
    let wide = load("flame_tiny_f16.safetensors", WeightType::F32);
    let half = load("flame_tiny_f16.safetensors", WeightType::F16);
    let (a, b) = (generate(&wide, 1), generate(&half, 3));
    assert!(
        a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
        "max diff {:e}",
        max_abs_diff(&a, &b)
    );
}

#[test]
fn half_weights_are_bit_identical_across_thread_counts() {
    let m = load("flame_tiny.safetensors", WeightType::Bf16);
    let base = generate(&m, 1);
    for threads in [2, 3] {
        let got = generate(&m, threads);
        assert!(
            base.iter()
                .zip(&got)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "{threads} threads differ from 1"
        );
    }
}
