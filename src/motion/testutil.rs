//! Test helpers shared by the motion modules' tests.

use super::{Format, Poses, ReadOptions};

/// A smooth, drifting and turning synthetic motion: every feature a different sinusoid of time
/// (rotations from arbitrary 6D vectors, a drifting root), decoded raw.
pub(crate) fn sinusoid_motion(format: Format, frames: usize) -> Poses {
    let dim = format.feature_dim();
    let x: Vec<f32> = (0..frames * dim)
        .map(|i| {
            let (t, c) = ((i / dim) as f32, (i % dim) as f32);
            (0.3 * c + 0.05 * t * (1.0 + c % 3.0)).sin() * 0.8
                + if c % 6.0 == 0.0 { 0.5 } else { 0.0 }
        })
        .collect();
    Poses::decode(format, &x, frames, &ReadOptions::default()).unwrap()
}
