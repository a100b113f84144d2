//! `flame::assemble`: a denoiser-only file plus a Hugging Face text encoder file gives a model
//! that loads and computes exactly what the complete file computes; bad inputs give clear errors
//! and leave no output behind.
//!
//! Fixtures: tests/fixtures/flame_tiny{,_f16}.safetensors (tools/make_fixtures.py), split here
//! into a denoiser-only file and a `roberta.`-prefixed text weights file.
//!
//! The demo model test (reference: tools/demo/parity.py, PyTorch) assembles the shipped
//! models/demo/flame_demo_denoiser.safetensors with the real all-MiniLM-L6-v2 (FLAME_MINILM_DIR)
//! and compares one denoiser forward per case of models/demo/flame_demo_parity.safetensors.
//! It skips while the demo model is not in the repository; FLAME_DEMO_DENOISER and
//! FLAME_DEMO_PARITY point it at other files (tools/demo/build_demo.sh does).

mod common;

use std::path::{Path, PathBuf};

use flame::assemble::{
    assemble, assemble_with, trained_actions, AssembleOptions, ACTIONS_KEY, TEXT_ASSEMBLED_KEY,
    TEXT_SOURCE_KEY,
};
use flame::checkpoint::ModelFile;
use flame::models::{Model, Workspace};
use flame::Error;
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// A fresh, empty directory for one test.
fn scratch(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flame-assemble-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// How to split a complete file into the two inputs of `assemble`.
#[derive(Default)]
struct Split {
    /// Text tensors not written to the text weights file.
    omit: Vec<&'static str>,
    /// Text tensors written with a wrong shape (their first dimension halved).
    misshape: Vec<&'static str>,
    /// Leave the `flame.text_source` metadata out of the denoiser file.
    no_source: bool,
}

/// Splits `complete` into `dir/denoiser.safetensors` (metadata + `flame.text_source`, no text
/// tensors) and `dir/text.safetensors` (HF names under `roberta.`, plus a position_ids buffer
/// as Hugging Face files carry). Returns the two paths.
fn split(complete: &Path, dir: &Path, how: &Split) -> (PathBuf, PathBuf) {
    let bytes = std::fs::read(complete).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let mut metadata = header.metadata().clone().unwrap();
    if !how.no_source {
        metadata.insert(
            TEXT_SOURCE_KEY.into(),
            r#"{"tensor_prefix": "text."}"#.into(),
        );
    }
    let mut den = Vec::new();
    let mut text = Vec::new();
    let mut halved = Vec::new();
    for (name, view) in file.tensors() {
        match name.strip_prefix("text.") {
            None => den.push((name, view)),
            Some(bare) if how.omit.contains(&bare) => {}
            Some(bare) if how.misshape.contains(&bare) => {
                let mut shape = view.shape().to_vec();
                shape[0] /= 2;
                let n: usize = shape.iter().product::<usize>() * view.dtype().size();
                halved.push((format!("roberta.{bare}"), view.dtype(), shape, n, view));
            }
            Some(bare) => text.push((format!("roberta.{bare}"), view)),
        }
    }
    for (name, dtype, shape, n, view) in &halved {
        text.push((
            name.clone(),
            TensorView::new(*dtype, shape.clone(), &view.data()[..*n]).unwrap(),
        ));
    }
    let position_ids: Vec<u8> = (0i64..64).flat_map(|i| i.to_le_bytes()).collect();
    text.push((
        "roberta.embeddings.position_ids".into(),
        TensorView::new(Dtype::I64, vec![1, 64], &position_ids).unwrap(),
    ));
    let den_path = dir.join("denoiser.safetensors");
    let text_path = dir.join("text.safetensors");
    safetensors::serialize_to_file(den, &Some(metadata), &den_path).unwrap();
    safetensors::serialize_to_file(text, &None, &text_path).unwrap();
    (den_path, text_path)
}

/// Text states and one guided-batch forward (cond + uncond rows) at t = 500.
fn outputs(m: &Model, prompt: &str, frames: usize) -> Vec<Vec<f32>> {
    let enc = m.text_encoder().unwrap().encode(prompt).unwrap();
    let x: Vec<f32> = (0..frames * m.motion_dim())
        .map(|i| ((i * 7919 % 1000) as f32 / 500.0 - 1.0) * 1.5)
        .collect();
    let mut xb = x.clone();
    xb.extend_from_slice(&x);
    let cond = m.encode_prompt(prompt).unwrap();
    let mut out = vec![0.0; 2 * frames * m.output_dim()];
    m.forward(
        &xb,
        frames,
        500.0,
        &[&cond, m.uncond().unwrap()],
        &mut out,
        &mut Workspace::default(),
    )
    .unwrap();
    vec![enc.hidden, enc.pooled, out]
}

fn assert_bit_identical(complete: &str) {
    let dir = scratch(complete);
    let (den, text) = split(&fixture(complete), &dir, &Split::default());
    let out = dir.join("assembled.safetensors");
    let report = assemble(&den, &text, &out).unwrap();
    assert_eq!(report.dropped, vec!["roberta.embeddings.position_ids"]);
    assert!(report.text_tensors > 0 && report.denoiser_tensors > 0);
    assert_eq!(report.bytes, std::fs::metadata(&out).unwrap().len());

    let original = Model::load(fixture(complete)).unwrap();
    let assembled = Model::load(&out).unwrap();
    assert_eq!(original.stored_dtype(), assembled.stored_dtype());
    let prompt = "a person walks forward and waves.";
    let (a, b) = (
        outputs(&original, prompt, 24),
        outputs(&assembled, prompt, 24),
    );
    for (x, y) in a.iter().zip(&b) {
        assert!(
            x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits()),
            "{complete}: outputs differ"
        );
    }
    // Every tensor is stored with its original dtype and bytes.
    let (orig, asm) = (
        std::fs::read(fixture(complete)).unwrap(),
        std::fs::read(&out).unwrap(),
    );
    let (orig, asm) = (
        SafeTensors::deserialize(&orig).unwrap(),
        SafeTensors::deserialize(&asm).unwrap(),
    );
    assert_eq!(orig.len(), asm.len());
    for (name, view) in orig.tensors() {
        let got = asm.tensor(&name).unwrap();
        assert_eq!(
            (got.dtype(), got.shape(), got.data()),
            (view.dtype(), view.shape(), view.data()),
            "{name}"
        );
    }
    let metadata = ModelFile::open(&out).unwrap();
    assert!(metadata.metadata(TEXT_SOURCE_KEY).is_none());
    assert!(metadata.metadata(TEXT_ASSEMBLED_KEY).is_some());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn assembled_f32_model_matches_the_complete_file() {
    assert_bit_identical("flame_tiny.safetensors");
}

#[test]
fn assembled_f16_model_matches_the_complete_file() {
    assert_bit_identical("flame_tiny_f16.safetensors");
}

/// Runs `assemble` on a split made `how`, expects an error whose text contains `want`, and
/// checks that nothing was left in the directory besides the inputs.
fn expect_error(test: &str, how: Split, want: &str) {
    let dir = scratch(test);
    let (den, text) = split(&fixture("flame_tiny.safetensors"), &dir, &how);
    let out = dir.join("assembled.safetensors");
    let e = assemble(&den, &text, &out).unwrap_err();
    assert!(matches!(e, Error::BadModelFile(_)), "{e:?}");
    let msg = e.to_string();
    assert!(msg.contains(want), "{msg}");
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    assert_eq!(left.len(), 2, "output or temporary file left behind");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn missing_text_tensor_is_named() {
    expect_error(
        "missing",
        Split {
            omit: vec!["encoder.layer.1.output.dense.weight"],
            ..Split::default()
        },
        "missing text encoder tensor `roberta.encoder.layer.1.output.dense.weight`",
    );
}

#[test]
fn wrong_shape_is_named() {
    expect_error(
        "shape",
        Split {
            misshape: vec!["embeddings.word_embeddings.weight"],
            ..Split::default()
        },
        "`roberta.embeddings.word_embeddings.weight` has shape [489, 48], the denoiser's config wants [979, 48]",
    );
}

#[test]
fn file_without_text_source_is_not_denoiser_only() {
    expect_error(
        "nosource",
        Split {
            no_source: true,
            ..Split::default()
        },
        "not a denoiser-only file (no `flame.text_source` metadata",
    );
}

#[test]
fn complete_file_is_not_denoiser_only() {
    let dir = scratch("complete");
    let (den, text) = split(&fixture("flame_tiny.safetensors"), &dir, &Split::default());
    let out = dir.join("assembled.safetensors");
    assemble(&den, &text, &out).unwrap();
    let again = dir.join("again.safetensors");
    let e = assemble(&out, &text, &again).unwrap_err().to_string();
    assert!(e.contains("not a denoiser-only file"), "{e}");
    let e = assemble(&fixture("flame_tiny.safetensors"), &text, &again)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a denoiser-only file"), "{e}");
    assert!(!again.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The `__metadata__` keys of a safetensors file in the order its header text lists them.
fn metadata_keys_in_file_order(bytes: &[u8]) -> Vec<String> {
    let (_, header) = SafeTensors::read_metadata(bytes).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let text = std::str::from_utf8(&bytes[8..8 + n]).unwrap();
    let start = text.find("\"__metadata__\":{").unwrap();
    let mut keys: Vec<(usize, String)> = header
        .metadata()
        .clone()
        .unwrap()
        .into_keys()
        .map(|k| (start + text[start..].find(&format!("\"{k}\":")).unwrap(), k))
        .collect();
    keys.sort();
    keys.into_iter().map(|(_, k)| k).collect()
}

#[test]
fn assembly_gives_the_same_bytes_every_time() {
    let dir = scratch("repeat");
    let (den, text) = split(&fixture("flame_tiny.safetensors"), &dir, &Split::default());
    let demo: Vec<String> = flame_demo::Family::ALL
        .iter()
        .map(|f| f.name().to_string())
        .collect();
    // Separate processes (each hashes with its own random keys) and this one.
    let mut files = Vec::new();
    for run in 0..3 {
        let out = dir.join(format!("cli{run}.safetensors"));
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_flame"))
            .arg("assemble")
            .args([&den, &text, &out])
            .arg("--demo-actions")
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        files.push(std::fs::read(&out).unwrap());
    }
    let lib = dir.join("lib.safetensors");
    let opts = AssembleOptions {
        actions: demo.clone(),
    };
    let report = assemble_with(&den, &text, &lib, &opts).unwrap();
    files.push(std::fs::read(&lib).unwrap());
    assert_eq!(report.bytes, files[0].len() as u64);
    for f in &files[1..] {
        assert!(f == &files[0], "assembled files differ");
    }
    // Deterministic by construction, not by luck: the metadata is written sorted by key.
    let keys = metadata_keys_in_file_order(&files[0]);
    let mut sorted = keys.clone();
    sorted.sort();
    assert_eq!(keys, sorted);
    assert!(keys.len() >= 5, "{keys:?}");

    let file = ModelFile::open(&lib).unwrap();
    assert_eq!(trained_actions(&file).unwrap(), Some(demo.clone()));
    assert_eq!(
        file.metadata(ACTIONS_KEY).unwrap(),
        serde_json::to_string(&demo).unwrap()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn action_names_are_checked() {
    let dir = scratch("names");
    let (den, text) = split(&fixture("flame_tiny.safetensors"), &dir, &Split::default());
    let out = dir.join("out.safetensors");
    for bad in ["", "walk,run", " walk"] {
        let opts = AssembleOptions {
            actions: vec!["jump".into(), bad.into()],
        };
        let e = assemble_with(&den, &text, &out, &opts).unwrap_err();
        assert!(matches!(e, Error::InvalidArgument(_)), "{bad:?}: {e:?}");
        assert!(!out.exists());
    }
    // Without actions the key is absent.
    assemble(&den, &text, &out).unwrap();
    assert_eq!(
        trained_actions(&ModelFile::open(&out).unwrap()).unwrap(),
        None
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn unreadable_inputs_are_clear_errors() {
    let dir = scratch("unreadable");
    let (den, text) = split(&fixture("flame_tiny.safetensors"), &dir, &Split::default());
    let out = dir.join("assembled.safetensors");
    let missing = dir.join("nope.safetensors");
    let e = assemble(&missing, &text, &out).unwrap_err();
    assert!(matches!(e, Error::Io { .. }), "{e:?}");
    assert!(e.to_string().contains("nope.safetensors"), "{e}");
    let e = assemble(&den, &missing, &out).unwrap_err();
    assert!(matches!(e, Error::Io { .. }), "{e:?}");

    let garbage = dir.join("garbage.safetensors");
    std::fs::write(&garbage, b"this is not a safetensors file").unwrap();
    let e = assemble(&garbage, &text, &out).unwrap_err().to_string();
    assert!(
        e.contains("garbage.safetensors: not a safetensors file"),
        "{e}"
    );
    let e = assemble(&den, &garbage, &out).unwrap_err().to_string();
    assert!(
        e.contains("garbage.safetensors: not a safetensors file"),
        "{e}"
    );
    // A text file of another encoder (the denoiser file itself has no text tensors at all).
    let e = assemble(&den, &den, &out).unwrap_err().to_string();
    assert!(e.contains("missing text encoder tensor"), "{e}");
    // An output directory that does not exist: a write error, said as such.
    let e = assemble(&den, &text, &dir.join("no/such/dir/out.safetensors")).unwrap_err();
    assert!(matches!(e, Error::Write { .. }), "{e:?}");
    assert!(e.to_string().starts_with("cannot write "), "{e}");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

// -- the demo model against PyTorch ---------------------------------------------------------------

fn env_or_repo(var: &str, repo_path: &str) -> PathBuf {
    std::env::var_os(var)
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join(repo_path))
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn demo_model_matches_pytorch() {
    let denoiser = env_or_repo(
        "FLAME_DEMO_DENOISER",
        "models/demo/flame_demo_denoiser.safetensors",
    );
    let parity = env_or_repo(
        "FLAME_DEMO_PARITY",
        "models/demo/flame_demo_parity.safetensors",
    );
    if !denoiser.exists() {
        common::skip(
            "assemble::demo_model_matches_pytorch",
            &format!("no demo model at {}", denoiser.display()),
        );
        return;
    }
    let Some(minilm) = common::minilm_dir() else {
        common::skip(
            "assemble::demo_model_matches_pytorch",
            "no all-MiniLM-L6-v2 (set FLAME_MINILM_DIR or run tools/try.sh)",
        );
        return;
    };
    let dir = scratch("demo");
    let out = dir.join("flame_demo.safetensors");
    assemble(&denoiser, &minilm.join("model.safetensors"), &out).unwrap();
    let m = Model::load(&out).unwrap();
    let expected = ModelFile::open(&parity).unwrap();
    let get = |name: &str| expected.tensor_any_shape(name).unwrap().data().to_vec();
    let cases: serde_json::Value =
        serde_json::from_str(expected.metadata("flame.parity").unwrap()).unwrap();
    let prompt = cases["prompt"].as_str().unwrap();
    let frames = cases["frames"].as_u64().unwrap() as usize;

    let text = m.text_encoder().unwrap().encode(prompt).unwrap();
    let d_text = max_abs_diff(&text.hidden, &get("text_cond_hidden"))
        .max(max_abs_diff(&text.pooled, &get("text_cond_pooled")));
    println!("demo parity: text states max abs diff {d_text:e}");
    assert!(d_text <= TOL, "text states differ by {d_text:e}");

    let x = get("x");
    let mut xb = x.clone();
    xb.extend_from_slice(&x);
    let cond = m.encode_prompt(prompt).unwrap();
    let od = m.output_dim();
    let mut worst = 0.0f32;
    for (k, t) in cases["timesteps"].as_array().unwrap().iter().enumerate() {
        let mut out = vec![0.0; 2 * frames * od];
        m.forward(
            &xb,
            frames,
            t.as_f64().unwrap() as f32,
            &[&cond, m.uncond().unwrap()],
            &mut out,
            &mut Workspace::default(),
        )
        .unwrap();
        let (oc, ou) = out.split_at(frames * od);
        let d = max_abs_diff(oc, &get(&format!("out_cond_{k}")))
            .max(max_abs_diff(ou, &get(&format!("out_uncond_{k}"))));
        println!("demo parity: t = {t}: denoiser output max abs diff {d:e}");
        worst = worst.max(d);
    }
    println!("demo parity: worst denoiser output max abs diff {worst:e}");
    assert!(
        worst <= TOL,
        "denoiser outputs differ by {worst:e} > {TOL:e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
