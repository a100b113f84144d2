//! The motion side of editing: keep-masks (channels per joint and body part, the standard tasks,
//! CLI parsing), references given as poses turned back into `smpl24_6d` features, and BVH files
//! written by libflame read back as references.
//!
//! Published sets: MDM's `HML_LOWER_BODY_MASK` dims and `in_between` with 0.25/0.75
//! (docs/official/mdm.md#editing), FLAME's kept joints 0,1,2,4,5,7,8,10,11 plus the translation
//! (docs/official/flame.md#editing), and Motion Flow Matching's "prediction" mask (docs/official/motionfm.md#editing). Motions are pseudo-random rotations (a fixed xorshift seed), with a root
//! that stands the body up so that the BVH reader can tell `native` from `gltf`.

use flame::motion::mask::{self, joint_channels, parse_frame_ranges, parse_joints, part_channels};
use flame::motion::rotation::{self, Mat3};
use flame::motion::{
    bvh, reference, BodyPart, Convention, Format, Layout, Mask, Poses, ReadOptions, Task,
};

const SMPL: Format = Format::Smpl24Rot6d;
const HML: Format = Format::HumanMl263;

/// Inclusive ranges → the channel list.
fn dims(ranges: &[(usize, usize)]) -> Vec<usize> {
    ranges.iter().flat_map(|&(a, b)| a..=b).collect()
}

// ------------------------------------------------------------------------------------------
// Channels and body parts

#[test]
fn humanml_lower_body_is_mdms_published_mask() {
    // HML_LOWER_BODY_MASK's True dims (docs/official/mdm.md#upper-body-mask).
    let want = dims(&[
        (0, 9),
        (13, 18),
        (22, 27),
        (31, 36),
        (67, 78),
        (85, 96),
        (103, 114),
        (121, 132),
        (193, 201),
        (205, 210),
        (214, 219),
        (223, 228),
        (259, 262),
    ]);
    assert_eq!(want.len(), 107);
    assert_eq!(part_channels(HML, BodyPart::LowerBody), want);
}

#[test]
fn smpl_lower_body_is_flames_kept_set() {
    // Translation 0..2 and joints 0,1,2,4,5,7,8,10,11 at 3+6j .. 3+6j+5 (docs/official/flame.md#editing).
    let mut want = vec![0, 1, 2];
    for j in [0, 1, 2, 4, 5, 7, 8, 10, 11] {
        want.extend(3 + 6 * j..3 + 6 * j + 6);
    }
    assert_eq!(part_channels(SMPL, BodyPart::LowerBody), want);
    // What FLAME regenerates: joints 3,6,9,12..23.
    let mut edited = Vec::new();
    for j in [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23] {
        edited.extend(3 + 6 * j..3 + 6 * j + 6);
    }
    assert_eq!(part_channels(SMPL, BodyPart::UpperBody), edited);
}

#[test]
fn lower_and_upper_body_partition_every_format() {
    for f in Format::ALL {
        let lower = part_channels(f, BodyPart::LowerBody);
        let upper = part_channels(f, BodyPart::UpperBody);
        let mut all: Vec<usize> = lower.iter().chain(&upper).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..f.feature_dim()).collect::<Vec<_>>(), "{f}");
        // Legs and arms sit inside their halves; the root path inside the lower body.
        for (part, half) in [
            (BodyPart::Legs, &lower),
            (BodyPart::RootPath, &lower),
            (BodyPart::Arms, &upper),
        ] {
            assert!(
                part_channels(f, part).iter().all(|c| half.contains(c)),
                "{f} {part}"
            );
        }
    }
}

#[test]
fn parts_have_hand_counted_sizes() {
    // smpl: arms 10 joints × 6; legs 8 × 6; root path 3.
    assert_eq!(part_channels(SMPL, BodyPart::Arms).len(), 60);
    assert_eq!(part_channels(SMPL, BodyPart::Legs).len(), 48);
    assert_eq!(part_channels(SMPL, BodyPart::RootPath), vec![0, 1, 2]);
    assert_eq!(mask::root_path_channels(HML), vec![0, 1, 2, 3]);
    // humanml: arms 8 joints × (3 ric + 6 rot + 3 vel); legs 8 × 12 + 4 contacts.
    assert_eq!(part_channels(HML, BodyPart::Arms).len(), 96);
    assert_eq!(part_channels(HML, BodyPart::Legs).len(), 100);
    // Left ankle (7): ric 22..25, rot 103..109, velocity 214..217, contact 259.
    assert_eq!(
        joint_channels(HML, 7).unwrap(),
        vec![22, 23, 24, 103, 104, 105, 106, 107, 108, 214, 215, 216, 259]
    );
    // The foot contacts follow docs/official/humanml3d.md#feature-layout's order: L ankle, L foot,
    // R ankle, R foot.
    for (joint, contact) in [(7, 259), (10, 260), (8, 261), (11, 262)] {
        assert!(joint_channels(HML, joint).unwrap().contains(&contact));
    }
}

// ------------------------------------------------------------------------------------------
// Masks and tasks

/// Frames of a mask where any channel is kept.
fn kept_frames(m: &Mask) -> Vec<usize> {
    let dim = m.format().feature_dim();
    (0..m.frames())
        .filter(|&t| m.flags()[t * dim..(t + 1) * dim].contains(&true))
        .collect()
}

#[test]
fn tasks_follow_the_official_masks() {
    // 196 frames (MDM's max): int(0.25·196) = 49, int(0.75·196) = 147.
    let m = Mask::for_task(HML, 196, Task::Inbetween).unwrap();
    let want: Vec<usize> = (0..49).chain(147..196).collect();
    assert_eq!(kept_frames(&m), want);
    assert_eq!(m.kept_count(), want.len() * 263);
    // 10 frames: int(2.5) = 2, int(7.5) = 7.
    let m = Mask::for_task(SMPL, 10, Task::Inbetween).unwrap();
    assert_eq!(kept_frames(&m), vec![0, 1, 7, 8, 9]);
    let m = Mask::for_task(SMPL, 10, Task::Predict).unwrap();
    assert_eq!(kept_frames(&m), vec![0, 1]);
    assert_eq!(m.kept_count(), 2 * 147);
    assert_eq!(m.last_kept_frame(), Some(1));

    let m = Mask::for_task(HML, 5, Task::UpperBody).unwrap();
    let lower = part_channels(HML, BodyPart::LowerBody);
    for row in m.flags().chunks(263) {
        let kept: Vec<usize> = (0..263).filter(|&c| row[c]).collect();
        assert_eq!(kept, lower);
    }
    let m = Mask::for_task(SMPL, 3, Task::Path).unwrap();
    assert_eq!(m.kept_count(), 9);
    assert!(m.flags()[147..150].iter().all(|&k| k) && !m.flags()[150]);
}

#[test]
fn degenerate_tasks_are_errors() {
    let e = Mask::for_task(SMPL, 3, Task::Predict)
        .unwrap_err()
        .to_string();
    assert!(e.contains("give at least 4"), "{e}");
    let e = Mask::for_task(SMPL, 1, Task::Inbetween)
        .unwrap_err()
        .to_string();
    assert!(e.contains("regenerates nothing"), "{e}");
    assert!(Mask::for_task(SMPL, 0, Task::Path).is_err());
    assert!(Mask::for_task(SMPL, 2, Task::Inbetween).is_ok());
    assert_eq!("upper-body".parse::<Task>().unwrap(), Task::UpperBody);
    let e = "middle".parse::<Task>().unwrap_err().to_string();
    assert!(e.contains("unknown editing task `middle`"), "{e}");
}

#[test]
fn mask_builders_set_exactly_what_they_name() {
    let mut m = Mask::new(SMPL, 6).unwrap();
    assert!(m.is_empty() && !m.is_full() && m.last_kept_frame().is_none());
    m.keep_frames(4, 6).unwrap();
    assert_eq!(kept_frames(&m), vec![4, 5]);
    m.keep_joint_named("l_knee", 0, 2).unwrap();
    // L_Knee = joint 4 → channels 27..33 on frames 0 and 1.
    for t in 0..2 {
        let kept: Vec<usize> = (0..147).filter(|&c| m.flags()[t * 147 + c]).collect();
        assert_eq!(kept, (27..33).collect::<Vec<_>>());
    }
    m.keep_joint_named("ROOT-PATH", 2, 3).unwrap();
    assert_eq!(m.kept_count(), 2 * 147 + 2 * 6 + 3);
    m.keep_joint_list("root,left_wrist,0", 3, 4).unwrap();
    // Frame 3: translation, pelvis 3..9 and L_Wrist (20) 123..129.
    let kept: Vec<usize> = (0..147).filter(|&c| m.flags()[3 * 147 + c]).collect();
    let want: Vec<usize> = (0..9).chain(123..129).collect();
    assert_eq!(kept, want);
    m.keep_all();
    assert!(m.is_full() && m.last_kept_frame() == Some(5));

    let flags: Vec<u8> = (0..2 * 263).map(|i| (i % 263 == 5) as u8).collect();
    let m = Mask::from_flags(HML, 2, &flags).unwrap();
    assert_eq!(m.kept_count(), 2);
    assert!(m.flags()[5] && m.flags()[263 + 5]);
}

#[test]
fn bad_mask_input_is_an_error() {
    let mut m = Mask::new(SMPL, 6).unwrap();
    let expect = |r: flame::Result<()>, text: &str| {
        let e = r.unwrap_err().to_string();
        assert!(e.contains(text), "`{e}` lacks `{text}`");
    };
    expect(m.keep_frames(3, 3), "empty range");
    expect(m.keep_frames(0, 7), "run past the motion's 6 frames");
    expect(
        m.keep_channels(&[0, 147], 0, 6),
        "channel 147 does not exist",
    );
    expect(m.keep_joint(24, 0, 6), "joint 24 does not exist");
    expect(m.keep_joint_named("tail", 0, 6), "unknown joint `tail`");
    expect(m.keep_joint_list("0,,1", 0, 6), "empty joint");
    assert!(m.is_empty(), "failed calls must not set anything");
    let mut h = Mask::new(HML, 2).unwrap();
    expect(
        h.keep_joint_named("L_Hand", 0, 2),
        "does not exist in humanml263",
    );
    let e = Mask::from_flags(SMPL, 2, &[0; 10]).unwrap_err().to_string();
    assert!(e.contains("mask holds 10 flags"), "{e}");
    let mut flags = vec![0u8; 147];
    flags[40] = 2;
    let e = Mask::from_flags(SMPL, 1, &flags).unwrap_err().to_string();
    assert!(e.contains("frame 0, channel 40 is 2"), "{e}");
    assert!(Mask::new(SMPL, usize::MAX).is_err());
}

#[test]
fn cli_lists_parse() {
    assert_eq!(
        parse_frame_ranges("0:10, 20:", 30).unwrap(),
        vec![(0, 10), (20, 30)]
    );
    assert_eq!(
        parse_frame_ranges(":5,-5:,7", 30).unwrap(),
        vec![(0, 5), (25, 30), (7, 8)]
    );
    for (bad, text) in [
        ("5:3", "empty range"),
        ("0:31", "31 is outside a motion of 30 frames"),
        ("a:4", "`a` is not an integer"),
        ("", "empty frame range"),
        ("1:2,,3:4", "empty frame range"),
        ("-31:", "outside a motion of 30 frames"),
        ("30", "run past"),
    ] {
        let e = parse_frame_ranges(bad, 30).unwrap_err().to_string();
        assert!(e.contains(text), "`{bad}`: `{e}` lacks `{text}`");
    }
    assert_eq!(
        parse_joints("0,L_Knee,left_wrist, R_HAND", SMPL).unwrap(),
        vec![0, 4, 20, 23]
    );
    assert_eq!(parse_joints("spine3,21", HML).unwrap(), vec![9, 21]);
    let e = parse_joints("R_Hand", HML).unwrap_err().to_string();
    assert!(e.contains("(23) does not exist in humanml263"), "{e}");
    let e = parse_joints("root", SMPL).unwrap_err().to_string();
    assert!(e.contains("not a joint"), "{e}");
    assert!(parse_joints("24", SMPL).is_err());
}

// ------------------------------------------------------------------------------------------
// References from poses

/// xorshift64*, so tests are deterministic without a dependency.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    fn rotation(&mut self, max_angle: f64) -> Mat3 {
        let axis = [
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
        ];
        rotation::axis_angle(&axis, self.range(-max_angle, max_angle))
    }
}

/// `frames` of smpl24_6d features with orthonormal 6D rows: a walk-like root (SMPL's tilt, a yaw
/// and a sway, so the body stands up in the Z-up world) and joints turned by up to 100°.
fn standing_features(frames: usize, seed: u64) -> Vec<f32> {
    let mut rng = Rng(seed);
    let tilt = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
    let mut out = Vec::new();
    for _ in 0..frames {
        out.extend([
            rng.range(-2.0, 2.0) as f32,
            rng.range(-2.0, 2.0) as f32,
            rng.range(0.8, 1.0) as f32,
        ]);
        let yaw = rotation::axis_angle(&[0.0, 1.0, 0.0], rng.range(-3.1, 3.1));
        let root = rotation::mul(&tilt, &rotation::mul(&yaw, &rng.rotation(0.4)));
        out.extend(rotation::to_6d_rows(&root).map(|x| x as f32));
        for _ in 1..24 {
            out.extend(rotation::to_6d_rows(&rng.rotation(1.75)).map(|x| x as f32));
        }
    }
    out
}

fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let (i, err) = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .enumerate()
        .fold((0, 0.0f32), |m, (i, e)| if e > m.1 { (i, e) } else { m });
    assert!(
        err <= tol,
        "{what}: value {i} (frame {}, channel {}) off by {err:e}: {} vs {}",
        i / 147,
        i % 147,
        got[i],
        want[i]
    );
}

const ROTATION_LAYOUTS: [Layout; 4] = [
    Layout::LocalMatrix,
    Layout::Local6d,
    Layout::LocalQuatXyzw,
    Layout::LocalQuatWxyz,
];

#[test]
fn poses_read_out_in_any_convention_give_the_features_back() {
    let frames = 7;
    let features = standing_features(frames, 0x9e37_79b9_7f4a_7c15);
    let poses = Poses::decode(SMPL, &features, frames, &ReadOptions::default()).unwrap();
    for c in Convention::ALL {
        let root = poses.layout(Layout::RootTranslation, c).unwrap();
        for layout in ROTATION_LAYOUTS {
            let rot = poses.layout(layout, c).unwrap();
            let back = reference::smpl24_features(&root, &rot, layout, c, frames).unwrap();
            assert_close(&format!("{c} {layout}"), &back, &features, 1e-5);
        }
    }
}

#[test]
fn non_unit_quaternions_are_normalised() {
    let features = standing_features(2, 7);
    let poses = Poses::decode(SMPL, &features, 2, &ReadOptions::default()).unwrap();
    let root = poses
        .layout(Layout::RootTranslation, Convention::Unity)
        .unwrap();
    let q: Vec<f32> = poses
        .layout(Layout::LocalQuatWxyz, Convention::Unity)
        .unwrap()
        .iter()
        .map(|x| 3.0 * x)
        .collect();
    let back =
        reference::smpl24_features(&root, &q, Layout::LocalQuatWxyz, Convention::Unity, 2).unwrap();
    assert_close("3·q", &back, &features, 1e-5);
}

#[test]
fn bad_references_are_errors() {
    let (root, eye) = (
        vec![0.0f32; 6],
        (0..48)
            .flat_map(|_| [1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0])
            .collect::<Vec<_>>(),
    );
    let c = Convention::Native;
    let expect = |r: flame::Result<Vec<f32>>, text: &str| {
        let e = r.unwrap_err().to_string();
        assert!(e.contains(text), "`{e}` lacks `{text}`");
    };
    expect(
        reference::smpl24_features(&root, &eye, Layout::GlobalPositions, c, 2),
        "must be a local layout",
    );
    expect(
        reference::smpl24_features(&root[..5], &eye, Layout::Local6d, c, 2),
        "reference root holds 5 values; 2 frames need 6",
    );
    expect(
        reference::smpl24_features(&root, &eye[..100], Layout::Local6d, c, 2),
        "reference rotations holds 100 values",
    );
    expect(
        reference::smpl24_features(&[], &[], Layout::Local6d, c, 0),
        "at least one frame",
    );
    let mut nan = eye.clone();
    nan[150] = f32::NAN;
    expect(
        reference::smpl24_features(&root, &nan, Layout::Local6d, c, 2),
        "not finite at frame 1, item 1",
    );
    let mut parallel = eye.clone();
    parallel[6 * 30 + 3..6 * 30 + 6].copy_from_slice(&[2.0, 0.0, 0.0]);
    expect(
        reference::smpl24_features(&root, &parallel, Layout::Local6d, c, 2),
        "frame 1, joint 6 (Spine2): its two 6D rows are zero or parallel",
    );
}

// ------------------------------------------------------------------------------------------
// BVH references

fn bvh_text(features: &[f32], frames: usize, c: Convention, fps: f32) -> String {
    let poses = Poses::decode(SMPL, features, frames, &ReadOptions::default()).unwrap();
    bvh::to_string(&poses, c, fps).unwrap()
}

#[test]
fn bvh_written_in_any_convention_reads_back_as_the_features() {
    let frames = 5;
    let features = standing_features(frames, 42);
    for c in Convention::ALL {
        let text = bvh_text(&features, frames, c, 20.0);
        let parsed = bvh::parse(&text).unwrap();
        assert_eq!(parsed.joints().len(), 24);
        assert_eq!(parsed.channel_count(), 6 + 23 * 3);
        let (back, n, conv, fps) = bvh::to_features(&parsed, SMPL).unwrap();
        assert_eq!((n, conv, fps), (frames, c, 20.0), "{c}");
        assert_close(&format!("bvh {c}"), &back, &features, 2e-5);
        let forced = bvh::to_features_in(&parsed, SMPL, c).unwrap();
        assert_eq!(forced, back);
    }
}

#[test]
fn bvh_frame_rate_survives_six_decimals() {
    let features = standing_features(2, 3);
    for fps in [30.0f32, 60.0, 120.0, 12.5] {
        let text = bvh_text(&features, 2, Convention::Gltf, fps);
        assert_eq!(bvh::parse(&text).unwrap().fps(), fps);
    }
}

#[test]
fn bvh_names_are_matched_case_insensitively_and_conventions_are_checked() {
    let features = standing_features(2, 11);
    let text = bvh_text(&features, 2, Convention::Ros, 20.0)
        .replace("L_Knee", "l_knee")
        .replace("Pelvis", "PELVIS");
    let parsed = bvh::parse(&text).unwrap();
    let (back, _, conv, _) = bvh::to_features(&parsed, SMPL).unwrap();
    assert_eq!(conv, Convention::Ros);
    assert_close("ros", &back, &features, 2e-5);
    let e = bvh::to_features_in(&parsed, SMPL, Convention::Blender)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not SMPL-24's in the blender convention"), "{e}");
    let e = bvh::to_features(&parsed, HML).unwrap_err().to_string();
    assert!(e.contains("BVH references need a smpl24_6d model"), "{e}");
}

/// The writer's text for 2 frames in glTF, with `edit` applied.
fn broken(edit: impl Fn(String) -> String) -> String {
    let e = bvh::parse(&edit(bvh_text(
        &standing_features(2, 5),
        2,
        Convention::Gltf,
        20.0,
    )))
    .and_then(|b| bvh::to_features(&b, SMPL).map(|_| ()));
    e.unwrap_err().to_string()
}

#[test]
fn malformed_bvh_is_an_error_with_a_line() {
    let cases: Vec<(&str, String)> = vec![
        (
            "no MOTION section",
            broken(|t| t.replace("MOTION", "MOTON")),
        ),
        (
            "file ends after 1 of the 2 frames",
            broken(|t| {
                let mut lines: Vec<&str> = t.lines().collect();
                lines.pop();
                lines.join("\n")
            }),
        ),
        (
            "has 77 values; the hierarchy declares 75 channels",
            broken(|t| t.trim_end().to_string() + " 1.0 2.0"),
        ),
        (
            "`abc` is not a finite number",
            broken(|t| t.replace("Frame Time: 0.050000\n", "Frame Time: 0.050000\nabc ")),
        ),
        (
            "joint `L_Knees` is not an SMPL-24 joint",
            broken(|t| t.replace("JOINT L_Knee", "JOINT L_Knees")),
        ),
        (
            "joint `R_Hip` appears twice",
            broken(|t| t.replace("JOINT L_Hip", "JOINT R_Hip")),
        ),
        (
            "more frame lines than the 1 declared",
            broken(|t| t.replace("Frames: 2", "Frames: 1")),
        ),
        (
            "file ends after 2 of the 18446744073709551615 frames",
            broken(|t| t.replace("Frames: 2", "Frames: 18446744073709551615")),
        ),
        (
            "unknown channel `Wrotation`",
            broken(|t| t.replacen("Zrotation", "Wrotation", 1)),
        ),
        (
            "`inf` is not a finite number",
            broken(|t| t.replacen("OFFSET 0.000000", "OFFSET inf", 1)),
        ),
        (
            "libflame reads exactly 3 X/Y/Z rotations",
            broken(|t| {
                t.replacen(
                    "CHANNELS 3 Zrotation Xrotation Yrotation",
                    "CHANNELS 3 Xposition Xrotation Yrotation",
                    1,
                )
            }),
        ),
        (
            "Frame Time must be positive",
            broken(|t| t.replace("0.050000", "0")),
        ),
        (
            "MOTION before joint",
            broken(|t| {
                let i = t.find("MOTION").unwrap();
                let j = t[..i].trim_end().rfind('}').unwrap();
                format!("{}{}", &t[..j], &t[j + 1..])
            }),
        ),
        (
            "match SMPL-24's rest skeleton in no convention",
            broken(|t| t.replacen("OFFSET 0.0", "OFFSET 0.5", 2)),
        ),
    ];
    for (want, got) in cases {
        assert!(got.contains(want), "`{got}` lacks `{want}`");
    }
    let e = bvh::parse("HIERARCHY\nROOT Pelvis\n{\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("no MOTION section"), "{e}");
    let e = bvh::parse("HIERARCHY\n}\nMOTION\nFrames: 0\nFrame Time: 0.05\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("BVH line 2: `}` without an open block"), "{e}");
}

#[test]
fn bvh_joints_are_matched_by_name_not_position() {
    // The writer's depth-first order is not SMPL's index order: L_Knee (SMPL joint 4) is the
    // file's third joint, hanging from the file's second (L_Hip).
    let parsed = bvh::parse(&bvh_text(
        &standing_features(1, 9),
        1,
        Convention::Unity,
        20.0,
    ))
    .unwrap();
    assert_eq!(parsed.joints()[2].name(), "L_Knee");
    assert_eq!(parsed.joints()[2].parent(), Some(1));
    assert!(bvh::to_features(&parsed, SMPL).is_ok());
}

#[test]
fn truncating_a_bvh_anywhere_never_panics() {
    let text = bvh_text(&standing_features(2, 13), 2, Convention::Unreal, 20.0);
    let mut ok = 0;
    for (cut, _) in text.char_indices().step_by(7) {
        if let Ok(b) = bvh::parse(&text[..cut]) {
            ok += 1;
            let _ = bvh::to_features(&b, SMPL);
        }
    }
    // Only a cut inside the last value of the last frame leaves a complete-looking file (the
    // value shortened); with a step of 7 characters at most 2 cuts land there.
    assert!(ok <= 2, "{ok} truncated files parsed");
}
