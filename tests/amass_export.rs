//! AMASS `.npz` export (`flame::motion::amass`, `flame --out x.npz`), checked from the bytes:
//! the archive is read back by a reader written here from PKWARE's APPNOTE (central directory,
//! local headers, CRC-32) and NumPy's `.npy` format, the keys, dtypes and shapes compared with
//! AMASS's (nghorbani/amass; docs/official/robots.md#amass-files), and the written axis-angles
//! composed with SMPL's
//! forward kinematics on libflame's skeleton in AMASS's Z-up world must give back libflame's
//! joint positions within 1e-5 m (`smpl24_6d`). Then NumPy reads the same files
//! (tests/amass_numpy.py: `np.load`, dtypes, shapes, and its own forward kinematics from
//! the offset table of docs/official/smpl.md#rest-offsets) when a Python with NumPy is there.
//!
//! `humanml263`: a demo motion is turned into HumanML3D features the way HumanML3D builds them
//! from SMPL joints (facing frame, root velocities, `ric` positions, per-chain IK rotations of
//! `t2m_raw_offsets` onto the bones: EricGuo5513/HumanML3D `motion_representation.ipynb`,
//! `common/skeleton.py` `inverse_kinematics_np`), decoded, exported, and the distance of the
//! file's forward kinematics from the decoded positions measured (docs/amass.md quotes it).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

mod common;

use flame::models::Model;
use flame::motion::amass::{self, Amass, AmassLayout};
use flame::motion::rotation::{self, Mat3, Vec3};
use flame::motion::{ik, Convention, Finish, Format, Poses, ReadOptions, Skeleton};
use flame::session::{Sampler, Session, SessionParams};

const TOL: f64 = 1e-5;

// ---- a reader of the archive, from the format documents ---------------------------------

struct Member {
    descr: String,
    shape: Vec<usize>,
    data: Vec<u8>,
}

fn u16_at(b: &[u8], i: usize) -> usize {
    u16::from_le_bytes([b[i], b[i + 1]]) as usize
}

fn u32_at(b: &[u8], i: usize) -> usize {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]) as usize
}

/// The members of a stored (uncompressed) ZIP archive of `.npy` files, keyed without `.npy`,
/// with each member's CRC-32 and both copies of its sizes checked.
fn read_npz(b: &[u8]) -> BTreeMap<String, Member> {
    let end = b.len() - 22;
    assert_eq!(u32_at(b, end), 0x0605_4b50, "end of central directory");
    let (count, cd_len, mut at) = (
        u16_at(b, end + 10),
        u32_at(b, end + 12),
        u32_at(b, end + 16),
    );
    assert_eq!(
        at + cd_len,
        end,
        "the central directory ends where the end record starts"
    );
    let mut out = BTreeMap::new();
    for _ in 0..count {
        assert_eq!(u32_at(b, at), 0x0201_4b50);
        assert_eq!(u16_at(b, at + 10), 0, "stored");
        let (crc, size, usize_) = (u32_at(b, at + 16), u32_at(b, at + 20), u32_at(b, at + 24));
        assert_eq!(size, usize_);
        let name_len = u16_at(b, at + 28);
        let name = std::str::from_utf8(&b[at + 46..at + 46 + name_len]).unwrap();
        let local = u32_at(b, at + 42);
        assert_eq!(u32_at(b, local), 0x0403_4b50);
        assert_eq!(u32_at(b, local + 14), crc);
        assert_eq!(&b[local + 30..local + 30 + name_len], name.as_bytes());
        let start = local + 30 + name_len + u16_at(b, local + 28);
        let npy = &b[start..start + size];
        assert_eq!(crc32fast::hash(npy) as usize, crc, "{name}: CRC-32");
        let key = name.strip_suffix(".npy").expect("members are .npy files");
        out.insert(key.to_string(), parse_npy(npy));
        at += 46 + name_len + u16_at(b, at + 30) + u16_at(b, at + 32);
    }
    out
}

/// A version 1.0 `.npy`: magic, header length, the header dict, the data.
fn parse_npy(b: &[u8]) -> Member {
    assert_eq!(&b[..8], b"\x93NUMPY\x01\x00");
    let len = u16_at(b, 8);
    assert_eq!((10 + len) % 64, 0, "data aligned as NumPy writes it");
    let header = std::str::from_utf8(&b[10..10 + len]).unwrap();
    let field = |key: &str| {
        let i = header.find(&format!("'{key}': ")).unwrap() + key.len() + 4;
        &header[i..]
    };
    let descr = field("descr")[1..].split('\'').next().unwrap().to_string();
    assert!(field("fortran_order").starts_with("False"));
    let dims = field("shape")[1..].split(')').next().unwrap();
    let shape = dims
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().unwrap())
        .collect();
    Member {
        descr,
        shape,
        data: b[10 + len..].to_vec(),
    }
}

impl Member {
    fn f64s(&self) -> Vec<f64> {
        assert_eq!(self.descr, "<f8");
        let n: usize = self.shape.iter().product();
        assert_eq!(self.data.len(), n * 8);
        self.data
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect()
    }

    fn text(&self) -> String {
        assert!(self.descr.starts_with("<U") && self.shape.is_empty());
        let s: String = self
            .data
            .chunks_exact(4)
            .map(|c| char::from_u32(u32::from_le_bytes(c.try_into().unwrap())).unwrap())
            .collect();
        s.trim_end_matches('\0').to_string()
    }
}

// ---- motions --------------------------------------------------------------------------------

/// A smooth synthetic `smpl24_6d` motion (root travelling and turning, every joint rotating)
/// that needs no model: features whose 6D rows are exact rotations.
fn synthetic_smpl(frames: usize) -> Vec<f32> {
    let mut x = Vec::with_capacity(frames * 147);
    for t in 0..frames {
        let s = t as f64 / 20.0;
        x.extend([0.4 * s, -0.8 * s, 0.05 * (3.0 * s).sin()].map(|v| v as f32));
        for j in 0..24 {
            let k = j as f64;
            let r = if j == 0 {
                // Standing up in the Z-up world (+90° about X) and turning about Z.
                rotation::mul(
                    &rotation::axis_angle(&[0.0, 0.0, 1.0], 0.7 * s),
                    &rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2),
                )
            } else {
                let axis = [(k * 0.7).sin(), (k * 1.3).cos(), 0.5 + (k * 0.3).sin()];
                rotation::axis_angle(&axis, 0.6 * (2.0 * s + k).sin())
            };
            x.extend(rotation::to_6d_rows(&r).map(|v| v as f32));
        }
    }
    x
}

/// The demo model's motion for `prompt` (`frames` frames, DDIM 10 steps), or None when the demo
/// model is not there (the caller skips).
fn demo_features(prompt: &str, frames: usize) -> Option<(Arc<Model>, Vec<f32>)> {
    let path = common::demo_model()?;
    let model = Arc::new(Model::load(&path).unwrap());
    let params = SessionParams {
        frames: Some(frames),
        steps: Some(10),
        sampler: Some(Sampler::Ddim),
        seed: 0,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(&model), &params).unwrap();
    s.set_prompt(prompt).unwrap();
    while s.step().unwrap() > 0 {}
    let x = s.sample().unwrap().to_vec();
    Some((model, x))
}

fn decode(format: Format, x: &[f32], opts: &ReadOptions) -> Poses {
    Poses::decode(format, x, x.len() / format.feature_dim(), opts).unwrap()
}

/// libflame's joint positions of `poses` (the first 22) in the AMASS world, a `separate` root
/// motion's travel put back on.
fn amass_positions(poses: &Poses) -> Vec<Vec3> {
    let w = amass::world_change(poses.format());
    let joints = poses.joint_count();
    let native = poses.positions(Convention::Native);
    let root_bone = poses
        .layout(flame::motion::Layout::RootBone, Convention::Native)
        .ok();
    (0..poses.frames())
        .flat_map(|t| {
            let travel = root_bone
                .as_ref()
                .map_or([0.0; 3], |b| [0, 1, 2].map(|k| b[t * 3 + k] as f64));
            native[t * joints..t * joints + 22]
                .iter()
                .map(move |p| rotation::apply(&w, &rotation::add(p, &travel)))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// SMPL forward kinematics of a file's `root_orient`, `pose_body` and `trans` on libflame's
/// skeleton, written here apart from the library's: the pelvis at `trans + J_pelvis`, world
/// rotations composed from the root, `p(j) = p(parent) + G(parent)·offset(j)`.
fn file_fk(root_orient: &[f64], pose_body: &[f64], trans: &[f64]) -> Vec<Vec3> {
    let skel = Skeleton::smpl24();
    let o = skel.rest_offsets();
    let rot = |v: &[f64]| -> Mat3 {
        let a = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if a == 0.0 {
            rotation::IDENTITY
        } else {
            rotation::axis_angle(&[v[0], v[1], v[2]], a)
        }
    };
    let frames = trans.len() / 3;
    let mut out = Vec::with_capacity(frames * 22);
    for t in 0..frames {
        let mut g = vec![rot(&root_orient[t * 3..t * 3 + 3])];
        let mut p = vec![rotation::add(
            &[trans[t * 3], trans[t * 3 + 1], trans[t * 3 + 2]],
            &o[0],
        )];
        for j in 1..22 {
            let parent = skel.parent(j).unwrap();
            let local = rot(&pose_body[t * 63 + (j - 1) * 3..][..3]);
            p.push(rotation::add(
                &p[parent],
                &rotation::apply(&g[parent], &o[j]),
            ));
            g.push(rotation::mul(&g[parent], &local));
        }
        out.extend(p);
    }
    out
}

fn max_distance(a: &[Vec3], b: &[Vec3]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            let d = [x[0] - y[0], x[1] - y[1], x[2] - y[2]];
            rotation::dot(&d, &d).sqrt()
        })
        .fold(0.0, f64::max)
}

/// Reads both layouts of `poses` back and checks every key, dtype, shape and value against
/// AMASS's and the forward kinematics against libflame's positions; returns the largest
/// distance of the file's forward kinematics from the positions.
fn check_files(poses: &Poses, fps: f64, what: &str) -> f64 {
    let n = poses.frames();
    let h = read_npz(&amass::to_npz(poses, fps, AmassLayout::SmplH).unwrap());
    let x = read_npz(&amass::to_npz(poses, fps, AmassLayout::SmplX).unwrap());
    let keys = |m: &BTreeMap<String, Member>| m.keys().cloned().collect::<Vec<_>>();
    assert_eq!(
        keys(&h),
        [
            "betas",
            "dmpls",
            "gender",
            "mocap_framerate",
            "poses",
            "trans"
        ]
    );
    assert_eq!(
        keys(&x),
        [
            "betas",
            "gender",
            "mocap_frame_rate",
            "mocap_time_length",
            "num_betas",
            "pose_body",
            "pose_eye",
            "pose_hand",
            "pose_jaw",
            "poses",
            "root_orient",
            "surface_model_type",
            "trans"
        ]
    );
    let shape = |m: &BTreeMap<String, Member>, k: &str| m[k].shape.clone();
    assert_eq!(shape(&h, "poses"), [n, 156]);
    assert_eq!(shape(&h, "trans"), [n, 3]);
    assert_eq!(shape(&h, "betas"), [16]);
    assert_eq!(shape(&h, "dmpls"), [n, 8]);
    assert_eq!(h["gender"].text(), "neutral");
    assert_eq!(h["mocap_framerate"].f64s(), [fps]);
    for (k, s) in [
        ("root_orient", vec![n, 3]),
        ("pose_body", vec![n, 63]),
        ("pose_hand", vec![n, 90]),
        ("pose_jaw", vec![n, 3]),
        ("pose_eye", vec![n, 6]),
        ("trans", vec![n, 3]),
        ("betas", vec![16]),
        ("poses", vec![n, 165]),
    ] {
        assert_eq!(shape(&x, k), s, "{k}");
    }
    assert_eq!(x["gender"].text(), "neutral");
    assert_eq!(x["surface_model_type"].text(), "smplx");
    assert_eq!(x["num_betas"].descr, "<i8");
    assert_eq!(x["num_betas"].data, 16i64.to_le_bytes());
    assert_eq!(x["mocap_frame_rate"].f64s(), [fps]);
    assert_eq!(x["mocap_time_length"].f64s(), [n as f64 / fps]);
    for (m, k) in [(&h, "betas"), (&h, "dmpls"), (&x, "betas")] {
        assert!(m[k].f64s().iter().all(|&v| v == 0.0), "{k}");
    }
    for k in ["pose_hand", "pose_jaw", "pose_eye"] {
        assert!(x[k].f64s().iter().all(|&v| v == 0.0), "{k}");
    }
    // The named keys and both `poses` agree: root, body, then zeros.
    let (root, body, trans) = (
        x["root_orient"].f64s(),
        x["pose_body"].f64s(),
        x["trans"].f64s(),
    );
    assert_eq!(h["trans"].f64s(), trans);
    for (poses_, width) in [(h["poses"].f64s(), 156), (x["poses"].f64s(), 165)] {
        for t in 0..n {
            let row = &poses_[t * width..(t + 1) * width];
            assert_eq!(&row[..3], &root[t * 3..t * 3 + 3]);
            assert_eq!(&row[3..66], &body[t * 63..t * 63 + 63]);
            assert!(row[66..].iter().all(|&v| v == 0.0));
        }
    }
    let fk = file_fk(&root, &body, &trans);
    let err = max_distance(&fk, &amass_positions(poses));
    println!("{what}: {n} frames at {fps} fps, file FK vs libflame positions: max {err:.2e} m");
    err
}

#[test]
fn smpl24_files_give_back_libflames_joints() {
    let x = synthetic_smpl(40);
    let raw = decode(Format::Smpl24Rot6d, &x, &ReadOptions::default());
    let err = check_files(&raw, 20.0, "synthetic smpl24_6d");
    assert!(err <= TOL, "{err}");
    // Game-ready at 30 fps with the travel on a root bone: resampled, feet locked, and the
    // pelvis's travel put back from the bone.
    let finished = decode(
        Format::Smpl24Rot6d,
        &x,
        &ReadOptions {
            finish: Finish {
                fps: Some(30.0),
                root_motion: flame::motion::RootMotion::Separate,
                ..Finish::game_ready()
            },
            ..Default::default()
        },
    );
    assert_eq!(finished.frames(), 59);
    let err = check_files(&finished, 30.0, "synthetic smpl24_6d, game-ready, 30 fps");
    assert!(err <= TOL, "{err}");
}

#[test]
fn demo_model_files_give_back_libflames_joints() {
    let Some((model, x)) = demo_features("a person walks forward and turns left.", 80) else {
        common::skip(
            "amass_export::demo_model_files_give_back_libflames_joints",
            "no demo model (run tools/try.sh or set FLAME_DEMO_MODEL)",
        );
        return;
    };
    let opts = model.read_options(1.0, true);
    let raw = decode(Format::Smpl24Rot6d, &x, &opts);
    let err = check_files(&raw, 20.0, "demo smpl24_6d");
    assert!(err <= TOL, "{err}");
    // The library's own forward kinematics of the parameters agrees with the test's.
    let a = Amass::from_poses(&raw, 20.0).unwrap();
    assert!(max_distance(&a.forward_kinematics(), &amass_positions(&raw)) <= TOL);
}

// ---- humanml263 ------------------------------------------------------------------------------

/// HumanML3D's kinematic chains (paramUtil.py `t2m_kinematic_chain`).
const CHAINS: [&[usize]; 5] = [
    &[0, 2, 5, 8, 11],
    &[0, 1, 4, 7, 10],
    &[0, 3, 6, 9, 12, 15],
    &[9, 14, 17, 19, 21],
    &[9, 13, 16, 18, 20],
];

fn ry(angle: f64) -> Mat3 {
    rotation::axis_angle(&[0.0, 1.0, 0.0], angle)
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The heading ψ (forward = (sin ψ, 0, cos ψ)) of SMPL-22 positions, Y up: HumanML3D's
/// `forward = cross(up, (r_hip − l_hip) + (r_shoulder − l_shoulder))`.
fn heading(p: &[Vec3]) -> f64 {
    let across = rotation::add(&sub(&p[2], &p[1]), &sub(&p[17], &p[16]));
    let f = rotation::cross(&[0.0, 1.0, 0.0], &across);
    f[0].atan2(f[2])
}

/// Raw (not normalised) `[frames, 263]` features of SMPL-22 positions `p` (Y up, HumanML3D's
/// frame), built as HumanML3D builds its data: the motion turned to face +Z and moved over the
/// origin at frame 0; per frame the facing rotation `r = Ry(−ψ)`, root yaw change (half, dim
/// 0), root velocity in the next frame's facing frame (1–2), root height (3), `ric` positions
/// (4–66), and per chain the IK rotations turning `t2m_raw_offsets` onto each bone, chained from
/// `r` (67–192, cont6d columns). Velocities and contacts are left at zero (not decoded into
/// positions or rotations).
fn humanml_features(p: &[Vec3], frames: usize) -> Vec<f32> {
    let psi0 = heading(&p[..22]);
    let turn = ry(-psi0);
    let start = rotation::apply(&turn, &p[0]);
    let p: Vec<Vec3> = p
        .iter()
        .map(|q| {
            let r = rotation::apply(&turn, q);
            [r[0] - start[0], r[1], r[2] - start[2]]
        })
        .collect();
    let hml = Skeleton::humanml22().rest_offsets();
    let psi: Vec<f64> = (0..frames).map(|t| heading(&p[t * 22..])).collect();
    let mut x = vec![0.0f64; frames * 263];
    for t in 0..frames {
        let q = &p[t * 22..(t + 1) * 22];
        let r = ry(-psi[t]);
        let row = &mut x[t * 263..(t + 1) * 263];
        if t + 1 < frames {
            let mut d = psi[t + 1] - psi[t];
            d = (d + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
            row[0] = -d / 2.0;
            let v = rotation::apply(&ry(-psi[t + 1]), &sub(&p[(t + 1) * 22], &q[0]));
            row[1] = v[0];
            row[2] = v[2];
        }
        row[3] = q[0][1];
        for j in 1..22 {
            let ric = rotation::apply(&r, &[q[j][0] - q[0][0], q[j][1], q[j][2] - q[0][2]]);
            row[4 + 3 * (j - 1)..][..3].copy_from_slice(&ric);
        }
        for chain in CHAINS {
            let mut acc = r;
            for pair in chain.windows(2) {
                let (a, b) = (pair[0], pair[1]);
                let onto = ik::rotate_onto(&hml[b], &sub(&q[b], &q[a]), None);
                let local = rotation::mul(&rotation::transpose(&acc), &onto);
                row[67 + 6 * (b - 1)..][..6].copy_from_slice(&rotation::to_6d_columns(&local));
                acc = onto;
            }
        }
    }
    x.into_iter().map(|v| v as f32).collect()
}

/// The forward kinematics of the features' 6D rotations alone, re-based onto SMPL's rest (step
/// 1 of `amass`'s module doc, without the fit to the positions), in the native frame.
fn rotations_only_fk(poses: &Poses) -> Vec<Vec3> {
    let smpl = Skeleton::smpl24().rest_offsets();
    let hml = Skeleton::humanml22().rest_offsets();
    let skel = Skeleton::humanml22();
    let mut next = [None; 22];
    for chain in CHAINS {
        for pair in chain[1..].windows(2) {
            next[pair[0]] = Some(pair[1]);
        }
    }
    let mut rest = [rotation::IDENTITY; 22];
    for j in 1..22 {
        rest[j] = match next[j] {
            Some(c) => ik::rotate_onto(&smpl[c], &hml[c], None),
            None => rest[skel.parent(j).unwrap()],
        };
    }
    let global = poses.global_rotations(Convention::Native);
    let pos = poses.positions(Convention::Native);
    let mut out = Vec::new();
    for t in 0..poses.frames() {
        let g: Vec<Mat3> = (0..22)
            .map(|j| rotation::mul(&global[t * 22 + j], &rest[j]))
            .collect();
        let mut p = vec![pos[t * 22]];
        for (j, offset) in smpl.iter().enumerate().take(22).skip(1) {
            let parent = skel.parent(j).unwrap();
            p.push(rotation::add(
                &p[parent],
                &rotation::apply(&g[parent], offset),
            ));
        }
        out.extend(p);
    }
    out
}

#[test]
fn humanml_files_follow_the_decoded_positions() {
    // A demo motion when the model is there, else the synthetic one: its SMPL joints in Y-up
    // axes (libflame's gltf convention: Y up, +Z forward, +X left, HumanML3D's own).
    let (x, source) = match demo_features("a person walks forward and waves.", 100) {
        Some((_, x)) => (x, "demo"),
        None => {
            common::skip(
                "amass_export::humanml_files_follow_the_decoded_positions (demo part)",
                "no demo model: measured on the synthetic motion only",
            );
            (synthetic_smpl(60), "synthetic")
        }
    };
    let smpl = decode(Format::Smpl24Rot6d, &x, &ReadOptions::default());
    let frames = smpl.frames();
    let yup: Vec<Vec3> = smpl
        .positions(Convention::Gltf)
        .chunks_exact(24)
        .flat_map(|j| j[..22].to_vec())
        .collect();
    let features = humanml_features(&yup, frames);
    let hml = decode(Format::HumanMl263, &features, &ReadOptions::default());
    // The encoding is faithful: decoding gives the positions back (up to f32 features).
    let native = hml.positions(Convention::Native);
    let turned = {
        let psi0 = heading(&yup[..22]);
        let s = rotation::apply(&ry(-psi0), &yup[0]);
        yup.iter()
            .map(|q| {
                let r = rotation::apply(&ry(-psi0), q);
                [r[0] - s[0], r[1], r[2] - s[2]]
            })
            .collect::<Vec<_>>()
    };
    let enc = max_distance(&native, &turned);
    println!("{source}: HumanML3D features decode to the SMPL joints within {enc:.2e} m");
    assert!(enc < 1e-4, "{enc}");

    let err = check_files(&hml, 20.0, &format!("{source} as humanml263"));
    let w = amass::world_change(Format::HumanMl263);
    let rot_only: Vec<Vec3> = rotations_only_fk(&hml)
        .iter()
        .map(|p| rotation::apply(&w, p))
        .collect();
    let err6d = max_distance(&rot_only, &amass_positions(&hml));
    println!(
        "{source} as humanml263: the 6D rotations alone on SMPL's rest put joints up to \
         {err6d:.3} m from the decoded positions; the written file (fitted) {err:.2e} m"
    );
    // Same bone lengths on both sides (SMPL's), so the fitted file is exact up to f32 features.
    assert!(err < 1e-4, "{err}");
    assert!(err6d > err);

    // A generated skeleton is not SMPL's neutral one: the same motion on a body 5% larger
    // (every bone 5% longer) shows what the differences of bone lengths cost.
    let larger: Vec<Vec3> = yup.iter().map(|p| p.map(|v| 1.05 * v)).collect();
    let hml = decode(
        Format::HumanMl263,
        &humanml_features(&larger, frames),
        &ReadOptions::default(),
    );
    let err = check_files(
        &hml,
        20.0,
        &format!("{source} as humanml263, body 5% larger"),
    );
    println!("{source} as humanml263 on a body 5% larger: the file's joints up to {err:.3} m off");
    assert!(err < 0.1, "{err}");
}

// ---- the NumPy check, the CLI and refusals --------------------------------------------------

/// Python with NumPy: `$FLAME_TEST_PYTHON`, else tools/check.sh's virtual environment.
fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FLAME_TEST_PYTHON") {
        return Some(p.into());
    }
    let venv = common::repo("target/test-venv/bin/python");
    venv.is_file().then_some(venv)
}

fn scratch(name: &str) -> PathBuf {
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("amass_{name}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn numpy_loads_the_files_and_its_forward_kinematics_agree() {
    const TEST: &str = "amass_export::numpy_loads_the_files_and_its_forward_kinematics_agree";
    let Some(python) = python() else {
        common::skip(
            TEST,
            "no Python with NumPy (set FLAME_TEST_PYTHON or run tools/check.sh, which makes \
             target/test-venv)",
        );
        return;
    };
    let dir = scratch("numpy");
    let x = synthetic_smpl(30);
    let mut cases = vec![(
        "synthetic",
        decode(Format::Smpl24Rot6d, &x, &ReadOptions::default()),
    )];
    if let Some((model, x)) = demo_features("a person jumps twice.", 60) {
        cases.push((
            "demo",
            decode(Format::Smpl24Rot6d, &x, &model.read_options(1.0, true)),
        ));
    }
    for (name, poses) in &cases {
        let fps = 20.0;
        for layout in AmassLayout::ALL {
            let bytes = amass::to_npz(poses, fps, layout).unwrap();
            std::fs::write(dir.join(format!("{name}_{layout}.npz")), bytes).unwrap();
        }
        let pos: Vec<f32> = amass_positions(poses)
            .iter()
            .flatten()
            .map(|&v| v as f32)
            .collect();
        flame::npy::write_f32(
            &dir.join(format!("{name}_positions.npy")),
            &[poses.frames(), 22, 3],
            &pos,
        )
        .unwrap();
        let out = Command::new(&python)
            .arg(common::repo("tests/amass_numpy.py"))
            .arg(dir.join(format!("{name}_smplh.npz")))
            .arg(dir.join(format!("{name}_smplx.npz")))
            .arg(dir.join(format!("{name}_positions.npy")))
            .args(["--fps", "20", "--frames", &poses.frames().to_string()])
            .output()
            .expect("run python");
        let text = String::from_utf8_lossy(&out.stdout);
        println!("{name}: {text}{}", String::from_utf8_lossy(&out.stderr));
        assert!(
            out.status.success(),
            "tests/amass_numpy.py failed on {name}"
        );
        assert!(text.contains("numpy fk max error"), "{text}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

fn flame_cli(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn the_cli_writes_both_layouts_and_refuses_bad_input() {
    let dir = scratch("cli");
    let model = common::repo("tests/fixtures/flame_tiny.safetensors");
    let model = model.to_str().unwrap();
    let features = dir.join("x.npy");
    let x = synthetic_smpl(20);
    flame::npy::write_f32(&features, &[20, 147], &x).unwrap();
    let (npy, h, xz) = (
        features.to_str().unwrap(),
        dir.join("h.npz"),
        dir.join("x.NPZ"),
    );
    let run = |extra: &[&str], out: &Path| {
        let mut args = vec!["retarget", "--in", npy, "--model", model, "--feet", "off"];
        args.extend(extra);
        args.extend(["--out", out.to_str().unwrap()]);
        flame_cli(&args)
    };
    let o = run(&["--fps", "30"], &h);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let files = read_npz(&std::fs::read(&h).unwrap());
    assert_eq!(files["poses"].shape, [29, 156]);
    assert_eq!(files["mocap_framerate"].f64s(), [30.0]);
    let o = run(&["--amass", "smplx"], &xz);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let files = read_npz(&std::fs::read(&xz).unwrap());
    assert_eq!(files["pose_body"].shape, [20, 63]);
    // The same poses as the library's (the CLI's pose options: feet off, no smoothing for
    // a BVH-free .npy input is the model's default σ; compare against that decode).
    let model_ = Model::load(model).unwrap();
    let opts = ReadOptions {
        finish: Finish {
            ground: false,
            ..Finish::default()
        },
        ..model_.read_options(1.0, true)
    };
    let poses = decode(Format::Smpl24Rot6d, &x, &opts);
    let want = Amass::from_poses(&poses, 20.0).unwrap();
    let got = files["pose_body"].f64s();
    let want: Vec<f64> = want.pose_body.iter().flatten().copied().collect();
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(worst < 1e-9, "{worst}");

    // Refusals: --amass without .npz, an unknown layout, NaN features, a .npy meaning features.
    let o = run(&["--amass", "smplx"], &dir.join("y.bvh"));
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("--amass"),
        "{o:?}"
    );
    let o = run(&["--amass", "smpl"], &h);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected smplh or smplx"));
    let mut nan = x.clone();
    nan[147 * 3 + 10] = f32::NAN;
    flame::npy::write_f32(&features, &[20, 147], &nan).unwrap();
    let o = run(&[], &h);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("not finite at frame 3"), "{err}");
    let o = flame_cli(&[
        "generate", "--model", model, "--prompt", "x", "--out", "a.npq",
    ]);
    assert!(String::from_utf8_lossy(&o.stderr).contains(".npz"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn empty_and_non_finite_motions_are_refused() {
    let none = Poses::decode(Format::Smpl24Rot6d, &[], 0, &ReadOptions::default()).unwrap();
    for layout in AmassLayout::ALL {
        let e = amass::to_npz(&none, 20.0, layout).unwrap_err().to_string();
        assert!(e.contains("at least one frame"), "{e}");
    }
    let poses = decode(
        Format::Smpl24Rot6d,
        &synthetic_smpl(3),
        &ReadOptions::default(),
    );
    let e = amass::to_npz(&poses, f64::NAN, AmassLayout::SmplH)
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame rate"), "{e}");
    // NaN features never become poses: the decoder names the frame and channel.
    let mut x = synthetic_smpl(3);
    x[147 + 4] = f32::NAN;
    let e = Poses::decode(Format::Smpl24Rot6d, &x, 3, &ReadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("not finite at frame 1, channel 4"), "{e}");
}
