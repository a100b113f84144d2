//! `flame::motion::skating` against `tools/skating_ratio.py`, two independent implementations of
//! GMD's / OmniControl's `calculate_skating_ratio` (data_loaders/humanml/utils/metrics.py in
//! korrawe/guided-motion-diffusion and neu-vi/OmniControl): synthetic motions written as .npy,
//! measured by both, the ratios equal within 1e-9.
//!
//! Python: `$FLAME_TEST_PYTHON`, else target/test-venv/bin/python (made by tools/check.sh with
//! NumPy). Without either the test skips and says so in target/tmp/skipped-tests.log.

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;

use flame::motion::skating::{self, LEFT_TOE, RIGHT_TOE};

const TEST: &str = "skating_numpy::rust_and_numpy_agree_on_synthetic_motions";

/// A named motion: `[frames, joints, 3]` positions, Y up, metres.
struct Motion {
    name: &'static str,
    frames: usize,
    joints: usize,
    positions: Vec<[f64; 3]>,
}

/// Deterministic pseudo-random numbers in [0, 1) (64-bit LCG, Knuth's MMIX constants).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Every joint at a standing pelvis height except the toes, which `toe(t, side)` places.
fn motion(
    name: &'static str,
    frames: usize,
    joints: usize,
    mut toe: impl FnMut(usize, usize) -> [f64; 3],
) -> Motion {
    let mut positions = vec![[0.0, 0.9, 0.0]; frames * joints];
    for t in 0..frames {
        for (side, j) in [LEFT_TOE, RIGHT_TOE].into_iter().enumerate() {
            positions[t * joints + j] = toe(t, side);
        }
    }
    // Stored as float32 in the file: round here so both sides read the same numbers.
    for p in &mut positions {
        *p = p.map(|v| v as f32 as f64);
    }
    Motion {
        name,
        frames,
        joints,
        positions,
    }
}

fn motions() -> Vec<Motion> {
    let fps = 20.0;
    let mut rng = Lcg(7);
    let mut noise = Lcg(11);
    vec![
        // Grounded left toe at 1 m/s: every step skates.
        motion("slide_1ms", 11, 22, |t, side| {
            [if side == 0 { t as f64 / fps } else { 0.3 }, 0.0, 0.0]
        }),
        // 0.7 m/s: the zero-padded window mean is 0.42 at the edge steps, so they do not skate.
        motion("edge_0p7", 11, 22, |t, side| {
            [
                0.0,
                0.01,
                if side == 1 { 0.7 * t as f64 / fps } else { 0.0 },
            ]
        }),
        // Up 10 cm in frames 0..=4, then down, sliding: contact needs the frame before.
        motion("landing", 11, 24, |t, _| {
            [t as f64 / fps, if t < 5 { 0.1 } else { 0.0 }, 0.0]
        }),
        // The shortest motion: one step (3 m/s, window mean 0.6: skates).
        motion("two_frames", 2, 22, |t, _| [0.15 * t as f64, 0.02, 0.0]),
        // A gait: each toe swings up to 8 cm half the time and slides in stance with a speed
        // that drifts between 0 and ~1.5 m/s, plus jitter; heights cross 5 cm often.
        motion("gait", 120, 24, {
            let mut x = [0.0, 0.15];
            move |t, side| {
                let phase = t as f64 / 12.0 * std::f64::consts::TAU + side as f64 * 3.1;
                let swing = phase.sin().max(0.0);
                let slide = 0.75 * (1.0 + (t as f64 / 17.0 + side as f64).sin());
                x[side] += (slide + 2.0 * swing) / fps + 0.01 * (rng.next() - 0.5);
                let y = 0.08 * swing + 0.03 * rng.next() - 0.005;
                [x[side], y, 0.05 * (t as f64 / 9.0).cos()]
            }
        }),
        // A random walk with heights in [-2, 8) cm and steps up to ~3.5 cm per axis.
        motion("noise", 60, 22, {
            let mut p = [[0.0; 3]; 2];
            move |_, side| {
                p[side][0] += 0.07 * (noise.next() - 0.5);
                p[side][2] += 0.07 * (noise.next() - 0.5);
                p[side][1] = 0.1 * noise.next() - 0.02;
                p[side]
            }
        }),
    ]
}

/// Python with NumPy: `$FLAME_TEST_PYTHON`, else tools/check.sh's virtual environment.
fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FLAME_TEST_PYTHON") {
        return Some(p.into());
    }
    let venv = common::repo("target/test-venv/bin/python");
    venv.is_file().then_some(venv)
}

/// Runs the NumPy tool on `files` and returns its JSON.
fn numpy_ratios(python: &Path, files: &[PathBuf], fps: f64) -> serde_json::Value {
    let out = Command::new(python)
        .arg(common::repo("tools/skating_ratio.py"))
        .args(files)
        .args(["--fps", &fps.to_string(), "--json"])
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "tools/skating_ratio.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("tools/skating_ratio.py --json prints JSON")
}

/// Which of the 8 combinations of (contact, speed > 0.5, window mean > 0.5) the motions reach,
/// as a bit set, so the cross-check is known to exercise every branch of the rule.
fn branches(m: &Motion, fps: f64) -> u8 {
    let mut seen = 0u8;
    let steps = m.frames - 1;
    for toe in [LEFT_TOE, RIGHT_TOE] {
        let at = |t: usize| m.positions[t * m.joints + toe];
        let speed: Vec<f64> = (0..steps)
            .map(|t| (at(t + 1)[0] - at(t)[0]).hypot(at(t + 1)[2] - at(t)[2]) * fps)
            .collect();
        for t in 0..steps {
            let sum: f64 = speed[t.saturating_sub(2)..(t + 3).min(steps)].iter().sum();
            let contact = at(t)[1] < 0.05 && at(t + 1)[1] < 0.05;
            let (fast, fast_mean) = (speed[t] > 0.5, sum / 5.0 > 0.5);
            let bits = (u8::from(contact) << 2) | (u8::from(fast) << 1) | u8::from(fast_mean);
            seen |= 1 << bits;
        }
    }
    seen
}

#[test]
fn rust_and_numpy_agree_on_synthetic_motions() {
    let Some(python) = python() else {
        common::skip(
            TEST,
            "no Python with NumPy (set FLAME_TEST_PYTHON or run tools/check.sh, which makes \
             target/test-venv)",
        );
        return;
    };
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("skating_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let motions = motions();
    let mut files = Vec::new();
    for m in &motions {
        let path = dir.join(format!("{}.npy", m.name));
        let data: Vec<f32> = m.positions.iter().flatten().map(|&v| v as f32).collect();
        flame::npy::write_f32(&path, &[m.frames, m.joints, 3], &data).unwrap();
        files.push(path);
    }

    let all = motions.iter().fold(0u8, |s, m| s | branches(m, 20.0));
    assert_eq!(all, 0xff, "the motions miss a branch: {all:08b}");

    for fps in [20.0, 30.0] {
        let json = numpy_ratios(&python, &files, fps);
        let rows = json["files"].as_array().unwrap();
        assert_eq!(rows.len(), motions.len());
        let mut ratios = Vec::new();
        for (m, row) in motions.iter().zip(rows) {
            let rust = skating::skating_ratio(&m.positions, m.frames, m.joints, fps).unwrap();
            let numpy = row["ratio"].as_f64().unwrap();
            println!("{} @ {fps} fps: rust {rust:.6}, numpy {numpy:.6}", m.name);
            assert!(
                (rust - numpy).abs() <= 1e-9,
                "{} at {fps} fps: rust {rust}, numpy {numpy}",
                m.name
            );
            let lowest = (0..m.frames)
                .flat_map(|t| [LEFT_TOE, RIGHT_TOE].map(|j| m.positions[t * m.joints + j][1]))
                .fold(f64::INFINITY, f64::min);
            assert_eq!(
                row["min_toe_height"].as_f64().unwrap(),
                lowest,
                "{}",
                m.name
            );
            assert_eq!(row["frames"].as_u64().unwrap() as usize, m.frames);
            ratios.push(rust);
        }
        let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
        assert!((json["mean_ratio"].as_f64().unwrap() - mean).abs() <= 1e-9);
        if fps == 20.0 {
            // The hand-derived values, so a shared misreading of the definition still shows.
            assert_eq!(&ratios[..4], &[1.0, 0.8, 0.5, 1.0]);
            // The random motions are neither all nor nothing.
            assert!(ratios[4] > 0.05 && ratios[4] < 0.95, "gait {}", ratios[4]);
            assert!(ratios[5] > 0.05 && ratios[5] < 0.95, "noise {}", ratios[5]);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
