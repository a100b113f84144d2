//! Helpers shared by integration tests (each test binary includes this module with `mod common;`
//! and uses what it needs).
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// A path inside the repository.
pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The largest absolute difference of two equally long slices.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The trained demo model: `$FLAME_DEMO_MODEL`, else models/demo/flame_demo.safetensors when
/// assembled, else the committed denoiser assembled once (in the test target's scratch folder)
/// with `$FLAME_MINILM_DIR`'s all-MiniLM-L6-v2. None (the caller skips) without any of them,
/// unless FLAME_REQUIRE_REAL_WEIGHTS=1.
pub fn demo_model() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("FLAME_DEMO_MODEL") {
        return Some(path.into());
    }
    let assembled = repo("models/demo/flame_demo.safetensors");
    if assembled.is_file() {
        return Some(assembled);
    }
    let require = std::env::var("FLAME_REQUIRE_REAL_WEIGHTS").as_deref() == Ok("1");
    let Some(minilm) = std::env::var_os("FLAME_MINILM_DIR").map(PathBuf::from) else {
        assert!(
            !require,
            "FLAME_REQUIRE_REAL_WEIGHTS=1 but FLAME_MINILM_DIR is not set"
        );
        return None;
    };
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
