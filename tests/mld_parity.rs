//! MLD through the session against the PyTorch reference: tools/reference/mld.py (official
//! module layouts, written from ChenFengYe/motion-latent-diffusion as docs/official/mola-mld.md#mld-denoiser
//! describes it, with standard post-LN layers) with diffusers'
//! own DDIMScheduler (leading spacing, steps_offset 1, set_alpha_to_one False, η 0);
//! fixtures tests/fixtures/mld_tiny.safetensors (converted by `tools/convert.py mld` from an
//! official-layout checkpoint) and tests/fixtures/mld_expected.*, written by
//! tools/make_latent_fixtures.py. The text vectors (prompt and "") are given.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::rel_diff;
use flame::checkpoint::ModelFile;
use flame::models::{Condition, MldDenoiser, Model, Workspace};
use flame::session::{Session, SessionParams, Which};

const TOL: f32 = 1e-4;
const FRAMES: usize = 40;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("mld_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn model() -> Arc<Model> {
    Arc::new(Model::load(fixture("mld_tiny.safetensors")).unwrap())
}

#[test]
fn one_forward_pass_and_the_decoder_match_reference() {
    let m = model();
    assert!(m
        .denoiser()
        .as_any()
        .downcast_ref::<MldDenoiser>()
        .is_some());
    let x = expected("noise");
    let t = expected("forward_t")[0];
    let (u, c) = (
        Condition::text_vector(expected("text_uncond")),
        Condition::text_vector(expected("text_cond")),
    );
    let batch = [x.clone(), x.clone()].concat();
    let mut out = vec![0.0; batch.len()];
    let mut ws = Workspace::default();
    m.forward(&batch, 1, t, &[&u, &c], &mut out, &mut ws)
        .unwrap();
    let n = x.len();
    let du = rel_diff(&out[..n], &expected("forward_eps_uncond"));
    let dc = rel_diff(&out[n..], &expected("forward_eps_cond"));
    assert!(du <= TOL && dc <= TOL, "uncond {du:e}, cond {dc:e}");
    // The decoder alone: the final latent of the reference's trajectory.
    let xs = expected("g1_xs");
    let mut features = Vec::new();
    let frames = m
        .decode(&xs[49 * 64..], FRAMES, &mut features, &mut ws)
        .unwrap();
    assert_eq!(frames, FRAMES, "MLD decodes the length it is asked for");
    let d = rel_diff(&features, &expected("g1_features"));
    assert!(d <= TOL, "decoded features {d:e}");
}

fn check_trajectory(guidance: f32, case: &str) {
    let m = model();
    let params = SessionParams {
        frames: Some(FRAMES),
        guidance: Some(guidance),
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(&m), &params).unwrap();
    s.set_condition(Condition::text_vector(expected("text_cond")))
        .unwrap();
    s.set_initial_noise(&expected("noise")).unwrap();
    assert_eq!((s.num_steps(), s.sample_rows()), (50, 1));
    // The fixture's text tower is a stand-in: the reference's encoding of "" is given too.
    s.set_unconditional(Some(Condition::text_vector(expected("text_uncond"))))
        .unwrap();
    let (xs, x0s) = (
        expected(&format!("{case}_xs")),
        expected(&format!("{case}_x0s")),
    );
    let n = 64;
    for k in 0..50 {
        s.step().unwrap();
        let dx = rel_diff(s.sample().unwrap(), &xs[k * n..(k + 1) * n]);
        let d0 = rel_diff(s.x0_estimate().unwrap(), &x0s[k * n..(k + 1) * n]);
        assert!(
            dx <= TOL && d0 <= TOL,
            "{case} step {k}: x {dx:e}, x0 {d0:e}"
        );
    }
    let (features, frames) = s.motion(Which::Sample).unwrap();
    assert_eq!(frames, FRAMES);
    let d = rel_diff(features, &expected(&format!("{case}_features")));
    assert!(d <= TOL, "{case}: decoded features {d:e}");
}

#[test]
fn conditional_50_step_trajectory_matches_reference() {
    check_trajectory(1.0, "g1");
}

#[test]
fn guided_50_step_trajectory_matches_reference() {
    check_trajectory(7.5, "g7_5");
}
