//! Half-precision weights chosen at load (`LoadOptions::weights`): the f16/bf16 kernels against
//! f32 runs of the same models.
//!
//! Fixtures: tests/fixtures/flame_tiny.safetensors (f32), flame_tiny_f16.safetensors (the same
//! network stored in f16) and mdm_tiny.safetensors, all written by tools/make_fixtures.py /
//! tools/make_mdm_fixtures.py.

use std::path::{Path, PathBuf};
use std::sync::Arc;

mod common;

use common::{demo_model, max_abs_diff};
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
        respacing: None,
        frames: Some(40),
        steps: Some(10),
        sampler: Some(Sampler::Ddim),
        eta: Some(0.0),
        guidance: None,
        clip_denoised: None,
        seed: 7,
        threads,
        looped: false,
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt("a person jumps over an obstacle").unwrap();
    s.run().unwrap().to_vec()
}

#[test]
fn half_weights_stay_close_to_f32_after_10_steps_on_a_trained_model() {
    // The trained demo model (FLAME, 4 × 256, all-MiniLM-L6-v2). Random-weight fixtures are no
    // use here: they amplify any rounding over 10 steps (the tiny FLAME fixture stored in f16
    // diverges from its f32 self by ~1).
    let Some(path) = demo_model() else {
        common::skip(
            "weights_half::half_weights_stay_close_to_f32_after_10_steps_on_a_trained_model",
            "no demo model (set FLAME_MINILM_DIR or run tools/try.sh)",
        );
        return;
    };
    let open = |weights| Arc::new(Model::load_with(&path, &LoadOptions { weights }).unwrap());
    let f32_model = open(WeightType::F32);
    let want = generate(&f32_model, 2);
    for ty in [WeightType::F16, WeightType::Bf16] {
        let m = open(ty);
        assert_eq!(m.weight_type(), ty);
        assert_eq!(
            m.linear_weight_bytes() * 2,
            f32_model.linear_weight_bytes(),
            "{ty:?} halves the linear weights"
        );
        let d = max_abs_diff(&generate(&m, 2), &want);
        eprintln!("{ty:?}: max abs feature difference after 10 steps {d:e}");
        // The bound is 1e-2, met by f16 (measured 2.3e-3). bf16 keeps 8 mantissa bits
        // to f16's 11 and measures 5.2e-2 on this model (features are in units of the corpus
        // std); its bound here is a regression guard, documented in docs/performance.md.
        let bound = if ty == WeightType::F16 { 1e-2 } else { 1e-1 };
        assert!(
            d < bound,
            "{ty:?}: features differ by {d:e} (bound {bound:e})"
        );
        // The text encoder's f32 weights are rounded either way, so the runs must differ.
        assert!(d > 0.0, "{ty:?}: weights were not narrowed");
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
