//! The motion formats a model file can declare (`config.motion.format`): their feature widths,
//! frame rates, skeletons, and the mean/std a normalised format is de-normalised with.

use std::fmt;
use std::str::FromStr;

use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Error, Result};

/// A feature layout, with a stable integer value for the C ABI.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum Format {
    /// `smpl24_6d` — FLAME: 147 = root translation (AMASS's Z-up world, metres) + 24 SMPL joints
    /// × 6D local rotation in pytorch3d's ROW convention; 20 fps; not normalised.
    Smpl24Rot6d = 0,
    /// `humanml263` — HumanML3D: 263 = root yaw velocity, root planar velocity, root height, 21
    /// root-relative joint positions, 21 cont6d (COLUMN convention) rotations, 22 joint velocities,
    /// 4 foot contacts; Y-up, metres, 20 fps; normalised by the model's mean/std.
    HumanMl263 = 1,
}

impl Format {
    /// Every format, in integer order.
    pub const ALL: [Format; 2] = [Format::Smpl24Rot6d, Format::HumanMl263];

    /// The name used in model files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Format::Smpl24Rot6d => "smpl24_6d",
            Format::HumanMl263 => "humanml263",
        }
    }

    /// The format with integer value `v` (the C ABI's enum).
    pub fn from_u32(v: u32) -> Result<Format> {
        Format::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown motion format {v}"))
    }

    /// Features per frame.
    pub fn feature_dim(self) -> usize {
        match self {
            Format::Smpl24Rot6d => 147,
            Format::HumanMl263 => 263,
        }
    }

    /// The frame rate of the data the format was defined on (both are resampled to 20 fps).
    pub fn fps(self) -> f32 {
        20.0
    }

    /// The skeleton the format's poses are given on.
    pub fn skeleton(self) -> &'static Skeleton {
        match self {
            Format::Smpl24Rot6d => Skeleton::smpl24(),
            Format::HumanMl263 => Skeleton::humanml22(),
        }
    }

    /// Whether models of this format work on z-normalised features (their model files carry
    /// `motion.mean` / `motion.std`): HumanML3D's are, FLAME's are not
    /// (docs/official/flame.md#motion-representation, docs/official/mdm.md#normalisation).
    pub fn is_normalized(self) -> bool {
        matches!(self, Format::HumanMl263)
    }

    /// Whether the features carry foot contacts.
    pub fn has_foot_contacts(self) -> bool {
        matches!(self, Format::HumanMl263)
    }

    /// Whether the decoded joint positions are the forward kinematics of the decoded rotations
    /// on the rest skeleton (`smpl24_6d`); `humanml263` decodes its positions from their own
    /// features, which its rotations only approximate.
    pub fn positions_are_kinematic(self) -> bool {
        matches!(self, Format::Smpl24Rot6d)
    }
}

impl FromStr for Format {
    type Err = Error;
    fn from_str(s: &str) -> Result<Format> {
        Format::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| {
                invalid_arg!("unknown motion format `{s}` (expected smpl24_6d or humanml263)")
            })
    }
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The per-feature statistics a model was trained on: features are de-normalised as
/// `x · std + mean` (in `f64`) before anything else. HumanML3D models carry them as the model
/// file's `motion.mean` / `motion.std` tensors; FLAME's features are not normalised.
#[derive(Clone, Copy, Debug)]
pub struct Normalization<'a> {
    /// Per-feature mean, one value per feature of a frame (263 for humanml263).
    pub mean: &'a [f32],
    /// Per-feature standard deviation, as long as `mean`; every value finite and non-zero.
    pub std: &'a [f32],
}

impl Normalization<'_> {
    /// `(x − mean) / std` in place, frame by frame (in `f64`, the inverse of de-normalising):
    /// how features in the format's own units enter a normalised model's space.
    pub fn normalize(&self, x: &mut [f32]) -> crate::error::Result<()> {
        let dim = self.mean.len();
        if dim == 0 || self.std.len() != dim || !x.len().is_multiple_of(dim) {
            return Err(crate::error::invalid_arg!(
                "cannot normalise {} values with {} means and {} stds",
                x.len(),
                dim,
                self.std.len()
            ));
        }
        if let Some(c) = self.std.iter().position(|s| !(s.is_finite() && *s != 0.0)) {
            return Err(crate::error::invalid_arg!(
                "normalisation std at channel {c} is zero or not finite"
            ));
        }
        for row in x.chunks_exact_mut(dim) {
            for ((v, &m), &s) in row.iter_mut().zip(self.mean).zip(self.std) {
                *v = ((*v as f64 - m as f64) / s as f64) as f32;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_integers_are_stable() {
        for (i, f) in Format::ALL.into_iter().enumerate() {
            assert_eq!(f as u32, i as u32);
            assert_eq!(Format::from_u32(i as u32).unwrap(), f);
            assert_eq!(f.name().parse::<Format>().unwrap(), f);
        }
        assert_eq!(Format::Smpl24Rot6d as u32, 0);
        assert_eq!(Format::HumanMl263 as u32, 1);
        assert!(Format::from_u32(2).is_err());
        let e = "bvh".parse::<Format>().unwrap_err().to_string();
        assert!(e.contains("unknown motion format `bvh`"), "{e}");
        assert_eq!(Format::Smpl24Rot6d.feature_dim(), 3 + 24 * 6);
        assert_eq!(
            Format::HumanMl263.feature_dim(),
            4 + 21 * 3 + 21 * 6 + 22 * 3 + 4
        );
    }
}
