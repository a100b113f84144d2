//! Retarget configurations ([`flame::robot::RetargetConfig::from_json`]) against a small biped
//! written here, then, for every configuration that reads, a retargeter and two frames of
//! solving on SMPL's rest pose (a frame in contact, one not). Input: the JSON text (lossy
//! UTF-8); the seeds are configurations for the biped in GMR's shape with libflame's keys.
//!
//! A configuration that reads must give a retargeter or a clear error, and a step must return a
//! finite residual or an error — never a panic, a hang or a non-finite joint vector.
#![no_main]

use flame::motion::rotation::{self, Vec3};
use flame::motion::Skeleton;
use flame::robot::{HumanFrame, RetargetConfig, Retargeter, Robot};
use libfuzzer_sys::fuzz_target;

/// A biped with the bodies the seeds name: a floating pelvis, a torso, two 3-joint legs ending
/// in a foot with a box sole, two 2-joint arms.
const BIPED: &str = r#"<robot name="biped">
  <link name="pelvis"/><link name="torso"/>
  <link name="l_thigh"/><link name="l_shank"/><link name="l_foot"><collision><origin xyz="0.04 0 -0.03"/><geometry><box size="0.2 0.08 0.02"/></geometry></collision></link>
  <link name="r_thigh"/><link name="r_shank"/><link name="r_foot"><collision><origin xyz="0.04 0 -0.03"/><geometry><box size="0.2 0.08 0.02"/></geometry></collision></link>
  <link name="l_upper_arm"/><link name="l_hand"/><link name="r_upper_arm"/><link name="r_hand"/>
  <joint name="waist" type="revolute"><parent link="pelvis"/><child link="torso"/><origin xyz="0 0 0.2"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" velocity="5" effort="1"/></joint>
  <joint name="l_hip" type="revolute"><parent link="pelvis"/><child link="l_thigh"/><origin xyz="0 0.1 -0.05"/><axis xyz="0 1 0"/><limit lower="-2" upper="1" velocity="5" effort="1"/></joint>
  <joint name="l_knee" type="revolute"><parent link="l_thigh"/><child link="l_shank"/><origin xyz="0 0 -0.4"/><axis xyz="0 1 0"/><limit lower="0" upper="2.5" velocity="5" effort="1"/></joint>
  <joint name="l_ankle" type="revolute"><parent link="l_shank"/><child link="l_foot"/><origin xyz="0 0 -0.4"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" velocity="5" effort="1"/></joint>
  <joint name="r_hip" type="revolute"><parent link="pelvis"/><child link="r_thigh"/><origin xyz="0 -0.1 -0.05"/><axis xyz="0 1 0"/><limit lower="-2" upper="1" velocity="5" effort="1"/></joint>
  <joint name="r_knee" type="revolute"><parent link="r_thigh"/><child link="r_shank"/><origin xyz="0 0 -0.4"/><axis xyz="0 1 0"/><limit lower="0" upper="2.5" velocity="5" effort="1"/></joint>
  <joint name="r_ankle" type="revolute"><parent link="r_shank"/><child link="r_foot"/><origin xyz="0 0 -0.4"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" velocity="5" effort="1"/></joint>
  <joint name="l_shoulder" type="revolute"><parent link="torso"/><child link="l_upper_arm"/><origin xyz="0 0.2 0.25"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" velocity="5" effort="1"/></joint>
  <joint name="l_elbow" type="continuous"><parent link="l_upper_arm"/><child link="l_hand"/><origin xyz="0 0 -0.5"/><axis xyz="0 1 0"/></joint>
  <joint name="r_shoulder" type="revolute"><parent link="torso"/><child link="r_upper_arm"/><origin xyz="0 -0.2 0.25"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" velocity="5" effort="1"/></joint>
  <joint name="r_elbow" type="prismatic"><parent link="r_upper_arm"/><child link="r_hand"/><origin xyz="0 0 -0.5"/><axis xyz="0 0 1"/><limit lower="-0.1" upper="0.1" velocity="1" effort="1"/></joint>
</robot>"#;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let robot = Robot::from_urdf(BIPED).expect("the biped reads");
    let Ok(config) = RetargetConfig::from_json(&text, &robot) else {
        return;
    };
    let Ok(retargeter) = Retargeter::new(robot, config) else {
        return;
    };
    // SMPL's rest pose, standing on the floor (Z up: the skeleton's Y up turned), identity
    // rotations: the targets every configuration's offsets are relative to.
    let skeleton = Skeleton::smpl24();
    let mut positions: Vec<Vec3> = Vec::with_capacity(skeleton.joint_count());
    for (j, off) in skeleton.rest_offsets().iter().enumerate() {
        let z_up = [off[2], off[0], off[1]];
        let at = match skeleton.parent(j) {
            Some(p) => rotation::add(&positions[p], &z_up),
            None => [0.0, 0.0, 0.95],
        };
        positions.push(at);
    }
    let rotations = vec![rotation::IDENTITY; positions.len()];
    let mut state = retargeter.state();
    for contacts in [[true; 4], [false, false, true, true]] {
        let frame = HumanFrame {
            positions: &positions,
            rotations: &rotations,
            contacts,
        };
        if let Ok(residual) = retargeter.step(&mut state, &frame, 0.05) {
            assert!(residual.is_finite(), "residual {residual}");
            assert!(state.q().iter().all(|v| v.is_finite()), "q {:?}", state.q());
        }
    }
});
