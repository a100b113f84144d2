//! Coordinate conventions: which axis is up, which way a character faces, handedness and unit,
//! for each engine preset and for each format's own (`native`) frame, and the change of frame
//! that takes decoded poses into a convention.
//!
//! A frame is described by where a standing character's **up**, **forward** (the way it faces)
//! and **left** point. Converting keeps those meanings: up stays up, forward stays forward, left
//! stays left. The matrix `M = A_to · A_fromᵀ` (columns of `A` = up, forward, left) is a signed
//! permutation; when handedness changes it is a reflection (det −1), and rotations are converted
//! as `R' = M R M⁻¹` so they stay proper (det +1) while positions become `p' = s·M p` (`s` = 100
//! for centimetres).
//!
//! Each format has two frames: the **world** frame its positions and root are in, and the **body**
//! frame its rest skeleton and joint rotations are in (a standing, unturned character). For
//! `humanml263` they are the same. For `smpl24_6d` the world is AMASS's Z-up frame while SMPL's
//! rest body is Y-up: the data's root rotation contains the +90° X tilt `T` that stands the body
//! up (Rx(+90°) maps y→z, z→−y, so the body's forward +Z becomes world −Y: the native forward is
//! −Y, and left stays +X). `native` keeps the data exactly as the model gives it (world and body
//! frames as they are, so a `smpl24_6d` rest pose lies along world +Y); every engine preset puts
//! both frames into the preset's axes, so the rest pose stands upright facing the preset's
//! forward and the tilt disappears from the root rotation: with `W` the world change and `C` the
//! body change, `root' = W·root·Cᵀ`, `local'(j) = C·local(j)·Cᵀ` for j > 0, `global' = W·global·Cᵀ`,
//! `offset' = s·C·offset`, `p' = s·W·p`.

use std::fmt;
use std::str::FromStr;

use super::format::Format;
use super::rotation::{self, Mat3, Vec3};
use crate::error::{invalid_arg, Error, Result};

/// A named coordinate convention, with a stable integer value for the C ABI.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum Convention {
    /// The format's own frame, data untouched (see the module doc).
    Native = 0,
    /// Left-handed, +Y up, +Z forward, +X right, metres.
    Unity = 1,
    /// Left-handed, +Z up, +X forward, +Y right, centimetres.
    Unreal = 2,
    /// Right-handed, +Z up, +X forward, +Y left, metres (REP 103).
    Ros = 3,
    /// Right-handed, +Z up, −Y forward, +X left, metres.
    Blender = 4,
    /// Right-handed, +Y up, +Z forward, +X left, metres.
    Gltf = 5,
}

/// A signed coordinate axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Axis {
    /// `+x`: `[1, 0, 0]`.
    PosX,
    /// `-x`: `[-1, 0, 0]`.
    NegX,
    /// `+y`: `[0, 1, 0]`.
    PosY,
    /// `-y`: `[0, -1, 0]`.
    NegY,
    /// `+z`: `[0, 0, 1]`.
    PosZ,
    /// `-z`: `[0, 0, -1]`.
    NegZ,
}

/// Which hand's rule the axes follow.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Handedness {
    /// Left = up × forward (ROS, Blender, glTF, and both formats' native frames).
    Right,
    /// Left = forward × up (Unity, Unreal): converting to or from it mirrors positions.
    Left,
}

/// The length unit of positions and offsets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unit {
    /// Metres: every convention but Unreal, and the models' own output.
    Metre,
    /// Centimetres (Unreal): positions and offsets are multiplied by 100.
    Centimetre,
}

/// Where a standing, unturned character's up, forward and left point, and the length unit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frame {
    /// The axis pointing up, out of the ground a character stands on.
    pub up: Axis,
    /// The axis a standing, unturned character faces.
    pub forward: Axis,
    /// The axis to that character's left (its own left hand's side).
    pub left: Axis,
    /// The length unit of positions and offsets.
    pub unit: Unit,
}

impl Axis {
    /// The unit vector along the axis, with its sign.
    pub fn vector(self) -> Vec3 {
        match self {
            Axis::PosX => [1.0, 0.0, 0.0],
            Axis::NegX => [-1.0, 0.0, 0.0],
            Axis::PosY => [0.0, 1.0, 0.0],
            Axis::NegY => [0.0, -1.0, 0.0],
            Axis::PosZ => [0.0, 0.0, 1.0],
            Axis::NegZ => [0.0, 0.0, -1.0],
        }
    }

    /// `+x`, `-y`, …
    pub fn name(self) -> &'static str {
        match self {
            Axis::PosX => "+x",
            Axis::NegX => "-x",
            Axis::PosY => "+y",
            Axis::NegY => "-y",
            Axis::PosZ => "+z",
            Axis::NegZ => "-z",
        }
    }
}

impl Handedness {
    /// `right` or `left`, as the JSON export's `handedness` field writes it.
    pub fn name(self) -> &'static str {
        match self {
            Handedness::Right => "right",
            Handedness::Left => "left",
        }
    }
}

impl Unit {
    /// Metres → this unit.
    pub fn scale(self) -> f64 {
        match self {
            Unit::Metre => 1.0,
            Unit::Centimetre => 100.0,
        }
    }

    /// `m` or `cm`.
    pub fn symbol(self) -> &'static str {
        match self {
            Unit::Metre => "m",
            Unit::Centimetre => "cm",
        }
    }
}

impl Frame {
    const fn new(up: Axis, forward: Axis, left: Axis, unit: Unit) -> Frame {
        Frame {
            up,
            forward,
            left,
            unit,
        }
    }

    /// The matrix whose columns are up, forward and left.
    fn basis(&self) -> Mat3 {
        let (u, f, l) = (self.up.vector(), self.forward.vector(), self.left.vector());
        [[u[0], f[0], l[0]], [u[1], f[1], l[1]], [u[2], f[2], l[2]]]
    }

    /// Right-handed when left = up × forward (det of the basis +1).
    pub fn handedness(&self) -> Handedness {
        if rotation::det(&self.basis()) > 0.0 {
            Handedness::Right
        } else {
            Handedness::Left
        }
    }

    /// The matrix taking coordinates in `self` to coordinates in `to` (same up/forward/left).
    fn change_to(&self, to: &Frame) -> Mat3 {
        rotation::mul(&to.basis(), &rotation::transpose(&self.basis()))
    }
}

/// The body frame of both skeletons: SMPL and HumanML3D rest poses are Y-up, face +Z, left +X.
const BODY: Frame = Frame::new(Axis::PosY, Axis::PosZ, Axis::PosX, Unit::Metre);

impl Convention {
    /// Every convention, in integer order.
    pub const ALL: [Convention; 6] = [
        Convention::Native,
        Convention::Unity,
        Convention::Unreal,
        Convention::Ros,
        Convention::Blender,
        Convention::Gltf,
    ];

    /// The name accepted by `FromStr` and the CLI's `--convention`.
    pub fn name(self) -> &'static str {
        match self {
            Convention::Native => "native",
            Convention::Unity => "unity",
            Convention::Unreal => "unreal",
            Convention::Ros => "ros",
            Convention::Blender => "blender",
            Convention::Gltf => "gltf",
        }
    }

    /// The convention with integer value `v` (the C ABI's enum).
    pub fn from_u32(v: u32) -> Result<Convention> {
        Convention::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown convention {v}"))
    }

    /// The frame positions are given in for `format` (for `native`, the format's world frame).
    pub fn frame(self, format: Format) -> Frame {
        use Axis::*;
        match self {
            Convention::Native => world_frame(format),
            Convention::Unity => Frame::new(PosY, PosZ, NegX, Unit::Metre),
            Convention::Unreal => Frame::new(PosZ, PosX, NegY, Unit::Centimetre),
            Convention::Ros => Frame::new(PosZ, PosX, PosY, Unit::Metre),
            Convention::Blender => Frame::new(PosZ, NegY, PosX, Unit::Metre),
            Convention::Gltf => Frame::new(PosY, PosZ, PosX, Unit::Metre),
        }
    }
}

/// A format's native world frame (see the module doc for smpl24_6d's forward).
fn world_frame(format: Format) -> Frame {
    match format {
        Format::Smpl24Rot6d => Frame::new(Axis::PosZ, Axis::NegY, Axis::PosX, Unit::Metre),
        Format::HumanMl263 => BODY,
    }
}

impl FromStr for Convention {
    type Err = Error;
    fn from_str(s: &str) -> Result<Convention> {
        Convention::ALL.into_iter().find(|c| c.name() == s).ok_or_else(|| {
            invalid_arg!("unknown convention `{s}` (expected native, unity, unreal, ros, blender or gltf)")
        })
    }
}

impl fmt::Display for Convention {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The change of frame from a format's decoded poses to a convention.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Change {
    /// World frame → target (positions, the root's outer side).
    world: Mat3,
    /// Body frame → target (rest offsets, joint rotations).
    body: Mat3,
    scale: f64,
}

impl Change {
    pub(crate) fn new(format: Format, convention: Convention) -> Change {
        if convention == Convention::Native {
            return Change {
                world: rotation::IDENTITY,
                body: rotation::IDENTITY,
                scale: 1.0,
            };
        }
        let to = convention.frame(format);
        Change {
            world: world_frame(format).change_to(&to),
            body: BODY.change_to(&to),
            scale: to.unit.scale(),
        }
    }

    /// `s·W·p` for a position.
    pub(crate) fn position(&self, p: &Vec3) -> Vec3 {
        rotation::apply(&self.world, p).map(|x| x * self.scale)
    }

    /// `s·C·o` for a rest offset.
    pub(crate) fn offset(&self, o: &Vec3) -> Vec3 {
        rotation::apply(&self.body, o).map(|x| x * self.scale)
    }

    /// `W·R·Cᵀ`: a rotation from the body frame into the world (a global rotation, or the root's).
    pub(crate) fn global(&self, r: &Mat3) -> Mat3 {
        rotation::mul(
            &self.world,
            &rotation::mul(r, &rotation::transpose(&self.body)),
        )
    }

    /// `C·R·Cᵀ`: a parent-relative rotation of a non-root joint.
    pub(crate) fn local(&self, r: &Mat3) -> Mat3 {
        rotation::mul(
            &self.body,
            &rotation::mul(r, &rotation::transpose(&self.body)),
        )
    }

    // The inverses read references given in a convention back into the native frame. `W` and
    // `C` are signed permutations, so their transposes undo them exactly (no rounding).

    /// `Wᵀ·p / s`: undoes [`Change::position`].
    pub(crate) fn inverse_position(&self, p: &Vec3) -> Vec3 {
        rotation::apply(&rotation::transpose(&self.world), p).map(|x| x / self.scale)
    }

    /// `Wᵀ·R·C`: undoes [`Change::global`].
    pub(crate) fn inverse_global(&self, r: &Mat3) -> Mat3 {
        rotation::mul(
            &rotation::transpose(&self.world),
            &rotation::mul(r, &self.body),
        )
    }

    /// `Cᵀ·R·C`: undoes [`Change::local`].
    pub(crate) fn inverse_local(&self, r: &Mat3) -> Mat3 {
        rotation::mul(
            &rotation::transpose(&self.body),
            &rotation::mul(r, &self.body),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_integers_and_handedness() {
        for (i, c) in Convention::ALL.into_iter().enumerate() {
            assert_eq!(c as u32, i as u32);
            assert_eq!(Convention::from_u32(i as u32).unwrap(), c);
            assert_eq!(c.name().parse::<Convention>().unwrap(), c);
        }
        assert!("maya"
            .parse::<Convention>()
            .unwrap_err()
            .to_string()
            .contains("unknown convention `maya`"));
        assert!(Convention::from_u32(6).is_err());
        let hand = |c: Convention| c.frame(Format::Smpl24Rot6d).handedness();
        assert_eq!(hand(Convention::Unity), Handedness::Left);
        assert_eq!(hand(Convention::Unreal), Handedness::Left);
        assert_eq!(hand(Convention::Ros), Handedness::Right);
        assert_eq!(hand(Convention::Blender), Handedness::Right);
        assert_eq!(hand(Convention::Gltf), Handedness::Right);
        assert_eq!(hand(Convention::Native), Handedness::Right);
        assert_eq!(Convention::Native.frame(Format::HumanMl263).up, Axis::PosY);
        assert_eq!(
            Convention::Native.frame(Format::Smpl24Rot6d).forward,
            Axis::NegY
        );
    }

    #[test]
    fn conversions_keep_rotations_proper() {
        let r = rotation::axis_angle(&[0.3, -1.0, 0.5], 1.2);
        for f in Format::ALL {
            for c in Convention::ALL {
                let ch = Change::new(f, c);
                let want = if c.frame(f).handedness() == Handedness::Left {
                    -1.0
                } else {
                    1.0
                };
                assert_eq!(rotation::det(&ch.world), want, "{f} {c}");
                assert_eq!(rotation::det(&ch.body), want, "{f} {c}");
                assert!((rotation::det(&ch.global(&r)) - 1.0).abs() < 1e-12);
                assert!((rotation::det(&ch.local(&r)) - 1.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn inverses_undo_every_change_exactly() {
        let r = rotation::axis_angle(&[0.3, -1.0, 0.5], 1.2);
        let p = [0.25, -1.5, 3.0];
        for f in Format::ALL {
            for c in Convention::ALL {
                let ch = Change::new(f, c);
                // Signed permutations and a power-of-ten scale of exact binary values: equal,
                // not merely close (0.25, 1.5 and 3 survive ×100 and ÷100 exactly).
                assert_eq!(ch.inverse_position(&ch.position(&p)), p, "{f} {c}");
                assert_eq!(ch.inverse_global(&ch.global(&r)), r, "{f} {c}");
                assert_eq!(ch.inverse_local(&ch.local(&r)), r, "{f} {c}");
            }
        }
    }

    #[test]
    fn smpl_tilt_is_the_difference_between_world_and_body() {
        // For every preset W·T = C, T = Rx(+90°): the tilt that stands SMPL's body up in Z-up.
        let tilt = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        for c in &Convention::ALL[1..] {
            let ch = Change::new(Format::Smpl24Rot6d, *c);
            let wt = rotation::mul(&ch.world, &tilt);
            for (a, b) in wt.iter().flatten().zip(ch.body.iter().flatten()) {
                assert!((a - b).abs() < 1e-15, "{c}");
            }
        }
    }
}
