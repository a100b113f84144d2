//! libflame: a pure-Rust CPU runtime for text-to-motion diffusion models.
//!
//! Data flows one way: [`session`] → [`models`] + [`diffusion`] → [`kernels`], with [`text`]
//! encoders, [`motion`] formats and the [`checkpoint`] loader beside them. Kernels know nothing
//! about transformers, models know nothing about the C ABI, and the sampler never knows which
//! network it drives.

pub mod assemble;
pub mod checkpoint;
pub mod config;
pub mod demo;
pub mod diffusion;
pub mod edit;
pub mod error;
pub mod ffi;
pub mod kernels;
pub mod models;
pub mod motion;
pub mod npy;
pub mod pool;
pub mod rng;
pub mod session;
pub mod text;

pub use error::{Error, Result};
