//! `flame::stream`: continuous motion from a timeline of prompts, on the random-weight fixtures
//! (FLAME's absolute smpl24_6d and MDM's relative humanml263) and, where assembled, the demo
//! model: determinism under any pump pattern and thread count, the kept overlap and the root
//! path continuing across seams, the window and its anchoring, interrupts, and bad input.

use std::sync::atomic::Ordering;
use std::sync::Arc;

mod common;

use common::{demo_model, repo};
use flame::models::Model;
use flame::motion::{Convention, Layout};
use flame::session::{Sampler, SessionParams};
use flame::stages::BodyPart;
use flame::stream::{Segment, Stream, StreamParams};

fn model(name: &str) -> Arc<Model> {
    Arc::new(Model::load(repo(&format!("tests/fixtures/{name}.safetensors"))).unwrap())
}

fn params(threads: usize) -> StreamParams {
    StreamParams {
        chunk: 40,
        overlap: 10,
        lookahead: 1000,
        window: 10_000,
        session: SessionParams {
            steps: Some(3),
            sampler: Some(Sampler::Ddim),
            seed: 5,
            threads,
            ..Default::default()
        },
    }
}

fn timeline(s: &mut Stream) {
    s.push(Segment::new("a person walks forward.", 50)).unwrap();
    s.push(Segment::new("a person waves.", 25)).unwrap();
    s.push(Segment::new("a person sits down.", 40)).unwrap();
}

/// Pumps `s` `per_call` steps at a time until it stops making progress.
fn run(s: &mut Stream, per_call: usize) -> usize {
    let mut calls = 0;
    loop {
        let r = s.pump(per_call).unwrap();
        calls += 1;
        if r.steps == 0 {
            return calls;
        }
    }
}

#[test]
fn the_same_timeline_gives_the_same_bits_whatever_the_pump_pattern_and_threads() {
    // Every family that keeps frames: diffusion (DDIM) and flow matching (Euler).
    for name in [
        "flame_tiny",
        "mdm_tiny",
        "motionfm_tiny",
        "omg_tiny",
        "finemogen_tiny",
    ] {
        let m = model(name);
        let params = |threads| {
            let mut p = params(threads);
            if name == "motionfm_tiny" {
                p.session.sampler = Some(Sampler::Euler);
            }
            p
        };
        let mut a = Stream::new(Arc::clone(&m), &params(1)).unwrap();
        timeline(&mut a);
        let calls = run(&mut a, 1);
        let mut b = Stream::new(Arc::clone(&m), &params(2)).unwrap();
        timeline(&mut b);
        run(&mut b, usize::MAX);
        assert_eq!(a.ready(), 115, "{name}");
        assert_eq!(b.ready(), 115, "{name}");
        // 50 = 40 + 10 new, 25 = 25, 40 = 30 + 10: five chunks of 3 steps.
        assert_eq!(calls, 16, "{name}");
        let (fa, fb) = (a.features(0, 115).unwrap(), b.features(0, 115).unwrap());
        assert!(
            fa.iter().zip(fb).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{name}"
        );
    }
}

/// Kept frames are the previous chunk's, exactly: the first `overlap` frames of every chunk
/// after the first are not regenerated, so what the stream emitted stays as it was when the
/// next chunk is appended.
#[test]
fn emitted_frames_do_not_change_when_the_next_chunk_lands() {
    for name in ["flame_tiny", "mdm_tiny"] {
        let m = model(name);
        let mut s = Stream::new(m, &params(1)).unwrap();
        s.push(Segment::new("a person walks forward.", 100))
            .unwrap();
        s.pump(3).unwrap();
        assert_eq!(s.ready(), 40);
        let before = s
            .read(0, 40, Layout::GlobalPositions, Convention::Gltf)
            .unwrap();
        s.pump(3).unwrap();
        assert_eq!(s.ready(), 70);
        let after = s
            .read(0, 40, Layout::GlobalPositions, Convention::Gltf)
            .unwrap();
        let worst = before
            .iter()
            .zip(&after)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "{name}: {worst}");
    }
}

/// Dropping frames behind the playhead re-anchors relative formats: the frames still held read
/// the same as in a stream that dropped nothing.
#[test]
fn the_window_drops_old_frames_and_keeps_the_rest_in_place() {
    for name in ["flame_tiny", "mdm_tiny"] {
        let m = model(name);
        let mut full = Stream::new(Arc::clone(&m), &params(1)).unwrap();
        timeline(&mut full);
        run(&mut full, usize::MAX);
        let mut p = params(1);
        p.window = 20;
        let mut short = Stream::new(m, &p).unwrap();
        timeline(&mut short);
        run(&mut short, usize::MAX);
        short.set_playhead(90).unwrap();
        assert_eq!(short.first_frame(), 70);
        let e = short
            .read(60, 10, Layout::RootTranslation, Convention::Native)
            .unwrap_err();
        assert!(e.to_string().contains("were dropped"), "{e}");
        let a = full
            .read(70, 45, Layout::GlobalPositions, Convention::Unity)
            .unwrap();
        let b = short
            .read(70, 45, Layout::GlobalPositions, Convention::Unity)
            .unwrap();
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{name}: {worst} m");
        let q_full = full
            .read(70, 45, Layout::GlobalQuatXyzw, Convention::Unity)
            .unwrap();
        let q_short = short
            .read(70, 45, Layout::GlobalQuatXyzw, Convention::Unity)
            .unwrap();
        // The same rotations; signs may differ (each read makes its tracks sign-continuous from
        // its own first frame).
        let worst = q_full
            .chunks_exact(4)
            .zip(q_short.chunks_exact(4))
            .map(|(x, y)| {
                let diff = |sign: f32| {
                    x.iter()
                        .zip(y)
                        .map(|(a, b)| (a - sign * b).abs())
                        .fold(0.0f32, f32::max)
                };
                diff(1.0).min(diff(-1.0))
            })
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{name}: quaternions {worst}");
    }
}

#[test]
fn interrupt_ends_the_segment_at_the_chunk_boundary() {
    let m = model("mdm_tiny");
    let mut s = Stream::new(m, &params(1)).unwrap();
    s.push(Segment::new("a person walks forward.", 200))
        .unwrap();
    s.push(Segment::new("a person jumps.", 50)).unwrap();
    s.pump(4).unwrap(); // chunk 1 done (40 frames), chunk 2 (30 new) one step in
    assert_eq!(s.ready(), 40);
    s.interrupt(Segment::new("a person sits down.", 20))
        .unwrap();
    run(&mut s, usize::MAX);
    // The walk ends with the chunk in flight (40 + 30), the jump is dropped, the sit follows.
    assert_eq!(s.ready(), 90);
}

#[test]
fn the_lookahead_bounds_the_work_and_an_empty_timeline_starves() {
    let m = model("flame_tiny");
    let mut p = params(1);
    p.lookahead = 45;
    let mut s = Stream::new(m, &p).unwrap();
    let r = s.pump(100).unwrap();
    assert_eq!((r.steps, r.ready, r.starving), (0, 0, true));
    s.push(Segment::new("a person walks forward.", 500))
        .unwrap();
    let r = s.pump(100).unwrap();
    // Two chunks reach 70 >= 45 frames; then it waits for the playhead.
    assert_eq!((r.steps, r.ready, r.starving), (6, 70, false));
    assert_eq!(s.pump(100).unwrap().steps, 0);
    s.set_playhead(30).unwrap();
    assert_eq!(s.pump(100).unwrap().ready, 100);
}

#[test]
fn bad_input_is_a_clear_error() {
    let m = model("flame_tiny");
    let mut s = Stream::new(Arc::clone(&m), &params(1)).unwrap();
    let e = s.push(Segment::new("a person walks.", 0)).unwrap_err();
    assert!(e.to_string().contains("at least one frame"), "{e}");
    s.push(Segment::new("a person walks.", 30)).unwrap();
    s.pump(1).unwrap();
    let e = s
        .read(0, 10, Layout::RootTranslation, Convention::Native)
        .unwrap_err();
    assert!(matches!(e, flame::Error::WrongState(_)), "{e}");
    assert!(e.to_string().contains("not generated yet"), "{e}");
    assert!(s
        .read(usize::MAX, 2, Layout::RootTranslation, Convention::Native)
        .is_err());
    let e = s.set_playhead(31).unwrap_err();
    assert!(e.to_string().contains("past the"), "{e}");
    // An empty range is empty in every layout and convention, before any frame is ready and
    // after; so are poses and features.
    let fresh = Stream::new(Arc::clone(&m), &params(1)).unwrap();
    for stream in [&fresh, &s] {
        for layout in Layout::ALL {
            for c in Convention::ALL {
                assert_eq!(stream.read(0, 0, layout, c).unwrap(), Vec::<f32>::new());
            }
        }
        assert_eq!(stream.poses(0, 0).unwrap().frames(), 0);
        assert!(stream.features(0, 0).unwrap().is_empty());
    }
    for (chunk, overlap) in [(40, 0), (40, 40), (471, 10)] {
        let p = StreamParams {
            chunk,
            overlap,
            ..params(1)
        };
        assert!(
            Stream::new(Arc::clone(&m), &p).is_err(),
            "{chunk} {overlap}"
        );
    }
    let p = StreamParams {
        session: SessionParams {
            frames: Some(10),
            ..Default::default()
        },
        ..params(1)
    };
    assert!(Stream::new(Arc::clone(&m), &p).is_err());
    // MLD's decoder has no gradient: it can neither keep frames nor steer towards them.
    let Err(e) = Stream::new(model("mld_tiny"), &params(1)) else {
        panic!("an MLD model made a stream");
    };
    assert!(
        e.to_string().contains("latent") && e.to_string().contains("gradient"),
        "{e}"
    );
    // Part texts are read by FineMoGen only: another family refuses them when the segment's
    // chunk starts, and empty part texts are refused at push.
    let mut s = Stream::new(Arc::clone(&m), &params(1)).unwrap();
    let mut seg = Segment::new("a person walks.", 30);
    seg.parts[BodyPart::LeftArm as usize] = Some("  ".into());
    let e = s.push(seg.clone()).unwrap_err();
    assert!(e.to_string().contains("part text is empty"), "{e}");
    seg.parts[BodyPart::LeftArm as usize] = Some("the left arm waves.".into());
    s.push(seg).unwrap();
    let e = s.pump(1).unwrap_err();
    assert!(e.to_string().contains("part"), "{e}");
}

/// A cancelled pump leaves no trace: raised between pumps or by another thread during one, the
/// pump returns `Cancelled` and pumping on gives the bits of a stream never cancelled.
#[test]
fn a_cancelled_pump_resumes_bit_identically() {
    for name in ["flame_tiny", "mdm_tiny"] {
        let m = model(name);
        let mut want = Stream::new(Arc::clone(&m), &params(1)).unwrap();
        timeline(&mut want);
        run(&mut want, usize::MAX);

        let mut s = Stream::new(Arc::clone(&m), &params(1)).unwrap();
        timeline(&mut s);
        let flag = s.cancel_flag();
        s.pump(4).unwrap();
        flag.store(true, Ordering::SeqCst);
        let e = s.pump(usize::MAX).unwrap_err();
        assert!(matches!(e, flame::Error::Cancelled), "{name}: {e}");
        assert_eq!(s.ready(), 40, "{name}: the cancelled step kept nothing");
        // Another thread raises the flag while pumps run; every pump either finishes or is
        // cancelled, and the stream goes on from where it stood.
        let raiser = {
            let flag = Arc::clone(&flag);
            std::thread::spawn(move || {
                for _ in 0..20 {
                    std::thread::sleep(std::time::Duration::from_micros(300));
                    flag.store(true, Ordering::SeqCst);
                }
            })
        };
        let mut cancelled = 0;
        loop {
            match s.pump(1) {
                Ok(r) if r.steps == 0 => break,
                Ok(_) => {}
                Err(flame::Error::Cancelled) => cancelled += 1,
                Err(e) => panic!("{name}: {e}"),
            }
        }
        raiser.join().unwrap();
        flag.store(false, Ordering::SeqCst);
        assert_eq!(s.ready(), 115, "{name}");
        let (a, b) = (s.features(0, 115).unwrap(), want.features(0, 115).unwrap());
        assert!(
            a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{name}: {cancelled} cancels changed the frames"
        );
    }
}

/// FineMoGen reads a segment's part texts: with every part given the segment's own text the
/// frames are those of the plain segment, bit for bit (the part heads then read the same text),
/// and another part text changes them. Chunks after the first keep frames as for any family.
#[test]
fn finemogen_segments_take_part_texts() {
    let m = model("finemogen_tiny");
    let p = StreamParams {
        chunk: 30,
        overlap: 8,
        ..params(1)
    };
    let frames = |segments: Vec<Segment>| {
        let mut s = Stream::new(Arc::clone(&m), &p).unwrap();
        for seg in segments {
            s.push(seg).unwrap();
        }
        run(&mut s, usize::MAX);
        assert_eq!(s.ready(), 50);
        s.features(0, 50).unwrap().to_vec()
    };
    let (walk, wave) = ("a person walks forward.", "a person waves.");
    let plain = frames(vec![Segment::new(walk, 20), Segment::new(wave, 30)]);
    let mut same = Segment::new(wave, 30);
    same.parts = std::array::from_fn(|_| Some(wave.to_string()));
    let with_same = frames(vec![Segment::new(walk, 20), same]);
    assert!(plain
        .iter()
        .zip(&with_same)
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    let mut arm = Segment::new(wave, 30);
    arm.parts[BodyPart::RightArm as usize] = Some("the right arm swings up and down.".into());
    let with_arm = frames(vec![Segment::new(walk, 20), arm]);
    let dim = m.motion_dim();
    // The first segment is the same; the second differs.
    assert_eq!(&plain[..20 * dim], &with_arm[..20 * dim]);
    assert!(plain[20 * dim..] != with_arm[20 * dim..]);
}

/// Latent models (MoLA) cannot keep frames: each chunk is steered towards the kept frames'
/// joint positions with position targets (MPGD), and only its new frames are appended. The
/// timeline, determinism and frame counts are as for any family.
#[test]
fn mola_streams_continue_through_position_targets() {
    let m = model("mola_tiny");
    let p = StreamParams {
        chunk: 32,
        overlap: 8,
        ..params(1)
    };
    let mut a = Stream::new(Arc::clone(&m), &p).unwrap();
    timeline(&mut a);
    run(&mut a, 1);
    let mut b = Stream::new(Arc::clone(&m), &StreamParams { ..p.clone() }).unwrap();
    timeline(&mut b);
    run(&mut b, usize::MAX);
    assert_eq!((a.ready(), b.ready()), (115, 115));
    let (fa, fb) = (a.features(0, 115).unwrap(), b.features(0, 115).unwrap());
    assert!(fa.iter().zip(fb).all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(fa.iter().all(|v| v.is_finite()));
    let pos = a
        .read(0, 115, Layout::GlobalPositions, Convention::Native)
        .unwrap();
    assert!(pos.iter().all(|v| v.is_finite()));
}

/// On the trained demo model: the root path continues across seams (no jump larger than the
/// largest step inside the chunks) and the pelvis keeps moving smoothly.
#[test]
fn seams_of_the_demo_model_are_continuous() {
    let Some(path) = demo_model() else {
        return;
    };
    let m = Arc::new(Model::load(&path).unwrap());
    let p = StreamParams {
        chunk: 120,
        overlap: 20,
        lookahead: 10_000,
        window: 10_000,
        session: SessionParams {
            steps: Some(20),
            sampler: Some(Sampler::Ddim),
            seed: 1,
            threads: 2,
            ..Default::default()
        },
    };
    let mut s = Stream::new(m, &p).unwrap();
    s.push(Segment::new("a person walks forward.", 200))
        .unwrap();
    s.push(Segment::new("a person jumps.", 100)).unwrap();
    run(&mut s, usize::MAX);
    let frames = s.ready();
    assert_eq!(frames, 300);
    let root = s
        .read(0, frames, Layout::RootTranslation, Convention::Gltf)
        .unwrap();
    let step = |t: usize| {
        (0..3)
            .map(|k| (root[(t + 1) * 3 + k] - root[t * 3 + k]).powi(2))
            .sum::<f32>()
            .sqrt()
    };
    // Chunk seams (first new frame of each chunk after the first): 120, 220.
    let seams = [119usize, 219];
    let inside = (0..frames - 1)
        .filter(|t| !seams.contains(t))
        .map(step)
        .fold(0.0f32, f32::max);
    for &t in &seams {
        assert!(
            step(t) <= inside,
            "seam at {t}: {} m vs {inside} m inside",
            step(t)
        );
    }
}

/// Quaternion tracks are sign-continuous over the timeline whatever ranges they are read in: an
/// engine reading one frame per tick gets the bits of one whole read, and frames dropped behind
/// the playhead do not flip the signs of the frames held.
#[test]
fn quaternion_tracks_keep_their_signs_across_reads_and_drops() {
    for name in ["flame_tiny", "mdm_tiny"] {
        let m = model(name);
        let joints = m.motion_format().skeleton().joint_count();
        let mut s = Stream::new(Arc::clone(&m), &params(1)).unwrap();
        timeline(&mut s);
        run(&mut s, usize::MAX);
        for (layout, conv) in [
            (Layout::LocalQuatXyzw, Convention::Unity),
            (Layout::GlobalQuatWxyz, Convention::Native),
        ] {
            let whole = s.read(0, 115, layout, conv).unwrap();
            let one_by_one: Vec<f32> = (0..115)
                .flat_map(|f| s.read(f, 1, layout, conv).unwrap())
                .collect();
            assert_eq!(whole, one_by_one, "{name} {layout:?}");
            // Continuous: neighbouring frames' quaternions of a joint are in one hemisphere.
            for f in 1..115 {
                for j in 0..joints {
                    let (a, b) = ((f - 1) * joints + j, f * joints + j);
                    let dot: f32 = (0..4).map(|k| whole[a * 4 + k] * whole[b * 4 + k]).sum();
                    assert!(dot >= -1e-6, "{name} {layout:?} frame {f} joint {j}: {dot}");
                }
            }
        }
        // Signs chosen per frame would flip somewhere on these random motions: the test can
        // fail.
        let m3 = s
            .read(0, 115, Layout::LocalMatrix, Convention::Unity)
            .unwrap();
        let raw: Vec<[f64; 4]> = m3
            .chunks_exact(9)
            .map(|r| {
                let m = [
                    [r[0] as f64, r[1] as f64, r[2] as f64],
                    [r[3] as f64, r[4] as f64, r[5] as f64],
                    [r[6] as f64, r[7] as f64, r[8] as f64],
                ];
                flame::motion::rotation::to_quat(&m)
            })
            .collect();
        let flips = (joints..raw.len())
            .filter(|&i| (0..4).map(|k| raw[i][k] * raw[i - joints][k]).sum::<f64>() < 0.0)
            .count();
        assert!(flips > 0, "{name}: no sign flip to correct");
        // Dropping frames keeps the held frames' signs.
        let before = s
            .read(60, 55, Layout::LocalQuatXyzw, Convention::Unity)
            .unwrap();
        let mut p = params(1);
        p.window = 10;
        let mut d = Stream::new(Arc::clone(&m), &p).unwrap();
        timeline(&mut d);
        run(&mut d, usize::MAX);
        d.read(0, 1, Layout::LocalQuatXyzw, Convention::Unity)
            .unwrap();
        d.set_playhead(70).unwrap();
        assert_eq!(d.first_frame(), 60);
        let after = d
            .read(60, 55, Layout::LocalQuatXyzw, Convention::Unity)
            .unwrap();
        assert_eq!(before, after, "{name}");
    }
}

/// MotionLCM continues each chunk through its trajectory ControlNet: the kept frames' joint
/// positions are the next chunk's control hint (the temporal-control route), and only its new
/// frames are appended. Deterministic under any pump pattern; a MotionLCM file without a
/// ControlNet is refused with the reason (MLD's decoder has no gradient either).
#[test]
fn motionlcm_streams_continue_through_the_controlnet() {
    let m = model("motionlcm_v2_control_tiny");
    let p = StreamParams {
        chunk: 32,
        overlap: 8,
        session: SessionParams {
            steps: Some(2),
            sampler: Some(Sampler::Lcm),
            seed: 5,
            threads: 1,
            ..Default::default()
        },
        ..params(1)
    };
    let mut a = Stream::new(Arc::clone(&m), &p).unwrap();
    timeline(&mut a);
    run(&mut a, 1);
    let mut b = Stream::new(Arc::clone(&m), &p).unwrap();
    timeline(&mut b);
    run(&mut b, usize::MAX);
    assert_eq!((a.ready(), b.ready()), (115, 115));
    let (fa, fb) = (a.features(0, 115).unwrap(), b.features(0, 115).unwrap());
    assert!(fa.iter().zip(fb).all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(fa.iter().all(|v| v.is_finite()));
    let Err(e) = Stream::new(model("motionlcm_v2_tiny"), &p) else {
        panic!("a MotionLCM file without a ControlNet made a stream");
    };
    assert!(e.to_string().contains("ControlNet"), "{e}");
}
