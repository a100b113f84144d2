//! `flame::robot`: the URDF reader, the tree, forward kinematics and Jacobians.
//!
//! - Hand-derived cases on small inline URDFs (a planar two-link arm by trigonometry, a
//!   prismatic joint, rpy origins against matrices written out here, a continuous joint, a mimic
//!   joint, a `world` link, MuJoCo's order).
//! - Jacobians against central finite differences of forward kinematics (base columns included)
//!   on the real GR1T2 and JVRC-1 descriptions (PyPI `fourier-robot-descriptions` 0.2.7 and
//!   `jvrc-description` 1.1.1, fetched into target/robots by tools/fetch_robots.sh, which these
//!   tests run when the files are missing).
//! - Every refused input as an error naming the element; truncations of the real files never
//!   panic; forward and Jacobians allocate nothing.
//! - Pinocchio (PyPI `pin`, tests/robot_pinocchio.py run by `$FLAME_TEST_PYTHON` or
//!   target/test-venv/bin/python) as the independent reference: every link's world placement at
//!   20 random configurations per robot, limits per joint, nq and nv.
//!
//! Without the URDFs (offline) the real-robot tests skip and say so in
//! target/tmp/skipped-tests.log, or fail when FLAME_REQUIRE_REAL_WEIGHTS=1.

use std::path::PathBuf;
use std::process::Command;

use flame::motion::rotation::{self, Mat3, Vec3};
use flame::robot::{
    forward, integrate, jacobian_point, Geometry, JointKind, Pose, Robot, RobotData,
};

mod common;

// Allocation counting (this thread's only: tests run in parallel).
#[global_allocator]
static GLOBAL: common::counting::Counting = common::counting::Counting;

// --- Helpers -------------------------------------------------------------------------------------

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
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

fn robot(text: &str) -> Robot {
    Robot::from_urdf(text).unwrap_or_else(|e| panic!("{e}"))
}

fn err(text: &str) -> String {
    match Robot::from_urdf(text) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

fn close3(a: &Vec3, b: &Vec3, tol: f64) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

fn mat_diff(a: &Mat3, b: &Mat3) -> f64 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

fn rot_x(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}
fn rot_y(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
}
fn rot_z(a: f64) -> Mat3 {
    let (s, c) = a.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

fn limit() -> &'static str {
    r#"<limit lower="-3" upper="3" velocity="2" effort="10"/>"#
}

/// A URDF from links and joints `(name, type, parent, child, extra elements)`.
fn urdf(links: &[&str], joints: &[(&str, &str, &str, &str, &str)]) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<robot name=\"t\">\n");
    for l in links {
        s.push_str(&format!("  <link name=\"{l}\"/>\n"));
    }
    for (name, kind, parent, child, extra) in joints {
        s.push_str(&format!(
            "  <joint name=\"{name}\" type=\"{kind}\">\n    <parent link=\"{parent}\"/>\n    \
             <child link=\"{child}\"/>\n    {extra}\n  </joint>\n"
        ));
    }
    s.push_str("</robot>\n");
    s
}

// --- Hand-derived kinematics ---------------------------------------------------------------------

const L1: f64 = 0.7;
const L2: f64 = 0.4;

/// Two links turning about z in the xy plane: shoulder at the base origin, elbow `L1` along the
/// upper link's x, a tip `L2` further (fixed joint).
fn planar_arm() -> String {
    let revolute_z = format!(r#"<axis xyz="0 0 1"/>{}"#, limit());
    urdf(
        &["base", "upper", "fore", "tip"],
        &[
            ("shoulder", "revolute", "base", "upper", &revolute_z),
            (
                "elbow",
                "revolute",
                "upper",
                "fore",
                &format!(r#"<origin xyz="{L1} 0 0"/>{revolute_z}"#),
            ),
            (
                "tip_joint",
                "fixed",
                "fore",
                "tip",
                &format!(r#"<origin xyz="{L2} 0 0"/>"#),
            ),
        ],
    )
}

#[test]
fn planar_arm_positions_and_jacobian_are_trigonometry() {
    let robot = robot(&planar_arm());
    assert_eq!(robot.dof_names(), ["shoulder", "elbow"]);
    assert_eq!((robot.nq(), robot.nv()), (9, 8));
    let tip = robot.link_index("tip").unwrap();
    let elbow_link = robot.link_index("fore").unwrap();
    let mut data = RobotData::new(&robot);
    let mut jac = vec![0.0; 6 * robot.nv()];
    for (q1, q2) in [(0.0, 0.0), (0.3, -1.2), (2.5, 0.9), (-1.0, 3.0)] {
        forward(&robot, &Pose::IDENTITY, &[q1, q2], &mut data).unwrap();
        let want = [
            L1 * q1.cos() + L2 * (q1 + q2).cos(),
            L1 * q1.sin() + L2 * (q1 + q2).sin(),
            0.0,
        ];
        assert!(close3(&data.link_pose(tip).translation, &want, 1e-15));
        assert!(close3(
            &data.link_pose(elbow_link).translation,
            &[L1 * q1.cos(), L1 * q1.sin(), 0.0],
            1e-15
        ));
        assert!(mat_diff(&data.link_pose(tip).rotation, &rot_z(q1 + q2)) < 1e-15);

        // ∂tip/∂q1 = (−L1 s1 − L2 s12, L1 c1 + L2 c12), ∂tip/∂q2 = (−L2 s12, L2 c12); both turn
        // about z.
        jacobian_point(&robot, &data, tip, [0.0; 3], &mut jac).unwrap();
        let nv = robot.nv();
        let (s1, c1, s12, c12) = (q1.sin(), q1.cos(), (q1 + q2).sin(), (q1 + q2).cos());
        let col = |c: usize| -> [f64; 6] { std::array::from_fn(|r| jac[r * nv + c]) };
        let want1 = [-L1 * s1 - L2 * s12, L1 * c1 + L2 * c12, 0.0, 0.0, 0.0, 1.0];
        let want2 = [-L2 * s12, L2 * c12, 0.0, 0.0, 0.0, 1.0];
        assert!(col(6)
            .iter()
            .zip(&want1)
            .all(|(a, b)| (a - b).abs() < 1e-15));
        assert!(col(7)
            .iter()
            .zip(&want2)
            .all(|(a, b)| (a - b).abs() < 1e-15));
    }

    // A base turned by θ about z and moved: the arm turns with it.
    let theta = 0.8;
    let base = Pose {
        rotation: rot_z(theta),
        translation: [1.0, -2.0, 0.5],
    };
    forward(&robot, &base, &[0.3, 0.4], &mut data).unwrap();
    let (a, b) = (theta + 0.3, theta + 0.7);
    let want = [
        1.0 + L1 * a.cos() + L2 * b.cos(),
        -2.0 + L1 * a.sin() + L2 * b.sin(),
        0.5,
    ];
    assert!(close3(&data.link_pose(tip).translation, &want, 1e-15));
}

#[test]
fn prismatic_joint_slides_along_its_normalised_axis() {
    let text = urdf(
        &["base", "carriage"],
        &[(
            "slide",
            "prismatic",
            "base",
            "carriage",
            r#"<origin xyz="0.1 0.2 0.3" rpy="0 0 1.5707963267948966"/><axis xyz="2 0 0"/>
               <limit lower="-0.5" upper="0.25" velocity="0.75" effort="100"/>"#,
        )],
    );
    let robot = robot(&text);
    let limits = robot.joint_limits();
    assert_eq!(
        (
            limits.lower[0],
            limits.upper[0],
            limits.velocity[0],
            limits.effort[0]
        ),
        (-0.5, 0.25, 0.75, 100.0)
    );
    assert_eq!(robot.joints()[0].kind, JointKind::Prismatic);
    let mut data = RobotData::new(&robot);
    // The axis x of the joint frame is the parent's y (yaw 90°): the carriage moves along y.
    forward(&robot, &Pose::IDENTITY, &[0.2], &mut data).unwrap();
    assert!(close3(
        &data.link_pose(1).translation,
        &[0.1, 0.4, 0.3],
        1e-15
    ));
    assert!(
        mat_diff(
            &data.link_pose(1).rotation,
            &rot_z(std::f64::consts::FRAC_PI_2)
        ) < 1e-15
    );
    let mut jac = vec![0.0; 6 * robot.nv()];
    jacobian_point(&robot, &data, 1, [0.3, 0.0, 0.0], &mut jac).unwrap();
    let col: Vec<f64> = (0..6).map(|r| jac[r * 7 + 6]).collect();
    assert!(col
        .iter()
        .zip([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
        .all(|(a, b)| (a - b).abs() < 1e-15));
}

#[test]
fn rpy_origins_are_fixed_axis_roll_pitch_yaw() {
    let (r, p, y) = (0.3, -1.1, 2.2);
    let text = urdf(
        &["a", "b", "c"],
        &[
            (
                "ab",
                "fixed",
                "a",
                "b",
                &format!(r#"<origin xyz="1 2 3" rpy="{r} {p} {y}"/>"#),
            ),
            (
                "bc",
                "fixed",
                "b",
                "c",
                r#"<origin xyz="0.5 0 0" rpy="1.5707963267948966 0 0"/>"#,
            ),
        ],
    );
    let robot = robot(&text);
    assert_eq!((robot.dof_count(), robot.nq(), robot.nv()), (0, 7, 6));
    let mut data = RobotData::new(&robot);
    forward(&robot, &Pose::IDENTITY, &[], &mut data).unwrap();
    // Fixed axes x, then y, then z: R = Rz(y) Ry(p) Rx(r).
    let want_b = rotation::mul(&rot_z(y), &rotation::mul(&rot_y(p), &rot_x(r)));
    assert!(mat_diff(&data.link_pose(1).rotation, &want_b) < 1e-15);
    assert_eq!(data.link_pose(1).translation, [1.0, 2.0, 3.0]);
    // c: b's frame, moved 0.5 along b's x, turned 90° about b's x.
    let want_c = rotation::mul(&want_b, &rot_x(std::f64::consts::FRAC_PI_2));
    assert!(mat_diff(&data.link_pose(2).rotation, &want_c) < 1e-15);
    let bx = [want_b[0][0], want_b[1][0], want_b[2][0]];
    let want_t = [1.0 + 0.5 * bx[0], 2.0 + 0.5 * bx[1], 3.0 + 0.5 * bx[2]];
    assert!(close3(&data.link_pose(2).translation, &want_t, 1e-15));
}

#[test]
fn continuous_joints_are_unbounded_and_periodic() {
    let text = urdf(
        &["base", "wheel"],
        &[(
            "spin",
            "continuous",
            "base",
            "wheel",
            r#"<axis xyz="0 1 0"/><limit velocity="30" effort="5"/>"#,
        )],
    );
    let robot = robot(&text);
    let limits = robot.joint_limits();
    assert_eq!(limits.lower[0], f64::NEG_INFINITY);
    assert_eq!(limits.upper[0], f64::INFINITY);
    assert_eq!(limits.velocity[0], 30.0);
    let mut a = RobotData::new(&robot);
    let mut b = RobotData::new(&robot);
    forward(&robot, &Pose::IDENTITY, &[7.0], &mut a).unwrap();
    forward(
        &robot,
        &Pose::IDENTITY,
        &[7.0 - 2.0 * std::f64::consts::PI],
        &mut b,
    )
    .unwrap();
    assert!(mat_diff(&a.link_pose(1).rotation, &b.link_pose(1).rotation) < 1e-14);
    assert!(mat_diff(&a.link_pose(1).rotation, &rot_y(7.0)) < 1e-14);

    // About −y: the rotation about y by −q.
    let negative = Robot::from_urdf(&text.replace(r#"xyz="0 1 0""#, r#"xyz="0 -1 0""#)).unwrap();
    forward(&negative, &Pose::IDENTITY, &[0.7], &mut a).unwrap();
    assert!(mat_diff(&a.link_pose(1).rotation, &rot_y(-0.7)) < 1e-15);
    // A general axis: Rodrigues by hand, about (1, 1, 0)/√2 by π/2.
    let diagonal = Robot::from_urdf(&text.replace(r#"xyz="0 1 0""#, r#"xyz="1 1 0""#)).unwrap();
    forward(
        &diagonal,
        &Pose::IDENTITY,
        &[std::f64::consts::FRAC_PI_2],
        &mut a,
    )
    .unwrap();
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let want = [[0.5, 0.5, h], [0.5, 0.5, -h], [-h, h, 0.0]];
    assert!(mat_diff(&a.link_pose(1).rotation, &want) < 1e-15);
}

#[test]
fn mimic_joints_follow_their_source_and_add_to_its_column() {
    let z = format!(r#"<axis xyz="0 0 1"/>{}"#, limit());
    let text = urdf(
        &["base", "a", "b", "c"],
        &[
            ("ja", "revolute", "base", "a", &z),
            (
                "jb",
                "revolute",
                "a",
                "b",
                &format!(
                    r#"<origin xyz="1 0 0"/>{z}<mimic joint="ja" multiplier="2" offset="0.1"/>"#
                ),
            ),
            // A mimic of a mimic: q_c = -1·q_b + 0 = -2 q_a - 0.1.
            (
                "jc",
                "revolute",
                "b",
                "c",
                &format!(r#"<origin xyz="1 0 0"/>{z}<mimic joint="jb" multiplier="-1"/>"#),
            ),
        ],
    );
    let robot = robot(&text);
    assert_eq!(robot.dof_names(), ["ja"]);
    assert_eq!(robot.mujoco_joint_order(), [0, 1, 2]);
    let q = [0.4];
    assert!((robot.joint_position(1, &q) - 0.9).abs() < 1e-15);
    assert!((robot.joint_position(2, &q) + 0.9).abs() < 1e-15);
    let mut data = RobotData::new(&robot);
    forward(&robot, &Pose::IDENTITY, &q, &mut data).unwrap();
    // The chain as three free joints at 0.4, 0.9, -0.9.
    let (t1, t2) = (0.4_f64, 1.3_f64);
    let want = [t1.cos() + t2.cos(), t1.sin() + t2.sin(), 0.0];
    assert!(close3(&data.link_pose(3).translation, &want, 1e-15));
    assert!(mat_diff(&data.link_pose(3).rotation, &rot_z(0.4)) < 1e-15);
    fd_check(&robot, &Pose::IDENTITY, &q, 1e-9);
}

#[test]
fn a_world_link_with_one_fixed_joint_is_dropped() {
    let text = urdf(
        &["world", "pelvis", "leg"],
        &[
            (
                "mount",
                "fixed",
                "world",
                "pelvis",
                r#"<origin xyz="0 0 1"/>"#,
            ),
            (
                "hip",
                "revolute",
                "pelvis",
                "leg",
                &format!(r#"<origin xyz="0 0.1 0"/>{}"#, limit()),
            ),
        ],
    );
    let robot = robot(&text);
    assert_eq!(robot.links()[0].name, "pelvis");
    assert_eq!(robot.link_index("world"), None);
    assert_eq!(robot.joints().len(), 1);
    assert_eq!(robot.world_mount().unwrap().translation, [0.0, 0.0, 1.0]);
    let mut data = RobotData::new(&robot);
    let base = Pose {
        rotation: rotation::IDENTITY,
        translation: [5.0, 0.0, 0.0],
    };
    forward(&robot, &base, &[0.0], &mut data).unwrap();
    assert_eq!(data.link_pose(0).translation, [5.0, 0.0, 0.0]);
    assert_eq!(data.link_pose(1).translation, [5.0, 0.1, 0.0]);

    // Floating from the world: the same. A revolute from the world: `world` stays as the root.
    let floating = text.replace(r#"type="fixed""#, r#"type="floating""#);
    assert_eq!(
        Robot::from_urdf(&floating).unwrap().links()[0].name,
        "pelvis"
    );
    let turning = text.replace(
        r#"type="fixed">"#,
        &format!(r#"type="revolute">{}"#, limit()),
    );
    let arm = Robot::from_urdf(&turning).unwrap();
    assert_eq!(arm.links()[0].name, "world");
    assert_eq!(arm.dof_names(), ["mount", "hip"]);
}

#[test]
fn mujoco_order_is_depth_first_and_dof_order_is_the_document_s() {
    let z = format!(r#"<axis xyz="0 0 1"/>{}"#, limit());
    // Joints listed breadth first: base -> (l1, r1), l1 -> l2, r1 -> r2.
    let text = urdf(
        &["base", "l1", "r1", "l2", "r2"],
        &[
            ("left_1", "revolute", "base", "l1", &z),
            ("right_1", "revolute", "base", "r1", &z),
            ("left_2", "revolute", "l1", "l2", &z),
            (
                "right_2",
                "continuous",
                "r1",
                "r2",
                r#"<axis xyz="0 0 1"/>"#,
            ),
        ],
    );
    let robot = robot(&text);
    assert_eq!(
        robot.dof_names(),
        ["left_1", "right_1", "left_2", "right_2"]
    );
    let links: Vec<&str> = robot.links().iter().map(|l| l.name.as_str()).collect();
    assert_eq!(links, ["base", "l1", "l2", "r1", "r2"]);
    let mujoco: Vec<&str> = robot
        .mujoco_joint_order()
        .iter()
        .map(|&j| robot.joints()[j].name.as_str())
        .collect();
    assert_eq!(mujoco, ["left_1", "left_2", "right_1", "right_2"]);
    for (i, l) in robot.links().iter().enumerate() {
        assert!(l.parent.is_none_or(|p| p < i));
    }
}

#[test]
fn collisions_are_read_with_their_origins() {
    let text = r#"<robot name="c">
      <link name="foot">
        <collision name="sole"><origin xyz="0.05 0 -0.02" rpy="0 0 0.5"/>
          <geometry><box size="0.2 0.1 0.02"/></geometry></collision>
        <collision><geometry><cylinder radius="0.03" length="0.1"/></geometry></collision>
        <collision><geometry><sphere radius="0.04"/></geometry></collision>
        <collision><geometry><mesh filename="package://x/foot.dae" scale="1 1 2"/></geometry></collision>
        <visual><geometry><mesh filename="ignored.stl"/></geometry></visual>
      </link></robot>"#;
    let robot = robot(text);
    let c = &robot.links()[0].collisions;
    assert_eq!(c.len(), 4);
    assert_eq!(c[0].name.as_deref(), Some("sole"));
    assert_eq!(c[0].origin.translation, [0.05, 0.0, -0.02]);
    assert!(mat_diff(&c[0].origin.rotation, &rot_z(0.5)) < 1e-15);
    assert_eq!(
        c[0].geometry,
        Geometry::Box {
            size: [0.2, 0.1, 0.02]
        }
    );
    assert_eq!(
        c[1].geometry,
        Geometry::Cylinder {
            radius: 0.03,
            length: 0.1
        }
    );
    assert_eq!(c[2].geometry, Geometry::Sphere { radius: 0.04 });
    assert_eq!(
        c[3].geometry,
        Geometry::Mesh {
            filename: "package://x/foot.dae".into(),
            scale: [1.0, 1.0, 2.0]
        }
    );
}

// --- Jacobians against finite differences ------------------------------------------------------

/// `vee((M − Mᵀ)/2)`: for `M = exp([w]×)` with small `w`, `w` to second order.
fn vee_skew(m: &Mat3) -> Vec3 {
    [
        0.5 * (m[2][1] - m[1][2]),
        0.5 * (m[0][2] - m[2][0]),
        0.5 * (m[1][0] - m[0][1]),
    ]
}

/// Every link's Jacobian at a point fixed on it against central differences of forward
/// kinematics over every velocity coordinate; returns the largest difference.
fn fd_check(robot: &Robot, base: &Pose, q: &[f64], tol: f64) -> f64 {
    let (n_links, nv) = (robot.links().len(), robot.nv());
    let points: Vec<Vec3> = (0..n_links)
        .map(|l| [0.05 * (l % 3) as f64, -0.03, 0.02 * (l % 5) as f64])
        .collect();
    let mut data = RobotData::new(robot);
    forward(robot, base, q, &mut data).unwrap();
    let jacobians: Vec<Vec<f64>> = (0..n_links)
        .map(|l| {
            let mut j = vec![0.0; 6 * nv];
            jacobian_point(robot, &data, l, points[l], &mut j).unwrap();
            j
        })
        .collect();
    let eps = 1e-6;
    let (mut plus, mut minus) = (RobotData::new(robot), RobotData::new(robot));
    let mut worst: f64 = 0.0;
    for c in 0..nv {
        // The velocity e_c integrated over ±eps: exactly the convention's meaning of column c.
        for (sign, d) in [(1.0, &mut plus), (-1.0, &mut minus)] {
            let (mut b, mut qq) = (*base, q.to_vec());
            let mut v = vec![0.0; nv];
            v[c] = sign;
            integrate(robot, &mut b, &mut qq, &v, eps).unwrap();
            forward(robot, &b, &qq, d).unwrap();
        }
        for l in 0..n_links {
            let (p1, p0) = (plus.link_pose(l), minus.link_pose(l));
            let (x1, x0) = (p1.point(&points[l]), p0.point(&points[l]));
            let turn = rotation::mul(&p1.rotation, &rotation::transpose(&p0.rotation));
            let w = vee_skew(&turn);
            let fd: [f64; 6] = std::array::from_fn(|r| {
                if r < 3 {
                    (x1[r] - x0[r]) / (2.0 * eps)
                } else {
                    w[r - 3] / (2.0 * eps)
                }
            });
            for (r, want) in fd.iter().enumerate() {
                let got = jacobians[l][r * nv + c];
                let diff = (got - want).abs();
                worst = worst.max(diff);
                assert!(
                    diff <= tol,
                    "link `{}`, row {r}, column {c}: Jacobian {got}, finite difference {want}",
                    robot.links()[l].name
                );
            }
        }
    }
    worst
}

/// A random base pose (position within a few metres, any rotation) and joint vector inside the
/// limits (±π for unbounded joints).
fn random_configuration(robot: &Robot, rng: &mut Lcg) -> (Pose, Vec<f64>) {
    let quat = [
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    ];
    let base = Pose::from_position_quat_xyzw(
        [
            rng.range(-2.0, 2.0),
            rng.range(-2.0, 2.0),
            rng.range(0.0, 1.5),
        ],
        quat,
    );
    let limits = robot.joint_limits();
    let q = (0..robot.dof_count())
        .map(|i| {
            let (lo, hi) = (
                limits.lower[i].max(-std::f64::consts::PI),
                limits.upper[i].min(std::f64::consts::PI),
            );
            rng.range(lo, hi)
        })
        .collect();
    (base, q)
}

#[test]
fn jacobians_match_finite_differences_on_gr1t2_and_jvrc1() {
    let test = "robot_urdf::jacobians_match_finite_differences_on_gr1t2_and_jvrc1";
    for name in ["gr1t2", "jvrc1"] {
        let Some((_, text)) = common::real_urdf(test, name) else {
            return;
        };
        let robot = robot(&text);
        let mut rng = Lcg(44);
        let mut worst: f64 = 0.0;
        for _ in 0..5 {
            let (base, q) = random_configuration(&robot, &mut rng);
            worst = worst.max(fd_check(&robot, &base, &q, 1e-6));
        }
        println!(
            "{name}: {} links, {} dofs; largest |Jacobian − central difference| {worst:.2e}",
            robot.links().len(),
            robot.dof_count()
        );
    }
}

#[test]
fn forward_and_jacobians_allocate_nothing() {
    let robot = robot(&planar_arm());
    let mut data = RobotData::new(&robot);
    let mut jac = vec![0.0; 6 * robot.nv()];
    let (mut base, mut q) = (Pose::IDENTITY, vec![0.1, 0.2]);
    let v = vec![0.1; robot.nv()];
    let before = common::counting::allocations();
    for i in 0..100 {
        forward(&robot, &base, &q, &mut data).unwrap();
        jacobian_point(&robot, &data, i % 4, [0.1, 0.0, 0.0], &mut jac).unwrap();
        integrate(&robot, &mut base, &mut q, &v, 0.01).unwrap();
    }
    assert_eq!(common::counting::allocations(), before);
}

#[test]
fn wrong_sizes_are_errors() {
    let robot = robot(&planar_arm());
    let mut data = RobotData::new(&robot);
    assert!(forward(&robot, &Pose::IDENTITY, &[0.0], &mut data)
        .unwrap_err()
        .to_string()
        .contains("q has 1 values"));
    forward(&robot, &Pose::IDENTITY, &[0.0, 0.0], &mut data).unwrap();
    let mut short = vec![0.0; 10];
    assert!(jacobian_point(&robot, &data, 3, [0.0; 3], &mut short).is_err());
    let mut jac = vec![0.0; 6 * robot.nv()];
    assert!(jacobian_point(&robot, &data, 4, [0.0; 3], &mut jac).is_err());
    let other = Robot::from_urdf(&urdf(&["x"], &[])).unwrap();
    assert!(forward(&other, &Pose::IDENTITY, &[], &mut data).is_err());
}

// --- Refused inputs ------------------------------------------------------------------------------

/// `(what, URDF, words the message must contain)`.
fn bad_inputs() -> Vec<(&'static str, String, Vec<&'static str>)> {
    let z = format!(r#"<axis xyz="0 0 1"/>{}"#, limit());
    let rev =
        |name: &'static str, p: &'static str, c: &'static str| (name, "revolute", p, c, z.as_str());
    let many_links: String = (0..10_001)
        .map(|i| format!("<link name=\"l{i}\"/>"))
        .collect();
    vec![
        (
            "cycle without a root",
            urdf(&["a", "b", "c"], &[rev("ab", "a", "b"), rev("bc", "b", "c"), rev("ca", "c", "a")]),
            vec!["cycle", "`ab`", "`bc`", "`ca`"],
        ),
        (
            "cycle beside the tree",
            urdf(&["r", "a", "b", "c"], &[rev("ra", "r", "a"), rev("bc", "b", "c"), rev("cb", "c", "b")]),
            vec!["cycle", "`bc`", "`cb`"],
        ),
        (
            "joint onto itself",
            urdf(&["a"], &[rev("self", "a", "a")]),
            vec!["`self`", "itself"],
        ),
        (
            "two parents",
            urdf(&["a", "b", "c"], &[rev("ac", "a", "c"), rev("bc", "b", "c")]),
            vec!["`c`", "two parents", "`ac`", "`bc`"],
        ),
        (
            "missing parent link",
            urdf(&["a"], &[rev("j", "nowhere", "a")]),
            vec!["`j`", "parent link `nowhere` does not exist"],
        ),
        (
            "missing child link",
            urdf(&["a"], &[rev("j", "a", "ghost")]),
            vec!["`j`", "child link `ghost` does not exist"],
        ),
        (
            "several roots",
            urdf(&["a", "b", "c"], &[rev("ab", "a", "b")]),
            vec!["2 links are roots", "`a`", "`c`"],
        ),
        (
            "zero axis",
            urdf(&["a", "b"], &[("j0", "revolute", "a", "b", &format!(r#"<axis xyz="0 0 0"/>{}"#, limit()))]),
            vec!["`j0`", "axis", "no direction"],
        ),
        (
            "lower above upper",
            urdf(&["a", "b"], &[("jl", "revolute", "a", "b", r#"<limit lower="1" upper="-1" velocity="1" effort="1"/>"#)]),
            vec!["`jl`", "lower 1 is above upper -1"],
        ),
        (
            "NaN in an origin",
            urdf(&["a", "b"], &[("jn", "fixed", "a", "b", r#"<origin xyz="0 NaN 0"/>"#)]),
            vec!["`jn`", "<origin>", "not finite"],
        ),
        (
            "infinity in a limit",
            urdf(&["a", "b"], &[("ji", "revolute", "a", "b", r#"<limit lower="-inf" upper="1" velocity="1" effort="1"/>"#)]),
            vec!["`ji`", "lower", "not finite"],
        ),
        (
            "malformed number",
            urdf(&["a", "b"], &[("jm", "fixed", "a", "b", r#"<origin rpy="0 0 1.2.3"/>"#)]),
            vec!["`jm`", "rpy", "not a number", "1.2.3"],
        ),
        (
            "two numbers for three",
            urdf(&["a", "b"], &[("j2", "fixed", "a", "b", r#"<origin xyz="1 2"/>"#)]),
            vec!["`j2`", "needs 3 numbers, has 2"],
        ),
        ("no links", "<robot name=\"empty\"></robot>".into(), vec!["no <link>"]),
        (
            "too many links",
            format!("<robot name=\"big\">{many_links}</robot>"),
            vec!["10001 links", "at most 10000"],
        ),
        (
            "duplicate link",
            urdf(&["a", "a"], &[]),
            vec!["two links are named `a`"],
        ),
        (
            "duplicate joint",
            urdf(&["a", "b", "c"], &[rev("j", "a", "b"), rev("j", "a", "c")]),
            vec!["two joints are named `j`"],
        ),
        (
            "revolute without limit",
            urdf(&["a", "b"], &[("nolim", "revolute", "a", "b", "")]),
            vec!["`nolim`", "needs a <limit>"],
        ),
        (
            "unknown type",
            urdf(&["a", "b"], &[("jt", "hinge", "a", "b", "")]),
            vec!["`jt`", "unknown type `hinge`"],
        ),
        (
            "floating inside the tree",
            urdf(&["a", "b"], &[("free", "floating", "a", "b", "")]),
            vec!["`free`", "floating inside the tree"],
        ),
        (
            "planar",
            urdf(&["a", "b"], &[("flat", "planar", "a", "b", "")]),
            vec!["`flat`", "planar"],
        ),
        (
            "mimic of a missing joint",
            urdf(&["a", "b"], &[("m", "revolute", "a", "b", &format!(r#"{}<mimic joint="ghost"/>"#, limit()))]),
            vec!["`m`", "mimics joint `ghost`, which does not exist"],
        ),
        (
            "mimic of a fixed joint",
            urdf(&["a", "b", "c"], &[("f", "fixed", "a", "b", ""), ("m", "revolute", "b", "c", &format!(r#"{}<mimic joint="f"/>"#, limit()))]),
            vec!["`m`", "mimics joint `f`", "fixed"],
        ),
        (
            "mimic cycle",
            urdf(&["a", "b", "c"], &[
                ("m1", "revolute", "a", "b", &format!(r#"{}<mimic joint="m2"/>"#, limit())),
                ("m2", "revolute", "b", "c", &format!(r#"{}<mimic joint="m1"/>"#, limit())),
            ]),
            vec!["mimic", "cycle", "`m1`"],
        ),
        (
            "negative radius",
            r#"<robot name="r"><link name="ball"><collision><geometry><sphere radius="-1"/></geometry></collision></link></robot>"#.into(),
            vec!["`ball`", "radius", "negative"],
        ),
        (
            "collision without shape",
            r#"<robot name="r"><link name="empty"><collision><origin xyz="0 0 0"/></collision></link></robot>"#.into(),
            vec!["`empty`", "without a <geometry>"],
        ),
        (
            "joint without child",
            "<robot name=\"r\"><link name=\"a\"/><joint name=\"orphan\" type=\"fixed\"><parent link=\"a\"/></joint></robot>".into(),
            vec!["`orphan`", "no <child>"],
        ),
        (
            "nameless link",
            "<robot name=\"r\"><link/></robot>".into(),
            vec!["<link>", "line 1", "no name"],
        ),
        ("not XML", "<robot><link name=\"a\"></robot>".into(), vec!["not readable XML"]),
        ("not a robot", "<sdf><link name=\"a\"/></sdf>".into(), vec!["<sdf>", "not <robot>"]),
        (
            "a DTD",
            "<!DOCTYPE robot [<!ENTITY a \"aaaa\">]><robot name=\"&a;\"><link name=\"a\"/></robot>".into(),
            vec!["not readable XML"],
        ),
    ]
}

#[test]
fn bad_inputs_are_clear_errors_naming_the_element() {
    for (what, text, words) in bad_inputs() {
        let message = err(&text);
        for w in words {
            assert!(message.contains(w), "{what}: `{w}` missing from: {message}");
        }
        assert!(
            message.starts_with("invalid argument: URDF"),
            "{what}: {message}"
        );
        println!("{what}: {message}");
    }
}

#[test]
fn truncated_files_never_panic() {
    let test = "robot_urdf::truncated_files_never_panic";
    let mut texts = vec![planar_arm()];
    for name in ["gr1t2", "jvrc1"] {
        if let Some((_, t)) = common::real_urdf(test, name) {
            texts.push(t);
        }
    }
    for text in &texts {
        let step = (text.len() / 1500).max(1);
        let mut accepted = 0;
        for end in (0..=text.len()).step_by(step) {
            if !text.is_char_boundary(end) {
                continue;
            }
            // A truncated file is an error (or, cut after `</robot>`, the robot itself).
            if let Ok(r) = Robot::from_urdf(&text[..end]) {
                accepted += 1;
                let mut data = RobotData::new(&r);
                forward(&r, &Pose::IDENTITY, &vec![0.0; r.dof_count()], &mut data).unwrap();
            }
        }
        assert!(accepted <= 2, "{accepted} truncations were accepted");
    }
}

// --- Real robots: structure and Pinocchio -------------------------------------------------------

#[test]
fn gr1t2_and_jvrc1_read_as_published() {
    let test = "robot_urdf::gr1t2_and_jvrc1_read_as_published";
    // (links, dofs, first dof, a collision count) from the files themselves.
    for (name, links, dofs, first) in [
        ("gr1t2", 37, 32, "left_hip_roll_joint"),
        // JVRC-1's 44 revolute joints include 10 finger joints that mimic a thumb joint.
        ("jvrc1", 60, 34, "R_HIP_P"),
    ] {
        let Some((_, text)) = common::real_urdf(test, name) else {
            return;
        };
        let robot = robot(&text);
        assert_eq!(robot.links().len(), links, "{name}");
        assert_eq!(robot.dof_count(), dofs, "{name}");
        assert_eq!(robot.dof_names()[0], first, "{name}");
        assert_eq!((robot.nq(), robot.nv()), (7 + dofs, 6 + dofs));
        // Both files list their joints depth first: MuJoCo's order is the document's.
        let movable: Vec<usize> = (0..robot.joints().len())
            .filter(|&j| robot.joints()[j].kind != JointKind::Fixed)
            .collect();
        assert_eq!(robot.mujoco_joint_order(), movable, "{name}");
        let shapes: usize = robot.links().iter().map(|l| l.collisions.len()).sum();
        println!("{name}: {links} links, {dofs} dofs, {shapes} collision shapes");
        assert!(shapes > 0);
    }
}

/// Python with Pinocchio: `$FLAME_TEST_PYTHON`, else tools/check.sh's virtual environment.
fn python() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FLAME_TEST_PYTHON") {
        return Some(p.into());
    }
    let venv = common::repo("target/test-venv/bin/python");
    venv.is_file().then_some(venv)
}

#[test]
fn pinocchio_places_every_link_where_libflame_does() {
    let test = "robot_urdf::pinocchio_places_every_link_where_libflame_does";
    let Some(python) = python() else {
        common::skip(
            test,
            "no Python with Pinocchio (set FLAME_TEST_PYTHON or run tools/check.sh, which makes \
             target/test-venv from tools/test-requirements.txt)",
        );
        return;
    };
    let mut requests = Vec::new();
    let mut ours = Vec::new();
    for name in ["gr1t2", "jvrc1"] {
        let Some((path, text)) = common::real_urdf(test, name) else {
            return;
        };
        let robot = robot(&text);
        let mut rng = Lcg(2044);
        let mut data = RobotData::new(&robot);
        let mut cases = Vec::new();
        let mut placements = Vec::new();
        for _ in 0..20 {
            let (base, q) = random_configuration(&robot, &mut rng);
            forward(&robot, &base, &q, &mut data).unwrap();
            // Every moving joint by name, mimic ones at their computed positions: Pinocchio
            // builds them as independent joints (its mimic support refuses JVRC-1, whose
            // fingers mimic a thumb joint it creates after them).
            let named: serde_json::Map<String, serde_json::Value> = robot
                .mujoco_joint_order()
                .iter()
                .map(|&j| {
                    let value = robot.joint_position(j, &q);
                    (robot.joints()[j].name.clone(), value.into())
                })
                .collect();
            cases.push(serde_json::json!({
                "base_position": base.translation,
                "base_quat_xyzw": base.quat_xyzw(),
                "q": named,
            }));
            placements.push(data.link_poses().to_vec());
        }
        let links: Vec<&str> = robot.links().iter().map(|l| l.name.as_str()).collect();
        requests.push(serde_json::json!({
            "name": name, "urdf": path, "links": links, "cases": cases,
        }));
        ours.push((robot, placements));
    }
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    let request = dir.join(format!("robot_pinocchio_{}.json", std::process::id()));
    std::fs::write(&request, serde_json::to_vec(&requests).unwrap()).unwrap();
    let out = Command::new(&python)
        .arg(common::repo("tests/robot_pinocchio.py"))
        .arg(&request)
        .output()
        .expect("run python");
    std::fs::remove_file(&request).unwrap();
    if out.status.code() == Some(77) {
        common::skip(
            test,
            &format!(
                "{} has no Pinocchio: {}",
                python.display(),
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        );
        return;
    }
    assert!(
        out.status.success(),
        "tests/robot_pinocchio.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let answers: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();

    for ((robot, placements), answer) in ours.iter().zip(answers.as_array().unwrap()) {
        let name = answer["name"].as_str().unwrap();
        // Pinocchio's mimic joints are degrees of freedom of their own (above).
        let mimics = robot.mujoco_joint_order().len() - robot.dof_count();
        let size = |k: &str| answer[k].as_u64().unwrap() as usize;
        assert_eq!(size("nq"), robot.nq() + mimics, "{name} nq");
        assert_eq!(size("nv"), robot.nv() + mimics, "{name} nv");

        // Limits per joint, by name: the degrees of freedom's from `joint_limits`, the mimic
        // joints' from their own `<limit>`.
        let limits = robot.joint_limits();
        for &j in robot.mujoco_joint_order() {
            let joint = &robot.joints()[j];
            let dof = &joint.name;
            let mine = match robot.dof_index(dof) {
                Some(i) => [
                    limits.lower[i],
                    limits.upper[i],
                    limits.velocity[i],
                    limits.effort[i],
                ],
                None => {
                    let l = joint.limit.unwrap();
                    [l.lower, l.upper, l.velocity, l.effort]
                }
            };
            let theirs = &answer["limits"][dof];
            for (k, want) in ["lower", "upper", "velocity", "effort"].iter().zip(mine) {
                let got = theirs[k]
                    .as_f64()
                    .unwrap_or_else(|| panic!("{name} {dof} {k}"));
                assert_eq!(got, want, "{name} {dof} {k}");
            }
        }

        // Pinocchio walks depth first with children sorted by joint name (urdfdom's map).
        let theirs: Vec<&str> = answer["joint_order"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        let mut sorted_dfs = Vec::new();
        dfs_by_name(robot, 0, &mut sorted_dfs);
        assert_eq!(theirs, sorted_dfs, "{name}: Pinocchio's joint order");

        let (mut worst_t, mut worst_r): (f64, f64) = (0.0, 0.0);
        for (case, mine) in answer["cases"].as_array().unwrap().iter().zip(placements) {
            for (l, link) in robot.links().iter().enumerate() {
                let p = &case[&link.name];
                let t: Vec<f64> = p["translation"]
                    .as_array()
                    .unwrap_or_else(|| panic!("{name}: Pinocchio has no frame `{}`", link.name))
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect();
                let r: Vec<f64> = p["rotation"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .flat_map(|row| row.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()))
                    .collect();
                let dt = (0..3)
                    .map(|k| (t[k] - mine[l].translation[k]).abs())
                    .fold(0.0, f64::max);
                let dr = (0..9)
                    .map(|k| (r[k] - mine[l].rotation[k / 3][k % 3]).abs())
                    .fold(0.0, f64::max);
                assert!(
                    dt <= 1e-9 && dr <= 1e-9,
                    "{name} `{}`: {dt:e} m, {dr:e}",
                    link.name
                );
                worst_t = worst_t.max(dt);
                worst_r = worst_r.max(dr);
            }
        }
        println!(
            "{name}: Pinocchio vs libflame over 20 configurations × {} links: translation \
             {worst_t:.2e} m, rotation {worst_r:.2e}; limits of {} joints equal; nq {} nv {} ({mimics} mimic joints)",
            robot.links().len(),
            robot.mujoco_joint_order().len(),
            robot.nq(),
            robot.nv()
        );
    }
}

/// Movable joint names, depth first from `link`, children in the order of their joint names.
fn dfs_by_name(robot: &Robot, link: usize, out: &mut Vec<String>) {
    let mut children: Vec<usize> = robot
        .joints()
        .iter()
        .enumerate()
        .filter(|(_, j)| j.parent == link)
        .map(|(i, _)| i)
        .collect();
    children.sort_by(|&a, &b| robot.joints()[a].name.cmp(&robot.joints()[b].name));
    for j in children {
        let joint = &robot.joints()[j];
        if joint.kind != JointKind::Fixed {
            out.push(joint.name.clone());
        }
        dfs_by_name(robot, joint.child, out);
    }
}
