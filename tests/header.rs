//! The checked-in C header must be exactly what cbindgen generates from the source.
//! Regenerate with `FLAME_UPDATE_HEADER=1 cargo test --test header` (or the cbindgen CLI of the
//! pinned version: `cbindgen --config cbindgen.toml --crate flame --output include/flame.h`).

use std::path::Path;

#[test]
fn header_is_up_to_date() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(dir.join("cbindgen.toml")).expect("cbindgen.toml");
    let bindings = cbindgen::Builder::new()
        .with_crate(dir)
        .with_config(config)
        .generate()
        .expect("cbindgen generates the header");
    let mut generated = Vec::new();
    bindings.write(&mut generated);
    let path = dir.join("include/flame.h");
    if std::env::var_os("FLAME_UPDATE_HEADER").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let current = std::fs::read(&path).unwrap_or_default();
    assert!(
        current == generated,
        "include/flame.h is stale: regenerate it with `FLAME_UPDATE_HEADER=1 cargo test --test header`"
    );
}

#[test]
fn version_macros_match_the_crate() {
    assert_eq!(
        flame::ffi::FLAME_VERSION_MAJOR.to_string(),
        env!("CARGO_PKG_VERSION_MAJOR")
    );
    assert_eq!(
        flame::ffi::FLAME_VERSION_MINOR.to_string(),
        env!("CARGO_PKG_VERSION_MINOR")
    );
    assert_eq!(
        flame::ffi::FLAME_VERSION_PATCH.to_string(),
        env!("CARGO_PKG_VERSION_PATCH")
    );
}

#[test]
fn header_declares_only_prefixed_names() {
    // Everything the header declares must carry the library's prefix, so including it cannot
    // collide with a host's names (tests/header.rs keeps cbindgen.toml's exclude list honest).
    let header =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("include/flame.h"))
            .unwrap();
    let mut bad = Vec::new();
    for line in header.lines() {
        let words: Vec<&str> = line
            .split(|c: char| !(c.is_alphanumeric() || c == '_'))
            .filter(|w| !w.is_empty())
            .collect();
        let declared = match words.as_slice() {
            ["define", name, ..] => Some(*name),
            ["typedef", "struct", name, ..] | ["typedef", "enum", name, ..] => Some(*name),
            ["typedef", _, name, ..] if !line.contains('(') => Some(*name),
            _ if line.contains('(')
                && !line.trim_start().starts_with("//")
                && !line.starts_with(' ') =>
            {
                words
                    .iter()
                    .find(|w| line.contains(&format!("{w}(")))
                    .copied()
            }
            _ => None,
        };
        if let Some(name) = declared {
            let ok = name.starts_with("Flame")
                || name.starts_with("flame_")
                || name.starts_with("FLAME_");
            if !ok && name != "FLAME_H" {
                bad.push(name.to_string());
            }
        }
    }
    assert!(
        bad.is_empty(),
        "unprefixed names in include/flame.h: {bad:?}"
    );
}
