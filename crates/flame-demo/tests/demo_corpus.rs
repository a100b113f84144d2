//! The procedural demo corpus and its rule-based classifier (`flame_demo`, docs/demo_corpus.md):
//! classifier accuracy on the corpus, physical plausibility measured on decoded motions,
//! determinism, descriptions and evaluation prompts, and the `flame-corpus` CLI round trip.
//! Run with `-- --nocapture` to see the confusion table and the measured bounds.

use std::collections::HashSet;

// The repository's test helpers (tests/common), shared with the runtime's tests.
#[path = "../../../tests/common/mod.rs"]
mod common;

use flame::motion::rotation::{self, Mat3};
use flame::motion::{Convention, Format, Poses, ReadOptions};
use flame_demo::corpus::{self, CorpusMotion};
use flame_demo::rig::{joint, FPS};
use flame_demo::sentences::normalize;
use flame_demo::{classify, Confusion, Family};

fn decode(m: &CorpusMotion) -> Poses {
    Poses::decode(
        Format::Smpl24Rot6d,
        &m.features,
        m.frames,
        &ReadOptions::default(),
    )
    .unwrap()
}

/// Judges a motion: one action → the whole motion; two → each part split at `split_frame`.
/// Returns whether every part is right.
fn judge(m: &CorpusMotion, confusion: &mut Confusion) -> bool {
    let p = decode(m).positions(Convention::Native);
    let j = joint::JOINTS;
    let cut = m.split_frame.unwrap_or(m.frames);
    let parts = [0..cut, cut..m.frames];
    let mut ok = true;
    for (r, &want) in parts.into_iter().zip(&m.actions) {
        let got = classify::classify(&p[r.start * j..r.end * j], r.len(), FPS);
        confusion.add(want, got);
        ok &= got == want;
    }
    ok
}

#[test]
fn classifier_labels_the_corpus() {
    let motions = corpus::generate(600, 7);
    let mut confusion = Confusion::default();
    let mut wrong = Vec::new();
    for m in &motions {
        if !judge(m, &mut confusion) {
            wrong.push(format!("{} {:?} {}", m.id, m.actions, m.variant));
        }
    }
    let acc = 1.0 - wrong.len() as f64 / motions.len() as f64;
    println!("{}", confusion.table());
    println!(
        "motions right: {:.2}% ({} wrong); parts right: {:.2}%",
        100.0 * acc,
        wrong.len(),
        100.0 * confusion.accuracy()
    );
    for w in wrong.iter().take(30) {
        println!("  wrong: {w}");
    }
    for f in Family::ALL {
        assert!(
            confusion.counts[f.index()].iter().sum::<usize>() >= 15,
            "{f} is under-represented"
        );
    }
    assert!(acc >= 0.95, "accuracy {acc}");
}

/// `R_aᵀ R_b` as a rotation vector (axis × angle).
fn log_rel(a: &Mat3, b: &Mat3) -> [f64; 3] {
    let r = rotation::mul(&rotation::transpose(a), b);
    let c = ((r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0).clamp(-1.0, 1.0);
    let angle = c.acos();
    let v = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
    let s = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if s < 1e-12 {
        return [0.0; 3];
    }
    v.map(|x| x / s * angle)
}

/// Signed angle of a rotation about a unit hinge axis (degrees).
fn hinge_degrees(r: &Mat3, hinge: [f64; 3]) -> f64 {
    let w = log_rel(&rotation::IDENTITY, r);
    (w[0] * hinge[0] + w[1] * hinge[1] + w[2] * hinge[2]).to_degrees()
}

#[test]
fn motions_are_physically_plausible() {
    let motions = corpus::generate(300, 11);
    let j = joint::JOINTS;
    let (mut max_slide, mut slide_frames) = ((0.0f64, String::new()), 0usize);
    let mut lowest = f64::MAX;
    let mut max_acc = (0.0f64, String::new());
    let (mut knee_min, mut knee_max, mut elbow_min) = (f64::MAX, f64::MIN, f64::MAX);
    let mut spine_max = 0.0f64;
    for m in &motions {
        assert!(
            (40..=200).contains(&m.frames),
            "{}: {} frames",
            m.id,
            m.frames
        );
        assert_eq!(m.features.len(), m.frames * 147);
        assert!(m.features.iter().all(|x| x.is_finite()), "{}", m.id);
        for row in m.features.chunks_exact(147) {
            for d in row[3..].chunks_exact(6) {
                let (a, b) = (&d[..3], &d[3..]);
                let dot = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f32>();
                assert!((dot(a, a) - 1.0).abs() < 1e-5 && (dot(b, b) - 1.0).abs() < 1e-5);
                assert!(dot(a, b).abs() < 1e-5, "{}: 6D rows not orthogonal", m.id);
            }
        }
        let poses = decode(m);
        let p = poses.positions(Convention::Native);
        let local = poses.local_rotations(Convention::Native);

        // Canonical start: pelvis above the origin, facing −Y (left hip at +X), feet on z = 0.
        assert!(p[0][0].abs() < 1e-4 && p[0][1].abs() < 1e-4, "{}", m.id);
        assert!(p[joint::L_HIP][0] > p[joint::R_HIP][0] + 0.1, "{}", m.id);
        for f in [joint::L_FOOT, joint::R_FOOT] {
            assert!(p[f][2].abs() < 2e-3, "{}: foot at {}", m.id, p[f][2]);
        }
        for q in &p {
            lowest = lowest.min(q[2]);
        }
        // Feet on the ground (within 5 mm in two consecutive frames) do not slide.
        for t in 1..m.frames {
            for f in [joint::L_FOOT, joint::R_FOOT] {
                let (a, b) = (p[(t - 1) * j + f], p[t * j + f]);
                if a[2] < 0.005 && b[2] < 0.005 {
                    let v = (b[0] - a[0]).hypot(b[1] - a[1]) * FPS;
                    if v > max_slide.0 {
                        max_slide = (v, format!("{} joint {f} frame {t} ({})", m.id, m.variant));
                    }
                    slide_frames += 1;
                }
            }
        }
        // C1 joint angles: bounded angular acceleration of every local rotation.
        for t in 1..m.frames - 1 {
            for k in 0..j {
                let w0 = log_rel(&local[(t - 1) * j + k], &local[t * j + k]);
                let w1 = log_rel(&local[t * j + k], &local[(t + 1) * j + k]);
                let a =
                    ((w1[0] - w0[0]).powi(2) + (w1[1] - w0[1]).powi(2) + (w1[2] - w0[2]).powi(2))
                        .sqrt()
                        * FPS
                        * FPS;
                if a > max_acc.0 {
                    max_acc = (a, format!("{} joint {k} frame {t} ({})", m.id, m.variant));
                }
            }
        }
        // Joint ranges: knees and elbows bend one way only; spine joints stay moderate.
        for t in 0..m.frames {
            let r = |k: usize| &local[t * j + k];
            for k in [joint::L_KNEE, joint::R_KNEE] {
                let a = hinge_degrees(r(k), [1.0, 0.0, 0.0]);
                knee_min = knee_min.min(a);
                knee_max = knee_max.max(a);
            }
            elbow_min = elbow_min
                .min(hinge_degrees(r(joint::L_ELBOW), [0.0, -1.0, 0.0]))
                .min(hinge_degrees(r(joint::R_ELBOW), [0.0, 1.0, 0.0]));
            for k in [
                joint::SPINE1,
                joint::SPINE2,
                joint::SPINE3,
                joint::NECK,
                joint::HEAD,
            ] {
                let w = log_rel(&rotation::IDENTITY, r(k));
                spine_max = spine_max.max(
                    (w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
                        .sqrt()
                        .to_degrees(),
                );
            }
        }
    }
    println!(
        "planted-foot speed: max {:.4} m/s at {} over {slide_frames} foot-frames",
        max_slide.0, max_slide.1
    );
    println!("lowest joint: {lowest:.4} m");
    println!(
        "max angular acceleration: {:.1} rad/s² at {}",
        max_acc.0, max_acc.1
    );
    println!("knee flexion: {knee_min:.1}..{knee_max:.1}°, elbow min {elbow_min:.1}°, spine/neck joint max {spine_max:.1}°");
    assert!(slide_frames > 10_000);
    assert!(max_slide.0 < 0.02, "planted feet slide: {max_slide:?}");
    assert!(lowest > -0.01, "a joint goes {lowest} m below the ground");
    // Running knees reach ~470 rad/s²; a pose jump or an IK flip of 90° in one frame gives
    // well over 1000.
    assert!(max_acc.0 < 600.0, "angular acceleration {max_acc:?}");
    assert!(
        knee_min > -5.0 && knee_max < 150.0,
        "knee {knee_min}..{knee_max}"
    );
    assert!(elbow_min > -5.0, "elbow hyperextends: {elbow_min}");
    assert!(spine_max < 45.0, "spine joint rotates {spine_max}°");
}

#[test]
fn same_seed_same_corpus_other_seed_other_corpus() {
    let a = corpus::generate(40, 3);
    let b = corpus::generate(40, 3);
    let c = corpus::generate(40, 4);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.features, y.features);
        assert_eq!(x.texts, y.texts);
        assert_eq!(x.actions, y.actions);
    }
    let same = a
        .iter()
        .zip(&c)
        .filter(|(x, y)| x.features == y.features)
        .count();
    assert_eq!(same, 0);
    // Motion i does not depend on the corpus size.
    assert_eq!(corpus::generate_one(17, 3).features, a[17].features);
}

fn eval_prompts() -> Vec<(Family, String)> {
    let path = common::repo("tests/fixtures/demo_eval_prompts.tsv");
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let (f, p) = l.split_once('\t').expect("family<TAB>prompt");
            (
                Family::from_name(f).unwrap_or_else(|| panic!("unknown family {f}")),
                p.to_string(),
            )
        })
        .collect()
}

#[test]
fn descriptions_are_varied_and_eval_prompts_are_unseen() {
    let motions = corpus::generate(4000, 0);
    let mut seen = HashSet::new();
    for m in &motions {
        let unique: HashSet<&String> = m.texts.iter().collect();
        assert!(unique.len() >= 5, "{}: {:?}", m.id, m.texts);
        for t in &m.texts {
            assert!(!t.contains('{') && !t.contains("  "), "{t}");
            seen.insert(normalize(t));
        }
    }
    println!("{} distinct training sentences", seen.len());
    let prompts = eval_prompts();
    assert!(prompts.len() >= 45);
    for f in Family::ALL {
        let n = prompts.iter().filter(|(g, _)| *g == f).count();
        assert!(n >= 3, "{f} has {n} evaluation prompts");
    }
    for (f, p) in &prompts {
        assert!(
            !seen.contains(&normalize(p)),
            "{f} prompt is a training sentence: {p}"
        );
    }
}

#[test]
fn cli_generates_and_checks_a_corpus() {
    let dir = std::env::temp_dir().join(format!("flame-corpus-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let bin = env!("CARGO_BIN_EXE_flame-corpus");
    let out = std::process::Command::new(bin)
        .args([
            "generate",
            "--out",
            dir.to_str().unwrap(),
            "--count",
            "45",
            "--seed",
            "5",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines = std::fs::read_to_string(dir.join("corpus.jsonl")).unwrap();
    assert_eq!(lines.lines().count(), 45);
    let first: serde_json::Value = serde_json::from_str(lines.lines().next().unwrap()).unwrap();
    assert_eq!(first["id"], "000000");
    assert_eq!(first["file"], "motions/000000.npy");
    let frames = first["frames"].as_u64().unwrap() as usize;
    let (shape, _) = flame::npy::read_f32(&dir.join("motions/000000.npy")).unwrap();
    assert_eq!(shape, vec![frames, 147]);
    assert_eq!(
        corpus::generate_one(0, 5).texts,
        serde_json::from_value::<Vec<String>>(first["texts"].clone()).unwrap()
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["count"], 45);
    assert_eq!(summary["seed"], 5);

    let out = std::process::Command::new(bin)
        .args(["check", dir.to_str().unwrap()])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    println!("{text}");
    assert!(out.status.success() && text.contains("motions:"), "{text}");
    let out = std::process::Command::new(bin)
        .args(["classify", dir.join("motions/000000.npy").to_str().unwrap()])
        .output()
        .unwrap();
    let got = String::from_utf8_lossy(&out.stdout).trim().to_string();
    assert!(Family::from_name(&got).is_some(), "{got}");

    // The same motion as joint positions (what `flame generate --positions` writes) gets the
    // same label; any other shape is refused with a message.
    let (_, features) = flame::npy::read_f32(&dir.join("motions/000000.npy")).unwrap();
    let positions: Vec<f32> = flame_demo::classify::positions_of(&features, frames)
        .unwrap()
        .iter()
        .flat_map(|p| p.map(|v| v as f32))
        .collect();
    let pos_file = dir.join("positions.npy");
    flame::npy::write_f32(&pos_file, &[frames, 24, 3], &positions).unwrap();
    let out = std::process::Command::new(bin)
        .args(["classify", pos_file.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), got);
    flame::npy::write_f32(&pos_file, &[frames, 72], &positions).unwrap();
    let out = std::process::Command::new(bin)
        .args(["classify", pos_file.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("[frames, 24, 3]"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
