//! Loops made at generation time ([`Cycle`]): a clip of `frames` frames whose end flows into its
//! start, generated with the family's own editing, as in-betweening is.
//!
//! 1. A first generation of `frames + lead` frames from the prompt: its frame `frames` is where
//!    the model takes the motion after one cycle (heading and horizontal position: the loop's
//!    root motion `T`, so a walking loop walks on).
//! 2. An edit of the same length that keeps the first `lead` frames and, after them, frames
//!    `frames..frames + lead` set to `T` of the first `lead` frames: the model generates the middle
//!    so that the end of the cycle runs into the start of the next one (the kept frames pasted
//!    exactly, the seams blended by the edit).
//! 3. The result's first `frames + 1` frames: the cycle and the next cycle's first frame, which
//!    [`crate::motion::Finish::wrap_to_last`] uses as the exact target of the wrap's correction
//!    (`motion::looping`) and then drops.
//!
//! `T` is a turn about the up axis and a horizontal shift of the root channels for formats with
//! an absolute root (smpl24_6d); humanml263's features are relative to the root's heading and
//! position, so copying the frames continues the path by itself. Latent families (MLD, MoLA)
//! cannot keep frames of a reference; for them, and for prompts given as time stages, a loop is
//! the post-processing wrap alone.
//!
//! [`Cycle`]: crate::cycle::Cycle

use crate::error::{invalid_arg, Result};
use crate::models::Model;
use crate::motion::{rotation, Format, Mask};
use crate::session::{Session, SessionParams};

/// Seconds of motion kept on either side of the wrap while the middle is generated: enough for
/// the denoiser to see where the start goes (a step of walking), short enough to leave most of
/// a 2–10 s clip free.
pub const LEAD_SECONDS: f64 = 0.5;

/// A loop's plan: the cycle's length and the frames kept on either side of the wrap.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cycle {
    frames: usize,
    lead: usize,
}

impl Cycle {
    /// The plan for a `frames`-frame loop of `model`; an error when the model cannot generate
    /// the lead frames past the cycle, or the cycle is too short to loop.
    pub fn new(model: &Model, frames: usize) -> Result<Cycle> {
        let fps = model.config().motion.fps as f64;
        let lead = ((LEAD_SECONDS * fps).round() as usize).max(2);
        if frames < 4 * lead {
            return Err(invalid_arg!(
                "a loop needs at least {} frames ({lead} kept on each side of the wrap and as many \
                 generated between), got {frames}",
                4 * lead
            ));
        }
        let max = model.max_frames();
        if frames + lead > max {
            return Err(invalid_arg!(
                "a loop of {frames} frames generates {} ({lead} past the cycle, to see where it \
                 goes), more than this model's {max}: ask for at most {} frames",
                frames + lead,
                max - lead
            ));
        }
        Ok(Cycle { frames, lead })
    }

    /// The cycle's length in frames.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Frames kept on either side of the wrap.
    pub fn lead(&self) -> usize {
        self.lead
    }

    /// The session parameters of both generations: `params` with `frames + lead` frames.
    pub fn params(&self, params: &SessionParams) -> SessionParams {
        SessionParams {
            frames: Some(self.frames + self.lead),
            ..params.clone()
        }
    }

    /// Sets up `session` (made with [`Cycle::params`], prompt not needed yet) to edit the first
    /// generation's features `first` into a loop.
    pub fn edit(&self, session: &mut Session, first: &[f32]) -> Result<()> {
        let model = session.model().clone();
        let dim = model.motion_dim();
        let total = self.frames + self.lead;
        if first.len() != total * dim {
            return Err(invalid_arg!(
                "the first generation has {} values, the loop needs {total} frames of {dim}",
                first.len()
            ));
        }
        let format = model.motion_format();
        let mut reference = first.to_vec();
        let (n, lead) = (self.frames, self.lead);
        reference.copy_within(0..lead * dim, n * dim);
        if format == Format::Smpl24Rot6d {
            let turn = root_move(&model, &first[..dim], &first[n * dim..(n + 1) * dim]);
            in_root_units(&model, &mut reference[n * dim..], |rows| {
                turn.apply(rows, dim)
            });
        }
        let mut mask = Mask::new(format, total)?;
        mask.keep_frames(0, lead)?;
        mask.keep_frames(n, total)?;
        session.set_reference(&reference)?;
        session.set_mask_from(&mask)
    }

    /// The loop's frames from the edited generation's features: the cycle and the next cycle's
    /// first frame (`frames + 1` rows).
    pub fn result<'a>(&self, edited: &'a [f32], dim: usize) -> Result<&'a [f32]> {
        let want = (self.frames + 1) * dim;
        edited.get(..want).ok_or_else(|| {
            invalid_arg!(
                "the edited generation has {} values, fewer than the {want} of a loop",
                edited.len()
            )
        })
    }
}

/// Runs `f` on smpl24_6d `rows` with their root channels (0..9: translation and root rotation
/// rows) in the format's own units: a normalised model's features are de-normalised around it,
/// since a turn mixes channels that the statistics scale differently.
pub(crate) fn in_root_units(model: &Model, rows: &mut [f32], f: impl FnOnce(&mut [f32])) {
    const ROOT: usize = 9;
    let dim = model.motion_dim();
    let opts = model.read_options(0.0, true);
    let Some(norm) = opts.normalization else {
        return f(rows);
    };
    let (mean, std) = (&norm.mean[..ROOT], &norm.std[..ROOT]);
    for row in rows.chunks_exact_mut(dim) {
        for c in 0..ROOT {
            row[c] = (row[c] as f64 * std[c] as f64 + mean[c] as f64) as f32;
        }
    }
    f(rows);
    for row in rows.chunks_exact_mut(dim) {
        for c in 0..ROOT {
            row[c] = ((row[c] as f64 - mean[c] as f64) / std[c] as f64) as f32;
        }
    }
}

/// The [`RootMove`] taking smpl24_6d row `a`'s root onto row `b`'s, both in model space
/// (read in the format's units, [`in_root_units`]).
pub(crate) fn root_move(model: &Model, a: &[f32], b: &[f32]) -> RootMove {
    let mut rows = [a, b].concat();
    let dim = a.len();
    let mut turn = None;
    in_root_units(model, &mut rows, |r| {
        turn = Some(RootMove::between(&r[..dim], &r[dim..]))
    });
    turn.expect("in_root_units runs its closure")
}

/// A turn about the world up axis (Z for smpl24_6d) and a horizontal shift of the root channels
/// (translation 0..3, root rotation rows 3..9 in 6D ROW form): the move taking one frame's root
/// onto another's heading and horizontal position.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RootMove {
    cos: f64,
    sin: f64,
    from: [f64; 2],
    to: [f64; 2],
}

impl RootMove {
    /// The move taking `a`'s root to `b`'s (rows of smpl24_6d features).
    pub(crate) fn between(a: &[f32], b: &[f32]) -> RootMove {
        // Forward = the decoded root rotation's third column (body +Z); its horizontal part is
        // (R[0][2], R[1][2]).
        let heading = |r: &[f32]| {
            let m = root_rotation(r);
            m[1][2].atan2(m[0][2])
        };
        let (sin, cos) = (heading(b) - heading(a)).sin_cos();
        RootMove {
            cos,
            sin,
            from: [a[0] as f64, a[1] as f64],
            to: [b[0] as f64, b[1] as f64],
        }
    }

    /// Applies the move to every row of `rows`. The root rotation is decoded first (6D → matrix,
    /// as the decoder does) and written back as the 6D of `Rz·R`: mixing the raw 6D rows would
    /// not commute with the decoder's Gram–Schmidt when a model's 6D output is not orthonormal.
    pub(crate) fn apply(&self, rows: &mut [f32], dim: usize) {
        let (c, s) = (self.cos, self.sin);
        let turn = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        for row in rows.chunks_exact_mut(dim) {
            let (x, y) = (row[0] as f64 - self.from[0], row[1] as f64 - self.from[1]);
            row[0] = (c * x - s * y + self.to[0]) as f32;
            row[1] = (s * x + c * y + self.to[1]) as f32;
            let r = rotation::mul(&turn, &root_rotation(row));
            for (v, d) in row[3..9].iter_mut().zip(rotation::to_6d_rows(&r)) {
                *v = d as f32;
            }
        }
    }
}

/// The root rotation of a smpl24_6d row, decoded as the decoder does.
fn root_rotation(row: &[f32]) -> crate::motion::rotation::Mat3 {
    let d: [f64; 6] = std::array::from_fn(|i| row[3 + i] as f64);
    rotation::from_6d_rows(&d)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smpl24_6d row standing at `(x, y)` and facing `yaw` about Z from the native forward.
    fn row(x: f32, y: f32, yaw: f64) -> Vec<f32> {
        let tilt = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let r = rotation::mul(&rotation::axis_angle(&[0.0, 0.0, 1.0], yaw), &tilt);
        let mut v = vec![x, y, 0.9];
        v.extend(rotation::to_6d_rows(&r).map(|c| c as f32));
        v.extend([0.5; 138]);
        v
    }

    #[test]
    fn the_root_move_takes_one_root_onto_the_other_and_carries_the_rest_along() {
        let a = row(0.3, -0.2, 0.4);
        let b = row(2.0, 1.0, 1.3);
        let m = RootMove::between(&a, &b);
        let mut moved = a.clone();
        m.apply(&mut moved, 147);
        for (u, v) in moved.iter().zip(&b).take(9) {
            assert!((u - v).abs() < 1e-6, "{moved:?}");
        }
        // A point 1 m ahead of `a` (its forward) lands 1 m ahead of `b`.
        let mut ahead = a.clone();
        let fwd = [a[5], a[8]];
        ahead[0] += fwd[0];
        ahead[1] += fwd[1];
        m.apply(&mut ahead, 147);
        assert!((ahead[0] - (b[0] + b[5])).abs() < 1e-6 && (ahead[1] - (b[1] + b[8])).abs() < 1e-6);
        // Joint rotations are untouched.
        assert_eq!(moved[9..], a[9..]);
    }
}
