//! The corpus generator's puppet: a handful of per-frame controls (pelvis placement, spine and
//! head angles, ankle targets, wrist targets) turned into SMPL-24 local rotations by analytic
//! two-bone IK, and encoded as `smpl24_6d` features.
//!
//! Everything here works in SMPL's own body frame used as a Y-up world ("rig frame": +Y up, +Z
//! the canonical forward, +X the character's left, metres, ground at y = 0). The native Z-up
//! world of `smpl24_6d` is that frame tilted by `T = Rx(+90°)` (y → z, z → −y), so the encoder
//! prepends `T` to the root rotation and rotates the pelvis position; joint rotations below the
//! root are body-frame already (see `motion::convention`).
//!
//! The ground is where the rest pose's lowest joints (L_Foot/R_Foot, the balls of the feet)
//! are when the foot is flat, so a flat foot's ankle sits [`Rig::ankle_heights`] above it (the
//! template is not symmetric: the right ankle sits 7.6 mm lower than the left).

use std::sync::OnceLock;

use flame::motion::rotation::{self as rot, Mat3, Vec3, IDENTITY};
use flame::motion::skeleton::Skeleton;

/// Frames per second of every corpus motion (FLAME's rate).
pub const FPS: f64 = 20.0;

/// SMPL-24 joint indices used by the generator and the classifier
/// (docs/official/smpl.md#joint-order).
pub mod joint {
    pub const PELVIS: usize = 0;
    pub const L_HIP: usize = 1;
    pub const R_HIP: usize = 2;
    pub const SPINE1: usize = 3;
    pub const L_KNEE: usize = 4;
    pub const R_KNEE: usize = 5;
    pub const SPINE2: usize = 6;
    pub const L_ANKLE: usize = 7;
    pub const R_ANKLE: usize = 8;
    pub const SPINE3: usize = 9;
    pub const L_FOOT: usize = 10;
    pub const R_FOOT: usize = 11;
    pub const NECK: usize = 12;
    pub const L_COLLAR: usize = 13;
    pub const R_COLLAR: usize = 14;
    pub const HEAD: usize = 15;
    pub const L_SHOULDER: usize = 16;
    pub const R_SHOULDER: usize = 17;
    pub const L_ELBOW: usize = 18;
    pub const R_ELBOW: usize = 19;
    pub const L_WRIST: usize = 20;
    pub const R_WRIST: usize = 21;
    pub const JOINTS: usize = 24;
}

/// `[left, right]` index of a limb; `SIDE[s]` is +1 for the left (+X) and −1 for the right.
pub const SIDE: [f64; 2] = [1.0, -1.0];

/// A foot target: ankle position (rig frame), heading of the foot, and pitch (toes down > 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Foot {
    pub ankle: Vec3,
    pub yaw: f64,
    pub pitch: f64,
}

/// One frame of controls. Angles in radians; `yaw` > 0 turns left (about +Y).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Pelvis joint position in the rig frame.
    pub pelvis: Vec3,
    /// Heading of the pelvis (0 = facing +Z).
    pub yaw: f64,
    /// Forward tilt of the pelvis.
    pub pitch: f64,
    /// Sideways tilt of the pelvis (> 0 drops the right hip).
    pub roll: f64,
    /// `[forward bend, bend to the left, twist to the left]` summed over the three spine joints.
    pub spine: Vec3,
    /// `[nod down, tilt to the left, turn to the left]` summed over neck and head.
    pub head: Vec3,
    pub feet: [Foot; 2],
    /// Wrist targets relative to each shoulder, in the chest's frame, as `[out, up, forward]`
    /// ("out" is away from the body's midline, so the two sides are authored alike).
    pub hands: [Vec3; 2],
}

/// A two-bone chain: the middle joint's offset from the upper joint, the end's offset from the
/// middle, and the hinge axis (upper joint's frame) about which a positive angle bends it.
#[derive(Clone, Copy, Debug)]
struct Chain {
    o1: Vec3,
    o2: Vec3,
    hinge: Vec3,
    /// Terms of `o1 · Rot(hinge, θ) o2 = a cos θ + b sin θ + c`.
    a: f64,
    b: f64,
    c: f64,
}

/// Skeleton constants the solver needs, derived once from the SMPL-24 rest offsets.
#[derive(Debug)]
pub struct Rig {
    offsets: Vec<Vec3>,
    legs: [Chain; 2],
    arms: [Chain; 2],
    /// Height of a flat foot's ankle above the ground, `[left, right]`.
    pub ankle_heights: [f64; 2],
    /// Pelvis height of the neutral standing pose (knees flexed by a few degrees).
    pub stand_height: f64,
}

/// Rig-frame → native Z-up world: `Rx(+90°)`.
const TILT: Mat3 = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];

impl Chain {
    fn new(o1: Vec3, o2: Vec3, hinge: Vec3) -> Chain {
        let (h1, h2) = (rot::dot(&hinge, &o1), rot::dot(&hinge, &o2));
        Chain {
            o1,
            o2,
            hinge,
            a: rot::dot(&o1, &o2) - h1 * h2,
            b: rot::dot(&o1, &rot::cross(&hinge, &o2)),
            c: h1 * h2,
        }
    }

    fn reach_sq(&self, extremum: f64) -> f64 {
        norm_sq(&self.o1) + norm_sq(&self.o2) + 2.0 * (self.c + extremum)
    }

    /// The longest distance from the upper to the end joint (the straightest bend).
    fn max_reach(&self) -> f64 {
        self.reach_sq(self.a.hypot(self.b)).sqrt()
    }

    /// Bend angle giving the distance `d` (clamped into the reachable range), ≥ the straightest.
    fn bend_for(&self, d: f64) -> f64 {
        let r = self.a.hypot(self.b);
        let (lo, hi) = (self.reach_sq(-r).sqrt(), self.reach_sq(r).sqrt());
        let d = d.clamp(lo * 1.001 + 1e-6, hi * 0.9995);
        let k = (d * d - norm_sq(&self.o1) - norm_sq(&self.o2)) / 2.0 - self.c;
        self.b.atan2(self.a) + (k / r).clamp(-1.0, 1.0).acos()
    }

    /// Solves the chain from `root` to `target`, bending about the world direction `hinge_w`
    /// (any vector not parallel to the limb). Returns the upper joint's world rotation and the
    /// middle joint's local rotation.
    fn solve(&self, root: &Vec3, target: &Vec3, hinge_w: &Vec3) -> (Mat3, Mat3) {
        let v_w = sub(target, root);
        let theta = self.bend_for(norm_sq(&v_w).sqrt());
        let bend = rot::axis_angle(&self.hinge, theta);
        let v_l = rot::add(&self.o1, &rot::apply(&bend, &self.o2));
        let local = frame_from(&v_l, &self.hinge);
        let world = frame_from(&v_w, hinge_w);
        (rot::mul(&world, &rot::transpose(&local)), bend)
    }
}

/// The rotation whose columns are `v̂`, the part of `h` orthogonal to `v` (normalised), and
/// their cross product.
fn frame_from(v: &Vec3, h: &Vec3) -> Mat3 {
    let e1 = normalize(v);
    let e2 = normalize(&sub(h, &scale(&e1, rot::dot(h, &e1))));
    let e3 = rot::cross(&e1, &e2);
    [
        [e1[0], e2[0], e3[0]],
        [e1[1], e2[1], e3[1]],
        [e1[2], e2[2], e3[2]],
    ]
}

pub(crate) fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn scale(a: &Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

pub(crate) fn norm_sq(a: &Vec3) -> f64 {
    rot::dot(a, a)
}

pub(crate) fn normalize(a: &Vec3) -> Vec3 {
    scale(a, 1.0 / norm_sq(a).sqrt().max(1e-12))
}

/// Rotation by `a` about +Y (heading; > 0 turns left).
pub(crate) fn ry(a: f64) -> Mat3 {
    rot::axis_angle(&[0.0, 1.0, 0.0], a)
}

/// Rotation by `a` about +X (> 0 tips +Y towards +Z: a forward bend, a knee flexion).
pub(crate) fn rx(a: f64) -> Mat3 {
    rot::axis_angle(&[1.0, 0.0, 0.0], a)
}

/// Rotation by `a` about +Z (> 0 tips +Y towards −X: leaning to the right).
pub(crate) fn rz(a: f64) -> Mat3 {
    rot::axis_angle(&[0.0, 0.0, 1.0], a)
}

/// The ground-plane unit vector a heading of `yaw` faces.
pub fn forward(yaw: f64) -> Vec3 {
    [yaw.sin(), 0.0, yaw.cos()]
}

/// The ground-plane unit vector to the left of a heading of `yaw`.
pub fn left(yaw: f64) -> Vec3 {
    [yaw.cos(), 0.0, -yaw.sin()]
}

impl Rig {
    /// The SMPL-24 rig (built once).
    pub fn get() -> &'static Rig {
        static R: OnceLock<Rig> = OnceLock::new();
        R.get_or_init(|| {
            use joint::*;
            let o = Skeleton::smpl24().rest_offsets().to_vec();
            let knee = [1.0, 0.0, 0.0];
            let legs = [
                Chain::new(o[L_KNEE], o[L_ANKLE], knee),
                Chain::new(o[R_KNEE], o[R_ANKLE], knee),
            ];
            // T-pose palms face down, so the elbow folds the forearm forward: about −Y on the
            // left (arm along +X), +Y on the right.
            let arms = [
                Chain::new(o[L_ELBOW], o[L_WRIST], [0.0, -1.0, 0.0]),
                Chain::new(o[R_ELBOW], o[R_WRIST], [0.0, 1.0, 0.0]),
            ];
            let ankle_heights = [-o[L_FOOT][1], -o[R_FOOT][1]];
            let hip_drop = -o[L_HIP][1];
            let stand_height = ankle_heights[0] + hip_drop + STAND_REACH * legs[0].max_reach();
            Rig {
                offsets: o,
                legs,
                arms,
                ankle_heights,
                stand_height,
            }
        })
    }

    /// Longest hip–ankle distance (m).
    pub fn leg_reach(&self) -> f64 {
        self.legs[0].max_reach().min(self.legs[1].max_reach())
    }

    /// Longest shoulder–wrist distance (m).
    pub fn arm_reach(&self) -> f64 {
        self.arms[0].max_reach().min(self.arms[1].max_reach())
    }

    /// The pelvis's world rotation for a pose.
    pub fn pelvis_rotation(pose: &Pose) -> Mat3 {
        rot::mul(&ry(pose.yaw), &rot::mul(&rx(pose.pitch), &rz(pose.roll)))
    }

    /// Hip joint position of `side` relative to the pelvis, for a pelvis rotation.
    pub fn hip_offset(&self, pelvis_rot: &Mat3, side: usize) -> Vec3 {
        rot::apply(pelvis_rot, &self.offsets[joint::L_HIP + side])
    }

    /// The 24 local rotations of a pose; entry 0 is the root's rotation in the rig frame.
    pub fn solve(&self, pose: &Pose) -> [Mat3; 24] {
        use joint::*;
        let o = &self.offsets;
        let mut local = [IDENTITY; 24];
        let g0 = Rig::pelvis_rotation(pose);
        local[PELVIS] = g0;

        for s in 0..2 {
            let foot = &pose.feet[s];
            let hip = rot::add(&pose.pelvis, &self.hip_offset(&g0, s));
            let (g_hip, knee) = self.legs[s].solve(&hip, &foot.ankle, &left(foot.yaw));
            local[L_HIP + s] = rot::mul(&rot::transpose(&g0), &g_hip);
            local[L_KNEE + s] = knee;
            let g_knee = rot::mul(&g_hip, &knee);
            let g_ankle = rot::mul(&ry(foot.yaw), &rx(foot.pitch));
            local[L_ANKLE + s] = rot::mul(&rot::transpose(&g_knee), &g_ankle);
        }

        // The spine bends over three joints in the proportions people show (most in the lower
        // back); the head's turn is shared between neck and head.
        let [bend, side_bend, twist] = pose.spine;
        for (j, share) in [(SPINE1, 0.4), (SPINE2, 0.35), (SPINE3, 0.25)] {
            local[j] = rot::mul(
                &ry(twist * share),
                &rot::mul(&rx(bend * share), &rz(-side_bend * share)),
            );
        }
        let [nod, tilt, turn] = pose.head;
        for (j, share) in [(NECK, 0.5), (HEAD, 0.5)] {
            local[j] = rot::mul(
                &ry(turn * share),
                &rot::mul(&rx(nod * share), &rz(-tilt * share)),
            );
        }

        let g3 = rot::mul(&g0, &local[SPINE1]);
        let p3 = rot::add(&pose.pelvis, &rot::apply(&g0, &o[SPINE1]));
        let g6 = rot::mul(&g3, &local[SPINE2]);
        let p6 = rot::add(&p3, &rot::apply(&g3, &o[SPINE2]));
        let g9 = rot::mul(&g6, &local[SPINE3]);
        let p9 = rot::add(&p6, &rot::apply(&g6, &o[SPINE3]));
        for s in 0..2 {
            // Collars stay at rest, so the shoulder hangs off the chest frame directly.
            let p13 = rot::add(&p9, &rot::apply(&g9, &o[L_COLLAR + s]));
            let shoulder = rot::add(&p13, &rot::apply(&g9, &o[L_SHOULDER + s]));
            let [out, up, fwd] = pose.hands[s];
            let rel = [SIDE[s] * out, up, fwd];
            let target = rot::add(&shoulder, &rot::apply(&g9, &rel));
            // The elbow points back, down and out: a pole away from every arm direction used.
            let pole = rot::apply(&g9, &normalize(&[SIDE[s] * 0.3, -0.5, -1.0]));
            let v = normalize(&sub(&target, &shoulder));
            let hinge = scale(&rot::cross(&v, &pole), -1.0);
            let (g_sh, elbow) = self.arms[s].solve(&shoulder, &target, &hinge);
            local[L_SHOULDER + s] = rot::mul(&rot::transpose(&g9), &g_sh);
            local[L_ELBOW + s] = elbow;
        }
        local
    }

    /// `[frames × 147]` `smpl24_6d` features of a pose sequence (native Z-up world).
    pub fn encode(&self, poses: &[Pose]) -> Vec<f32> {
        let mut out = Vec::with_capacity(poses.len() * 147);
        for pose in poses {
            let local = self.solve(pose);
            let pelvis = rot::apply(&TILT, &pose.pelvis);
            let trans = sub(&pelvis, &self.offsets[0]);
            out.extend(trans.iter().map(|&v| v as f32));
            for (j, r) in local.iter().enumerate() {
                let r = if j == 0 { rot::mul(&TILT, r) } else { *r };
                out.extend(rot::to_6d_rows(&r).iter().map(|&v| v as f32));
            }
        }
        out
    }

    /// The neutral standing pose at a ground position `(x, z)` facing `yaw`.
    pub fn stand(&self, x: f64, z: f64, yaw: f64) -> Pose {
        let feet = [0, 1].map(|s| self.neutral_foot(x, z, yaw, s));
        Pose {
            pelvis: [x, self.stand_height, z],
            yaw,
            pitch: 0.0,
            roll: 0.0,
            spine: [0.0; 3],
            head: [0.0; 3],
            feet,
            hands: [HANG; 2],
        }
    }

    /// Where foot `side` stands in the neutral pose under a pelvis at `(x, z)` facing `yaw`.
    pub fn neutral_foot(&self, x: f64, z: f64, yaw: f64, side: usize) -> Foot {
        let (f, l) = (forward(yaw), left(yaw));
        let w = SIDE[side] * STANCE_HALF_WIDTH;
        Foot {
            ankle: [
                x + w * l[0] - 0.03 * f[0],
                self.ankle_heights[side],
                z + w * l[2] - 0.03 * f[2],
            ],
            yaw: yaw + SIDE[side] * TOE_OUT,
            pitch: 0.0,
        }
    }
}

/// Hip–ankle distance of the neutral stance as a fraction of the leg's reach (knees ~15° bent,
/// far enough from straight that small pelvis motions do not whip the knee angle).
pub const STAND_REACH: f64 = 0.992;
/// Wrist target of an arm hanging relaxed (`[out, up, forward]` from the shoulder).
pub const HANG: Vec3 = [0.04, -0.47, 0.05];
/// Ankle distance from the body's midline in the neutral stance.
pub const STANCE_HALF_WIDTH: f64 = 0.095;
/// Feet turn out by this much in the neutral stance.
pub const TOE_OUT: f64 = 0.08;

#[cfg(test)]
mod tests {
    use super::*;
    use flame::motion::{Convention, Format, Poses, ReadOptions};

    fn decode(poses: &[Pose]) -> Vec<Vec3> {
        let f = Rig::get().encode(poses);
        Poses::decode(
            Format::Smpl24Rot6d,
            &f,
            poses.len(),
            &ReadOptions::default(),
        )
        .unwrap()
        .positions(Convention::Native)
    }

    #[test]
    fn neutral_stance_stands_on_the_native_ground_facing_minus_y() {
        let rig = Rig::get();
        let p = decode(&[rig.stand(0.0, 0.0, 0.0)]);
        // Ground = z 0 at the balls of the feet (the lowest joints), pelvis above the origin.
        for j in [joint::L_FOOT, joint::R_FOOT] {
            assert!(p[j][2].abs() < 1e-6, "{:?}", p[j]);
        }
        let lowest = p.iter().map(|q| q[2]).fold(f64::MAX, f64::min);
        assert!(lowest > -1e-6);
        // Features are f32, so the origin holds to f32 rounding of the rest-pelvis offset.
        assert!(p[0][0].abs() < 1e-6 && p[0][1].abs() < 1e-6);
        assert!((p[0][2] - rig.stand_height).abs() < 1e-6);
        // Facing −Y: the toes are at smaller y than the ankles; left (L_Hip) is +X.
        assert!(p[joint::L_FOOT][1] < p[joint::L_ANKLE][1] - 0.05);
        assert!(p[joint::L_HIP][0] > 0.05 && p[joint::R_HIP][0] < -0.05);
        assert!(p[joint::HEAD][2] > 1.4);
    }

    #[test]
    fn ik_puts_ankles_and_wrists_on_their_targets() {
        let rig = Rig::get();
        let mut pose = rig.stand(0.3, -0.2, 0.7);
        pose.feet[0].ankle[1] += 0.2;
        pose.feet[0].ankle[2] += 0.15;
        pose.pelvis[1] -= 0.1;
        pose.spine = [0.3, 0.1, -0.2];
        pose.hands = [[0.1, 0.35, 0.1], [-0.1, -0.05, 0.4]];
        let p = decode(&[pose]);
        for s in 0..2 {
            let a = rot::apply(&TILT, &pose.feet[s].ankle);
            let got = p[joint::L_ANKLE + s];
            assert!(
                norm_sq(&sub(&a, &got)).sqrt() < 1e-5,
                "{s}: {got:?} vs {a:?}"
            );
        }
        // Wrists: distance to the shoulder matches the target's length.
        for s in 0..2 {
            let d = norm_sq(&sub(&p[joint::L_WRIST + s], &p[joint::L_SHOULDER + s])).sqrt();
            assert!((d - norm_sq(&pose.hands[s]).sqrt()).abs() < 1e-5);
        }
    }
}
