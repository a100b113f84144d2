//! Post-processing of motions: temporal Gaussian smoothing of features (FLAME's official output
//! step) and quaternion sign continuity between frames.

/// Gaussian smoothing over time of every channel of a frame-major `[frames, channels]` array,
/// exactly as `scipy.ndimage.gaussian_filter1d(x, sigma, axis=0)` with its defaults (FLAME's
/// `t2m_sample.py`; docs/official/flame.md#temporal-smoothing): mode "reflect" (the edge sample
/// repeated: d c b a | a b c d | d c b a), truncate 4.0, so radius `⌊4σ + 0.5⌋` and weights
/// `exp(−k²/2σ²)` normalised to sum 1. `sigma <= 0` leaves the data unchanged. FLAME smooths all
/// 147 channels with σ = 1.
pub fn gaussian_smooth(data: &mut [f64], frames: usize, channels: usize, sigma: f64) {
    if sigma <= 0.0 || frames == 0 || channels == 0 {
        return;
    }
    let radius = (4.0 * sigma + 0.5) as isize;
    let mut weights: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k * k) as f64 / (sigma * sigma)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.iter_mut().for_each(|w| *w /= total);

    let n = frames as isize;
    let reflect = |i: isize| -> usize {
        let m = i.rem_euclid(2 * n);
        (if m >= n { 2 * n - 1 - m } else { m }) as usize
    };
    let mut column = vec![0.0; frames];
    for c in 0..channels {
        for (t, x) in column.iter_mut().enumerate() {
            *x = data[t * channels + c];
        }
        for t in 0..frames {
            let acc: f64 = (-radius..=radius)
                .zip(&weights)
                .map(|(k, w)| w * column[reflect(t as isize + k)])
                .sum();
            data[t * channels + c] = acc;
        }
    }
}

/// Makes each joint's quaternion track continuous: `q[t]` is negated when `dot(q[t], q[t−1]) < 0`
/// (with `q[t−1]` already corrected), so interpolating between frames never takes the long way
/// round. `quats` is `[frames, joints]`, any component order.
pub fn make_continuous(quats: &mut [[f64; 4]], frames: usize, joints: usize) {
    for t in 1..frames {
        for j in 0..joints {
            let prev = quats[(t - 1) * joints + j];
            let q = &mut quats[t * joints + j];
            if prev.iter().zip(q.iter()).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
                *q = q.map(|x| -x);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_matches_scipy_on_a_short_signal() {
        // scipy 1.17: gaussian_filter1d(np.array([0., 1, 0, 0, 3]), 1.0); the signal is shorter
        // than the radius (4), so the reflection wraps more than once.
        let want = [
            0.29636406495114936,
            0.4170724077100671,
            0.4173742434034225,
            0.9418788466526199,
            1.9273104372827414,
        ];
        let mut y = vec![0.0, 1.0, 0.0, 0.0, 3.0];
        gaussian_smooth(&mut y, 5, 1, 1.0);
        for (a, b) in y.iter().zip(want) {
            assert!((a - b).abs() < 1e-15, "{y:?}");
        }
        // Mass is kept by reflection, and a constant stays constant.
        let mut c = vec![2.5; 7];
        gaussian_smooth(&mut c, 7, 1, 1.0);
        assert!(c.iter().all(|v| (v - 2.5).abs() < 1e-12));
        // One frame, several channels: reflection repeats the sample.
        let mut one = vec![1.0, -2.0];
        gaussian_smooth(&mut one, 1, 2, 1.0);
        assert!((one[0] - 1.0).abs() < 1e-12 && (one[1] + 2.0).abs() < 1e-12);
    }

    #[test]
    fn continuity_flips_against_the_previous_frame() {
        let mut q = vec![
            [1.0, 0.0, 0.0, 0.0],
            [-0.9, 0.1, 0.0, 0.0],
            [0.8, -0.2, 0.0, 0.0],
        ];
        make_continuous(&mut q, 3, 1);
        assert_eq!(q[1], [0.9, -0.1, -0.0, -0.0]);
        assert_eq!(q[2], [0.8, -0.2, 0.0, 0.0]);
    }
}
