//! GEMM wrappers.

/// `y[m, n] = x[m, k] · w[n, k]ᵀ + bias[n]` (PyTorch `Linear`). `y` is overwritten.
pub fn linear(x: &[f32], w: &[f32], bias: Option<&[f32]>, y: &mut [f32], m: usize, k: usize, n: usize) {
    let _ = (x, w, bias, y, m, k, n);
    unimplemented!()
}

/// `c[m, n] = a[m, k] · b[n, k]ᵀ`. `c` is overwritten.
pub fn matmul_nt(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize) {
    let _ = (a, b, c, m, k, n);
    unimplemented!()
}

/// `c[m, n] = a[m, k] · b[k, n]`. `c` is overwritten.
pub fn matmul_nn(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize) {
    let _ = (a, b, c, m, k, n);
    unimplemented!()
}
