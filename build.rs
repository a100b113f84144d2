//! Gives the shared library a location-independent name, so programs linked against it by path
//! look for `libflame.so` (or `@rpath/libflame.dylib`) at run time, not the build machine's path.

fn main() {
    match std::env::var("CARGO_CFG_TARGET_OS").as_deref() {
        Ok("linux") => println!("cargo:rustc-cdylib-link-arg=-Wl,-soname,libflame.so"),
        Ok("macos") => {
            println!("cargo:rustc-cdylib-link-arg=-Wl,-install_name,@rpath/libflame.dylib")
        }
        _ => {}
    }
    println!("cargo:rerun-if-changed=build.rs");
}
