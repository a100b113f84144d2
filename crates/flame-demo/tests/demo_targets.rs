//! Joint-position targets on the trained demo model (FLAME, smpl24_6d), at the model's defaults
//! (DDIM, 10 steps, 120 frames = 6 s at 20 fps) and the session's target defaults (scale 0.6,
//! constant schedule for this family; `DEMO_TARGET_SCALE` / `DEMO_TARGET_SCHEDULE` override
//! them): the guided motion follows what the targets ask where the unguided motion from the
//! same seed does not.
//!
//! - A pelvis path on the ground (x, y of the native Z-up frame; height free): 3 m straight,
//!   then a quarter circle of 1 m radius. Median distance to the path over the frames.
//! - The right wrist 25 cm above the head at one frame. Distance at that frame.
//!
//! Prints the numbers (`cargo test -p flame-demo --test demo_targets -- --nocapture`). The model
//! is found as in demo_eval.rs; skipped without it unless FLAME_REQUIRE_REAL_WEIGHTS=1.

use std::sync::Arc;

#[path = "../../../tests/common/mod.rs"]
mod common;

use common::{demo_model, skip};
use flame::models::Model;
use flame::motion::{Convention, Poses};
use flame::session::{Session, SessionParams, Which};
use flame::targets::{TargetParams, TargetSchedule};

const FRAMES: usize = 120;
const JOINTS: usize = 24;
const PELVIS: usize = 0;
const HEAD: usize = 15;
const RIGHT_WRIST: usize = 21;
const SEEDS: [u64; 3] = [0, 1, 2];

fn model() -> Option<Arc<Model>> {
    match demo_model() {
        Some(path) => Some(Arc::new(Model::load(path).unwrap())),
        None => {
            skip("demo_targets", "no demo model (set FLAME_MINILM_DIR)");
            None
        }
    }
}

/// Native joint positions `[frames × joints]` of a generation, guided by `targets` (values and
/// mask) when given.
fn generate(
    model: &Arc<Model>,
    prompt: &str,
    seed: u64,
    targets: Option<(&[f32], &[u8])>,
    params: Option<TargetParams>,
) -> Vec<[f64; 3]> {
    let p = SessionParams {
        seed,
        frames: Some(FRAMES),
        ..SessionParams::default()
    };
    let mut s = Session::new(Arc::clone(model), &p).unwrap();
    s.set_prompt(prompt).unwrap();
    if let Some((values, mask)) = targets {
        s.set_position_target_values(values, Some(mask), Convention::Native)
            .unwrap();
        if let Some(p) = params {
            s.set_target_params(&p).unwrap();
        }
    }
    s.run().unwrap();
    let (x, frames) = s.motion(Which::Sample).unwrap();
    Poses::decode(
        model.motion_format(),
        x,
        frames,
        &model.read_options(0.0, true),
    )
    .unwrap()
    .positions(Convention::Native)
}

/// The path point at frame `f` from `start`: 3 m along +x over the first 80 frames, then a
/// quarter circle of radius 1 m turning toward +y over the last 40.
fn path_point(start: [f64; 2], f: usize) -> [f64; 2] {
    if f <= 80 {
        [start[0] + 3.0 * f as f64 / 80.0, start[1]]
    } else {
        let a = std::f64::consts::FRAC_PI_2 * (f - 80) as f64 / 40.0;
        [start[0] + 3.0 + a.sin(), start[1] + 1.0 - a.cos()]
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn params_from_env() -> Option<TargetParams> {
    let scale = std::env::var("DEMO_TARGET_SCALE").ok()?;
    let schedule = std::env::var("DEMO_TARGET_SCHEDULE").unwrap_or_else(|_| "constant".into());
    Some(TargetParams {
        scale: scale.parse().unwrap(),
        schedule: schedule.parse::<TargetSchedule>().unwrap(),
    })
}

#[test]
fn the_pelvis_follows_a_path_on_the_ground() {
    let Some(model) = model() else { return };
    let params = params_from_env();
    for seed in SEEDS {
        let prompt = "a person walks forward.";
        let unguided = generate(&model, prompt, seed, None, params);
        let p0 = unguided[PELVIS];
        let start = [p0[0], p0[1]];
        let mut values = vec![0.0f32; FRAMES * JOINTS * 3];
        let mut mask = vec![0u8; values.len()];
        for f in 0..FRAMES {
            let at = (f * JOINTS + PELVIS) * 3;
            let q = path_point(start, f);
            values[at] = q[0] as f32;
            values[at + 1] = q[1] as f32;
            mask[at] = 1;
            mask[at + 1] = 1;
        }
        let guided = generate(&model, prompt, seed, Some((&values, &mask)), params);
        let err = |p: &[[f64; 3]]| {
            median(
                (0..FRAMES)
                    .map(|f| distance(&p[f * JOINTS][..2], &path_point(start, f)))
                    .collect(),
            )
        };
        let (before, after) = (err(&unguided), err(&guided));
        println!(
            "seed {seed}: pelvis to path, median over {FRAMES} frames: unguided {before:.3} m, guided {after:.3} m"
        );
        assert!(
            after < 0.10,
            "seed {seed}: guided pelvis {after} m from the path"
        );
        assert!(
            before > 0.5,
            "seed {seed}: the unguided motion already follows the path"
        );
    }
}

#[test]
fn the_right_wrist_reaches_above_the_head() {
    let Some(model) = model() else { return };
    let params = params_from_env();
    let frame = 60;
    for seed in SEEDS {
        let prompt = "a person walks forward.";
        let unguided = generate(&model, prompt, seed, None, params);
        let head = unguided[frame * JOINTS + HEAD];
        let goal = [head[0], head[1], head[2] + 0.25];
        let mut values = vec![0.0f32; FRAMES * JOINTS * 3];
        let mut mask = vec![0u8; values.len()];
        let at = (frame * JOINTS + RIGHT_WRIST) * 3;
        for k in 0..3 {
            values[at + k] = goal[k] as f32;
            mask[at + k] = 1;
        }
        let guided = generate(&model, prompt, seed, Some((&values, &mask)), params);
        let (before, after) = (
            distance(&unguided[frame * JOINTS + RIGHT_WRIST], &goal),
            distance(&guided[frame * JOINTS + RIGHT_WRIST], &goal),
        );
        println!(
            "seed {seed}: right wrist to its target at frame {frame}: unguided {before:.3} m, guided {after:.3} m"
        );
        assert!(
            after < 0.10,
            "seed {seed}: guided wrist {after} m from its target"
        );
        assert!(
            before > 0.3,
            "seed {seed}: the unguided wrist is already there"
        );
    }
}
