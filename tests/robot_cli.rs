//! `flame generate|retarget --robot robot.urdf`: the robot trajectory files from the command line
//! (the tiny FLAME fixture's motion onto the real GR1T2 and JVRC-1 descriptions, fetched into
//! target/robots by tools/fetch_robots.sh), the default configuration lookup, and every refusal
//! as a clear message with exit status 1 (2 for what the grammar refuses) before any model is
//! loaded. The files' contents are checked in tests/robot_export.rs (NumPy, MuJoCo); here the
//! shapes, the frame counts after `--fps` and the names.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("robot_cli_{name}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn flame_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .current_dir(dir)
        .args(args)
        .output()
        .unwrap()
}

fn flame(args: &[&str]) -> Output {
    flame_in(&common::repo(""), args)
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn model() -> String {
    common::repo("tests/fixtures/flame_tiny.safetensors")
        .display()
        .to_string()
}

/// `generate` with the tiny model, 40 frames at 20 fps, and `extra` arguments.
fn generate(extra: &[&str]) -> Output {
    let m = model();
    let mut args = vec![
        "generate",
        "--model",
        &m,
        "--prompt",
        "a person walks forward",
        "--frames",
        "40",
        "--steps",
        "3",
    ];
    args.extend_from_slice(extra);
    flame(&args)
}

fn csv_rows(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect()
}

fn contains(bytes: &[u8], s: &str) -> bool {
    bytes.windows(s.len()).any(|w| w == s.as_bytes())
}

#[test]
fn generate_writes_each_layout() {
    const TEST: &str = "robot_cli::generate_writes_each_layout";
    let Some((urdf, _)) = common::real_urdf(TEST, "gr1t2") else {
        return;
    };
    let urdf = urdf.display().to_string();
    let dir = scratch("layouts");
    let csv = dir.join("walk.csv");
    let o = generate(&[
        "--robot",
        &urdf,
        "--out",
        csv.to_str().unwrap(),
        "--fps",
        "30",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The shipped configuration, found from the current directory (the repository).
    assert!(
        stderr(&o).contains("configuration robots/gr1t2.json"),
        "{}",
        stderr(&o)
    );
    assert!(stderr(&o).contains("residual median"), "{}", stderr(&o));
    let rows = csv_rows(&csv);
    // 40 frames at 20 fps span 1.95 s: 59 frames at 30 fps.
    assert_eq!(rows.len(), 59);
    for r in &rows {
        assert_eq!(r.len(), 7 + 32);
        let norm: f64 = r[3..7].iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-9, "{norm}");
    }
    assert!(!std::fs::read_to_string(&csv).unwrap().starts_with('#'));

    let with_header = dir.join("walk_header.csv");
    let o = generate(&[
        "--robot",
        &urdf,
        "--out",
        with_header.to_str().unwrap(),
        "--fps",
        "30",
        "--csv-header",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = std::fs::read_to_string(&with_header).unwrap();
    assert!(
        text.starts_with("# x,y,z,qx,qy,qz,qw,left_hip_roll_joint,"),
        "{}",
        &text[..80]
    );
    // The same motion, the same rows.
    assert_eq!(csv_rows(&with_header), rows);

    let npz = dir.join("walk.npz");
    let o = generate(&[
        "--robot",
        &urdf,
        "--out",
        npz.to_str().unwrap(),
        "--fps",
        "30",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&npz).unwrap();
    for key in ["fps", "root_pos", "root_rot", "dof_pos", "joint_names"] {
        assert!(contains(&bytes, &format!("{key}.npy")), "{key}");
    }
    assert!(contains(&bytes, "'shape': (59, 32)"));
    assert!(!contains(&bytes, "smpl"), "an AMASS file was written");

    for (name, format) in [("walk_qpos.npy", None), ("walk_qpos.csv", Some("qpos"))] {
        let out = dir.join(name);
        let mut args = vec![
            "--robot",
            &urdf,
            "--out",
            out.to_str().unwrap(),
            "--fps",
            "30",
        ];
        if let Some(f) = format {
            args.extend(["--robot-format", f]);
        }
        let o = generate(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        let qpos: Vec<Vec<f64>> = if name.ends_with(".npy") {
            let (shape, v) = flame::npy::read_f32(&out).unwrap();
            assert_eq!(shape, [59, 39]);
            v.chunks(39)
                .map(|r| r.iter().map(|&x| x as f64).collect())
                .collect()
        } else {
            csv_rows(&out)
        };
        // w first: BeyondMimic's x, y, z, w turned into w, x, y, z (f32 for the .npy).
        for (q, r) in qpos.iter().zip(&rows) {
            let want = [r[6], r[3], r[4], r[5]];
            for k in 0..4 {
                assert!((q[3 + k] - want[k]).abs() < 1e-6, "{q:?} {r:?}");
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn retarget_carries_a_bvh_onto_the_robot() {
    const TEST: &str = "robot_cli::retarget_carries_a_bvh_onto_the_robot";
    let Some((urdf, _)) = common::real_urdf(TEST, "jvrc1") else {
        return;
    };
    let urdf = urdf.display().to_string();
    let dir = scratch("retarget");
    let bvh = dir.join("walk.bvh");
    let o = generate(&["--out", bvh.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = dir.join("walk.csv");
    let config = common::repo("robots/jvrc1.json").display().to_string();
    let o = flame(&[
        "retarget",
        "--in",
        bvh.to_str().unwrap(),
        "--robot",
        &urdf,
        "--retarget",
        &config,
        "--out",
        out.to_str().unwrap(),
        "--fps",
        "50",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let rows = csv_rows(&out);
    // 40 frames at 20 fps span 1.95 s: 98 frames at 50 fps.
    assert_eq!(rows.len(), 98);
    assert!(rows.iter().all(|r| r.len() == 7 + 34));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_robot_input_is_refused_before_the_model_loads() {
    let dir = scratch("refusals");
    let toy = dir.join("toy.urdf");
    std::fs::write(
        &toy,
        r#"<robot name="toy_bot"><link name="base"/><link name="a"/>
           <joint name="j" type="revolute"><parent link="base"/><child link="a"/>
           <axis xyz="0 0 1"/><limit lower="-1" upper="1" velocity="1" effort="1"/></joint>
           </robot>"#,
    )
    .unwrap();
    let cycle = dir.join("cycle.urdf");
    std::fs::write(
        &cycle,
        r#"<robot name="c"><link name="a"/><link name="b"/>
           <joint name="ab" type="fixed"><parent link="a"/><child link="b"/></joint>
           <joint name="ba" type="fixed"><parent link="b"/><child link="a"/></joint></robot>"#,
    )
    .unwrap();
    let bad_config = dir.join("bad.json");
    std::fs::write(&bad_config, r#"{"robot_root_name": "no_such_body"}"#).unwrap();
    let out = |n: &str| dir.join(n).display().to_string();
    let (toy, cycle, bad_config) = (
        toy.display().to_string(),
        cycle.display().to_string(),
        bad_config.display().to_string(),
    );
    let m = model();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "--retarget".into(),
                bad_config.clone(),
                "--out".into(),
                out("a.csv"),
            ],
            "--retarget needs --robot",
        ),
        (
            vec!["--csv-header".into(), "--out".into(), out("a.bvh")],
            "--csv-header needs --robot",
        ),
        (
            vec!["--robot".into(), toy.clone(), "--out".into(), out("a.bvh")],
            "not .bvh",
        ),
        (
            vec![
                "--robot".into(),
                toy.clone(),
                "--robot-format".into(),
                "gmr".into(),
                "--out".into(),
                out("a.csv"),
            ],
            "a .csv cannot hold the gmr layout",
        ),
        (
            vec![
                "--robot".into(),
                toy.clone(),
                "--csv-header".into(),
                "--out".into(),
                out("a.npz"),
            ],
            "--csv-header is for a .csv",
        ),
        (
            vec![
                "--robot".into(),
                toy.clone(),
                "--convention".into(),
                "unity".into(),
                "--out".into(),
                out("a.csv"),
            ],
            "URDF's world",
        ),
        (
            vec!["--robot".into(), toy.clone(), "--out".into(), out("a.csv")],
            "no retarget configuration for robot `toy_bot`: give --retarget FILE.json",
        ),
        (
            vec!["--robot".into(), cycle, "--out".into(), out("a.csv")],
            "cycle.urdf",
        ),
        (
            vec![
                "--robot".into(),
                toy.clone(),
                "--retarget".into(),
                bad_config,
                "--out".into(),
                out("a.csv"),
            ],
            "no_such_body",
        ),
        (
            vec![
                "--robot".into(),
                out("missing.urdf"),
                "--out".into(),
                out("a.csv"),
            ],
            "missing.urdf",
        ),
    ];
    for (extra, want) in cases {
        let mut args = vec![
            "generate".to_string(),
            "--model".into(),
            m.clone(),
            "--prompt".into(),
            "walk".into(),
        ];
        args.extend(extra);
        let argv: Vec<&str> = args.iter().map(String::as_str).collect();
        // From the scratch folder: no robots/ there, so the lookup reaches its later places.
        let o = flame_in(&dir, &argv);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {e}");
        assert!(e.contains(want), "{args:?}: want {want:?} in {e}");
        assert!(!e.contains("loaded"), "{args:?}: the model was loaded: {e}");
        assert!(!e.contains("panicked"), "{e}");
    }
    let o = flame_in(
        &dir,
        &[
            "generate",
            "--prompt",
            "walk",
            "--robot-format",
            "csv",
            "--out",
            "a.csv",
        ],
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("expected beyondmimic, gmr or qpos"));
    std::fs::remove_dir_all(&dir).unwrap();
}
