//! A [`Rig`] read from a BVH hierarchy ([`read`]).
//!
//! - **Bones.** The `ROOT` and `JOINT`s in file order, named as the file names them, each at
//!   its `OFFSET` from its parent with no rest rotation (BVH rests are the offsets alone; the
//!   root's OFFSET is its rest position). `End Site`s are not bones.
//! - **Hierarchy only.** The `MOTION` section is not read (a rig needs none, and a clip's
//!   motion, broken or huge, does not stop its skeleton from being used); a file may end after
//!   its hierarchy.
//! - **Units.** BVH says nothing about its unit. Given none, [`read`] guesses from the rest
//!   joints' extent (the largest side of the box around them: the height of a standing
//!   character whatever its up axis, or its arm span, which is about the same): above
//!   [`CENTIMETRE_EXTENT`] units the file is taken to be in centimetres (0.01 m a unit; Mixamo,
//!   Blender exports scaled by 100, most motion-capture files), otherwise in metres. A file in
//!   inches (a 1.7 m person is ~60 units across) is taken as centimetres: callers let users
//!   say the unit (`metres_per_unit`).

use super::rig::{BoneSpec, RestTransform, Rig, RigSource};
use crate::error::{invalid_arg, Result};
use crate::motion::bvh;

/// Rest joint extent (file units) above which a BVH file is taken to be in centimetres: a
/// human in metres spans about 1.5 to 2, in centimetres 150 to 200.
pub const CENTIMETRE_EXTENT: f64 = 20.0;

/// The rig of a BVH hierarchy (module doc). `metres_per_unit` is the file's unit in metres
/// (0.01 for centimetres), guessed from the skeleton's size when `None`. Errors are the
/// parser's (with line numbers), a unit that is not a positive length, a guess on a skeleton
/// whose joints all coincide, and [`Rig::new`]'s.
pub fn read(text: &str, metres_per_unit: Option<f64>) -> Result<Rig> {
    // The hierarchy and an empty motion section in place of the file's (same line numbers).
    let lines: Vec<&str> = text.lines().collect();
    let motion_at = lines
        .iter()
        .position(|l| l.split_whitespace().next() == Some("MOTION"))
        .unwrap_or(lines.len());
    let mut hierarchy = lines[..motion_at].join("\n");
    hierarchy.push_str("\nMOTION\nFrames: 0\nFrame Time: 1\n");
    let parsed = bvh::parse(&hierarchy)?;
    let joints = parsed.joints();
    let bones: Vec<BoneSpec> = joints
        .iter()
        .map(|j| BoneSpec {
            name: j.name().to_string(),
            parent: j.parent(),
            rest: RestTransform::offset(j.offset()),
        })
        .collect();
    let unit = match metres_per_unit {
        Some(u) => u,
        None => {
            let extent = rest_extent(&bones);
            if !extent.is_finite() {
                return Err(invalid_arg!(
                    "BVH: the hierarchy's rest joint positions are not finite (OFFSETs too large)"
                ));
            }
            if extent <= 0.0 {
                return Err(invalid_arg!(
                    "BVH: every joint of the hierarchy is at the same place (all OFFSETs zero?), so its unit cannot be told; give it"
                ));
            }
            guess_unit(extent)
        }
    };
    Rig::new(bones, unit, RigSource::Bvh)
}

/// Metres per unit for a skeleton `extent` units across (module doc).
pub fn guess_unit(extent: f64) -> f64 {
    if extent > CENTIMETRE_EXTENT {
        0.01
    } else {
        1.0
    }
}

/// The largest side of the box around the rest joint positions (bones parents first, as the
/// parser gives them). NaN when a position is not finite.
fn rest_extent(bones: &[BoneSpec]) -> f64 {
    let mut world: Vec<[f64; 3]> = Vec::with_capacity(bones.len());
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for b in bones {
        let t = b.rest.translation;
        let p = match b.parent {
            Some(p) if p < world.len() => {
                [world[p][0] + t[0], world[p][1] + t[1], world[p][2] + t[2]]
            }
            _ => t,
        };
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        world.push(p);
    }
    let sides = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
    if sides.iter().any(|s| !s.is_finite()) {
        return f64::NAN;
    }
    sides.into_iter().fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Mixamo-like hierarchy in centimetres: hips 100 above the origin, a spine, a head, a
    /// leg to the ground (an End Site under the head and the foot).
    const CM: &str = "HIERARCHY
ROOT Hips
{
  OFFSET 0 100 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 -2
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 60 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 20 0
      }
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 9 -5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT LeftFoot
    {
      OFFSET 0 -95 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 0 10
      }
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.033333
0 100 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0
";

    #[test]
    fn joints_are_bones_at_their_offsets_and_end_sites_are_not() {
        let rig = read(CM, None).unwrap();
        assert_eq!(
            rig.names(),
            ["Hips", "Spine", "Head", "LeftUpLeg", "LeftFoot"]
        );
        assert_eq!(rig.parents(), [None, Some(0), Some(1), Some(0), Some(3)]);
        assert_eq!(rig.source(), &RigSource::Bvh);
        assert!(rig.declared_map().is_empty());
        // World positions: sums of offsets down the chain.
        let p = rig.rest_world_positions();
        assert_eq!(p[0], [0.0, 100.0, 0.0]);
        assert_eq!(p[2], [0.0, 170.0, -2.0]);
        assert_eq!(p[4], [9.0, 0.0, 0.0]);
        assert_eq!(rig.rest()[1].translation, [0.0, 10.0, -2.0]);
        assert!(rig
            .rest_world_rotations()
            .iter()
            .all(|r| *r == crate::motion::rotation::IDENTITY));
        // 0 to 170 units high: centimetres.
        assert_eq!(rig.metres_per_unit(), 0.01);
    }

    #[test]
    fn the_unit_is_guessed_from_the_extent_or_given() {
        // The same skeleton in metres: 1.7 units high.
        let metres = CM
            .replace("OFFSET 0 100 0", "OFFSET 0 1 0")
            .replace("OFFSET 0 10 -2", "OFFSET 0 0.1 -0.02")
            .replace("OFFSET 0 60 0", "OFFSET 0 0.6 0")
            .replace("OFFSET 9 -5 0", "OFFSET 0.09 -0.05 0")
            .replace("OFFSET 0 -95 0", "OFFSET 0 -0.95 0");
        let rig = read(&metres, None).unwrap();
        assert_eq!(rig.metres_per_unit(), 1.0);
        let head = rig.rest_world_positions()[2];
        assert!(
            (head[1] - 1.7).abs() < 1e-12 && head[2] == -0.02,
            "{head:?}"
        );
        // A Z-up skeleton: the extent is along Z.
        let z_up = CM
            .replace("OFFSET 0 100 0", "OFFSET 0 0 100")
            .replace("OFFSET 0 60 0", "OFFSET 0 0 60");
        assert_eq!(read(&z_up, None).unwrap().metres_per_unit(), 0.01);
        // The boundary: above 20 units is centimetres.
        assert_eq!(guess_unit(20.0), 1.0);
        assert_eq!(guess_unit(20.5), 0.01);
        // Given, the unit is taken as it is (inches here).
        assert_eq!(read(CM, Some(0.0254)).unwrap().metres_per_unit(), 0.0254);
        let e = read(CM, Some(0.0)).unwrap_err().to_string();
        assert!(e.contains("positive length"), "{e}");
        let e = read(CM, Some(f64::NAN)).unwrap_err().to_string();
        assert!(e.contains("positive length"), "{e}");
    }

    #[test]
    fn the_motion_section_is_not_needed_or_read() {
        let hierarchy_only = &CM[..CM.find("MOTION").unwrap()];
        let a = read(hierarchy_only, None).unwrap();
        // A broken motion section (too few values, a frame count that lies) does not matter.
        let broken = format!("{hierarchy_only}MOTION\nFrames: 99\nFrame Time: -1\n1 2 3\n");
        let b = read(&broken, None).unwrap();
        let c = read(CM, None).unwrap();
        for rig in [&a, &b] {
            assert_eq!(rig.names(), c.names());
            assert_eq!(rig.rest_world_positions(), c.rest_world_positions());
        }
    }

    #[test]
    fn bad_hierarchies_are_errors_with_their_line() {
        let e = read("", None).unwrap_err().to_string();
        assert!(e.contains("HIERARCHY"), "{e}");
        let no_offset = CM.replace("    OFFSET 0 60 0\n", "");
        let e = read(&no_offset, None).unwrap_err().to_string();
        assert!(e.contains("`Head` has no OFFSET"), "{e}");
        let twice = CM.replace("JOINT LeftFoot", "JOINT Spine");
        let e = read(&twice, None).unwrap_err().to_string();
        assert!(e.contains("`Spine` appears twice"), "{e}");
        let unclosed = &CM[..CM.rfind('}').unwrap()];
        let e = read(unclosed, None).unwrap_err().to_string();
        assert!(e.contains("is closed"), "{e}");
        // Every joint at the origin: no unit can be guessed, but one can be given.
        let flat = "HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nJOINT b\n{\nOFFSET 0 0 0\n}\n}\n";
        let e = read(flat, None).unwrap_err().to_string();
        assert!(e.contains("same place"), "{e}");
        assert_eq!(read(flat, Some(1.0)).unwrap().bone_count(), 2);
        // Offsets too large for f64 sums.
        let huge = "HIERARCHY\nROOT a\n{\nOFFSET 1e308 0 0\nJOINT b\n{\nOFFSET 1e308 0 0\n}\n}\n";
        assert!(read(huge, None).is_err());
        assert!(read(huge, Some(1.0)).is_err());
    }

    #[test]
    fn every_truncation_is_an_answer_not_a_panic() {
        for cut in 0..CM.len() {
            if CM.is_char_boundary(cut) {
                let _ = read(&CM[..cut], None);
            }
        }
    }
}
