//! Backward of the element-wise and reshaping steps between a decoder's layers and the loss.

use crate::error::{invalid_arg, Result};

/// ReLU's backward in place: `grad[i] = 0` where `y[i] <= 0`. `y` may be the ReLU's output or
/// its input (same sign test); at exactly 0 the gradient is 0, as PyTorch's.
pub fn relu_backward(y: &[f32], grad: &mut [f32]) {
    debug_assert_eq!(y.len(), grad.len(), "relu_backward: lengths");
    for (g, &v) in grad.iter_mut().zip(y) {
        if v <= 0.0 {
            *g = 0.0;
        }
    }
}

/// Backward of nearest-neighbour ×2 upsampling over frames (frame-major rows of `width`; output
/// frames `2i` and `2i + 1` copy input frame `i`): `grad_in[i] = grad_out[2i] + grad_out[2i + 1]`.
/// `grad_in` is resized to `frames_in · width` and overwritten.
pub fn upsample_nearest2_backward(
    grad_out: &[f32],
    frames_in: usize,
    width: usize,
    grad_in: &mut Vec<f32>,
) {
    debug_assert_eq!(grad_out.len(), 2 * frames_in * width, "upsample: lengths");
    grad_in.resize(frames_in * width, 0.0);
    if width == 0 {
        return;
    }
    for (gi, pair) in grad_in
        .chunks_exact_mut(width)
        .zip(grad_out.chunks_exact(2 * width))
    {
        let (a, b) = pair.split_at(width);
        for ((g, &x), &y) in gi.iter_mut().zip(a).zip(b) {
            *g = x + y;
        }
    }
}

/// Backward of de-normalisation `y = x · std + mean` (per channel, rows of `std.len()`):
/// `dx = dy · std`, in place.
pub fn denormalize_backward(grad: &mut [f64], std: &[f32]) -> Result<()> {
    if std.is_empty() || !grad.len().is_multiple_of(std.len()) {
        return Err(invalid_arg!(
            "cannot de-normalise the gradient of {} values with {} stds",
            grad.len(),
            std.len()
        ));
    }
    for row in grad.chunks_exact_mut(std.len()) {
        for (g, &s) in row.iter_mut().zip(std) {
            *g *= s as f64;
        }
    }
    Ok(())
}

/// MPGD's loss `L = Σ_i ‖(pos_i − target_i) ⊙ w_i‖₂` (`w` is 0 or 1 per coordinate, MoLA's
/// `m = c ≠ 0`) and its gradient `dL/dpos_i = w_i ⊙ d_i / ‖d_i‖` with `d_i = (pos_i − target_i) ⊙
/// w_i`, written to `grad` (0 where `‖d_i‖ = 0`, as torch's norm backward). Returns `L`.
pub fn l2_norm_sum_grad(
    pos: &[[f64; 3]],
    target: &[[f64; 3]],
    weight: &[[f64; 3]],
    grad: &mut [[f64; 3]],
) -> f64 {
    debug_assert!(
        pos.len() == target.len() && pos.len() == weight.len() && pos.len() == grad.len(),
        "l2_norm_sum_grad: lengths"
    );
    let mut loss = 0.0;
    for (((p, c), w), g) in pos.iter().zip(target).zip(weight).zip(grad.iter_mut()) {
        let d: [f64; 3] = std::array::from_fn(|k| (p[k] - c[k]) * w[k]);
        let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        loss += norm;
        *g = if norm > 0.0 {
            std::array::from_fn(|k| w[k] * d[k] / norm)
        } else {
            [0.0; 3]
        };
    }
    loss
}
