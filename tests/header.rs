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
