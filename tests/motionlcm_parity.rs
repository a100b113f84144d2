//! MotionLCM (v1 and v2) through the session against the PyTorch reference
//! tools/reference/motionlcm.py, which steps with diffusers' own `LCMScheduler` (through
//! tools/reference/diffusers_lcm.py, v2's table included) and encodes prompts with transformers'
//! own `T5EncoderModel` plus sentence-t5's head. Fixtures: tests/fixtures/motionlcm_v1_tiny and
//! motionlcm_v2_tiny (tiny official-layout random checkpoints converted by
//! `tools/convert.py motionlcm`) and motionlcm_expected.safetensors, all written by
//! tools/make_motionlcm_fixtures.py.
//!
//! Asserted (measured in brackets, relative to max(1, |reference|)): the prompts' sentence
//! vectors within 1e-5 (1.6e-7); one denoiser call at t = 699, w = 6.5 within 1e-5 (4.3e-7);
//! the guidance embedding within 1e-6; the 1-, 2- and 4-step runs (the file's guidance for the
//! step count, the reference's initial and re-noising draws) within 1e-4 at every step's
//! consistency estimate and the final latent (6.0e-6 v1, 1.5e-6 v2) and at the decoded features
//! (1.1e-6).

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::rel_diff;
use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model, MotionLcmDenoiser, Workspace};
use flame::rng::NoiseSource;
use flame::session::{Session, SessionParams, Which};

const FRAMES: usize = 24;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("motionlcm_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn model(release: &str) -> Arc<Model> {
    Arc::new(Model::load(fixture(&format!("motionlcm_{release}_tiny.safetensors"))).unwrap())
}

fn prompts() -> Vec<String> {
    let f = ModelFile::open(&fixture("motionlcm_expected.safetensors")).unwrap();
    serde_json::from_str(f.metadata("prompts").unwrap()).unwrap()
}

/// Hands out the reference's re-noising draws, in order.
struct Replay(Vec<f32>, usize);

impl NoiseSource for Replay {
    fn fill(&mut self, out: &mut [f32]) {
        out.copy_from_slice(&self.0[self.1..self.1 + out.len()]);
        self.1 += out.len();
    }
}

#[test]
fn prompts_encode_as_sentence_t5_does() {
    let m = model("v1");
    for (i, p) in prompts().iter().enumerate() {
        let c = m.encode_prompt(p).unwrap();
        let d = rel_diff(c.as_text_vector().unwrap(), &expected(&format!("text.{i}")));
        assert!(d <= 1e-5, "prompt {i}: {d:e}");
    }
    // Both releases share the text encoder.
    let v2 = model("v2").encode_prompt(&prompts()[0]).unwrap();
    let d = rel_diff(v2.as_text_vector().unwrap(), &expected("text.0"));
    assert!(d <= 1e-5, "v2: {d:e}");
}

#[test]
fn one_denoiser_call_matches_reference() {
    for release in ["v1", "v2"] {
        let m = model(release);
        assert!(m
            .denoiser()
            .as_any()
            .downcast_ref::<MotionLcmDenoiser>()
            .is_some());
        let p = |n: &str| expected(&format!("{release}.forward.{n}"));
        let z = p("z");
        let cond = Condition::text_vector(expected("text.0"));
        let mut out = vec![0.0; z.len()];
        let rows = m.sample_rows(FRAMES);
        m.forward_embedded(
            &z,
            rows,
            p("t")[0],
            p("w")[0],
            &[&cond],
            None,
            &mut out,
            &mut Workspace::default(),
            &flame::models::Cancel::never(),
        )
        .unwrap();
        let d = rel_diff(&out, &p("eps"));
        assert!(d <= 1e-5, "{release}: eps {d:e}");
    }
}

fn check_run(release: &str, steps: usize) {
    let m = model(release);
    let case = |n: &str| expected(&format!("{release}.s{steps}.{n}"));
    let params = SessionParams {
        frames: Some(FRAMES),
        steps: Some(steps),
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(&m), &params).unwrap();
    assert_eq!(s.num_steps(), steps);
    s.set_prompt(&prompts()[0]).unwrap();
    s.set_initial_noise(&case("noise")).unwrap();
    s.set_noise_source(Box::new(Replay(case("renoise"), 0)));
    let denoised = case("denoised");
    let n = denoised.len() / steps;
    for k in 0..steps {
        s.step().unwrap();
        let d = rel_diff(s.x0_estimate().unwrap(), &denoised[k * n..(k + 1) * n]);
        assert!(
            d <= 1e-4,
            "{release} {steps} steps, step {k}: estimate {d:e}"
        );
    }
    let d = rel_diff(s.sample().unwrap(), &case("latent"));
    assert!(d <= 1e-4, "{release} {steps} steps: latent {d:e}");
    let (features, frames) = s.motion(Which::Sample).unwrap();
    assert_eq!(frames, FRAMES);
    let d = rel_diff(features, &case("features"));
    assert!(d <= 1e-4, "{release} {steps} steps: features {d:e}");
}

#[test]
fn v1_runs_of_1_2_and_4_steps_match_reference() {
    for steps in [1, 2, 4] {
        check_run("v1", steps);
    }
}

#[test]
fn v2_runs_of_1_2_and_4_steps_match_reference() {
    for steps in [1, 2, 4] {
        check_run("v2", steps);
    }
}

#[test]
fn the_guidance_embedding_matches_the_reference() {
    for release in ["v1", "v2"] {
        let want = expected(&format!("{release}.embedding"));
        let mut e = vec![0.0; want.len()];
        flame::kernels::guidance_embedding(expected(&format!("{release}.forward.w"))[0], &mut e);
        // The argument reaches 6500 rad, where one f32 ulp of it is 4.9e-4: both sides form it
        // in f32 the same way, so only sin/cos rounding (≤ 1 ulp of the result) differs.
        let d = common::max_abs_diff(&e, &want);
        assert!(d <= 1e-6, "{release}: {d:e}");
    }
}

fn load_err(bytes: Vec<u8>) -> String {
    match Model::from_bytes(&bytes) {
        Ok(_) => panic!("the file loaded"),
        Err(e) => e.to_string(),
    }
}

/// A safetensors file's bytes with metadata `key` set to `value`.
fn with_metadata(bytes: &[u8], key: &str, value: &str) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    header["__metadata__"][key] = value.into();
    let mut text = serde_json::to_vec(&header).unwrap();
    while !text.len().is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

#[test]
fn bad_files_and_settings_are_refused_with_the_reason() {
    let v1 = std::fs::read(fixture("motionlcm_v1_tiny.safetensors")).unwrap();
    let v2 = std::fs::read(fixture("motionlcm_v2_tiny.safetensors")).unwrap();
    // A v2 file whose configuration claims a v1 latent (channels = width).
    let e = load_err(common::with_config(&v2, |c| {
        c["denoiser"]["latent_channels"] = 32.into();
        c["vae"]["latent_channels"] = 32.into();
    }));
    assert!(
        e.contains("`denoiser.latent_pre.weight` (MotionLCM v2's latent projection)"),
        "{e}"
    );
    // A v1 file claiming v2's latent misses the projections.
    let e = load_err(common::with_config(&v1, |c| {
        c["denoiser"]["latent_channels"] = 8.into();
        c["vae"]["latent_channels"] = 8.into();
    }));
    assert!(e.contains("denoiser.latent_pre.weight"), "{e}");
    // A tokenizer whose ids exceed the T5 embedding table (CLIP's, 49408 ids).
    let clip = std::fs::read_to_string(fixture("clip_tokenizer/tokenizer.json")).unwrap();
    let e = load_err(with_metadata(&v1, "flame.tokenizer", &clip));
    assert!(e.contains("vocab") || e.contains("vocabulary"), "{e}");
    // A guidance for a step count the release has no timesteps for.
    let e = load_err(common::with_config(&v2, |c| {
        c["defaults"]["guidance_by_steps"]["3"] = 9.0.into();
    }));
    assert!(
        e.contains("defaults.guidance_by_steps.3") && e.contains("1, 2, 4"),
        "{e}"
    );
    let e = load_err(common::with_config(&v1, |c| {
        c["diffusion"]["lcm_timesteps"] = "table".into();
    }));
    assert!(
        e.contains("unknown config diffusion.lcm_timesteps `table`"),
        "{e}"
    );
    let e = load_err(common::with_config(&v1, |c| {
        c["diffusion"]["spacing"] = "leading".into();
    }));
    assert!(
        e.contains("motionlcm samples with the latent consistency sampler"),
        "{e}"
    );
    // The consistency sampler's fields on a DDIM-spaced model.
    let mld = std::fs::read(fixture("mld_tiny.safetensors")).unwrap();
    let e = load_err(common::with_config(&mld, |c| {
        c["diffusion"]["lcm_timesteps"] = "grid".into();
    }));
    assert!(e.contains("need diffusion.spacing `lcm`"), "{e}");
    let e = load_err(common::with_config(&v1, |c| {
        c["denoiser"]["cond_dim"] = 15.into();
    }));
    assert!(e.contains("cond_dim 15 is not even"), "{e}");

    // Sessions: a step count the table lacks, a sampler of another family.
    let m = model("v2");
    let session = |steps: Option<usize>, sampler: Option<flame::session::Sampler>| {
        let p = SessionParams {
            frames: Some(FRAMES),
            steps,
            sampler,
            ..Default::default()
        };
        Session::new(Arc::clone(&m), &p)
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    let e = session(Some(3), None);
    assert!(
        e.contains("no 3-step schedule") && e.contains("samples 1, 2, 4 steps"),
        "{e}"
    );
    let e = session(None, Some(flame::session::Sampler::Ddim));
    assert!(e.contains("samples with lcm"), "{e}");
    let e = model("v1")
        .encode_prompt(&"walk ".repeat(400))
        .map(|_| ())
        .err();
    assert!(
        e.is_none(),
        "a long prompt is cut to max_length, not refused: {e:?}"
    );
}

#[test]
fn guidance_defaults_follow_the_step_count_and_a_blank_prompt_still_embeds_it() {
    // v2's "dynamic" scale: the same noise at 2 steps gives a different estimate under the
    // file's 12.5 than under an explicit 8.0.
    let m = model("v2");
    let run = |guidance: Option<f32>, prompt: &str| {
        let p = SessionParams {
            frames: Some(FRAMES),
            steps: Some(2),
            guidance,
            seed: 7,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(&m), &p).unwrap();
        s.set_prompt(prompt).unwrap();
        s.run().unwrap().to_vec()
    };
    let p = &prompts()[0];
    assert_eq!(run(None, p), run(Some(12.5), p));
    assert_ne!(run(None, p), run(Some(8.0), p));
    // A blank prompt conditions on the empty prompt's vector at the embedded scale.
    let blank = run(None, "");
    assert!(blank.iter().all(|v| v.is_finite()));
    assert_ne!(blank, run(Some(8.0), ""));
}
