//! `flame generate` pose outputs, end to end on the tiny FLAME fixture
//! (tests/fixtures/flame_tiny.safetensors, format smpl24_6d): the writer follows the extension,
//! `--positions` and the JSON carry the same numbers as the library, bad arguments fail early
//! with a message.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use flame::motion::{self, Convention, Format, Layout, ReadOptions};

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flame_motion_cli_{}_{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn generate(extra: &[&str]) -> Output {
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/flame_tiny.safetensors");
    let mut args = vec![
        "generate",
        "--model",
        model.to_str().unwrap(),
        "--prompt",
        "a person walks",
    ];
    args.extend_from_slice(&[
        "--frames",
        "16",
        "--steps",
        "2",
        "--seed",
        "3",
        "--threads",
        "1",
    ]);
    args.extend_from_slice(extra);
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(&args)
        .output()
        .unwrap()
}

fn ok(out: Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn outputs_carry_the_library_numbers() {
    let d = tmp_dir("ok");
    let (raw, pos, json, bvh) = (
        d.join("raw.npy"),
        d.join("pos.npy"),
        d.join("m.json"),
        d.join("m.bvh"),
    );
    ok(generate(&[
        "--out",
        raw.to_str().unwrap(),
        "--positions",
        pos.to_str().unwrap(),
        "--convention",
        "ros",
    ]));
    let (shape, x) = flame::npy::read_f32(&raw).unwrap();
    assert_eq!(shape, vec![16, 147]);
    // Defaults for smpl24_6d: FLAME's smoothing (sigma 1), continuous quaternions, and the
    // game-ready finish (feet locked, floor at 0) at the model's 20 fps.
    let smooth = ReadOptions {
        smooth_sigma: 1.0,
        finish: motion::Finish::game_ready(),
        ..Default::default()
    };
    let want = motion::read_layout(
        Format::Smpl24Rot6d,
        &x,
        16,
        Layout::GlobalPositions,
        Convention::Ros,
        &smooth,
    )
    .unwrap();
    let (pshape, p) = flame::npy::read_f32(&pos).unwrap();
    assert_eq!(pshape, vec![16, 24, 3]);
    assert_eq!(p, want);

    // Same seed, same motion: the JSON is the library's JSON of those features.
    ok(generate(&[
        "--out",
        json.to_str().unwrap(),
        "--convention",
        "unity",
        "--smooth",
        "0",
        "--quat",
        "xyzw",
        "--feet",
        "off",
    ]));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(
        (v["convention"].as_str(), v["rotation_quat_order"].as_str()),
        (Some("unity"), Some("xyzw"))
    );
    let raw_opts = ReadOptions::default();
    let root = motion::read_layout(
        Format::Smpl24Rot6d,
        &x,
        16,
        Layout::RootTranslation,
        Convention::Unity,
        &raw_opts,
    )
    .unwrap();
    let quats = motion::read_layout(
        Format::Smpl24Rot6d,
        &x,
        16,
        Layout::LocalQuatXyzw,
        Convention::Unity,
        &raw_opts,
    )
    .unwrap();
    for t in 0..16 {
        for k in 0..3 {
            assert_eq!(
                v["translation"][t][k].as_f64().unwrap() as f32,
                root[t * 3 + k]
            );
        }
        for k in 0..4 {
            assert_eq!(
                v["rotation_quat"][t][5][k].as_f64().unwrap() as f32,
                quats[(t * 24 + 5) * 4 + k]
            );
        }
    }

    ok(generate(&[
        "--out",
        bvh.to_str().unwrap(),
        "--convention",
        "gltf",
    ]));
    let text = std::fs::read_to_string(&bvh).unwrap();
    assert!(
        text.starts_with("HIERARCHY\nROOT Pelvis\n")
            && text.contains("Frames: 16\nFrame Time: 0.050000\n")
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn bad_arguments_fail_before_sampling() {
    let d = tmp_dir("bad");
    let out = |name: &str| d.join(name).to_str().unwrap().to_string();
    let cases: [(Vec<String>, &str); 6] = [
        (
            vec!["--out".into(), out("m.txt")],
            "--out must end in .npy, .npz, .bvh, .json, .glb, .gltf or .vrma",
        ),
        (
            vec![
                "--out".into(),
                out("m.bvh"),
                "--convention".into(),
                "maya".into(),
            ],
            "unknown convention `maya`",
        ),
        (
            vec!["--out".into(), out("m.bvh"), "--smooth".into(), "-1".into()],
            "the sigma must be a number of frames, 0 or more",
        ),
        (
            vec![
                "--out".into(),
                out("m.json"),
                "--quat".into(),
                "zyxw".into(),
            ],
            "unknown quaternion order",
        ),
        (
            vec![
                "--out".into(),
                out("m.bvh"),
                "--positions".into(),
                out("p.csv"),
            ],
            "--positions must end in .npy",
        ),
        (
            vec!["--out".into(), out("m.bvh"), "--smooth".into(), "x".into()],
            "invalid value 'x' for '--smooth <SIGMA>'",
        ),
    ];
    for (args, msg) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = generate(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?} succeeded");
        assert!(err.contains(msg), "{args:?}: {err}");
        assert!(!err.contains("step 1/"), "{args:?}: sampled before failing");
    }
    assert_eq!(std::fs::read_dir(&d).unwrap().count(), 0, "no file written");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn weights_option_selects_the_linear_weight_type() {
    let d = tmp_dir("weights");
    let run = |w: &str| {
        let out = d.join(format!("{w}.npy"));
        ok(generate(&["--weights", w, "--out", out.to_str().unwrap()]));
        flame::npy::read_f32(&out).unwrap().1
    };
    let (full, half) = (run("f32"), run("bf16"));
    assert_eq!(full.len(), half.len());
    assert!(half.iter().all(|v| v.is_finite()));
    assert_ne!(full, half, "bf16 weights must change the numbers");
    let out = generate(&[
        "--weights",
        "f8",
        "--out",
        d.join("x.npy").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--weights"));
}
