//! Accuracy of every weight type on the trained demo model: the features after the model's 10
//! DDIM steps (120 frames, guidance 2, three prompts × two seeds) against the f32 run, max and
//! mean absolute difference, printed as a table (`cargo test -p flame-demo --test demo_weights
//! -- --nocapture`; docs/performance.md quotes it). Types the CPU cannot run (bf16-compute
//! without AVX512_BF16, int8 without AVX2) are refused at load with the instruction's name,
//! and the test says it skipped them. Int8 runs on the kernel in use (`FLAME_KERNEL=avx2`
//! measures the AVX2 path, whose activations have 63 levels).
//!
//! The bounds are this model's measured errors with room (a regression guard, not a goal):
//! f16 and the bf16 types only round weights (and, for bf16-compute, each layer's input) to
//! 11 or 8 significant bits; int8 quantises weights per output and activations per row to 8
//! bits, which a 10-step sampler amplifies.

use std::sync::Arc;

#[path = "../../../tests/common/mod.rs"]
mod common;

use common::{demo_model, skip};
use flame::kernels::WeightType;
use flame::models::{LoadOptions, Model};
use flame::session::{Session, SessionParams, Which};

const PROMPTS: [&str; 3] = [
    "a person walks forward.",
    "a person jumps twice.",
    "a person waves with the right hand.",
];
const SEEDS: [u64; 2] = [0, 1];

fn features(model: &Arc<Model>, prompt: &str, seed: u64) -> Vec<f32> {
    let params = SessionParams {
        frames: Some(120),
        seed,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt(prompt).unwrap();
    s.run().unwrap();
    s.motion(Which::Sample).unwrap().0.to_vec()
}

#[test]
fn every_weight_type_is_close_to_f32_on_the_demo_model() {
    let Some(path) = demo_model() else {
        skip("demo_weights", "no demo model (set FLAME_MINILM_DIR)");
        return;
    };
    let load = |weights| Model::load_with(&path, &LoadOptions { weights }).map(Arc::new);
    let f32_model = load(WeightType::F32).unwrap();
    let want: Vec<Vec<f32>> = PROMPTS
        .iter()
        .flat_map(|p| SEEDS.map(|s| features(&f32_model, p, s)))
        .collect();
    println!("weights        max |Δ|   mean |Δ|   (features after 10 steps vs f32, 6 runs)");
    // (type, bound on max, bound on mean)
    let bounds = [
        (WeightType::F16, 0.02, 1e-3),
        (WeightType::Bf16, 0.15, 4e-3),
        (WeightType::Bf16Compute, 0.08, 2e-3),
        (WeightType::Int8, 0.8, 0.05),
    ];
    for (ty, max_bound, mean_bound) in bounds {
        let model = match load(ty) {
            Ok(m) => m,
            Err(e) => {
                assert!(!ty.native_on_this_cpu(), "{ty:?}: {e}");
                assert!(e.to_string().contains("AVX512_"), "{e}");
                println!("{:<14} skipped: {e}", ty.name());
                continue;
            }
        };
        let (mut max, mut sum, mut count) = (0.0f64, 0.0f64, 0usize);
        for (i, p) in PROMPTS.iter().enumerate() {
            for (j, &s) in SEEDS.iter().enumerate() {
                let got = features(&model, p, s);
                let w = &want[i * SEEDS.len() + j];
                assert_eq!(got.len(), w.len());
                for (a, b) in got.iter().zip(w) {
                    let d = (a - b).abs() as f64;
                    max = max.max(d);
                    sum += d;
                    count += 1;
                }
            }
        }
        let mean = sum / count as f64;
        println!("{:<14} {max:>8.4}   {mean:>8.5}", ty.name());
        assert!(
            max > 0.0,
            "{ty:?} gave the f32 bits: the type is not in effect"
        );
        assert!(
            max <= max_bound && mean <= mean_bound,
            "{ty:?}: max {max}, mean {mean}"
        );
    }
}
