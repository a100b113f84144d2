//! Which of a [`Rig`]'s bones is which humanoid bone ([`BoneMap`]).
//!
//! The pivot between every source skeleton and every rig is the VRM 1.0 humanoid bone set
//! ([`HumanBone`]: the 22 body bones libflame drives; eyes, jaw and fingers are not driven).
//! libflame's joints are paired with it once ([`HumanBone::smpl_joint`]); a rig is paired with it
//! by [`BoneMap::auto`] (the file's declared VRM map, or the bones' names), by an explicit JSON
//! map ([`BoneMap::from_json`]), or both (the JSON overriding the automatic map).
//!
//! # Name matching
//!
//! Without a declared map, [`BoneMap::auto`] reads each bone name as words, case-insensitively:
//!
//! - **Prefixes** are dropped first: anything up to the last `|` (`Armature|Hips`) or `:` (a
//!   namespace: `mixamorig:`, `mixamorig1:`, `Character1:`), then `mixamorig` with or without
//!   digits (`mixamorigHips`), `Armature_`, `CC_Base_`, VRoid's `J_Bip_`, 3ds Max's `Bip01 `,
//!   and Rigify's `DEF-` (deform bones). Blender's numbered duplicate suffix `.001` marks a
//!   segment (Rigify's `DEF-upper_arm.L.001`): never mapped, except on Rigify's spine.
//! - **Words**: split at `_`, `.`, `-`, spaces, camel case and digits (`LeftUpLeg` → left, up,
//!   leg; `spine_01` → spine, 01). `L`/`Left` and `R`/`Right` anywhere (`L_`, `_l`, `.L`,
//!   `Left…`, `…Left`, `left_`) give the side; `C` (VRoid's centre), `jnt`, `joint`, `bone` are
//!   ignored. The other words, joined, must be exactly one of the body words below, so a bone
//!   with any further word is never mapped: twist bones (`upperarm_twist_01_l`), IK and control
//!   bones (`ik_foot_l`, `thigh_fk.L`), end points (`HeadTop_End`, `LeftToe_End`), fingers
//!   (`LeftHandIndex1`), correctives (`clavicle_pec_l`), Rigify's `ORG-`/`MCH-` bones.
//! - **Body words.** With a side: shoulder / clavicle / collar → shoulder; upperarm / arm /
//!   uparm → upper arm; forearm / lowerarm / loarm / elbow → lower arm; hand / wrist → hand;
//!   thigh / upleg / upperleg / hip → upper leg; shin / calf / leg / lowerleg / loleg / knee →
//!   lower leg; foot / ankle → foot; toe / toes / toebase / ball → toes. Without a side: hips /
//!   pelvis / hip → hips; spine (numbered or not); chest; upperchest; neck (numbered or not);
//!   head.
//! - **Joint names** (SMPL, SMPL-X, AMASS: a bone named after the joint it starts at): when a
//!   rig has both a collar (or clavicle) and a shoulder on one side, its shoulder is the upper
//!   arm (and, if it also has a wrist, its hand is the hand's end point, not mapped); when it
//!   has both an ankle and a foot, its ankle is the foot and its foot the toes. So `L_Collar`,
//!   `L_Shoulder`, `L_Elbow`, `L_Wrist`, `L_Hip`, `L_Knee`, `L_Ankle`, `L_Foot` map to the
//!   shoulder, upper arm, lower arm, hand, upper leg, lower leg, foot and toes.
//! - **Spine.** The bones named spine (`Spine`, `Spine1`, `spine_01`…), ordered from the hips
//!   up: the first is the spine; with two, the second is the chest; with three or more, the
//!   last is the upper chest and the middle one (index n/2) the chest — Mixamo's `Spine`,
//!   `Spine1`, `Spine2` and SMPL's `Spine1`–`Spine3` give spine, chest, upper chest as
//!   three-vrm's Mixamo map does, UE5's `spine_01`…`spine_05` give spine_01, spine_03 and
//!   spine_05 (the upper chest needs a chest in VRM, so a middle bone is the chest rather than
//!   none; the others stay unmapped but in [`BoneMap::spine_chain`]). Bones named chest or
//!   upper chest take those places first. Of several necks (`neck_01`, `neck_02`) the lowest.
//! - **Rigify** (a rig with bones `spine` and `spine.001`, with or without `DEF-`): Rigify's
//!   human metarig (Blender's `rigify/metarigs/human.py`) names its torso and head
//!   `spine` (the hips), `spine.001` (spine), `.002` (chest), `.003` (upper chest), `.004`
//!   (neck), `.005` (upper neck, unmapped) and `.006` (head); the highest number from `.005` up
//!   is taken as the head. When a rig has `DEF-` bones and they map every required bone, only
//!   they are used (a generated Rigify rig also has control bones named `hips`, `chest`,
//!   `neck`, `head`, `shoulder.L`…).
//!
//! **Ambiguity.** When several bones claim one humanoid bone (`Hip` and `Pelvis` in Character
//! Creator rigs, `calf_l` and a `knee_l` helper), bones are chosen parents first (hips, spine…,
//! shoulders, arms, hands, legs) and of the claimants the one below the bone already chosen for
//! its humanoid parent wins, then the one nearest the root (an ancestor before its
//! descendants), then the first in the rig. Bones under a chosen hand (fingers, props) are never
//! mapped. A bone is mapped at most once.
//!
//! **Hierarchy.** Every map (automatic, declared or JSON) is checked against the rig's tree:
//! within a chain the child must be below its parent (spine, chest and upper chest below the
//! bone before them; lower arm, hand; lower leg, foot, toes; the head below a mapped neck); a
//! humanoid bone's rig bone is never above one of its humanoid ancestors'; a left bone is never
//! below a right one nor the reverse; nothing is below a hand; the upper chest needs the chest.
//! Between the torso and a limb (hips → upper leg, upper chest → shoulder → upper arm, upper
//! chest → neck) the rig may place the bones side by side instead: Rigify's generated rigs
//! parent each rig's deform chain under its `ORG-` bones, so `DEF-thigh.L` is not below
//! `DEF-spine`, in the whole armature or exported with deform bones only.

use std::fmt;

use serde::de::{Deserialize, Deserializer, MapAccess, Visitor};

use super::rig::Rig;
use crate::error::{invalid_arg, Result};
use crate::motion::Skeleton;

/// The largest JSON bone map accepted, in bytes.
pub const MAX_JSON_BYTES: usize = 1 << 20;

/// At most this many of the rig's bone names in an error message.
const NAMES_LISTED: usize = 40;

/// Names in messages are cut to this many characters.
const NAME_CHARS: usize = 64;

/// The VRM 1.0 humanoid bones libflame drives (the body; eyes, jaw and fingers are not driven).
/// Each variant names its VRM humanBone, the SMPL joint that drives it, and whether VRM 1.0
/// requires it ([`HumanBone::is_required`]). Left and right are the character's own.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum HumanBone {
    /// `hips`: the humanoid's root, the bone the root motion moves; SMPL's `Pelvis`. Required.
    Hips,
    /// `spine`: the lowest spine bone, above the hips; SMPL's `Spine1`. Required.
    Spine,
    /// `chest`: above the spine; SMPL's `Spine2`. Optional.
    Chest,
    /// `upperChest`: above the chest (only with a chest); SMPL's `Spine3`. Optional.
    UpperChest,
    /// `neck`: SMPL's `Neck`. Optional.
    Neck,
    /// `head`: SMPL's `Head`. Required.
    Head,
    /// `leftShoulder`: the collarbone (clavicle); SMPL's `L_Collar`. Optional.
    LeftShoulder,
    /// `leftUpperArm`: shoulder to elbow; SMPL's `L_Shoulder`. Required.
    LeftUpperArm,
    /// `leftLowerArm`: the forearm, elbow to wrist; SMPL's `L_Elbow`. Required.
    LeftLowerArm,
    /// `leftHand`: from the wrist (its fingers are not driven); SMPL's `L_Wrist`. Required.
    LeftHand,
    /// `rightShoulder`: the collarbone (clavicle); SMPL's `R_Collar`. Optional.
    RightShoulder,
    /// `rightUpperArm`: shoulder to elbow; SMPL's `R_Shoulder`. Required.
    RightUpperArm,
    /// `rightLowerArm`: the forearm, elbow to wrist; SMPL's `R_Elbow`. Required.
    RightLowerArm,
    /// `rightHand`: from the wrist (its fingers are not driven); SMPL's `R_Wrist`. Required.
    RightHand,
    /// `leftUpperLeg`: the thigh, hip to knee; SMPL's `L_Hip`. Required.
    LeftUpperLeg,
    /// `leftLowerLeg`: the shin, knee to ankle; SMPL's `L_Knee`. Required.
    LeftLowerLeg,
    /// `leftFoot`: ankle to the ball of the foot; SMPL's `L_Ankle`. Required.
    LeftFoot,
    /// `leftToes`: from the ball of the foot; SMPL's `L_Foot`. Optional.
    LeftToes,
    /// `rightUpperLeg`: the thigh, hip to knee; SMPL's `R_Hip`. Required.
    RightUpperLeg,
    /// `rightLowerLeg`: the shin, knee to ankle; SMPL's `R_Knee`. Required.
    RightLowerLeg,
    /// `rightFoot`: ankle to the ball of the foot; SMPL's `R_Ankle`. Required.
    RightFoot,
    /// `rightToes`: from the ball of the foot; SMPL's `R_Foot`. Optional.
    RightToes,
}

const COUNT: usize = 22;

/// VRM humanBone names, in [`HumanBone::ALL`]'s order.
const NAMES: [&str; COUNT] = [
    "hips",
    "spine",
    "chest",
    "upperChest",
    "neck",
    "head",
    "leftShoulder",
    "leftUpperArm",
    "leftLowerArm",
    "leftHand",
    "rightShoulder",
    "rightUpperArm",
    "rightLowerArm",
    "rightHand",
    "leftUpperLeg",
    "leftLowerLeg",
    "leftFoot",
    "leftToes",
    "rightUpperLeg",
    "rightLowerLeg",
    "rightFoot",
    "rightToes",
];

/// SMPL-24's joint for each humanoid bone, in [`HumanBone::ALL`]'s order.
const SMPL_JOINTS: [&str; COUNT] = [
    "Pelvis",
    "Spine1",
    "Spine2",
    "Spine3",
    "Neck",
    "Head",
    "L_Collar",
    "L_Shoulder",
    "L_Elbow",
    "L_Wrist",
    "R_Collar",
    "R_Shoulder",
    "R_Elbow",
    "R_Wrist",
    "L_Hip",
    "L_Knee",
    "L_Ankle",
    "L_Foot",
    "R_Hip",
    "R_Knee",
    "R_Ankle",
    "R_Foot",
];

/// The same joints as SMPL-X and HumanML3D-22 name them (SMPL's first 22 joints, lower case).
const SMPLX_JOINTS: [&str; COUNT] = [
    "pelvis",
    "spine1",
    "spine2",
    "spine3",
    "neck",
    "head",
    "left_collar",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_collar",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_hip",
    "left_knee",
    "left_ankle",
    "left_foot",
    "right_hip",
    "right_knee",
    "right_ankle",
    "right_foot",
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    Left,
    Right,
}

/// A limb bone without its side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Limb {
    Shoulder,
    UpperArm,
    LowerArm,
    Hand,
    UpperLeg,
    LowerLeg,
    Foot,
    Toes,
}

impl HumanBone {
    /// Parents first: every bone comes after its [`HumanBone::parent`].
    pub const ALL: [HumanBone; COUNT] = [
        HumanBone::Hips,
        HumanBone::Spine,
        HumanBone::Chest,
        HumanBone::UpperChest,
        HumanBone::Neck,
        HumanBone::Head,
        HumanBone::LeftShoulder,
        HumanBone::LeftUpperArm,
        HumanBone::LeftLowerArm,
        HumanBone::LeftHand,
        HumanBone::RightShoulder,
        HumanBone::RightUpperArm,
        HumanBone::RightLowerArm,
        HumanBone::RightHand,
        HumanBone::LeftUpperLeg,
        HumanBone::LeftLowerLeg,
        HumanBone::LeftFoot,
        HumanBone::LeftToes,
        HumanBone::RightUpperLeg,
        HumanBone::RightLowerLeg,
        HumanBone::RightFoot,
        HumanBone::RightToes,
    ];

    /// The position in [`HumanBone::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// The VRM humanBone name (`hips`, `upperChest`, `leftUpperArm`…).
    pub fn name(self) -> &'static str {
        NAMES[self.index()]
    }

    /// The bone with VRM humanBone name `name`, exactly as VRM spells it.
    pub fn from_name(name: &str) -> Option<HumanBone> {
        NAMES.iter().position(|&n| n == name).map(|i| Self::ALL[i])
    }

    /// Required by VRM 1.0: hips, spine, head, upper and lower legs, feet, upper and lower
    /// arms, hands. The others (chest, upper chest, neck, shoulders, toes) are optional.
    pub fn is_required(self) -> bool {
        use HumanBone::*;
        !matches!(
            self,
            Chest | UpperChest | Neck | LeftShoulder | RightShoulder | LeftToes | RightToes
        )
    }

    /// The VRM specification's humanoid parent (`None` for the hips). When a map lacks an
    /// optional parent, the bone's parent is the next ancestor up ([`BoneMap::mapped_parent`]).
    pub fn parent(self) -> Option<HumanBone> {
        use HumanBone::*;
        Some(match self {
            Hips => return None,
            Spine | LeftUpperLeg | RightUpperLeg => Hips,
            Chest => Spine,
            UpperChest => Chest,
            Neck | LeftShoulder | RightShoulder => UpperChest,
            Head => Neck,
            LeftUpperArm => LeftShoulder,
            RightUpperArm => RightShoulder,
            LeftLowerArm => LeftUpperArm,
            RightLowerArm => RightUpperArm,
            LeftHand => LeftLowerArm,
            RightHand => RightLowerArm,
            LeftLowerLeg => LeftUpperLeg,
            RightLowerLeg => RightUpperLeg,
            LeftFoot => LeftLowerLeg,
            RightFoot => RightLowerLeg,
            LeftToes => LeftFoot,
            RightToes => RightFoot,
        })
    }

    /// The SMPL-24 (and HumanML3D-22) joint that drives this bone: `Pelvis` → hips, `Spine1`,
    /// `Spine2`, `Spine3` → spine, chest, upper chest, `L_Collar` → left shoulder,
    /// `L_Shoulder` → left upper arm, `L_Elbow`, `L_Wrist`, `L_Hip`, `L_Knee`, `L_Ankle`, and
    /// `L_Foot` → left toes (SMPL's `L_Hand`, the hand's end, has no VRM bone).
    pub fn smpl_joint(self) -> &'static str {
        SMPL_JOINTS[self.index()]
    }

    /// The same joint as SMPL-X and HumanML3D-22 name it (`pelvis`, `spine1`, `left_collar`…).
    pub fn smplx_joint(self) -> &'static str {
        SMPLX_JOINTS[self.index()]
    }

    fn side(self) -> Option<Side> {
        match self.name().as_bytes()[0] {
            b'l' => Some(Side::Left),
            b'r' => Some(Side::Right),
            _ => None,
        }
    }

    fn limb(limb: Limb, side: Side) -> HumanBone {
        use HumanBone::*;
        let (left, right) = match limb {
            Limb::Shoulder => (LeftShoulder, RightShoulder),
            Limb::UpperArm => (LeftUpperArm, RightUpperArm),
            Limb::LowerArm => (LeftLowerArm, RightLowerArm),
            Limb::Hand => (LeftHand, RightHand),
            Limb::UpperLeg => (LeftUpperLeg, RightUpperLeg),
            Limb::LowerLeg => (LeftLowerLeg, RightLowerLeg),
            Limb::Foot => (LeftFoot, RightFoot),
            Limb::Toes => (LeftToes, RightToes),
        };
        match side {
            Side::Left => left,
            Side::Right => right,
        }
    }

    /// Whether this bone must be below `parent`, its nearest mapped humanoid ancestor, in the
    /// rig: within a chain (module doc) — the torso's, an arm's from the upper arm down, a leg's,
    /// and neck to head.
    fn strictly_below(self, parent: HumanBone) -> bool {
        use HumanBone::*;
        match self {
            Spine | Chest | UpperChest => true,
            Head => parent == Neck,
            LeftLowerArm | LeftHand | RightLowerArm | RightHand | LeftLowerLeg | LeftFoot
            | LeftToes | RightLowerLeg | RightFoot | RightToes => {
                parent.side() == self.side() && !matches!(parent, LeftShoulder | RightShoulder)
            }
            _ => false,
        }
    }

    /// The bone for a VRM name in any case.
    fn from_name_any_case(name: &str) -> Option<HumanBone> {
        HumanBone::from_name(name).or_else(|| {
            NAMES
                .iter()
                .position(|n| n.eq_ignore_ascii_case(name))
                .map(|i| Self::ALL[i])
        })
    }
}

impl fmt::Display for HumanBone {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// VRM humanoid bones libflame does not drive (eyes, jaw, fingers of VRM 0.x and 1.0), in any
/// case: accepted in a JSON map and ignored.
fn is_undriven_vrm_name(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    if matches!(lower.as_str(), "lefteye" | "righteye" | "jaw") {
        return true;
    }
    let Some(finger) = lower
        .strip_prefix("left")
        .or_else(|| lower.strip_prefix("right"))
    else {
        return false;
    };
    if let Some(j) = finger.strip_prefix("thumb") {
        return ["metacarpal", "proximal", "intermediate", "distal"].contains(&j);
    }
    ["index", "middle", "ring", "little"].iter().any(|f| {
        finger
            .strip_prefix(f)
            .is_some_and(|j| ["proximal", "intermediate", "distal"].contains(&j))
    })
}

/// A rig bone for each [`HumanBone`] (or none). Made by [`BoneMap::auto`] or
/// [`BoneMap::from_json`], which check it against the rig's hierarchy (module doc); then
/// [`BoneMap::check_required`] says whether it can drive the rig.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct BoneMap {
    bones: [Option<usize>; COUNT],
}

impl BoneMap {
    /// The map the rig's file declares (VRM humanBones) if it declares one, otherwise one made
    /// from the bone names (module doc). Bones it cannot find stay unmapped (see
    /// [`BoneMap::check_required`]); a map that contradicts the rig's hierarchy is refused, with
    /// the bones named (a JSON map can then say which bones are meant).
    pub fn auto(rig: &Rig) -> Result<BoneMap> {
        let map = if rig.declared_map().is_empty() {
            let parsed: Vec<Option<Parsed>> = rig.names().iter().map(|n| parse(n)).collect();
            let tree = Tree::new(rig);
            let deform: Vec<usize> = (0..rig.bone_count())
                .filter(|&b| parsed[b].as_ref().is_some_and(|p| p.deform))
                .collect();
            let from_deform = (!deform.is_empty())
                .then(|| match_names(&tree, &parsed, &deform))
                .filter(|m| m.missing().next().is_none());
            match from_deform {
                Some(m) => m,
                None => {
                    let all: Vec<usize> = (0..rig.bone_count()).collect();
                    match_names(&tree, &parsed, &all)
                }
            }
        } else {
            BoneMap::declared(rig)?
        };
        map.check_hierarchy(rig)?;
        Ok(map)
    }

    /// The VRM file's own map. Undriven bones (eyes, jaw, fingers) and names VRM does not have
    /// are skipped.
    fn declared(rig: &Rig) -> Result<BoneMap> {
        let mut map = BoneMap::default();
        for (name, b) in rig.declared_map() {
            let Some(h) = HumanBone::from_name_any_case(name) else {
                continue;
            };
            if *b >= rig.bone_count() {
                return Err(invalid_arg!(
                    "the file maps humanoid bone `{h}` to bone {b}, past the rig's {}",
                    rig.bone_count()
                ));
            }
            if map.bones[h.index()].is_some() {
                return Err(invalid_arg!("the file maps humanoid bone `{h}` twice"));
            }
            if let Some((g, _)) = map.mapped().find(|&(_, c)| c == *b) {
                return Err(invalid_arg!(
                    "the file maps bone {} to both humanoid bones `{g}` and `{h}`",
                    quote(rig.name(*b))
                ));
            }
            map.bones[h.index()] = Some(*b);
        }
        map.lower_lone_upper_chest();
        Ok(map)
    }

    /// An explicit map over `base` (or over nothing): a JSON object whose keys are VRM
    /// humanBone names (`"hips"`, `"leftUpperArm"`; any case) and whose values are the rig's
    /// bone names, exactly, or `null` to leave a bone unmapped. Keys for bones libflame does not
    /// drive (`leftEye`, `rightEye`, `jaw`, fingers such as `leftIndexProximal`) are checked and
    /// ignored. A bone the JSON names is taken from whichever humanoid bone `base` gave it to.
    /// Refused, with the key or name: more than [`MAX_JSON_BYTES`], invalid JSON, anything but an
    /// object, an unknown key (with the nearest VRM names), a key given twice, a value neither a
    /// string nor `null`, a bone the rig does not have (with its nearest names), one bone for two
    /// keys, and a result that contradicts the rig's hierarchy.
    pub fn from_json(rig: &Rig, json: &str, base: Option<BoneMap>) -> Result<BoneMap> {
        if json.len() > MAX_JSON_BYTES {
            return Err(invalid_arg!(
                "a bone map of {} bytes is over the {} byte limit",
                json.len(),
                MAX_JSON_BYTES
            ));
        }
        let entries = serde_json::from_str::<Entries>(json).map_err(|e| {
            use serde_json::error::Category;
            match e.classify() {
                Category::Data => invalid_arg!(
                    "a bone map must be a JSON object of VRM humanoid bone names to rig bone \
                     names (or null): {e}"
                ),
                _ => invalid_arg!("the bone map is not valid JSON: {e}"),
            }
        })?;
        let mut explicit: [Option<Option<usize>>; COUNT] = [None; COUNT];
        let mut seen: Vec<String> = Vec::new();
        for (key, value) in &entries.0 {
            let human = HumanBone::from_name_any_case(key);
            if human.is_none() && !is_undriven_vrm_name(key) {
                return Err(unknown_key(key));
            }
            let lower = key.to_ascii_lowercase();
            if seen.contains(&lower) {
                return Err(invalid_arg!("the bone map gives {} twice", quote(key)));
            }
            seen.push(lower);
            let bone = match value {
                serde_json::Value::Null => None,
                serde_json::Value::String(name) => {
                    Some(rig.find(name).ok_or_else(|| not_in_rig(rig, key, name))?)
                }
                other => {
                    return Err(invalid_arg!(
                        "the bone map's {} must be a rig bone name (a string) or null, got {}",
                        quote(key),
                        kind(other)
                    ))
                }
            };
            if let Some(h) = human {
                explicit[h.index()] = Some(bone);
            }
        }
        let mut map = base.unwrap_or_default();
        for h in HumanBone::ALL {
            let Some(bone) = explicit[h.index()] else {
                continue;
            };
            if let Some(b) = bone {
                for g in HumanBone::ALL {
                    if g == h || map.bones[g.index()] != Some(b) {
                        continue;
                    }
                    if explicit[g.index()].is_some_and(|e| e == Some(b)) {
                        return Err(invalid_arg!(
                            "the bone map gives bone {} to both `{g}` and `{h}`",
                            quote(rig.name(b))
                        ));
                    }
                    map.bones[g.index()] = None;
                }
            }
            map.bones[h.index()] = bone;
        }
        map.check_hierarchy(rig)?;
        Ok(map)
    }

    /// The rig bone mapped to `h`.
    pub fn bone(&self, h: HumanBone) -> Option<usize> {
        self.bones[h.index()]
    }

    /// The mapped bones, in [`HumanBone::ALL`]'s order (parents first).
    pub fn mapped(&self) -> impl Iterator<Item = (HumanBone, usize)> + '_ {
        HumanBone::ALL
            .into_iter()
            .filter_map(|h| self.bone(h).map(|b| (h, b)))
    }

    /// `h`'s nearest mapped humanoid ancestor and its rig bone (the parent when mapped, else
    /// the next ancestor up: a rig without a neck has the head's parent at the upper chest, or
    /// the chest, or the spine).
    pub fn mapped_parent(&self, h: HumanBone) -> Option<(HumanBone, usize)> {
        let mut p = h.parent();
        while let Some(g) = p {
            if let Some(b) = self.bone(g) {
                return Some((g, b));
            }
            p = g.parent();
        }
        None
    }

    /// The required bones this map lacks.
    fn missing(&self) -> impl Iterator<Item = HumanBone> + '_ {
        HumanBone::ALL
            .into_iter()
            .filter(|h| h.is_required() && self.bone(*h).is_none())
    }

    /// Refuses a map without every required bone (hips, spine, head, upper and lower legs, feet,
    /// upper and lower arms, hands), listing what is missing, what was found and the rig's
    /// bone names (up to 40).
    pub fn check_required(&self, rig: &Rig) -> Result<()> {
        let missing: Vec<&str> = self.missing().map(HumanBone::name).collect();
        if missing.is_empty() {
            return Ok(());
        }
        let found: Vec<String> = self
            .mapped()
            .map(|(h, b)| match rig.names().get(b) {
                Some(name) => format!("{h} = {}", quote(name)),
                None => format!("{h} = bone {b}"),
            })
            .collect();
        let found = if found.is_empty() {
            "nothing".to_string()
        } else {
            found.join(", ")
        };
        Err(invalid_arg!(
            "the rig lacks required humanoid bones: {} (no bone name matched them and no bone map \
             named them). Found: {found}. The rig's {}: {}. Name them in a bone map, for example \
             {{\"{}\": \"<bone name>\"}}",
            missing.join(", "),
            plural(rig.bone_count(), "bone"),
            list_names(rig.names()),
            missing[0]
        ))
    }

    /// The rig's spine, bottom up: every bone on the path from the hips up to the neck (the head
    /// when no neck is mapped), both ends excluded, mapped or not (1 to 5 bones or more), since
    /// the retarget spreads the spine's rotation over all of them. When that end is not below
    /// the hips (Rigify's neck chain), the path up to and including the highest mapped spine
    /// bone (upper chest, chest or spine); without hips, the mapped spine bones.
    pub fn spine_chain(&self, rig: &Rig) -> Vec<usize> {
        use HumanBone::*;
        let tree = Tree::new(rig);
        let in_rig = |b: &usize| *b < rig.bone_count();
        let mapped_spine = || -> Vec<usize> {
            [Spine, Chest, UpperChest]
                .iter()
                .filter_map(|&h| self.bone(h))
                .filter(in_rig)
                .collect()
        };
        let Some(hips) = self.bone(Hips).filter(in_rig) else {
            return mapped_spine();
        };
        if let Some(end) = self.bone(Neck).or(self.bone(Head)).filter(in_rig) {
            if let Some(path) = tree.between(hips, end) {
                return path;
            }
        }
        for h in [UpperChest, Chest, Spine] {
            if let Some(top) = self.bone(h).filter(in_rig) {
                if let Some(mut path) = tree.between(hips, top) {
                    path.push(top);
                    return path;
                }
            }
        }
        mapped_spine()
    }

    /// (source joint, rig bone) for every mapped bone whose joint `source` has, by its SMPL
    /// or SMPL-X name ([`HumanBone::smpl_joint`], [`HumanBone::smplx_joint`]): the pairs
    /// [`super::Transfer::new`] takes.
    pub fn source_pairs(&self, source: &Skeleton) -> Vec<(usize, usize)> {
        let names = source.joint_names();
        self.mapped()
            .filter_map(|(h, b)| {
                let j = names
                    .iter()
                    .position(|&n| n == h.smpl_joint() || n == h.smplx_joint())?;
                Some((j, b))
            })
            .collect()
    }

    /// The map as JSON, every humanoid bone in [`HumanBone::ALL`]'s order (`null` when
    /// unmapped): what [`BoneMap::from_json`] reads, for a user to edit.
    pub fn to_json(&self, rig: &Rig) -> String {
        let mut out = String::from("{\n");
        for (k, h) in HumanBone::ALL.into_iter().enumerate() {
            let value = match self.bone(h).and_then(|b| rig.names().get(b)) {
                Some(name) => serde_json::Value::String(name.clone()).to_string(),
                None => "null".to_string(),
            };
            let comma = if k + 1 < COUNT { "," } else { "" };
            out += &format!("  \"{h}\": {value}{comma}\n");
        }
        out + "}\n"
    }

    /// VRM's upper chest needs a chest: an upper chest alone becomes the chest.
    fn lower_lone_upper_chest(&mut self) {
        use HumanBone::*;
        if self.bone(Chest).is_none() {
            self.bones[Chest.index()] = self.bones[UpperChest.index()].take();
        }
    }

    /// The hierarchy checks of the module doc.
    fn check_hierarchy(&self, rig: &Rig) -> Result<()> {
        let n = rig.bone_count();
        if let Some((h, b)) = self.mapped().find(|&(_, b)| b >= n) {
            return Err(invalid_arg!(
                "the bone map gives `{h}` bone {b}, past the rig's {n}"
            ));
        }
        let name = |b: usize| quote(rig.name(b));
        for (h, b) in self.mapped() {
            if let Some((g, _)) = self.mapped().find(|&(g, c)| g < h && c == b) {
                return Err(invalid_arg!(
                    "the bone map gives bone {} to both `{g}` and `{h}`",
                    name(b)
                ));
            }
        }
        if self.bone(HumanBone::UpperChest).is_some() && self.bone(HumanBone::Chest).is_none() {
            return Err(invalid_arg!(
                "the bone map has an upperChest but no chest (VRM's upper chest needs a chest): \
                 map the chest too or leave the upper chest unmapped"
            ));
        }
        let tree = Tree::new(rig);
        for (h, b) in self.mapped() {
            if let Some((p, pb)) = self.mapped_parent(h) {
                if h.strictly_below(p) && !tree.is_below(b, pb) {
                    return Err(invalid_arg!(
                        "`{h}` is bone {}, which is not below `{p}`'s bone {} in the rig: the \
                         bone map does not follow the rig's hierarchy",
                        name(b),
                        name(pb)
                    ));
                }
            }
            let mut up = h.parent();
            while let Some(g) = up {
                if let Some(gb) = self.bone(g) {
                    if tree.is_below(gb, b) {
                        return Err(invalid_arg!(
                            "`{h}` is bone {}, which is above `{g}`'s bone {} in the rig: the \
                             bone map runs against the rig's hierarchy",
                            name(b),
                            name(gb)
                        ));
                    }
                }
                up = g.parent();
            }
            let Some(side) = h.side() else {
                continue;
            };
            for (g, gb) in self.mapped() {
                if g.side().is_some_and(|s| s != side) && tree.is_below(b, gb) {
                    return Err(invalid_arg!(
                        "`{h}` is bone {}, which is below `{g}`'s bone {}: left and right are \
                         crossed",
                        name(b),
                        name(gb)
                    ));
                }
            }
        }
        for hand in [HumanBone::LeftHand, HumanBone::RightHand] {
            let Some(hb) = self.bone(hand) else {
                continue;
            };
            if let Some((h, b)) = self.mapped().find(|&(_, b)| tree.is_below(b, hb)) {
                return Err(invalid_arg!(
                    "`{h}` is bone {}, which is below `{hand}`'s bone {}: bones under a hand \
                     (fingers) are not body bones",
                    name(b),
                    name(hb)
                ));
            }
        }
        Ok(())
    }
}

/// The rig's tree: parents (parents first) and depths.
struct Tree<'a> {
    parents: &'a [Option<usize>],
    depth: Vec<usize>,
}

impl<'a> Tree<'a> {
    fn new(rig: &'a Rig) -> Tree<'a> {
        let parents = rig.parents();
        let mut depth = vec![0; parents.len()];
        for b in 0..parents.len() {
            if let Some(p) = parents[b] {
                depth[b] = depth[p] + 1;
            }
        }
        Tree { parents, depth }
    }

    /// Whether `b` is a proper descendant of `a`. Ancestors come first in a rig, so the walk
    /// stops as soon as it passes `a`'s index.
    fn is_below(&self, b: usize, a: usize) -> bool {
        let mut up = self.parents[b];
        while let Some(p) = up {
            if p <= a {
                return p == a;
            }
            up = self.parents[p];
        }
        false
    }

    /// The bones strictly between `low` and its descendant `high`, bottom up; `None` when
    /// `high` is not below `low`.
    fn between(&self, low: usize, high: usize) -> Option<Vec<usize>> {
        let mut path = Vec::new();
        let mut up = self.parents[high];
        while let Some(p) = up {
            if p == low {
                path.reverse();
                return Some(path);
            }
            if p < low {
                return None;
            }
            path.push(p);
            up = self.parents[p];
        }
        None
    }
}

/// A bone name read as words (module doc).
#[derive(Debug)]
struct Parsed {
    /// Rigify's `DEF-` prefix.
    deform: bool,
    /// Blender's `.NNN` suffix.
    segment: Option<u32>,
    side: Option<Side>,
    /// The words that are neither side nor number, lower case, joined.
    core: String,
    number: Option<u32>,
}

/// `s` without `prefix` (ASCII, any case).
fn strip_ci<'a>(s: &'a str, prefix: &str) -> Option<&'a str> {
    s.get(..prefix.len())
        .filter(|head| head.eq_ignore_ascii_case(prefix))
        .map(|_| &s[prefix.len()..])
}

/// The name without the prefixes of the module doc, and whether it had `DEF-`.
fn strip_prefixes(name: &str) -> (&str, bool) {
    let mut s = name.rsplit(['|', ':']).next().unwrap_or(name);
    let mut deform = false;
    loop {
        let before = s.len();
        if let Some(rest) = strip_ci(s, "mixamorig") {
            let rest = rest.trim_start_matches(|c: char| c.is_ascii_digit());
            s = rest.strip_prefix(['_', '.', '-']).unwrap_or(rest);
        } else if let Some(rest) = strip_ci(s, "bip") {
            let digits = rest.trim_start_matches(|c: char| c.is_ascii_digit());
            if digits.len() == rest.len() {
                break;
            }
            s = digits.strip_prefix([' ', '_']).unwrap_or(digits);
        } else if let Some(rest) = ["def-", "def_", "def."].iter().find_map(|p| strip_ci(s, p)) {
            deform = true;
            s = rest;
        } else if let Some(rest) = ["armature_", "armature.", "cc_base_", "j_bip_"]
            .iter()
            .find_map(|p| strip_ci(s, p))
        {
            s = rest;
        }
        if s.len() == before {
            break;
        }
    }
    (s, deform)
}

/// The words of a name: split at anything not a letter or digit, at a lower-to-upper case
/// change, between letters and digits, and before the last capital of a run of capitals
/// followed by a lower-case letter (`LHand` → L, Hand). Lower case.
fn words(s: &str) -> Vec<String> {
    let mut out = Vec::new();
    for run in s.split(|c: char| !c.is_alphanumeric()) {
        let cs: Vec<char> = run.chars().collect();
        let mut start = 0;
        for i in 1..cs.len() {
            let (a, b) = (cs[i - 1], cs[i]);
            let split = (a.is_lowercase() && b.is_uppercase())
                || (a.is_alphabetic() != b.is_alphabetic())
                || (a.is_uppercase()
                    && b.is_uppercase()
                    && cs.get(i + 1).is_some_and(|c| c.is_lowercase()));
            if split {
                out.push(cs[start..i].iter().collect::<String>().to_lowercase());
                start = i;
            }
        }
        if start < cs.len() {
            out.push(cs[start..].iter().collect::<String>().to_lowercase());
        }
    }
    out
}

/// A bone name read as words; `None` when it names nothing (both sides, two numbers, no
/// words left).
fn parse(name: &str) -> Option<Parsed> {
    let (mut s, deform) = strip_prefixes(name);
    let mut segment = None;
    let b = s.as_bytes();
    if b.len() >= 5 && b[b.len() - 4] == b'.' && b[b.len() - 3..].iter().all(u8::is_ascii_digit) {
        segment = s[s.len() - 3..].parse().ok();
        s = &s[..s.len() - 4];
    }
    let mut side = None;
    let mut number = None;
    let mut core = String::new();
    let set_side = |s: Side, side: &mut Option<Side>| -> Option<()> {
        if side.is_some_and(|t| t != s) {
            return None;
        }
        *side = Some(s);
        Some(())
    };
    for word in words(s) {
        let (glued, word) = if word.len() > 4 && word.starts_with("left") {
            (Some(Side::Left), word[4..].to_string())
        } else if word.len() > 5 && word.starts_with("right") {
            (Some(Side::Right), word[5..].to_string())
        } else {
            (None, word)
        };
        if let Some(g) = glued {
            set_side(g, &mut side)?;
        }
        match word.as_str() {
            "l" | "left" => set_side(Side::Left, &mut side)?,
            "r" | "right" => set_side(Side::Right, &mut side)?,
            "c" | "jnt" | "joint" | "bone" => {}
            w if w.chars().all(|c| c.is_ascii_digit()) => {
                if number.is_some() {
                    return None;
                }
                number = Some(w.parse().ok()?);
            }
            w => core.push_str(w),
        }
    }
    (!core.is_empty()).then_some(Parsed {
        deform,
        segment,
        side,
        core,
        number,
    })
}

/// A body word with a side (module doc); joint names are told apart in `match_names`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SidedWord {
    Collar,
    Shoulder,
    UpperArm,
    LowerArm,
    Elbow,
    Wrist,
    Hand,
    UpperLeg,
    Hip,
    LowerLeg,
    Knee,
    Ankle,
    Foot,
    Toes,
}

fn sided_word(core: &str) -> Option<SidedWord> {
    use SidedWord::*;
    Some(match core {
        "collar" | "clavicle" | "collarbone" => Collar,
        "shoulder" => Shoulder,
        "upperarm" | "arm" | "uparm" => UpperArm,
        "forearm" | "lowerarm" | "loarm" => LowerArm,
        "elbow" => Elbow,
        "wrist" => Wrist,
        "hand" => Hand,
        "thigh" | "upleg" | "upperleg" => UpperLeg,
        "hip" => Hip,
        "shin" | "calf" | "leg" | "lowerleg" | "loleg" => LowerLeg,
        "knee" => Knee,
        "ankle" => Ankle,
        "foot" => Foot,
        "toe" | "toes" | "toebase" | "ball" => Toes,
        _ => return None,
    })
}

/// The map the names give, from the bones in `pool` (module doc).
fn match_names(tree: &Tree, parsed: &[Option<Parsed>], pool: &[usize]) -> BoneMap {
    use HumanBone::*;
    let sided = |w: SidedWord| {
        pool.iter().any(|&b| {
            parsed[b].as_ref().is_some_and(|p| {
                p.side.is_some() && p.segment.is_none() && sided_word(&p.core) == Some(w)
            })
        })
    };
    let arm_joints = (sided(SidedWord::Collar)) && sided(SidedWord::Shoulder);
    let hand_is_end = arm_joints && sided(SidedWord::Wrist);
    let leg_joints = sided(SidedWord::Ankle) && sided(SidedWord::Foot);
    let center_spine = |segment: Option<u32>| {
        pool.iter().any(|&b| {
            parsed[b].as_ref().is_some_and(|p| {
                p.side.is_none() && p.core == "spine" && p.number.is_none() && p.segment == segment
            })
        })
    };
    let rigify = center_spine(None) && center_spine(Some(1));

    let mut claims: Vec<(HumanBone, usize)> = Vec::new();
    let mut spines: Vec<(usize, Option<u32>)> = Vec::new();
    let mut rigify_spine: Vec<(u32, usize)> = Vec::new();
    for &b in pool {
        let Some(p) = &parsed[b] else {
            continue;
        };
        if let Some(side) = p.side {
            if p.segment.is_some() {
                continue;
            }
            let limb = match sided_word(&p.core) {
                Some(SidedWord::Collar) => Limb::Shoulder,
                Some(SidedWord::Shoulder) if arm_joints => Limb::UpperArm,
                Some(SidedWord::Shoulder) => Limb::Shoulder,
                Some(SidedWord::UpperArm) => Limb::UpperArm,
                Some(SidedWord::LowerArm | SidedWord::Elbow) => Limb::LowerArm,
                Some(SidedWord::Hand) if hand_is_end => continue,
                Some(SidedWord::Wrist | SidedWord::Hand) => Limb::Hand,
                Some(SidedWord::UpperLeg | SidedWord::Hip) => Limb::UpperLeg,
                Some(SidedWord::LowerLeg | SidedWord::Knee) => Limb::LowerLeg,
                Some(SidedWord::Foot) if leg_joints => Limb::Toes,
                Some(SidedWord::Ankle | SidedWord::Foot) => Limb::Foot,
                Some(SidedWord::Toes) => Limb::Toes,
                None => continue,
            };
            claims.push((HumanBone::limb(limb, side), b));
            continue;
        }
        if rigify && p.core == "spine" && p.number.is_none() {
            rigify_spine.push((p.segment.unwrap_or(0), b));
            continue;
        }
        if p.segment.is_some() {
            continue;
        }
        match p.core.as_str() {
            "hips" | "pelvis" | "hip" => claims.push((Hips, b)),
            "spine" => spines.push((b, p.number)),
            "chest" => claims.push((Chest, b)),
            "upperchest" => claims.push((UpperChest, b)),
            "neck" => claims.push((Neck, b)),
            "head" => claims.push((Head, b)),
            _ => {}
        }
    }
    if let Some(top) = rigify_spine.iter().map(|s| s.0).max() {
        for &(k, b) in &rigify_spine {
            let h = match k {
                0 => Hips,
                1 => Spine,
                2 => Chest,
                3 => UpperChest,
                4 => Neck,
                k if k == top && k >= 5 => Head,
                _ => continue,
            };
            claims.push((h, b));
        }
    }
    spines.sort_by_key(|&(b, number)| (tree.depth[b], number.map_or(0, |n| u64::from(n) + 1), b));
    let named = |h: HumanBone| claims.iter().any(|c| c.0 == h);
    let (named_chest, named_upper) = (named(Chest), named(UpperChest));
    if let Some(&(first, _)) = spines.first() {
        claims.push((Spine, first));
    }
    let n = spines.len();
    if !named_chest && n >= 2 {
        let chest = if named_upper { n - 1 } else { n / 2 };
        claims.push((Chest, spines[chest].0));
        if !named_upper && n >= 3 {
            claims.push((UpperChest, spines[n - 1].0));
        }
    }

    let mut map = BoneMap::default();
    let mut used = vec![false; tree.parents.len()];
    for h in HumanBone::ALL {
        let parent = map.mapped_parent(h).map(|(_, b)| b);
        let hands: Vec<usize> = [LeftHand, RightHand]
            .iter()
            .filter_map(|&g| map.bone(g))
            .collect();
        let best = claims
            .iter()
            .filter(|&&(g, b)| g == h && !used[b] && !hands.iter().any(|&hb| tree.is_below(b, hb)))
            .min_by_key(|&&(_, b)| {
                (
                    parent.is_some_and(|p| !tree.is_below(b, p)),
                    tree.depth[b],
                    b,
                )
            });
        if let Some(&(_, b)) = best {
            map.bones[h.index()] = Some(b);
            used[b] = true;
        }
    }
    map.lower_lone_upper_chest();
    map
}

/// A JSON object's entries in order (duplicates kept, so they can be refused).
struct Entries(Vec<(String, serde_json::Value)>);

impl<'de> Deserialize<'de> for Entries {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Entries, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Entries;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("an object")
            }
            fn visit_map<A: MapAccess<'de>>(
                self,
                mut m: A,
            ) -> std::result::Result<Entries, A::Error> {
                let mut entries = Vec::new();
                while let Some(entry) = m.next_entry::<String, serde_json::Value>()? {
                    entries.push(entry);
                }
                Ok(Entries(entries))
            }
        }
        d.deserialize_map(V)
    }
}

fn kind(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

/// A name for a message: in backquotes, escaped, at most [`NAME_CHARS`] characters.
fn quote(name: &str) -> String {
    let mut s: String = name
        .chars()
        .take(NAME_CHARS)
        .flat_map(char::escape_debug)
        .collect();
    if name.chars().nth(NAME_CHARS).is_some() {
        s.push('…');
    }
    format!("`{s}`")
}

fn plural(n: usize, what: &str) -> String {
    if n == 1 {
        format!("1 {what}")
    } else {
        format!("{n} {what}s")
    }
}

/// Up to [`NAMES_LISTED`] names, then how many more.
fn list_names(names: &[String]) -> String {
    let mut s: Vec<String> = names.iter().take(NAMES_LISTED).map(|n| quote(n)).collect();
    if names.len() > NAMES_LISTED {
        s.push(format!("… and {} more", names.len() - NAMES_LISTED));
    }
    s.join(", ")
}

/// Levenshtein distance over characters, lower case, of the first [`NAME_CHARS`] of each.
fn distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a
        .chars()
        .take(NAME_CHARS)
        .flat_map(char::to_lowercase)
        .collect();
    let b: Vec<char> = b
        .chars()
        .take(NAME_CHARS)
        .flat_map(char::to_lowercase)
        .collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.iter().enumerate() {
        let mut diagonal = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let next = (diagonal + usize::from(ca != cb))
                .min(row[j] + 1)
                .min(row[j + 1] + 1);
            diagonal = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

/// At most three of `names` close to `wanted` (by the whole name or without its prefixes).
fn close<'a>(wanted: &str, names: impl Iterator<Item = &'a str>) -> Vec<&'a str> {
    let limit = (wanted.chars().take(NAME_CHARS).count() / 3).max(2);
    let mut scored: Vec<(usize, usize, &str)> = names
        .enumerate()
        .filter_map(|(i, name)| {
            let d = distance(wanted, name).min(distance(wanted, strip_prefixes(name).0));
            (d <= limit).then_some((d, i, name))
        })
        .collect();
    scored.sort_unstable();
    // The nearest, and those at most one edit further.
    let best = scored.first().map_or(0, |s| s.0);
    scored
        .into_iter()
        .take_while(|s| s.0 <= best + 1)
        .take(3)
        .map(|s| s.2)
        .collect()
}

fn unknown_key(key: &str) -> crate::error::Error {
    let near = close(key, NAMES.iter().copied());
    let hint = if near.is_empty() {
        String::new()
    } else {
        format!(" (did you mean {}?)", near.join(" or "))
    };
    invalid_arg!(
        "the bone map's key {} is not a VRM humanoid bone{hint}; libflame maps {}",
        quote(key),
        NAMES.join(", ")
    )
}

fn not_in_rig(rig: &Rig, key: &str, name: &str) -> crate::error::Error {
    let near = close(name, rig.names().iter().map(String::as_str));
    let hint = if near.is_empty() {
        format!(
            "its {}: {}",
            plural(rig.bone_count(), "bone"),
            list_names(rig.names())
        )
    } else {
        let near: Vec<String> = near.iter().map(|n| quote(n)).collect();
        format!("close names: {}", near.join(", "))
    };
    invalid_arg!(
        "the bone map's {} names bone {}, which the rig does not have; {hint}",
        quote(key),
        quote(name)
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::retarget::{BoneSpec, RestTransform, RigSource};
    use HumanBone::*;

    /// A rig from (name, parent name; "" for a root), parents listed first, each bone 10 cm
    /// from its parent.
    fn rig_of<S: AsRef<str>>(bones: &[(S, S)]) -> Rig {
        let names: Vec<&str> = bones.iter().map(|b| b.0.as_ref()).collect();
        let specs = bones
            .iter()
            .enumerate()
            .map(|(i, (name, parent))| {
                let parent = parent.as_ref();
                let parent = (!parent.is_empty()).then(|| {
                    names[..i]
                        .iter()
                        .position(|n| *n == parent)
                        .unwrap_or_else(|| panic!("{parent} is not before {}", name.as_ref()))
                });
                BoneSpec {
                    name: name.as_ref().to_string(),
                    parent,
                    rest: RestTransform::offset([0.0, 0.1, 0.0]),
                }
            })
            .collect();
        Rig::new(specs, 1.0, RigSource::Code).unwrap()
    }

    /// The map as (VRM name, rig bone name), for comparisons.
    fn named(map: &BoneMap, rig: &Rig) -> Vec<(&'static str, String)> {
        map.mapped()
            .map(|(h, b)| (h.name(), rig.name(b).to_string()))
            .collect()
    }

    fn expect(pairs: &[(HumanBone, &str)]) -> Vec<(&'static str, String)> {
        let mut v: Vec<(HumanBone, &str)> = pairs.to_vec();
        v.sort_by_key(|p| p.0);
        v.into_iter()
            .map(|(h, n)| (h.name(), n.to_string()))
            .collect()
    }

    fn names_of(rig: &Rig, bones: &[usize]) -> Vec<String> {
        bones.iter().map(|&b| rig.name(b).to_string()).collect()
    }

    /// Mixamo's skeleton (as in any Mixamo FBX/glTF download: 65 bones with fingers, head top
    /// and toe ends, eyes on some characters), with `prefix` before every name.
    fn mixamo(prefix: &str) -> Vec<(String, String)> {
        let mut b: Vec<(String, String)> = Vec::new();
        let mut add = |name: &str, parent: &str| {
            let parent = if parent.is_empty() {
                String::new()
            } else {
                format!("{prefix}{parent}")
            };
            b.push((format!("{prefix}{name}"), parent));
        };
        add("Hips", "");
        add("Spine", "Hips");
        add("Spine1", "Spine");
        add("Spine2", "Spine1");
        add("Neck", "Spine2");
        add("Head", "Neck");
        add("HeadTop_End", "Head");
        add("LeftEye", "Head");
        add("RightEye", "Head");
        for side in ["Left", "Right"] {
            add(&format!("{side}Shoulder"), "Spine2");
            add(&format!("{side}Arm"), &format!("{side}Shoulder"));
            add(&format!("{side}ForeArm"), &format!("{side}Arm"));
            add(&format!("{side}Hand"), &format!("{side}ForeArm"));
            for finger in ["Thumb", "Index", "Middle", "Ring", "Pinky"] {
                let mut parent = format!("{side}Hand");
                for k in 1..=4 {
                    let name = format!("{side}Hand{finger}{k}");
                    add(&name, &parent);
                    parent = name;
                }
            }
            add(&format!("{side}UpLeg"), "Hips");
            add(&format!("{side}Leg"), &format!("{side}UpLeg"));
            add(&format!("{side}Foot"), &format!("{side}Leg"));
            add(&format!("{side}ToeBase"), &format!("{side}Foot"));
            add(&format!("{side}Toe_End"), &format!("{side}ToeBase"));
        }
        b
    }

    fn mixamo_expected(prefix: &str) -> Vec<(&'static str, String)> {
        let pairs = [
            (Hips, "Hips"),
            (Spine, "Spine"),
            (Chest, "Spine1"),
            (UpperChest, "Spine2"),
            (Neck, "Neck"),
            (Head, "Head"),
            (LeftShoulder, "LeftShoulder"),
            (LeftUpperArm, "LeftArm"),
            (LeftLowerArm, "LeftForeArm"),
            (LeftHand, "LeftHand"),
            (RightShoulder, "RightShoulder"),
            (RightUpperArm, "RightArm"),
            (RightLowerArm, "RightForeArm"),
            (RightHand, "RightHand"),
            (LeftUpperLeg, "LeftUpLeg"),
            (LeftLowerLeg, "LeftLeg"),
            (LeftFoot, "LeftFoot"),
            (LeftToes, "LeftToeBase"),
            (RightUpperLeg, "RightUpLeg"),
            (RightLowerLeg, "RightLeg"),
            (RightFoot, "RightFoot"),
            (RightToes, "RightToeBase"),
        ];
        let with: Vec<(HumanBone, String)> = pairs
            .iter()
            .map(|(h, n)| (*h, format!("{prefix}{n}")))
            .collect();
        let refs: Vec<(HumanBone, &str)> = with.iter().map(|(h, n)| (*h, n.as_str())).collect();
        expect(&refs)
    }

    #[test]
    fn mixamo_with_and_without_the_colon_maps_as_three_vrm_does() {
        for prefix in [
            "mixamorig:",
            "mixamorig",
            "mixamorig1:",
            "mixamorig_",
            "Armature|mixamorig:",
            "Character1:",
            "",
        ] {
            let rig = rig_of(&mixamo(prefix));
            let map = BoneMap::auto(&rig).unwrap();
            assert_eq!(
                named(&map, &rig),
                mixamo_expected(prefix),
                "prefix {prefix}"
            );
            map.check_required(&rig).unwrap();
            let spine = names_of(&rig, &map.spine_chain(&rig));
            let want: Vec<String> = ["Spine", "Spine1", "Spine2"]
                .iter()
                .map(|n| format!("{prefix}{n}"))
                .collect();
            assert_eq!(spine, want);
        }
    }

    /// UE5's Manny/Quinn skeleton (SK_Mannequin) as its bones are listed in the editor: root,
    /// pelvis, five spine bones, two necks, twist and corrective bones, metacarpals, IK bones.
    fn ue5() -> Vec<(String, String)> {
        let mut b: Vec<(String, String)> = Vec::new();
        let mut add = |name: &str, parent: &str| b.push((name.to_string(), parent.to_string()));
        add("root", "");
        add("pelvis", "root");
        add("spine_01", "pelvis");
        add("spine_02", "spine_01");
        add("spine_03", "spine_02");
        add("spine_04", "spine_03");
        add("spine_05", "spine_04");
        add("neck_01", "spine_05");
        add("neck_02", "neck_01");
        add("head", "neck_02");
        for s in ["l", "r"] {
            let n = |base: &str| format!("{base}_{s}");
            add(&n("clavicle"), "spine_05");
            add(&n("clavicle_pec"), &n("clavicle"));
            add(&n("clavicle_scap"), &n("clavicle"));
            add(&format!("spine_04_latissimus_{s}"), "spine_04");
            add(&n("upperarm"), &n("clavicle"));
            add(&n("upperarm_twist_01"), &n("upperarm"));
            add(&n("upperarm_twist_02"), &n("upperarm"));
            add(&n("upperarm_correctiveRoot"), &n("upperarm"));
            add(&n("upperarm_bicep"), &n("upperarm_correctiveRoot"));
            add(&n("upperarm_tricep"), &n("upperarm_correctiveRoot"));
            add(&n("lowerarm"), &n("upperarm"));
            add(&n("lowerarm_twist_01"), &n("lowerarm"));
            add(&n("lowerarm_twist_02"), &n("lowerarm"));
            add(&n("lowerarm_correctiveRoot"), &n("lowerarm"));
            add(&n("hand"), &n("lowerarm"));
            add(&n("wrist_inner"), &n("hand"));
            add(&n("wrist_outer"), &n("hand"));
            for f in ["index", "middle", "ring", "pinky"] {
                add(&n(&format!("{f}_metacarpal")), &n("hand"));
                add(&n(&format!("{f}_01")), &n(&format!("{f}_metacarpal")));
                add(&n(&format!("{f}_02")), &n(&format!("{f}_01")));
                add(&n(&format!("{f}_03")), &n(&format!("{f}_02")));
            }
            add(&n("thumb_01"), &n("hand"));
            add(&n("thumb_02"), &n("thumb_01"));
            add(&n("thumb_03"), &n("thumb_02"));
            add(&n("weapon"), &n("hand"));
            add(&n("thigh"), "pelvis");
            add(&n("thigh_twist_01"), &n("thigh"));
            add(&n("thigh_twist_02"), &n("thigh"));
            add(&n("thigh_correctiveRoot"), &n("thigh"));
            add(&n("calf"), &n("thigh"));
            add(&n("calf_twist_01"), &n("calf"));
            add(&n("calf_twist_02"), &n("calf"));
            add(&n("calf_correctiveRoot"), &n("calf"));
            add(&n("calf_knee"), &n("calf_correctiveRoot"));
            add(&n("ankle_bck"), &n("calf_correctiveRoot"));
            add(&n("foot"), &n("calf"));
            add(&n("ball"), &n("foot"));
        }
        add("ik_foot_root", "root");
        add("ik_foot_l", "ik_foot_root");
        add("ik_foot_r", "ik_foot_root");
        add("ik_hand_root", "root");
        add("ik_hand_gun", "ik_hand_root");
        add("ik_hand_l", "ik_hand_gun");
        add("ik_hand_r", "ik_hand_gun");
        add("interaction", "root");
        add("center_of_mass", "root");
        b
    }

    fn ue_limbs() -> Vec<(HumanBone, &'static str)> {
        vec![
            (LeftShoulder, "clavicle_l"),
            (LeftUpperArm, "upperarm_l"),
            (LeftLowerArm, "lowerarm_l"),
            (LeftHand, "hand_l"),
            (RightShoulder, "clavicle_r"),
            (RightUpperArm, "upperarm_r"),
            (RightLowerArm, "lowerarm_r"),
            (RightHand, "hand_r"),
            (LeftUpperLeg, "thigh_l"),
            (LeftLowerLeg, "calf_l"),
            (LeftFoot, "foot_l"),
            (LeftToes, "ball_l"),
            (RightUpperLeg, "thigh_r"),
            (RightLowerLeg, "calf_r"),
            (RightFoot, "foot_r"),
            (RightToes, "ball_r"),
        ]
    }

    #[test]
    fn ue5_mannequin_maps_its_five_spine_bones_and_skips_twist_corrective_and_ik_bones() {
        let rig = rig_of(&ue5());
        let map = BoneMap::auto(&rig).unwrap();
        let mut want = vec![
            (Hips, "pelvis"),
            (Spine, "spine_01"),
            (Chest, "spine_03"),
            (UpperChest, "spine_05"),
            (Neck, "neck_01"),
            (Head, "head"),
        ];
        want.extend(ue_limbs());
        assert_eq!(named(&map, &rig), expect(&want));
        map.check_required(&rig).unwrap();
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["spine_01", "spine_02", "spine_03", "spine_04", "spine_05"]
        );
    }

    #[test]
    fn ue4_mannequin_three_spine_bones() {
        let mut bones: Vec<(String, String)> = ue5()
            .into_iter()
            .filter(|(n, _)| !matches!(n.as_str(), "spine_04" | "spine_05" | "neck_02"))
            .filter(|(n, _)| !n.starts_with("spine_04_"))
            .collect();
        for (name, parent) in &mut bones {
            match (name.as_str(), parent.as_str()) {
                ("neck_01", _) | (_, "spine_05") => *parent = "spine_03".into(),
                ("head", _) => *parent = "neck_01".into(),
                _ => {}
            }
        }
        let rig = rig_of(&bones);
        let map = BoneMap::auto(&rig).unwrap();
        let mut want = vec![
            (Hips, "pelvis"),
            (Spine, "spine_01"),
            (Chest, "spine_02"),
            (UpperChest, "spine_03"),
            (Neck, "neck_01"),
            (Head, "head"),
        ];
        want.extend(ue_limbs());
        assert_eq!(named(&map, &rig), expect(&want));
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["spine_01", "spine_02", "spine_03"]
        );
    }

    /// The deform bones of a rig generated by Rigify from Blender's human metarig
    /// (`rigify/metarigs/human.py` in blender/blender-addons, as of commit b42d6862; limbs with
    /// 2 segments, the default): the torso `spine`…`spine.003` (a `spines.basic_spine`), neck
    /// and head `spine.004`…`spine.006` (`spines.super_head`), `pelvis.L`, `breast.L` and
    /// `shoulder.L` (`basic.super_copy`), the arm and leg chains with their `.001` segments
    /// (`limbs.arm`, `limbs.leg`: thigh, shin, foot, toe), the palm and fingers
    /// (`limbs.super_palm`, `limbs.super_finger`) and some of the face's. Parents as Blender's
    /// glTF exporter writes them with "deform bones only": each bone under its nearest deform
    /// ancestor. Rigify parents each deform chain under the chain's ORG parent
    /// (`limb_rigs.py`'s `parent_deform_chain`, `super_copy.py`'s deform under its ORG bone),
    /// so the neck chain, each leg, shoulder, arm, pelvis and breast, and the palms are roots.
    fn rigify_deform() -> Vec<(String, String)> {
        let mut b: Vec<(String, String)> = Vec::new();
        let mut add = |name: &str, parent: &str| b.push((name.to_string(), parent.to_string()));
        add("DEF-spine", "");
        add("DEF-spine.001", "DEF-spine");
        add("DEF-spine.002", "DEF-spine.001");
        add("DEF-spine.003", "DEF-spine.002");
        add("DEF-spine.004", "");
        add("DEF-spine.005", "DEF-spine.004");
        add("DEF-spine.006", "DEF-spine.005");
        for s in ["L", "R"] {
            let n = |base: &str| format!("DEF-{base}.{s}");
            add(&n("pelvis"), "");
            add(&n("breast"), "");
            add(&n("thigh"), "");
            add(&format!("{}.001", n("thigh")), &n("thigh"));
            add(&n("shin"), &format!("{}.001", n("thigh")));
            add(&format!("{}.001", n("shin")), &n("shin"));
            add(&n("foot"), &format!("{}.001", n("shin")));
            add(&n("toe"), &n("foot"));
            add(&n("shoulder"), "");
            add(&n("upper_arm"), "");
            add(&format!("{}.001", n("upper_arm")), &n("upper_arm"));
            add(&n("forearm"), &format!("{}.001", n("upper_arm")));
            add(&format!("{}.001", n("forearm")), &n("forearm"));
            add(&n("hand"), &format!("{}.001", n("forearm")));
            for k in 1..=4 {
                add(&format!("DEF-palm.0{k}.{s}"), "");
            }
            for f in ["thumb", "f_index", "f_middle", "f_ring", "f_pinky"] {
                add(&format!("DEF-{f}.01.{s}"), "");
                add(&format!("DEF-{f}.02.{s}"), &format!("DEF-{f}.01.{s}"));
                add(&format!("DEF-{f}.03.{s}"), &format!("DEF-{f}.02.{s}"));
            }
            add(&n("ear"), "");
            add(&n("forehead"), "");
            add(&n("lid.T"), "");
        }
        add("DEF-jaw", "");
        add("DEF-tongue", "");
        add("DEF-nose", "");
        b
    }

    fn rigify_expected() -> Vec<(&'static str, String)> {
        expect(&[
            (Hips, "DEF-spine"),
            (Spine, "DEF-spine.001"),
            (Chest, "DEF-spine.002"),
            (UpperChest, "DEF-spine.003"),
            (Neck, "DEF-spine.004"),
            (Head, "DEF-spine.006"),
            (LeftShoulder, "DEF-shoulder.L"),
            (LeftUpperArm, "DEF-upper_arm.L"),
            (LeftLowerArm, "DEF-forearm.L"),
            (LeftHand, "DEF-hand.L"),
            (RightShoulder, "DEF-shoulder.R"),
            (RightUpperArm, "DEF-upper_arm.R"),
            (RightLowerArm, "DEF-forearm.R"),
            (RightHand, "DEF-hand.R"),
            (LeftUpperLeg, "DEF-thigh.L"),
            (LeftLowerLeg, "DEF-shin.L"),
            (LeftFoot, "DEF-foot.L"),
            (LeftToes, "DEF-toe.L"),
            (RightUpperLeg, "DEF-thigh.R"),
            (RightLowerLeg, "DEF-shin.R"),
            (RightFoot, "DEF-foot.R"),
            (RightToes, "DEF-toe.R"),
        ])
    }

    #[test]
    fn rigify_deform_bones_map_by_the_human_metarig_numbering() {
        let rig = rig_of(&rigify_deform());
        let map = BoneMap::auto(&rig).unwrap();
        assert_eq!(named(&map, &rig), rigify_expected());
        map.check_required(&rig).unwrap();
        // The neck chain is not below the hips: the spine is the torso's chain.
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["DEF-spine.001", "DEF-spine.002", "DEF-spine.003"]
        );
    }

    #[test]
    fn rigify_deform_bones_win_over_the_generated_rigs_control_bones() {
        // The whole armature: the deform bones under ORG bones, beside Rigify's controls
        // (`root`, `torso`, `hips`, `chest`, `neck`, `head`, `shoulder.L`, FK/IK bones) and
        // mechanism bones.
        let mut b: Vec<(String, String)> = Vec::new();
        let mut add = |name: &str, parent: &str| b.push((name.to_string(), parent.to_string()));
        add("root", "");
        add("torso", "root");
        add("hips", "torso");
        add("chest", "torso");
        add("ORG-spine", "hips");
        add("ORG-spine.001", "ORG-spine");
        add("ORG-spine.002", "chest");
        add("ORG-spine.003", "ORG-spine.002");
        add("neck", "ORG-spine.003");
        add("head", "neck");
        add("ORG-spine.004", "neck");
        add("MCH-spine.004", "ORG-spine.004");
        for s in ["L", "R"] {
            add(&format!("shoulder.{s}"), "ORG-spine.003");
            add(&format!("ORG-shoulder.{s}"), &format!("shoulder.{s}"));
            add(&format!("upper_arm_fk.{s}"), &format!("ORG-shoulder.{s}"));
            add(&format!("hand_ik.{s}"), "root");
            add(&format!("ORG-thigh.{s}"), "ORG-spine");
            add(&format!("thigh_fk.{s}"), "ORG-spine");
            add(&format!("MCH-thigh_parent.{s}"), "root");
            add(&format!("foot_ik.{s}"), "root");
            add(&format!("toe.{s}"), &format!("foot_ik.{s}"));
        }
        let org_of = |name: &str| -> String {
            match name {
                "DEF-spine" => "ORG-spine".into(),
                "DEF-spine.004" => "ORG-spine.003".into(),
                n if n.starts_with("DEF-thigh.") => format!("ORG-thigh.{}", &n[10..11]),
                n if n.starts_with("DEF-shoulder.") || n.starts_with("DEF-upper_arm.") => {
                    format!("ORG-shoulder.{}", &n[n.len() - 1..])
                }
                _ => "root".into(),
            }
        };
        for (name, parent) in rigify_deform() {
            let parent = if parent.is_empty() {
                org_of(&name)
            } else {
                parent
            };
            b.push((name, parent));
        }
        let rig = rig_of(&b);
        let map = BoneMap::auto(&rig).unwrap();
        assert_eq!(named(&map, &rig), rigify_expected());
    }

    #[test]
    fn a_vrm_declared_map_is_used_as_declared() {
        // Names that matching would read otherwise: the declared map alone counts. A hat bone
        // named `Head` is not the head; fingers, eyes and unknown names in the file are skipped.
        let names = [
            ("root", ""),
            ("b_hips", "root"),
            ("b_spine", "b_hips"),
            ("b_chest", "b_spine"),
            ("b_neck", "b_chest"),
            ("b_head", "b_neck"),
            ("Head", "b_head"),
            ("b_eye_l", "b_head"),
            ("b_arm_up_l", "b_chest"),
            ("b_arm_lo_l", "b_arm_up_l"),
            ("b_hand_l", "b_arm_lo_l"),
            ("b_thumb_l", "b_hand_l"),
            ("b_arm_up_r", "b_chest"),
            ("b_arm_lo_r", "b_arm_up_r"),
            ("b_hand_r", "b_arm_lo_r"),
            ("b_leg_up_l", "b_hips"),
            ("b_leg_lo_l", "b_leg_up_l"),
            ("b_foot_l", "b_leg_lo_l"),
            ("b_leg_up_r", "b_hips"),
            ("b_leg_lo_r", "b_leg_up_r"),
            ("b_foot_r", "b_leg_lo_r"),
        ];
        // Indices in the rig's stored order (parents first, depth first), not the list's.
        let rig = rig_of(&names);
        let index = |n: &str| rig.find(n).unwrap();
        let declared = [
            ("hips", "b_hips"),
            ("spine", "b_spine"),
            ("chest", "b_chest"),
            ("neck", "b_neck"),
            ("head", "b_head"),
            ("leftEye", "b_eye_l"),
            ("leftUpperArm", "b_arm_up_l"),
            ("leftLowerArm", "b_arm_lo_l"),
            ("leftHand", "b_hand_l"),
            ("leftThumbProximal", "b_thumb_l"),
            ("rightUpperArm", "b_arm_up_r"),
            ("rightLowerArm", "b_arm_lo_r"),
            ("rightHand", "b_hand_r"),
            ("leftUpperLeg", "b_leg_up_l"),
            ("leftLowerLeg", "b_leg_lo_l"),
            ("leftFoot", "b_foot_l"),
            ("rightUpperLeg", "b_leg_up_r"),
            ("rightLowerLeg", "b_leg_lo_r"),
            ("rightFoot", "b_foot_r"),
            ("somethingElse", "root"),
        ];
        let declared_indices: Vec<(String, usize)> = declared
            .iter()
            .map(|(h, b)| (h.to_string(), index(b)))
            .collect();
        let rig = rig_of(&names).with_declared(declared_indices).unwrap();
        let map = BoneMap::auto(&rig).unwrap();
        let want: Vec<(HumanBone, &str)> = declared
            .iter()
            .filter_map(|(h, b)| HumanBone::from_name(h).map(|h| (h, *b)))
            .collect();
        assert_eq!(named(&map, &rig), expect(&want));
        map.check_required(&rig).unwrap();
        // Optional shoulders, upper chest and toes missing: still valid.
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["b_spine", "b_chest"]
        );

        // A file that maps one humanoid bone twice or one bone to two humanoid bones.
        let twice = rig_of(&names)
            .with_declared(vec![("hips".into(), 1), ("hips".into(), 2)])
            .unwrap();
        let e = BoneMap::auto(&twice).unwrap_err().to_string();
        assert!(e.contains("maps humanoid bone `hips` twice"), "{e}");
        let shared = rig_of(&names)
            .with_declared(vec![("hips".into(), 1), ("spine".into(), 1)])
            .unwrap();
        let e = BoneMap::auto(&shared).unwrap_err().to_string();
        assert!(e.contains("bone `b_hips` to both"), "{e}");
    }

    #[test]
    fn smpl_and_smplx_joint_names_map_by_joint() {
        let s = Skeleton::smpl24();
        let bones: Vec<(String, String)> = (0..24)
            .map(|j| {
                let parent = s
                    .parent(j)
                    .map_or(String::new(), |p| s.joint_names()[p].into());
                (s.joint_names()[j].to_string(), parent)
            })
            .collect();
        let rig = rig_of(&bones);
        let map = BoneMap::auto(&rig).unwrap();
        let want: Vec<(HumanBone, &str)> = HumanBone::ALL
            .iter()
            .map(|&h| (h, h.smpl_joint()))
            .collect();
        assert_eq!(named(&map, &rig), expect(&want));
        map.check_required(&rig).unwrap();
        // Each pair is a joint and the rig bone of the same name.
        let pairs = map.source_pairs(s);
        assert_eq!(pairs.len(), 22);
        assert!(
            pairs
                .iter()
                .all(|&(j, b)| s.joint_names()[j] == rig.name(b)),
            "{pairs:?}"
        );
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["Spine1", "Spine2", "Spine3"]
        );
        // HumanML3D-22 has no hands: the same map without them.
        assert_eq!(map.source_pairs(Skeleton::humanml22()), pairs);

        // SMPL-X / AMASS names: lower case, `left_`, fingers and eyes after the wrists.
        let mut x: Vec<(String, String)> = Vec::new();
        let mut add = |n: &str, p: &str| x.push((n.to_string(), p.to_string()));
        add("pelvis", "");
        add("spine1", "pelvis");
        add("spine2", "spine1");
        add("spine3", "spine2");
        add("neck", "spine3");
        add("head", "neck");
        add("jaw", "head");
        add("left_eye_smplhf", "head");
        add("right_eye_smplhf", "head");
        for s in ["left", "right"] {
            let n = |j: &str| format!("{s}_{j}");
            add(&n("hip"), "pelvis");
            add(&n("knee"), &n("hip"));
            add(&n("ankle"), &n("knee"));
            add(&n("foot"), &n("ankle"));
            add(&n("collar"), "spine3");
            add(&n("shoulder"), &n("collar"));
            add(&n("elbow"), &n("shoulder"));
            add(&n("wrist"), &n("elbow"));
            for f in ["index", "middle", "pinky", "ring", "thumb"] {
                add(&n(&format!("{f}1")), &n("wrist"));
                add(&n(&format!("{f}2")), &n(&format!("{f}1")));
                add(&n(&format!("{f}3")), &n(&format!("{f}2")));
            }
        }
        let rig = rig_of(&x);
        let map = BoneMap::auto(&rig).unwrap();
        let smplx = |j: &str| -> String {
            j.replace("L_", "left_")
                .replace("R_", "right_")
                .to_lowercase()
        };
        let want: Vec<(HumanBone, String)> = HumanBone::ALL
            .iter()
            .map(|&h| (h, smplx(h.smpl_joint())))
            .collect();
        assert!(want.iter().all(|(h, n)| h.smplx_joint() == n));
        let want: Vec<(HumanBone, &str)> = want.iter().map(|(h, n)| (*h, n.as_str())).collect();
        assert_eq!(named(&map, &rig), expect(&want));
    }

    #[test]
    fn one_spine_bone_and_no_neck_toes_or_shoulders_is_still_valid() {
        let rig = rig_of(&[
            ("Hips", ""),
            ("Spine", "Hips"),
            ("Head", "Spine"),
            ("LeftArm", "Spine"),
            ("LeftForeArm", "LeftArm"),
            ("LeftHand", "LeftForeArm"),
            ("RightArm", "Spine"),
            ("RightForeArm", "RightArm"),
            ("RightHand", "RightForeArm"),
            ("LeftUpLeg", "Hips"),
            ("LeftLeg", "LeftUpLeg"),
            ("LeftFoot", "LeftLeg"),
            ("RightUpLeg", "Hips"),
            ("RightLeg", "RightUpLeg"),
            ("RightFoot", "RightLeg"),
        ]);
        let map = BoneMap::auto(&rig).unwrap();
        map.check_required(&rig).unwrap();
        assert_eq!(map.mapped().count(), 15);
        assert!(HumanBone::ALL
            .iter()
            .all(|h| h.is_required() == map.bone(*h).is_some()));
        assert_eq!(names_of(&rig, &map.spine_chain(&rig)), ["Spine"]);
        // The head's parent is the spine, the upper arms' too (the next mapped ancestors).
        assert_eq!(map.mapped_parent(Head).map(|p| p.0), Some(Spine));
        assert_eq!(map.mapped_parent(LeftUpperArm).map(|p| p.0), Some(Spine));
    }

    #[test]
    fn an_upper_chest_without_a_chest_becomes_the_chest() {
        let rig = rig_of(&[
            ("Hips", ""),
            ("Spine", "Hips"),
            ("UpperChest", "Spine"),
            ("Neck", "UpperChest"),
            ("Head", "Neck"),
        ]);
        let map = BoneMap::auto(&rig).unwrap();
        assert_eq!(map.bone(Chest), rig.find("UpperChest"));
        assert_eq!(map.bone(UpperChest), None);
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            ["Spine", "UpperChest"]
        );
    }

    #[test]
    fn a_rig_missing_required_bones_is_refused_with_what_is_missing_and_found() {
        let bones: Vec<(String, String)> = mixamo("mixamorig:")
            .into_iter()
            .filter(|(n, _)| !n.contains("LeftFoot") && !n.contains("LeftToe"))
            .filter(|(n, _)| !n.contains("RightHand"))
            .collect();
        let rig = rig_of(&bones);
        let map = BoneMap::auto(&rig).unwrap();
        let e = map.check_required(&rig).unwrap_err().to_string();
        assert!(
            e.contains("lacks required humanoid bones: rightHand, leftFoot"),
            "{e}"
        );
        assert!(e.contains("hips = `mixamorig:Hips`"), "{e}");
        assert!(
            e.contains("rightLowerArm = `mixamorig:RightForeArm`"),
            "{e}"
        );
        assert!(
            e.contains(&format!(
                "The rig's {} bones: `mixamorig:Hips`",
                bones.len()
            )),
            "{e}"
        );
        assert!(
            e.contains(&format!("… and {} more", bones.len() - 40)),
            "{e}"
        );
        assert!(e.contains("{\"rightHand\": \"<bone name>\"}"), "{e}");

        // Nothing found at all.
        let rig = rig_of(&[("a", ""), ("b", "a")]);
        let e = BoneMap::auto(&rig)
            .unwrap()
            .check_required(&rig)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("Found: nothing. The rig's 2 bones: `a`, `b`."),
            "{e}"
        );
    }

    #[test]
    fn plain_left_right_variants_and_other_namings() {
        // (bone names in the order hips, spine, chest, neck, head, left shoulder, upper arm,
        // lower arm, hand, upper leg, lower leg, foot, toes; `{}` is the side's letter or
        // word) for a rig of the usual shape.
        let namings: [(&str, [&str; 13], [&str; 2]); 8] = [
            (
                "L_ prefixes",
                [
                    "Pelvis",
                    "Spine",
                    "Chest",
                    "Neck",
                    "Head",
                    "{}_Clavicle",
                    "{}_UpperArm",
                    "{}_Forearm",
                    "{}_Hand",
                    "{}_Thigh",
                    "{}_Calf",
                    "{}_Foot",
                    "{}_Toe",
                ],
                ["L", "R"],
            ),
            (
                "_l suffixes",
                [
                    "hips",
                    "spine",
                    "chest",
                    "neck",
                    "head",
                    "shoulder_{}",
                    "upperarm_{}",
                    "lowerarm_{}",
                    "hand_{}",
                    "upperleg_{}",
                    "lowerleg_{}",
                    "foot_{}",
                    "toes_{}",
                ],
                ["l", "r"],
            ),
            (
                ".L suffixes (a Rigify metarig style without spine numbers)",
                [
                    "hips",
                    "spine",
                    "chest",
                    "neck",
                    "head",
                    "shoulder.{}",
                    "upper_arm.{}",
                    "forearm.{}",
                    "hand.{}",
                    "thigh.{}",
                    "shin.{}",
                    "foot.{}",
                    "toe.{}",
                ],
                ["L", "R"],
            ),
            (
                "Left suffixes",
                [
                    "Hips",
                    "Spine",
                    "Chest",
                    "Neck",
                    "Head",
                    "Shoulder{}",
                    "Arm{}",
                    "ForeArm{}",
                    "Hand{}",
                    "UpLeg{}",
                    "Leg{}",
                    "Foot{}",
                    "Toe{}",
                ],
                ["Left", "Right"],
            ),
            (
                "left_ prefixes",
                [
                    "hips",
                    "spine",
                    "chest",
                    "neck",
                    "head",
                    "{}_shoulder",
                    "{}_upper_arm",
                    "{}_lower_arm",
                    "{}_hand",
                    "{}_upper_leg",
                    "{}_lower_leg",
                    "{}_foot",
                    "{}_toes",
                ],
                ["left", "right"],
            ),
            (
                "Unity Humanoid / VRM humanBone names",
                [
                    "Hips",
                    "Spine",
                    "Chest",
                    "Neck",
                    "Head",
                    "{}Shoulder",
                    "{}UpperArm",
                    "{}LowerArm",
                    "{}Hand",
                    "{}UpperLeg",
                    "{}LowerLeg",
                    "{}Foot",
                    "{}Toes",
                ],
                ["Left", "Right"],
            ),
            (
                "VRM humanBone names in camel case",
                [
                    "hips",
                    "spine",
                    "chest",
                    "neck",
                    "head",
                    "{}Shoulder",
                    "{}UpperArm",
                    "{}LowerArm",
                    "{}Hand",
                    "{}UpperLeg",
                    "{}LowerLeg",
                    "{}Foot",
                    "{}Toes",
                ],
                ["left", "right"],
            ),
            (
                "VRoid's J_Bip_ names",
                [
                    "J_Bip_C_Hips",
                    "J_Bip_C_Spine",
                    "J_Bip_C_Chest",
                    "J_Bip_C_Neck",
                    "J_Bip_C_Head",
                    "J_Bip_{}_Shoulder",
                    "J_Bip_{}_UpperArm",
                    "J_Bip_{}_LowerArm",
                    "J_Bip_{}_Hand",
                    "J_Bip_{}_UpperLeg",
                    "J_Bip_{}_LowerLeg",
                    "J_Bip_{}_Foot",
                    "J_Bip_{}_ToeBase",
                ],
                ["L", "R"],
            ),
        ];
        let humans = [
            Hips,
            Spine,
            Chest,
            Neck,
            Head,
            LeftShoulder,
            LeftUpperArm,
            LeftLowerArm,
            LeftHand,
            LeftUpperLeg,
            LeftLowerLeg,
            LeftFoot,
            LeftToes,
        ];
        let right =
            |h: HumanBone| HumanBone::from_name(&h.name().replace("left", "right")).unwrap();
        for (what, n, sides) in namings {
            let mut bones: Vec<(String, String)> = Vec::new();
            for k in 0..5 {
                let parent = if k == 0 {
                    String::new()
                } else {
                    n[k - 1].to_string()
                };
                bones.push((n[k].to_string(), parent));
            }
            let mut want: Vec<(HumanBone, String)> =
                (0..5).map(|k| (humans[k], n[k].to_string())).collect();
            for (s, side) in sides.iter().enumerate() {
                let name = |k: usize| n[k].replace("{}", side);
                for (k, &human) in humans.iter().enumerate().skip(5) {
                    let parent = match k {
                        5 => n[2].to_string(),
                        9 => n[0].to_string(),
                        _ => name(k - 1),
                    };
                    bones.push((name(k), parent));
                    let h = if s == 0 { human } else { right(human) };
                    want.push((h, name(k)));
                }
            }
            let rig = rig_of(&bones);
            let map = BoneMap::auto(&rig).unwrap_or_else(|e| panic!("{what}: {e}"));
            let want: Vec<(HumanBone, &str)> = want.iter().map(|(h, s)| (*h, s.as_str())).collect();
            assert_eq!(named(&map, &rig), expect(&want), "{what}");
        }
    }

    #[test]
    fn three_ds_max_biped_with_thighs_under_the_spine_and_clavicles_under_the_neck() {
        let rig = rig_of(&[
            ("Bip01", ""),
            ("Bip01 Pelvis", "Bip01"),
            ("Bip01 Spine", "Bip01 Pelvis"),
            ("Bip01 L Thigh", "Bip01 Spine"),
            ("Bip01 L Calf", "Bip01 L Thigh"),
            ("Bip01 L Foot", "Bip01 L Calf"),
            ("Bip01 L Toe0", "Bip01 L Foot"),
            ("Bip01 R Thigh", "Bip01 Spine"),
            ("Bip01 R Calf", "Bip01 R Thigh"),
            ("Bip01 R Foot", "Bip01 R Calf"),
            ("Bip01 R Toe0", "Bip01 R Foot"),
            ("Bip01 Spine1", "Bip01 Spine"),
            ("Bip01 Spine2", "Bip01 Spine1"),
            ("Bip01 Neck", "Bip01 Spine2"),
            ("Bip01 Head", "Bip01 Neck"),
            ("Bip01 L Clavicle", "Bip01 Neck"),
            ("Bip01 L UpperArm", "Bip01 L Clavicle"),
            ("Bip01 L Forearm", "Bip01 L UpperArm"),
            ("Bip01 L Hand", "Bip01 L Forearm"),
            ("Bip01 R Clavicle", "Bip01 Neck"),
            ("Bip01 R UpperArm", "Bip01 R Clavicle"),
            ("Bip01 R Forearm", "Bip01 R UpperArm"),
            ("Bip01 R Hand", "Bip01 R Forearm"),
        ]);
        let map = BoneMap::auto(&rig).unwrap();
        map.check_required(&rig).unwrap();
        assert_eq!(map.mapped().count(), 22);
        assert_eq!(rig.name(map.bone(Hips).unwrap()), "Bip01 Pelvis");
        assert_eq!(rig.name(map.bone(LeftToes).unwrap()), "Bip01 L Toe0");
        assert_eq!(rig.name(map.bone(UpperChest).unwrap()), "Bip01 Spine2");
    }

    #[test]
    fn ambiguous_names_are_settled_by_the_hierarchy() {
        // Character Creator: `Hip` (the body's root) above `Pelvis`; the hips is the ancestor.
        // A `knee_l` helper under `calf_l` loses to it; a stray `Foot_L` prop under the left hand
        // is never a foot, and the real foot under the calf wins.
        let rig = rig_of(&[
            ("CC_Base_BoneRoot", ""),
            ("CC_Base_Hip", "CC_Base_BoneRoot"),
            ("CC_Base_Pelvis", "CC_Base_Hip"),
            ("CC_Base_Waist", "CC_Base_Hip"),
            ("CC_Base_Spine01", "CC_Base_Waist"),
            ("CC_Base_Spine02", "CC_Base_Spine01"),
            ("CC_Base_NeckTwist01", "CC_Base_Spine02"),
            ("CC_Base_Head", "CC_Base_NeckTwist01"),
            ("CC_Base_L_Clavicle", "CC_Base_Spine02"),
            ("CC_Base_L_Upperarm", "CC_Base_L_Clavicle"),
            ("CC_Base_L_Forearm", "CC_Base_L_Upperarm"),
            ("CC_Base_L_Hand", "CC_Base_L_Forearm"),
            ("Foot_L", "CC_Base_L_Hand"),
            ("CC_Base_R_Clavicle", "CC_Base_Spine02"),
            ("CC_Base_R_Upperarm", "CC_Base_R_Clavicle"),
            ("CC_Base_R_Forearm", "CC_Base_R_Upperarm"),
            ("CC_Base_R_Hand", "CC_Base_R_Forearm"),
            ("CC_Base_L_Thigh", "CC_Base_Pelvis"),
            ("CC_Base_L_Calf", "CC_Base_L_Thigh"),
            ("knee_l", "CC_Base_L_Calf"),
            ("CC_Base_L_Foot", "CC_Base_L_Calf"),
            ("CC_Base_R_Thigh", "CC_Base_Pelvis"),
            ("CC_Base_R_Calf", "CC_Base_R_Thigh"),
            ("CC_Base_R_Foot", "CC_Base_R_Calf"),
        ]);
        let map = BoneMap::auto(&rig).unwrap();
        map.check_required(&rig).unwrap();
        let name = |h| rig.name(map.bone(h).unwrap());
        assert_eq!(name(Hips), "CC_Base_Hip");
        assert_eq!(name(Spine), "CC_Base_Spine01");
        assert_eq!(name(Chest), "CC_Base_Spine02");
        assert_eq!(name(LeftLowerLeg), "CC_Base_L_Calf");
        assert_eq!(name(LeftFoot), "CC_Base_L_Foot");
        assert_eq!(map.bone(Neck), None);
        // No neck: the spine runs to the head, through the unrecognised neck bone.
        assert_eq!(
            names_of(&rig, &map.spine_chain(&rig)),
            [
                "CC_Base_Waist",
                "CC_Base_Spine01",
                "CC_Base_Spine02",
                "CC_Base_NeckTwist01"
            ]
        );
    }

    #[test]
    fn maps_against_the_hierarchy_are_refused() {
        // Upper and lower leg swapped in the tree.
        let rig = rig_of(&[
            ("Hips", ""),
            ("Spine", "Hips"),
            ("Head", "Spine"),
            ("LeftLeg", "Hips"),
            ("LeftUpLeg", "LeftLeg"),
            ("LeftFoot", "LeftUpLeg"),
        ]);
        let e = BoneMap::auto(&rig).unwrap_err().to_string();
        assert!(
            e.contains("`leftLowerLeg` is bone `LeftLeg`, which is not below `leftUpperLeg`'s bone `LeftUpLeg`"),
            "{e}"
        );
        // Left and right crossed: the left hand under the right forearm.
        let rig = rig_of(&[
            ("Hips", ""),
            ("RightArm", "Hips"),
            ("RightForeArm", "RightArm"),
            ("LeftHand", "RightForeArm"),
        ]);
        let e = BoneMap::auto(&rig).unwrap_err().to_string();
        assert!(e.contains("left and right are crossed"), "{e}");
        // A torso bone above the hips.
        let rig = rig_of(&[("Chest", ""), ("Hips", "Chest"), ("Spine", "Hips")]);
        let e = BoneMap::auto(&rig).unwrap_err().to_string();
        assert!(
            e.contains("`chest` is bone `Chest`, which is not below `spine`'s bone `Spine`"),
            "{e}"
        );
        let rig = rig_of(&[("LeftShoulder", ""), ("Hips", "LeftShoulder")]);
        let e = BoneMap::auto(&rig).unwrap_err().to_string();
        assert!(
            e.contains(
                "`leftShoulder` is bone `LeftShoulder`, which is above `hips`'s bone `Hips`"
            ),
            "{e}"
        );

        // JSON: hand and forearm swapped; a toe on a finger.
        let rig = rig_of(&mixamo("mixamorig:"));
        let base = BoneMap::auto(&rig).unwrap();
        let e = BoneMap::from_json(
            &rig,
            r#"{"leftLowerArm": "mixamorig:LeftHand", "leftHand": "mixamorig:LeftForeArm"}"#,
            Some(base.clone()),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`leftHand` is bone `mixamorig:LeftForeArm`, which is not below"),
            "{e}"
        );
        let e = BoneMap::from_json(
            &rig,
            r#"{"leftToes": "mixamorig:LeftHandIndex1"}"#,
            Some(base.clone()),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains(
                "`leftToes` is bone `mixamorig:LeftHandIndex1`, which is not below `leftFoot`'s"
            ),
            "{e}"
        );
        let e = BoneMap::from_json(
            &rig,
            r#"{"neck": "mixamorig:LeftHandIndex1", "head": null}"#,
            Some(base.clone()),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`neck` is bone `mixamorig:LeftHandIndex1`, which is below `leftHand`'s bone `mixamorig:LeftHand`: bones under a hand"),
            "{e}"
        );
        let e = BoneMap::from_json(&rig, r#"{"chest": null}"#, Some(base))
            .unwrap_err()
            .to_string();
        assert!(e.contains("upperChest but no chest"), "{e}");
    }

    #[test]
    fn json_overrides_the_automatic_map() {
        let rig = rig_of(&mixamo("mixamorig:"));
        let base = BoneMap::auto(&rig).unwrap();
        // Unmapping optional bones, in any key case.
        let map = BoneMap::from_json(
            &rig,
            r#"{"leftToes": null, "RightToes": null, "upperChest": null}"#,
            Some(base.clone()),
        )
        .unwrap();
        assert_eq!(map.bone(LeftToes), None);
        assert_eq!(map.bone(RightToes), None);
        assert_eq!(map.bone(UpperChest), None);
        assert_eq!(map.bone(Chest), base.bone(Chest));
        assert_eq!(map.mapped().count(), 19);
        map.check_required(&rig).unwrap();
        // The spine chain still runs up to the neck, through the unmapped Spine2.
        assert_eq!(map.spine_chain(&rig), base.spine_chain(&rig));

        // A bone the JSON names is taken from the humanoid bone the base gave it to.
        let map = BoneMap::from_json(&rig, r#"{"chest": "mixamorig:Spine2"}"#, Some(base.clone()))
            .unwrap();
        assert_eq!(rig.name(map.bone(Chest).unwrap()), "mixamorig:Spine2");
        assert_eq!(map.bone(UpperChest), None);

        // Keys for bones libflame does not drive are accepted and ignored.
        let map = BoneMap::from_json(
            &rig,
            r#"{"leftThumbProximal": "mixamorig:LeftHandThumb2", "leftEye": "mixamorig:LeftEye",
                "jaw": null, "rightLittleDistal": "mixamorig:RightHandPinky3"}"#,
            Some(base.clone()),
        )
        .unwrap();
        assert_eq!(map, base);
        assert_eq!(
            BoneMap::from_json(&rig, "{}", Some(base.clone())).unwrap(),
            base
        );

        // The whole map written out and read back, over nothing.
        let json = base.to_json(&rig);
        assert!(
            json.starts_with("{\n  \"hips\": \"mixamorig:Hips\",\n"),
            "{json}"
        );
        assert_eq!(BoneMap::from_json(&rig, &json, None).unwrap(), base);

        // A rig whose names match nothing: the JSON alone.
        let names: Vec<(String, String)> = (0..15)
            .map(|i| {
                let parent = match i {
                    0 => String::new(),
                    1 | 9 | 12 => "j0".into(),
                    3 | 6 => "j1".into(),
                    i => format!("j{}", i - 1),
                };
                (format!("j{i}"), parent)
            })
            .collect();
        let rig = rig_of(&names);
        let empty = BoneMap::auto(&rig).unwrap();
        assert_eq!(empty.mapped().count(), 0);
        let json = r#"{"hips": "j0", "spine": "j1", "head": "j2",
            "leftUpperArm": "j3", "leftLowerArm": "j4", "leftHand": "j5",
            "rightUpperArm": "j6", "rightLowerArm": "j7", "rightHand": "j8",
            "leftUpperLeg": "j9", "leftLowerLeg": "j10", "leftFoot": "j11",
            "rightUpperLeg": "j12", "rightLowerLeg": "j13", "rightFoot": "j14"}"#;
        let map = BoneMap::from_json(&rig, json, Some(empty)).unwrap();
        map.check_required(&rig).unwrap();
        assert_eq!(map, BoneMap::from_json(&rig, json, None).unwrap());
        assert_eq!(names_of(&rig, &map.spine_chain(&rig)), ["j1"]);
    }

    #[test]
    fn json_errors_are_clear() {
        let rig = rig_of(&mixamo("mixamorig:"));
        let err = |json: &str| {
            BoneMap::from_json(&rig, json, None)
                .unwrap_err()
                .to_string()
        };
        let e = err(r#"{"leftUpperArmm": "mixamorig:LeftArm"}"#);
        assert!(
            e.contains(
                "key `leftUpperArmm` is not a VRM humanoid bone (did you mean leftUpperArm?)"
            ),
            "{e}"
        );
        let e = err(r#"{"tail": null}"#);
        assert!(
            e.contains("`tail` is not a VRM humanoid bone; libflame maps hips, spine"),
            "{e}"
        );
        let e = err(r#"{"leftUpperArm": "mixamorig:LeftArmm"}"#);
        assert!(
            e.contains("names bone `mixamorig:LeftArmm`, which the rig does not have; close names: `mixamorig:LeftArm`"),
            "{e}"
        );
        let e = err(r#"{"hips": "hips"}"#);
        assert!(e.contains("close names: `mixamorig:Hips`"), "{e}");
        let e = err(r#"{"hips": "zzzzzzzzzzzz"}"#);
        let listed = format!("its {} bones: `mixamorig:Hips`, ", rig.bone_count());
        assert!(e.contains(&listed), "{e}");
        for (value, what) in [
            ("3", "a number"),
            ("true", "a boolean"),
            ("[]", "an array"),
            ("{}", "an object"),
        ] {
            let e = err(&format!(r#"{{"hips": {value}}}"#));
            assert!(
                e.contains(&format!(
                    "`hips` must be a rig bone name (a string) or null, got {what}"
                )),
                "{e}"
            );
        }
        for json in ["[1]", "\"hips\"", "null", "3"] {
            let e = err(json);
            assert!(
                e.contains("must be a JSON object of VRM humanoid bone names"),
                "{json}: {e}"
            );
        }
        for json in ["{\"hips\": ", "{hips: 1}", "", "{\"hips\": \"a\"} x"] {
            let e = err(json);
            assert!(e.contains("is not valid JSON"), "{json}: {e}");
        }
        let e = err(r#"{"hips": "mixamorig:Hips", "Hips": null}"#);
        assert!(e.contains("gives `Hips` twice"), "{e}");
        let e = err(r#"{"chest": "mixamorig:Spine1", "upperChest": "mixamorig:Spine1"}"#);
        assert!(
            e.contains("gives bone `mixamorig:Spine1` to both `chest` and `upperChest`"),
            "{e}"
        );
        let big = format!("{{{}}}", " ".repeat(MAX_JSON_BYTES));
        let e = err(&big);
        assert!(e.contains("over the 1048576 byte limit"), "{e}");
        // Exactly at the limit is read.
        let at = format!("{{{}}}", " ".repeat(MAX_JSON_BYTES - 2));
        assert!(BoneMap::from_json(&rig, &at, None).is_ok());
        // A base made for another rig.
        let mut other = BoneMap::default();
        other.bones[0] = Some(1000);
        let e = BoneMap::from_json(&rig, "{}", Some(other))
            .unwrap_err()
            .to_string();
        let past = format!("`hips` bone 1000, past the rig's {}", rig.bone_count());
        assert!(e.contains(&past), "{e}");
    }

    #[test]
    fn human_bones_name_parents_and_requirements() {
        assert_eq!(HumanBone::ALL.len(), 22);
        for (i, h) in HumanBone::ALL.iter().enumerate() {
            assert_eq!(h.index(), i);
            assert_eq!(HumanBone::from_name(h.name()), Some(*h));
            if let Some(p) = h.parent() {
                assert!(p < *h, "{h} after its parent {p}");
            }
        }
        assert_eq!(HumanBone::from_name("Hips"), None);
        assert_eq!(
            HumanBone::ALL.iter().filter(|h| h.is_required()).count(),
            15
        );
        assert_eq!(LeftUpperArm.parent(), Some(LeftShoulder));
        assert_eq!(Neck.parent(), Some(UpperChest));
        assert_eq!(RightToes.parent(), Some(RightFoot));
        assert!(is_undriven_vrm_name("leftThumbMetacarpal"));
        assert!(is_undriven_vrm_name("rightIndexIntermediate"));
        assert!(!is_undriven_vrm_name("leftIndexMetacarpal"));
        assert!(!is_undriven_vrm_name("left"));
    }

    #[test]
    fn name_reading() {
        let p = |n: &str| parse(n).map(|p| (p.side, p.core, p.number, p.segment, p.deform));
        assert_eq!(
            p("mixamorig:LeftUpLeg"),
            Some((Some(Side::Left), "upleg".into(), None, None, false))
        );
        assert_eq!(
            p("DEF-upper_arm.L.001"),
            Some((Some(Side::Left), "upperarm".into(), None, Some(1), true))
        );
        assert_eq!(
            p("spine_05"),
            Some((None, "spine".into(), Some(5), None, false))
        );
        assert_eq!(
            p("LHand"),
            Some((Some(Side::Left), "hand".into(), None, None, false))
        );
        assert_eq!(
            p("lefthand"),
            Some((Some(Side::Left), "hand".into(), None, None, false))
        );
        assert_eq!(
            p("Bip01 R Toe0"),
            Some((Some(Side::Right), "toe".into(), Some(0), None, false))
        );
        assert_eq!(p("upperarm_twist_01_l").unwrap().1, "upperarmtwist");
        assert!(p("L_Hand_R").is_none());
        assert!(p("Bip01").is_none());
        assert!(p("spine_1_2").is_none());
        assert!(p("mixamorig:").is_none());
        assert!(p("neck_99999999999").is_none());
    }
}
