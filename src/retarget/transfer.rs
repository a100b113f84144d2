//! The rest-relative transform ([`Transfer`]): a libflame pose carried onto a [`Rig`].
//!
//! The common core of VRM Animation's pose transform (vrm-c/vrm-specification,
//! `specification/VRMC_vrm_animation-1.0/how_to_transform_human_pose.md`), three-vrm's
//! normalized bones and three.js's `SkeletonUtils.retarget`: each source bone's rotation away
//! from its rest, in world axes (`D = G · W⁻¹`, G its world rotation, W its rest world
//! rotation), is given to the matching target bone on top of *its* rest (`G' = D · W'`), and
//! local rotations follow from the worlds (`L' = G'(parent)ᵀ · G'`). Here:
//!
//! - **Axes.** libflame's poses are read in glTF axes (Y up, +Z forward, +X left), where the
//!   rest skeleton stands with identity rotations, so `D = G`. The rig's up, left and forward
//!   come from its rest pose (hips to head; right thigh to left thigh), so a rig facing −Z
//!   (VRM 0.x), lying in Z-up axes or mirrored in its node tree needs no flag: `C` turns source
//!   axes into the rig's and `D' = C · D · Cᵀ`.
//! - **Retarget pose.** A rest-relative delta assumes both rests agree: a T-pose source on an
//!   A-pose rig would leave the arms 45° down. As Unreal's IK Retargeter does with its retarget
//!   pose, each mapped target bone's rest is first turned (smallest arc) so that it points where
//!   the source's bone points at rest (toward the next mapped joint down the chain), `W' = A · W`;
//!   a bone with no mapped child (hand, head, toes) takes its parent's turn, keeping its rest
//!   relation to it. Every mapped bone with a mapped child then points exactly where the source's
//!   does, in every frame.
//! - **Spine.** However many bones the rig has between hips and neck (1 to 5 or more, mapped or
//!   not), each takes the source spine's delta at its place along the chain (by rest length):
//!   deltas of neighbouring source spine joints blended by spherical interpolation, then the
//!   smallest turn aiming it at the chord of the source's posed spine between the same
//!   fractions, so the rig's spine follows the source's curve.
//! - **Missing and extra bones.** A source joint the rig lacks (no shoulder, no neck) passes its
//!   motion on through the world deltas of its children. Target bones with no source (twist,
//!   IK, `root`, fingers) keep their rest rotation relative to their parent: twist bones take no
//!   share of a limb's twist, the limb bone carries all of it.
//! - **Bones beside the hips.** A rig may hang body bones beside the hips rather than under
//!   them (Blender's Rigify, exported with deform bones only: `DEF-thigh.L`, `DEF-upper_arm.L`
//!   and the face bones are roots of their own). Such a bone without a source of its own
//!   follows the driven bone nearest to it at rest, rigidly; a driven one keeps its own
//!   rotation and its rest offset from its humanoid parent's bone (the thigh from the hips,
//!   the upper arm from the shoulder). Either way it moves with the body and its translation
//!   is animated; [`Transfer::anchor`] names the bone it is placed from.
//! - **Hips translation.** Scaled by the ratio of the legs' lengths (thigh plus shin, both
//!   sides' mean), turned into the rig's axes and units, put in the hips' parent's frame (at
//!   rest), and raised by what keeps the rest pose at rest (the rig's hips height minus the
//!   scaled source's). VRMA and three-vrm scale by the hips heights' ratio, which is the same
//!   number for a rig whose hips bone sits where SMPL's pelvis does; the legs' ratio also
//!   holds for one whose hips bone does not (Rigify's sits below its thighs: the hips ratio
//!   would need its straight legs bent by 20 degrees to reach the floor).
//!
//! [`Transfer`] is immutable (shareable); [`Transfer::frame`] writes one frame into caller-owned
//! buffers and allocates nothing.

use super::rig::Rig;
use crate::error::{invalid_arg, Result};
use crate::motion::ik::rotate_onto;
use crate::motion::rotation::{self, Mat3, Vec3};
use crate::motion::Skeleton;

/// SMPL's joint indices, shared by SMPL-24 and HumanML3D-22 (SMPL's joint order; HumanML3D's
/// 22 joints are SMPL's first 22 in the same order, see `crate::motion::skeleton`).
pub mod smpl {
    /// Pelvis: the root; its position is the motion's root translation.
    pub const PELVIS: usize = 0;
    /// L_Hip: the left hip joint, where the left thigh starts.
    pub const L_HIP: usize = 1;
    /// R_Hip: the right hip joint, where the right thigh starts.
    pub const R_HIP: usize = 2;
    /// L_Knee: where the left shin starts.
    pub const L_KNEE: usize = 4;
    /// R_Knee: where the right shin starts.
    pub const R_KNEE: usize = 5;
    /// Spine1, Spine2, Spine3.
    pub const SPINE: [usize; 3] = [3, 6, 9];
    /// L_Ankle: where the left foot starts.
    pub const L_ANKLE: usize = 7;
    /// R_Ankle: where the right foot starts.
    pub const R_ANKLE: usize = 8;
    /// L_Foot: the ball of the left foot, where the toes start.
    pub const L_FOOT: usize = 10;
    /// R_Foot: the ball of the right foot, where the toes start.
    pub const R_FOOT: usize = 11;
    /// Neck: the top of the spine, where the neck starts.
    pub const NECK: usize = 12;
    /// Head: where the head starts.
    pub const HEAD: usize = 15;
}

/// How one rig bone is driven.
#[derive(Clone, Copy, Debug)]
enum Drive {
    /// Takes source joint `joint`'s delta on top of its retarget rest.
    Joint { joint: usize, rest: Mat3 },
    /// A spine bone: the blend of source joints `lo` and `hi`'s deltas at `t`, then aimed so
    /// that its end lands on the source's posed spine at the same fraction of its length.
    Spine {
        lo: usize,
        hi: usize,
        t: f64,
        rest: Mat3,
        /// Its place in the rig's spine chain (0 = the bone above the hips).
        k: usize,
        /// Its start's rest offset from the chain point before (the hips' for `k = 0`, else
        /// spine bone `k − 1`'s start), in that bone's rest frame; its end's (the next spine
        /// bone's start, or the neck's or head's) in its own rest frame.
        start: Vec3,
        end: Vec3,
        /// The fraction of the rig's chain length at its end.
        to: f64,
    },
    /// Keeps its rest rotation relative to its parent.
    Rest,
    /// A bone outside the hips' subtree (and not above the hips): moves rigidly with driven
    /// bone `bone`, keeping its rest relation to it: `G = G_bone · rel`.
    Follow { bone: usize, rel: Mat3 },
}

/// A source skeleton's pose carried onto a rig (module doc).
#[derive(Clone, Debug)]
pub struct Transfer {
    drive: Vec<Drive>,
    parents: Vec<Option<usize>>,
    /// Rest local rotations (the `Rest` bones') and rest world rotations of the roots.
    rest_local: Vec<Mat3>,
    /// Source axes → rig axes.
    axes: Mat3,
    source_joints: usize,
    hips: usize,
    /// Source metres → rig units, the legs' ratio included.
    scale: f64,
    /// The rig's floor (lowest foot joint at rest) along the rig's direction of the source's
    /// world up, in rig units, as a point on that axis through the origin.
    floor: Vec3,
    /// The hips' parent at rest: world position and inverse linear part (`None`: hips is a
    /// root).
    hips_parent: Option<(Vec3, Mat3)>,
    /// The source's spine chain (pelvis, spine joints, neck) with each point's rest offset from
    /// the one before and its fraction of the chain's rest length; `chain_len` points are used.
    chain: [usize; MAX_CHAIN],
    chain_off: [Vec3; MAX_CHAIN],
    chain_frac: [f64; MAX_CHAIN],
    chain_len: usize,
    /// Rig units per source metre along the spines (their lengths' ratio).
    chain_scale: f64,
    /// The rig's spine bones, bottom up.
    spine_bones: Vec<usize>,
    /// Bones in an order where each comes after what its world position depends on (its
    /// parent, or its anchor).
    order: Vec<usize>,
    /// Per bone beside the body: the bone it keeps its rest offset from ([`Transfer::anchor`]).
    anchor: Vec<Option<usize>>,
}

/// How far (degrees) a rest direction may be from an axis of its skeleton's world and still be
/// taken as it: above any spine's lean at rest, far below a rig turned on purpose.
const SNAP_DEGREES: f64 = 20.0;

/// `u` (unit) replaced by the signed world axis nearest to it when within [`SNAP_DEGREES`].
fn snap(u: &Vec3) -> Vec3 {
    let i = (0..3)
        .max_by(|&a, &b| u[a].abs().total_cmp(&u[b].abs()))
        .expect("three axes");
    if u[i].abs() >= SNAP_DEGREES.to_radians().cos() {
        let mut a = [0.0; 3];
        a[i] = u[i].signum();
        a
    } else {
        *u
    }
}

/// Bones between a rig's hips and its neck that are spread over the source's spine.
const MAX_RIG_SPINE: usize = 32;

/// The length of a polyline.
fn length(chain: &[Vec3]) -> f64 {
    chain.windows(2).map(|w| norm(&sub(&w[1], &w[0]))).sum()
}

/// Points of a source spine chain (SMPL's: pelvis, three spine joints, neck).
const MAX_CHAIN: usize = 8;

impl Transfer {
    /// A transfer from `source` (libflame's skeleton, rest offsets in glTF axes) onto `rig`,
    /// with `pairs` of (source joint, rig bone). `spine` lists the source's spine joints from
    /// the pelvis's child up to the neck's parent and `rig_spine` the rig's bones between its
    /// hips and its neck (or head), both bottom up. The pairs must map the pelvis, both thighs
    /// and the neck or the head (the spine's end).
    pub fn new(
        source: &Skeleton,
        rig: &Rig,
        pairs: &[(usize, usize)],
        spine: &[usize],
        rig_spine: &[usize],
    ) -> Result<Transfer> {
        let joints = source.joint_count();
        if joints < 22 {
            return Err(invalid_arg!(
                "the source skeleton has {joints} joints: SMPL's first 22 are needed"
            ));
        }
        let n = rig.bone_count();
        let mut joint_of = vec![None; n];
        let mut bone_of = vec![None; joints];
        for &(j, b) in pairs {
            if j >= joints || b >= n {
                return Err(invalid_arg!(
                    "pair ({j}, {b}) is past the source's {joints} joints or the rig's {n} bones"
                ));
            }
            if let Some(other) = joint_of[b].replace(j) {
                return Err(invalid_arg!(
                    "rig bone `{}` is mapped twice (source joints {other} and {j})",
                    rig.name(b)
                ));
            }
            bone_of[j] = Some(b);
        }
        // SMPL-24 and HumanML3D-22 share SMPL's joint order (their names differ).
        let (pelvis, l_hip, r_hip) = (smpl::PELVIS, smpl::L_HIP, smpl::R_HIP);
        let need = |j: usize, what: &str| -> Result<usize> {
            bone_of[j].ok_or_else(|| {
                invalid_arg!("the bone map needs the {what}: no rig bone is mapped to it")
            })
        };
        let hips = need(pelvis, "hips")?;
        let (lb, rb) = (need(l_hip, "left thigh")?, need(r_hip, "right thigh")?);
        let top = match bone_of[smpl::NECK] {
            Some(_) => smpl::NECK,
            None => smpl::HEAD,
        };
        let head = need(top, "neck or head")?;
        // A rig without a neck runs its spine from the hips to the head: the source's neck is
        // then one more joint of the spine it spreads over the rig's bones.
        let spine_to_head: Vec<usize>;
        let spine = if top == smpl::HEAD && source.parent(smpl::HEAD) == Some(smpl::NECK) {
            spine_to_head = spine.iter().copied().chain([smpl::NECK]).collect();
            &spine_to_head[..]
        } else {
            spine
        };

        // Source rest world positions (rotations are all identity in glTF axes).
        let offsets = source.rest_offsets();
        let mut src_pos = vec![[0.0; 3]; joints];
        for j in 1..joints {
            let p = source.parent(j).expect("only the root has none");
            src_pos[j] = rotation::add(&src_pos[p], &offsets[j]);
        }
        let pos = rig.rest_world_positions();
        let frame_of = |left: Vec3, up: Vec3| -> Result<Mat3> {
            // Up first (a spine leans, but a character stands along its world's up axis), then
            // left made perpendicular to it.
            let u = unit(&up)
                .map(|u| snap(&u))
                .ok_or_else(|| invalid_arg!("the rig's spine has no length"))?;
            let l = unit(&sub(&left, &scale(&u, rotation::dot(&left, &u))))
                .ok_or_else(|| invalid_arg!("the rig's thighs coincide or run along its spine"))?;
            let l = snap(&l);
            let l = unit(&sub(&l, &scale(&u, rotation::dot(&l, &u)))).unwrap_or(l);
            let f = rotation::cross(&l, &u);
            Ok([[l[0], u[0], f[0]], [l[1], u[1], f[1]], [l[2], u[2], f[2]]])
        };
        // Both frames are made the same way from the rest skeletons (up from the hips to the
        // spine's end, left from the right thigh to the left), so skeletons of one shape get
        // the exact turn between them: C = F_rig · F_sourceᵀ. Each direction within
        // `SNAP_DEGREES` of an axis of its skeleton's world is taken as that axis: SMPL's spine
        // leans 5° forward at rest, a game rig's stands straight or leans otherwise, and a
        // frame built on the leans themselves would tilt the source's up on the rig (a walk
        // forward would go downhill: 25 cm over 4 m on a Mixamo rig).
        let src_frame = frame_of(
            sub(&src_pos[l_hip], &src_pos[r_hip]),
            sub(&src_pos[top], &src_pos[pelvis]),
        )?;
        let rig_frame = frame_of(sub(&pos[lb], &pos[rb]), sub(&pos[head], &pos[hips]))?;
        let axes = rotation::mul(&rig_frame, &rotation::transpose(&src_frame));
        let up = [rig_frame[0][1], rig_frame[1][1], rig_frame[2][1]];

        // Hips heights above the lowest foot joint: the source's in metres, the rig's in units.
        let feet = [smpl::L_ANKLE, smpl::R_ANKLE, smpl::L_FOOT, smpl::R_FOOT];
        // Heights along each skeleton's own up (its frame's), so one shape gives a ratio of 1.
        let src_up = [src_frame[0][1], src_frame[1][1], src_frame[2][1]];
        let src_floor = feet
            .iter()
            .map(|&j| rotation::dot(&src_pos[j], &src_up))
            .fold(f64::INFINITY, f64::min);
        let src_height = rotation::dot(&src_pos[pelvis], &src_up) - src_floor;
        let rig_floor = feet
            .iter()
            .filter_map(|&j| bone_of[j])
            .map(|b| rotation::dot(&pos[b], &up))
            .fold(f64::INFINITY, f64::min);
        let rig_height = rotation::dot(&pos[hips], &up) - rig_floor;
        if !(src_height > 0.0 && rig_height > 0.0) {
            return Err(invalid_arg!(
                "the rig's hips are not above its feet at rest (hips height {rig_height} units)"
            ));
        }
        // Leg lengths: thigh plus shin (hip to knee to ankle joints), both sides' mean.
        let legs = |p: &dyn Fn(usize) -> Option<Vec3>| -> Option<f64> {
            let side = |h: usize, k: usize, a: usize| {
                let norm = |v: Vec3| rotation::dot(&v, &v).sqrt();
                Some(norm(sub(&p(k)?, &p(h)?)) + norm(sub(&p(a)?, &p(k)?)))
            };
            let l = side(l_hip, smpl::L_KNEE, smpl::L_ANKLE)?;
            let r = side(r_hip, smpl::R_KNEE, smpl::R_ANKLE)?;
            Some(0.5 * (l + r))
        };
        let src_legs = legs(&|j| Some(src_pos[j])).unwrap_or(0.0);
        let rig_legs = legs(&|j| bone_of[j].map(|b| pos[b])).unwrap_or(0.0);
        if !(src_legs > 0.0 && rig_legs > 0.0) {
            return Err(invalid_arg!(
                "the rig's legs have no length at rest ({rig_legs} units from hips to ankles)"
            ));
        }
        // Source metres to rig units: the legs' ratio, so that a straight source leg at any
        // angle is a straight rig leg at the same angle and a stride scales with the legs
        // that take it. The hips heights' ratio (VRMA's and three-vrm's) is nearly the same
        // number on a rig whose hips bone sits where SMPL's pelvis does; one whose hips bone
        // or ankles sit elsewhere (Blender's Rigify hangs its hips bone below the thighs)
        // would have its pelvis's dips scaled by another ratio than its legs, and straight
        // source legs would need its knees bent by up to 20 degrees to reach the floor.
        let scale_factor = rig_legs / src_legs;
        // What keeps the rest pose at rest: the rig's hips height minus the scaled source's.
        let lift = rig_height - scale_factor * src_height;

        // Retarget rests: each mapped bone turned to point where its source bone points.
        let world = rig.rest_world_rotations();
        let mut turn = vec![rotation::IDENTITY; n];
        let mut drive = vec![Drive::Rest; n];
        let mut rest_local = vec![rotation::IDENTITY; n];
        let in_spine = |b: usize| rig_spine.contains(&b);
        for b in 0..n {
            rest_local[b] = match rig.parent(b) {
                Some(p) => rotation::mul(&rotation::transpose(&world[p]), &world[b]),
                None => world[b],
            };
            let inherited = rig.parent(b).map_or(rotation::IDENTITY, |p| turn[p]);
            let Some(j) = joint_of[b].filter(|_| !in_spine(b)) else {
                turn[b] = inherited;
                continue;
            };
            turn[b] = match (j != pelvis)
                .then(|| chain_child(source, j, &bone_of))
                .flatten()
            {
                Some(c) => {
                    let target = rotation::apply(&axes, &sub(&src_pos[c], &src_pos[j]));
                    let to = bone_of[c].expect("mapped");
                    let here = sub(&pos[to], &pos[b]);
                    if norm(&here) * rig.metres_per_unit() < 1e-5 {
                        return Err(invalid_arg!(
                            "rig bones `{}` and `{}` are at one place at rest: a zero-length \
                             bone has no direction to drive",
                            rig.name(b),
                            rig.name(to)
                        ));
                    }
                    rotate_onto(&here, &target, None)
                }
                None => inherited,
            };
            drive[b] = Drive::Joint {
                joint: j,
                rest: rotation::mul(&turn[b], &world[b]),
            };
        }
        // The spine: fractions along the chains by rest length.
        let (mut chain, mut chain_off) = ([0; MAX_CHAIN], [[0.0; 3]; MAX_CHAIN]);
        let (mut chain_frac, mut chain_len) = ([0.0; MAX_CHAIN], 0);
        let mut chain_scale = 1.0;
        if !rig_spine.is_empty() {
            if spine.is_empty() {
                return Err(invalid_arg!("the source has no spine joints to spread"));
            }
            let src_chain: Vec<Vec3> = std::iter::once(pelvis)
                .chain(spine.iter().copied())
                .chain(std::iter::once(top))
                .map(|j| src_pos[j])
                .collect();
            let rig_chain: Vec<Vec3> = std::iter::once(hips)
                .chain(rig_spine.iter().copied())
                .chain(std::iter::once(head))
                .map(|b| pos[b])
                .collect();
            let (sf, rf) = (fractions(&src_chain), fractions(&rig_chain));
            if rig_spine.len() > MAX_RIG_SPINE {
                return Err(invalid_arg!(
                    "the rig has {} bones between its hips and its neck; at most {MAX_RIG_SPINE} \
                     are spread",
                    rig_spine.len()
                ));
            }
            // Rig units per source metre along the spine: its points land on the source's
            // posed spine at the same fractions, scaled to the rig's spine.
            chain_scale = length(&rig_chain) / length(&src_chain).max(1e-12);
            let ids: Vec<usize> = std::iter::once(pelvis)
                .chain(spine.iter().copied())
                .chain(std::iter::once(top))
                .collect();
            if ids.len() > MAX_CHAIN || ids.windows(2).any(|w| source.parent(w[1]) != Some(w[0])) {
                return Err(invalid_arg!(
                    "the source's spine joints must form one chain from the pelvis to the neck"
                ));
            }
            chain_len = ids.len();
            for (i, &j) in ids.iter().enumerate() {
                chain[i] = j;
                chain_off[i] = if i == 0 { [0.0; 3] } else { offsets[j] };
                chain_frac[i] = sf[i];
            }
            // Source spine joint i spans points i + 1..i + 2 of its chain; rig bone k spans
            // points k + 1..k + 2 of its own. A rig bone takes the source deltas at its
            // midpoint, blended between the two source spine joints' midpoints around it.
            let m = spine.len();
            let src_mid: Vec<f64> = (0..m).map(|i| (sf[i + 1] + sf[i + 2]) / 2.0).collect();
            for (k, &b) in rig_spine.iter().enumerate() {
                let mid = (rf[k + 1] + rf[k + 2]) / 2.0;
                let i = (0..m).rev().find(|&i| src_mid[i] <= mid).unwrap_or(0);
                let (lo, hi) = (spine[i], spine[(i + 1).min(m - 1)]);
                let t = if i + 1 < m && mid > src_mid[i] {
                    ((mid - src_mid[i]) / (src_mid[i + 1] - src_mid[i])).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                // Pointed along the source chain's segment holding the same place.
                let s = (0..src_chain.len() - 1)
                    .rev()
                    .find(|&s| sf[s] <= mid)
                    .unwrap_or(0);
                let target = rotation::apply(&axes, &sub(&src_chain[s + 1], &src_chain[s]));
                let here = sub(&rig_chain[k + 2], &rig_chain[k + 1]);
                let rest = rotation::mul(&rotate_onto(&here, &target, None), &world[b]);
                let prev = if k == 0 { hips } else { rig_spine[k - 1] };
                let in_frame =
                    |bone: usize, v: Vec3| rotation::apply(&rotation::transpose(&world[bone]), &v);
                drive[b] = Drive::Spine {
                    lo,
                    hi,
                    t,
                    rest,
                    k,
                    start: in_frame(prev, sub(&rig_chain[k + 1], &rig_chain[k])),
                    end: in_frame(b, here),
                    to: rf[k + 2],
                };
            }
        }
        // A driven bone beside the body is placed from the bone of its joint's nearest mapped
        // ancestor (Rigify's `DEF-thigh.L` from the hips, `DEF-upper_arm.L` from the
        // shoulder); an unmapped spine bone there, from the hips.
        let placed_from: Vec<Option<usize>> = (0..n)
            .map(|b| match drive[b] {
                Drive::Joint { joint, .. } => {
                    let mut j = source.parent(joint);
                    while let Some(a) = j {
                        if let Some(x) = bone_of[a] {
                            return Some(x);
                        }
                        j = source.parent(a);
                    }
                    None
                }
                Drive::Spine { .. } => Some(hips),
                _ => None,
            })
            .collect();
        let (order, anchor) = follow_outsiders(rig, hips, &mut drive, &placed_from);
        // The floor point: the rig's lowest foot joint at rest, measured along the rig's
        // direction of the source's world up (`C·ŷ`, which a leaning spine does not tilt), so
        // the source's origin lands under the rig's origin, not beside it.
        let world_up = [axes[0][1], axes[1][1], axes[2][1]];
        let floor_height = feet
            .iter()
            .filter_map(|&j| bone_of[j])
            .map(|b| rotation::dot(&pos[b], &world_up))
            .fold(f64::INFINITY, f64::min);
        let floor = scale(&world_up, floor_height + lift);
        let hips_parent = rig.parent(hips).map(|p| {
            let lin = rig.rest_world_linear()[p];
            (pos[p], invert(&lin))
        });
        if let Some((_, inv)) = &hips_parent {
            if inv.iter().flatten().any(|v| !v.is_finite()) {
                return Err(invalid_arg!(
                    "the hips' parent `{}` has a degenerate scale",
                    rig.name(rig.parent(hips).expect("has one"))
                ));
            }
        }
        Ok(Transfer {
            drive,
            parents: rig.parents().to_vec(),
            rest_local,
            axes,
            source_joints: joints,
            hips,
            scale: scale_factor,
            floor,
            hips_parent,
            chain,
            chain_off,
            chain_frac,
            chain_len,
            chain_scale,
            spine_bones: rig_spine.to_vec(),
            order,
            anchor,
        })
    }

    /// Rig bones this transfer writes.
    pub fn bone_count(&self) -> usize {
        self.drive.len()
    }

    /// The rig's hips bone.
    pub fn hips(&self) -> usize {
        self.hips
    }

    /// The bone a bone beside the body keeps its rest offset from, turned with it, if it is
    /// one (module doc): its position then comes from there and its translation moves.
    pub fn anchor(&self, bone: usize) -> Option<usize> {
        self.anchor.get(bone).copied().flatten()
    }

    /// Sets the followers' world rotations again from the bones they follow (after IK turned
    /// some of those).
    pub(crate) fn refresh_followers(&self, world: &mut [Mat3]) {
        for &b in &self.order {
            if let Drive::Follow { bone, rel } = self.drive[b] {
                world[b] = rotation::mul(&world[bone], &rel);
            }
        }
    }

    /// Bones ordered so that each comes after its parent, or after the bone it follows.
    pub fn position_order(&self) -> &[usize] {
        &self.order
    }

    /// A source world point (glTF axes, metres, floor at height 0) where the hips translation
    /// puts it on the rig: in the rig's world, rig units, scaled by the legs' ratio
    /// and lifted onto the rig's floor. The pelvis lands where [`Transfer::frame`] puts the
    /// hips.
    pub fn place(&self, p: &Vec3) -> Vec3 {
        rotation::add(
            &self.floor,
            &scale(&rotation::apply(&self.axes, p), self.scale),
        )
    }

    /// The rig's up direction (unit, rig world axes).
    pub fn up(&self) -> Vec3 {
        [self.axes[0][1], self.axes[1][1], self.axes[2][1]]
    }

    /// Rig units per source metre (the legs' ratio included).
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// One frame: `source_world` are the source joints' world rotations and `source_root` the
    /// pelvis position (metres, floor at height 0), both in glTF axes; writes every rig bone's
    /// world rotation (`world`) and local rotation (`local`, parent-relative; a root's is its
    /// world), and returns the hips' translation relative to its parent, in rig units.
    pub fn frame(
        &self,
        source_world: &[Mat3],
        source_root: &Vec3,
        world: &mut [Mat3],
        local: &mut [Mat3],
    ) -> Result<Vec3> {
        let n = self.drive.len();
        if source_world.len() != self.source_joints || world.len() != n || local.len() != n {
            return Err(invalid_arg!(
                "a frame needs {} source rotations and {n} rig rotations, got {}, {} and {}",
                self.source_joints,
                source_world.len(),
                world.len(),
                local.len()
            ));
        }
        let delta = |j: usize| {
            rotation::mul(
                &rotation::mul(&self.axes, &source_world[j]),
                &rotation::transpose(&self.axes),
            )
        };
        // The rig's spine points (relative to the hips), set as its spine bones are.
        let mut spine_at = [[0.0; 3]; MAX_RIG_SPINE];
        // In dependency order: a `Rest` bone after its parent, a follower after its anchor.
        for &b in &self.order {
            world[b] = match self.drive[b] {
                Drive::Joint { joint, rest } => rotation::mul(&delta(joint), &rest),
                Drive::Spine {
                    lo,
                    hi,
                    t,
                    rest,
                    k,
                    start,
                    end,
                    to,
                } => {
                    // The blended delta, then the smallest turn putting the bone's end on the
                    // source's posed spine at the same fraction (scaled to the rig's spine),
                    // from where its start is now: the rig's spine follows the source's curve
                    // whatever its bone count, and hips to neck points where the source's does.
                    let blend = slerp(&delta(lo), &delta(hi), t);
                    let g = rotation::mul(&blend, &rest);
                    let prev = if k == 0 {
                        self.hips
                    } else {
                        self.spine_bones[k - 1]
                    };
                    let before = if k == 0 { [0.0; 3] } else { spine_at[k - 1] };
                    let at = rotation::add(&before, &rotation::apply(&world[prev], &start));
                    spine_at[k] = at;
                    let now = rotation::apply(&g, &end);
                    let goal = scale(
                        &rotation::apply(&self.axes, &self.spine_point(source_world, to)),
                        self.chain_scale,
                    );
                    let aim = rotate_onto(&now, &sub(&goal, &at), None);
                    rotation::mul(&aim, &g)
                }
                Drive::Rest => match self.parents[b] {
                    Some(p) => rotation::mul(&world[p], &self.rest_local[b]),
                    None => self.rest_local[b],
                },
                Drive::Follow { bone, rel } => rotation::mul(&world[bone], &rel),
            };
        }
        for b in 0..n {
            local[b] = match self.parents[b] {
                Some(p) => rotation::mul(&rotation::transpose(&world[p]), &world[b]),
                None => world[b],
            };
        }
        let at = self.place(source_root);
        Ok(match &self.hips_parent {
            Some((origin, inv)) => rotation::apply(inv, &sub(&at, origin)),
            None => at,
        })
    }
}

impl Transfer {
    /// The point at fraction `f` of the source's posed spine chain (relative to the pelvis,
    /// source axes): the chain's points placed by the joints' world rotations, then linear
    /// between the two around `f`.
    fn spine_point(&self, source_world: &[Mat3], f: f64) -> Vec3 {
        let (mut p, mut at) = ([0.0; 3], [0.0; 3]);
        for i in 1..self.chain_len {
            let next = rotation::add(
                &p,
                &rotation::apply(&source_world[self.chain[i - 1]], &self.chain_off[i]),
            );
            let (a, b) = (self.chain_frac[i - 1], self.chain_frac[i]);
            if f <= b || i + 1 == self.chain_len {
                let u = if b > a {
                    ((f - a) / (b - a)).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                at = rotation::add(&scale(&p, 1.0 - u), &scale(&next, u));
                break;
            }
            p = next;
        }
        at
    }
}

/// Bones beside the body: an undriven bone with no driven ancestor that is not above the hips
/// (Blender's Rigify rig: `ORG-spine`, a sibling of the hips `DEF-spine` and parent of
/// `DEF-thigh.L`) follows the driven bone nearest to it at rest, rigidly, so it moves with the
/// body instead of staying where the rig stood; a driven bone with no driven ancestor (the
/// same export's `DEF-thigh.L`, a root of its own) keeps its own rotation and is placed from
/// `placed_from` (its humanoid parent's bone). Returns an order of the bones in which each
/// comes after what its position depends on, and each such bone's anchor. A bone that would
/// end up depending on itself through anchors keeps its rest place relative to its parent.
fn follow_outsiders(
    rig: &Rig,
    hips: usize,
    drive: &mut [Drive],
    placed_from: &[Option<usize>],
) -> (Vec<usize>, Vec<Option<usize>>) {
    let n = rig.bone_count();
    let ancestor_of = |a: usize, b: usize| {
        let mut at = Some(b);
        while let Some(x) = at {
            if x == a {
                return true;
            }
            at = rig.parent(x);
        }
        false
    };
    let pos = rig.rest_world_positions();
    let world = rig.rest_world_rotations();
    let is_driven = |d: &Drive| matches!(d, Drive::Joint { .. } | Drive::Spine { .. });
    let driven: Vec<usize> = (0..n).filter(|&b| is_driven(&drive[b])).collect();
    // A bone with a driven ancestor (the hips included) is carried by it; a bone above the
    // hips holds them. The rest are beside the body.
    let carried = |b: usize, drive: &[Drive]| {
        let mut at = rig.parent(b);
        while let Some(x) = at {
            if is_driven(&drive[x]) {
                return true;
            }
            at = rig.parent(x);
        }
        false
    };
    let mut anchor = vec![None; n];
    for b in 0..n {
        if b == hips || ancestor_of(b, hips) || carried(b, drive) {
            continue;
        }
        if is_driven(&drive[b]) {
            anchor[b] = placed_from[b].filter(|&f| !ancestor_of(b, f));
            continue;
        }
        if !matches!(drive[b], Drive::Rest) {
            continue;
        }
        let nearest = driven
            .iter()
            .copied()
            .filter(|&f| !ancestor_of(b, f))
            .min_by(|&x, &y| {
                let d = |f: usize| norm(&sub(&pos[f], &pos[b]));
                d(x).total_cmp(&d(y))
            });
        if let Some(f) = nearest {
            drive[b] = Drive::Follow {
                bone: f,
                rel: rotation::mul(&rotation::transpose(&world[f]), &world[b]),
            };
            anchor[b] = Some(f);
        }
    }
    // Depth-first: a bone's position needs its anchor's, else its parent's.
    let mut order = Vec::with_capacity(n);
    // 0 unvisited, 1 on the path, 2 placed.
    let mut state = vec![0u8; n];
    for start in 0..n {
        let mut path = vec![start];
        while let Some(&b) = path.last() {
            if state[b] == 2 {
                path.pop();
                continue;
            }
            state[b] = 1;
            match anchor[b].or(rig.parent(b)) {
                Some(d) if state[d] == 0 => path.push(d),
                Some(d) if state[d] == 1 => {
                    // A cycle through anchors: the one met last keeps its rest place relative
                    // to its parent (parents alone never cycle), and is looked at again.
                    let demote = path
                        .iter()
                        .rev()
                        .copied()
                        .find(|&x| anchor[x].is_some())
                        .expect("a cycle holds an anchored bone");
                    anchor[demote] = None;
                    if matches!(drive[demote], Drive::Follow { .. }) {
                        drive[demote] = Drive::Rest;
                    }
                    for &x in &path {
                        state[x] = 0;
                    }
                    path.truncate(1);
                }
                _ => {
                    state[b] = 2;
                    order.push(b);
                    path.pop();
                }
            }
        }
    }
    (order, anchor)
}

/// The child of source joint `j` its direction is taken toward: its mapped child, the one
/// continuing its own direction when it has several (the neck over the collars).
fn chain_child(source: &Skeleton, j: usize, bone_of: &[Option<usize>]) -> Option<usize> {
    let own = source.rest_offsets()[j];
    source
        .children(j)
        .filter(|&c| bone_of[c].is_some())
        .max_by(|&a, &b| {
            let score = |c: usize| {
                let o = source.rest_offsets()[c];
                rotation::dot(&o, &own) / (norm(&o) * norm(&own)).max(1e-12)
            };
            score(a).total_cmp(&score(b))
        })
}

/// Cumulative rest lengths along `chain`, as fractions of the whole (one per point).
fn fractions(chain: &[Vec3]) -> Vec<f64> {
    let mut acc = vec![0.0];
    for w in chain.windows(2) {
        let last = *acc.last().expect("non-empty");
        acc.push(last + norm(&sub(&w[1], &w[0])));
    }
    let total = acc.last().copied().unwrap_or(0.0).max(1e-12);
    acc.iter().map(|a| a / total).collect()
}

/// Spherical interpolation of two rotations (shortest arc).
fn slerp(a: &Mat3, b: &Mat3, t: f64) -> Mat3 {
    if t <= 0.0 {
        return *a;
    }
    let (qa, mut qb) = (rotation::to_quat(a), rotation::to_quat(b));
    let mut d: f64 = qa.iter().zip(&qb).map(|(x, y)| x * y).sum();
    if d < 0.0 {
        qb = qb.map(|x| -x);
        d = -d;
    }
    let q: [f64; 4] = if d > 0.9995 {
        std::array::from_fn(|i| qa[i] + t * (qb[i] - qa[i]))
    } else {
        let th = d.acos();
        let (wa, wb) = (((1.0 - t) * th).sin() / th.sin(), (t * th).sin() / th.sin());
        std::array::from_fn(|i| wa * qa[i] + wb * qb[i])
    };
    rotation::quat_to_matrix(&q)
}

fn invert(m: &Mat3) -> Mat3 {
    let det = rotation::det(m);
    let c =
        |r0: usize, c0: usize, r1: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [c(1, 1, 2, 2), -c(0, 1, 2, 2), c(0, 1, 1, 2)],
        [-c(1, 0, 2, 2), c(0, 0, 2, 2), -c(0, 0, 1, 2)],
        [c(1, 0, 2, 1), -c(0, 0, 2, 1), c(0, 0, 1, 1)],
    ];
    adj.map(|row| row.map(|v| v / det))
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scale(a: &Vec3, k: f64) -> Vec3 {
    a.map(|v| v * k)
}

fn norm(a: &Vec3) -> f64 {
    rotation::dot(a, a).sqrt()
}

fn unit(a: &Vec3) -> Option<Vec3> {
    let l = norm(a);
    (l > 1e-12).then(|| scale(a, 1.0 / l))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::retarget::{BoneSpec, RestTransform, RigSource};

    /// A deterministic rotation per bone (the rig's arbitrary rest axes and rolls).
    fn roll(k: usize) -> Mat3 {
        let a = [(k as f64 * 1.7).sin(), (k as f64 * 0.9).cos(), 0.4];
        rotation::axis_angle(&a, 0.3 + k as f64 * 0.77)
    }

    /// A rig built from SMPL-24's joint positions unlike SMPL in every way that breaks naive
    /// code: centimetres, Z up and facing −Y, arms lowered 45° (A-pose), a 5-bone spine in
    /// place of 3, a twist bone under each upper arm and thigh, a `root` bone on the ground,
    /// other names, and a different rest rotation on every bone. Returns the rig and the
    /// (SMPL joint, rig bone) pairs.
    pub(crate) fn test_rig(spine_bones: usize) -> (Rig, Vec<(usize, usize)>, Vec<usize>) {
        let s = Skeleton::smpl24();
        let mut p = vec![[0.0; 3]; 24];
        for j in 1..24 {
            p[j] = rotation::add(&p[s.parent(j).unwrap()], &s.rest_offsets()[j]);
        }
        // A-pose: each arm (shoulder joint down) turned 45° down about the forward axis.
        for (shoulder, sign) in [(16usize, 1.0), (17, -1.0)] {
            let pivot = p[shoulder];
            let down = rotation::axis_angle(&[0.0, 0.0, 1.0], -sign * std::f64::consts::FRAC_PI_4);
            for j in [shoulder, shoulder + 2, shoulder + 4, shoulder + 6] {
                p[j] = rotation::add(&pivot, &rotation::apply(&down, &sub(&p[j], &pivot)));
            }
        }
        // glTF axes (Y up, +Z forward) → Z up, −Y forward (+X left stays); then centimetres.
        let to_z_up = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let place = |v: &Vec3| scale(&rotation::apply(&to_z_up, v), 100.0);
        // (name, parent bone, position)
        let mut bones: Vec<(String, Option<usize>, Vec3)> = Vec::new();
        let mut pairs = Vec::new();
        let mut add = |name: &str, parent: Option<usize>, at: Vec3, joint: Option<usize>| {
            bones.push((name.to_string(), parent, at));
            if let Some(j) = joint {
                pairs.push((j, bones.len() - 1));
            }
            bones.len() - 1
        };
        let mut ground = place(&p[0]);
        ground[2] = -120.0;
        let root = add("root", None, ground, None);
        let hips = add("pelvis", Some(root), place(&p[0]), Some(0));
        // `spine_bones` spine bones: 3 on SMPL's spine joints, otherwise evenly between the
        // pelvis and the neck.
        let mut spine = Vec::new();
        let mut last = hips;
        for k in 1..=spine_bones {
            let t = k as f64 / (spine_bones + 1) as f64;
            let at = match spine_bones {
                3 => p[[3, 6, 9][k - 1]],
                _ => rotation::add(&scale(&p[0], 1.0 - t), &scale(&p[12], t)),
            };
            last = add(&format!("spine_0{k}"), Some(last), place(&at), None);
            spine.push(last);
        }
        let neck = add("neck_01", Some(last), place(&p[12]), Some(12));
        add("head", Some(neck), place(&p[15]), Some(15));
        for (side, collar, shoulder, elbow, wrist, hip, knee, ankle, toe) in [
            ("l", 13, 16, 18, 20, 1, 4, 7, 10),
            ("r", 14, 17, 19, 21, 2, 5, 8, 11),
        ] {
            let c = add(
                &format!("clavicle_{side}"),
                Some(last),
                place(&p[collar]),
                Some(collar),
            );
            let u = add(
                &format!("upperarm_{side}"),
                Some(c),
                place(&p[shoulder]),
                Some(shoulder),
            );
            let mid = scale(&rotation::add(&p[shoulder], &p[elbow]), 0.5);
            add(
                &format!("upperarm_twist_01_{side}"),
                Some(u),
                place(&mid),
                None,
            );
            let l = add(
                &format!("lowerarm_{side}"),
                Some(u),
                place(&p[elbow]),
                Some(elbow),
            );
            add(
                &format!("hand_{side}"),
                Some(l),
                place(&p[wrist]),
                Some(wrist),
            );
            let t = add(
                &format!("thigh_{side}"),
                Some(hips),
                place(&p[hip]),
                Some(hip),
            );
            let mid = scale(&rotation::add(&p[hip], &p[knee]), 0.5);
            add(
                &format!("thigh_twist_01_{side}"),
                Some(t),
                place(&mid),
                None,
            );
            let k = add(
                &format!("calf_{side}"),
                Some(t),
                place(&p[knee]),
                Some(knee),
            );
            let f = add(
                &format!("foot_{side}"),
                Some(k),
                place(&p[ankle]),
                Some(ankle),
            );
            add(&format!("ball_{side}"), Some(f), place(&p[toe]), Some(toe));
        }
        // Rest rotations: every bone its own world roll; translations in the parent's axes.
        let world: Vec<Mat3> = (0..bones.len()).map(roll).collect();
        let specs = bones
            .iter()
            .enumerate()
            .map(|(b, (name, parent, at))| {
                let (translation, rot) = match parent {
                    Some(q) => (
                        rotation::apply(&rotation::transpose(&world[*q]), &sub(at, &bones[*q].2)),
                        rotation::mul(&rotation::transpose(&world[*q]), &world[b]),
                    ),
                    None => (*at, world[b]),
                };
                BoneSpec {
                    name: name.clone(),
                    parent: *parent,
                    rest: RestTransform {
                        translation,
                        rotation: rot,
                        scale: [1.0; 3],
                    },
                }
            })
            .collect();
        let rig = Rig::new(specs, 0.01, RigSource::Code).unwrap();
        (rig, pairs, spine)
    }

    /// World positions of the rig posed with `local` rotations and the hips' translation.
    pub(crate) fn posed(rig: &Rig, local: &[Mat3], hips: usize, hips_t: &Vec3) -> Vec<Vec3> {
        let mut world = vec![rotation::IDENTITY; rig.bone_count()];
        let mut pos = vec![[0.0; 3]; rig.bone_count()];
        for b in 0..rig.bone_count() {
            let t = if b == hips {
                *hips_t
            } else {
                rig.rest()[b].translation
            };
            match rig.parent(b) {
                Some(p) => {
                    world[b] = rotation::mul(&world[p], &local[b]);
                    pos[b] = rotation::add(&pos[p], &rotation::apply(&world[p], &t));
                }
                None => {
                    world[b] = local[b];
                    pos[b] = t;
                }
            }
        }
        pos
    }

    pub(crate) fn angle(a: &Vec3, b: &Vec3) -> f64 {
        (rotation::dot(a, b) / (norm(a) * norm(b)))
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    /// A source motion in glTF axes: every joint turning about its own axis, the spine's by at
    /// most 0.25 rad (15°) per joint as people bend, limbs by up to 1 rad, the pelvis turning
    /// and drifting. Returns per frame the world rotations, positions and the pelvis position.
    pub(crate) fn source_motion(frames: usize) -> Vec<(Vec<Mat3>, Vec<Vec3>, Vec3)> {
        let s = Skeleton::smpl24();
        (0..frames)
            .map(|t| {
                let t = t as f64 * 0.15;
                let mut g = vec![rotation::IDENTITY; 24];
                let mut p = vec![[0.0; 3]; 24];
                let root = [0.3 * t.sin(), 0.9 + 0.05 * (2.0 * t).sin(), 0.4 * t];
                for j in 0..24 {
                    let amp = if [3, 6, 9].contains(&j) { 0.25 } else { 1.0 };
                    let axis = [(j as f64).sin(), (j as f64 * 2.3).cos(), 0.5];
                    let r = rotation::axis_angle(&axis, amp * (t + j as f64).sin());
                    match s.parent(j) {
                        None => {
                            g[j] = r;
                            p[j] = root;
                        }
                        Some(q) => {
                            g[j] = rotation::mul(&g[q], &r);
                            p[j] =
                                rotation::add(&p[q], &rotation::apply(&g[q], &s.rest_offsets()[j]));
                        }
                    }
                }
                (g, p, root)
            })
            .collect()
    }

    #[test]
    fn mapped_bones_point_where_the_source_bones_point_on_an_unlike_rig() {
        for (spine_bones, spine_bound) in [(3, 1e-4), (5, 2.0), (1, 2.5)] {
            let (worst_limb, worst_spine) = directions_off(spine_bones);
            assert!(
                worst_limb < 1e-4,
                "{spine_bones} spine bones: a limb is {worst_limb}° off"
            );
            assert!(
                worst_spine < spine_bound,
                "{spine_bones} spine bones: hips to neck is {worst_spine}° off"
            );
        }
    }

    /// The largest angle between a mapped rig bone and its source bone over a clip, for limbs
    /// and for hips–neck, with a rig of `spine_bones` spine bones.
    fn directions_off(spine_bones: usize) -> (f64, f64) {
        let (rig, pairs, spine) = test_rig(spine_bones);
        let source = Skeleton::smpl24();
        let tr = Transfer::new(source, &rig, &pairs, &[3, 6, 9], &spine).unwrap();
        let motion = source_motion(40);
        let n = rig.bone_count();
        let (mut world, mut local) = (vec![rotation::IDENTITY; n], vec![rotation::IDENTITY; n]);
        // The rig's axes: Z up, −Y forward, +X left (source: Y up, +Z forward, +X left).
        let axes = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let bone = |name: &str| rig.find(name).unwrap();
        // (source from, source to, rig from, rig to): limbs, neck–head.
        let limbs = [
            (16, 18, "upperarm_l", "lowerarm_l"),
            (18, 20, "lowerarm_l", "hand_l"),
            (17, 19, "upperarm_r", "lowerarm_r"),
            (19, 21, "lowerarm_r", "hand_r"),
            (1, 4, "thigh_l", "calf_l"),
            (4, 7, "calf_l", "foot_l"),
            (2, 5, "thigh_r", "calf_r"),
            (5, 8, "calf_r", "foot_r"),
            (12, 15, "neck_01", "head"),
            (13, 16, "clavicle_l", "upperarm_l"),
            (7, 10, "foot_l", "ball_l"),
        ];
        let (mut worst_limb, mut worst_spine) = (0.0f64, 0.0f64);
        let mut offset: Option<Vec3> = None;
        for (t, (g, sp, root)) in motion.iter().enumerate() {
            let hips_t = tr.frame(g, root, &mut world, &mut local).unwrap();
            let rp = posed(&rig, &local, tr.hips(), &hips_t);
            for (a, b, ra, rb) in limbs {
                let want = rotation::apply(&axes, &sub(&sp[b], &sp[a]));
                let got = sub(&rp[bone(rb)], &rp[bone(ra)]);
                worst_limb = worst_limb.max(angle(&want, &got));
            }
            let want = rotation::apply(&axes, &sub(&sp[12], &sp[0]));
            let got = sub(&rp[bone("neck_01")], &rp[bone("pelvis")]);
            worst_spine = worst_spine.max(angle(&want, &got));
            // Twist bones follow their limb at rest: the twist bone stays on the bone's line.
            let on_line = angle(
                &sub(&rp[bone("upperarm_twist_01_l")], &rp[bone("upperarm_l")]),
                &sub(&rp[bone("lowerarm_l")], &rp[bone("upperarm_l")]),
            );
            assert!(on_line < 1e-4, "twist bone off the arm by {on_line}°");
            // Legs and hips land where the source's are, in rig axes and centimetres (the
            // same skeleton: a hips-height ratio of 1), up to one offset for the whole clip (the
            // floors): every leg joint, every frame.
            for (j, name) in [(0, "pelvis"), (4, "calf_l"), (8, "foot_r"), (10, "ball_l")] {
                let want = scale(&rotation::apply(&axes, &sp[j]), 100.0);
                let off = sub(&rp[bone(name)], &want);
                let first = offset.get_or_insert(off);
                let drift = norm(&sub(&off, first));
                assert!(drift < 1e-6, "frame {t} {name}: {drift} cm off");
            }
        }
        eprintln!(
            "{spine_bones} spine bones: worst limb {worst_limb:.2e}°, hips–neck {worst_spine:.3}°"
        );
        (worst_limb, worst_spine)
    }
}
