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

pub(crate) use activation::erf;
pub use activation::{gelu_erf, gelu_tanh, quick_gelu, relu, silu, softmax_rows, tanh};
pub use attention::{multi_head_attention, AttentionScratch};
pub use elementwise::{add_bias, add_inplace, scale_inplace};
pub use embedding::{embedding, guidance_embedding, sinusoid_cos_first, sinusoid_interleaved};
pub use gemm::{linear, matmul_nn, matmul_nt};
pub use norm::{add_layer_norm, layer_norm};
pub use packed::{
    f32_tile, kernel_name, linear_packed, Activation, PackedLinear, PackedWeights, WeightType,
};

use std::cell::Cell;

thread_local! {
    static SERIAL: Cell<bool> = const { Cell::new(false) };
}

/// The threads a kernel call may split over: the current rayon pool's, or 1 inside [`serial`].
pub(crate) fn threads() -> usize {
    if in_serial() {
        1
    } else {
        rayon::current_num_threads()
    }
}

/// Runs `f` with every kernel call it makes on this thread unsplit, and uncharged in
/// [`profile`] (the caller charges the whole). For callers that already run independent calls
/// in parallel, such as a mixture's experts: splitting each call again would have both threads
/// pack the same activations and wake each other for every call. The same bits either way.
pub(crate) fn serial<R>(f: impl FnOnce() -> R) -> R {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            SERIAL.with(|s| s.set(self.0));
        }
    }
    let _restore = Restore(SERIAL.with(|s| s.replace(true)));
    f()
}

/// Whether the calling thread is inside [`serial`].
pub(crate) fn in_serial() -> bool {
    SERIAL.with(Cell::get)
}
