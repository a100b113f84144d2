//! MotionLCM's trajectory ControlNet (v1 and v2) against the PyTorch reference
//! tools/reference/motionlcm_control.py, which itself was checked against the official modules
//! of both tags when the fixtures were made. Fixtures: tests/fixtures/motionlcm_{v1,v2}_control_tiny
//! (tiny official-layout control checkpoints converted by `tools/convert.py motionlcm
//! --control-mean --control-std`) and motionlcm_control_expected.safetensors, written by
//! tools/make_motionlcm_control_fixtures.py.
//!
//! Asserted, relative to max(1, |reference|): the normalised hint and the frame mask from joint
//! positions with NaN for free values (exact up to f32 rounding); the trajectory encoder's
//! output for a dense hint, a sparse one (where v1's row-sum rule and v2's mask rule disagree on
//! a frame) and an empty one; the ControlNet's residuals and the controlled ε of one call; the
//! controlled 1- and 2-step runs (latent, every step's estimate, decoded features).

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::rel_diff;
use flame::checkpoint::ModelFile;
use flame::models::{Cancel, Condition, Model, MotionLcmDenoiser, Workspace};
use flame::motion::{Convention, Format};
use flame::rng::NoiseSource;
use flame::session::{Session, SessionParams, Which};
use flame::targets::PositionTargets;

const FRAMES: usize = 24;
const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("motionlcm_control_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn model(release: &str) -> Arc<Model> {
    Arc::new(
        Model::load(fixture(&format!(
            "motionlcm_{release}_control_tiny.safetensors"
        )))
        .unwrap(),
    )
}

fn lcm(m: &Model) -> &MotionLcmDenoiser {
    m.denoiser().as_any().downcast_ref().unwrap()
}

fn prompt() -> String {
    let f = ModelFile::open(&fixture("motionlcm_control_expected.safetensors")).unwrap();
    let p: Vec<String> = serde_json::from_str(f.metadata("prompts").unwrap()).unwrap();
    p[0].clone()
}

struct Replay(Vec<f32>, usize);

impl NoiseSource for Replay {
    fn fill(&mut self, out: &mut [f32]) {
        out.copy_from_slice(&self.0[self.1..self.1 + out.len()]);
        self.1 += out.len();
    }
}

/// The hint rows of `{release}.{case}joints` (NaN = free) through the library, and the
/// frames with a followed value.
fn hint(m: &Model, release: &str, case: &str) -> (Vec<f32>, Vec<bool>) {
    let joints = expected(&format!("{release}.{case}joints"));
    let t = PositionTargets::new(Format::HumanMl263, &joints, None, Convention::Native).unwrap();
    let hinted = t
        .weights()
        .chunks_exact(22)
        .map(|f| f.iter().flatten().any(|&w| w > 0.0))
        .collect();
    (
        lcm(m).control_hint(t.positions(), t.weights()).unwrap(),
        hinted,
    )
}

#[test]
fn hints_and_the_trajectory_encoder_match_reference() {
    for release in ["v1", "v2"] {
        let m = model(release);
        for case in ["", "sparse."] {
            let (h, hinted) = hint(&m, release, case);
            let d = rel_diff(&h, &expected(&format!("{release}.{case}hint")));
            assert!(d <= 1e-6, "{release} {case}hint {d:e}");
            let cond = lcm(&m).control_condition(&h, &hinted, FRAMES).unwrap();
            let d = rel_diff(&cond, &expected(&format!("{release}.{case}control_cond")));
            assert!(d <= TOL, "{release} {case}control_cond {d:e}");
        }
        // Nothing hinted: the encoder attends to its global tokens alone.
        let zeros = vec![0.0; FRAMES * 66];
        let cond = lcm(&m)
            .control_condition(&zeros, &[false; FRAMES], FRAMES)
            .unwrap();
        let d = rel_diff(&cond, &expected(&format!("{release}.empty_cond")));
        assert!(d <= TOL, "{release} empty_cond {d:e}");
    }
}

#[test]
fn residuals_and_a_controlled_call_match_reference() {
    for release in ["v1", "v2"] {
        let m = model(release);
        let p = |n: &str| expected(&format!("{release}.forward.{n}"));
        let (h, hinted) = hint(&m, release, "");
        let cond = lcm(&m).control_condition(&h, &hinted, FRAMES).unwrap();
        let text = expected("text.0");
        let (z, t, w) = (p("z"), p("t")[0], p("w")[0]);
        let r = lcm(&m).control_residuals(&z, t, w, &text, &cond).unwrap();
        let d = rel_diff(&r, &expected(&format!("{release}.residuals")));
        assert!(d <= TOL, "{release} residuals {d:e}");
        let c = Condition::text_vector(text);
        let rows = m.sample_rows(FRAMES);
        let mut eps = vec![0.0; z.len()];
        let mut ws = Workspace::default();
        let never = Cancel::never();
        m.forward_embedded(
            &z,
            rows,
            t,
            w,
            &[&c],
            Some(&cond),
            &mut eps,
            &mut ws,
            &never,
        )
        .unwrap();
        let d = rel_diff(&eps, &p("eps"));
        assert!(d <= TOL, "{release} controlled eps {d:e}");
        // The same workspace without control gives the plain network's ε.
        m.forward_embedded(&z, rows, t, w, &[&c], None, &mut eps, &mut ws, &never)
            .unwrap();
        let d = rel_diff(&eps, &p("eps_plain"));
        assert!(d <= TOL, "{release} plain eps {d:e}");
    }
}

#[test]
fn controlled_runs_match_reference() {
    for release in ["v1", "v2"] {
        let m = model(release);
        for steps in [1, 2] {
            let case = |n: &str| expected(&format!("{release}.s{steps}.{n}"));
            let params = SessionParams {
                frames: Some(FRAMES),
                steps: Some(steps),
                guidance: Some(case("guidance")[0]),
                threads: 2,
                ..Default::default()
            };
            let mut s = Session::new(Arc::clone(&m), &params).unwrap();
            s.set_prompt(&prompt()).unwrap();
            let joints = expected(&format!("{release}.joints"));
            s.set_control_values(&joints, None, Convention::Native)
                .unwrap();
            assert!(s.has_control());
            s.set_initial_noise(&case("noise")).unwrap();
            s.set_noise_source(Box::new(Replay(case("renoise"), 0)));
            let denoised = case("denoised");
            let n = denoised.len() / steps;
            for k in 0..steps {
                s.step().unwrap();
                let d = rel_diff(s.x0_estimate().unwrap(), &denoised[k * n..(k + 1) * n]);
                assert!(d <= TOL, "{release} {steps} steps, step {k}: {d:e}");
            }
            let d = rel_diff(s.sample().unwrap(), &case("latent"));
            assert!(d <= TOL, "{release} {steps} steps: latent {d:e}");
            let (features, frames) = s.motion(Which::Sample).unwrap();
            assert_eq!(frames, FRAMES);
            let d = rel_diff(features, &case("features"));
            assert!(d <= TOL, "{release} {steps} steps: features {d:e}");
        }
    }
}

#[test]
fn bad_controls_are_refused_with_the_reason() {
    let m = model("v2");
    let params = SessionParams {
        frames: Some(FRAMES),
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(&m), &params).unwrap();
    let err = |r: flame::Result<()>| r.unwrap_err().to_string();
    // NaN everywhere: nothing to follow.
    let e = err(s.set_control_values(&vec![f32::NAN; FRAMES * 66], None, Convention::Native));
    assert!(e.contains("constrain"), "{e}");
    // The wrong joint count.
    let e = err(s.set_control_values(&vec![0.0; FRAMES * 21 * 3], None, Convention::Native));
    assert!(e.contains("22 joints"), "{e}");
    // More frames than the session.
    let e = err(s.set_control_values(&vec![0.0; (FRAMES + 1) * 66], None, Convention::Native));
    assert!(e.contains("the session has 24"), "{e}");
    assert!(!s.has_control(), "nothing was set");
    // A file without a ControlNet.
    let plain = Arc::new(Model::load(fixture("motionlcm_v2_tiny.safetensors")).unwrap());
    let mut s = Session::new(plain, &params).unwrap();
    let e = err(s.set_control_values(&vec![0.0; FRAMES * 66], None, Convention::Native));
    assert!(e.contains("no ControlNet"), "{e}");
    // A model of another family.
    let mld = Arc::new(Model::load(fixture("mld_tiny.safetensors")).unwrap());
    let mut s = Session::new(
        mld,
        &SessionParams {
            frames: Some(FRAMES),
            ..Default::default()
        },
    )
    .unwrap();
    let e = err(s.set_control_values(&vec![0.0; FRAMES * 66], None, Convention::Native));
    assert!(e.contains("no trajectory control"), "{e}");
    // Files: a std of 0, a missing section.
    let bytes = std::fs::read(fixture("motionlcm_v1_control_tiny.safetensors")).unwrap();
    let e = match Model::from_bytes(&common::zero_tensors(&bytes, |n| n == "control.std_raw")) {
        Ok(_) => panic!("a zero std loaded"),
        Err(e) => e.to_string(),
    };
    assert!(e.contains("`control.std_raw` holds 0"), "{e}");
    let e = match Model::from_bytes(&common::with_config(&bytes, |c| {
        c.as_object_mut().unwrap().remove("control");
    })) {
        Ok(_) => panic!("ControlNet tensors without a control section loaded"),
        Err(e) => e.to_string(),
    };
    assert!(e.contains("no `control` section"), "{e}");
}

/// Editing on a control file goes through the ControlNet: `set_task_targets` with the
/// prediction task gives the same run, bit for bit, as a hint kept here by hand from the
/// task's definition (the reference's 22 joints on frames `[0, ⌊L/4⌋)`, nothing after), and that
/// run differs from the uncontrolled one.
#[test]
fn editing_tasks_follow_the_reference_through_the_control_net() {
    use flame::motion::{Poses, Task};
    for release in ["v1", "v2"] {
        let m = model(release);
        let params = SessionParams {
            frames: Some(FRAMES),
            steps: Some(2),
            seed: 7,
            threads: 2,
            ..Default::default()
        };
        let run = |set: &dyn Fn(&mut Session)| {
            let mut s = Session::new(Arc::clone(&m), &params).unwrap();
            s.set_prompt(&prompt()).unwrap();
            set(&mut s);
            s.run().unwrap();
            s.motion(Which::Sample).unwrap().0.to_vec()
        };
        let reference = run(&|_| {});
        let edited = run(&|s| {
            s.set_task_targets(&reference, Task::Predict).unwrap();
            assert!(
                s.has_control(),
                "{release}: the task became the control hint"
            );
        });
        let poses = Poses::decode(
            m.motion_format(),
            &reference,
            FRAMES,
            &m.read_options(0.0, true),
        )
        .unwrap();
        let positions = poses.positions(Convention::Native);
        let keep: Vec<bool> = (0..FRAMES * 22).map(|i| i / 22 < FRAMES / 4).collect();
        let hint =
            PositionTargets::from_positions(m.motion_format(), &positions, FRAMES, &keep).unwrap();
        let by_hand = run(&|s| s.set_control(&hint).unwrap());
        assert_eq!(
            edited, by_hand,
            "{release}: the task's hint is the hand-written one"
        );
        let d = rel_diff(&edited, &reference);
        assert!(
            d > 1e-3,
            "{release}: the control changes the motion ({d:e})"
        );
    }
}
