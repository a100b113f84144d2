//! Element-wise arithmetic that models need between the heavier kernels.

/// `x += y`.
pub fn add_inplace(x: &mut [f32], y: &[f32]) {
    assert_eq!(x.len(), y.len(), "add_inplace: length mismatch");
    x.iter_mut().zip(y).for_each(|(a, &b)| *a += b);
}

/// Adds `bias` (length `n`) to every row of `x` (`[rows, n]`).
pub fn add_bias(x: &mut [f32], bias: &[f32]) {
    let n = bias.len();
    if n == 0 {
        return;
    }
    assert_eq!(
        x.len() % n,
        0,
        "add_bias: length not a multiple of bias length"
    );
    for row in x.chunks_exact_mut(n) {
        row.iter_mut().zip(bias).for_each(|(a, &b)| *a += b);
    }
}

/// `x *= s`.
pub fn scale_inplace(x: &mut [f32], s: f32) {
    x.iter_mut().for_each(|a| *a *= s);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn add_and_scale() {
        let mut x = vec![1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        add_inplace(&mut x, &[0.5, 0.5, 0.5, -1.0, -1.0, -1.0]);
        assert_eq!(x, [1.5, 2.5, 3.5, 3.0, 4.0, 5.0]);
        add_bias(&mut x, &[10.0, 20.0, 30.0]);
        assert_eq!(x, [11.5, 22.5, 33.5, 13.0, 24.0, 35.0]);
        scale_inplace(&mut x, 2.0);
        assert_eq!(x, [23.0, 45.0, 67.0, 26.0, 48.0, 70.0]);
        add_bias(&mut x, &[]);
    }
}
