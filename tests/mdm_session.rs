//! MDM and Motion Flow Matching through the session (the same step API as FLAME), against the
//! PyTorch reference. Reference: tools/reference/mdm.py (official module names, MDM's DDIM with
//! x0 prediction and guidance on x0, Motion Flow Matching's Euler loop with guidance on the
//! velocity); fixtures: tests/fixtures/{mdm,motionfm}_tiny.safetensors (converted by
//! tools/convert.py from official-layout checkpoints) and tests/fixtures/mdm_expected.*, written by
//! tools/make_mdm_fixtures.py. The text vector is given (the fixtures' CLIP tower is a stand-in).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model};
use flame::session::{Sampler, Session, SessionParams};

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("mdm_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn session(file: &str, sampler: Sampler) -> Session {
    let model = Arc::new(Model::load(fixture(file)).unwrap());
    let params = SessionParams {
        frames: Some(12),
        steps: Some(10),
        sampler: Some(sampler),
        eta: Some(0.0),
        guidance: Some(2.5),
        seed: 3,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(model, &params).unwrap();
    s.set_condition(Condition::text_vector(expected("text")))
        .unwrap();
    s
}

fn check_trajectory(mut s: Session, x_start: &str, xs: &str, x0s: Option<&str>) {
    s.set_initial_noise(&expected(x_start)).unwrap();
    let (xs, x0s) = (expected(xs), x0s.map(expected));
    let n = 12 * 263;
    for k in 0..10 {
        assert_eq!(s.step().unwrap(), 9 - k);
        let d = max_abs_diff(s.sample().unwrap(), &xs[k * n..(k + 1) * n]);
        eprintln!("step {k}: x max abs diff {d:e}");
        assert!(d <= TOL, "x at step {k}: {d:e}");
        if let Some(x0s) = &x0s {
            let d = max_abs_diff(s.x0_estimate().unwrap(), &x0s[k * n..(k + 1) * n]);
            assert!(d <= TOL, "x0 at step {k}: {d:e}");
        }
    }
}

#[test]
fn mdm_ddim_trajectory_with_guidance_matches_reference() {
    check_trajectory(
        session("mdm_tiny.safetensors", Sampler::Ddim),
        "ddim_x_T",
        "ddim_xs",
        Some("ddim_x0s"),
    );
}

#[test]
fn motionfm_euler_trajectory_with_guidance_matches_reference() {
    check_trajectory(
        session("motionfm_tiny.safetensors", Sampler::Euler),
        "euler_x_0",
        "euler_xs",
        None,
    );
}

#[test]
fn motionfm_second_order_samplers_converge_to_euler_with_many_steps() {
    // Not a parity test: Heun and midpoint run through the same step API, and with a fine grid
    // all three integrate the same ODE, so their results agree closely.
    let run = |sampler, steps| {
        let model = Arc::new(Model::load(fixture("motionfm_tiny.safetensors")).unwrap());
        let p = SessionParams {
            frames: Some(12),
            steps: Some(steps),
            sampler: Some(sampler),
            guidance: Some(2.5),
            threads: 1,
            ..Default::default()
        };
        let mut s = Session::new(model, &p).unwrap();
        s.set_condition(Condition::text_vector(expected("text")))
            .unwrap();
        s.set_initial_noise(&expected("euler_x_0")).unwrap();
        s.run().unwrap().to_vec()
    };
    let heun = run(Sampler::Heun, 50);
    let mid = run(Sampler::Midpoint, 50);
    let euler_fine = run(Sampler::Euler, 400);
    let euler_coarse = run(Sampler::Euler, 10);
    let d_second = max_abs_diff(&heun, &mid);
    let d_heun = max_abs_diff(&heun, &euler_fine);
    let d_coarse = max_abs_diff(&euler_coarse, &euler_fine);
    eprintln!(
        "heun-midpoint {d_second:e}, heun-euler400 {d_heun:e}, euler10-euler400 {d_coarse:e}"
    );
    assert!(
        d_heun < d_coarse,
        "a second-order method at 50 steps is closer to the fine solution"
    );
}

#[test]
fn wrong_sampler_for_the_model_and_wrong_condition_are_errors() {
    let model = Arc::new(Model::load(fixture("motionfm_tiny.safetensors")).unwrap());
    let p = |s| SessionParams {
        sampler: Some(s),
        ..Default::default()
    };
    let e = Session::new(Arc::clone(&model), &p(Sampler::Ddim))
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("flow-matching model takes euler, heun or midpoint"),
        "{e}"
    );
    let mdm = Arc::new(Model::load(fixture("mdm_tiny.safetensors")).unwrap());
    let e = Session::new(Arc::clone(&mdm), &p(Sampler::Heun))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("diffusion model takes ddpm or ddim"), "{e}");
    let mut s = Session::new(mdm, &SessionParams::default()).unwrap();
    let e = s
        .set_condition(Condition::text_vector(vec![0.0; 3]))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("text vector has 3 values, the model expects 512"),
        "{e}"
    );
    // The defaults of the converted files: MDM samples with DDPM, MotionFM with 10 Euler steps.
    let s = Session::new(model, &SessionParams::default()).unwrap();
    assert_eq!(s.num_steps(), 10);
}

#[test]
fn flame_info_reports_the_converted_models() {
    for (file, arch, pred, sampler) in [
        ("mdm_tiny.safetensors", "mdm", "predicts x0", "sampler ddpm"),
        (
            "motionfm_tiny.safetensors",
            "motionfm",
            "predicts velocity",
            "sampler euler",
        ),
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_flame"))
            .arg("info")
            .arg(fixture(file))
            .output()
            .unwrap();
        assert!(out.status.success());
        let text = String::from_utf8(out.stdout).unwrap();
        assert!(
            text.contains(&format!("architecture:   {arch}\n")),
            "{text}"
        );
        assert!(
            text.contains("motion:         humanml263 (263 features per frame, 20 fps"),
            "{text}"
        );
        assert!(text.contains("text encoder:   clip"), "{text}");
        assert!(text.contains(pred) && text.contains(sampler), "{text}");
    }
}

#[test]
fn prompts_go_through_the_clip_tower() {
    // The fixtures' CLIP tower is a random stand-in, so only the plumbing is checked here (the
    // tower itself is tested in tests/text_clip.rs): a prompt gives a 512-d vector that differs
    // between prompts, and a whole generation from it runs.
    let model = Arc::new(Model::load(fixture("motionfm_tiny.safetensors")).unwrap());
    let a = model.encode_prompt("a person jumps").unwrap();
    let a = a.as_text_vector().unwrap();
    let b = model.encode_prompt("a person waves").unwrap();
    let b = b.as_text_vector().unwrap();
    assert_eq!(a.len(), 512);
    assert!(max_abs_diff(a, b) > 1e-3);
    let u = model.uncond().unwrap().as_text_vector().unwrap();
    assert!(
        u.iter().all(|&v| v == 0.0),
        "MDM's unconditional input is a zero vector"
    );
    let mut s = Session::new(
        model,
        &SessionParams {
            frames: Some(8),
            seed: 1,
            threads: 1,
            ..Default::default()
        },
    )
    .unwrap();
    s.set_prompt("a person jumps").unwrap();
    assert!(s.run().unwrap().iter().all(|v| v.is_finite()));
}
