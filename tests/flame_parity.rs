//! FLAME parity against the PyTorch reference.
//!
//! Reference: tools/reference/flame.py and tools/reference/diffusion.py (the official module and
//! sampler semantics); fixtures: tests/fixtures/flame_tiny.safetensors (converted by
//! tools/convert.py from an official-layout Lightning checkpoint) and
//! tests/fixtures/flame_tiny_expected.{safetensors,json}, written by tools/make_fixtures.py.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::checkpoint::ModelFile;
use flame::models::{Model, Workspace};
use flame::rng::ReplayNoise;
use flame::session::{Sampler, Session, SessionParams};
use safetensors::tensor::{Dtype, TensorView};

const TOL: f32 = 1e-4;

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
        let file = ModelFile::open(&fixture("flame_tiny_expected.safetensors")).unwrap();
        let text = std::fs::read_to_string(fixture("flame_tiny_expected.json")).unwrap();
        Expected {
            file,
            json: serde_json::from_str(&text).unwrap(),
        }
    }
    fn get(&self, name: &str) -> Vec<f32> {
        self.file.tensor_any_shape(name).unwrap().data().to_vec()
    }
    fn prompt(&self) -> String {
        self.json["prompt"].as_str().unwrap().to_string()
    }
    fn frames(&self) -> usize {
        self.json["frames"].as_u64().unwrap() as usize
    }
    fn guidance(&self) -> f32 {
        self.json["guidance"].as_f64().unwrap() as f32
    }
}

fn model() -> Arc<Model> {
    Arc::new(Model::load(fixture("flame_tiny.safetensors")).unwrap())
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f32) {
    let d = max_abs_diff(got, want);
    eprintln!("{what}: max abs diff {d:e}");
    assert!(d <= tol, "{what}: max abs diff {d:e} > {tol:e}");
}

#[test]
fn text_encoder_matches_transformers() {
    let (m, e) = (model(), Expected::load());
    let cond = m.text_encoder().unwrap().encode(&e.prompt()).unwrap();
    assert_close("cond hidden", &cond.hidden, &e.get("text_cond_hidden"), TOL);
    assert_close("cond pooled", &cond.pooled, &e.get("text_cond_pooled"), TOL);
    let unc = m.text_encoder().unwrap().encode("").unwrap();
    assert_close(
        "uncond hidden",
        &unc.hidden,
        &e.get("text_uncond_hidden"),
        TOL,
    );
    assert_close(
        "uncond pooled",
        &unc.pooled,
        &e.get("text_uncond_pooled"),
        TOL,
    );
}

#[test]
fn one_forward_with_guidance_matches_reference() {
    let (m, e) = (model(), Expected::load());
    let frames = e.frames();
    let x = e.get("forward_x");
    let t = e.get("forward_t")[0];
    let cond = m.encode_prompt(&e.prompt()).unwrap();
    let uncond = m.uncond().unwrap();
    let mut xb = x.clone();
    xb.extend_from_slice(&x);
    let od = m.output_dim();
    let mut out = vec![0.0; 2 * frames * od];
    m.forward(
        &xb,
        frames,
        t,
        &[&cond, uncond],
        &mut out,
        &mut Workspace::default(),
    )
    .unwrap();
    let (oc, ou) = out.split_at(frames * od);
    assert_close("forward cond", oc, &e.get("forward_out_cond"), TOL);
    assert_close("forward uncond", ou, &e.get("forward_out_uncond"), TOL);

    let d = m.motion_dim();
    let s = e.guidance();
    let guided: Vec<f32> = (0..frames * d)
        .map(|i| {
            let (f, c) = (i / d, i % d);
            let (yc, yu) = (oc[f * od + c], ou[f * od + c]);
            yu + s * (yc - yu)
        })
        .collect();
    assert_close("guided eps", &guided, &e.get("forward_eps_guided"), TOL);
}

fn session(m: &Arc<Model>, e: &Expected, sampler: Sampler, threads: usize) -> Session {
    let params = SessionParams {
        respacing: None,
        frames: Some(e.frames()),
        steps: Some(10),
        sampler: Some(sampler),
        eta: Some(0.0),
        guidance: Some(e.guidance()),
        clip_denoised: None,
        seed: 7,
        threads,
        looped: false,
    };
    Session::new(Arc::clone(m), &params).unwrap()
}

fn check_trajectory(sampler: Sampler, prefix: &str) {
    let (m, e) = (model(), Expected::load());
    let mut s = session(&m, &e, sampler, 2);
    s.set_initial_noise(&e.get(&format!("{prefix}_x_T")))
        .unwrap();
    if sampler == Sampler::Ddpm {
        s.set_noise_source(Box::new(ReplayNoise::new(e.get("ddpm_noise"))));
    }
    s.set_prompt(&e.prompt()).unwrap();
    let xs = e.get(&format!("{prefix}_xs"));
    let x0s = e.get(&format!("{prefix}_x0s"));
    let n = s.frames() * m.motion_dim();
    for k in 0..10 {
        let left = s.step().unwrap();
        assert_eq!(left, 9 - k);
        assert_close(
            &format!("{prefix} x0 at step {k}"),
            s.x0_estimate().unwrap(),
            &x0s[k * n..(k + 1) * n],
            TOL,
        );
        assert_close(
            &format!("{prefix} x at step {k}"),
            s.sample().unwrap(),
            &xs[k * n..(k + 1) * n],
            TOL,
        );
    }
}

#[test]
fn ddim_trajectory_matches_reference() {
    check_trajectory(Sampler::Ddim, "ddim");
}

#[test]
fn ddpm_trajectory_with_given_noise_matches_reference() {
    check_trajectory(Sampler::Ddpm, "ddpm");
}

#[test]
fn respacing_sends_original_timesteps() {
    let e = Expected::load();
    let map = e.get("timestep_map");
    let want: Vec<f32> = (0..10).map(|i| (i * 111) as f32).collect();
    assert_eq!(map, want, "the reference's respacing of 1000 steps into 10");
}

#[test]
fn seeded_generation_is_bit_identical_across_runs_and_thread_counts() {
    let (m, e) = (model(), Expected::load());
    let run = |threads| {
        let mut s = session(&m, &e, Sampler::Ddpm, threads);
        s.set_prompt("a person jumps twice").unwrap();
        s.run().unwrap().to_vec()
    };
    let a = run(1);
    assert_eq!(a, run(1));
    assert_eq!(a, run(2));
    assert_eq!(a, run(3));
    let mut other = session(&m, &e, Sampler::Ddpm, 1);
    other.set_prompt("a person jumps twice").unwrap();
    let first = other.run().unwrap().to_vec();
    other.reset();
    assert_eq!(
        first,
        other.run().unwrap(),
        "reset restarts the seeded stream"
    );
}

#[test]
fn f16_file_matches_reference_with_f16_rounded_weights() {
    // Reference: the same PyTorch forward with every weight rounded to f16 (f16w_* tensors).
    let e = Expected::load();
    let m16 = Model::load(fixture("flame_tiny_f16.safetensors")).unwrap();
    assert_eq!(m16.stored_dtype().map(|d| d.name()), Some("f16"));
    let frames = e.frames();
    let x = e.get("forward_x");
    let cond = m16.encode_prompt(&e.prompt()).unwrap();
    let mut xb = x.clone();
    xb.extend_from_slice(&x);
    let od = m16.output_dim();
    let mut out = vec![0.0; 2 * frames * od];
    let t = e.get("forward_t")[0];
    m16.forward(
        &xb,
        frames,
        t,
        &[&cond, m16.uncond().unwrap()],
        &mut out,
        &mut Workspace::default(),
    )
    .unwrap();
    let (oc, ou) = out.split_at(frames * od);
    assert_close("f16 forward cond", oc, &e.get("f16w_forward_out_cond"), TOL);
    assert_close(
        "f16 forward uncond",
        ou,
        &e.get("f16w_forward_out_uncond"),
        TOL,
    );
    // And it is a different model from the f32 one, by about f16's rounding.
    let d = max_abs_diff(oc, &e.get("forward_out_cond"));
    assert!(d > 1e-6 && d < 1e-2, "f16 vs f32 forward differ by {d:e}");
}

#[test]
fn wrong_order_and_bad_arguments_are_errors() {
    let (m, e) = (model(), Expected::load());
    let mut s = session(&m, &e, Sampler::Ddim, 1);
    assert!(s.sample().is_none() && s.x0_estimate().is_none());
    assert_eq!(
        s.step().unwrap_err().to_string(),
        "wrong state: set a prompt before stepping"
    );
    assert!(s
        .set_initial_noise(&[0.0; 3])
        .unwrap_err()
        .to_string()
        .contains("expected"));
    let mut nan = vec![0.0; s.frames() * m.motion_dim()];
    nan[5] = f32::NAN;
    assert!(s
        .set_initial_noise(&nan)
        .unwrap_err()
        .to_string()
        .contains("NaN"));
    let bad = |p: SessionParams| Session::new(Arc::clone(&m), &p).err().unwrap().to_string();
    assert!(bad(SessionParams {
        frames: Some(0),
        ..Default::default()
    })
    .contains("frames must be between 1 and 470 for this model, got 0"));
    assert!(bad(SessionParams {
        frames: Some(471),
        ..Default::default()
    })
    .contains("frames must be between 1 and 470 for this model, got 471"));
    assert!(bad(SessionParams {
        steps: Some(1001),
        ..Default::default()
    })
    .contains("steps must be between 1 and 1000 for this model, got 1001"));
    assert!(bad(SessionParams {
        guidance: Some(f32::NAN),
        ..Default::default()
    })
    .contains("guidance"));
    s.set_prompt("walk").unwrap();
    s.run().unwrap();
    assert!(s.step().unwrap_err().to_string().contains("finished"));
    let flag = s.cancel_flag();
    s.reset();
    flag.store(true, std::sync::atomic::Ordering::SeqCst);
    assert!(matches!(s.step(), Err(flame::Error::Cancelled)));
    assert_eq!(s.step().unwrap(), 9, "cancel only abandons one step");
}

/// Rewrites the tiny model file with changed metadata and/or tensors.
fn rewrite(
    meta: impl FnOnce(&mut HashMap<String, String>),
    tensors: impl FnOnce(&mut Vec<(String, Dtype, Vec<usize>, Vec<u8>)>),
) -> Vec<u8> {
    let bytes = std::fs::read(fixture("flame_tiny.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let mut md = header.metadata().clone().unwrap();
    meta(&mut md);
    let mut list: Vec<_> = st
        .tensors()
        .into_iter()
        .map(|(n, v)| (n, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
        .collect();
    list.sort_by(|a, b| a.0.cmp(&b.0));
    tensors(&mut list);
    let views: Vec<(String, TensorView)> = list
        .iter()
        .map(|(n, d, s, b)| (n.clone(), TensorView::new(*d, s.clone(), b).unwrap()))
        .collect();
    safetensors::serialize(views, &Some(md)).unwrap()
}

fn load_err(bytes: &[u8]) -> String {
    match Model::from_bytes(bytes) {
        Ok(_) => panic!("loading must fail"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn bad_model_files_get_clear_errors() {
    let good = std::fs::read(fixture("flame_tiny.safetensors")).unwrap();
    assert!(Model::from_bytes(&good).is_ok());

    let e = load_err(&good[..good.len() / 2]);
    assert!(e.contains("truncated"), "truncated file: {e}");
    let e = load_err(&good[..4]);
    assert!(e.contains("too short"), "tiny file: {e}");
    let mut corrupt = good.clone();
    corrupt[8] = b'x';
    assert!(load_err(&corrupt).contains("does not start with '{'"));
    let e = load_err(b"GIF89a this is not a model file at all");
    assert!(e.starts_with("bad model file:"), "{e}");

    let e = load_err(&rewrite(
        |m| drop(m.insert("flame.config".into(), "{\"format_version\": 1,".into())),
        |_| {},
    ));
    assert!(e.contains("`flame.config` is not valid JSON"), "{e}");
    let e = load_err(&rewrite(|m| drop(m.remove("flame.config")), |_| {}));
    assert!(e.contains("not a libflame model file"), "{e}");
    let e = load_err(&rewrite(
        |m| {
            let c = m["flame.config"]
                .replace("\"architecture\": \"flame\"", "\"architecture\": \"unet\"");
            m.insert("flame.config".into(), c);
        },
        |_| {},
    ));
    assert_eq!(
        e,
        "bad model file: unknown architecture `unet` (supported: flame, mdm, motionfm, mola, mld, motionlcm, finemogen, omg)"
    );
    let e = load_err(&rewrite(|m| drop(m.remove("flame.tokenizer")), |_| {}));
    assert!(e.contains("flame.tokenizer"), "{e}");

    // An unsupported dtype on a weight the model needs.
    let e = load_err(&rewrite(
        |_| {},
        |l| {
            let t = l
                .iter_mut()
                .find(|t| t.0 == "input_projection.bias")
                .unwrap();
            t.1 = Dtype::I32;
        },
    ));
    assert!(
        e.contains("tensor `input_projection.bias` has unsupported dtype I32"),
        "{e}"
    );
    // A wrong shape: the message names the tensor and both shapes.
    let e = load_err(&rewrite(
        |_| {},
        |l| {
            let t = l
                .iter_mut()
                .find(|t| t.0 == "tf_decoder.layers.1.linear1.bias")
                .unwrap();
            t.2 = vec![t.2[0] / 2, 2];
        },
    ));
    assert!(
        e.contains("tensor `tf_decoder.layers.1.linear1.bias` has shape ["),
        "{e}"
    );
    // A missing tensor.
    let e = load_err(&rewrite(
        |_| {},
        |l| l.retain(|t| t.0 != "last_projection.weight"),
    ));
    assert_eq!(
        e,
        "bad model file: tensor `last_projection.weight` is missing"
    );
}
