//! A whole rig pose from a libflame pose ([`Target::pose`]) and a whole clip
//! ([`Target::motion`]): the rest-relative transfer, then two-bone IK on the rig's legs (and,
//! when asked, arms) so proportions that differ from the source's do not make the feet slide or
//! float.
//!
//! **Feet.** The hips translation is scaled by the legs' ratio
//! ([`crate::retarget::Transfer::scale`]), but a rig's thigh/shin split, foot height and hip
//! width still differ from SMPL's, so copied leg directions alone put the ankles a little off
//! where the scaled source's are: a planted foot floats, sinks or slides. While the source's
//! foot is planted (its contacts, ramping in and out over four frames; every frame for poses
//! without contacts or a single [`Target::pose`]), each leg (upper leg → lower leg → foot) is
//! solved so the ankle reaches
//! - in height, the source ankle placed on the rig ([`crate::retarget::Transfer::place`]: the
//!   same map that places the hips), raised by the difference of the two skeletons' ankle
//!   heights below the hips at rest (`h_rig − s·h_source`), so a source foot flat on its floor
//!   is flat on the rig's;
//! - horizontally, where the rotations put it, moved by the clip's anchor in
//!   [`Target::motion`]: over each contact the planted heel is held at one place (or, while
//!   only the toes are down, the toes are), and on the frames around it the toes move as the
//!   scaled source's do, whole while the source's toes are within the contact band, then
//!   fading out with the weight (Kovar, Schreiner and Gleicher,
//!   "Footskate Cleanup for Motion Capture Editing", SCA 2002, section 4). Aiming at the
//!   placed source ankle in 3D instead would bend the legs of every rig whose thigh/shin split
//!   is not SMPL's, by up to 8 degrees on a child's proportions, for no contact gained. A hold
//!   is taken only as far as it turns the thigh and shin at most `HOLD_TURN` (8°) from the
//!   transferred leg and stays within reach: near full extension a centimetre nearer costs
//!   ~17° of knee, and on a rig whose thigh/shin split is far from SMPL's (Blender's Rigify
//!   metarig, 54/46 against 49/51) a full hold bent the legs 13.6° off the source's. The foot
//!   gives the rest, a few millimetres a frame, far below a skating speed.
//!
//! Contacts of the source therefore stay contacts, held where the source's are held (the foot
//! cleanup of the game-ready clips runs on the source before this), and the knee keeps its
//! bend plane (`crate::motion::ik`). The foot keeps its world rotation, then is pitched about
//! the ankle so its toes stand at the source's toes' height; bones between thigh and shin
//! (twist bones) turn with the thigh.
//!
//! **Hands** (optional, [`Options::hands`]): the same for upper arm → forearm → hand, the wrist
//! reaching the source's wrist placed on the rig, for props and contacts with the body.
//!
//! A pose is written into a caller-owned [`RigPose`]; nothing is allocated per frame.

use super::bonemap::HumanBone;
use super::target::Target;
use crate::error::{invalid_arg, Result};
use crate::motion::ik;
use crate::motion::rotation::{self, Mat3, Vec3, IDENTITY};
use crate::motion::{Convention, Poses};

/// What runs after the rotations are carried over.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Options {
    /// Two-bone IK on the legs onto the source's placed ankles (default on).
    pub feet: bool,
    /// Two-bone IK on the arms onto the source's placed wrists (default off).
    pub hands: bool,
}

impl Default for Options {
    fn default() -> Options {
        Options {
            feet: true,
            hands: false,
        }
    }
}

/// One rig pose: per bone world and local rotations and world positions (rig axes and units),
/// and the hips translation relative to its parent's rest frame (what a file's hips node
/// takes). Made once per rig ([`RigPose::new`]) and rewritten by every [`Target::pose`].
#[derive(Clone, Debug)]
pub struct RigPose {
    /// Every bone's world rotation (rig axes; rest rotations included, so at rest these are
    /// the rig's rest world rotations). Row-major, acting on column vectors.
    pub world: Vec<Mat3>,
    /// Every bone's rotation relative to its parent: what a file's node or an engine's bone
    /// takes.
    pub local: Vec<Mat3>,
    /// Every bone's world position (rig axes and units).
    pub positions: Vec<Vec3>,
    /// Every bone's translation relative to its parent (rig units): the rest translation,
    /// except for the bones of [`Target::moving`].
    pub translation: Vec<Vec3>,
    /// The hips bone's translation relative to its parent's rest frame (rig units).
    pub hips: Vec3,
}

impl RigPose {
    /// Storage for `target`'s rig, at identity.
    pub fn new(target: &Target) -> RigPose {
        let n = target.rig().bone_count();
        RigPose {
            world: vec![IDENTITY; n],
            local: vec![IDENTITY; n],
            positions: vec![[0.0; 3]; n],
            translation: target.rig().rest().iter().map(|r| r.translation).collect(),
            hips: [0.0; 3],
        }
    }
}

/// A retargeted clip: `[frames × bones]` local rotations and world positions, `[frames]` hips
/// translations, at `fps`.
#[derive(Clone, Debug)]
pub struct RigMotion {
    /// Frames per second (the source poses').
    pub fps: f64,
    /// Number of frames.
    pub frames: usize,
    /// Number of the rig's bones (the stride of the per-bone arrays).
    pub bones: usize,
    /// The rig's hips bone (the one bone whose translation moves).
    pub hips_bone: usize,
    /// Parent-relative rotations in the rig's bone frames (rest rotations included: at rest
    /// these are the rig's rest local rotations).
    pub local: Vec<Mat3>,
    /// `[frames × bones]` world rotations (rig axes, rest rotations included).
    pub world: Vec<Mat3>,
    /// `[frames × bones]` world positions (rig axes and units).
    pub positions: Vec<Vec3>,
    /// `[frames × bones]` translations relative to the parent (rig units): the rest
    /// translation except for the bones of `moving`.
    pub translation: Vec<Vec3>,
    /// Bones whose translation is animated: the hips, then the bones beside the body
    /// ([`super::Transfer::anchor`]).
    pub moving: Vec<usize>,
    /// The hips translation relative to its parent bone's rest frame, rig units.
    pub hips: Vec<Vec3>,
}

impl RigMotion {
    /// Frame `t`'s local rotations.
    pub fn local_frame(&self, t: usize) -> &[Mat3] {
        &self.local[t * self.bones..(t + 1) * self.bones]
    }

    /// Frame `t`'s world rotations.
    pub fn world_frame(&self, t: usize) -> &[Mat3] {
        &self.world[t * self.bones..(t + 1) * self.bones]
    }

    /// Frame `t`'s world positions.
    pub fn positions_frame(&self, t: usize) -> &[Vec3] {
        &self.positions[t * self.bones..(t + 1) * self.bones]
    }

    /// Frame `t`'s translations.
    pub fn translation_frame(&self, t: usize) -> &[Vec3] {
        &self.translation[t * self.bones..(t + 1) * self.bones]
    }
}

/// A two-bone chain of the rig and the source joint its end follows.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Chain {
    upper: usize,
    lower: usize,
    end: usize,
    source_end: usize,
    /// Added to the placed source end (rig units, along up): `h_rig − s·h_source` for
    /// ankles, nothing for wrists.
    lift: f64,
    /// A leg's toes (rig bone, source joint, lift as the ankle's): while planted, the foot is
    /// pitched about the ankle so the toes stand at the source's toes' height.
    toe: Option<(usize, usize, f64)>,
}

/// Which turn of a chain's solution a bone takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Part {
    Upper,
    Lower,
}

/// The IK data of a [`Target`], made once with it.
#[derive(Clone, Debug)]
pub(crate) struct Limbs {
    /// Legs (left, right) then arms (left, right).
    chains: [Chain; 4],
    /// Per bone: the chain (index into `chains`) whose solution turns it, and which turn.
    /// The end's subtree keeps its world rotations.
    part: Vec<Option<(u8, Part)>>,
    /// Per bone: the leg (0 left, 1 right) whose foot's subtree holds it (the foot included).
    foot: Vec<Option<u8>>,
    /// Per bone: the uniform scale of its rest world transform (positions of children are
    /// `world · scale · translation`).
    world_scale: Vec<f64>,
}

impl Limbs {
    pub(crate) fn new(
        target_rig: &super::Rig,
        map: &super::bonemap::BoneMap,
        transfer: &super::Transfer,
    ) -> Result<Limbs> {
        use super::transfer::smpl;
        use HumanBone::*;
        let rig = target_rig;
        let bone = |h: HumanBone| {
            map.bone(h)
                .ok_or_else(|| invalid_arg!("the bone map has no `{}`", h.name()))
        };
        let src = crate::motion::Skeleton::smpl24();
        let mut src_pos = vec![[0.0; 3]; 24];
        for j in 1..24 {
            let p = src.parent(j).expect("only the root has none");
            src_pos[j] = rotation::add(&src_pos[p], &src.rest_offsets()[j]);
        }
        let up = transfer.up();
        let pos = rig.rest_world_positions();
        let mut chains = [Chain {
            upper: 0,
            lower: 0,
            end: 0,
            source_end: 0,
            lift: 0.0,
            toe: None,
        }; 4];
        let specs = [
            (
                LeftUpperLeg,
                LeftLowerLeg,
                LeftFoot,
                smpl::L_ANKLE,
                Some(LeftToes),
            ),
            (
                RightUpperLeg,
                RightLowerLeg,
                RightFoot,
                smpl::R_ANKLE,
                Some(RightToes),
            ),
            (LeftUpperArm, LeftLowerArm, LeftHand, 20, None),
            (RightUpperArm, RightLowerArm, RightHand, 21, None),
        ];
        // A joint's rest height below the hips, the rig's against the scaled source's (source
        // up is glTF's +Y; `up` is where it points on the rig).
        let lift_of = |bone: usize, joint: usize| {
            let rig_h = rotation::dot(&sub(&pos[bone], &pos[transfer.hips()]), &up);
            rig_h - transfer.scale() * src_pos[joint][1]
        };
        for (c, (u, l, e, j, toes)) in specs.into_iter().enumerate() {
            let end = bone(e)?;
            let leg = toes.is_some();
            let lift = if leg { lift_of(end, j) } else { 0.0 };
            let toe = toes.and_then(|t| map.bone(t)).map(|t| {
                let joint = if c == 0 { smpl::L_FOOT } else { smpl::R_FOOT };
                (t, joint, lift_of(t, joint))
            });
            chains[c] = Chain {
                upper: bone(u)?,
                lower: bone(l)?,
                end,
                source_end: j,
                lift,
                toe,
            };
        }
        let n = rig.bone_count();
        let under = |b: usize, top: usize| {
            let mut at = Some(b);
            while let Some(x) = at {
                if x == top {
                    return true;
                }
                at = rig.parent(x);
            }
            false
        };
        let mut part = vec![None; n];
        for (c, ch) in chains.iter().enumerate() {
            if !(under(ch.lower, ch.upper) && under(ch.end, ch.lower)) {
                return Err(invalid_arg!(
                    "rig bones `{}`, `{}` and `{}` are not one chain",
                    rig.name(ch.upper),
                    rig.name(ch.lower),
                    rig.name(ch.end)
                ));
            }
            for (b, slot) in part.iter_mut().enumerate() {
                if under(b, ch.end) {
                    continue;
                }
                if under(b, ch.lower) {
                    *slot = Some((c as u8, Part::Lower));
                } else if under(b, ch.upper) {
                    *slot = Some((c as u8, Part::Upper));
                }
            }
        }
        let foot = (0..n)
            .map(|b| (0..2u8).find(|&c| under(b, chains[c as usize].end)))
            .collect();
        let world_scale = rig
            .rest_world_linear()
            .iter()
            .map(|m| rotation::det(m).abs().cbrt())
            .collect();
        Ok(Limbs {
            chains,
            part,
            foot,
            world_scale,
        })
    }
}

/// Frames over which a foot's IK weight ramps in and out around its contacts.
const CONTACT_RAMP: usize = 4;

/// Metres: the source toe height under which a foot counts as near the floor (the contact
/// height of the foot-skating metric and of libflame's contact detection,
/// [`crate::motion::contacts::ContactParams::height`]).
const CONTACT_HEIGHT: f64 = 0.05;

/// Per frame, each foot's IK weight (left, right): 1 while the source's ankle or toe is
/// planted, ramping linearly to 0 over [`CONTACT_RAMP`] frames before and after, so the leg
/// eases into its planted place; empty when the poses carry no contacts (then every frame is
/// weighted 1).
fn contact_weights(poses: &Poses) -> Vec<[f64; 2]> {
    let Some(contacts) = poses.foot_contacts() else {
        return Vec::new();
    };
    let n = contacts.len();
    let planted = |t: usize, side: usize| {
        contacts[t][2 * side]
            .max(contacts[t][2 * side + 1])
            .clamp(0.0, 1.0)
    };
    (0..n)
        .map(|t| {
            [0, 1].map(|side| {
                let lo = t.saturating_sub(CONTACT_RAMP);
                let hi = (t + CONTACT_RAMP).min(n - 1);
                (lo..=hi)
                    .map(|u| {
                        let d = u.abs_diff(t) as f64;
                        planted(u, side) * (1.0 - d / (CONTACT_RAMP as f64 + 1.0))
                    })
                    .fold(0.0, f64::max)
            })
        })
        .collect()
}

/// Radians (8°): the most a held foot may turn its thigh or shin away from the transferred
/// leg (`pose_anchored`). Leg directions are to stay within 10° of the source's; this leaves
/// room for the height goal's own bend.
const HOLD_TURN: f64 = 8.0 * std::f64::consts::PI / 180.0;

/// Halvings of the anchor's share when the hold is limited: 2⁻¹² of a few centimetres.
const HOLD_BISECTIONS: usize = 12;

/// The angle between two vectors (0 when either is zero).
fn angle(a: &Vec3, b: &Vec3) -> f64 {
    let c = rotation::cross(a, b);
    rotation::dot(&c, &c).sqrt().atan2(rotation::dot(a, b))
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dist(a: &Vec3, b: &Vec3) -> f64 {
    let d = sub(a, b);
    rotation::dot(&d, &d).sqrt()
}

impl Target {
    /// One rig pose from one source frame, all in glTF axes: `source_world` the joints' world
    /// rotations, `source_positions` their positions and `source_root` the pelvis (metres,
    /// floor at height 0). Allocates nothing.
    pub fn pose(
        &self,
        source_world: &[Mat3],
        source_positions: &[Vec3],
        source_root: &Vec3,
        options: &Options,
        out: &mut RigPose,
    ) -> Result<()> {
        self.pose_weighted(
            source_world,
            source_positions,
            source_root,
            options,
            [1.0; 2],
            out,
        )
    }

    /// [`Target::pose`] with the feet's IK weighted per foot (left, right; 0 to 1): the ankle
    /// goes that far from where the rotations put it toward the placed source ankle.
    /// [`Target::motion`] weights by the source's foot contacts, so a foot in the air keeps the
    /// source's leg directions and a planted one stays where the source's is.
    pub fn pose_weighted(
        &self,
        source_world: &[Mat3],
        source_positions: &[Vec3],
        source_root: &Vec3,
        options: &Options,
        feet_weight: [f64; 2],
        out: &mut RigPose,
    ) -> Result<()> {
        self.pose_anchored(
            source_world,
            source_positions,
            source_root,
            options,
            feet_weight,
            [None; 2],
            out,
        )
    }

    /// [`Target::pose_weighted`] with planted feet held in place: a foot with an anchor
    /// (rig units: the move that puts its ankle where it stands over the whole contact) has
    /// its ankle's goal moved by it horizontally, so it does not slide while the source's
    /// does not.
    #[allow(clippy::too_many_arguments)]
    fn pose_anchored(
        &self,
        source_world: &[Mat3],
        source_positions: &[Vec3],
        source_root: &Vec3,
        options: &Options,
        feet_weight: [f64; 2],
        anchors: [Option<Vec3>; 2],
        out: &mut RigPose,
    ) -> Result<()> {
        let n = self.rig().bone_count();
        if out.world.len() != n
            || out.local.len() != n
            || out.positions.len() != n
            || out.translation.len() != n
        {
            return Err(invalid_arg!(
                "the pose buffers are not for this rig ({n} bones)"
            ));
        }
        if source_positions.len() != source_world.len() {
            return Err(invalid_arg!(
                "{} source positions for {} rotations",
                source_positions.len(),
                source_world.len()
            ));
        }
        out.hips =
            self.transfer()
                .frame(source_world, source_root, &mut out.world, &mut out.local)?;
        let limbs = self.limbs();
        self.forward(out);
        let chains = match (options.feet, options.hands) {
            (true, true) => 0..4,
            (true, false) => 0..2,
            (false, true) => 2..4,
            (false, false) => 0..0,
        };
        if chains.is_empty() {
            return Ok(());
        }
        let up = self.transfer().up();
        let mut turn = [(IDENTITY, IDENTITY); 4];
        let mut any = false;
        for c in chains {
            let ch = &limbs.chains[c];
            let p = &out.positions;
            let placed = rotation::add(
                &self.transfer().place(&source_positions[ch.source_end]),
                &[0, 1, 2].map(|i| up[i] * ch.lift),
            );
            let w = if c < 2 {
                feet_weight[c].clamp(0.0, 1.0)
            } else {
                1.0
            };
            if w <= 0.0 {
                continue;
            }
            // Feet: the height is the placed source ankle's; the horizontal place is the
            // anchor's, else where the rotations put it (moving it there too would bend the
            // legs of every rig whose thigh/shin split is not SMPL's, by up to 8 degrees on a
            // child's proportions, for no contact gained: contacts are heights). Wrists: the
            // placed source wrist.
            // The goal with `k` of the anchor's move (feet) or the placed wrist (hands).
            let goal_with = |k: f64| {
                let want = if c < 2 {
                    let from = match anchors[c] {
                        Some(d) => [0, 1, 2].map(|i| p[ch.end][i] + k * d[i]),
                        None => p[ch.end],
                    };
                    let h = rotation::dot(&sub(&placed, &from), &up);
                    [0, 1, 2].map(|i| from[i] + h * up[i])
                } else {
                    placed
                };
                [0, 1, 2].map(|i| p[ch.end][i] + w * (want[i] - p[ch.end][i]))
            };
            let goal = goal_with(1.0);
            // A limb already on its goal is left as the transfer made it: the solver's reach
            // limit would otherwise bend a straight leg by ~1.6°.
            let length = dist(&p[ch.upper], &p[ch.lower]) + dist(&p[ch.lower], &p[ch.end]);
            if dist(&p[ch.end], &goal) <= 1e-9 * length {
                continue;
            }
            let solve = |goal: &Vec3| ik::solve(&p[ch.upper], &p[ch.lower], &p[ch.end], goal);
            let mut s = solve(&goal);
            if c < 2 && anchors[c].is_some() {
                // Holding a foot must not cost the leg its direction or its height: near full
                // extension a centimetre nearer needs ~17° more knee, and a hold past the
                // leg's reach would leave the foot off the floor. So where the held goal
                // would turn the thigh or shin more than HOLD_TURN from the transferred leg
                // (the source's directions), or is out of reach where the unheld one is not,
                // only as much of the hold is taken as avoids both (bisection on the anchor's
                // share). The foot then gives by what is left, millimetres a frame, far below
                // a skating speed.
                let (thigh, shin) = (
                    sub(&p[ch.lower], &p[ch.upper]),
                    sub(&p[ch.end], &p[ch.lower]),
                );
                let turn_ok = |s: &ik::TwoBone| {
                    angle(&thigh, &sub(&s.mid, &p[ch.upper]))
                        .max(angle(&shin, &sub(&s.end, &s.mid)))
                        <= HOLD_TURN
                };
                // A held goal reached within the turn fits whatever the unheld one does; only
                // otherwise is the unheld leg solved.
                if !(s.reached && turn_ok(&s)) {
                    let free = solve(&goal_with(0.0));
                    let fits = |t: &ik::TwoBone| turn_ok(t) && (t.reached || !free.reached);
                    if !fits(&s) {
                        let (mut lo, mut hi) = (0.0, 1.0);
                        s = free;
                        for _ in 0..HOLD_BISECTIONS {
                            let k = 0.5 * (lo + hi);
                            let t = solve(&goal_with(k));
                            if fits(&t) {
                                (lo, s) = (k, t);
                            } else {
                                hi = k;
                            }
                        }
                    }
                }
            }
            turn[c] = (s.upper, s.lower);
            any = true;
        }
        if any {
            for b in 0..n {
                if let Some((c, part)) = limbs.part[b] {
                    let (u, l) = &turn[c as usize];
                    let d = if part == Part::Upper { u } else { l };
                    out.world[b] = rotation::mul(d, &out.world[b]);
                }
            }
            self.transfer().refresh_followers(&mut out.world);
            self.locals_and_positions(out);
        }
        if options.feet && self.pitch_toes(source_positions, feet_weight, out) {
            self.locals_and_positions(out);
        }
        Ok(())
    }

    /// While a foot is planted (weight `feet_weight`), pitches it about the ankle so that its
    /// toes stand at the source's toes' height (placed and lifted as the ankle is): a rig's foot
    /// is longer or shorter against its ankle's height than SMPL's, so copying the foot's
    /// rotation alone leaves the toes of a rising heel up to centimetres off. The horizontal
    /// direction of the foot is kept. Returns whether a foot turned.
    fn pitch_toes(
        &self,
        source_positions: &[Vec3],
        feet_weight: [f64; 2],
        out: &mut RigPose,
    ) -> bool {
        let limbs = self.limbs();
        let up = self.transfer().up();
        let mut turned = false;
        for (c, ch) in limbs.chains[..2].iter().enumerate() {
            let w = feet_weight[c].clamp(0.0, 1.0);
            let Some((toe, joint, lift)) = ch.toe else {
                continue;
            };
            if w <= 0.0 || joint >= source_positions.len() {
                continue;
            }
            let (ankle, tip) = (out.positions[ch.end], out.positions[toe]);
            let v = sub(&tip, &ankle);
            let len = rotation::dot(&v, &v).sqrt();
            let goal = rotation::dot(&self.transfer().place(&source_positions[joint]), &up) + lift;
            let rise = rotation::dot(&v, &up);
            let want =
                (rise + w * (goal - rotation::dot(&tip, &up))).clamp(-0.999 * len, 0.999 * len);
            let flat = sub(&v, &up.map(|x| x * rise));
            let flat_len = rotation::dot(&flat, &flat).sqrt();
            // A foot standing on its toes (no horizontal part) or already there: nothing to do.
            let upright = flat_len.is_nan() || flat_len <= 1e-9 * len.max(f64::MIN_POSITIVE);
            if upright || (want - rise).abs() <= 1e-12 * len {
                continue;
            }
            let k = (len * len - want * want).max(0.0).sqrt() / flat_len;
            let to = [0, 1, 2].map(|i| flat[i] * k + up[i] * want);
            let d = ik::rotate_onto(&v, &to, None);
            for b in 0..out.world.len() {
                if limbs.foot[b] == Some(c as u8) {
                    out.world[b] = rotation::mul(&d, &out.world[b]);
                }
            }
            turned = true;
        }
        turned
    }

    /// Local rotations from the world ones, then positions.
    fn locals_and_positions(&self, out: &mut RigPose) {
        for b in 0..out.world.len() {
            out.local[b] = match self.rig().parent(b) {
                Some(p) => rotation::mul(&rotation::transpose(&out.world[p]), &out.world[b]),
                None => out.world[b],
            };
        }
        self.forward(out);
    }

    /// World positions and translations from `out`'s world rotations and hips translation,
    /// in the transfer's dependency order: a bone beside the body keeps its rest offset from
    /// its anchor, turned with it; its translation is then what puts it there.
    fn forward(&self, out: &mut RigPose) {
        let rig = self.rig();
        let transfer = self.transfer();
        let hips = transfer.hips();
        let ws = &self.limbs().world_scale;
        let (rest_pos, rest_rot) = (rig.rest_world_positions(), rig.rest_world_rotations());
        for &b in transfer.position_order() {
            if let Some(f) = transfer.anchor(b) {
                let d = rotation::mul(&out.world[f], &rotation::transpose(&rest_rot[f]));
                let at = rotation::add(
                    &out.positions[f],
                    &rotation::apply(&d, &sub(&rest_pos[b], &rest_pos[f])),
                );
                out.positions[b] = at;
                out.translation[b] = match rig.parent(b) {
                    Some(p) => {
                        let v = rotation::apply(
                            &rotation::transpose(&out.world[p]),
                            &sub(&at, &out.positions[p]),
                        );
                        v.map(|x| x / ws[p])
                    }
                    None => at,
                };
                continue;
            }
            let t = if b == hips {
                out.hips
            } else {
                rig.rest()[b].translation
            };
            out.translation[b] = t;
            out.positions[b] = match rig.parent(b) {
                Some(p) => {
                    let v = rotation::apply(&out.world[p], &t);
                    rotation::add(&out.positions[p], &v.map(|x| x * ws[p]))
                }
                None => t,
            };
        }
    }

    /// Per frame, each foot's anchor: the horizontal move of its ankle's goal that holds the
    /// planted part of the foot where it stands. Over a run of fully planted frames, the place
    /// a first pass (feet on, no anchors) gives the ankle in the middle of the run's
    /// heel-planted frames (the source's ankle in contact; of the whole run if it never is),
    /// as Kimodo's cleanup takes one target per contact interval (nv-tlabs/kimodo). Where only
    /// the toes are planted (a heel rising before toe-off, or a toe landing first), the toes are
    /// held instead, where the heel-planted frame next to them left them: a rig's foot longer or
    /// shorter than the scaled source's would otherwise swing its toes forward as it pivots.
    /// The rig's own stride, not the source's scaled one: only the sliding its proportions add
    /// is taken out.
    #[allow(clippy::too_many_arguments)]
    fn anchors(
        &self,
        world: &[Mat3],
        positions: &[Vec3],
        root: &[Vec3],
        options: &Options,
        weights: &[[f64; 2]],
        contacts: &[[f64; 4]],
        pose: &mut RigPose,
    ) -> Result<Vec<[Option<Vec3>; 2]>> {
        let joints = if root.is_empty() {
            0
        } else {
            world.len() / root.len()
        };
        let limbs = self.limbs();
        // Pass 1: each frame's ankle and toes (the ankle when the rig has no toes).
        let mut feet = Vec::with_capacity(root.len());
        for (t, r) in root.iter().enumerate() {
            let span = t * joints..(t + 1) * joints;
            self.pose_weighted(
                &world[span.clone()],
                &positions[span],
                r,
                options,
                weights[t],
                pose,
            )?;
            feet.push([0, 1].map(|c| {
                let ch = &limbs.chains[c];
                let toe = ch.toe.map_or(ch.end, |(b, _, _)| b);
                (pose.positions[ch.end], pose.positions[toe])
            }));
        }
        let heel = |t: usize, side: usize| contacts.get(t).is_some_and(|c| c[2 * side] >= 0.5);
        let mut out = vec![[None; 2]; root.len()];
        for side in 0..2 {
            // The fully planted runs, each frame's move within them.
            let mut moves: Vec<Option<Vec3>> = vec![None; root.len()];
            let mut runs: Vec<(usize, usize)> = Vec::new();
            let mut t = 0;
            while t < weights.len() {
                if weights[t][side] < 1.0 {
                    t += 1;
                    continue;
                }
                let start = t;
                while t < weights.len() && weights[t][side] >= 1.0 {
                    t += 1;
                }
                runs.push((start, t));
                let heels: Vec<usize> = (start..t).filter(|&u| heel(u, side)).collect();
                let Some(&middle) = heels.get(heels.len() / 2) else {
                    // Toes only: held where they stand in the middle of the run.
                    let at = feet[(start + t - 1) / 2][side].1;
                    for (u, m) in moves.iter_mut().enumerate().take(t).skip(start) {
                        *m = Some(sub(&at, &feet[u][side].1));
                    }
                    continue;
                };
                let anchor = feet[middle][side].0;
                for u in heels.iter().copied() {
                    moves[u] = Some(sub(&anchor, &feet[u][side].0));
                }
                // Toe-only frames: the toes stay where the nearest heel-planted frame put them.
                for u in start..t {
                    if moves[u].is_some() {
                        continue;
                    }
                    let e = *heels
                        .iter()
                        .min_by_key(|&&h| h.abs_diff(u))
                        .expect("the run has a heel-planted frame");
                    let d = moves[e].expect("set above");
                    let toes = rotation::add(&feet[e][side].1, &d);
                    moves[u] = Some(sub(&toes, &feet[u][side].1));
                }
            }
            // A ramp frame (lifting off, touching down) moves its toes as the scaled source's
            // toes move from the nearest run's end frame, where they are held: the rig's own
            // stride would otherwise swing them faster or slower than the source's at the
            // moment they leave or reach the floor. The IK weight then fades the move out
            // (Kovar et al. 2002, section 4: the adjustment is blended into the neighbouring
            // frames), so a swinging foot is not pulled back to where it stood.
            let ch = &limbs.chains[side];
            let joint = ch.toe.map_or(ch.source_end, |(_, j, _)| j);
            let src = |u: usize| self.transfer().place(&positions[u * joints + joint]);
            for (u, o) in out.iter_mut().enumerate() {
                if weights[u][side] <= 0.0 {
                    continue;
                }
                let near = runs.iter().min_by_key(|&&(a, b)| {
                    if u < a {
                        a - u
                    } else {
                        u.saturating_sub(b - 1)
                    }
                });
                o[side] = near.and_then(|&(a, b)| {
                    let e = u.clamp(a, b - 1);
                    let held = rotation::add(&feet[e][side].1, &moves[e]?);
                    let want = rotation::add(&held, &sub(&src(u), &src(e)));
                    // The goal takes `w` of the move (`pose_anchored`). The move is eased out
                    // as smoothstep(w) instead, and kept whole while the source's toes are
                    // still near the floor: below the contact height, fading out by its release
                    // height (1.5 times it; `ContactParams` height and release, the band of
                    // libflame's contact detection). A toe that grazes the floor moves as the
                    // source's does, and lets go once the foot is up.
                    let w = weights[u][side];
                    let height = positions[u * joints + joint][1];
                    let near = (3.0 - 2.0 * height / CONTACT_HEIGHT).clamp(0.0, 1.0);
                    let ease = (w * w * (3.0 - 2.0 * w)).max(near) / w;
                    Some(sub(&want, &feet[u][side].1).map(|x| x * ease))
                });
            }
        }
        Ok(out)
    }

    /// Bones whose translation moves: the hips, then the bones beside the body
    /// ([`super::Transfer::anchor`]).
    pub fn moving(&self) -> Vec<usize> {
        let t = self.transfer();
        std::iter::once(t.hips())
            .chain((0..self.rig().bone_count()).filter(|&b| t.anchor(b).is_some()))
            .collect()
    }

    /// A whole clip: `poses` (any libflame format, any finish) carried onto the rig.
    pub fn motion(&self, poses: &Poses, fps: f64, options: &Options) -> Result<RigMotion> {
        let joints = poses.joint_count();
        let frames = poses.frames();
        let world = poses.global_rotations(Convention::Gltf);
        let positions = poses.positions(Convention::Gltf);
        let root = poses.root_translation(Convention::Gltf);
        let n = self.rig().bone_count();
        let total = frames
            .checked_mul(n)
            .filter(|&t| t <= 1 << 28)
            .ok_or_else(|| invalid_arg!("{frames} frames of a {n}-bone rig is too much"))?;
        let mut motion = RigMotion {
            fps,
            frames,
            bones: n,
            hips_bone: self.transfer().hips(),
            local: Vec::with_capacity(total),
            world: Vec::with_capacity(total),
            positions: Vec::with_capacity(total),
            translation: Vec::with_capacity(total),
            moving: self.moving(),
            hips: Vec::with_capacity(frames),
        };
        let mut pose = RigPose::new(self);
        let weights = contact_weights(poses);
        let anchors = if options.feet && !weights.is_empty() {
            let contacts = poses.foot_contacts().unwrap_or(&[]);
            self.anchors(
                &world, &positions, &root, options, &weights, contacts, &mut pose,
            )?
        } else {
            Vec::new()
        };
        for (t, root) in root.iter().enumerate() {
            let span = t * joints..(t + 1) * joints;
            self.pose_anchored(
                &world[span.clone()],
                &positions[span],
                root,
                options,
                weights.get(t).copied().unwrap_or([1.0; 2]),
                anchors.get(t).copied().unwrap_or([None; 2]),
                &mut pose,
            )?;
            motion.local.extend_from_slice(&pose.local);
            motion.world.extend_from_slice(&pose.world);
            motion.positions.extend_from_slice(&pose.positions);
            motion.translation.extend_from_slice(&pose.translation);
            motion.hips.push(pose.hips);
        }
        Ok(motion)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::Skeleton;
    use crate::retarget::rig::{BoneSpec, RestTransform, Rig, RigSource};
    use crate::retarget::transfer::tests::{angle, source_motion, test_rig};

    /// `rig` with the bones named in `shins` moved to `k` of their rest offset from their
    /// parent (a rig with the source's directions but other proportions).
    fn reshaped(rig: &Rig, shins: &[&str], k: f64) -> Rig {
        let bones = (0..rig.bone_count())
            .map(|b| {
                let mut rest = rig.rest()[b];
                if shins.contains(&rig.name(b)) {
                    rest = RestTransform {
                        translation: rest.translation.map(|v| v * k),
                        ..rest
                    };
                }
                BoneSpec {
                    name: rig.name(b).to_string(),
                    parent: rig.parent(b),
                    rest,
                }
            })
            .collect();
        Rig::new(bones, rig.metres_per_unit(), RigSource::Code).unwrap()
    }

    #[test]
    fn feet_reach_the_placed_source_ankles_and_toes() {
        // Shins 25% shorter than SMPL's in proportion: copied leg directions alone leave the
        // ankles off the placed source ankles' heights by centimetres; the IK puts them there,
        // without moving them horizontally (no anchors: a single pose).
        let (built, _, _) = test_rig(3);
        let rig = reshaped(&built, &["foot_l", "foot_r"], 0.75);
        let target = Target::auto(Skeleton::smpl24(), rig).unwrap();
        let (mut with, mut without) = (RigPose::new(&target), RigPose::new(&target));
        let off = Options {
            feet: false,
            hands: false,
        };
        let (mut worst_without, mut worst_with, mut turned) = (0.0f64, 0.0f64, 0.0f64);
        let mut toe_off = 0.0f64;
        let limbs = target.limbs();
        for (g, p, root) in source_motion(40) {
            target.pose(&g, &p, &root, &off, &mut without).unwrap();
            target
                .pose(&g, &p, &root, &Options::default(), &mut with)
                .unwrap();
            for ch in &limbs.chains[..2] {
                let up = target.transfer().up();
                // The goal: where the rotations put the ankle, at the placed (and lifted)
                // source ankle's height.
                let placed = rotation::add(
                    &target.transfer().place(&p[ch.source_end]),
                    &up.map(|v| v * ch.lift),
                );
                let free = without.positions[ch.end];
                let h = rotation::dot(&sub(&placed, &free), &up);
                let goal = rotation::add(&free, &up.map(|v| v * h));
                worst_without = worst_without.max(dist(&without.positions[ch.end], &goal));
                // Reachable goals are reached; a goal past the leg's length leaves the leg
                // straight toward it.
                let (hip, ankle) = (with.positions[ch.upper], with.positions[ch.end]);
                let reach =
                    dist(&hip, &with.positions[ch.lower]) + dist(&with.positions[ch.lower], &ankle);
                if dist(&hip, &goal) < 0.99 * reach {
                    worst_with = worst_with.max(dist(&ankle, &goal));
                }
                // The toes stand at the source's toes' height (placed and lifted) whether or
                // not the ankle reached: a foot pitches to make up for it.
                let (toe, joint, lift) = ch.toe.unwrap();
                let toe_goal = rotation::dot(&target.transfer().place(&p[joint]), &up) + lift;
                toe_off = toe_off.max((rotation::dot(&with.positions[toe], &up) - toe_goal).abs());
                // Pitched only: the foot's heading (ankle to toes, horizontal) is the one the
                // rotations gave it.
                let heading = |pose: &RigPose| {
                    let v = sub(&pose.positions[toe], &pose.positions[ch.end]);
                    let h = sub(&v, &up.map(|x| x * rotation::dot(&v, &up)));
                    h.map(|x| x / rotation::dot(&h, &h).sqrt())
                };
                let (a, b) = (heading(&with), heading(&without));
                turned = turned.max(dist(&a, &b));
            }
        }
        // Centimetre units: off by more than a centimetre without IK, on target with it.
        assert!(worst_without > 1.0, "{worst_without}");
        assert!(worst_with < 1e-6, "{worst_with}");
        assert!(turned < 1e-9, "a foot's heading turned by {turned} rad");
        assert!(toe_off < 1e-6, "a toe is {toe_off} cm off its height");
    }

    #[test]
    fn a_held_foot_turns_the_leg_at_most_hold_turn_and_always_meets_its_height() {
        // Anchors of 1 mm to 20 cm (rig units are centimetres) toward and away from each hip,
        // on a rig whose shins are 10% longer: small holds are met in full; large ones would
        // bend the knee far past HOLD_TURN from the transferred leg, so only part of the move
        // is taken, the thigh and shin turn by HOLD_TURN (to the bisection's precision), never
        // more unless the height alone needs it, and the ankle is at its goal height always.
        let (built, _, _) = test_rig(3);
        let rig = reshaped(&built, &["foot_l", "foot_r"], 1.1);
        let target = Target::auto(Skeleton::smpl24(), rig).unwrap();
        let mut poses = [0; 3].map(|_| RigPose::new(&target));
        let limbs = target.limbs();
        let up = target.transfer().up();
        let (mut full, mut limited, mut excess, mut worst_height) = (0, 0, 0.0f64, 0.0f64);
        let turn = |a: &[Vec3], b: &[Vec3], ch: &Chain| {
            super::angle(
                &sub(&a[ch.lower], &a[ch.upper]),
                &sub(&b[ch.lower], &b[ch.upper]),
            )
            .max(super::angle(
                &sub(&a[ch.end], &a[ch.lower]),
                &sub(&b[ch.end], &b[ch.lower]),
            ))
        };
        let flat = |v: &Vec3| sub(v, &up.map(|x| x * rotation::dot(v, &up)));
        for (g, p, root) in source_motion(12) {
            for size in [0.1, 1.0, 5.0, 20.0] {
                for sign in [1.0, -1.0] {
                    let [bare, free, held] = &mut poses;
                    let off = Options {
                        feet: false,
                        hands: false,
                    };
                    let on = Options::default();
                    target.pose(&g, &p, &root, &off, bare).unwrap();
                    target.pose(&g, &p, &root, &on, free).unwrap();
                    // Moves from the transferred ankle, horizontally toward (+) or away from
                    // (−) the hip.
                    let moves = [0, 1].map(|c| {
                        let ch = &limbs.chains[c];
                        let d = flat(&sub(&bare.positions[ch.upper], &bare.positions[ch.end]));
                        let n = rotation::dot(&d, &d).sqrt().max(1e-9);
                        Some(d.map(|x| sign * size * x / n))
                    });
                    target
                        .pose_anchored(&g, &p, &root, &on, [1.0; 2], moves, held)
                        .unwrap();
                    for (c, ch) in limbs.chains[..2].iter().enumerate() {
                        let (b, f, h) = (&bare.positions, &free.positions, &held.positions);
                        let height = |q: &[Vec3]| rotation::dot(&q[ch.end], &up);
                        worst_height = worst_height.max((height(h) - height(f)).abs());
                        let bend = turn(b, h, ch);
                        excess = excess.max(bend - HOLD_TURN.max(turn(b, f, ch)));
                        // The goal: the moved ankle at the free pose's height.
                        let moved = rotation::add(&b[ch.end], &moves[c].unwrap());
                        let goal = rotation::add(
                            &moved,
                            &up.map(|x| x * (height(f) - rotation::dot(&moved, &up))),
                        );
                        let reach =
                            dist(&b[ch.upper], &b[ch.lower]) + dist(&b[ch.lower], &b[ch.end]);
                        let off = flat(&sub(&h[ch.end], &goal));
                        if rotation::dot(&off, &off).sqrt() < 1e-6 {
                            full += 1;
                        } else if dist(&b[ch.upper], &goal) < reach - 1e-6 {
                            limited += 1;
                            assert!(bend > HOLD_TURN - 1e-3, "gave way at {bend} rad");
                        }
                    }
                }
            }
        }
        assert!(full > 0 && limited > 0, "{full} met, {limited} limited");
        assert!(
            excess <= 1e-12,
            "{} deg past the limit",
            excess.to_degrees()
        );
        assert!(worst_height < 1e-6, "{worst_height}");
    }

    #[test]
    fn ik_leaves_a_rig_of_the_sources_proportions_as_the_transfer_made_it() {
        // The unlike rig has SMPL's proportions: the placed ankles are where the legs put
        // them, so the legs keep their source directions exactly.
        let (built, _, _) = test_rig(5);
        let target = Target::auto(Skeleton::smpl24(), built).unwrap();
        let mut pose = RigPose::new(&target);
        let axes = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let rig = target.rig();
        let bone = |name: &str| rig.find(name).unwrap();
        let mut worst = 0.0f64;
        for (g, p, root) in source_motion(30) {
            target
                .pose(
                    &g,
                    &p,
                    &root,
                    &Options {
                        feet: true,
                        hands: true,
                    },
                    &mut pose,
                )
                .unwrap();
            for (a, b, ra, rb) in [
                (1, 4, "thigh_l", "calf_l"),
                (5, 8, "calf_r", "foot_r"),
                (2, 5, "thigh_r", "calf_r"),
                (4, 7, "calf_l", "foot_l"),
            ] {
                let want = rotation::apply(&axes, &sub(&p[b], &p[a]));
                let got = sub(&pose.positions[bone(rb)], &pose.positions[bone(ra)]);
                worst = worst.max(angle(&want, &got));
            }
        }
        assert!(worst < 1e-4, "a leg is {worst}° off its source");
    }

    #[test]
    fn a_clip_is_its_frames() {
        let (built, _, _) = test_rig(2);
        let target = Target::auto(Skeleton::smpl24(), built).unwrap();
        let n = target.rig().bone_count();
        let poses =
            crate::motion::testutil::sinusoid_motion(crate::motion::Format::Smpl24Rot6d, 12);
        let m = target.motion(&poses, 20.0, &Options::default()).unwrap();
        assert_eq!((m.frames, m.bones, m.local.len()), (12, n, 12 * n));
        let world = poses.global_rotations(Convention::Gltf);
        let pos = poses.positions(Convention::Gltf);
        let root = poses.root_translation(Convention::Gltf);
        let mut one = RigPose::new(&target);
        target
            .pose(
                &world[5 * 24..6 * 24],
                &pos[5 * 24..6 * 24],
                &root[5],
                &Options::default(),
                &mut one,
            )
            .unwrap();
        assert_eq!(m.local_frame(5), &one.local[..]);
        assert_eq!(m.hips[5], one.hips);
    }
}
