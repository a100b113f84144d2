//! `flame-bench robot-retarget --urdf FILE --config FILE --model M [--frames 120] [--dir D]
//! [--runs 1]`: frames per second of retargeting the demo model's motions onto a robot
//! ([`flame::robot::Retargeter::motion`], one thread), the side of libflame in
//! tools/robot_bench.py, which runs mink on the same motions between these runs.
//!
//! The motions (`--frames` frames each at the model's rate, finished as `flame generate` does
//! for a robot: contacts, floor, feet locked, 30 fps) are generated once and kept in `--dir` as
//! the model's features (`motion_<i>.npy`), so later runs time the same motions without
//! generating them again. After timing, each motion's human frames as the retargeter reads
//! them (`motion_<i>.human.npz`: joint_names, positions [N, J, 3], rotations [N, J, 3, 3],
//! contacts [N, 2]) and its trajectory (`motion_<i>.trajectory.npz`, GMR's fields) are written
//! for the comparison. Prints one `MOTION=` line per motion and one `RESULT` line.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use flame::models::Model;
use flame::motion::contacts::{self, ContactParams};
use flame::motion::{Convention, Finish, Poses, ReadOptions, Skeleton};
use flame::npz::Npz;
use flame::robot::{RetargetConfig, Retargeter, Robot, Trajectory};
use flame::session::{Sampler, Session, SessionParams};

use super::arg;

/// Walking (contacts), arm motion, turning, a jump: the demo model's vocabulary.
const PROMPTS: [&str; 4] = [
    "a person walks forward and waves.",
    "a person walks in a circle",
    "a person waves",
    "a person jumps",
];
const FPS: f64 = 30.0;

fn features(model: &Arc<Model>, prompt: &str, frames: usize, seed: u64, path: &Path) -> Vec<f32> {
    let dim = model.motion_format().feature_dim();
    if let Ok((shape, x)) = flame::npy::read_f32(path) {
        if shape == [frames, dim] {
            return x;
        }
    }
    let params = SessionParams {
        frames: Some(frames),
        steps: Some(10),
        sampler: Some(Sampler::Ddim),
        seed,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(model), &params).expect("session");
    s.set_prompt(prompt).expect("prompt");
    while s.step().expect("step") > 0 {}
    let x = s.sample().expect("sample").to_vec();
    flame::npy::write_f32(path, &[frames, dim], &x).expect("write the motion");
    x
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

pub fn robot_retarget_bench(args: &[String]) {
    let urdf: String = arg(args, "--urdf", "target/robots/gr1t2.urdf".to_string());
    let config_path: String = arg(args, "--config", "robots/gr1t2.json".to_string());
    let model_path: String = arg(
        args,
        "--model",
        "models/demo/flame_demo.safetensors".to_string(),
    );
    let frames: usize = arg(args, "--frames", 120);
    let dir: PathBuf = arg(args, "--dir", "target/robot-bench".to_string()).into();
    let runs: usize = arg(args, "--runs", 1);
    std::fs::create_dir_all(&dir).expect("create --dir");

    let text = std::fs::read_to_string(&urdf).unwrap_or_else(|e| {
        panic!("cannot read {urdf}: {e} (bash tools/fetch_robots.sh fetches GR1T2 and JVRC-1)")
    });
    let robot = Robot::from_urdf(&text).unwrap_or_else(|e| panic!("{urdf}: {e}"));
    let config_text = std::fs::read_to_string(&config_path)
        .unwrap_or_else(|e| panic!("cannot read {config_path}: {e}"));
    let config = RetargetConfig::from_json(&config_text, &robot)
        .unwrap_or_else(|e| panic!("{config_path}: {e}"));
    let name = robot.name().to_string();
    let retargeter = Retargeter::new(robot, config).unwrap_or_else(|e| panic!("{e}"));

    let model = Arc::new(Model::load(Path::new(&model_path)).expect("load the model"));
    let format = model.motion_format();
    let opts = ReadOptions {
        finish: Finish {
            fps: Some(FPS),
            ..Finish::game_ready()
        },
        ..model.read_options(1.0, true)
    };
    let motions: Vec<Poses> = PROMPTS
        .iter()
        .enumerate()
        .map(|(i, prompt)| {
            let path = dir.join(format!("motion_{i}.npy"));
            let x = features(&model, prompt, frames, i as u64, &path);
            Poses::decode(format, &x, frames, &opts).expect("decode")
        })
        .collect();
    let total: usize = motions.iter().map(Poses::frames).sum();

    let mut fps = Vec::new();
    let mut last = Vec::new();
    for _ in 0..runs.max(1) {
        let t = Instant::now();
        last = motions
            .iter()
            .map(|p| retargeter.motion(p, FPS).expect("retarget"))
            .collect();
        fps.push(total as f64 / t.elapsed().as_secs_f64());
    }
    fps.sort_by(f64::total_cmp);
    let median = fps[fps.len() / 2];

    for (i, (poses, traj)) in motions.iter().zip(&last).enumerate() {
        let stem = dir.join(format!("motion_{i}"));
        write_human(poses, FPS, &stem.with_extension("human.npz"));
        write_trajectory(traj, &stem.with_extension("trajectory.npz"));
        println!("MOTION={}", stem.display());
    }
    let residual: Vec<f64> = last
        .iter()
        .flat_map(|t| t.residual.iter().copied())
        .collect();
    let mean_residual = residual.iter().sum::<f64>() / residual.len().max(1) as f64;
    println!(
        "{name}: {} motions, {total} frames at {FPS} fps, {median:.0} frames/s (median of {} \
         runs, one thread, scalar f64 code); mean residual {mean_residual:.4}",
        motions.len(),
        fps.len()
    );
    println!(
        "RESULT robot={name} frames={total} fps={median:.1} runs={} avx2_compiled={} \
         kernel={}",
        fps.len(),
        cfg!(target_feature = "avx2"),
        flame::kernels::kernel_name(),
    );
}
