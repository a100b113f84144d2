//! `flame-bench retarget --rig FILE [--rig FILE ...] [--frames 200] [--runs 7]`: the cost of
//! carrying one libflame frame onto a user's rig ([`flame::retarget::Target::pose`]: the
//! rest-relative transfer, forward kinematics and the feet's two-bone IK), in microseconds per
//! frame, with and without the IK, and for comparison the cost of decoding the same frame's
//! poses from features. Medians over the runs; one `RESULT` line per rig.

use std::time::Instant;

use flame::motion::{Convention, Format, Poses, ReadOptions, Skeleton};
use flame::retarget::{bvh_rig, gltf_rig, Options, RigPose, Target};

use super::arg;

/// A smooth synthetic smpl24_6d clip: every feature its own sinusoid, the root drifting.
fn clip(frames: usize) -> Poses {
    let dim = Format::Smpl24Rot6d.feature_dim();
    let x: Vec<f32> = (0..frames * dim)
        .map(|i| {
            let (t, c) = ((i / dim) as f32, (i % dim) as f32);
            (0.3 * c + 0.05 * t * (1.0 + c % 3.0)).sin() * 0.8
                + if c % 6.0 == 0.0 { 0.5 } else { 0.0 }
        })
        .collect();
    Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default())
        .expect("a synthetic clip decodes")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn retarget_bench(args: &[String]) {
    let frames: usize = arg(args, "--frames", 200);
    let runs: usize = arg(args, "--runs", 7);
    let rigs: Vec<&String> = args
        .windows(2)
        .filter(|w| w[0] == "--rig")
        .map(|w| &w[1])
        .collect();
    if rigs.is_empty() {
        eprintln!(
            "usage: flame-bench retarget --rig FILE [--rig FILE ...] [--frames 200] [--runs 7]"
        );
        std::process::exit(2);
    }
    let poses = clip(frames);
    let world = poses.global_rotations(Convention::Gltf);
    let pos = poses.positions(Convention::Gltf);
    let root = poses.root_translation(Convention::Gltf);
    let j = poses.joint_count();
    for path in rigs {
        let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {path}: {e}"));
        let rig = if path.ends_with(".bvh") {
            bvh_rig::read(std::str::from_utf8(&bytes).expect("UTF-8"), None)
        } else {
            gltf_rig::read(&bytes, None)
        }
        .unwrap_or_else(|e| panic!("cannot read {path}: {e}"));
        let bones = rig.bone_count();
        let target = Target::auto(Skeleton::smpl24(), rig)
            .unwrap_or_else(|e| panic!("cannot retarget onto {path}: {e}"));
        let mut out = RigPose::new(&target);
        let mut time = |options: &Options| {
            let t = Instant::now();
            for f in 0..frames {
                target
                    .pose(
                        &world[f * j..(f + 1) * j],
                        &pos[f * j..(f + 1) * j],
                        &root[f],
                        options,
                        &mut out,
                    )
                    .expect("a frame retargets");
            }
            t.elapsed().as_secs_f64() * 1e6 / frames as f64
        };
        let (feet, plain) = (
            Options::default(),
            Options {
                feet: false,
                hands: false,
            },
        );
        let (mut with_ik, mut without) = (Vec::new(), Vec::new());
        // Interleaved so that a slow moment of the machine lands on both.
        time(&feet);
        for _ in 0..runs {
            with_ik.push(time(&feet));
            without.push(time(&plain));
        }
        let (a, b) = (median(with_ik), median(without));
        println!("{path}: {bones} bones, {frames} frames, {runs} runs");
        println!("  per frame: {a:.2} us with foot IK, {b:.2} us without");
        println!("RESULT retarget rig={path} bones={bones} us_per_frame={a:.3} us_per_frame_no_ik={b:.3}");
    }
}
