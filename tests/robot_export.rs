//! `flame::robot::export` read back by the pipelines' own readers: BeyondMimic's CSV with
//! `np.loadtxt(file, delimiter=",")` (HybridRobotics/whole_body_tracking
//! `scripts/csv_to_npz.py`), GMR's fields with `np.load`, and MuJoCo's qpos rows fed verbatim
//! to MuJoCo (PyPI `mujoco`) compiling the same URDF: its bodies must land where libflame's
//! forward kinematics puts the links, which checks the joint order and the w-first quaternion.
//! Python: tests/robot_export_numpy.py, run by `$FLAME_TEST_PYTHON` or target/test-venv.
//!
//! Real robots: GR1T2 and JVRC-1 from target/robots (tools/fetch_robots.sh); without them, or
//! without Python, the tests skip and say so in target/tmp/skipped-tests.log (they fail instead
//! when FLAME_REQUIRE_REAL_WEIGHTS=1).

use std::path::{Path, PathBuf};
use std::process::Command;

use flame::robot::export::{self, RobotFile};
use flame::robot::{forward, Pose, Robot, RobotData, Trajectory};

mod common;

/// Python with NumPy: `$FLAME_TEST_PYTHON`, else tools/check.sh's virtual environment.
fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FLAME_TEST_PYTHON") {
        return Some(p.into());
    }
    let venv = common::repo("target/test-venv/bin/python");
    venv.is_file().then_some(venv)
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("robot_export_{name}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A small deterministic generator (xorshift64*), values in [0, 1).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

/// `frames` random configurations within the limits (±π for unlimited joints) and random base
/// poses (a unit quaternion with w of either sign).
fn random_trajectory(robot: &Robot, frames: usize, seed: u64) -> Trajectory {
    let mut rng = Rng(seed);
    let lim = robot.joint_limits();
    let n = robot.dof_count();
    let mut t = Trajectory {
        fps: 30.0,
        robot: robot.name().to_string(),
        dof_names: robot.dof_names().to_vec(),
        root_pos: Vec::new(),
        root_rot_xyzw: Vec::new(),
        dof_pos: Vec::new(),
        residual: vec![0.0; frames],
    };
    for _ in 0..frames {
        t.root_pos.push([
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(0.5, 1.2),
        ]);
        let q: [f64; 4] = std::array::from_fn(|_| rng.range(-1.0, 1.0));
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        t.root_rot_xyzw.push(q.map(|v| v / norm));
        for d in 0..n {
            let pi = std::f64::consts::PI;
            let (lo, hi) = (lim.lower[d].max(-pi), lim.upper[d].min(pi));
            t.dof_pos.push(rng.range(lo, hi));
        }
    }
    t
}

#[test]
fn pipelines_read_the_files_and_mujoco_places_the_qpos_as_libflame_does() {
    const TEST: &str =
        "robot_export::pipelines_read_the_files_and_mujoco_places_the_qpos_as_libflame_does";
    let Some(python) = python() else {
        common::skip(TEST, "no Python with NumPy (set FLAME_TEST_PYTHON)");
        return;
    };
    for name in ["gr1t2", "jvrc1"] {
        let Some((path, text)) = common::real_urdf(TEST, name) else {
            return;
        };
        let robot = Robot::from_urdf(&text).unwrap();
        let frames = 6;
        let traj = random_trajectory(&robot, frames, 0x5eed + name.len() as u64);
        let dir = scratch(name);
        for (file, header, out) in [
            (RobotFile::BeyondMimicCsv, false, "beyondmimic.csv"),
            (RobotFile::BeyondMimicCsv, true, "beyondmimic_header.csv"),
            (RobotFile::GmrNpz, false, "gmr.npz"),
            (RobotFile::QposCsv, true, "qpos.csv"),
            (RobotFile::QposNpy, false, "qpos.npy"),
        ] {
            let bytes = export::to_bytes(&traj, &robot, file, header).unwrap();
            std::fs::write(dir.join(out), bytes).unwrap();
        }
        // Every link's world position by libflame's forward kinematics, and the links' names.
        let mut data = RobotData::new(&robot);
        let mut links = Vec::new();
        for t in 0..frames {
            let base = Pose::from_position_quat_xyzw(traj.root_pos[t], traj.root_rot_xyzw[t]);
            forward(&robot, &base, traj.dof_row(t), &mut data).unwrap();
            for l in 0..robot.links().len() {
                links.extend(data.link_pose(l).translation);
            }
        }
        let n_links = robot.links().len();
        let npy = flame::npy::encode_f64(&[frames, n_links, 3], &links).unwrap();
        std::fs::write(dir.join("links.npy"), npy).unwrap();
        let names: Vec<&str> = robot.links().iter().map(|l| l.name.as_str()).collect();
        std::fs::write(dir.join("links.txt"), names.join("\n")).unwrap();
        let out = Command::new(&python)
            .arg(common::repo("tests/robot_export_numpy.py"))
            .arg(&dir)
            .arg(&path)
            .output()
            .expect("run python");
        let stdout = String::from_utf8_lossy(&out.stdout);
        println!("{name}: {stdout}{}", String::from_utf8_lossy(&out.stderr));
        assert!(
            out.status.success(),
            "tests/robot_export_numpy.py failed on {name}"
        );
        assert!(stdout.contains("mujoco body max error"), "{stdout}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
