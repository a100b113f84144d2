//! A minute of continuous motion on the demo model: a `flame::stream::Stream` over a timeline of
//! eight segments (8 × 150 frames = 60 s at 20 fps, eight families of held-out prompts), three
//! seeds. Shown:
//!
//! - no seam where the joint velocity jumps more than the largest frame-to-frame velocity change
//!   inside the chunks (on joint positions: `|v(t+1) − v(t)|`, the worst joint, at the seam
//!   frames against every other frame);
//! - the root path continuous: no root step at a seam longer than the longest inside a chunk;
//! - each segment classified as its prompt's family by `flame_demo::classify` at the rate single
//!   clips of the same prompts and seeds reach (at most one segment fewer over the 24).
//!
//! Prints the measurements (`cargo test -p flame-demo --test demo_stream -- --nocapture`).
//! Skipped without the demo model unless FLAME_REQUIRE_REAL_WEIGHTS=1 (see tests/common).

use std::sync::Arc;

#[path = "../../../tests/common/mod.rs"]
mod common;

use common::demo_model;
use flame::models::Model;
use flame::motion::{Convention, Poses};
use flame::session::{Session, SessionParams};
use flame::stream::{Segment, Stream, StreamParams};
use flame_demo::{classify, Family};

const SEGMENT_FRAMES: usize = 150;
const SEEDS: [u64; 3] = [0, 1, 2];
const CHUNK: usize = 120;
const OVERLAP: usize = 20;

/// Eight held-out prompts of eight families (tests/fixtures/demo_eval_prompts.tsv wording).
const TIMELINE: [(Family, &str); 8] = [
    (
        Family::Walk,
        "a man takes a relaxed walk straight in front of him",
    ),
    (Family::Wave, "a person waves hi with the right hand"),
    (Family::Jump, "the person jumps up high one time"),
    (Family::Run, "somebody jogs forward at a comfortable pace"),
    (Family::Squat, "a person doing squat exercises"),
    (Family::Clap, "somebody claps hands happily several times"),
    (
        Family::Punch,
        "a man throwing left and right punches in the air",
    ),
    (Family::Bow, "a person bows politely to someone"),
];

/// The CLI's pose defaults for smpl24_6d: σ = 1 smoothing, continuous rotations.
fn positions(model: &Model, x: &[f32], frames: usize) -> Vec<[f64; 3]> {
    Poses::decode(
        model.motion_format(),
        x,
        frames,
        &model.read_options(1.0, true),
    )
    .unwrap()
    .positions(Convention::Native)
}

fn sub(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm(v: &[f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[test]
fn a_minute_of_eight_prompts_has_continuous_seams_and_recognisable_segments() {
    let Some(path) = demo_model() else {
        common::skip(
            "demo_stream::a_minute_of_eight_prompts_has_continuous_seams_and_recognisable_segments",
            "no demo model (set FLAME_MINILM_DIR or run tools/try.sh to assemble it)",
        );
        return;
    };
    let model = Arc::new(Model::load(&path).unwrap());
    let fps = model.config().motion.fps as f64;
    let total = SEGMENT_FRAMES * TIMELINE.len();
    let (mut stream_ok, mut single_ok) = (0, 0);
    let (mut worst_seam, mut worst_inside) = (0.0f64, 0.0f64);
    let (mut worst_seam_step, mut worst_inside_step) = (0.0f64, 0.0f64);
    for seed in SEEDS {
        let params = StreamParams {
            chunk: CHUNK,
            overlap: OVERLAP,
            lookahead: total,
            window: total,
            session: SessionParams {
                seed,
                threads: 2,
                ..SessionParams::default()
            },
        };
        let mut s = Stream::new(Arc::clone(&model), &params).unwrap();
        for (_, prompt) in TIMELINE {
            s.push(Segment::new(prompt, SEGMENT_FRAMES)).unwrap();
        }
        // Chunk starts, in timeline frames, as the stream plans them: every segment in chunks
        // of CHUNK − OVERLAP new frames (the very first CHUNK).
        let mut seams = Vec::new();
        while s.pump(usize::MAX).unwrap().steps > 0 {}
        assert_eq!(s.ready(), total);
        let mut at = 0;
        for k in 0..TIMELINE.len() {
            let end = (k + 1) * SEGMENT_FRAMES;
            while at < end {
                if at > 0 {
                    seams.push(at);
                }
                at += if at == 0 { CHUNK } else { CHUNK - OVERLAP }.min(end - at);
            }
        }
        let x = s.features(0, total).unwrap().to_vec();
        let p = positions(&model, &x, total);
        let joints = p.len() / total;
        // Velocity change at frame t: |v(t) − v(t−1)|, v(t) = p(t+1) − p(t), worst joint.
        let change = |t: usize| {
            (0..joints)
                .map(|j| {
                    let v1 = sub(&p[(t + 1) * joints + j], &p[t * joints + j]);
                    let v0 = sub(&p[t * joints + j], &p[(t - 1) * joints + j]);
                    norm(&sub(&v1, &v0))
                })
                .fold(0.0, f64::max)
        };
        let root_step = |t: usize| norm(&sub(&p[(t + 1) * joints], &p[t * joints]));
        // A seam touches the changes at the last kept frame and the first new one.
        let near_seam = |t: usize| seams.iter().any(|&s| t + 1 >= s && t <= s);
        for t in 1..total - 1 {
            if near_seam(t) {
                worst_seam = worst_seam.max(change(t));
                worst_seam_step = worst_seam_step.max(root_step(t));
            } else {
                worst_inside = worst_inside.max(change(t));
                worst_inside_step = worst_inside_step.max(root_step(t));
            }
        }
        // Each segment labelled, and the same prompt as a single clip at the model's defaults.
        for (k, (family, prompt)) in TIMELINE.iter().enumerate() {
            let seg = &p[k * SEGMENT_FRAMES * joints..(k + 1) * SEGMENT_FRAMES * joints];
            let got = classify::classify(seg, SEGMENT_FRAMES, fps);
            stream_ok += (got == *family) as usize;
            let mut single = Session::new(
                Arc::clone(&model),
                &SessionParams {
                    seed,
                    threads: 2,
                    ..SessionParams::default()
                },
            )
            .unwrap();
            single.set_prompt(prompt).unwrap();
            let frames = single.frames();
            let y = single.run().unwrap().to_vec();
            let q = positions(&model, &y, frames);
            single_ok += (classify::classify(&q, frames, fps) == *family) as usize;
            println!(
                "seed {seed} segment {k} {:>6}: stream {:>6}",
                family.name(),
                got.name()
            );
        }
    }
    let n = SEEDS.len() * TIMELINE.len();
    println!(
        "60 s timeline x {} seeds: worst velocity change at seams {:.4} m/frame, inside chunks \
         {:.4}; worst root step at seams {:.4} m, inside {:.4}; segments classified {stream_ok} \
         of {n}, single clips {single_ok} of {n}",
        SEEDS.len(),
        worst_seam,
        worst_inside,
        worst_seam_step,
        worst_inside_step
    );
    assert!(worst_seam <= worst_inside, "{worst_seam} > {worst_inside}");
    assert!(
        worst_seam_step <= worst_inside_step,
        "{worst_seam_step} > {worst_inside_step}"
    );
    assert!(stream_ok + 1 >= single_ok, "{stream_ok} vs {single_ok}");
}
