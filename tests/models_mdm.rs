//! MDM / Motion Flow Matching denoiser parity against the PyTorch reference.
//!
//! Reference: tools/reference/mdm.py; fixtures: tests/fixtures/{mdm,motionfm}_tiny.safetensors
//! (converted by tools/convert.py mdm / motionfm from official-layout checkpoints) and
//! tests/fixtures/mdm_expected.{safetensors,json}, written by tools/make_mdm_fixtures.py.
//! The text vector is fed directly (the files' text towers are placeholders).

use std::path::{Path, PathBuf};

use flame::checkpoint::{ModelFile, CONFIG_KEY};
use flame::models::mdm::{MdmConfig, MdmDenoiser, TimeIndex, Workspace};

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn load(name: &str, time_index: TimeIndex) -> MdmDenoiser {
    let file = ModelFile::open(&fixture(name)).unwrap();
    let config: serde_json::Value =
        serde_json::from_str(file.metadata(CONFIG_KEY).unwrap()).unwrap();
    let cfg: MdmConfig = serde_json::from_value(config["denoiser"].clone()).unwrap();
    MdmDenoiser::load(&file, &cfg)
        .unwrap()
        .with_time_index(time_index)
}

struct Expected(ModelFile);

impl Expected {
    fn load() -> Expected {
        Expected(ModelFile::open(&fixture("mdm_expected.safetensors")).unwrap())
    }
    fn get(&self, name: &str) -> Vec<f32> {
        self.0.tensor_any_shape(name).unwrap().data().to_vec()
    }
    fn frames(&self) -> usize {
        self.0.shape("forward_x").unwrap()[0]
    }
}

fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let d = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    eprintln!("{what}: max abs diff {d:e}");
    assert!(d <= tol, "{what}: max abs diff {d:e} > {tol:e}");
}

/// `[cond; uncond]` forward on the same x; returns (cond, uncond) outputs.
fn pair(
    net: &MdmDenoiser,
    x: &[f32],
    frames: usize,
    t: f32,
    text: &[f32],
    ws: &mut Workspace,
) -> (Vec<f32>, Vec<f32>) {
    let zeros = vec![0.0; text.len()];
    let mut xb = x.to_vec();
    xb.extend_from_slice(x);
    let mut out = vec![0.0; xb.len()];
    net.forward(&xb, frames, t, &[text, &zeros], &mut out, ws)
        .unwrap();
    let uncond = out.split_off(x.len());
    (out, uncond)
}

fn guide(cond: &[f32], uncond: &[f32], s: f32) -> Vec<f32> {
    cond.iter()
        .zip(uncond)
        .map(|(c, u)| u + s * (c - u))
        .collect()
}

#[test]
fn mdm_forward_matches_reference() {
    let e = Expected::load();
    let net = load("mdm_tiny.safetensors", TimeIndex::Diffusion);
    assert_eq!(net.motion_dim(), 263);
    let (c, u) = pair(
        &net,
        &e.get("forward_x"),
        e.frames(),
        e.get("forward_t_diffusion")[0],
        &e.get("text"),
        &mut Workspace::default(),
    );
    assert_close("mdm cond", &c, &e.get("mdm_out_cond"), TOL);
    assert_close("mdm uncond", &u, &e.get("mdm_out_uncond"), TOL);
}

#[test]
fn motionfm_forward_matches_reference() {
    let e = Expected::load();
    let net = load("motionfm_tiny.safetensors", TimeIndex::FlowMatching);
    let t = e.get("forward_t_flow")[0];
    assert_eq!(TimeIndex::FlowMatching.row(t), Some(49));
    let (c, u) = pair(
        &net,
        &e.get("forward_x"),
        e.frames(),
        t,
        &e.get("text"),
        &mut Workspace::default(),
    );
    assert_close("motionfm cond", &c, &e.get("motionfm_out_cond"), TOL);
    assert_close("motionfm uncond", &u, &e.get("motionfm_out_uncond"), TOL);
}

/// Every DDIM step's guided x0 from the reference's own x_t (per-step, so errors do not compound).
#[test]
fn mdm_ddim_steps_match_reference() {
    let e = Expected::load();
    let net = load("mdm_tiny.safetensors", TimeIndex::Diffusion);
    let (frames, n) = (e.frames(), e.frames() * 263);
    let (text, xs, x0s) = (e.get("text"), e.get("ddim_xs"), e.get("ddim_x0s"));
    let mut x = e.get("ddim_x_T");
    let mut ws = Workspace::default();
    for (k, t) in e.get("ddim_model_t").into_iter().enumerate() {
        let (c, u) = pair(&net, &x, frames, t, &text, &mut ws);
        let x0 = guide(&c, &u, 2.5);
        assert_close(
            &format!("ddim x0 step {k}"),
            &x0,
            &x0s[k * n..(k + 1) * n],
            TOL,
        );
        x = xs[k * n..(k + 1) * n].to_vec();
    }
}

/// The whole 10-step Euler trajectory run in Rust (errors may compound, still within 1e-4).
#[test]
fn motionfm_euler_trajectory_matches_reference() {
    let e = Expected::load();
    let net = load("motionfm_tiny.safetensors", TimeIndex::FlowMatching);
    let (frames, n) = (e.frames(), e.frames() * 263);
    let (text, xs, vs) = (e.get("text"), e.get("euler_xs"), e.get("euler_vs"));
    let steps = 10usize;
    let dt = 1.0f32 / steps as f32;
    let mut x = e.get("euler_x_0");
    let mut ws = Workspace::default();
    for k in 0..steps {
        let t = k as f32 / steps as f32;
        assert_eq!(t, e.get("euler_t")[k]);
        let (c, u) = pair(&net, &x, frames, t, &text, &mut ws);
        let v = guide(&c, &u, 2.5);
        assert_close(
            &format!("euler v step {k}"),
            &v,
            &vs[k * n..(k + 1) * n],
            TOL,
        );
        for (xi, vi) in x.iter_mut().zip(&v) {
            *xi += dt * vi;
        }
        assert_close(
            &format!("euler x step {k}"),
            &x,
            &xs[k * n..(k + 1) * n],
            TOL,
        );
    }
}

#[test]
fn rejects_bad_inputs() {
    let net = load("mdm_tiny.safetensors", TimeIndex::Diffusion);
    let mut ws = Workspace::default();
    let x = vec![0.0; 4 * 263];
    let mut out = vec![0.0; 4 * 263];
    let short = vec![0.0; 10];
    assert!(net
        .forward(&x, 4, 10.0, &[&short], &mut out, &mut ws)
        .is_err());
    let text = vec![0.0; 512];
    assert!(net
        .forward(&x, 4, 2.5, &[&text], &mut out, &mut ws)
        .is_err());
    assert!(net
        .forward(&x, 4, 1e9, &[&text], &mut out, &mut ws)
        .is_err());
    assert!(net
        .forward(&x, 4, 10.0, &[&text], &mut out, &mut ws)
        .is_ok());
}
