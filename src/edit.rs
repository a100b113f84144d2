//! Editing a reference motion through a keep-mask: which algorithm imposes the kept values during
//! sampling (each as its paper's official code does: docs/official/flame.md#editing,
//! docs/official/mdm.md#editing, docs/official/motionfm.md#editing), and the final paste with
//! blended seams.
//!
//! Everything here works on model-space features, frame-major `[frames, dim]`, with one keep
//! flag per value (`true` = keep the reference).

use crate::error::{invalid_arg, Error, Result};

/// How a session imposes the kept reference values while sampling.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EditMethod {
    /// The model family's own method: FLAME files use [`EditMethod::NoisedReference`], MDM files
    /// [`EditMethod::ReplaceX0`], flow-matching files [`EditMethod::RewriteTrajectory`].
    #[default]
    Auto,
    /// FLAME: before every step, diffuse the reference to the step's noise level (fresh noise)
    /// and overwrite the kept values of x_t. Diffusion models only.
    NoisedReference,
    /// MDM: after guidance, overwrite the kept values of the predicted clean motion x̂0 with the
    /// reference. Diffusion models only.
    ReplaceX0,
    /// Motion Flow Matching: while `k / N ≤ edit_till`, overwrite the kept values of x with the
    /// straight path `((N − k)·z0 + k·ref) / N` from the initial noise z0 to the reference.
    /// Flow-matching models only.
    RewriteTrajectory,
}

impl EditMethod {
    /// Every method; the index of each is its value in the C ABI (`FlameEditMethod`).
    pub const ALL: [EditMethod; 4] = [
        EditMethod::Auto,
        EditMethod::NoisedReference,
        EditMethod::ReplaceX0,
        EditMethod::RewriteTrajectory,
    ];

    /// The name `FromStr` and the CLI's `--method` take (`auto`, `noised-reference`, ...).
    pub fn name(self) -> &'static str {
        match self {
            EditMethod::Auto => "auto",
            EditMethod::NoisedReference => "noised-reference",
            EditMethod::ReplaceX0 => "replace-x0",
            EditMethod::RewriteTrajectory => "rewrite-trajectory",
        }
    }

    /// The method of C ABI value `v` (its index in [`EditMethod::ALL`]); an error for any other
    /// value.
    pub fn from_u32(v: u32) -> Result<EditMethod> {
        EditMethod::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown edit method {v} (expected 0, 1, 2 or 3)"))
    }
}

impl std::str::FromStr for EditMethod {
    type Err = Error;
    fn from_str(s: &str) -> Result<EditMethod> {
        EditMethod::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                invalid_arg!(
                    "unknown edit method `{s}` (expected auto, noised-reference, replace-x0 or rewrite-trajectory)"
                )
            })
    }
}

/// Editing settings of a session.
#[derive(Clone, Debug, PartialEq)]
pub struct EditParams {
    /// How the kept values are imposed while sampling.
    pub method: EditMethod,
    /// Flow models: the fraction of the steps (from the noise end) during which the trajectory
    /// is rewritten, in [0, 1]. The Motion Flow Matching paper's default is 0.2.
    pub edit_till: f32,
    /// After the last step, copy the kept values of the reference exactly into the result and
    /// blend the seams, so kept frames and joints are the reference bit for bit. Off = the
    /// official behaviour (the kept parts are only as close as the algorithm makes them).
    pub paste: bool,
    /// Frames on each side of a temporal seam over which the paste's offset fades out; 0 pastes
    /// without blending.
    pub seam_frames: usize,
}

impl Default for EditParams {
    fn default() -> EditParams {
        EditParams {
            method: EditMethod::Auto,
            edit_till: 0.2,
            paste: true,
            seam_frames: 4,
        }
    }
}

impl EditParams {
    /// Checks the values (not whether the method suits a model: the session does that).
    pub fn validate(&self) -> Result<()> {
        if !(self.edit_till.is_finite() && (0.0..=1.0).contains(&self.edit_till)) {
            return Err(invalid_arg!(
                "`edit_till` (the share of the steps that rewrite the trajectory) must be between 0 and 1, got {}",
                self.edit_till
            ));
        }
        if self.seam_frames > 1000 {
            return Err(invalid_arg!(
                "`seam_frames` must be between 0 and 1000, got {}",
                self.seam_frames
            ));
        }
        Ok(())
    }
}

/// `x ← x·(¬keep) + r·keep`, value by value.
pub fn impose(x: &mut [f32], reference: &[f32], keep: &[bool]) {
    for ((v, &r), &k) in x.iter_mut().zip(reference).zip(keep) {
        if k {
            *v = r;
        }
    }
}

/// Motion Flow Matching's rewriting target at step `k` of `n`: `((n − k)·z0 + k·ref) / n`, in
/// f32 and in that order (as the official code computes it), for the kept values of `x`.
pub fn impose_flow_path(
    x: &mut [f32],
    z0: &[f32],
    reference: &[f32],
    keep: &[bool],
    k: usize,
    n: usize,
) {
    let (a, b, d) = ((n - k) as f32, k as f32, n as f32);
    for (((v, &z), &r), &kp) in x.iter_mut().zip(z0).zip(reference).zip(keep) {
        if kp {
            *v = (a * z + b * r) / d;
        }
    }
}

/// Whether Motion Flow Matching rewrites at step `k` of `n`: `k / n ≤ edit_till`, compared in
/// f64 as the official (Python) loop does.
pub fn flow_rewrites(k: usize, n: usize, edit_till: f32) -> bool {
    (k as f64) / (n as f64) <= edit_till as f64
}

/// The final paste: kept values become the reference exactly; in every channel, the frames
/// next to a kept run get the offset (reference − generated) at that run's edge, faded out
/// over `seam` frames with a raised cosine (weight 1 at the edge, 0 beyond `seam` frames, zero
/// slope at both ends), so the result is continuous at the seams and unchanged far from them.
pub fn paste_with_seams(
    x: &mut [f32],
    reference: &[f32],
    keep: &[bool],
    frames: usize,
    dim: usize,
    seam: usize,
) {
    debug_assert!(x.len() == frames * dim && reference.len() == x.len() && keep.len() == x.len());
    let fade = |d: usize| -> f32 {
        if d > seam {
            0.0
        } else {
            let a = std::f64::consts::PI * d as f64 / (seam + 1) as f64;
            (0.5 * (1.0 + a.cos())) as f32
        }
    };
    // In place: a run's left offset is taken from its kept neighbour before that frame is
    // overwritten, and its right neighbour is overwritten only after the run.
    for c in 0..dim {
        let at = |f: usize| f * dim + c;
        let mut left = None;
        let mut f = 0;
        while f < frames {
            if keep[at(f)] {
                left = Some(reference[at(f)] - x[at(f)]);
                x[at(f)] = reference[at(f)];
                f += 1;
                continue;
            }
            // A run of generated frames [f, end).
            let end = (f..frames).find(|&g| keep[at(g)]).unwrap_or(frames);
            let right = (end < frames).then(|| reference[at(end)] - x[at(end)]);
            for g in f..end {
                let mut v = x[at(g)];
                if let Some(dl) = left {
                    v += fade(g + 1 - f) * dl;
                }
                if let Some(dr) = right {
                    v += fade(end - g) * dr;
                }
                x[at(g)] = v;
            }
            f = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for (i, m) in EditMethod::ALL.into_iter().enumerate() {
            assert_eq!(m.name().parse::<EditMethod>().unwrap(), m);
            assert_eq!(EditMethod::from_u32(i as u32).unwrap(), m);
        }
        assert!("x0".parse::<EditMethod>().is_err());
        assert!(EditMethod::from_u32(4).is_err());
    }

    #[test]
    fn params_are_checked() {
        assert!(EditParams::default().validate().is_ok());
        for bad in [-0.1, 1.5, f32::NAN] {
            let p = EditParams {
                edit_till: bad,
                ..Default::default()
            };
            assert!(p.validate().is_err(), "{bad}");
        }
    }

    #[test]
    fn flow_path_in_f32_order() {
        // ((10 − 3)·z + 3·r)/10 with z = 0.1, r = 1: 7·0.1 = 0.7 (f32), + 3 = 3.7, / 10.
        let mut x = [5.0, 5.0];
        impose_flow_path(&mut x, &[0.1, 0.1], &[1.0, 1.0], &[true, false], 3, 10);
        assert_eq!(x[0], (7.0f32 * 0.1f32 + 3.0f32) / 10.0f32);
        assert_eq!(x[1], 5.0);
        assert!(flow_rewrites(2, 10, 0.2));
        assert!(!flow_rewrites(3, 10, 0.2));
        assert!(flow_rewrites(0, 10, 0.0));
    }

    #[test]
    fn paste_by_hand() {
        // One channel, frames 0..2 kept, 2..8 generated, seam 2: fade(1) = 0.75, fade(2) = 0.25.
        let frames = 8;
        let reference: Vec<f32> = (0..frames).map(|f| f as f32).collect();
        let mut x = vec![10.0f32; frames];
        let keep: Vec<bool> = (0..frames).map(|f| f < 2).collect();
        paste_with_seams(&mut x, &reference, &keep, frames, 1, 2);
        // Offset at the edge (frame 1): 1 − 10 = −9.
        assert_eq!(&x[..2], &[0.0, 1.0]);
        assert!((x[2] - (10.0 - 0.75 * 9.0)).abs() < 1e-6);
        assert!((x[3] - (10.0 - 0.25 * 9.0)).abs() < 1e-6);
        assert_eq!(&x[4..], &[10.0; 4]);
    }

    #[test]
    fn paste_keeps_exact_values_and_makes_seams_continuous() {
        // Two channels; the generated motion is smooth but offset from the reference; frames
        // [0, 10) and [30, 40) kept (an in-between), channel 1 also kept everywhere.
        let (frames, dim) = (40, 2);
        let reference: Vec<f32> = (0..frames * dim)
            .map(|i| ((i / dim) as f32 * 0.1).sin())
            .collect();
        let generated: Vec<f32> = (0..frames * dim)
            .map(|i| ((i / dim) as f32 * 0.1).sin() + 0.5 + 0.01 * (i / dim) as f32)
            .collect();
        let keep: Vec<bool> = (0..frames * dim)
            .map(|i| i % dim == 1 || !(10..30).contains(&(i / dim)))
            .collect();
        let mut x = generated.clone();
        paste_with_seams(&mut x, &reference, &keep, frames, dim, 4);
        for i in 0..x.len() {
            if keep[i] {
                assert_eq!(x[i].to_bits(), reference[i].to_bits());
            }
        }
        let vel = |v: &[f32], f: usize| (v[(f + 1) * dim] - v[f * dim]).abs();
        let kept_max = (0..frames - 1)
            .filter(|&f| keep[f * dim] && keep[(f + 1) * dim])
            .map(|f| vel(&reference, f))
            .fold(0.0f32, f32::max);
        let gen_max = (10..29).map(|f| vel(&generated, f)).fold(0.0f32, f32::max);
        // The offsets at the seams (0.5 + 0.01·f: 0.59 at frame 9, 0.8 at frame 30) are spread
        // over the 4 seam frames: every step stays below the larger of the kept and generated
        // parts' steps plus the raised cosine's steepest share (0.31) of the offset.
        let offset = [9, 30]
            .iter()
            .map(|&f| (generated[f * dim] - reference[f * dim]).abs())
            .fold(0.0f32, f32::max);
        for f in [9, 10, 11, 12, 26, 27, 28, 29] {
            assert!(
                vel(&x, f) <= kept_max.max(gen_max) + 0.32 * offset,
                "frame {f}: {} vs {kept_max}",
                vel(&x, f)
            );
        }
        // Without blending the seam is a 0.5 jump.
        let mut raw = generated.clone();
        paste_with_seams(&mut raw, &reference, &keep, frames, dim, 0);
        assert!(vel(&raw, 9) > 0.45);
        // Far from the seams the generated values are untouched.
        assert_eq!(x[20 * dim], generated[20 * dim]);
    }
}
