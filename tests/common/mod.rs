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
