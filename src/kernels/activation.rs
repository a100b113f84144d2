//! Element-wise activations and softmax, in place.

pub fn relu(x: &mut [f32]) { let _ = x; unimplemented!() }
/// Exact GELU, `x · Φ(x)` with the error function.
pub fn gelu_erf(x: &mut [f32]) { let _ = x; unimplemented!() }
/// CLIP's `x · sigmoid(1.702 x)`.
pub fn quick_gelu(x: &mut [f32]) { let _ = x; unimplemented!() }
pub fn silu(x: &mut [f32]) { let _ = x; unimplemented!() }
pub fn tanh(x: &mut [f32]) { let _ = x; unimplemented!() }
/// Softmax over each row of `n` values.
pub fn softmax_rows(x: &mut [f32], n: usize) { let _ = (x, n); unimplemented!() }
