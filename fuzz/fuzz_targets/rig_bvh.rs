//! BVH rigs ([`flame::retarget::bvh_rig::read`]). The first byte picks what the rest is:
//! - even: BVH text as it is (lossy UTF-8), with a unit chosen by the second byte (guessed, 1,
//!   0.01, 0, −1, NaN, ∞, or a tiny one);
//! - odd: a hierarchy built from the bytes (each joint a parent among those before it, a
//!   name from the names automatic bone maps know or a mangled one, an OFFSET from three bytes,
//!   now and then an End Site or a MOTION section), so most inputs are well-formed files that
//!   reach the bone map and the retarget target.
//!
//! A rig that reads is consistent (parents first, every joint's OFFSET its rest translation
//! with no rest rotation, finite rest frames, a positive unit: the one given, or 0.01 / 1 when
//! guessed); a unit that is not a positive length is refused; a bone map and a retarget target
//! made from it are errors or work, never a panic.
#![no_main]

use flame::motion::Skeleton;
use flame::retarget::bonemap::BoneMap;
use flame::retarget::{bvh_rig, Rig, Target};
use libfuzzer_sys::fuzz_target;

const NAMES: [&str; 24] = [
    "Hips",
    "Spine",
    "Spine1",
    "Spine2",
    "Neck",
    "Head",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "LeftToeBase",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "RightToeBase",
    "pelvis",
    "thigh_l",
];

fn check(rig: &Rig, unit: Option<f64>) {
    let n = rig.bone_count();
    assert!(n >= 1);
    for (b, p) in rig.parents().iter().enumerate() {
        assert!(p.is_none_or(|p| p < b));
        assert_eq!(rig.rest()[b].rotation, flame::motion::rotation::IDENTITY);
        assert_eq!(rig.rest()[b].scale, [1.0; 3]);
    }
    assert!(rig
        .rest_world_positions()
        .iter()
        .flatten()
        .all(|v| v.is_finite()));
    match unit {
        Some(u) => assert_eq!(rig.metres_per_unit(), u),
        None => assert!(rig.metres_per_unit() == 0.01 || rig.metres_per_unit() == 1.0),
    }
    if let Ok(map) = BoneMap::auto(rig) {
        if map.check_required(rig).is_ok() {
            let _ = Target::new(Skeleton::smpl24(), rig.clone(), map);
        }
    }
}

/// A BVH file from bytes: joints of known or mangled names under earlier joints.
fn built(data: &[u8]) -> String {
    let joints: Vec<&[u8]> = data.chunks(5).take(64).collect();
    let mut children = vec![Vec::new(); joints.len()];
    for (j, c) in joints.iter().enumerate().skip(1) {
        children[c[0] as usize % j].push(j);
    }
    fn write(j: usize, depth: usize, joints: &[&[u8]], children: &[Vec<usize>], out: &mut String) {
        let c = joints[j];
        let byte = |i: usize| c.get(i).copied().unwrap_or(0);
        let name = match byte(1) {
            b if (b as usize) < NAMES.len() * 8 => NAMES[b as usize % NAMES.len()].to_string(),
            b => format!("joint{b}_{j}"),
        };
        let o = |i: usize| (byte(i) as f64 - 128.0) / 4.0;
        let kind = if depth == 0 { "ROOT" } else { "JOINT" };
        out.push_str(&format!(
            "{kind} {name}\n{{\nOFFSET {} {} {}\n",
            o(2),
            o(3),
            o(4)
        ));
        out.push_str(if depth == 0 {
            "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
        } else {
            "CHANNELS 3 Zrotation Xrotation Yrotation\n"
        });
        if children[j].is_empty() && byte(1) % 2 == 0 {
            out.push_str("End Site\n{\nOFFSET 0 1 0\n}\n");
        }
        for &k in &children[j] {
            write(k, depth + 1, joints, children, out);
        }
        out.push_str("}\n");
    }
    let mut out = String::from("HIERARCHY\n");
    if !joints.is_empty() {
        write(0, 0, &joints, &children, &mut out);
    }
    if data.len() % 3 == 0 {
        out.push_str("MOTION\nFrames: 1\nFrame Time: 0.05\n0 0 0\n");
    }
    out
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let (text, unit) = if mode % 2 == 0 {
        let Some((&u, rest)) = rest.split_first() else {
            return;
        };
        let unit = match u % 8 {
            0 => None,
            1 => Some(1.0),
            2 => Some(0.01),
            3 => Some(0.0),
            4 => Some(-1.0),
            5 => Some(f64::NAN),
            6 => Some(f64::INFINITY),
            _ => Some(1e-300),
        };
        (String::from_utf8_lossy(rest).into_owned(), unit)
    } else {
        (built(rest), None)
    };
    let read = bvh_rig::read(&text, unit);
    if unit.is_some_and(|u| !(u.is_finite() && u > 0.0)) {
        assert!(read.is_err(), "unit {unit:?} accepted");
        return;
    }
    if let Ok(rig) = read {
        check(&rig, unit);
    }
});
