//! Latent consistency sampler parity: `flame::diffusion::lcm` reproduces diffusers' own
//! `LCMScheduler` as MotionLCM v1 (the grid from `original_inference_steps` 50) and v2 (its
//! timestep table, including the 4-step list that repeats 299) run it.
//!
//! Reference: tools/reference/diffusers_lcm.py (runs `LCMScheduler` itself, diffusers 0.42.1);
//! fixture: tests/fixtures/lcm_diffusers.{safetensors,json}, written by
//! tools/make_lcm_fixtures.py (deterministic; needs torch, diffusers, safetensors). Asserted: the
//! timesteps of `set_timesteps(n)` for n = 1 to 50 exactly, and every sample and consistency
//! estimate of each trajectory bit for bit: the same f32 operations in the same order. (torch's
//! float32 `sqrt` is not always correctly rounded, tests/diffusers_ddim.rs says more; the few
//! √ᾱ and `c_out` values these runs use happen to be, so a fixture regenerated on another torch
//! could need a tolerance of an ulp.)

use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::diffusion::lcm::{LcmSampler, LcmTimesteps};

const TOL: f32 = 0.0;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn load() -> (ModelFile, serde_json::Value) {
    let file = ModelFile::open(&fixture("lcm_diffusers.safetensors")).unwrap();
    let text = std::fs::read_to_string(fixture("lcm_diffusers.json")).unwrap();
    (file, serde_json::from_str(&text).unwrap())
}

fn get(file: &ModelFile, name: &str) -> Vec<f32> {
    file.tensor_any_shape(name).unwrap().data().to_vec()
}

fn ints(v: &serde_json::Value) -> Vec<usize> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_u64().unwrap() as usize)
        .collect()
}

/// The fake network of tools/reference/diffusers_ddim.py: ε = (0.5·x + bias) + s(t),
/// s(t) = float32(t·0.0003 − 0.2).
fn fake_eps(x: &[f32], t: usize, bias: &[f32]) -> Vec<f32> {
    let shift = (t as f64 * 0.0003 - 0.2) as f32;
    x.iter()
        .zip(bias)
        .map(|(v, b)| (v * 0.5 + b) + shift)
        .collect()
}

#[test]
fn v1_grid_matches_set_timesteps_for_every_count() {
    let (_, json) = load();
    let rule = LcmTimesteps::Grid { original_steps: 50 };
    for n in 1..=50 {
        let want = ints(&json["timesteps"][n.to_string()]);
        assert_eq!(rule.timesteps(n, 1000).unwrap(), want, "{n} steps");
    }
}

#[test]
fn trajectories_match_diffusers() {
    let (file, json) = load();
    let x_t = get(&file, "x_T");
    let bias = get(&file, "bias");
    let n = x_t.len();
    for case in json["cases"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let want_t = ints(&case["timesteps"]);
        let steps = want_t.len();
        let rule = if name.starts_with("v1") {
            LcmTimesteps::Grid { original_steps: 50 }
        } else {
            LcmTimesteps::V2Table
        };
        let sampler = LcmSampler::motionlcm(rule, steps).unwrap();
        assert_eq!(sampler.timesteps(), want_t, "{name}");
        let noise = get(&file, &format!("{name}.noise"));
        let samples = get(&file, &format!("{name}.samples"));
        let denoised_want = get(&file, &format!("{name}.denoised"));
        let mut z = x_t.clone();
        let mut d = vec![0.0f32; n];
        let mut worst = 0.0f32;
        for (i, &t) in sampler.timesteps().iter().enumerate() {
            let eps = fake_eps(&z, t, &bias);
            sampler.denoise(i, &eps, &z, &mut d);
            if i + 1 < steps {
                sampler.renoise(i, &d, &noise[i * n..(i + 1) * n], &mut z);
            } else {
                z.copy_from_slice(&d);
            }
            for (got, want) in [(&d, &denoised_want), (&z, &samples)] {
                for (a, b) in got.iter().zip(&want[i * n..(i + 1) * n]) {
                    worst = worst.max((a - b).abs());
                }
            }
        }
        assert!(worst <= TOL, "{name}: max difference {worst}");
        // The trajectory moved: the sampler is not the identity.
        assert!(
            z.iter().zip(&x_t).any(|(a, b)| (a - b).abs() > 0.1),
            "{name}"
        );
    }
}

#[test]
fn counts_the_release_has_no_schedule_for_are_refused() {
    let msg = LcmSampler::motionlcm(LcmTimesteps::V2Table, 3)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("no 3-step schedule") && msg.contains("1, 2, 4"),
        "{msg}"
    );
    let msg = LcmSampler::motionlcm(LcmTimesteps::Grid { original_steps: 50 }, 64)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("1 to 50"), "{msg}");
}
