//! The user's character as a retarget target ([`Target`]): a [`Rig`], its [`BoneMap`] and the
//! [`Transfer`] from one of libflame's skeletons, made once and shared; [`Target::frame`]
//! drives it one frame at a time.

use super::bonemap::BoneMap;
use super::pose::Limbs;
use super::rig::Rig;
use super::transfer::{smpl, Transfer};
use crate::error::Result;
use crate::motion::rotation::{Mat3, Vec3};
use crate::motion::Skeleton;

/// A rig ready to take libflame poses (module doc).
#[derive(Clone, Debug)]
pub struct Target {
    rig: Rig,
    map: BoneMap,
    transfer: Transfer,
    limbs: Limbs,
}

impl Target {
    /// `rig` driven from `source` (SMPL-24 or HumanML3D-22) through `map`, which must map the
    /// required humanoid bones ([`BoneMap::check_required`]).
    pub fn new(source: &Skeleton, rig: Rig, map: BoneMap) -> Result<Target> {
        map.check_required(&rig)?;
        let pairs = map.source_pairs(source);
        let spine = map.spine_chain(&rig);
        let transfer = Transfer::new(source, &rig, &pairs, &smpl::SPINE, &spine)?;
        let limbs = Limbs::new(&rig, &map, &transfer)?;
        Ok(Target {
            rig,
            map,
            transfer,
            limbs,
        })
    }

    /// [`Target::new`] with the automatic bone map ([`BoneMap::auto`]).
    pub fn auto(source: &Skeleton, rig: Rig) -> Result<Target> {
        let map = BoneMap::auto(&rig)?;
        Target::new(source, rig, map)
    }

    /// The rig being driven.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The bone map in use (to show or save it: [`BoneMap::to_json`]).
    pub fn map(&self) -> &BoneMap {
        &self.map
    }

    /// The rest-relative transform from the source skeleton to the rig.
    pub fn transfer(&self) -> &Transfer {
        &self.transfer
    }

    pub(crate) fn limbs(&self) -> &Limbs {
        &self.limbs
    }

    /// One frame ([`Transfer::frame`]): source world rotations and pelvis position in glTF
    /// axes (metres, floor at 0) in; the rig's world and local rotations written, the hips'
    /// translation (relative to its parent, rig units) returned.
    pub fn frame(
        &self,
        source_world: &[Mat3],
        source_root: &Vec3,
        world: &mut [Mat3],
        local: &mut [Mat3],
    ) -> Result<Vec3> {
        self.transfer.frame(source_world, source_root, world, local)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::rotation::{self, IDENTITY};
    use crate::retarget::bvh_rig;
    use crate::retarget::transfer::tests::{angle, posed, source_motion, test_rig};

    /// The BVH hierarchy of `rig` (offsets from its rest world positions; BVH has no rest
    /// rotations), one frame of zeros.
    fn bvh_of(rig: &Rig) -> String {
        let pos = rig.rest_world_positions();
        fn write(rig: &Rig, pos: &[Vec3], b: usize, depth: usize, out: &mut String) {
            let pad = "  ".repeat(depth);
            let o = match rig.parent(b) {
                Some(p) => [0, 1, 2].map(|i| pos[b][i] - pos[p][i]),
                None => pos[b],
            };
            let kind = if depth == 0 { "ROOT" } else { "JOINT" };
            out.push_str(&format!("{pad}{kind} {}\n{pad}{{\n", rig.name(b)));
            out.push_str(&format!("{pad}  OFFSET {} {} {}\n", o[0], o[1], o[2]));
            let ch = if depth == 0 {
                "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
            } else {
                "CHANNELS 3 Zrotation Xrotation Yrotation"
            };
            out.push_str(&format!("{pad}  {ch}\n"));
            let kids: Vec<usize> = rig.children(b).collect();
            if kids.is_empty() {
                out.push_str(&format!(
                    "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET 0 0 1\n{pad}  }}\n"
                ));
            }
            for c in kids {
                write(rig, pos, c, depth + 1, out);
            }
            out.push_str(&format!("{pad}}}\n"));
        }
        let mut out = String::from("HIERARCHY\n");
        write(rig, pos, 0, 0, &mut out);
        let channels = 6 + 3 * (rig.bone_count() - 1);
        out.push_str(&format!(
            "MOTION\nFrames: 1\nFrame Time: 0.05\n{}\n",
            vec!["0"; channels].join(" ")
        ));
        out
    }

    #[test]
    fn a_bvh_rig_with_engine_names_is_mapped_and_driven_by_itself() {
        // The unlike rig (cm, Z up facing −Y, A-pose, 5 spine bones, twist bones, a root) as a
        // BVH file: read back, its unit guessed, its UE-style names mapped automatically.
        let (built, _, _) = test_rig(5);
        let rig = bvh_rig::read(&bvh_of(&built), None).unwrap();
        assert_eq!(rig.metres_per_unit(), 0.01);
        let target = Target::auto(Skeleton::smpl24(), rig).unwrap();
        let rig = target.rig();
        assert_eq!(target.map().spine_chain(rig).len(), 5);
        let n = rig.bone_count();
        let (mut world, mut local) = (vec![IDENTITY; n], vec![IDENTITY; n]);
        let axes = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let bone = |name: &str| rig.find(name).unwrap();
        let mut worst = 0.0f64;
        for (g, sp, root) in source_motion(20) {
            let hips = target.frame(&g, &root, &mut world, &mut local).unwrap();
            let rp = posed(rig, &local, target.transfer().hips(), &hips);
            for (a, b, ra, rb) in [
                (16, 18, "upperarm_l", "lowerarm_l"),
                (19, 21, "lowerarm_r", "hand_r"),
                (2, 5, "thigh_r", "calf_r"),
                (4, 7, "calf_l", "foot_l"),
                (12, 15, "neck_01", "head"),
            ] {
                let want = rotation::apply(&axes, &[0, 1, 2].map(|i| sp[b][i] - sp[a][i]));
                let got = [0, 1, 2].map(|i| rp[bone(rb)][i] - rp[bone(ra)][i]);
                worst = worst.max(angle(&want, &got));
            }
        }
        assert!(worst < 1e-4, "a bone is {worst}° off its source");
    }

    #[test]
    fn a_zero_length_mapped_bone_is_refused_by_name() {
        let (built, _, _) = test_rig(3);
        let mut text = bvh_of(&built);
        // The left forearm's offset made zero: the elbow sits on the shoulder.
        let at = text.find("JOINT lowerarm_l").unwrap();
        let line = text[at..].find("OFFSET").unwrap() + at;
        let end = text[line..].find('\n').unwrap() + line;
        text.replace_range(line..end, "OFFSET 0 0 0");
        let rig = bvh_rig::read(&text, None).unwrap();
        let e = Target::auto(Skeleton::smpl24(), rig)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`upperarm_l` and `lowerarm_l` are at one place"),
            "{e}"
        );
    }
}
