//! Rotation math in `f64`: 3×3 matrices, quaternions, the two 6D encodings of the official code,
//! and the ZXY Euler angles the BVH writer uses. Nothing here knows about skeletons or formats.
//!
//! Matrices are row-major (`m[row][col]`) and act on column vectors (`v' = M v`), so a chain of
//! rotations composes left to right from the root (`world = parent · local`). Quaternions are
//! stored w first (`[w, x, y, z]`) inside the crate; layouts reorder on output.

/// A 3-vector.
pub type Vec3 = [f64; 3];
/// A row-major 3×3 matrix acting on column vectors.
pub type Mat3 = [[f64; 3]; 3];
/// A quaternion, w first.
pub type QuatWxyz = [f64; 4];

/// The identity matrix.
pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// `a · b`.
pub fn mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (r, row) in out.iter_mut().enumerate() {
        for (c, x) in row.iter_mut().enumerate() {
            *x = a[r][0] * b[0][c] + a[r][1] * b[1][c] + a[r][2] * b[2][c];
        }
    }
    out
}

/// `mᵀ` (the inverse of a rotation).
pub fn transpose(m: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (r, row) in m.iter().enumerate() {
        for (c, x) in row.iter().enumerate() {
            out[c][r] = *x;
        }
    }
    out
}

/// `m · v`.
pub fn apply(m: &Mat3, v: &Vec3) -> Vec3 {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// `a + b`.
pub fn add(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a × b`.
pub fn cross(a: &Vec3, b: &Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `a · b`.
pub fn dot(a: &Vec3, b: &Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The determinant (+1 for a proper rotation, −1 for a reflection).
pub fn det(m: &Mat3) -> f64 {
    dot(&m[0], &cross(&m[1], &m[2]))
}

/// `v / max(|v|, 1e-12)`: the guard of `torch.nn.functional.normalize`, so a zero vector from a
/// model gives a zero (degenerate) matrix rather than NaNs.
fn normalize(v: &Vec3) -> Vec3 {
    let n = dot(v, v).sqrt().max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

/// FLAME's 6D (pytorch3d `rotation_6d_to_matrix`, docs/official/flame.md#6d-to-rotation-matrix):
/// Gram–Schmidt on the two
/// 3-vectors, and the results are the ROWS of the matrix.
pub fn from_6d_rows(d: &[f64; 6]) -> Mat3 {
    let a1 = [d[0], d[1], d[2]];
    let a2 = [d[3], d[4], d[5]];
    let b1 = normalize(&a1);
    let k = dot(&b1, &a2);
    let b2 = normalize(&[a2[0] - k * b1[0], a2[1] - k * b1[1], a2[2] - k * b1[2]]);
    let b3 = cross(&b1, &b2);
    [b1, b2, b3]
}

/// The inverse of [`from_6d_rows`] on rotations: the first two rows, `[R00,R01,R02,R10,R11,R12]`.
pub fn to_6d_rows(m: &Mat3) -> [f64; 6] {
    [m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2]]
}

/// HumanML3D's cont6d (`quaternion.py`, docs/official/humanml3d.md#cont6d-column-convention):
/// x = normalise(a), z = normalise(x × b), y = z × x, and
/// x, y, z are the COLUMNS of the matrix.
pub fn from_6d_columns(d: &[f64; 6]) -> Mat3 {
    let x = normalize(&[d[0], d[1], d[2]]);
    let z = normalize(&cross(&x, &[d[3], d[4], d[5]]));
    let y = cross(&z, &x);
    [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]]
}

/// The inverse of [`from_6d_columns`] on rotations: `[R00,R10,R20,R01,R11,R21]`.
pub fn to_6d_columns(m: &Mat3) -> [f64; 6] {
    [m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1]]
}

/// Matrix → quaternion by pytorch3d's procedure
/// (docs/official/flame.md#rotation-matrix-to-quaternion): the candidate built from the largest of
/// the four |q| estimates (the first on ties), divided by `2·max(|q|, 0.1)`; then the sign is
/// chosen so that w ≥ 0, as newer pytorch3d does, so every caller gets the same hemisphere whatever
/// the matrix's history.
pub fn to_quat(m: &Mat3) -> QuatWxyz {
    let [[m00, m01, m02], [m10, m11, m12], [m20, m21, m22]] = *m;
    let q_abs = [
        1.0 + m00 + m11 + m22,
        1.0 + m00 - m11 - m22,
        1.0 - m00 + m11 - m22,
        1.0 - m00 - m11 + m22,
    ]
    .map(|x: f64| x.max(0.0).sqrt());
    let mut best = 0;
    for i in 1..4 {
        if q_abs[i] > q_abs[best] {
            best = i;
        }
    }
    let a = q_abs[best];
    let cand = match best {
        0 => [a * a, m21 - m12, m02 - m20, m10 - m01],
        1 => [m21 - m12, a * a, m10 + m01, m02 + m20],
        2 => [m02 - m20, m10 + m01, a * a, m12 + m21],
        _ => [m10 - m01, m20 + m02, m21 + m12, a * a],
    };
    let s = if cand[0] < 0.0 { -1.0 } else { 1.0 } / (2.0 * a.max(0.1));
    cand.map(|x| x * s)
}

/// Quaternion (w first) → matrix, HumanML3D's `quaternion_to_matrix`
/// (docs/official/humanml3d.md#quaternion-conventions): the active
/// rotation, with `s = 2/|q|²` so a non-unit quaternion still gives a rotation.
pub fn quat_to_matrix(q: &QuatWxyz) -> Mat3 {
    let [w, x, y, z] = *q;
    let s = 2.0 / (w * w + x * x + y * y + z * z);
    [
        [
            1.0 - s * (y * y + z * z),
            s * (x * y - z * w),
            s * (x * z + y * w),
        ],
        [
            s * (x * y + z * w),
            1.0 - s * (x * x + z * z),
            s * (y * z - x * w),
        ],
        [
            s * (x * z - y * w),
            s * (y * z + x * w),
            1.0 - s * (x * x + y * y),
        ],
    ]
}

/// The rotation by `angle` radians about the unit `axis` (right-hand rule), Rodrigues' formula.
pub fn axis_angle(axis: &Vec3, angle: f64) -> Mat3 {
    let [x, y, z] = normalize(axis);
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [
        [c + t * x * x, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, c + t * z * z],
    ]
}

/// Euler angles in degrees `[z, x, y]` with `m = Rz(z) · Rx(x) · Ry(y)`: the order of BVH channels
/// `Zrotation Xrotation Yrotation`. ZXY keeps the singularity on the X (pitch) axis, away from
/// the yaw axis of both Y-up and Z-up frames, so a character turning on the spot never hits it.
pub fn to_euler_zxy_degrees(m: &Mat3) -> [f64; 3] {
    // m = [[ca·cc − sa·sb·sc, −sa·cb, ca·sc + sa·sb·cc],
    //      [sa·cc + ca·sb·sc,  ca·cb, sa·sc − ca·sb·cc],
    //      [−cb·sc,            sb,    cb·cc]]
    let cb = m[2][0].hypot(m[2][2]);
    let x = m[2][1].atan2(cb);
    let (z, y) = if cb > 1e-12 {
        ((-m[0][1]).atan2(m[1][1]), (-m[2][0]).atan2(m[2][2]))
    } else {
        // Gimbal lock (x = ±90°): only z ± y is defined; put it all in z.
        (m[1][0].atan2(m[0][0]), 0.0)
    };
    [z.to_degrees(), x.to_degrees(), y.to_degrees()]
}

/// The inverse of [`to_euler_zxy_degrees`].
pub fn from_euler_zxy_degrees(zxy: &[f64; 3]) -> Mat3 {
    let rz = axis_angle(&[0.0, 0.0, 1.0], zxy[0].to_radians());
    let rx = axis_angle(&[1.0, 0.0, 0.0], zxy[1].to_radians());
    let ry = axis_angle(&[0.0, 1.0, 0.0], zxy[2].to_radians());
    mul(&rz, &mul(&rx, &ry))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Mat3, b: &Mat3, tol: f64) -> bool {
        (0..3).all(|r| (0..3).all(|c| (a[r][c] - b[r][c]).abs() < tol))
    }

    fn some_rotations() -> Vec<Mat3> {
        let mut out = vec![IDENTITY];
        for (i, axis) in [
            [1.0, 2.0, 3.0],
            [-0.3, 0.1, 0.9],
            [0.0, 1.0, 0.0],
            [1.0, 0.0, 0.0],
        ]
        .iter()
        .enumerate()
        {
            for angle in [0.3, 1.7, 3.1, -2.5, std::f64::consts::PI] {
                out.push(axis_angle(axis, angle + 0.01 * i as f64));
            }
        }
        out
    }

    #[test]
    fn six_d_encodings_round_trip_and_differ_by_a_transpose() {
        for m in some_rotations() {
            assert!(close(&from_6d_rows(&to_6d_rows(&m)), &m, 1e-12));
            assert!(close(&from_6d_columns(&to_6d_columns(&m)), &m, 1e-12));
            // The row convention read as columns gives the transpose
            // (docs/official/humanml3d.md#cont6d-column-convention).
            assert!(close(
                &from_6d_columns(&to_6d_rows(&m)),
                &transpose(&m),
                1e-12
            ));
        }
    }

    #[test]
    fn gram_schmidt_orthonormalises_model_output() {
        let m = from_6d_rows(&[2.0, 0.1, 0.0, 0.3, 0.5, 0.0]);
        assert!(close(&mul(&m, &transpose(&m)), &IDENTITY, 1e-12));
        assert!((det(&m) - 1.0).abs() < 1e-12);
        assert_eq!(m[0], [2.0 / 4.01f64.sqrt(), 0.1 / 4.01f64.sqrt(), 0.0]);
        let z = from_6d_rows(&[0.0; 6]);
        assert!(z.iter().flatten().all(|x| x.is_finite()));
    }

    #[test]
    fn quaternions_round_trip_with_w_non_negative() {
        for m in some_rotations() {
            let q = to_quat(&m);
            assert!(q[0] >= 0.0, "{q:?}");
            assert!(close(&quat_to_matrix(&q), &m, 1e-12));
        }
        // 90° about +Z: (cos 45°, 0, 0, sin 45°).
        let q = to_quat(&axis_angle(&[0.0, 0.0, 1.0], std::f64::consts::FRAC_PI_2));
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!((q[0] - h).abs() < 1e-15 && (q[3] - h).abs() < 1e-15 && q[1] == 0.0 && q[2] == 0.0);
    }

    #[test]
    fn euler_zxy_round_trips_including_gimbal_lock() {
        for m in some_rotations() {
            assert!(close(
                &from_euler_zxy_degrees(&to_euler_zxy_degrees(&m)),
                &m,
                1e-12
            ));
        }
        let locked = from_euler_zxy_degrees(&[30.0, 90.0, 20.0]);
        assert!(close(
            &from_euler_zxy_degrees(&to_euler_zxy_degrees(&locked)),
            &locked,
            1e-9
        ));
        let e = to_euler_zxy_degrees(&from_euler_zxy_degrees(&[10.0, -20.0, 30.0]));
        assert!(
            (e[0] - 10.0).abs() < 1e-12
                && (e[1] + 20.0).abs() < 1e-12
                && (e[2] - 30.0).abs() < 1e-12
        );
    }
}
