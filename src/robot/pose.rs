//! A rigid placement ([`Pose`]: rotation matrix + translation, `f64`) and the few operations the
//! robot model needs on it: composition, points, URDF's roll-pitch-yaw, quaternions with their
//! order in the name. Nothing here knows about links or joints.

use crate::motion::rotation::{self, Mat3, Vec3, IDENTITY};

/// A frame placed in its parent's: `x_parent = rotation · x_local + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Row-major, acting on column vectors (as in [`crate::motion::rotation`]).
    pub rotation: Mat3,
    /// Metres.
    pub translation: Vec3,
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    /// No rotation, no translation.
    pub const IDENTITY: Pose = Pose {
        rotation: IDENTITY,
        translation: [0.0; 3],
    };

    /// URDF's `<origin xyz rpy>`: `rpy` is fixed-axis roll, pitch, yaw (about x, then y, then z
    /// of the parent frame), so `R = Rz(yaw) · Ry(pitch) · Rx(roll)`.
    pub fn from_xyz_rpy(xyz: Vec3, rpy: Vec3) -> Pose {
        Pose {
            rotation: rpy_matrix(rpy),
            translation: xyz,
        }
    }

    /// A position and a unit quaternion stored **x, y, z, w** (ROS, Pinocchio, BeyondMimic's and
    /// GMR's files). A non-unit quaternion is normalised.
    pub fn from_position_quat_xyzw(position: Vec3, xyzw: [f64; 4]) -> Pose {
        let [x, y, z, w] = xyzw;
        Pose {
            rotation: rotation::quat_to_matrix(&[w, x, y, z]),
            translation: position,
        }
    }

    /// The rotation as a unit quaternion stored **x, y, z, w**, with w ≥ 0.
    pub fn quat_xyzw(&self) -> [f64; 4] {
        let [w, x, y, z] = rotation::to_quat(&self.rotation);
        [x, y, z, w]
    }

    /// `self · other`: `other` is placed in `self`'s frame.
    pub fn then(&self, other: &Pose) -> Pose {
        Pose {
            rotation: rotation::mul(&self.rotation, &other.rotation),
            translation: self.point(&other.translation),
        }
    }

    /// The inverse placement (`self.inverse().then(self)` is the identity).
    pub fn inverse(&self) -> Pose {
        let rotation = rotation::transpose(&self.rotation);
        let t = rotation::apply(&rotation, &self.translation);
        Pose {
            rotation,
            translation: [-t[0], -t[1], -t[2]],
        }
    }

    /// A point given in this frame, in the parent's.
    pub fn point(&self, p: &Vec3) -> Vec3 {
        rotation::add(&rotation::apply(&self.rotation, p), &self.translation)
    }
}

/// `Rz(yaw) · Ry(pitch) · Rx(roll)`, written out (no products of three matrices per joint).
pub fn rpy_matrix([roll, pitch, yaw]: Vec3) -> Mat3 {
    let (sr, cr) = roll.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy) = yaw.sin_cos();
    [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
}

/// The rotation by `angle` about the **unit** `axis` (Rodrigues), without
/// [`rotation::axis_angle`]'s normalisation: joint axes are normalised once, when the robot is
/// read, and this runs once per joint per forward pass.
pub fn unit_axis_rotation(axis: &Vec3, angle: f64) -> Mat3 {
    let [x, y, z] = *axis;
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [
        [c + t * x * x, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, c + t * z * z],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Mat3, b: &Mat3) -> bool {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(x, y)| (x - y).abs() < 1e-14)
    }

    #[test]
    fn rpy_is_z_then_y_then_x_applied_right_to_left() {
        let (r, p, y) = (0.3, -0.7, 1.9);
        let want = rotation::mul(
            &rotation::axis_angle(&[0.0, 0.0, 1.0], y),
            &rotation::mul(
                &rotation::axis_angle(&[0.0, 1.0, 0.0], p),
                &rotation::axis_angle(&[1.0, 0.0, 0.0], r),
            ),
        );
        assert!(close(&rpy_matrix([r, p, y]), &want));
    }

    #[test]
    fn inverse_undoes_and_quaternions_round_trip() {
        let a = Pose::from_xyz_rpy([0.1, -2.0, 0.5], [0.4, 0.2, -1.1]);
        let id = a.inverse().then(&a);
        assert!(close(&id.rotation, &IDENTITY));
        assert!(id.translation.iter().all(|v| v.abs() < 1e-14));
        let b = Pose::from_position_quat_xyzw(a.translation, a.quat_xyzw());
        assert!(close(&a.rotation, &b.rotation));
    }
}
