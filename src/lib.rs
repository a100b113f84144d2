//! libflame: a pure-Rust CPU runtime for text-to-motion diffusion models.
//!
//! Data flows one way: [`session`] → [`models`] + [`diffusion`] → [`kernels`], with [`text`]
//! encoders, [`motion`] formats and the [`checkpoint`] loader beside them. Kernels know nothing
//! about transformers, models know nothing about the C ABI, and the sampler never knows which
//! network it drives.
//!
//! Only [`ffi`] faces C: the other modules are marked `cbindgen:ignore` so that no public Rust
//! item of theirs leaks into include/flame.h.

/// cbindgen:ignore
pub mod assemble;
/// cbindgen:ignore
pub mod checkpoint;
/// cbindgen:ignore
pub mod config;
/// cbindgen:ignore
pub mod cycle;
/// cbindgen:ignore
pub mod diffusion;
/// cbindgen:ignore
pub mod edit;
/// cbindgen:ignore
pub mod error;
pub mod ffi;
/// cbindgen:ignore
pub mod grad;
/// cbindgen:ignore
pub mod kernels;
/// cbindgen:ignore
pub mod models;
/// cbindgen:ignore
pub mod motion;
/// cbindgen:ignore
pub mod npy;
/// cbindgen:ignore
pub mod npz;
/// cbindgen:ignore
pub mod pool;
/// cbindgen:ignore
pub mod retarget;
/// cbindgen:ignore
pub mod rng;
/// cbindgen:ignore
pub mod robot;
/// cbindgen:ignore
pub mod session;
/// cbindgen:ignore
pub mod stages;
/// cbindgen:ignore
pub mod stream;
/// cbindgen:ignore
pub mod targets;
/// cbindgen:ignore
pub mod text;

pub use error::{Error, Result};

/// The guide's Rust examples (README.md and the pages of docs/ that have any), compiled by
/// `cargo test --doc` as doctests of this crate (in tools/check.sh's `rust` stage); examples
/// that need a converted checkpoint are `no_run`, the others run on the test fixtures.
/// tools/docs_blocks.py checks that every page with a Rust block is listed here.
/// cbindgen:ignore
#[cfg(doctest)]
mod guide {
    macro_rules! pages {
        ($($name:ident = $path:literal),* $(,)?) => {
            $(
                #[doc = include_str!($path)]
                pub struct $name;
            )*
        };
    }
    pages! {
        Readme = "../README.md",
        RustApi = "../docs/rust-api.md",
        Streams = "../docs/streams.md",
        Conventions = "../docs/conventions.md",
        GameReady = "../docs/game-ready.md",
        Architecture = "../docs/architecture.md",
        Preview = "../docs/preview.md",
        Robots = "../docs/robots.md",
    }
}
