//! Layer normalisation.

/// Row-wise LayerNorm in place: each row of `dim` values is normalised (biased variance) and
/// scaled by `gamma`, shifted by `beta`.
pub fn layer_norm(x: &mut [f32], dim: usize, gamma: &[f32], beta: &[f32], eps: f32) {
    let _ = (x, dim, gamma, beta, eps);
    unimplemented!()
}

/// `x = LayerNorm(x + residual)` row-wise (the post-LN residual step).
pub fn add_layer_norm(x: &mut [f32], residual: &[f32], dim: usize, gamma: &[f32], beta: &[f32], eps: f32) {
    let _ = (x, residual, dim, gamma, beta, eps);
    unimplemented!()
}
