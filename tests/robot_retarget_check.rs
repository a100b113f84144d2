//! The robot retargeter checked by other people's kinematics (tests/robot_retarget_check.py):
//! the demo model's motions retargeted onto the real GR1T2 and JVRC-1 (PyPI
//! `fourier-robot-descriptions` 0.2.7, `jvrc-description` 1.1.1, fetched by
//! tools/fetch_robots.sh) with the shipped configurations robots/gr1t2.json and
//! robots/jvrc1.json, written as GMR's fields, and then in Python:
//!
//! - Pinocchio's forward kinematics of the written joint trajectories: hands and feet relative to
//!   the root body against the human joints the retargeter was given, scaled and offset as the
//!   configuration says (GMR's rules, made again in Python): median at most 5 cm;
//! - no joint outside Pinocchio's `lowerPositionLimit` / `upperPositionLimit` of the same URDF;
//! - the lowest collision point of every frame at most 1 cm below the floor: GR1T2's collision
//!   primitives through MuJoCo; JVRC-1's COLLADA collision meshes (which MuJoCo cannot read)
//!   through Pinocchio's geometry, from the meshes of the same `jvrc-description` wheel
//!   (downloaded once, hash-checked, into target/robots/jvrc1-package);
//! - while the human's foot is in contact (this frame and the previous), the robot's foot body
//!   moves less than 2 cm per frame horizontally.
//!
//! Without Python, its packages, the URDFs or the demo model the test skips and says so in
//! target/tmp/skipped-tests.log, or fails when FLAME_REQUIRE_REAL_WEIGHTS=1.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use flame::models::Model;
use flame::motion::contacts::{self, ContactParams};
use flame::motion::{Convention, Finish, Format, Poses, Skeleton};
use flame::npz::Npz;
use flame::robot::{RetargetConfig, Retargeter, Robot, Trajectory};
use flame::session::{Sampler, Session, SessionParams};

mod common;

const TEST: &str = "robot_retarget_check::pinocchio_and_mujoco_accept_the_retargeted_motions";

/// Prompts of the demo model's vocabulary: walking (contacts), arm motion (hands), turning.
const PROMPTS: [&str; 3] = [
    "a person walks forward and waves.",
    "a person walks in a circle",
    "a person waves",
];
/// Frames generated per prompt at the model's 20 fps (written at 30 fps).
const FRAMES: usize = 80;
/// The frame rate trackers read (BeyondMimic, PHC, GMR).
const FPS: f64 = 30.0;

/// Python with the test packages: `$FLAME_TEST_PYTHON`, else tools/check.sh's environment.
fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FLAME_TEST_PYTHON") {
        return Some(p.into());
    }
    let venv = common::repo("target/test-venv/bin/python");
    venv.is_file().then_some(venv)
}

/// Skips (or fails under FLAME_REQUIRE_REAL_WEIGHTS=1) naming what is missing.
fn missing(reason: &str) {
    assert!(
        !common::require_real_weights(),
        "FLAME_REQUIRE_REAL_WEIGHTS=1 but {reason}"
    );
    common::skip(TEST, reason);
}

fn real_urdf(name: &str) -> Option<PathBuf> {
    let path = common::repo(&format!("target/robots/{name}.urdf"));
    if !path.is_file() {
        let _ = Command::new("bash")
            .arg(common::repo("tools/fetch_robots.sh"))
            .status();
    }
    path.is_file().then_some(path)
}

/// The demo model's poses for `prompt`, finished as `flame generate` does for a robot: contacts,
/// floor, feet locked, resampled to 30 fps.
fn demo_poses(model: &Arc<Model>, prompt: &str, seed: u64) -> Poses {
    let params = SessionParams {
        frames: Some(FRAMES),
        steps: Some(10),
        sampler: Some(Sampler::Ddim),
        seed,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt(prompt).unwrap();
    while s.step().unwrap() > 0 {}
    let x = s.sample().unwrap().to_vec();
    let format: Format = model.motion_format();
    let opts = flame::motion::ReadOptions {
        finish: Finish {
            fps: Some(FPS),
            ..Finish::game_ready()
        },
        ..model.read_options(1.0, true)
    };
    Poses::decode(format, &x, x.len() / format.feature_dim(), &opts).unwrap()
}

/// GMR's fields through the exporter `flame generate --robot ... --out x.npz` uses.
fn write_trajectory(traj: &Trajectory, path: &Path) {
    let bytes = flame::robot::export::gmr_npz(traj).expect("GMR's fields");
    std::fs::write(path, bytes).expect("write the trajectory");
}

/// The human frames as [`Retargeter::motion`] reads them (its module doc: libflame's joints in
/// [`Convention::Ros`], contacts by [`contacts::of`] with the default parameters), for Python to
/// scale by itself: joint names in SMPL-X's and in libflame's spelling, positions, world
/// rotations, the four contact slots.
fn write_human(poses: &Poses, fps: f64, path: &Path) {
    let (n, j) = (poses.frames(), poses.joint_count());
    let positions: Vec<f64> = poses
        .positions(Convention::Ros)
        .into_iter()
        .flatten()
        .collect();
    let rotations: Vec<f64> = poses
        .global_rotations(Convention::Ros)
        .into_iter()
        .flatten()
        .flatten()
        .collect();
    let contacts: Vec<f64> = contacts::of(poses, fps, &ContactParams::default())
        .into_iter()
        .flatten()
        .map(|c| if c { 1.0 } else { 0.0 })
        .collect();
    let smplx: Vec<&str> = Skeleton::humanml22()
        .joint_names()
        .iter()
        .copied()
        .chain(["left_hand", "right_hand"])
        .take(j)
        .collect();
    let smpl: Vec<&str> = Skeleton::smpl24().joint_names()[..j].to_vec();
    let mut npz = Npz::new();
    npz.add_strs("joint_names", &smplx).unwrap();
    npz.add_strs("joint_names_smpl", &smpl).unwrap();
    npz.add_f64("positions", &[n, j, 3], &positions).unwrap();
    npz.add_f64("rotations", &[n, j, 3, 3], &rotations).unwrap();
    npz.add_f64("contacts", &[n, 4], &contacts).unwrap();
    std::fs::write(path, npz.finish()).expect("write the human frames");
}

fn f(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("no number `{key}` in {v}"))
}

#[test]
fn pinocchio_and_mujoco_accept_the_retargeted_motions() {
    let Some(python) = python() else {
        return missing(
            "no Python with Pinocchio and MuJoCo (set FLAME_TEST_PYTHON or run tools/check.sh, \
             which makes target/test-venv from tools/test-requirements.txt)",
        );
    };
    let Some(model_path) = common::demo_model() else {
        return missing(
            "no demo model (tools/try.sh assembles models/demo/flame_demo.safetensors)",
        );
    };
    let model = Arc::new(Model::load(&model_path).unwrap());
    let motions: Vec<(&str, Poses)> = PROMPTS
        .iter()
        .enumerate()
        .map(|(i, p)| (*p, demo_poses(&model, p, i as u64)))
        .collect();

    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("robot_retarget_check_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Human joint index -> column of the human file's contacts.
    let slots: serde_json::Map<String, serde_json::Value> = contacts::SLOT_JOINTS
        .iter()
        .enumerate()
        .map(|(column, joint)| (joint.to_string(), column.into()))
        .collect();
    let mut request = Vec::new();
    for (name, floor) in [("gr1t2", "mujoco"), ("jvrc1", "pinocchio-meshes")] {
        let Some(urdf) = real_urdf(name) else {
            return missing(&format!(
                "target/robots/{name}.urdf is missing and tools/fetch_robots.sh could not fetch \
                 it (offline?)"
            ));
        };
        let robot = Robot::from_urdf(&std::fs::read_to_string(&urdf).unwrap()).unwrap();
        let config_path = common::repo(&format!("robots/{name}.json"));
        let config =
            RetargetConfig::from_json(&std::fs::read_to_string(&config_path).unwrap(), &robot)
                .unwrap_or_else(|e| panic!("{}: {e}", config_path.display()));
        let retargeter = Retargeter::new(robot, config).unwrap();
        let mut cases = Vec::new();
        for (i, (prompt, poses)) in motions.iter().enumerate() {
            let traj = retargeter.motion(poses, FPS).unwrap();
            traj.validate().unwrap();
            assert_eq!(traj.frames(), poses.frames(), "{name} {prompt}");
            let (t, h) = (
                dir.join(format!("{name}_{i}.trajectory.npz")),
                dir.join(format!("{name}_{i}.human.npz")),
            );
            write_trajectory(&traj, &t);
            write_human(poses, FPS, &h);
            cases.push(serde_json::json!({
                "name": prompt, "trajectory": t, "human": h,
                "contact_slots": slots,
            }));
        }
        let mut robot_request = serde_json::json!({
            "name": name, "urdf": urdf, "config": config_path, "floor": floor, "cases": cases,
        });
        if name == "jvrc1" {
            robot_request["mesh_package"] = serde_json::json!({
                "requirement": "jvrc-description==1.1.1",
                "sha256": "68f8bc88cdb9a221bc60ba2ec26a77560100cead738e8e2ce8e4599764526c5c",
                "dir": common::repo("target/robots/jvrc1-package"),
            });
        }
        request.push(robot_request);
    }
    let request_path = dir.join("request.json");
    std::fs::write(&request_path, serde_json::to_vec(&request).unwrap()).unwrap();
    let out = Command::new(&python)
        .arg(common::repo("tests/robot_retarget_check.py"))
        .arg(&request_path)
        .output()
        .expect("run python");
    match out.status.code() {
        Some(77) => {
            return missing(&format!(
                "{} lacks Pinocchio or MuJoCo: {}",
                python.display(),
                String::from_utf8_lossy(&out.stderr).trim()
            ))
        }
        Some(78) => {
            return missing(&format!(
                "JVRC-1's collision meshes could not be downloaded: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ))
        }
        _ => {}
    }
    assert!(
        out.status.success(),
        "tests/robot_retarget_check.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let answers: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();

    let mut failures = Vec::new();
    for robot in answers.as_array().unwrap() {
        let name = robot["name"].as_str().unwrap();
        for case in robot["cases"].as_array().unwrap() {
            let prompt = case["name"].as_str().unwrap();
            let (hands, feet) = (&case["hands"], &case["feet"]);
            let lowest = &case["lowest"];
            let sole = &case["sole_speed"];
            println!(
                "{name} `{prompt}` ({} frames, {} in contact): hands median {:.1} max {:.1} cm, \
                 feet median {:.1} max {:.1} cm; {} limit violations (worst {:.1e}); lowest \
                 point {:.1} cm (frame {}, floor by {}); sole speed in contact median {:.2} max \
                 {:.2} cm/frame over {} steps",
                case["frames"],
                case["contact_frames"],
                100.0 * f(hands, "median"),
                100.0 * f(hands, "max"),
                100.0 * f(feet, "median"),
                100.0 * f(feet, "max"),
                case["limit_violations"],
                f(case, "limit_worst_excess"),
                100.0 * f(lowest, "min"),
                lowest["frame"],
                robot["floor"].as_str().unwrap(),
                100.0 * sole["median"].as_f64().unwrap_or(0.0),
                100.0 * sole["max"].as_f64().unwrap_or(0.0),
                sole["count"],
            );
            let mut check = |ok: bool, what: String| {
                if !ok {
                    failures.push(format!("{name} `{prompt}`: {what}"));
                }
            };
            check(
                f(hands, "median") <= 0.05,
                format!("hands median {:.4} m > 0.05", f(hands, "median")),
            );
            check(
                f(feet, "median") <= 0.05,
                format!("feet median {:.4} m > 0.05", f(feet, "median")),
            );
            check(
                case["limit_violations"].as_u64() == Some(0),
                format!("{} joint-limit violations", case["limit_violations"]),
            );
            check(
                f(lowest, "min") >= -0.01,
                format!(
                    "lowest collision point {:.4} m below the floor",
                    f(lowest, "min")
                ),
            );
            if let Some(max) = sole["max"].as_f64() {
                check(
                    max < 0.02,
                    format!("sole slides {max:.4} m in a contact frame"),
                );
            }
        }
        // Hands and feet were compared at all, and contacts were there to hold.
        let counted: u64 = robot["cases"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["sole_speed"]["count"].as_u64().unwrap())
            .sum();
        assert!(counted > 0, "{name}: no contact frames in any motion");
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
