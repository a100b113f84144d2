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
