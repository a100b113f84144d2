//! MoLA through the session against the PyTorch reference: tools/reference/mola.py (official
//! module layouts, written from sony/MoLA as docs/official/mola-mld.md#mola-denoiser describes
//! it) with diffusers' own DDIMScheduler (trailing
//! spacing, set_alpha_to_one False, η 0); fixtures tests/fixtures/mola_tiny.safetensors
//! (converted by `tools/convert.py mola` from official-layout checkpoints) and
//! tests/fixtures/mola_expected.*, written by tools/make_latent_fixtures.py. The text vector is
//! given (the fixture's CLIP tower is a stand-in). The flag bias of the tiny VAE is set so the
//! valid-length cut lands strictly inside the decoded frames.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::{max_abs_diff, rel_diff};
use flame::checkpoint::ModelFile;
use flame::models::mola::VaeWorkspace;
use flame::models::{Condition, Model, MolaDenoiser};
use flame::session::{Session, SessionParams, Which};

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("mola_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn scalar(name: &str) -> usize {
    expected(name)[0] as usize
}

fn model() -> Arc<Model> {
    Arc::new(Model::load(fixture("mola_tiny.safetensors")).unwrap())
}

fn mola(model: &Model) -> &MolaDenoiser {
    model
        .denoiser()
        .as_any()
        .downcast_ref::<MolaDenoiser>()
        .expect("a MoLA model")
}

#[test]
fn vae_decoder_and_valid_length_match_reference() {
    let m = model();
    let vae = mola(&m).vae();
    for (latent, logits, features, length) in [
        (
            "vae_latent",
            "vae_flag_logits",
            "vae_features",
            "vae_length",
        ),
        (
            "allvalid_latent",
            "",
            "allvalid_features",
            "allvalid_length",
        ),
    ] {
        let z = expected(latent);
        let rows = z.len() / 16;
        let mut ws = VaeWorkspace::default();
        let raw = vae.decode_raw(&z, rows, &mut ws).to_vec();
        assert_eq!(raw.len(), 4 * rows * 264);
        if !logits.is_empty() {
            let flag: Vec<f32> = raw.chunks_exact(264).map(|f| f[263]).collect();
            let d = rel_diff(&flag, &expected(logits));
            assert!(d <= TOL, "{latent}: flag logits {d:e}");
        }
        let valid = vae.valid_frames(&raw, 4 * rows);
        assert_eq!(valid, scalar(length), "{latent}: valid length");
        assert!(
            valid > 10 && valid < 4 * rows,
            "{latent}: the cut is inside"
        );
        let mut out = Vec::new();
        let mut ws = flame::models::Workspace::default();
        let frames = m.decode(&z, 4 * rows - 4, &mut out, &mut ws).unwrap();
        assert_eq!(frames, valid);
        let d = rel_diff(&out, &expected(features));
        assert!(d <= TOL, "{latent}: features {d:e}");
    }
}

#[test]
fn one_forward_pass_matches_reference() {
    let m = model();
    let x = expected("noise");
    let t = expected("forward_t")[0];
    let text = Condition::text_vector(expected("text"));
    let zeros = Condition::text_vector(vec![0.0; 512]);
    let mut batch = x.clone();
    batch.extend_from_slice(&x);
    let mut out = vec![0.0; batch.len()];
    let mut ws = flame::models::Workspace::default();
    m.forward(&batch, 16, t, &[&text, &zeros], &mut out, &mut ws)
        .unwrap();
    let n = x.len();
    let dc = rel_diff(&out[..n], &expected("forward_eps_cond"));
    let du = rel_diff(&out[n..], &expected("forward_eps_uncond"));
    assert!(dc <= TOL && du <= TOL, "cond {dc:e}, uncond {du:e}");
}

fn session(guidance: f32, threads: usize) -> Session {
    let params = SessionParams {
        frames: Some(60),
        guidance: Some(guidance),
        threads,
        ..Default::default()
    };
    let mut s = Session::new(model(), &params).unwrap();
    s.set_condition(Condition::text_vector(expected("text")))
        .unwrap();
    s.set_initial_noise(&expected("noise")).unwrap();
    s
}

fn check_trajectory(mut s: Session, case: &str) {
    assert_eq!(s.num_steps(), 50);
    assert_eq!(s.sample_rows(), 16, "(60 + 4) // 4 latent rows");
    let (xs, x0s) = (
        expected(&format!("{case}_xs")),
        expected(&format!("{case}_x0s")),
    );
    let n = 16 * 16;
    let mut worst = 0.0f32;
    for k in 0..50 {
        assert_eq!(s.step().unwrap(), 49 - k);
        let dx = rel_diff(s.sample().unwrap(), &xs[k * n..(k + 1) * n]);
        let d0 = rel_diff(s.x0_estimate().unwrap(), &x0s[k * n..(k + 1) * n]);
        assert!(
            dx <= TOL && d0 <= TOL,
            "{case} step {k}: x {dx:e}, x0 {d0:e}"
        );
        worst = worst.max(dx).max(d0);
    }
    eprintln!("{case}: worst relative difference over 50 steps {worst:e}");
    let (features, frames) = s.motion(Which::Sample).unwrap();
    assert_eq!(frames, scalar(&format!("{case}_length")));
    let d = rel_diff(features, &expected(&format!("{case}_features")));
    assert!(d <= TOL, "{case}: decoded features {d:e}");
}

#[test]
fn guided_50_step_trajectory_matches_reference() {
    check_trajectory(session(11.0, 2), "g11");
}

#[test]
fn scale_1_and_0_run_one_conditional_pass_as_the_official_sampler() {
    check_trajectory(session(1.0, 1), "g1");
    check_trajectory(session(0.0, 2), "g1");
}

#[test]
fn the_estimate_decodes_too_and_is_cached_per_step() {
    let mut s = session(11.0, 1);
    assert!(
        s.motion(Which::Estimate).is_err(),
        "no estimate before a step"
    );
    s.step().unwrap();
    let (a, fa) = s
        .motion(Which::Estimate)
        .map(|(x, f)| (x.to_vec(), f))
        .unwrap();
    let (b, fb) = s
        .motion(Which::Estimate)
        .map(|(x, f)| (x.to_vec(), f))
        .unwrap();
    assert_eq!((a.len(), fa), (b.len(), fb));
    assert_eq!(max_abs_diff(&a, &b), 0.0);
    assert_eq!(a.len(), fa * 263);
    s.step().unwrap();
    let (c, _) = s.motion(Which::Estimate).unwrap();
    assert!(
        c.len() != a.len() || max_abs_diff(c, &a) > 0.0,
        "a new step decodes again"
    );
}

#[test]
fn masks_and_references_are_refused_with_a_reason() {
    let mut s = session(11.0, 1);
    let e = s
        .set_reference(&vec![0.0; 10 * 263])
        .unwrap_err()
        .to_string();
    assert!(e.contains("samples a latent"), "{e}");
    let e = s.set_mask(&vec![0; 16 * 16]).unwrap_err().to_string();
    assert!(e.contains("samples a latent"), "{e}");
}

#[test]
fn a_reset_or_new_noise_decodes_the_new_generation() {
    let fresh = |noise: &[f32]| {
        let mut s = session(11.0, 1);
        s.set_initial_noise(noise).unwrap();
        s.step().unwrap();
        s.motion(Which::Sample).map(|(x, _)| x.to_vec()).unwrap()
    };
    let other: Vec<f32> = expected("noise").iter().map(|v| -v).collect();
    let mut s = session(11.0, 1);
    s.step().unwrap();
    let first = s.motion(Which::Sample).map(|(x, _)| x.to_vec()).unwrap();
    s.reset();
    s.set_initial_noise(&other).unwrap();
    s.step().unwrap();
    let (again, _) = s.motion(Which::Sample).unwrap();
    assert_eq!(max_abs_diff(again, &fresh(&other)), 0.0);
    assert!(first.len() != again.len() || max_abs_diff(&first, again) > 0.0);
}
