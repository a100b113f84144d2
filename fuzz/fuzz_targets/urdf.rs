//! URDF robots ([`flame::robot::Robot::from_urdf`]), then forward kinematics and a Jacobian of
//! every link on each robot that reads. The first byte picks what the input is:
//! - even (`<` is even, so a URDF file is a seed as it is): the whole input as text (lossy
//!   UTF-8);
//! - odd: a description built from the rest, 8 bytes a joint (its parent among all links, so
//!   cycles, two parents and several roots come up; each of the six types; axes from a small
//!   set that includes zero; origins, limits that may cross, a mimic of an earlier, later or
//!   missing joint, now and then a collision shape, a `world` root or a duplicate name), so
//!   most inputs reach the tree and the kinematics rather than the XML parser.
//!
//! A robot that reads is consistent (links parents first, sizes `7 + n` and `6 + n`, lower ≤
//! upper); on built descriptions, whose numbers are small, every pose and Jacobian entry is
//! finite.
#![no_main]

use flame::robot::{forward, jacobian_point, Pose, Robot, RobotData};
use libfuzzer_sys::fuzz_target;

const TYPES: [&str; 7] = [
    "revolute",
    "continuous",
    "prismatic",
    "fixed",
    "floating",
    "planar",
    "hinge",
];
const AXES: [&str; 6] = ["1 0 0", "0 1 0", "0 0 1", "0 0 0", "1 1 0", "0 -2 1e-3"];

/// A URDF from bytes (module doc).
fn built(data: &[u8]) -> String {
    let joints: Vec<&[u8]> = data.chunks(8).take(200).collect();
    let n_links = joints.len() + 1;
    let link = |i: usize| {
        if i == 0 && data.first().is_some_and(|b| b % 16 == 1) {
            "world".to_string()
        } else {
            format!("l{i}")
        }
    };
    let mut out = String::from("<robot name=\"fuzz\">\n");
    for i in 0..n_links {
        let shape = match data.get(i).map_or(0, |b| b % 8) {
            0 => "<box size=\"0.1 0.2 0.3\"/>",
            1 => "<sphere radius=\"0.05\"/>",
            2 => "<cylinder radius=\"0.02\" length=\"0.4\"/>",
            3 => "<mesh filename=\"package://x/y.dae\"/>",
            _ => "",
        };
        out.push_str(&format!("<link name=\"{}\">", link(i)));
        if !shape.is_empty() {
            out.push_str(&format!(
                "<collision><origin xyz=\"0 0 0.1\" rpy=\"0.1 0 0\"/><geometry>{shape}</geometry></collision>"
            ));
        }
        out.push_str("</link>\n");
    }
    for (j, c) in joints.iter().enumerate() {
        let byte = |i: usize| c.get(i).copied().unwrap_or(0);
        // Mostly a parent among the links before the child (a tree), sometimes any link.
        let parent = if byte(0) < 224 {
            byte(0) as usize % (j + 1)
        } else {
            byte(0) as usize % n_links
        };
        let name = if byte(7) == 255 {
            "j0".to_string()
        } else {
            format!("j{j}")
        };
        let kind = TYPES[byte(1) as usize % TYPES.len()];
        let axis = AXES[byte(2) as usize % AXES.len()];
        let f = |b: u8| (b as f64 - 128.0) / 64.0;
        let (lower, upper) = (f(byte(5)), f(byte(6)));
        out.push_str(&format!(
            "<joint name=\"{name}\" type=\"{kind}\"><parent link=\"{}\"/><child link=\"{}\"/>\
             <origin xyz=\"{} {} 0.1\" rpy=\"0 {} 0\"/><axis xyz=\"{axis}\"/>",
            link(parent),
            link(j + 1),
            f(byte(3)),
            f(byte(4)),
            f(byte(3) ^ byte(4)),
        ));
        if byte(7) % 4 != 3 {
            out.push_str(&format!(
                "<limit lower=\"{lower}\" upper=\"{upper}\" velocity=\"{}\" effort=\"1\"/>",
                byte(7) % 5
            ));
        }
        if byte(7) % 8 == 5 {
            let source = byte(2) as usize % (joints.len() + 1);
            out.push_str(&format!(
                "<mimic joint=\"j{source}\" multiplier=\"{}\" offset=\"0.1\"/>",
                f(byte(6))
            ));
        }
        out.push_str("</joint>\n");
    }
    out.push_str("</robot>\n");
    out
}

fn exercise(robot: &Robot, finite: bool) {
    let n = robot.dof_count();
    assert_eq!((robot.nq(), robot.nv()), (7 + n, 6 + n));
    assert_eq!(robot.dof_names().len(), n);
    for (i, l) in robot.links().iter().enumerate() {
        assert!(l.parent.is_none_or(|p| p < i));
        assert_eq!(l.parent.is_none(), i == 0);
        assert_eq!(robot.link_index(&l.name), Some(i));
    }
    let limits = robot.joint_limits();
    assert_eq!(limits.lower.len(), n);
    assert!((0..n).all(|i| limits.lower[i] <= limits.upper[i]));
    assert!(robot.mujoco_joint_order().len() >= n);

    let q: Vec<f64> = (0..n)
        .map(|i| (limits.lower[i].max(-1.0) + limits.upper[i].min(1.0)) / 2.0)
        .collect();
    let base = Pose::from_xyz_rpy([0.1, -0.2, 0.9], [0.3, -0.2, 1.0]);
    let mut data = RobotData::new(robot);
    forward(robot, &base, &q, &mut data).unwrap();
    let mut jac = vec![0.0; 6 * robot.nv()];
    for l in 0..robot.links().len() {
        jacobian_point(robot, &data, l, [0.01, 0.0, -0.02], &mut jac).unwrap();
        if finite {
            let p = data.link_pose(l);
            assert!(p
                .translation
                .iter()
                .chain(p.rotation.iter().flatten())
                .all(|v| v.is_finite()));
            assert!(jac.iter().all(|v| v.is_finite()));
        }
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let (text, finite) = if mode % 2 == 0 {
        (String::from_utf8_lossy(data).into_owned(), false)
    } else {
        (built(rest), true)
    };
    if let Ok(robot) = Robot::from_urdf(&text) {
        exercise(&robot, finite);
    }
});
