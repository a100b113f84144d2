//! AMASS-style SMPL parameters ([`Amass`]) from decoded poses, written as the `.npz` files
//! robot-learning pipelines read (GMR, PHC, human2humanoid). Nothing here runs a body model or
//! reads `.npz` files.
//!
//! # What AMASS holds (nghorbani/amass, `notebooks/01-AMASS_Visualization.ipynb`; the SMPL-X
//! keys as AMASS's SMPL-X release `*_stageii.npz` has them; `poses`' SMPL-X order is smplx's
//! `full_pose`, vchoutas/smplx `smplx/body_models.py` `SMPLX.forward`)
//!
//! - Axis-angle rotations in radians, parent-relative; the root's (`root_orient`) is global:
//!   it takes SMPL's Y-up body frame into AMASS's Z-up world, so a standing body's root carries
//!   the +90° X tilt (`root_orient ≈ (π/2, 0, 0)` for a body facing −Y).
//! - `trans`: SMPL puts the pelvis joint at `J_pelvis(betas) + trans` whatever `root_orient`
//!   is (the root rotation turns the body about its rest pelvis), so `trans = pelvis − J_pelvis`
//!   with `J_pelvis` the rest pelvis of libflame's neutral SMPL skeleton at `betas = 0`
//!   ([`Skeleton::smpl24`]'s row 0, `(−0.0018, −0.2233, 0.0282)` m, in the body frame: not
//!   turned by `root_orient`). A reader whose body model has another rest pelvis (the SMPL-H
//!   and SMPL-X templates are not SMPL's) sees the body moved by the difference.
//! - Body joints: SMPL-H's and SMPL-X's first 22 joints are SMPL's (pelvis, then the 21 of
//!   `pose_body` in SMPL order 1..=21); SMPL-24's joints 22 and 23 (hands) are not among them
//!   (SMPL-H/X carry 15 finger joints per hand instead), so they are not written. Hands, jaw
//!   and eyes are at rest (zeros), `betas` are 16 zeros, `gender` is "neutral".
//!
//! # The world frame
//!
//! AMASS's world is Z up, right-handed, metres; it fixes no facing (each capture faces where its
//! subject did). libflame writes every format in one frame, the [`Convention::Blender`] axes (+Z
//! up, a body with identity rotations facing −Y, its left +X), because that is the frame
//! `smpl24_6d` models already work in: FLAME's features are AMASS SMPL parameters
//! (docs/official/flame.md#motion-representation, docs/official/smpl.md#axes), so for them the
//! change is the identity and the file holds the model's own rotations and translation.
//! `humanml263` poses (Y up, +Z forward, +X left) turn by `Rx(+90°)`: `(x, y, z) → (x, −z, y)`.
//! HumanML3D built its data the other way (EricGuo5513/HumanML3D, `raw_pose_processing.ipynb`:
//! `trans_matrix` swaps y and z, then `data[..., 0] *= -1`: `(x, y, z)_HumanML3D = (−x, z,
//! y)_AMASS`), whose inverse `(x, y, z) → (−x, z, y)` is this change followed by a half turn about
//! Z; HumanML3D then turned each motion to face +Z at its first frame
//! (`motion_representation.ipynb`), so its AMASS facing is not recoverable and both are AMASS
//! frames. libflame keeps one facing for both formats (tested in
//! `world_change_is_blenders_and_humanml3ds_inverse_up_to_a_half_turn`).
//!
//! # Rotations of `humanml263` poses
//!
//! HumanML3D's rotations hang on its own rest skeleton (arms down, feet forward:
//! `t2m_raw_offsets`), not SMPL's T-pose, and come from an IK without twist (HumanML3D issues
//! #107, #112, #119; docs/official/humanml3d.md#rotation-features), so
//! [`Poses::local_rotations`] cannot be written as SMPL parameters as they are. Per frame, in
//! the body frame:
//!
//! 1. each joint's world rotation from the features' 6D channels (`humanml263`'s hanging) is
//!    re-based onto SMPL's rest: `G(j)·A(j)`, `A(j)` the smallest rotation taking SMPL's rest
//!    bone from j to its next joint in the HumanML3D chain onto HumanML3D's (what a retarget
//!    pose does, `crate::retarget::transfer`); the twist about each bone is the features';
//! 2. the pelvis and Spine3 (three children each) take the rotation that puts their children
//!    where the decoded positions have them (two-vector frames: pelvis from the hip line and the
//!    spine, Spine3 from the neck and the collar line), since HumanML3D's root rotation is its
//!    facing only (no tilt);
//! 3. every other bone is swung (smallest rotation) from where its joint lands by forward
//!    kinematics onto the decoded position of its next joint; the leaves (feet, head, wrists)
//!    keep their parent's rotation.
//!
//! So the file's forward kinematics follow the decoded positions up to the differences of bone
//! lengths between the generated skeleton and SMPL's neutral one (docs/amass.md has the
//! measured numbers). `smpl24_6d` positions are the forward kinematics of its rotations on this
//! skeleton, so its files reproduce them to rounding.

use std::fmt;
use std::str::FromStr;

use super::convention::{Change, Convention};
use super::format::Format;
use super::ik::rotate_onto;
use super::poses::Poses;
use super::rotation::{self, Mat3, Vec3};
use super::skeleton::{self, Skeleton, HUMANML22_CHAINS};
use crate::error::{invalid_arg, Error, Result};
use crate::npz::Npz;

/// SMPL-H's and SMPL-X's body joints: the pelvis and the 21 of `pose_body`.
pub const BODY_JOINTS: usize = 22;
/// Shape coefficients written (AMASS's `betas` length).
pub const NUM_BETAS: usize = 16;
/// DMPL soft-tissue coefficients per frame in SMPL-H files.
const NUM_DMPLS: usize = 8;

/// Which AMASS release's keys a file has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum AmassLayout {
    /// SMPL-H (`*_poses.npz`): `poses` [N, 156] = root 3 + body 63 + left hand 45 + right hand
    /// 45, `trans`, `betas`, `gender`, `mocap_framerate`, `dmpls` [N, 8]. PHC and human2humanoid
    /// read these.
    SmplH = 0,
    /// SMPL-X (`*_stageii.npz`): `root_orient`, `pose_body`, `pose_hand` [N, 90], `pose_jaw`,
    /// `pose_eye` [N, 6], `trans`, `betas`, `num_betas`, `gender`, `surface_model_type`,
    /// `mocap_frame_rate`, `mocap_time_length`, and `poses` [N, 165] in smplx's `full_pose`
    /// order: root 3, body 63, jaw 3, left eye 3, right eye 3, left hand 45, right hand 45.
    /// GMR reads these.
    SmplX = 1,
}

impl AmassLayout {
    /// Every layout, indexed by its integer value (the C ABI's: 0 `smplh`, 1 `smplx`).
    pub const ALL: [AmassLayout; 2] = [AmassLayout::SmplH, AmassLayout::SmplX];

    /// `smplh` or `smplx`, as `FromStr` and the CLI's `--amass` take them.
    pub fn name(self) -> &'static str {
        match self {
            AmassLayout::SmplH => "smplh",
            AmassLayout::SmplX => "smplx",
        }
    }

    /// The layout with integer value `v` (the C ABI's).
    pub fn from_u32(v: u32) -> Result<AmassLayout> {
        AmassLayout::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown AMASS layout {v} (0 smplh, 1 smplx)"))
    }
}

impl FromStr for AmassLayout {
    type Err = Error;
    fn from_str(s: &str) -> Result<AmassLayout> {
        AmassLayout::ALL
            .into_iter()
            .find(|l| l.name() == s)
            .ok_or_else(|| invalid_arg!("unknown AMASS layout `{s}` (expected smplh or smplx)"))
    }
}

impl fmt::Display for AmassLayout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A motion as AMASS SMPL parameters: AMASS's Z-up world, radians, metres.
#[derive(Clone, Debug, PartialEq)]
pub struct Amass {
    /// Frames per second (`mocap_framerate` / `mocap_frame_rate`).
    pub fps: f64,
    /// `[frames]` the root's global axis-angle.
    pub root_orient: Vec<Vec3>,
    /// `[frames × 21]` parent-relative axis-angles of SMPL joints 1..=21.
    pub pose_body: Vec<Vec3>,
    /// `[frames]` `pelvis − J_pelvis` (module doc).
    pub trans: Vec<Vec3>,
}

impl Amass {
    /// The AMASS parameters of `poses` at `fps` frames per second (module doc). Refuses an
    /// empty motion, a rate that is not a positive number, and poses that are not finite.
    pub fn from_poses(poses: &Poses, fps: f64) -> Result<Amass> {
        let frames = poses.frames();
        if frames == 0 {
            return Err(invalid_arg!("an AMASS file needs at least one frame"));
        }
        if !(fps.is_finite() && fps > 0.0) {
            return Err(invalid_arg!(
                "an AMASS file needs a frame rate > 0, got {fps}"
            ));
        }
        check_finite(poses)?;
        let joints = poses.joint_count();
        let world = world_change(poses.format());
        let rest_pelvis = Skeleton::smpl24().rest_offsets()[0];
        let rebase = Rebase::new();
        let mut out = Amass {
            fps,
            root_orient: Vec::with_capacity(frames),
            pose_body: Vec::with_capacity(frames * (BODY_JOINTS - 1)),
            trans: Vec::with_capacity(frames),
        };
        let mut global = [rotation::IDENTITY; BODY_JOINTS];
        for t in 0..frames {
            let span = t * joints..(t + 1) * joints;
            // A separate root motion's travel is on the root bone: AMASS has none, so it goes
            // back onto the pelvis.
            let travel = poses.root_bone.get(t).copied().unwrap_or([0.0; 3]);
            let positions: Vec<Vec3> = poses.positions[span.clone()]
                .iter()
                .map(|p| rotation::add(p, &travel))
                .collect();
            match poses.format() {
                Format::Smpl24Rot6d => global.copy_from_slice(&poses.global[t * joints..][..22]),
                Format::HumanMl263 => rebase.frame(&poses.global[span], &positions, &mut global),
            }
            let pelvis = rotation::apply(&world, &positions[0]);
            out.trans.push(sub(&pelvis, &rest_pelvis));
            out.root_orient
                .push(axis_angle(&rotation::mul(&world, &global[0])));
            for j in 1..BODY_JOINTS {
                let parent = SMPL_PARENTS[j];
                let local = rotation::mul(&rotation::transpose(&global[parent]), &global[j]);
                out.pose_body.push(axis_angle(&local));
            }
        }
        Ok(out)
    }

    /// Number of frames (the length of `trans` and `root_orient`).
    pub fn frames(&self) -> usize {
        self.trans.len()
    }

    /// `[frames × 22]` joint positions by SMPL's forward kinematics of these parameters on
    /// libflame's neutral SMPL skeleton: the pelvis at `trans + J_pelvis`, then
    /// `p(j) = p(parent) + G(parent)·offset(j)`, `G(0)` = the root's rotation, in AMASS's world.
    /// What a reader posing this skeleton gets; tests compare it with the decoded positions.
    pub fn forward_kinematics(&self) -> Vec<Vec3> {
        let skel = Skeleton::smpl24();
        let offsets = &skel.rest_offsets()[..BODY_JOINTS];
        let parents = &skel.parents()[..BODY_JOINTS];
        let mut out = vec![[0.0; 3]; self.frames() * BODY_JOINTS];
        let mut world = [rotation::IDENTITY; BODY_JOINTS];
        let mut local = [rotation::IDENTITY; BODY_JOINTS];
        for (t, positions) in out.chunks_exact_mut(BODY_JOINTS).enumerate() {
            local[0] = from_axis_angle(&self.root_orient[t]);
            let body = &self.pose_body[t * (BODY_JOINTS - 1)..(t + 1) * (BODY_JOINTS - 1)];
            for (l, v) in local[1..].iter_mut().zip(body) {
                *l = from_axis_angle(v);
            }
            let pelvis = rotation::add(&self.trans[t], &offsets[0]);
            // Cannot fail: the slices have the hierarchy's length and SMPL's parents come first.
            let _ = skeleton::forward_kinematics(
                parents, offsets, &pelvis, &local, positions, &mut world,
            );
        }
        out
    }

    /// The `.npz` archive of `layout` (keys in [`AmassLayout`]'s doc), every array `float64`.
    pub fn to_npz(&self, layout: AmassLayout) -> Result<Vec<u8>> {
        let n = self.frames();
        let flat = |v: &[Vec3]| -> Vec<f64> { v.iter().flatten().copied().collect() };
        let (root, body) = (flat(&self.root_orient), flat(&self.pose_body));
        let check = |what: &str, v: &[f64]| match v.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(invalid_arg!("AMASS {what} is not finite at value {i}")),
            None => Ok(()),
        };
        check("trans", &flat(&self.trans))?;
        check("root_orient", &root)?;
        check("pose_body", &body)?;
        let mut z = Npz::new();
        match layout {
            AmassLayout::SmplH => {
                z.add_f64("poses", &[n, 156], &full_pose(&root, &body, n, 156))?;
                z.add_f64("trans", &[n, 3], &flat(&self.trans))?;
                z.add_f64("betas", &[NUM_BETAS], &[0.0; NUM_BETAS])?;
                z.add_str("gender", "neutral")?;
                z.add_scalar_f64("mocap_framerate", self.fps)?;
                z.add_f64("dmpls", &[n, NUM_DMPLS], &zeros(n, NUM_DMPLS)?)?;
            }
            AmassLayout::SmplX => {
                z.add_f64("root_orient", &[n, 3], &root)?;
                z.add_f64("pose_body", &[n, 63], &body)?;
                z.add_f64("pose_hand", &[n, 90], &zeros(n, 90)?)?;
                z.add_f64("pose_jaw", &[n, 3], &zeros(n, 3)?)?;
                z.add_f64("pose_eye", &[n, 6], &zeros(n, 6)?)?;
                z.add_f64("trans", &[n, 3], &flat(&self.trans))?;
                z.add_f64("betas", &[NUM_BETAS], &[0.0; NUM_BETAS])?;
                z.add_scalar_i64("num_betas", NUM_BETAS as i64)?;
                z.add_str("gender", "neutral")?;
                z.add_str("surface_model_type", "smplx")?;
                z.add_scalar_f64("mocap_frame_rate", self.fps)?;
                z.add_scalar_f64("mocap_time_length", n as f64 / self.fps)?;
                z.add_f64("poses", &[n, 165], &full_pose(&root, &body, n, 165))?;
            }
        }
        Ok(z.finish())
    }
}

/// The `.npz` bytes of `poses` at `fps` in `layout`: [`Amass::from_poses`] then
/// [`Amass::to_npz`].
pub fn to_npz(poses: &Poses, fps: f64, layout: AmassLayout) -> Result<Vec<u8>> {
    Amass::from_poses(poses, fps)?.to_npz(layout)
}

/// The change of frame from `format`'s native world to the AMASS world written
/// ([`Convention::Blender`]'s axes, module doc): the identity for `smpl24_6d`, `Rx(+90°)` for
/// `humanml263`. Rotations keep their body side (SMPL's Y-up body frame is both formats' body
/// frame), so a root rotation becomes `W·R` and positions `W·p`.
pub fn world_change(format: Format) -> Mat3 {
    let ch = Change::new(format, Convention::Blender);
    let cols = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|e| ch.position(&e));
    rotation::transpose(&cols)
}

/// SMPL's parents for the 22 body joints.
const SMPL_PARENTS: [usize; BODY_JOINTS] = [
    0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
];
const PELVIS: usize = 0;
const L_HIP: usize = 1;
const R_HIP: usize = 2;
const SPINE1: usize = 3;
const SPINE3: usize = 9;
const NECK: usize = 12;
const L_COLLAR: usize = 13;
const R_COLLAR: usize = 14;

/// Step 1 and the aims of steps 2–3 of the module doc, made once: for each joint the next joint
/// in its HumanML3D chain and the rest re-basing `A(j)`.
struct Rebase {
    next: [Option<usize>; BODY_JOINTS],
    rest: [Mat3; BODY_JOINTS],
}

impl Rebase {
    fn new() -> Rebase {
        let smpl = Skeleton::smpl24().rest_offsets();
        let hml = Skeleton::humanml22().rest_offsets();
        let mut next = [None; BODY_JOINTS];
        for chain in HUMANML22_CHAINS {
            for pair in chain[1..].windows(2) {
                next[pair[0]] = Some(pair[1]);
            }
        }
        let mut rest = [rotation::IDENTITY; BODY_JOINTS];
        for j in 1..BODY_JOINTS {
            rest[j] = match next[j] {
                Some(c) => rotate_onto(&smpl[c], &hml[c], None),
                // A leaf keeps its parent's re-basing: its local rotation stays the identity.
                None => rest[SMPL_PARENTS[j]],
            };
        }
        Rebase { next, rest }
    }

    /// One frame's SMPL world rotations (body frame = native frame for humanml263) from its
    /// hung rotations `hung` and decoded positions `target`.
    fn frame(&self, hung: &[Mat3], target: &[Vec3], global: &mut [Mat3; BODY_JOINTS]) {
        let offsets = Skeleton::smpl24().rest_offsets();
        let mut at = [[0.0; 3]; BODY_JOINTS];
        at[PELVIS] = target[PELVIS];
        for j in 0..BODY_JOINTS {
            if j > 0 {
                let p = SMPL_PARENTS[j];
                at[j] = rotation::add(&at[p], &rotation::apply(&global[p], &offsets[j]));
            }
            global[j] = match (j, self.next[j]) {
                (PELVIS, _) => two_vector_frame(
                    [&sub(&offsets[L_HIP], &offsets[R_HIP]), &offsets[SPINE1]],
                    [
                        &sub(&target[L_HIP], &target[R_HIP]),
                        &sub(&target[SPINE1], &target[PELVIS]),
                    ],
                ),
                (SPINE3, _) => two_vector_frame(
                    [&offsets[NECK], &sub(&offsets[L_COLLAR], &offsets[R_COLLAR])],
                    [
                        &sub(&target[NECK], &at[SPINE3]),
                        &sub(&target[L_COLLAR], &target[R_COLLAR]),
                    ],
                ),
                (_, Some(c)) => {
                    let g = rotation::mul(&hung[j], &self.rest[j]);
                    let bone = rotation::apply(&g, &offsets[c]);
                    let swing = rotate_onto(&bone, &sub(&target[c], &at[j]), None);
                    rotation::mul(&swing, &g)
                }
                (_, None) => global[SMPL_PARENTS[j]],
            };
        }
    }
}

/// The rotation taking the frame built on rest vectors (`a`, `b` made perpendicular to `a`) onto
/// the one built on the posed vectors likewise: `a` exactly, `b` within the plane. A degenerate
/// pair (zero or parallel vectors) gives the identity rather than NaN.
fn two_vector_frame(rest: [&Vec3; 2], posed: [&Vec3; 2]) -> Mat3 {
    let basis = |a: &Vec3, b: &Vec3| -> Option<Mat3> {
        let x = unit(a)?;
        let k = rotation::dot(&x, b);
        let y = unit(&[b[0] - k * x[0], b[1] - k * x[1], b[2] - k * x[2]])?;
        let z = rotation::cross(&x, &y);
        // Columns x, y, z.
        Some([[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]])
    };
    match (basis(rest[0], rest[1]), basis(posed[0], posed[1])) {
        (Some(r), Some(p)) => rotation::mul(&p, &rotation::transpose(&r)),
        _ => rotation::IDENTITY,
    }
}

fn unit(v: &Vec3) -> Option<Vec3> {
    let n = rotation::dot(v, v).sqrt();
    (n > 1e-9).then(|| v.map(|x| x / n))
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The axis-angle vector (axis × angle, angle in [0, π]) of a rotation, through its quaternion
/// (pytorch3d's `matrix_to_quaternion`, w ≥ 0; [`rotation::to_quat`]) as pytorch3d's
/// `quaternion_to_axis_angle` does: `angle = 2·atan2(|v|, w)`, which stays accurate near 0 and
/// π where `acos` of the trace does not. A degenerate (non-orthonormal) matrix from a model's
/// 6D output gives the rotation of its normalised quaternion.
pub fn axis_angle(m: &Mat3) -> Vec3 {
    let q = rotation::to_quat(m);
    let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|c| c / norm);
    let s = (x * x + y * y + z * z).sqrt();
    // angle/s → 2/w as s → 0 (w → 1); below 1e-8 the difference is under 1e-16.
    let k = if s > 1e-8 {
        2.0 * s.atan2(w) / s
    } else {
        2.0 / w
    };
    [x * k, y * k, z * k]
}

/// The rotation of an axis-angle vector (Rodrigues; the identity for a zero vector).
pub fn from_axis_angle(v: &Vec3) -> Mat3 {
    let angle = rotation::dot(v, v).sqrt();
    if angle < 1e-300 {
        return rotation::IDENTITY;
    }
    rotation::axis_angle(v, angle)
}

/// `[frames, width]`: the root and body in the first 66 columns (SMPL-H's and smplx's
/// `full_pose` both start so), zeros (hands, jaw, eyes at rest) after them.
fn full_pose(root: &[f64], body: &[f64], frames: usize, width: usize) -> Vec<f64> {
    let mut out = vec![0.0; frames * width];
    for (t, row) in out.chunks_exact_mut(width).enumerate() {
        row[..3].copy_from_slice(&root[t * 3..t * 3 + 3]);
        row[3..66].copy_from_slice(&body[t * 63..t * 63 + 63]);
    }
    out
}

/// `frames × width` zeros, the size checked first.
fn zeros(frames: usize, width: usize) -> Result<Vec<f64>> {
    let n = frames
        .checked_mul(width)
        .ok_or_else(|| invalid_arg!("{frames} frames × {width} values overflow"))?;
    Ok(vec![0.0; n])
}

/// The first frame and joint whose position or rotation is not finite, as an error.
fn check_finite(poses: &Poses) -> Result<()> {
    let joints = poses.joint_count();
    let bad_vec = |v: &Vec3| !v.iter().all(|x| x.is_finite());
    let bad_mat = |m: &Mat3| !m.iter().flatten().all(|x| x.is_finite());
    let found = (0..poses.frames() * joints).find(|&i| {
        bad_vec(&poses.positions[i]) || bad_mat(&poses.global[i]) || bad_mat(&poses.local[i])
    });
    if let Some(i) = found {
        return Err(invalid_arg!(
            "poses are not finite at frame {}, joint {} ({}): nothing to write as AMASS",
            i / joints,
            i % joints,
            poses.format().skeleton().joint_names()[i % joints]
        ));
    }
    if let Some(t) = poses.root_bone.iter().position(bad_vec) {
        return Err(invalid_arg!(
            "the root bone is not finite at frame {t}: nothing to write as AMASS"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::testutil::sinusoid_motion;

    fn close(a: &Vec3, b: &Vec3, tol: f64) -> bool {
        (0..3).all(|k| (a[k] - b[k]).abs() <= tol)
    }

    #[test]
    fn axis_angles_round_trip_near_zero_and_pi() {
        for (axis, angle) in [
            ([1.0, 2.0, 3.0], 0.7),
            ([0.0, 0.0, 1.0], 1e-10),
            ([0.3, -1.0, 0.2], std::f64::consts::PI - 1e-9),
            ([1.0, 0.0, 0.0], std::f64::consts::PI),
            ([-0.5, 0.5, 0.7], 2.5),
        ] {
            let m = rotation::axis_angle(&axis, angle);
            let v = axis_angle(&m);
            let back = from_axis_angle(&v);
            for r in 0..3 {
                assert!(close(&back[r], &m[r], 1e-12), "{axis:?} {angle}");
            }
            let n = rotation::dot(&v, &v).sqrt();
            assert!((n - angle).abs() < 1e-9, "{axis:?} {angle}: |v| = {n}");
        }
        // +90° about X: (π/2, 0, 0), the tilt of an AMASS body standing.
        let half_pi = std::f64::consts::FRAC_PI_2;
        let tilt = axis_angle(&rotation::axis_angle(&[1.0, 0.0, 0.0], half_pi));
        assert!(close(
            &tilt,
            &[std::f64::consts::FRAC_PI_2, 0.0, 0.0],
            1e-15
        ));
    }

    #[test]
    fn world_change_is_blenders_and_humanml3ds_inverse_up_to_a_half_turn() {
        assert_eq!(world_change(Format::Smpl24Rot6d), rotation::IDENTITY);
        let w = world_change(Format::HumanMl263);
        // Rx(+90°): y → z, z → −y.
        assert_eq!(w, [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]);
        // HumanML3D's AMASS → HumanML3D map is (x, y, z) → (−x, z, y); its inverse is Rz(π)·W.
        let hml_from_amass = [[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]];
        let inverse = rotation::transpose(&hml_from_amass);
        let half_turn = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rotation::mul(&half_turn, &w), inverse);
    }

    #[test]
    fn smpl24_files_pose_the_same_joints() {
        let poses = sinusoid_motion(Format::Smpl24Rot6d, 12);
        let a = Amass::from_poses(&poses, 20.0).unwrap();
        let fk = a.forward_kinematics();
        let want = poses.positions(Convention::Native);
        let mut worst = 0.0f64;
        for t in 0..12 {
            for j in 0..BODY_JOINTS {
                let (g, w) = (fk[t * BODY_JOINTS + j], want[t * 24 + j]);
                worst = worst.max((0..3).map(|k| (g[k] - w[k]).abs()).fold(0.0, f64::max));
            }
            // trans is the model's translation feature: pelvis − rest pelvis.
            let rest = Skeleton::smpl24().rest_offsets()[0];
            assert!(close(&a.trans[t], &sub(&want[t * 24], &rest), 1e-12));
        }
        assert!(worst < 1e-9, "{worst}");
    }

    #[test]
    fn humanml_files_follow_the_decoded_positions_up_to_bone_lengths() {
        let poses = sinusoid_motion(Format::HumanMl263, 10);
        let a = Amass::from_poses(&poses, 20.0).unwrap();
        let fk = a.forward_kinematics();
        let w = world_change(Format::HumanMl263);
        let want = poses.positions(Convention::Native);
        // The pelvis is placed exactly; every other joint within the sum of bone-length
        // differences along its chain (the synthetic features' positions are far from any
        // skeleton, so only the pelvis and finiteness are checked tightly here; the export
        // test measures real motions).
        for t in 0..10 {
            let pelvis = rotation::apply(&w, &want[t * 22]);
            assert!(close(&fk[t * BODY_JOINTS], &pelvis, 1e-12));
        }
        assert!(fk.iter().flatten().all(|x| x.is_finite()));
    }

    #[test]
    fn refusals_are_clear_errors() {
        let poses = sinusoid_motion(Format::Smpl24Rot6d, 3);
        let e = Amass::from_poses(&poses.frames_range(0, 0), 20.0).unwrap_err();
        assert!(e.to_string().contains("at least one frame"), "{e}");
        for fps in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(Amass::from_poses(&poses, fps).is_err(), "{fps}");
        }
        let mut bad = poses.clone();
        bad.positions[24 + 5][1] = f64::NAN;
        let e = Amass::from_poses(&bad, 20.0).unwrap_err().to_string();
        assert!(e.contains("not finite at frame 1, joint 5 (R_Knee)"), "{e}");
        let mut bad = poses.clone();
        bad.global[2 * 24 + 20][0][0] = f64::INFINITY;
        let e = Amass::from_poses(&bad, 20.0).unwrap_err().to_string();
        assert!(e.contains("frame 2, joint 20"), "{e}");
        assert_eq!("smplx".parse::<AmassLayout>().unwrap(), AmassLayout::SmplX);
        assert!("smpl"
            .parse::<AmassLayout>()
            .unwrap_err()
            .to_string()
            .contains("expected smplh or smplx"));
        assert!(AmassLayout::from_u32(2).is_err());
    }

    #[test]
    fn layouts_hold_their_keys_in_order() {
        let poses = sinusoid_motion(Format::HumanMl263, 4);
        let a = Amass::from_poses(&poses, 30.0).unwrap();
        let find = |b: &[u8], s: &str| b.windows(s.len()).any(|w| w == s.as_bytes());
        let h = a.to_npz(AmassLayout::SmplH).unwrap();
        for key in [
            "poses",
            "trans",
            "betas",
            "gender",
            "mocap_framerate",
            "dmpls",
        ] {
            assert!(find(&h, &format!("{key}.npy")), "{key}");
        }
        assert!(find(&h, "'shape': (4, 156)"));
        let x = a.to_npz(AmassLayout::SmplX).unwrap();
        for key in [
            "root_orient",
            "pose_body",
            "pose_hand",
            "pose_jaw",
            "pose_eye",
            "num_betas",
            "surface_model_type",
            "mocap_frame_rate",
            "mocap_time_length",
        ] {
            assert!(find(&x, &format!("{key}.npy")), "{key}");
        }
        assert!(find(&x, "'shape': (4, 165)") && find(&x, "'shape': (4, 63)"));
    }
}
