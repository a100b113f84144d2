//! `flame edit`: the editing tasks from the command line, with .npy and BVH references.

use std::path::{Path, PathBuf};
use std::process::Command;

use flame::motion::{self, Format, Mask, Task};

const FRAMES: usize = 24;
const DIM: usize = 147;

fn flame() -> Command {
    Command::new(env!("CARGO_BIN_EXE_flame"))
}

fn model() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/flame_tiny.safetensors")
        .display()
        .to_string()
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flame_edit_cli_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn run(args: &[&str]) -> (bool, String) {
    let out = flame().args(args).output().unwrap();
    let text = String::from_utf8_lossy(&out.stderr).to_string();
    (out.status.success(), text)
}

/// The reference walk (24 frames, seed 3) written to `out`, with `extra` options.
fn generate_walk(out: &Path, extra: &[&str]) -> (bool, String) {
    let m = model();
    let mut args = vec![
        "generate",
        "--model",
        &m,
        "--prompt",
        "a person walks forward",
        "--frames",
        "24",
        "--steps",
        "4",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

/// Each test writes its own reference (tests run in parallel in one process).
fn generate_reference(tag: &str) -> (PathBuf, Vec<f32>) {
    let path = tmp(&format!("ref_{tag}.npy"));
    let (ok, err) = generate_walk(&path, &[]);
    assert!(ok, "{err}");
    let (shape, x) = flame::npy::read_f32(&path).unwrap();
    assert_eq!(shape, vec![FRAMES, DIM]);
    (path, x)
}

fn edit(reference: &Path, extra: &[&str], out: &Path) -> (bool, String) {
    let m = model();
    let mut args = vec![
        "edit",
        "--model",
        &m,
        "--reference",
        reference.to_str().unwrap(),
        "--prompt",
        "a person waves",
        "--steps",
        "4",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn every_task_keeps_its_values_exactly() {
    let (reference, r) = generate_reference("every");
    for task in Task::ALL {
        let out = tmp(&format!("edit_{}.npy", task.name()));
        let (ok, err) = edit(&reference, &["--task", task.name()], &out);
        assert!(ok, "{task}: {err}");
        let (_, x) = flame::npy::read_f32(&out).unwrap();
        let mask = Mask::for_task(Format::Smpl24Rot6d, FRAMES, task).unwrap();
        let kept: Vec<usize> = (0..x.len()).filter(|&i| mask.flags()[i]).collect();
        assert!(!kept.is_empty());
        for &i in &kept {
            assert_eq!(x[i].to_bits(), r[i].to_bits(), "{task}: value {i}");
        }
        let changed = (0..x.len())
            .filter(|&i| !mask.flags()[i] && x[i] != r[i])
            .count();
        assert!(changed > 0, "{task}: nothing generated");
    }
}

#[test]
fn keep_frames_and_joints_add_to_the_mask() {
    let (reference, r) = generate_reference("mixed");
    let out = tmp("edit_mixed.npy");
    let (ok, err) = edit(
        &reference,
        &["--keep-frames", "0:3,20:", "--keep-joints", "root,L_Wrist"],
        &out,
    );
    assert!(ok, "{err}");
    assert!(err.contains("keeping"), "{err}");
    let (_, x) = flame::npy::read_f32(&out).unwrap();
    let l_wrist = motion::mask::joint_channels(Format::Smpl24Rot6d, 20).unwrap();
    for f in 0..FRAMES {
        for c in 0..DIM {
            let i = f * DIM + c;
            let kept = !(3..20).contains(&f) || c < 3 || l_wrist.contains(&c);
            if kept {
                assert_eq!(x[i].to_bits(), r[i].to_bits(), "frame {f} channel {c}");
            }
        }
    }
    // The official behaviour: nothing is pasted, so the kept frames are only close.
    let raw = tmp("edit_mixed_raw.npy");
    let (ok, err) = edit(
        &reference,
        &["--keep-frames", "0:3", "--paste", "off"],
        &raw,
    );
    assert!(ok, "{err}");
    let (_, y) = flame::npy::read_f32(&raw).unwrap();
    assert!((0..3 * DIM).any(|i| y[i] != r[i]));
}

#[test]
fn a_bvh_reference_written_by_libflame_is_read_back() {
    let (reference, _) = generate_reference("bvh");
    for convention in ["gltf", "unreal"] {
        let bvh = tmp(&format!("ref_{convention}.bvh"));
        // Raw poses (`--feet off`): the floor and foot locking would move the root off the
        // features this test compares with.
        let (ok, err) = generate_walk(
            &bvh,
            &["--smooth", "0", "--convention", convention, "--feet", "off"],
        );
        assert!(ok, "{err}");
        let out = tmp(&format!("edit_from_{convention}.npy"));
        // smpl24_6d's native and gltf BVHs share their offsets and a random-weight motion has
        // no clear up axis, so gltf is named; unreal's centimetre offsets are recognised.
        let extra: &[&str] = if convention == "gltf" {
            &["--task", "path", "--reference-convention", "gltf"]
        } else {
            &["--task", "path"]
        };
        let (ok, err) = edit(&bvh, extra, &out);
        assert!(ok, "{err}");
        if convention == "unreal" {
            assert!(err.contains("unreal convention"), "{err}");
        }
        // The kept root path is the BVH's root, which is the .npy reference's translation to
        // the BVH's 6 printed decimals.
        let (_, x) = flame::npy::read_f32(&out).unwrap();
        let (_, r) = flame::npy::read_f32(&reference).unwrap();
        for f in 0..FRAMES {
            for c in 0..3 {
                let d = (x[f * DIM + c] - r[f * DIM + c]).abs();
                assert!(d < 1e-4, "{convention} frame {f} channel {c}: {d}");
            }
        }
    }
}

#[test]
fn prediction_continues_a_shorter_reference() {
    let (reference, r) = generate_reference("predict");
    let out = tmp("edit_predict.npy");
    let (ok, err) = edit(&reference, &["--task", "predict", "--frames", "40"], &out);
    assert!(ok, "{err}");
    let (shape, x) = flame::npy::read_f32(&out).unwrap();
    assert_eq!(shape, vec![40, DIM]);
    assert_eq!(&x[..FRAMES * DIM], &r[..]);
}

#[test]
fn bad_edits_are_refused_with_a_message() {
    let (reference, _) = generate_reference("bad");
    let out = tmp("bad.npy");
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec![], "nothing is kept"),
        (vec!["--task", "sideways"], "unknown editing task"),
        (vec!["--keep-frames", "30:40"], "frame"),
        (vec!["--keep-joints", "tail"], "tail"),
        (vec!["--task", "path", "--frames", "10"], "more than the 10"),
        (vec!["--task", "path", "--paste", "maybe"], "--paste"),
        (vec!["--task", "path", "--edit-till", "2"], "edit_till"),
        (
            vec!["--task", "path", "--method", "rewrite-trajectory"],
            "does not apply",
        ),
    ];
    for (extra, want) in cases {
        let (ok, err) = edit(&reference, &extra, &out);
        assert!(!ok, "{extra:?} succeeded");
        assert!(err.contains(want), "{extra:?}: {err}");
    }
    let missing = tmp("missing.npy");
    let (ok, err) = edit(&missing, &["--task", "path"], &out);
    assert!(!ok && err.contains("cannot read"), "{err}");
    let wrong = tmp("wrong.npy");
    flame::npy::write_f32(&wrong, &[4, 5], &[0.0; 20]).unwrap();
    let (ok, err) = edit(&wrong, &["--task", "path"], &out);
    assert!(!ok && err.contains("expected [frames, 147]"), "{err}");
}

#[test]
fn preview_writes_a_png_next_to_any_output() {
    for out in ["prev.npy", "prev.bvh"] {
        let out = tmp(out);
        let png = tmp(&format!(
            "{}.png",
            out.file_name().unwrap().to_str().unwrap()
        ));
        let (ok, err) = run(&[
            "generate",
            "--model",
            &model(),
            "--prompt",
            "a person jumps",
            "--frames",
            "24",
            "--steps",
            "2",
            "--out",
            out.to_str().unwrap(),
            "--preview",
            png.to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
        let bytes = std::fs::read(&png).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        assert!(out.exists());
    }
    let (ok, err) = run(&[
        "generate",
        "--model",
        &model(),
        "--prompt",
        "x",
        "--out",
        "x.npy",
        "--preview",
        "x.jpg",
    ]);
    assert!(!ok && err.contains("--preview must end in .png"), "{err}");
}

/// `--targets`: a pelvis path in the glTF convention (Y up, metres), NaN elsewhere, with no
/// reference; the result's pelvis (read back with `--positions`) is nearer the path than the
/// unguided motion's. Then bad targets files.
#[test]
fn targets_steer_from_the_command_line() {
    let m = model();
    let joints = 24;
    let plain = tmp("targets_plain.npy");
    let plain_pos = tmp("targets_plain_pos.npy");
    let (ok, err) = generate_walk(
        &plain,
        &[
            "--positions",
            plain_pos.to_str().unwrap(),
            "--convention",
            "gltf",
        ],
    );
    assert!(ok, "{err}");
    let (_, p) = flame::npy::read_f32(&plain_pos).unwrap();
    let mut t = vec![f32::NAN; FRAMES * joints * 3];
    for f in 0..FRAMES {
        let at = f * joints * 3;
        // From the unguided start, 5 cm per frame along glTF's +x on the ground (x, z).
        t[at] = p[0] + 0.05 * f as f32;
        t[at + 2] = p[2];
    }
    let targets = tmp("targets.npy");
    flame::npy::write_f32(&targets, &[FRAMES, joints, 3], &t).unwrap();
    let out = tmp("targets_out.npy");
    let pos = tmp("targets_pos.npy");
    let (ok, err) = run(&[
        "edit",
        "--model",
        &m,
        "--targets",
        targets.to_str().unwrap(),
        "--prompt",
        "a person walks forward",
        "--frames",
        "24",
        "--steps",
        "4",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--positions",
        pos.to_str().unwrap(),
        "--convention",
        "gltf",
    ]);
    assert!(ok, "{err}");
    assert!(err.contains("steering 48 joint coordinates over 24 frames toward --targets (scale 0.6, constant schedule)"), "{err}");
    assert!(err.contains("position targets: loss"), "{err}");
    let (_, q) = flame::npy::read_f32(&pos).unwrap();
    let miss = |p: &[f32]| -> f32 {
        (0..FRAMES)
            .map(|f| {
                let (a, at) = (&p[f * joints * 3..], f * joints * 3);
                ((a[0] - t[at]).powi(2) + (a[2] - t[at + 2]).powi(2)).sqrt()
            })
            .sum::<f32>()
            / FRAMES as f32
    };
    let (before, after) = (miss(&p), miss(&q));
    assert!(after < 0.5 * before, "{before} -> {after}");

    // Bad targets: wrong shape, a constrained infinity, a scale out of range.
    let bad = tmp("targets_bad.npy");
    flame::npy::write_f32(&bad, &[FRAMES, 22, 3], &vec![0.0; FRAMES * 22 * 3]).unwrap();
    let (ok, err) = run(&[
        "edit",
        "--model",
        &m,
        "--targets",
        bad.to_str().unwrap(),
        "--prompt",
        "a",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("expected [frames, 24, 3] joint positions"),
        "{err}"
    );
    let mut inf = t.clone();
    inf[3] = f32::INFINITY;
    flame::npy::write_f32(&bad, &[FRAMES, joints, 3], &inf).unwrap();
    let (ok, err) = run(&[
        "edit",
        "--model",
        &m,
        "--targets",
        bad.to_str().unwrap(),
        "--prompt",
        "a",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("is inf but constrained"), "{err}");
    let (ok, err) = run(&[
        "edit",
        "--model",
        &m,
        "--targets",
        targets.to_str().unwrap(),
        "--target-scale",
        "101",
        "--prompt",
        "a",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("target scale must be"), "{err}");
    let (ok, err) = run(&[
        "edit",
        "--model",
        &m,
        "--prompt",
        "a",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--reference"), "{err}");
}

/// A latent model edits by MPGD (`--method auto`): the reference's pelvis becomes the target.
#[test]
fn a_latent_model_edits_by_mpgd() {
    let mola = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/mola_tiny.safetensors")
        .display()
        .to_string();
    let reference = tmp("mola_ref.npy");
    let (ok, err) = run(&[
        "generate",
        "--model",
        &mola,
        "--prompt",
        "a person walks",
        "--frames",
        "24",
        "--steps",
        "5",
        "--seed",
        "1",
        "--out",
        reference.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let out = tmp("mola_out.npy");
    let (ok, err) = run(&[
        "edit",
        "--model",
        &mola,
        "--reference",
        reference.to_str().unwrap(),
        "--task",
        "path",
        "--prompt",
        "a person runs",
        "--frames",
        "24",
        "--steps",
        "5",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        err.contains("toward the reference (MPGD, scale 0.6, mpgd schedule)"),
        "{err}"
    );
    let (ok, err) = run(&[
        "edit",
        "--model",
        &mola,
        "--reference",
        reference.to_str().unwrap(),
        "--task",
        "path",
        "--method",
        "replace-x0",
        "--prompt",
        "a",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("samples a latent"), "{err}");
}
