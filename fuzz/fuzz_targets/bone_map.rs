//! Bone maps: the first byte picks the input's use. Even: the rest as text (lossy UTF-8) is a
//! JSON map for `BoneMap::from_json` over a fixed Mixamo-style rig, over its automatic map
//! (bit 1) or over nothing. Odd: the rest is a bone list, one bone a line, each line's first
//! byte its parent (0: a root, otherwise that byte modulo the bones before it) and the rest its
//! name, made into a rig and mapped by `BoneMap::auto`; with bit 1 set the rig also declares a
//! VRM map (each bone whose name starts with a byte below 26 declares that humanoid bone, or an
//! eye, a finger or an unknown name). A map that comes out must have each rig bone at most
//! once and inside the rig, a spine chain of distinct rig bones, `check_required` must answer,
//! and its JSON must read back as the same map.
#![no_main]

use std::sync::OnceLock;

use flame::retarget::bonemap::{BoneMap, HumanBone};
use flame::retarget::{BoneSpec, RestTransform, Rig, RigSource};
use libfuzzer_sys::fuzz_target;

fn rig(bones: Vec<(String, Option<usize>)>) -> flame::Result<Rig> {
    let specs = bones
        .into_iter()
        .map(|(name, parent)| BoneSpec {
            name,
            parent,
            rest: RestTransform::offset([0.0, 0.1, 0.0]),
        })
        .collect();
    Rig::new(specs, 1.0, RigSource::Code)
}

/// A Mixamo-style rig (with a namespace, fingers and end bones) and its automatic map.
fn fixed() -> &'static (Rig, BoneMap) {
    static FIXED: OnceLock<(Rig, BoneMap)> = OnceLock::new();
    FIXED.get_or_init(|| {
        let mut bones: Vec<(String, Option<usize>)> = Vec::new();
        let mut add = |name: &str, parent: Option<usize>| {
            bones.push((format!("mixamorig:{name}"), parent));
            bones.len() - 1
        };
        let hips = add("Hips", None);
        let spine = add("Spine", Some(hips));
        let spine1 = add("Spine1", Some(spine));
        let spine2 = add("Spine2", Some(spine1));
        let neck = add("Neck", Some(spine2));
        let head = add("Head", Some(neck));
        add("HeadTop_End", Some(head));
        for side in ["Left", "Right"] {
            let s = add(&format!("{side}Shoulder"), Some(spine2));
            let a = add(&format!("{side}Arm"), Some(s));
            let f = add(&format!("{side}ForeArm"), Some(a));
            let h = add(&format!("{side}Hand"), Some(f));
            let i = add(&format!("{side}HandIndex1"), Some(h));
            add(&format!("{side}HandIndex2"), Some(i));
            let u = add(&format!("{side}UpLeg"), Some(hips));
            let l = add(&format!("{side}Leg"), Some(u));
            let f = add(&format!("{side}Foot"), Some(l));
            let t = add(&format!("{side}ToeBase"), Some(f));
            add(&format!("{side}Toe_End"), Some(t));
        }
        let rig = rig(bones).expect("the fixed rig");
        let map = BoneMap::auto(&rig).expect("the fixed rig's map");
        (rig, map)
    })
}

fn check(map: &BoneMap, rig: &Rig) {
    let n = rig.bone_count();
    let mut seen = vec![false; n];
    for (_, b) in map.mapped() {
        assert!(b < n, "bone {b} of {n}");
        assert!(!seen[b], "bone {b} mapped twice");
        seen[b] = true;
    }
    let _ = map.check_required(rig);
    let mut in_chain = vec![false; n];
    for b in map.spine_chain(rig) {
        assert!(b < n && !in_chain[b], "spine chain bone {b}");
        in_chain[b] = true;
    }
    let json = map.to_json(rig);
    let back = BoneMap::from_json(rig, &json, None)
        .unwrap_or_else(|e| panic!("a map's own JSON does not read back: {e}\n{json}"));
    assert_eq!(&back, map);
}

/// Declared names: the humanoid bones, then bones libflame does not drive and unknown names.
fn declared_name(k: u8) -> &'static str {
    match k as usize {
        k if k < HumanBone::ALL.len() => HumanBone::ALL[k].name(),
        22 => "leftEye",
        23 => "leftThumbProximal",
        24 => "Hips",
        _ => "tail",
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    if mode & 1 == 0 {
        let (rig, auto) = fixed();
        let json = String::from_utf8_lossy(rest);
        let base = (mode & 2 != 0).then(|| auto.clone());
        if let Ok(map) = BoneMap::from_json(rig, &json, base) {
            check(&map, rig);
        }
        return;
    }
    let mut bones: Vec<(String, Option<usize>)> = Vec::new();
    let mut declared = Vec::new();
    for line in rest.split(|&b| b == b'\n') {
        let Some((&p, name)) = line.split_first() else {
            continue;
        };
        let k = bones.len();
        let parent = (k > 0 && p != 0).then(|| usize::from(p) % k);
        if let Some(&d) = name.first().filter(|&&d| d < 26) {
            declared.push((declared_name(d).to_string(), k));
        }
        bones.push((String::from_utf8_lossy(name).into_owned(), parent));
    }
    let Ok(mut rig) = rig(bones) else {
        return;
    };
    if mode & 2 != 0 {
        let Ok(with) = rig.with_declared(declared) else {
            return;
        };
        rig = with;
    }
    if let Ok(map) = BoneMap::auto(&rig) {
        check(&map, &rig);
    }
});
