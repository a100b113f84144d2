//! Every convention preset on a pose worked out by hand: the character stands in its rest pose,
//! turned 90° to its LEFT, root at (1, 2, 3) in the format's native frame; for smpl24_6d the
//! left elbow is also bent so the forearm points forward.
//!
//! How the expected numbers were derived. A convention says where the character's up (U),
//! forward (F) and left (L) point. Turning 90° left sends the body's forward to the world's left
//! and the body's left to the world's back, so a joint whose rest offset from the root is
//! (x = left, y = up, z = forward) in the body frame lands at
//!     root + y·U + (−x)·F + z·L.
//! Writing a point as (up, fwd, left) components, each preset's coordinates are
//!     unity (U=+Y, F=+Z, L=−X):           (−left, up, fwd)
//!     unreal (U=+Z, F=+X, L=−Y, cm):      100·(fwd, −left, up)
//!     ros (U=+Z, F=+X, L=+Y):             (fwd, left, up)
//!     blender (U=+Z, F=−Y, L=+X):         (left, −fwd, up)
//!     gltf (U=+Y, F=+Z, L=+X):            (left, up, fwd)
//!     native smpl24_6d (U=+Z, F=−Y, L=+X): (left, −fwd, up);  native humanml263 = gltf.
//! The turn is +90° about up in a right-handed frame and −90° in a left-handed one (a left turn
//! is counter-clockwise seen from above): unity Ry(−90°), unreal Rz(−90°), ros and blender
//! Rz(+90°), gltf Ry(+90°). As quaternions (x, y, z, w) with h = √½: Ry(±90°) = (0, ±h, 0, h),
//! Rz(±90°) = (0, 0, ±h, h).

use flame::motion::{rotation, Convention, Format, Layout, Poses, ReadOptions};

const H: f64 = std::f64::consts::FRAC_1_SQRT_2;
const TOL: f64 = 1e-6;

struct Expected {
    convention: Convention,
    root: [f64; 3],
    head: [f64; 3],
    left_wrist: [f64; 3],
    /// The root's local (= world) rotation, x y z w.
    root_q: [f64; 4],
    /// smpl24_6d only: the left elbow's local rotation, x y z w.
    elbow_q: [f64; 4],
    /// The left wrist's world rotation, x y z w.
    wrist_global_q: [f64; 4],
}

fn assert_close(what: &str, got: &[f64], want: &[f64]) {
    for (g, w) in got.iter().zip(want) {
        assert!(
            (g - w).abs() < TOL * w.abs().max(1.0),
            "{what}: got {got:?}, want {want:?}"
        );
    }
}

fn check(poses: &Poses, e: &Expected, joints: (usize, usize, usize)) {
    let c = e.convention;
    let (head, elbow, wrist) = joints;
    let p = poses.positions(c);
    let n = poses.joint_count();
    let last = (poses.frames() - 1) * n;
    assert_close(
        &format!("{c} root"),
        &poses.root_translation(c)[poses.frames() - 1],
        &e.root,
    );
    assert_close(&format!("{c} root joint"), &p[last], &e.root);
    assert_close(&format!("{c} head"), &p[last + head], &e.head);
    assert_close(&format!("{c} left wrist"), &p[last + wrist], &e.left_wrist);
    let xyzw = |q: &[f64; 4]| [q[1], q[2], q[3], q[0]];
    let local = poses.quaternions(&poses.local_rotations(c));
    assert_close(
        &format!("{c} root rotation"),
        &xyzw(&local[last]),
        &e.root_q,
    );
    assert_close(
        &format!("{c} elbow rotation"),
        &xyzw(&local[last + elbow]),
        &e.elbow_q,
    );
    let global = poses.quaternions(&poses.global_rotations(c));
    assert_close(
        &format!("{c} wrist world rotation"),
        &xyzw(&global[last + wrist]),
        &e.wrist_global_q,
    );
    // The f32 layouts carry the same numbers.
    let lay = poses.layout(Layout::LocalQuatXyzw, c).unwrap();
    let lay_root: Vec<f64> = lay[last * 4..last * 4 + 4]
        .iter()
        .map(|&v| v as f64)
        .collect();
    assert_close(&format!("{c} layout root rotation"), &lay_root, &e.root_q);
}

/// smpl24_6d features for one frame: translation (1, 2, 3); root = Rz(+90°)·Rx(+90°) (the
/// tilt that stands SMPL's Y-up body in the Z-up world, then a left turn about world up); left
/// elbow (18) = Ry(−90°) in the body frame, which sends the forearm from the body's left (+X)
/// to its front (+Z); everything else identity.
fn smpl_features() -> Vec<f32> {
    let half_pi = std::f64::consts::FRAC_PI_2;
    let mut f = vec![0.0f32; 147];
    f[..3].copy_from_slice(&[1.0, 2.0, 3.0]);
    for j in 0..24 {
        let r = match j {
            0 => rotation::mul(
                &rotation::axis_angle(&[0.0, 0.0, 1.0], half_pi),
                &rotation::axis_angle(&[1.0, 0.0, 0.0], half_pi),
            ),
            18 => rotation::axis_angle(&[0.0, 1.0, 0.0], -half_pi),
            _ => rotation::IDENTITY,
        };
        for (k, v) in rotation::to_6d_rows(&r).iter().enumerate() {
            f[3 + 6 * j + k] = *v as f32;
        }
    }
    f
}

#[test]
fn smpl24_6d_in_every_convention() {
    // Body-frame offsets from the pelvis (sums of the rows of docs/official/smpl.md#rest-offsets),
    // (left, up, forward):
    //   head (3+6+9+12+15)           = (0.00678462, 0.57590586, 0.00831267)
    //   left elbow (3+6+9+13+16+18)  = (0.43384509, 0.43651203, −0.07059347)
    //   left wrist = elbow + Ry(−90°)·offset20, Ry(−90°)(x, y, z) = (−z, y, x):
    //     + (0.00117092, 0.00898603, 0.24923363) = (0.43501601, 0.44549806, 0.17864016)
    // Pelvis = translation + rest pelvis (docs/official/smpl.md#forward-kinematics), native Z-up world:
    //   (1, 2, 3) + (−0.00179506, −0.22333345, 0.02821913) = (0.99820494, 1.77666655, 3.02821913)
    //   → (up, fwd, left) = (3.02821913, −1.77666655, 0.99820494)   [native F = −Y]
    // Head  (up, fwd, left) = (3.02821913 + 0.57590586, −1.77666655 − 0.00678462, 0.99820494 + 0.00831267)
    //                       = (3.60412499, −1.78345117, 1.00651761)
    // Wrist (up, fwd, left) = (3.02821913 + 0.44549806, −1.77666655 − 0.43501601, 0.99820494 + 0.17864016)
    //                       = (3.47371719, −2.21168256, 1.17684510)
    // Elbow: a rotation about up taking left to forward, i.e. a 90° RIGHT turn: unity Ry(+90°),
    // unreal Rz(+90°), ros and blender Rz(−90°), gltf Ry(−90°); native = the raw Ry(−90°).
    // The wrist's world rotation = left turn · right turn = identity in every preset; natively
    // Rz(90°)·Rx(90°)·Ry(−90°) = Rx(+90°) = (h, 0, 0, h): the tilt stays in native data.
    // Native root Rz(90°)·Rx(90°) = (cos45, 0, 0, sin45)⊗(cos45, sin45, 0, 0) = w 0.5, (0.5, 0.5, 0.5).
    let cases = [
        Expected {
            convention: Convention::Native,
            root: [0.99820494, 1.77666655, 3.02821913],
            head: [1.00651761, 1.78345117, 3.60412499],
            left_wrist: [1.17684510, 2.21168256, 3.47371719],
            root_q: [0.5, 0.5, 0.5, 0.5],
            elbow_q: [0.0, -H, 0.0, H],
            wrist_global_q: [H, 0.0, 0.0, H],
        },
        Expected {
            convention: Convention::Unity,
            root: [-0.99820494, 3.02821913, -1.77666655],
            head: [-1.00651761, 3.60412499, -1.78345117],
            left_wrist: [-1.17684510, 3.47371719, -2.21168256],
            root_q: [0.0, -H, 0.0, H],
            elbow_q: [0.0, H, 0.0, H],
            wrist_global_q: [0.0, 0.0, 0.0, 1.0],
        },
        Expected {
            convention: Convention::Unreal,
            root: [-177.666655, -99.820494, 302.821913],
            head: [-178.345117, -100.651761, 360.412499],
            left_wrist: [-221.168256, -117.684510, 347.371719],
            root_q: [0.0, 0.0, -H, H],
            elbow_q: [0.0, 0.0, H, H],
            wrist_global_q: [0.0, 0.0, 0.0, 1.0],
        },
        Expected {
            convention: Convention::Ros,
            root: [-1.77666655, 0.99820494, 3.02821913],
            head: [-1.78345117, 1.00651761, 3.60412499],
            left_wrist: [-2.21168256, 1.17684510, 3.47371719],
            root_q: [0.0, 0.0, H, H],
            elbow_q: [0.0, 0.0, -H, H],
            wrist_global_q: [0.0, 0.0, 0.0, 1.0],
        },
        Expected {
            convention: Convention::Blender,
            root: [0.99820494, 1.77666655, 3.02821913],
            head: [1.00651761, 1.78345117, 3.60412499],
            left_wrist: [1.17684510, 2.21168256, 3.47371719],
            root_q: [0.0, 0.0, H, H],
            elbow_q: [0.0, 0.0, -H, H],
            wrist_global_q: [0.0, 0.0, 0.0, 1.0],
        },
        Expected {
            convention: Convention::Gltf,
            root: [0.99820494, 3.02821913, -1.77666655],
            head: [1.00651761, 3.60412499, -1.78345117],
            left_wrist: [1.17684510, 3.47371719, -2.21168256],
            root_q: [0.0, H, 0.0, H],
            elbow_q: [0.0, -H, 0.0, H],
            wrist_global_q: [0.0, 0.0, 0.0, 1.0],
        },
    ];
    let poses = Poses::decode(
        Format::Smpl24Rot6d,
        &smpl_features(),
        1,
        &ReadOptions::default(),
    )
    .unwrap();
    for e in &cases {
        check(&poses, e, (15, 18, 20));
    }
}

/// humanml263 features for two frames (raw, no normalisation). Frame 1 is the pose under test:
/// - dim 0 of frame 0 = −π/4: θ[1] = −π/4, q_root = (cos θ, 0, sin θ, 0) = Ry(−90°), positions
///   use qinv(q_root) = Ry(+90°), which turns the body's +Z forward to +X, its left: a left turn;
/// - dims 1, 2 of frame 0 = (−3, 1): v = Ry(+90°)·(−3, 0, 1) = (1, 0, 3) (Ry(90°)(x,y,z) = (z, y, −x));
///   dim 3 of frame 1 = 2 (root height) → root (1, 2, 3);
/// - ric = the rest skeleton relative to the root (y absolute: + 2);
/// - cont6d: the chain product R(q_root)·R(c₁)⋯ must be the turn Ry(+90°) for every bone, so the
///   first joint of each chain (1, 2, 3, 13, 14) stores Ry(−90°)ᵀ·Ry(90°) = Ry(180°) = diag(−1, 1, −1)
///   (columns (−1,0,0), (0,1,0)) and the others identity ((1,0,0), (0,1,0)).
fn humanml_features() -> Vec<f32> {
    let skel = Format::HumanMl263.skeleton();
    let mut rest = vec![[0.0f64; 3]; 22];
    for j in 1..22 {
        let p = skel.parent(j).unwrap();
        rest[j] = rotation::add(&rest[p], &skel.rest_offsets()[j]);
    }
    let mut f = vec![0.0f32; 2 * 263];
    f[0] = -std::f32::consts::FRAC_PI_4;
    f[1] = -3.0;
    f[2] = 1.0;
    for t in 0..2 {
        let row = &mut f[t * 263..(t + 1) * 263];
        row[3] = 2.0;
        for j in 1..22 {
            let r = &rest[j];
            row[4 + 3 * (j - 1)..7 + 3 * (j - 1)].copy_from_slice(&[
                r[0] as f32,
                (r[1] + 2.0) as f32,
                r[2] as f32,
            ]);
            let first_in_chain = t == 1 && [1, 2, 3, 13, 14].contains(&j);
            let d6: [f32; 6] = if first_in_chain {
                [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            } else {
                [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            };
            row[67 + 6 * (j - 1)..73 + 6 * (j - 1)].copy_from_slice(&d6);
        }
    }
    f
}

#[test]
fn humanml263_in_every_convention() {
    // HumanML3D rest offsets (t2m directions × SMPL lengths) from the root, (left, up, forward):
    //   head (3, 6, 9, 12 up; 15 forward) = (0, 0.52438115, 0.08297173)
    //   left wrist (3, 6, 9 up; 13 left; 16, 18, 20 down) = (0.14900163, −0.30088179, 0)
    // Root (1, 2, 3) in native Y-up, +Z forward, +X left → (up, fwd, left) = (2, 3, 1).
    // Head  (up, fwd, left) = (2 + 0.52438115, 3 − 0, 1 + 0.08297173) = (2.52438115, 3, 1.08297173)
    // Wrist (up, fwd, left) = (2 − 0.30088179, 3 − 0.14900163, 1 + 0) = (1.69911821, 2.85099837, 1)
    // Every joint's world rotation is the left turn (no elbow bend here: elbow_q is identity).
    let id = [0.0, 0.0, 0.0, 1.0];
    let cases = [
        Expected {
            convention: Convention::Native,
            root: [1.0, 2.0, 3.0],
            head: [1.08297173, 2.52438115, 3.0],
            left_wrist: [1.0, 1.69911821, 2.85099837],
            root_q: [0.0, H, 0.0, H],
            elbow_q: id,
            wrist_global_q: [0.0, H, 0.0, H],
        },
        Expected {
            convention: Convention::Unity,
            root: [-1.0, 2.0, 3.0],
            head: [-1.08297173, 2.52438115, 3.0],
            left_wrist: [-1.0, 1.69911821, 2.85099837],
            root_q: [0.0, -H, 0.0, H],
            elbow_q: id,
            wrist_global_q: [0.0, -H, 0.0, H],
        },
        Expected {
            convention: Convention::Unreal,
            root: [300.0, -100.0, 200.0],
            head: [300.0, -108.297173, 252.438115],
            left_wrist: [285.099837, -100.0, 169.911821],
            root_q: [0.0, 0.0, -H, H],
            elbow_q: id,
            wrist_global_q: [0.0, 0.0, -H, H],
        },
        Expected {
            convention: Convention::Ros,
            root: [3.0, 1.0, 2.0],
            head: [3.0, 1.08297173, 2.52438115],
            left_wrist: [2.85099837, 1.0, 1.69911821],
            root_q: [0.0, 0.0, H, H],
            elbow_q: id,
            wrist_global_q: [0.0, 0.0, H, H],
        },
        Expected {
            convention: Convention::Blender,
            root: [1.0, -3.0, 2.0],
            head: [1.08297173, -3.0, 2.52438115],
            left_wrist: [1.0, -2.85099837, 1.69911821],
            root_q: [0.0, 0.0, H, H],
            elbow_q: id,
            wrist_global_q: [0.0, 0.0, H, H],
        },
        Expected {
            convention: Convention::Gltf,
            root: [1.0, 2.0, 3.0],
            head: [1.08297173, 2.52438115, 3.0],
            left_wrist: [1.0, 1.69911821, 2.85099837],
            root_q: [0.0, H, 0.0, H],
            elbow_q: id,
            wrist_global_q: [0.0, H, 0.0, H],
        },
    ];
    let poses = Poses::decode(
        Format::HumanMl263,
        &humanml_features(),
        2,
        &ReadOptions::default(),
    )
    .unwrap();
    for e in &cases {
        check(&poses, e, (15, 18, 20));
    }
    // Here rotations and positions agree, so posing the rest skeleton reproduces the positions.
    for c in Convention::ALL {
        let offsets: Vec<[f64; 3]> = flame::motion::rest_offsets(Format::HumanMl263, c)
            .chunks(3)
            .map(|o| [o[0] as f64, o[1] as f64, o[2] as f64])
            .collect();
        let local = poses.local_rotations(c);
        let (mut p, mut w) = (vec![[0.0; 3]; 22], vec![rotation::IDENTITY; 22]);
        let root = poses.root_translation(c)[1];
        flame::motion::skeleton::forward_kinematics(
            Format::HumanMl263.skeleton().parents(),
            &offsets,
            &root,
            &local[22..],
            &mut p,
            &mut w,
        )
        .unwrap();
        let want = poses.positions(c);
        for j in 0..22 {
            assert_close(&format!("{c} FK joint {j}"), &p[j], &want[22 + j]);
        }
    }
}
