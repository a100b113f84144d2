//! Checks of the files a command reads and writes, done before any model is loaded so that a
//! typo in a path costs nothing.

use std::fs::OpenOptions;
use std::path::{Path, PathBuf};

/// The lower-case extension of `path` (`X.BVH` → `bvh`).
pub fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

/// Whether `path` can be written: it is not a folder, its folder exists and takes a new file
/// (probed by creating and removing one, the only test that also holds for root and for
/// read-only mounts), and an existing file there opens for writing (not truncated here).
pub fn check_writable(path: &Path) -> Result<(), String> {
    let p = path.display();
    if path.is_dir() {
        return Err(format!("cannot write {p}: it is a folder"));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.exists() {
        return Err(format!(
            "cannot write {p}: the folder {} does not exist",
            dir.display()
        ));
    }
    if !dir.is_dir() {
        return Err(format!(
            "cannot write {p}: {} is not a folder",
            dir.display()
        ));
    }
    if path.exists() {
        OpenOptions::new()
            .write(true)
            .open(path)
            .map_err(|e| format!("cannot write {p}: {e}"))?;
        return Ok(());
    }
    let probe = probe_path(path);
    OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .map_err(|e| format!("cannot write {p}: {e}"))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// A file name next to `path` that no one else uses.
fn probe_path(path: &Path) -> PathBuf {
    let mut name = std::ffi::OsString::from(".");
    name.push(path.file_name().unwrap_or_default());
    name.push(format!(".flame-probe-{}", std::process::id()));
    path.with_file_name(name)
}

/// Whether `path` is a file that can be opened for reading.
pub fn check_readable(path: &Path) -> Result<(), String> {
    if path.is_dir() {
        return Err(format!("cannot read {}: it is a folder", path.display()));
    }
    std::fs::File::open(path)
        .map(drop)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// Whether `a` and `b` are one existing file (by their canonical paths).
pub fn same_file(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// Fails when two outputs name the same file (the second write would replace the first).
pub fn check_distinct(outputs: &[(&str, &Path)]) -> Result<(), String> {
    for (i, (a, pa)) in outputs.iter().enumerate() {
        if let Some((b, _)) = outputs[i + 1..].iter().find(|(_, pb)| pb == pa) {
            return Err(format!("{a} and {b} name the same file {}", pa.display()));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("flame_paths_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn writable_checks_leave_nothing_behind() {
        let d = scratch("w");
        check_writable(&d.join("x.bvh")).unwrap();
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 0, "probe removed");
        let e = check_writable(&d).unwrap_err();
        assert!(e.ends_with("it is a folder"), "{e}");
        let e = check_writable(&d.join("missing/x.bvh")).unwrap_err();
        assert!(e.contains("missing does not exist"), "{e}");
        std::fs::write(d.join("file"), b"").unwrap();
        let e = check_writable(&d.join("file/x.bvh")).unwrap_err();
        assert!(e.contains("is not a folder"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn extensions_ignore_case() {
        assert_eq!(extension(Path::new("a/X.BVH")).as_deref(), Some("bvh"));
        assert_eq!(extension(Path::new("p.Npy")).as_deref(), Some("npy"));
        assert_eq!(extension(Path::new("noext")), None);
    }

    #[test]
    fn the_same_file_twice_is_refused() {
        let (a, b) = (Path::new("m.npy"), Path::new("p.npy"));
        check_distinct(&[("--out", a), ("--positions", b)]).unwrap();
        let e = check_distinct(&[("--out", a), ("--positions", a)]).unwrap_err();
        assert_eq!(e, "--out and --positions name the same file m.npy");
    }
}
