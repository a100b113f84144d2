//! FineMoGen against the PyTorch reference of the released code: tools/reference/finemogen.py
//! (written from the released code as docs/official/finemogen.md describes it, the tutel routing
//! written out), on a tiny official-layout random
//! model converted by `tools/convert.py finemogen` (tests/fixtures/finemogen_tiny.safetensors),
//! expected outputs from tools/make_finemogen_fixtures.py (tests/fixtures/finemogen_expected.*).
//! The fixture's gates are shaped so every routing decision has a margin far above f32 error
//! (the generator checks it, and its float64 run takes the same decisions), and capacity drops
//! happen in both mixtures of experts in every call; the json records how many.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::max_abs_diff;
use flame::checkpoint::ModelFile;
use flame::models::finemogen::{FinemogenCondition, FinemogenWorkspace};
use flame::models::{Cancel, FinemogenDenoiser, Model, TextModel};
use flame::session::{Session, SessionParams, Which};
use flame::stages::{BodyPart, Stage};

/// Trajectories (50 steps) and forward outputs; the text encoder within 1e-5.
const TOL: f32 = 1e-4;
const TEXT_TOL: f32 = 1e-5;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("finemogen_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn json() -> serde_json::Value {
    let text = std::fs::read_to_string(fixture("finemogen_expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn prompt(key: &str) -> String {
    json()["prompts"][key].as_str().unwrap().to_string()
}

fn model() -> Arc<Model> {
    Arc::new(Model::load(fixture("finemogen_tiny.safetensors")).unwrap())
}

fn finemogen(model: &Model) -> &FinemogenDenoiser {
    model
        .denoiser()
        .as_any()
        .downcast_ref::<FinemogenDenoiser>()
        .expect("a FineMoGen model")
}

/// Dropped choices of one MoE kind (`text` or `motion`) over the layers of a fixture case.
fn dropped(case: &str, kind: &str) -> usize {
    let moe = &json()["cases"][case]["moe"];
    moe.as_object()
        .unwrap()
        .iter()
        .filter(|(k, _)| k.starts_with(kind))
        .map(|(_, v)| {
            (v["first_dropped"].as_u64().unwrap() + v["second_dropped"].as_u64().unwrap()) as usize
        })
        .sum()
}

#[test]
fn text_encoder_matches_reference() {
    let m = model();
    let TextModel::Clip { encoder, context } = m.text_model() else {
        panic!("CLIP")
    };
    for key in ["A", "B", "C"] {
        let text = prompt(key);
        let clip = encoder.encode(&text, *context).unwrap();
        let ids: Vec<u32> = json()["ids"][key]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as u32)
            .collect();
        assert_eq!(clip.ids, ids, "{key}: all 77 positions, padded with 0");
        let d = max_abs_diff(&clip.tokens, &expected(&format!("clip.{key}")));
        assert!(d < TEXT_TOL, "clip.{key}: {d}");
        let xf = finemogen(&m).encode_text(m.text_model(), &text).unwrap();
        let d = max_abs_diff(&xf, &expected(&format!("xf.{key}")));
        assert!(d < TEXT_TOL, "xf.{key}: {d}");
    }
}

#[test]
fn one_forward_pass_matches_reference_with_the_same_drops() {
    let m = model();
    let net = finemogen(&m);
    let j = json();
    let t = j["forward"]["t"].as_f64().unwrap() as f32;
    let frames = j["forward"]["frames"].as_u64().unwrap() as usize;
    let cond = m.encode_prompt(&prompt("A")).unwrap();
    let text_dropped = cond.get::<FinemogenCondition>().unwrap().text_dropped;
    assert!(text_dropped > 0);
    assert_eq!(text_dropped, dropped("forward", "text"));
    let x1 = expected("forward.x");
    let x = [x1.clone(), x1].concat();
    let mut out = vec![0.0; x.len()];
    let mut ws = FinemogenWorkspace::default();
    let null = m.uncond().unwrap();
    net.forward_with(
        &x,
        frames,
        t,
        &[&cond, null],
        &mut out,
        &mut ws,
        &Cancel::never(),
    )
    .unwrap();
    assert!(ws.motion_dropped > 0);
    assert_eq!(ws.motion_dropped, dropped("forward", "motion"));
    let n = frames * 263;
    let d_text = max_abs_diff(&out[..n], &expected("forward.text"));
    let d_null = max_abs_diff(&out[n..], &expected("forward.null"));
    println!("forward: text row {d_text:.2e}, null row {d_null:.2e}, motion drops {}, text drops {text_dropped}", ws.motion_dropped);
    assert!(d_text < TOL && d_null < TOL, "{d_text} {d_null}");
}

/// Runs a session of `frames` frames from `case.noise` through the 50 steps and compares the
/// sample (and x̂0 when the fixture has it) with `case.x` / `case.x0` at the stored steps;
/// returns the session.
fn trajectory(case: &str, frames: usize, set: impl FnOnce(&mut Session)) -> Session {
    let m = model();
    let params = SessionParams {
        frames: Some(frames),
        seed: 7,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(m, &params).unwrap();
    assert_eq!(s.num_steps(), 50, "the file's respacing 15,15,8,6,6");
    set(&mut s);
    s.set_initial_noise(&expected(&format!("{case}.noise")))
        .unwrap();
    let xs = expected(&format!("{case}.x"));
    let x0s = ModelFile::open(&fixture("finemogen_expected.safetensors"))
        .unwrap()
        .contains(&format!("{case}.x0"))
        .then(|| expected(&format!("{case}.x0")));
    // The fixture stores steps `steps_kept` (1-based) of the 50.
    let kept: Vec<usize> = json()["steps_kept"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    assert_eq!(kept.last(), Some(&50));
    let per = xs.len() / kept.len();
    let (mut worst, mut worst0) = (0f32, 0f32);
    for step in 1..=50 {
        s.step().unwrap();
        let Some(i) = kept.iter().position(|&k| k == step) else {
            continue;
        };
        let d = max_abs_diff(s.sample().unwrap(), &xs[i * per..(i + 1) * per]);
        worst = worst.max(d);
        assert!(d < TOL, "{case}: sample after step {step} differs by {d}");
        if let Some(x0s) = &x0s {
            let d = max_abs_diff(s.x0_estimate().unwrap(), &x0s[i * per..(i + 1) * per]);
            worst0 = worst0.max(d);
            assert!(d < TOL, "{case}: x0 of step {step} differs by {d}");
        }
    }
    println!("{case}: 50 steps, worst sample difference {worst:.2e}, worst x0 {worst0:.2e}");
    s
}

#[test]
fn one_prompt_trajectory_matches_reference() {
    let text = prompt("A");
    trajectory("single", 40, |s| s.set_prompt(&text).unwrap());
}

#[test]
fn two_stage_composition_matches_reference() {
    let j = json();
    let (la, lb) = (
        j["stages"]["La"].as_u64().unwrap() as usize,
        j["stages"]["Lb"].as_u64().unwrap() as usize,
    );
    let stages = [Stage::new(prompt("A"), la), Stage::new(prompt("B"), lb)];
    let mut s = trajectory("stages", la + lb, |s| {
        s.set_prompt_stages(&stages).unwrap();
        assert_eq!(
            s.sample_rows(),
            2 * la.max(lb),
            "[stages, longest stage] rows"
        );
    });
    let (motion, frames) = s.motion(Which::Sample).unwrap();
    assert_eq!(frames, la + lb);
    let d = max_abs_diff(motion, &expected("stages.motion"));
    assert!(d < TOL, "concatenated stages: {d}");
}

#[test]
fn part_texts_match_reference() {
    let stage = Stage::new(prompt("A"), 40)
        .with_part(BodyPart::LeftArm, prompt("B"))
        .with_part(BodyPart::Pelvis, prompt("C"));
    trajectory("parts", 40, |s| s.set_prompt_stages(&[stage]).unwrap());
}

#[test]
fn part_texts_equal_to_the_overall_text_give_the_plain_result_bit_for_bit() {
    let m = model();
    let text = prompt("B");
    let run = |set: &dyn Fn(&mut Session)| {
        let params = SessionParams {
            frames: Some(30),
            steps: Some(4),
            seed: 11,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(&m), &params).unwrap();
        set(&mut s);
        s.run().unwrap().to_vec()
    };
    let plain = run(&|s| s.set_prompt(&text).unwrap());
    let mut stage = Stage::new(&text, 30);
    for p in BodyPart::ALL {
        stage = stage.with_part(p, &text);
    }
    let parts = run(&|s| s.set_prompt_stages(std::slice::from_ref(&stage)).unwrap());
    assert!(plain
        .iter()
        .zip(&parts)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    // And a different part text changes the motion.
    let other = run(&|s| {
        s.set_prompt_stages(&[Stage::new(&text, 30).with_part(BodyPart::LeftArm, "a person waves")])
            .unwrap()
    });
    let d = max_abs_diff(&plain, &other);
    println!("a different left-arm text moves the result by {d}");
    assert!(d > 1e-5, "{d}");
}

fn flame_cli(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .env_remove("FLAME_MODEL")
        .output()
        .unwrap()
}

fn scratch(test: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flame_fmg_{}_{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `flame generate --stage A@La --stage B@Lb --noise [2, Lb, 263] --out x.npy` writes the
/// concatenated stages of the reference; `--prompt-file` (HuMMan-MoGen layout at 30 fps) gives
/// the same stages.
#[test]
fn the_cli_composes_stages_from_flags_and_from_a_prompt_file() {
    let j = json();
    let (la, lb) = (
        j["stages"]["La"].as_u64().unwrap() as usize,
        j["stages"]["Lb"].as_u64().unwrap() as usize,
    );
    let d = scratch("stages");
    let noise = d.join("noise.npy");
    flame::npy::write_f32(&noise, &[2, la.max(lb), 263], &expected("stages.noise")).unwrap();
    let model = fixture("finemogen_tiny.safetensors").display().to_string();
    let want = expected("stages.motion");
    let (a, b) = (
        format!("{}@{la}", prompt("A")),
        format!("{}@{lb}", prompt("B")),
    );
    let out = d.join("x.npy");
    let o = flame_cli(&[
        "generate",
        "--model",
        &model,
        "--stage",
        &a,
        "--stage",
        &b,
        "--noise",
        noise.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (shape, x) = flame::npy::read_f32(&out).unwrap();
    assert_eq!(shape, [la + lb, 263]);
    let diff = max_abs_diff(&x, &want);
    assert!(diff < TOL, "{diff}");

    // The same stages as a prompt file counted at 30 fps: 24 → 36, 31 → 46.5 → frames 36..83.
    let file = d.join("prompt.json");
    let json = format!(
        r#"{{"fps": 30, "stages": [
            {{"start_frame": 0, "end_frame": 36, "all": "{}", "head": ""}},
            {{"start_frame": 36, "end_frame": 83, "all": "{}"}}]}}"#,
        prompt("A"),
        prompt("B")
    );
    std::fs::write(&file, json).unwrap();
    let out2 = d.join("y.npy");
    let o = flame_cli(&[
        "generate",
        "--model",
        &model,
        "--prompt-file",
        file.to_str().unwrap(),
        "--noise",
        noise.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(flame::npy::read_f32(&out2).unwrap().1, x);

    // Errors: --frames disagreeing with the stages, a stage without frames, --prompt with --stage.
    let o = flame_cli(&[
        "generate",
        "--model",
        &model,
        "--stage",
        &a,
        "--stage",
        &b,
        "--frames",
        "50",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("the stages add up to 55 frames"));
    let o = flame_cli(&[
        "generate",
        "--model",
        &model,
        "--stage",
        "walk",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected TEXT@FRAMES"));
    let o = flame_cli(&[
        "generate",
        "--model",
        &model,
        "--stage",
        &a,
        "--prompt",
        "x",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let _ = std::fs::remove_dir_all(&d);
}
