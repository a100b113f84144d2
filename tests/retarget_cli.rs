//! `--rig` and `flame retarget`, end to end on the tiny FLAME fixture: a rig that is libflame's
//! own skeleton renamed to Mixamo's bones and scaled to centimetres by hand must move exactly as
//! libflame's joints do (a hand-derived case: same shape, so the retarget is the identity up to
//! units and names); bad arguments fail before any model is loaded, with a message.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;

use common::max_abs_diff;

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flame_retarget_cli_{}_{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn flame(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .output()
        .unwrap()
}

fn model() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/flame_tiny.safetensors")
        .display()
        .to_string()
}

fn generate(extra: &[&str]) -> Output {
    let m = model();
    let mut args = vec![
        "generate",
        "--model",
        &m,
        "--prompt",
        "a person walks",
        "--frames",
        "16",
        "--steps",
        "2",
        "--seed",
        "3",
        "--threads",
        "1",
    ];
    args.extend_from_slice(extra);
    flame(&args)
}

fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn fails_with(out: &Output, what: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "succeeded; stderr: {err}");
    assert!(err.contains(what), "`{what}` not in: {err}");
}

/// libflame's SMPL joint names (as its BVH writes them) and Mixamo's for the same joints.
const MIXAMO: [(&str, &str); 24] = [
    ("Pelvis", "mixamorig:Hips"),
    ("L_Hip", "mixamorig:LeftUpLeg"),
    ("L_Knee", "mixamorig:LeftLeg"),
    ("L_Ankle", "mixamorig:LeftFoot"),
    ("L_Foot", "mixamorig:LeftToeBase"),
    ("R_Hip", "mixamorig:RightUpLeg"),
    ("R_Knee", "mixamorig:RightLeg"),
    ("R_Ankle", "mixamorig:RightFoot"),
    ("R_Foot", "mixamorig:RightToeBase"),
    ("Spine1", "mixamorig:Spine"),
    ("Spine2", "mixamorig:Spine1"),
    ("Spine3", "mixamorig:Spine2"),
    ("Neck", "mixamorig:Neck"),
    ("Head", "mixamorig:Head"),
    ("L_Collar", "mixamorig:LeftShoulder"),
    ("L_Shoulder", "mixamorig:LeftArm"),
    ("L_Elbow", "mixamorig:LeftForeArm"),
    ("L_Wrist", "mixamorig:LeftHand"),
    ("L_Hand", "mixamorig:LeftHandMiddle1"),
    ("R_Collar", "mixamorig:RightShoulder"),
    ("R_Shoulder", "mixamorig:RightArm"),
    ("R_Elbow", "mixamorig:RightForeArm"),
    ("R_Wrist", "mixamorig:RightHand"),
    ("R_Hand", "mixamorig:RightHandMiddle1"),
];

/// libflame's BVH hierarchy with Mixamo's names and every OFFSET in centimetres.
fn mixamo_rig(bvh: &str) -> String {
    let mut out = String::new();
    for line in bvh.lines() {
        let t = line.trim_start();
        let pad = &line[..line.len() - t.len()];
        if t.starts_with("MOTION") {
            // One frame of zeros: a rig file's hierarchy is what is read.
            out.push_str("MOTION\nFrames: 1\nFrame Time: 0.05\n");
            out.push_str(&vec!["0"; 6 + 3 * 23].join(" "));
            out.push('\n');
            break;
        }
        if let Some(name) = t.strip_prefix("ROOT ").or_else(|| t.strip_prefix("JOINT ")) {
            let kind = &t[..t.len() - name.len()];
            let m = MIXAMO.iter().find(|(a, _)| *a == name.trim()).unwrap().1;
            out.push_str(&format!("{pad}{kind}{m}\n"));
        } else if let Some(v) = t.strip_prefix("OFFSET ") {
            let cm: Vec<String> = v
                .split_whitespace()
                .map(|x| format!("{:.6}", x.parse::<f64>().unwrap() * 100.0))
                .collect();
            out.push_str(&format!("{pad}OFFSET {}\n", cm.join(" ")));
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

fn npy(path: &Path) -> (Vec<usize>, Vec<f32>) {
    flame::npy::read_f32(path).unwrap()
}

#[test]
fn a_renamed_centimetre_copy_of_the_skeleton_moves_as_libflames_joints() {
    let d = tmp_dir("mixamo");
    let (src_bvh, src_pos) = (d.join("src.bvh"), d.join("src.npy"));
    ok(&generate(&[
        "--out",
        src_bvh.to_str().unwrap(),
        "--positions",
        src_pos.to_str().unwrap(),
    ]));
    let rig = d.join("mixamo.bvh");
    std::fs::write(
        &rig,
        mixamo_rig(&std::fs::read_to_string(&src_bvh).unwrap()),
    )
    .unwrap();
    let (out_bvh, rig_pos, src_pos2) = (d.join("out.bvh"), d.join("rig.npy"), d.join("s2.npy"));
    // From the sampled motion directly, and from its BVH through `flame retarget`.
    ok(&generate(&[
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out_bvh.to_str().unwrap(),
        "--rig-positions",
        rig_pos.to_str().unwrap(),
        "--positions",
        src_pos2.to_str().unwrap(),
    ]));
    let (shape, src) = npy(&src_pos);
    let (rshape, rp) = npy(&rig_pos);
    assert_eq!(shape, [16, 24, 3]);
    assert_eq!(rshape, [16, 24, 3]);
    assert_eq!(npy(&src_pos2).1, src, "--positions changed with --rig");
    // The rig's bones in the BVH's order (depth first) and SMPL's joint order.
    let text = std::fs::read_to_string(&rig).unwrap();
    let order: Vec<&str> = text
        .lines()
        .filter_map(|l| {
            let t = l.trim_start();
            t.strip_prefix("ROOT ").or_else(|| t.strip_prefix("JOINT "))
        })
        .collect();
    let hips = order.iter().position(|n| *n == "mixamorig:Hips").unwrap();
    let mut worst = 0.0f64;
    for f in 0..16 {
        let at = |v: &[f32], i: usize| [0, 1, 2].map(|k| v[(f * 24 + i) * 3 + k] as f64);
        // libflame's BVH names SMPL's joints as the skeleton does, in SMPL's order (the order
        // of `--positions`).
        let smpl = flame::motion::Skeleton::smpl24().joint_names();
        for (j, smpl_name) in smpl.iter().enumerate() {
            let name = MIXAMO.iter().find(|(a, _)| a == smpl_name).unwrap().1;
            let b = order.iter().position(|n| *n == name).unwrap();
            let (s, s0) = (at(&src, j), at(&src, 0));
            let (r, r0) = (at(&rp, b), at(&rp, hips));
            for k in 0..3 {
                // Centimetres against metres, relative to the pelvis (the rig's floor is its
                // own, the BVH's rest pelvis height under it).
                worst = worst.max(((r[k] - r0[k]) / 100.0 - (s[k] - s0[k])).abs());
            }
            if j == 0 {
                // The horizontal path is carried whole.
                for k in [0, 2] {
                    worst = worst.max((r[k] / 100.0 - s[k]).abs());
                }
            }
        }
    }
    assert!(worst < 1e-5, "a joint is {worst} m from libflame's");

    // `flame retarget` from the BVH gives the same rig motion (the BVH holds the finished
    // poses to 6 decimals).
    let (again, rig_pos2) = (d.join("again.bvh"), d.join("rig2.npy"));
    ok(&flame(&[
        "retarget",
        "--rig",
        rig.to_str().unwrap(),
        "--in",
        src_bvh.to_str().unwrap(),
        // The random fixture's motion does not stand upright, which is how a BVH's native
        // and gltf conventions are told apart: say it.
        "--in-convention",
        "gltf",
        "--out",
        again.to_str().unwrap(),
        "--rig-positions",
        rig_pos2.to_str().unwrap(),
    ]));
    let rp2 = npy(&rig_pos2).1;
    let diff = max_abs_diff(&rp, &rp2);
    assert!(diff < 0.05, "retarget from the BVH is {diff} cm off");

    // And from the same motion written as glTF (f32 tracks, glTF's own axes: no convention
    // to name).
    let (src_glb, rig_pos3) = (d.join("src.glb"), d.join("rig3.npy"));
    ok(&generate(&["--out", src_glb.to_str().unwrap()]));
    ok(&flame(&[
        "retarget",
        "--rig",
        rig.to_str().unwrap(),
        "--in",
        src_glb.to_str().unwrap(),
        "--out",
        d.join("again3.bvh").to_str().unwrap(),
        "--rig-positions",
        rig_pos3.to_str().unwrap(),
    ]));
    let rp3 = npy(&rig_pos3).1;
    let diff = max_abs_diff(&rp, &rp3);
    assert!(diff < 0.01, "retarget from the glTF is {diff} cm off");
}

#[test]
fn rig_arguments_are_checked_before_the_model_loads() {
    let d = tmp_dir("args");
    let out = d.join("x.bvh");
    let o = out.to_str().unwrap();
    // A missing model file would fail later: these must fail first, on the rig.
    let no_model = ["--model", "/nonexistent/model.safetensors"];
    let run = |extra: &[&str]| {
        let mut a = vec!["generate", "--prompt", "a person walks"];
        a.extend_from_slice(&no_model);
        a.extend_from_slice(extra);
        flame(&a)
    };
    fails_with(
        &run(&["--rig-map", "m.json", "--out", o]),
        "--rig-map needs --rig",
    );
    fails_with(
        &run(&["--rig", "/nonexistent/rig.glb", "--out", o]),
        "cannot read /nonexistent/rig.glb",
    );
    let txt = d.join("rig.txt");
    std::fs::write(&txt, "x").unwrap();
    fails_with(
        &run(&["--rig", txt.to_str().unwrap(), "--out", o]),
        "--rig must end in .glb, .gltf, .vrm or .bvh",
    );
    // A skeleton with no arms cannot be driven: the missing bones are listed.
    let legs = d.join("legs.bvh");
    std::fs::write(
        &legs,
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 90 0\n CHANNELS 6 Xposition Yposition Zposition \
         Zrotation Xrotation Yrotation\n JOINT LeftUpLeg\n {\n  OFFSET 10 -5 0\n  CHANNELS 3 \
         Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\nMOTION\n\
         Frames: 1\nFrame Time: 0.05\n0 0 0 0 0 0 0 0 0\n",
    )
    .unwrap();
    let e = run(&["--rig", legs.to_str().unwrap(), "--out", o]);
    fails_with(&e, "lacks required humanoid bones");
    fails_with(&e, "leftUpperArm");
    // A rig's files are the character or a .vrma.
    let src = d.join("src.bvh");
    ok(&generate(&["--out", src.to_str().unwrap()]));
    let rig = d.join("rig.bvh");
    std::fs::write(&rig, mixamo_rig(&std::fs::read_to_string(&src).unwrap())).unwrap();
    let r = rig.to_str().unwrap();
    let json = d.join("x.json");
    fails_with(
        &run(&["--rig", r, "--out", json.to_str().unwrap()]),
        "with --rig, --out is the character",
    );
    fails_with(
        &run(&["--rig", r, "--out", d.join("x.glb").to_str().unwrap()]),
        "a .bvh rig is handed back as .bvh",
    );
    fails_with(&run(&["--rig", r, "--out", r]), "is the --rig file");
    // A bone map naming a bone the rig does not have.
    let map = d.join("map.json");
    std::fs::write(&map, r#"{"leftHand": "mixamorig:LeftPaw"}"#).unwrap();
    fails_with(
        &run(&["--rig", r, "--rig-map", map.to_str().unwrap(), "--out", o]),
        "mixamorig:LeftPaw",
    );
    // `flame retarget` needs a rig (or a .vrma) and an input it can read.
    fails_with(
        &flame(&["retarget", "--in", src.to_str().unwrap(), "--out", o]),
        "retarget needs --rig",
    );
    fails_with(
        &flame(&[
            "retarget",
            "--rig",
            r,
            "--in",
            txt.to_str().unwrap(),
            "--out",
            o,
        ]),
        "--in must end in .bvh or .glb/.gltf",
    );
}
