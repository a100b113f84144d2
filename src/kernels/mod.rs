//! Numeric building blocks on row-major `f32` slices: linear layers on weights packed at load
//! (`packed`: AVX-512, AVX2/FMA and portable micro-kernels chosen at run time, f32/f16/bf16 weights, split across the current rayon
//! pool), attention, normalisation, activations and embeddings, plus general GEMMs on
//! `matrixmultiply` (`gemm`: activation-by-activation products and the benchmark's baseline).
//!
//! Kernels know nothing about transformers or models. Weights use PyTorch's layout (`Linear.weight`
//! is `[out, in]`). Parallel work is only ever split over independent outputs (rows, columns,
//! heads), never over a reduction, so results are bit-identical for every thread count.
//!
//! Where a kernel takes explicit sizes (GEMM, attention, embedding), inputs may be longer than it
//! reads and the output at least as long as the result (nothing past it is written), so scratch
//! buffers and strided views pass straight in; in-place kernels act on the whole slice.

mod activation;
mod attention;
mod elementwise;
mod embedding;
mod gemm;
mod norm;
mod packed;
pub mod profile;
#[cfg(test)]
mod testutil;

pub use activation::{gelu_erf, gelu_tanh, quick_gelu, relu, silu, softmax_rows, tanh};
pub use attention::{multi_head_attention, AttentionScratch};
pub use elementwise::{add_bias, add_inplace, scale_inplace};
pub use embedding::{embedding, sinusoid_cos_first, sinusoid_interleaved};
pub use gemm::{linear, matmul_nn, matmul_nt};
pub use norm::{add_layer_norm, layer_norm};
pub use packed::{
    f32_tile, kernel_name, linear_packed, Activation, PackedLinear, PackedWeights, WeightType,
};
