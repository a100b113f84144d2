//! guided-diffusion respacing strings (`"ddimN"`, `"N"`, section counts) through every way in:
//! `SessionParams.respacing`, the C ABI's `FlameSessionParams.respacing` (called here as a C
//! program would) and the CLI's `--respacing`; and the refusals for a flow model, a model with
//! diffusers spacing, and a step count that disagrees.
//!
//! The check that a string picks the right steps needs no stored numbers: over T = 1000 the stride
//! rule "ddim4" keeps {0, 250, 500, 750}, exactly what four one-step sections "1,1,1,1" keep (the
//! first step of each 250-step section), while "4" (the section rule, = `steps` 4) keeps
//! {0, 333, 666, 999}. So "ddim4" and "1,1,1,1" must give the same bits, "4" those of `steps` 4,
//! and the two pairs must differ. Models: tests/fixtures/{flame,mdm,motionfm}_tiny.safetensors
//! (random weights; DDIM η = 0, so runs are deterministic).

use std::ffi::CString;
use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::Arc;

mod common;

use common::repo;
use flame::checkpoint::{ModelFile, CONFIG_KEY};
use flame::ffi::*;
use flame::models::Model;
use flame::session::{Sampler, Session, SessionParams};
use flame::Error;

fn tiny(name: &str) -> PathBuf {
    repo(&format!("tests/fixtures/{name}_tiny.safetensors"))
}

fn model(name: &str) -> Arc<Model> {
    Arc::new(Model::load(tiny(name)).unwrap())
}

fn params(steps: Option<usize>, respacing: Option<&str>) -> SessionParams {
    SessionParams {
        frames: Some(8),
        steps,
        respacing: respacing.map(str::to_owned),
        sampler: Some(Sampler::Ddim),
        guidance: Some(2.5),
        seed: 5,
        threads: 1,
        ..Default::default()
    }
}

/// The final sample's bits of a whole generation.
fn run(m: &Arc<Model>, p: &SessionParams) -> Vec<u32> {
    let mut s = Session::new(Arc::clone(m), p).unwrap();
    s.set_prompt("a person jumps").unwrap();
    while s.steps_left() > 0 {
        s.step().unwrap();
    }
    s.sample().unwrap().iter().map(|v| v.to_bits()).collect()
}

fn refused(m: &Arc<Model>, p: &SessionParams) -> String {
    match Session::new(Arc::clone(m), p) {
        Err(e @ Error::InvalidArgument(_)) => e.to_string(),
        Err(e) => panic!("{p:?}: {e}"),
        Ok(_) => panic!("{p:?} was accepted"),
    }
}

/// `name`'s tiny model file with its `diffusion` section changed by `edit` (the safetensors
/// header rewritten; tensor offsets are relative to its end, so the data stays valid).
fn with_diffusion(name: &str, edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
    let bytes = std::fs::read(tiny(name)).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let meta = &mut header["__metadata__"];
    let mut cfg: serde_json::Value =
        serde_json::from_str(meta[CONFIG_KEY].as_str().unwrap()).unwrap();
    edit(&mut cfg["diffusion"]);
    meta[CONFIG_KEY] = cfg.to_string().into();
    let mut text = header.to_string().into_bytes();
    while !text.len().is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    ModelFile::from_bytes(&out).unwrap();
    out
}

#[test]
fn session_params_respacing_picks_the_steps() {
    let m = model("flame");
    let stride = run(&m, &params(None, Some("ddim4")));
    assert_eq!(stride, run(&m, &params(None, Some("1,1,1,1"))));
    assert_eq!(stride, run(&m, &params(Some(4), Some(" ddim4 "))));
    let sections = run(&m, &params(None, Some("4")));
    assert_eq!(sections, run(&m, &params(Some(4), None)));
    assert_ne!(
        stride, sections,
        "{{0,250,500,750}} and {{0,333,666,999}} differ"
    );
    let s = Session::new(Arc::clone(&m), &params(None, Some("15,15,8,6,6"))).unwrap();
    assert_eq!(s.num_steps(), 50);

    let e = refused(&m, &params(Some(5), Some("ddim4")));
    assert!(
        e.contains("steps 5 disagrees with respacing \"ddim4\", which keeps 4 steps"),
        "{e}"
    );
    let e = refused(&m, &params(None, Some("ddim999")));
    assert!(e.contains("cannot create exactly 999 steps"), "{e}");
    let e = refused(&m, &params(None, Some("")));
    assert!(e.contains("respacing is empty"), "{e}");
    let e = refused(&m, &params(None, Some("10,x")));
    assert!(
        e.contains("expected \"ddimN\" or comma-separated counts"),
        "{e}"
    );

    // MDM (x0-prediction) respaces the same way.
    let mdm = model("mdm");
    let s = Session::new(Arc::clone(&mdm), &params(None, Some("ddim10"))).unwrap();
    assert_eq!(s.num_steps(), 10);
}

#[test]
fn flow_and_diffusers_spaced_models_refuse_a_respacing() {
    let flow = model("motionfm");
    let mut p = params(None, Some("ddim10"));
    p.sampler = Some(Sampler::Euler);
    let e = refused(&flow, &p);
    assert!(e.contains("flow-matching model integrates an ODE"), "{e}");

    // MDM's file with MoLA's scheduler settings: steps only.
    let bytes = with_diffusion("mdm", |d| {
        d["schedule"] = "scaled_linear".into();
        d["spacing"] = "trailing".into();
        d["steps_offset"] = 1.into();
        d["set_alpha_to_one"] = false.into();
    });
    let trailing = Arc::new(Model::from_bytes(&bytes).unwrap());
    let e = refused(&trailing, &params(None, Some("ddim50")));
    assert!(
        e.contains("guided-diffusion's") && e.contains("diffusers' `trailing` timesteps"),
        "{e}"
    );
    let s = Session::new(Arc::clone(&trailing), &params(Some(10), None)).unwrap();
    assert_eq!(s.num_steps(), 10);
    assert_eq!(run(&trailing, &params(Some(10), None)).len(), 8 * 263);
    let e = refused(&trailing, &params(Some(61), None));
    assert!(e.contains("trailing spacing cannot take 61 steps"), "{e}");

    // `flame info` names the spacing; `--respacing` is refused with the library's reason.
    let dir = std::env::temp_dir().join(format!("flame_trailing_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("mdm_trailing.safetensors");
    std::fs::write(&file, &bytes).unwrap();
    let info = cli(&["info", file.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(
        text.contains(
            "spacing:        trailing (diffusers DDIM), steps_offset 1, set_alpha_to_one false"
        ),
        "{text}"
    );
    let o = cli(&[
        "generate",
        "--model",
        file.to_str().unwrap(),
        "--prompt",
        "a person jumps",
        "--frames",
        "8",
        "--sampler",
        "ddim",
        "--respacing",
        "ddim10",
        "--threads",
        "1",
        "--out",
        dir.join("x.npy").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.code() == Some(1) && err.contains("guided-diffusion's"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

unsafe fn last_error() -> String {
    std::ffi::CStr::from_ptr(flame_last_error())
        .to_string_lossy()
        .into_owned()
}

/// `flame_session_new` with `p`; the session's total step count, or the error.
unsafe fn ffi_session(m: *const FlameModel, p: *const FlameSessionParams) -> Result<u32, String> {
    let mut s: *mut FlameSession = std::ptr::null_mut();
    if flame_session_new(m, p, &mut s) != FlameStatus::Ok {
        assert!(s.is_null(), "no session written on failure");
        return Err(last_error());
    }
    let (mut done, mut total) = (0u32, 0u32);
    assert_eq!(
        flame_session_progress(s, &mut done, &mut total),
        FlameStatus::Ok
    );
    flame_session_free(s);
    Ok(total)
}

#[test]
fn c_abi_respacing_field() {
    let path = CString::new(tiny("flame").to_str().unwrap()).unwrap();
    let mut m: *mut FlameModel = std::ptr::null_mut();
    unsafe {
        assert_eq!(
            flame_model_load(path.as_ptr(), std::ptr::null(), &mut m),
            FlameStatus::Ok
        );
        let mut p = std::mem::zeroed::<FlameSessionParams>();
        assert_eq!(flame_session_params_default(&mut p), FlameStatus::Ok);
        assert!(p.respacing.is_null(), "no respacing by default");
        p.threads = 1;
        assert_eq!(ffi_session(m, &p), Ok(1000));
        let spec = CString::new("ddim50").unwrap();
        p.respacing = spec.as_ptr();
        assert_eq!(ffi_session(m, &p), Ok(50));
        p.steps = 50;
        assert_eq!(ffi_session(m, &p), Ok(50));
        p.steps = 40;
        let e = ffi_session(m, &p).unwrap_err();
        assert!(
            e.contains("steps 40 disagrees with respacing \"ddim50\""),
            "{e}"
        );
        p.steps = 0;
        let bad = CString::new("ddim999").unwrap();
        p.respacing = bad.as_ptr();
        let e = ffi_session(m, &p).unwrap_err();
        assert!(e.contains("cannot create exactly 999 steps"), "{e}");
        let not_utf8 = [0xffu8, 0xfe, 0];
        p.respacing = not_utf8.as_ptr().cast();
        let e = ffi_session(m, &p).unwrap_err();
        assert!(e.contains("`respacing` is not valid UTF-8"), "{e}");

        // A caller built against version 1 (40 bytes, no `respacing`): what follows is never
        // read, so garbage there changes nothing.
        #[repr(C)]
        struct V1 {
            p: FlameSessionParams,
            poison: [u8; 16],
        }
        let mut v1: V1 = std::mem::zeroed();
        std::ptr::write_bytes(
            &mut v1 as *mut V1 as *mut u8,
            0xA5,
            std::mem::size_of::<V1>(),
        );
        flame_session_params_default(&mut v1.p);
        v1.p.threads = 1;
        v1.p.steps = 7;
        std::ptr::write_bytes(std::ptr::addr_of_mut!(v1.p.respacing).cast::<u8>(), 0xA5, 8);
        v1.p.struct_size = 40;
        assert_eq!(ffi_session(m, &v1.p), Ok(7));
        v1.p.struct_size = 39;
        let e = ffi_session(m, &v1.p).unwrap_err();
        assert!(e.contains("struct_size is 39, expected at least 40"), "{e}");
        flame_model_free(m);
    }
}

fn cli(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .env_remove("FLAME_MODEL")
        .output()
        .unwrap()
}

/// `flame generate` on the tiny FLAME with DDIM and `extra`; the .npy bytes, or stderr.
fn generate(dir: &std::path::Path, out: &str, extra: &[&str]) -> Result<Vec<u8>, String> {
    let out = dir.join(out);
    let model = tiny("flame");
    let mut args = vec![
        "generate",
        "--model",
        model.to_str().unwrap(),
        "--prompt",
        "a person jumps",
        "--frames",
        "8",
        "--sampler",
        "ddim",
        "--seed",
        "5",
        "--threads",
        "1",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = cli(&args);
    if o.status.success() {
        Ok(std::fs::read(&out).unwrap())
    } else {
        Err(String::from_utf8_lossy(&o.stderr).into_owned())
    }
}

#[test]
fn cli_respacing_option() {
    let help = cli(&["generate", "--help"]);
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("--respacing <SPEC>"), "{text}");
    let dir = std::env::temp_dir().join(format!("flame_respacing_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let stride = generate(&dir, "a.npy", &["--respacing", "ddim4"]).unwrap();
    assert_eq!(
        stride,
        generate(&dir, "b.npy", &["--respacing", "1,1,1,1"]).unwrap()
    );
    let sections = generate(&dir, "c.npy", &["--respacing", "4"]).unwrap();
    assert_eq!(
        sections,
        generate(&dir, "d.npy", &["--steps", "4"]).unwrap()
    );
    assert_ne!(stride, sections);
    let e = generate(&dir, "e.npy", &["--respacing", "3", "--steps", "2"]).unwrap_err();
    assert!(e.contains("steps 2 disagrees with respacing \"3\""), "{e}");
    assert!(!dir.join("e.npy").exists(), "nothing written on failure");
    std::fs::remove_dir_all(&dir).unwrap();
}
