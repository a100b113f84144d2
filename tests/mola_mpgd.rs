//! MoLA's MPGD editing through the session against the PyTorch reference
//! (tools/reference/mola_mpgd.py: the official algorithm with torch.autograd on the reference
//! modules of tools/reference/mola.py and diffusers' DDIM table), on the tiny MoLA model, for
//! the three official tasks (path, in-betweening, upper-body editing): every step's latent and
//! edited x̂0, the loss at each step's unedited x̂0, and the final features cut by the flag.
//! Fixture: tests/fixtures/mola_mpgd_expected.*, written by tools/make_mpgd_fixtures.py.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::{max_abs_diff, rel_diff};
use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model};
use flame::motion::Convention;
use flame::session::{Session, SessionParams, Which};
use flame::targets::{TargetParams, TargetSchedule};

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("mola_mpgd_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

/// The largest difference relative to max(1, the largest |reference| value).
fn scaled_diff(got: &[f32], want: &[f32]) -> f32 {
    let scale = want.iter().fold(1.0f32, |m, w| m.max(w.abs()));
    max_abs_diff(got, want) / scale
}

#[test]
fn mpgd_edits_match_the_reference_step_by_step() {
    let model = Arc::new(Model::load(fixture("mola_tiny.safetensors")).unwrap());
    let frames = 24;
    for task in ["path", "inbetweening", "upper_edit"] {
        let params = SessionParams {
            frames: Some(frames),
            guidance: Some(11.0),
            threads: 1,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(&model), &params).unwrap();
        assert_eq!(s.num_steps(), 50);
        s.set_condition(Condition::text_vector(expected("text")))
            .unwrap();
        s.set_initial_noise(&expected("noise")).unwrap();
        // MoLA's control: zeros are unconstrained, coordinate by coordinate.
        let control = expected(&format!("{task}_control"));
        let mask: Vec<u8> = control.iter().map(|&c| (c != 0.0) as u8).collect();
        s.set_position_target_values(&control, Some(&mask), Convention::Native)
            .unwrap();
        s.set_target_params(&TargetParams {
            scale: expected("edit_scale")[0],
            schedule: TargetSchedule::Mpgd,
        })
        .unwrap();
        let (xs, x0s, losses) = (
            expected(&format!("{task}_xs")),
            expected(&format!("{task}_x0s")),
            expected(&format!("{task}_loss")),
        );
        let n = 7 * 16;
        let (mut worst, mut worst_x0) = (0.0f32, 0.0f32);
        for k in 0..50 {
            s.step().unwrap();
            let dx = rel_diff(s.sample().unwrap(), &xs[k * n..(k + 1) * n]);
            // The edited x̂0 holds the gradient step ρ·∇L, whose float32 rounding is relative to
            // the step's largest value (up to ~30 here), not to each element.
            let d0 = scaled_diff(s.x0_estimate().unwrap(), &x0s[k * n..(k + 1) * n]);
            let loss = s.target_loss().unwrap();
            let dl = ((loss - losses[k] as f64) / losses[k] as f64).abs() as f32;
            assert!(
                dx <= TOL && d0 <= TOL && dl <= TOL,
                "{task} step {k}: latent {dx:e}, edited x0 {d0:e}, loss {loss} vs {} ({dl:e})",
                losses[k]
            );
            worst = worst.max(dx).max(d0);
            worst_x0 = worst_x0.max(rel_diff(s.x0_estimate().unwrap(), &x0s[k * n..(k + 1) * n]));
        }
        let (features, got_frames) = s.motion(Which::Sample).unwrap();
        assert_eq!(got_frames, expected(&format!("{task}_length"))[0] as usize);
        let df = rel_diff(features, &expected(&format!("{task}_features")));
        assert!(df <= TOL, "{task}: features {df:e}");
        println!(
            "{task}: worst step difference {worst:e} (edited x0 element-wise {worst_x0:e}), features {df:e}"
        );
    }
}

#[test]
fn task_targets_from_a_reference_are_the_official_controls() {
    // `path` and `upper_edit` taken from the reference motion by `Session::set_task_targets`
    // constrain what the official controls do (the pelvis at frame 0, whose x and z the official
    // control leaves free, sits exactly on its target there), so the edit is the same.
    let model = Arc::new(Model::load(fixture("mola_tiny.safetensors")).unwrap());
    for (task, name) in [
        (flame::motion::Task::Path, "path"),
        (flame::motion::Task::UpperBody, "upper_edit"),
    ] {
        let params = SessionParams {
            frames: Some(24),
            guidance: Some(11.0),
            threads: 1,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(&model), &params).unwrap();
        s.set_condition(Condition::text_vector(expected("text")))
            .unwrap();
        s.set_initial_noise(&expected("noise")).unwrap();
        s.set_task_targets(&expected("reference_features"), task)
            .unwrap();
        assert_eq!(s.target_params().schedule, TargetSchedule::Mpgd);
        s.run().unwrap();
        let xs = expected(&format!("{name}_xs"));
        let d = rel_diff(s.sample().unwrap(), &xs[49 * 112..]);
        assert!(d <= TOL, "{name}: final latent {d:e}");
    }
}
