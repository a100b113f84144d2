//! MotionLCM's consistency latent tuning (`Session::tune_latent`, `flame generate --optimize`)
//! against PyTorch autograd: tools/reference/motionlcm_tuning.py runs the release's loop
//! (torch.optim.Adam, diffusers' cosine schedule and LCMScheduler) on the trajectory-control tiny
//! files; tools/make_motionlcm_tuning_fixtures.py wrote tests/fixtures/
//! motionlcm_tuning_expected.safetensors.
//!
//! Asserted, relative to max(1, |reference|) unless said: the product back through the
//! controlled denoiser (its ControlNet copy included) and through the VAE decoder for random
//! upstream gradients; the loss (hint + 100 × the noise regulariser) and its whole gradient at a
//! latent; the latent after 12 iterations of the loop and the loss at each; that the tuned
//! latent is what the session then samples from; and the refusals.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::rel_diff;
use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model, Workspace};
use flame::motion::{Convention, Format};
use flame::session::{Session, SessionParams, Which};
use flame::targets::PositionTargets;
use flame::tuning::TuningParams;
use flame::Error;

const FRAMES: usize = 24;
const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn tensor(file: &str, name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture(file)).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn expected(name: &str) -> Vec<f32> {
    tensor("motionlcm_tuning_expected.safetensors", name)
}

fn model(release: &str) -> Arc<Model> {
    Arc::new(
        Model::load(fixture(&format!(
            "motionlcm_{release}_control_tiny.safetensors"
        )))
        .unwrap(),
    )
}

fn prompt() -> String {
    let f = ModelFile::open(&fixture("motionlcm_tuning_expected.safetensors")).unwrap();
    let p: Vec<String> = serde_json::from_str(f.metadata("prompts").unwrap()).unwrap();
    p[0].clone()
}

/// The main hint of the control fixtures (pelvis on every frame, five joints on frames 0-4).
fn hint(release: &str) -> PositionTargets {
    let joints = tensor(
        "motionlcm_control_expected.safetensors",
        &format!("{release}.joints"),
    );
    PositionTargets::new(Format::HumanMl263, &joints, None, Convention::Native).unwrap()
}

/// A 1-step session of the prompt with the hint as its control.
fn session(m: &Arc<Model>, release: &str) -> Session {
    let params = SessionParams {
        frames: Some(FRAMES),
        steps: Some(1),
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(m), &params).unwrap();
    s.set_prompt(&prompt()).unwrap();
    s.set_control(&hint(release)).unwrap();
    s
}

/// The relative difference of f64 values, as `rel_diff`.
fn rel_diff64(got: &[f64], want: &[f32]) -> f64 {
    got.iter()
        .zip(want)
        .map(|(g, &w)| (g - w as f64).abs() / (w as f64).abs().max(1.0))
        .fold(0.0, f64::max)
}

#[test]
fn the_network_and_decoder_products_match_autograd() {
    for release in ["v1", "v2"] {
        let m = model(release);
        let p = |n: &str| expected(&format!("{release}.{n}"));
        let den = m.denoiser();
        let text = tensor("motionlcm_control_expected.safetensors", "text.0");
        let cond = Condition::text_vector(text);
        let h = hint(release);
        let control = den
            .encode_control(FRAMES, h.positions(), h.weights())
            .unwrap();
        let (z, t, w) = (p("z"), p("t")[0], p("guidance")[0] - 1.0);
        let rows = m.sample_rows(FRAMES);
        let mut eps = vec![0.0; z.len()];
        let mut tape = Workspace::default();
        den.eps_recorded(&z, rows, t, w, &cond, Some(&control), &mut eps, &mut tape)
            .unwrap();
        let mut dz = vec![0.0; z.len()];
        den.eps_vjp(&p("eps_up"), &mut dz, &mut tape).unwrap();
        let d = rel_diff(&dz, &p("eps_vjp"));
        eprintln!("{release} denoiser + ControlNet vjp {d:e}");
        assert!(d <= TOL, "{release} denoiser + ControlNet vjp {d:e}");

        let dec = den.decoder().unwrap();
        let mut feats = Vec::new();
        let mut tape = Workspace::default();
        dec.decode_recorded(&z, rows, FRAMES, &mut feats, &mut tape)
            .unwrap();
        // The recorded decode is the sampling decode's to rounding.
        let mut plain = Vec::new();
        dec.decode(&z, rows, FRAMES, &mut plain, &mut Workspace::default())
            .unwrap();
        assert!(
            rel_diff(&feats, &plain) <= 1e-5,
            "{release} recorded decode"
        );
        dec.decode_vjp(&p("feat_up"), &mut dz, &mut tape).unwrap();
        let d = rel_diff(&dz, &p("dec_vjp"));
        eprintln!("{release} VAE decoder vjp {d:e}");
        assert!(d <= TOL, "{release} VAE decoder vjp {d:e}");
    }
}

#[test]
fn the_loss_and_its_gradient_match_autograd() {
    for release in ["v1", "v2"] {
        let m = model(release);
        let p = |n: &str| expected(&format!("{release}.{n}"));
        let s = session(&m, release);
        let (loss, grad) = s.tuning_gradient(&p("z"), &TuningParams::new(400)).unwrap();
        let want = p("loss")[0] as f64;
        assert!(
            (loss - want).abs() <= 1e-5 * want.abs(),
            "{release} loss {loss} vs {want}"
        );
        // Relative to the largest component (the regulariser's share dwarfs some).
        let want = p("grad");
        let top = want.iter().fold(0f32, |a, v| a.max(v.abs())) as f64;
        let d = grad
            .iter()
            .zip(&want)
            .map(|(g, &w)| (g - w as f64).abs())
            .fold(0.0, f64::max)
            / top;
        eprintln!("{release} gradient {d:e}");
        assert!(d <= TOL as f64, "{release} gradient {d:e}");
    }
}

#[test]
fn twelve_iterations_match_the_release_loop_and_sampling_uses_the_result() {
    for release in ["v1", "v2"] {
        let m = model(release);
        let p = |n: &str| expected(&format!("{release}.{n}"));
        let mut s = session(&m, release);
        s.set_initial_noise(&p("z")).unwrap();
        let report = s.tune_latent(&TuningParams::new(12)).unwrap();
        let tuned = s.initial_noise().unwrap().to_vec();
        let d = rel_diff(&tuned, &p("tuned"));
        eprintln!("{release} tuned latent {d:e}");
        assert!(d <= TOL, "{release} tuned latent {d:e}");
        let d = rel_diff64(&report.losses, &p("losses"));
        eprintln!("{release} losses {d:e}");
        assert!(d <= 1e-5, "{release} losses {d:e}");
        assert_eq!(report.iterations, 12);
        // The hint is followed better, as the loss says.
        assert!(report.hint_loss[1] < report.hint_loss[0], "{report:?}");
        assert!(
            report.control_error[1] < report.control_error[0],
            "{report:?}"
        );
        // The session samples from the tuned latent: the bits of a session given it by hand.
        s.run().unwrap();
        let mut by_hand = session(&m, release);
        by_hand.set_initial_noise(&tuned).unwrap();
        by_hand.run().unwrap();
        assert_eq!(s.sample(), by_hand.sample(), "{release}");
        let motion = |s: &mut Session| s.motion(Which::Sample).unwrap().0.to_vec();
        assert_eq!(motion(&mut s), motion(&mut by_hand));
    }
}

#[test]
fn tuning_refuses_what_it_cannot_run() {
    let m = model("v2");
    let err = |r: flame::Result<flame::tuning::TuningReport>| r.unwrap_err().to_string();
    let params = TuningParams::new(3);
    // No control.
    let mut s = Session::new(
        Arc::clone(&m),
        &SessionParams {
            frames: Some(FRAMES),
            steps: Some(1),
            ..Default::default()
        },
    )
    .unwrap();
    s.set_prompt(&prompt()).unwrap();
    assert!(matches!(s.tune_latent(&params), Err(Error::WrongState(_))));
    // Nothing was drawn: the seed's run is unchanged.
    assert!(s.initial_noise().is_none());
    // Two steps.
    let mut s = Session::new(
        Arc::clone(&m),
        &SessionParams {
            frames: Some(FRAMES),
            steps: Some(2),
            ..Default::default()
        },
    )
    .unwrap();
    s.set_prompt(&prompt()).unwrap();
    s.set_control(&hint("v2")).unwrap();
    assert!(err(s.tune_latent(&params)).contains("1-step sampler"));
    // Zero iterations, a warm-up longer than the run, after the first step.
    let mut s = session(&m, "v2");
    assert!(err(s.tune_latent(&TuningParams::new(0))).contains("1 to"));
    let long = TuningParams {
        warmup: Some(5),
        ..params
    };
    assert!(err(s.tune_latent(&long)).contains("warm-up"));
    let e = s
        .tuning_gradient(&[1.0; 3], &params)
        .unwrap_err()
        .to_string();
    assert!(e.contains("finite values"), "{e}");
    s.step().unwrap();
    assert!(matches!(s.tune_latent(&params), Err(Error::WrongState(_))));
    // A model without a consistency sampler.
    let mld = Arc::new(Model::load(fixture("mld_tiny.safetensors")).unwrap());
    let mut s = Session::new(mld, &SessionParams::default()).unwrap();
    assert!(err(s.tune_latent(&params)).contains("latent consistency"));
}

#[test]
fn a_cancelled_tuning_leaves_the_seeds_latent() {
    let m = model("v1");
    let mut s = session(&m, "v1");
    s.cancel_flag()
        .store(true, std::sync::atomic::Ordering::SeqCst);
    assert!(matches!(
        s.tune_latent(&TuningParams::new(5)),
        Err(Error::Cancelled)
    ));
    s.cancel_flag()
        .store(false, std::sync::atomic::Ordering::SeqCst);
    s.run().unwrap();
    let mut plain = session(&m, "v1");
    plain.run().unwrap();
    assert_eq!(s.sample(), plain.sample());
}
