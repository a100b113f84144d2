//! diffusers DDIM parity: the sampler built from a `diffusion` configuration with diffusers'
//! spacing reproduces diffusers 0.42.1's own `DDIMScheduler` as MoLA (trailing) and MLD
//! (leading, steps_offset 1) use it, with `set_alpha_to_one` false (docs/official/mola-mld.md#mola-scheduler,
//! docs/official/mola-mld.md#mld-scheduler, docs/official/mola-mld.md#scheduler-tables-in-float32).
//!
//! Reference: tools/reference/diffusers_ddim.py (runs `DDIMScheduler` itself); fixture:
//! tests/fixtures/ddim_diffusers.{safetensors,json}, written by tools/make_ddim_fixtures.py
//! (deterministic; needs torch, diffusers, safetensors). Asserted: the float32 ᾱ table bit for
//! bit, the timesteps of `set_timesteps` exactly (and the counts diffusers itself cannot sample
//! refused), and every sample and x̂0 of each trajectory within 1e-5. Not bit for bit: torch's
//! CPU float32 `sqrt` (2.15, AVX2 kernels) is not correctly rounded — it differs from IEEE sqrt
//! by one ulp for about a fifth of inputs — so √ᾱ and √(1 − ᾱ) differ by an ulp now and then and
//! the 50-step samples (values up to ~25) by up to ~8e-6.

use std::path::{Path, PathBuf};

use flame::checkpoint::ModelFile;
use flame::config::{Defaults, DiffusionConfig};
use flame::diffusion::{
    build_sampler, diffusers_alphas_cumprod, diffusers_timesteps, BetaSchedule, BuiltSampler,
    DiffusionSampler, Method, SamplerChoice, Spacing,
};

const TOL: f32 = 1e-5;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

struct Expected {
    file: ModelFile,
    json: serde_json::Value,
}

impl Expected {
    fn load() -> Expected {
        let file = ModelFile::open(&fixture("ddim_diffusers.safetensors")).unwrap();
        let text = std::fs::read_to_string(fixture("ddim_diffusers.json")).unwrap();
        Expected {
            file,
            json: serde_json::from_str(&text).unwrap(),
        }
    }
    fn get(&self, name: &str) -> Vec<f32> {
        self.file.tensor_any_shape(name).unwrap().data().to_vec()
    }
}

fn ints(v: &serde_json::Value) -> Vec<i64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_i64().unwrap())
        .collect()
}

/// MoLA's and MLD's `diffusion` section (scaled_linear 0.00085–0.012 over 1000 steps).
fn config(
    spacing: &str,
    steps_offset: usize,
    set_alpha_to_one: bool,
    pred: &str,
    clip: bool,
) -> DiffusionConfig {
    DiffusionConfig {
        num_timesteps: 1000,
        schedule: "scaled_linear".into(),
        parameterization: pred.into(),
        variance: "fixed_small".into(),
        clip_denoised: clip,
        uncond: "zeros".into(),
        spacing: spacing.into(),
        steps_offset,
        set_alpha_to_one,
        lcm_timesteps: None,
        original_inference_steps: None,
        timestep_scaling: None,
    }
}

fn defaults(steps: usize) -> Defaults {
    Defaults {
        sampler: "ddim".into(),
        steps,
        guidance: 1.0,
        eta: 0.0,
        frames: 1,
        respacing: None,
        guidance_by_steps: None,
    }
}

fn sampler(dc: &DiffusionConfig, steps: usize, eta: f32) -> DiffusionSampler {
    let choice = SamplerChoice {
        method: Method::Ddim,
        steps: Some(steps),
        respacing: None,
        eta: Some(eta),
        clip_denoised: None,
    };
    match build_sampler(dc, &defaults(50), &choice).unwrap() {
        BuiltSampler::Diffusion(d) => *d,
        BuiltSampler::Flow(_) | BuiltSampler::Lcm(_) => panic!("a diffusion sampler"),
    }
}

/// The fake network of tools/reference/diffusers_ddim.py, in the same float32 order:
/// ε = (0.5·x + bias) + f32(t·0.0003 − 0.2).
fn fake_eps(x: &[f32], t: f32, bias: &[f32], out: &mut [f32]) {
    let shift = (t as f64 * 0.0003 - 0.2) as f32;
    for ((o, &xi), &b) in out.iter_mut().zip(x).zip(bias) {
        *o = (xi * 0.5 + b) + shift;
    }
}

#[test]
fn alphas_cumprod_is_diffusers_float32_table() {
    let e = Expected::load();
    let want = e.get("alphas_cumprod");
    let got = diffusers_alphas_cumprod(&flame::diffusion::betas(BetaSchedule::ScaledLinear, 1000));
    assert_eq!(got.len(), 1000);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let got32: Vec<f32> = got.iter().map(|&a| a as f32).collect();
    assert!(
        got.iter().all(|&a| f64::from(a as f32) == a),
        "widened f32 values"
    );
    assert_eq!(bits(&got32), bits(&want));
}

#[test]
fn timesteps_match_set_timesteps() {
    let e = Expected::load();
    let table = e.json["timesteps"].as_object().unwrap();
    assert!(table.len() >= 30);
    let mut refused = 0;
    for (key, want) in table {
        let want = ints(want);
        let mut parts = key.split('_');
        let spacing: Spacing = parts.next().unwrap().parse().unwrap();
        let offset: usize = parts.next().unwrap()["offset".len()..].parse().unwrap();
        let n: usize = parts.next().unwrap().parse().unwrap();
        let got = diffusers_timesteps(spacing, 1000, n, offset);
        if want.len() != n {
            // diffusers' trailing rule gives one timestep too many, the last at −1.
            assert_eq!((want.len(), want.last()), (n + 1, Some(&-1)), "{key}");
            let msg = got.unwrap_err().to_string();
            assert!(
                msg.contains(&format!("cannot take {n} steps")),
                "{key}: {msg}"
            );
            refused += 1;
        } else if want[0] >= 1000 {
            // Leading 1000 steps + offset 1 starts at t = 1000, past diffusers' own table.
            let msg = got.unwrap_err().to_string();
            assert!(
                msg.contains("past the last training step 999"),
                "{key}: {msg}"
            );
            refused += 1;
        } else {
            let got: Vec<i64> = got.unwrap().iter().map(|&t| t as i64).collect();
            assert_eq!(got, want, "{key}");
        }
    }
    // Trailing at 61 steps and leading with offset 1 at 1000 steps.
    assert_eq!(refused, 2);
    // The official schedules (docs/official/mola-mld.md#mld-scheduler, docs/official/mola-mld.md#mola-scheduler): MLD
    // 981, 961, …, 1; MoLA 999, 979, …, 19.
    let mld = ints(&table["leading_offset1_50"]);
    assert_eq!((mld[0], mld[1], mld[49]), (981, 961, 1));
    let mola = ints(&table["trailing_offset1_50"]);
    assert_eq!((mola[0], mola[1], mola[49]), (999, 979, 19));
}

#[test]
fn trajectories_match_ddim_scheduler_step() {
    let e = Expected::load();
    let x_t = e.get("x_T");
    let bias = e.get("bias");
    let n = x_t.len();
    let cases = e.json["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 6);
    for case in cases {
        let name = case["name"].as_str().unwrap();
        let steps = case["steps"].as_u64().unwrap() as usize;
        let eta = case["eta"].as_f64().unwrap() as f32;
        let dc = config(
            case["spacing"].as_str().unwrap(),
            case["steps_offset"].as_u64().unwrap() as usize,
            case["set_alpha_to_one"].as_bool().unwrap(),
            case["prediction"].as_str().unwrap(),
            case["clip_sample"].as_bool().unwrap(),
        );
        let s = sampler(&dc, steps, eta);
        assert_eq!(s.num_steps(), steps, "{name}");
        let timesteps = ints(&case["timesteps"]);
        let samples = e.get(&format!("{name}.samples"));
        let estimates = e.get(&format!("{name}.estimates"));
        let noise = (eta > 0.0).then(|| e.get(&format!("{name}.noise")));
        let (mut x, mut eps) = (x_t.clone(), vec![0.0f32; n]);
        let (mut x_prev, mut x0) = (vec![0.0f32; n], vec![0.0f32; n]);
        let mut worst = 0.0f32;
        for k in 0..steps {
            // Sampling runs spaced index N−1 down to 0; the network sees the original step.
            let t = steps - 1 - k;
            assert_eq!(s.model_timestep(t) as i64, timesteps[k], "{name} step {k}");
            fake_eps(&x, s.model_timestep(t), &bias, &mut eps);
            let z = noise.as_ref().map(|z| &z[k * n..(k + 1) * n]);
            assert_eq!(s.needs_noise(t), z.is_some(), "{name} step {k}");
            s.step(t, &x, &eps, None, z, &mut x_prev, &mut x0).unwrap();
            for (got, want, what) in [(&x_prev, &samples, "sample"), (&x0, &estimates, "x0")] {
                let want = &want[k * n..(k + 1) * n];
                let d = got
                    .iter()
                    .zip(want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                assert!(d <= TOL, "{name}: {what} after step {k} differs by {d}");
                worst = worst.max(d);
            }
            std::mem::swap(&mut x, &mut x_prev);
        }
        println!("{name}: {steps} steps, largest difference {worst:e}");
    }
}
