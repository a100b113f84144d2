//! OMG-style models against tools/reference/omg.py (the layout's definition; the paper as
//! docs/official/omg.md lists it and docs/omg.md for the choices), on a tiny random model with nonzero up-projections converted
//! by `tools/convert.py omg` (tests/fixtures/omg_tiny.safetensors; expected outputs from
//! tools/make_omg_fixtures.py in tests/fixtures/omg_expected.*).

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use common::max_abs_diff;
use flame::checkpoint::ModelFile;
use flame::models::omg::{OmgCondition, OmgWorkspace};
use flame::models::{Cancel, Model, OmgDenoiser};
use flame::session::{Session, SessionParams};
use flame::Error;

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn expected(name: &str) -> Vec<f32> {
    let f = ModelFile::open(&fixture("omg_expected.safetensors")).unwrap();
    f.tensor_any_shape(name).unwrap().data().to_vec()
}

fn json() -> serde_json::Value {
    let text = std::fs::read_to_string(fixture("omg_expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn prompt() -> String {
    let j = json();
    let p = &j["prompts"]["A"];
    p.as_str().unwrap().to_string()
}

fn model() -> Arc<Model> {
    Arc::new(Model::load(fixture("omg_tiny.safetensors")).unwrap())
}

fn omg(model: &Model) -> &OmgDenoiser {
    model
        .denoiser()
        .as_any()
        .downcast_ref::<OmgDenoiser>()
        .expect("an OMG-style model")
}

fn frames() -> usize {
    json()["frames"].as_u64().unwrap() as usize
}

/// The fixture model with its configuration changed by `edit` (same weights).
fn variant(edit: impl FnOnce(&mut serde_json::Value)) -> Arc<Model> {
    let bytes = std::fs::read(fixture("omg_tiny.safetensors")).unwrap();
    Arc::new(Model::from_bytes(&common::with_config(&bytes, edit)).unwrap())
}

/// D_c and D_u of the fixture's forward, as libflame computes them.
fn forward(m: &Model) -> (Vec<f32>, Vec<f32>) {
    let t = json()["forward"]["t"].as_f64().unwrap() as f32;
    let n = frames();
    let cond = m.encode_prompt(&prompt()).unwrap();
    let x1 = expected("forward.x");
    let x = [x1.clone(), x1].concat();
    let mut out = vec![0.0; x.len()];
    let mut ws = OmgWorkspace::default();
    omg(m)
        .forward_with(
            &x,
            n,
            t,
            &[&cond, m.uncond().unwrap()],
            &mut out,
            &mut ws,
            &Cancel::never(),
        )
        .unwrap();
    let half = n * m.motion_dim();
    (out[..half].to_vec(), out[half..].to_vec())
}

#[test]
fn text_tokens_match_reference() {
    let m = model();
    let (tokens, eos) = omg(&m).text_tokens(m.text_model(), &prompt()).unwrap();
    let want = expected("text.tokens");
    assert_eq!(tokens.len(), want.len(), "SOT..EOT tokens");
    let width = omg(&m).config().control.as_ref().unwrap().text_dim;
    assert_eq!((eos + 1) * width, tokens.len());
    let d = max_abs_diff(&tokens, &want);
    assert!(d < 1e-5, "{d}");
    let cond = m.encode_prompt(&prompt()).unwrap();
    assert_eq!(cond.get::<OmgCondition>().unwrap().token_count(), eos + 1);
}

#[test]
fn one_forward_matches_the_parameter_blend_not_the_output_blend() {
    let m = model();
    let (cond, uncond) = forward(&m);
    let d_c = max_abs_diff(&cond, &expected("forward.cond"));
    let d_u = max_abs_diff(&uncond, &expected("forward.uncond"));
    let blend_outputs = expected("forward.blend_outputs");
    let apart = max_abs_diff(&blend_outputs, &expected("forward.cond"));
    let d_o = max_abs_diff(&cond, &blend_outputs);
    println!("forward: D_c {d_c:.2e}, D_u {d_u:.2e}; blending outputs instead moves D_c by {apart:.2e} (libflame {d_o:.2e} from it)");
    assert!(d_c < TOL && d_u < TOL, "{d_c} {d_u}");
    assert!(
        apart > 100.0 * TOL,
        "the fixture must tell the two blends apart: {apart}"
    );
    assert!(d_o > 50.0 * TOL);
    // The ControlNet moves the prediction.
    assert!(max_abs_diff(&cond, &uncond) > 1e-2);
}

#[test]
fn the_configuration_choices_are_read_from_the_file() {
    // Two cross-attention heads, RoPE on 8 of 16 head dims, all 77 text positions: the same
    // weights under each choice against the reference run with it.
    type Edit = Box<dyn FnOnce(&mut serde_json::Value)>;
    let cases: [(&str, Edit, bool); 4] = [
        (
            "forward.cond_heads2",
            Box::new(|c| c["denoiser"]["control"]["attn_heads"] = 2.into()),
            true,
        ),
        (
            "forward.cond_rope8",
            Box::new(|c| c["denoiser"]["rope_dims"] = 8.into()),
            true,
        ),
        (
            "forward.uncond_rope8",
            Box::new(|c| c["denoiser"]["rope_dims"] = 8.into()),
            false,
        ),
        (
            "forward.cond_padding",
            Box::new(|c| c["denoiser"]["control"]["text_padding"] = true.into()),
            true,
        ),
    ];
    for (key, edit, cond) in cases {
        let m = variant(edit);
        let (c, u) = forward(&m);
        let got = if cond { c } else { u };
        let d = max_abs_diff(&got, &expected(key));
        let apart = max_abs_diff(
            &got,
            &expected(if cond {
                "forward.cond"
            } else {
                "forward.uncond"
            }),
        );
        println!("{key}: {d:.2e} (the default choice is {apart:.2e} away)");
        assert!(d < TOL, "{key}: {d}");
        assert!(
            apart > 100.0 * TOL,
            "{key} must differ from the default: {apart}"
        );
    }
}

#[test]
fn three_hundred_frames_at_30_fps_through_the_backbone() {
    // The backbone-only file says 30 fps; the rows the fixture kept of D_u at 300 frames.
    let b = Arc::new(Model::load(fixture("omg_tiny_backbone.safetensors")).unwrap());
    assert_eq!(b.config().motion.fps, 30.0);
    let j = json();
    let (frames, t) = (
        j["long"]["frames"].as_u64().unwrap() as usize,
        j["long"]["t"].as_f64().unwrap() as f32,
    );
    let f = b.motion_dim();
    let x: Vec<f32> = (0..frames * f)
        .map(|i| ((0.05 * (i / f) as f64 + 0.3 * (i % f) as f64).sin()) as f32)
        .collect();
    assert_eq!(&x[..2 * f], &expected("long.x_head")[..]);
    let mut out = vec![0.0; x.len()];
    let mut ws = OmgWorkspace::default();
    omg(&b)
        .forward_with(
            &x,
            frames,
            t,
            &[b.uncond().unwrap()],
            &mut out,
            &mut ws,
            &Cancel::never(),
        )
        .unwrap();
    let want = expected("long.uncond_rows");
    for (k, row) in j["long"]["rows"].as_array().unwrap().iter().enumerate() {
        let r = row.as_u64().unwrap() as usize;
        let d = max_abs_diff(&out[r * f..(r + 1) * f], &want[k * f..(k + 1) * f]);
        assert!(d < TOL, "row {r}: {d}");
    }
}

#[test]
fn zero_up_projections_give_the_backbone_bit_for_bit() {
    // The same file with every `control.up.*` tensor zeroed.
    let bytes = std::fs::read(fixture("omg_tiny.safetensors")).unwrap();
    let zeroed = common::zero_tensors(&bytes, |name| name.contains(".control.up."));
    let m = Arc::new(Model::from_bytes(&zeroed).unwrap());
    let (cond, uncond) = forward(&m);
    assert!(cond
        .iter()
        .zip(&uncond)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    let d = max_abs_diff(&cond, &expected("forward.zero_up"));
    assert!(d < TOL, "{d}");
}

fn trajectory(case: &str, text: &str) {
    let m = model();
    let j = json();
    let steps = j["steps"].as_array().unwrap().len();
    let params = SessionParams {
        frames: Some(frames()),
        steps: Some(steps),
        guidance: Some(j["guidance"].as_f64().unwrap() as f32),
        seed: 5,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(m, &params).unwrap();
    s.set_prompt(text).unwrap();
    s.set_initial_noise(&expected("guided.noise")).unwrap();
    let kept: Vec<usize> = j["steps_kept"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let xs = expected(&format!("{case}.x"));
    let per = xs.len() / kept.len();
    let mut worst = 0f32;
    for step in 1..=steps {
        s.step().unwrap();
        if let Some(i) = kept.iter().position(|&k| k == step) {
            let d = max_abs_diff(s.sample().unwrap(), &xs[i * per..(i + 1) * per]);
            worst = worst.max(d);
            assert!(d < TOL, "{case}: step {step}: {d}");
        }
    }
    println!("{case}: {steps} steps, worst difference {worst:.2e}");
}

#[test]
fn guided_trajectory_matches_reference() {
    trajectory("guided", &prompt());
}

#[test]
fn unconditional_trajectory_runs_the_backbone_alone() {
    trajectory("uncond", "");
}

#[test]
fn backbone_only_files_refuse_prompts_and_long_motions_are_refused() {
    let b = Arc::new(Model::load(fixture("omg_tiny_backbone.safetensors")).unwrap());
    match b.encode_prompt("a person walks") {
        Err(Error::InvalidArgument(m)) => assert!(m.contains("no ControlNet"), "{m}"),
        other => panic!("{other:?}"),
    }
    let mut s = Session::new(
        Arc::clone(&b),
        &SessionParams {
            frames: Some(30),
            steps: Some(3),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(s.set_prompt("a person walks").is_err());
    s.set_prompt("").unwrap();
    s.run().unwrap();
    let max = b.max_frames();
    let too_long = SessionParams {
        frames: Some(max + 1),
        ..Default::default()
    };
    match Session::new(b, &too_long) {
        Err(Error::InvalidArgument(m)) => {
            assert!(m.contains(&format!("between 1 and {max}")), "{m}")
        }
        other => panic!("{:?}", other.map(|_| ())),
    }
}

#[test]
fn configurations_that_disagree_with_the_tensors_are_refused() {
    let bad = |file: &str, edit: Box<dyn FnOnce(&mut serde_json::Value)>, want: &str| {
        let bytes = std::fs::read(fixture(file)).unwrap();
        match Model::from_bytes(&common::with_config(&bytes, edit)) {
            Err(Error::BadModelFile(m)) => assert!(m.contains(want), "{m:?} lacks {want:?}"),
            other => panic!("{want}: {:?}", other.map(|_| ())),
        }
    };
    bad(
        "omg_tiny.safetensors",
        Box::new(|c| c["denoiser"]["d_model"] = 64.into()),
        "tensor `denoiser.x_embed.weight` has shape [32, 263], expected [64, 263]",
    );
    bad(
        "omg_tiny.safetensors",
        Box::new(|c| c["denoiser"]["control"] = serde_json::Value::Null),
        "config denoiser.control is null but the file has `denoiser.control.*` tensors",
    );
    // (with the backbone file's narrower stand-in CLIP width, so the check reaches the tensors)
    let mut control = json()["config"]["denoiser"]["control"].clone();
    control["text_dim"] = 8.into();
    bad(
        "omg_tiny_backbone.safetensors",
        Box::new(move |c| c["denoiser"]["control"] = control),
        "no tensor `denoiser.control.blocks.1.*`",
    );
    bad(
        "omg_tiny.safetensors",
        Box::new(|c| c["denoiser"]["control"]["conv_kernel"] = 2.into()),
        "conv_kernel 2 is not odd",
    );
    bad(
        "omg_tiny.safetensors",
        Box::new(|c| c["denoiser"]["mlp_activation"] = "relu".into()),
        "unknown config denoiser.mlp_activation `relu`",
    );
    bad(
        "omg_tiny.safetensors",
        Box::new(|c| c["diffusion"]["uncond"] = "zeros".into()),
        "the unconditional branch of an OMG-style model is its backbone",
    );
}
