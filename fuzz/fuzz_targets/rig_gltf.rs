//! Rig files: the bytes to the glTF/GLB/VRM rig reader as they are, and split at their last
//! 0xFF byte into a file and a skin name; the same bytes as text (lossy UTF-8) to the BVH rig
//! reader. A rig that reads is consistent: parents first, finite rest frames, a declared map
//! inside the rig, a positive unit. The bytes also go to the reader of libflame's own glTF
//! motions (`flame retarget --in x.glb`): a motion that reads has finite `smpl24_6d`
//! features for its frames at a positive rate.
#![no_main]

use flame::retarget::{bvh_rig, gltf_motion, gltf_rig, Rig};
use libfuzzer_sys::fuzz_target;

fn check(rig: &Rig) {
    let n = rig.bone_count();
    assert!(n >= 1);
    assert_eq!(rig.names().len(), n);
    for (b, p) in rig.parents().iter().enumerate() {
        assert!(p.is_none_or(|p| p < b));
    }
    assert!(rig
        .rest_world_positions()
        .iter()
        .flatten()
        .all(|v| v.is_finite()));
    assert!(rig
        .rest_world_rotations()
        .iter()
        .flatten()
        .flatten()
        .all(|v| v.is_finite()));
    assert!(rig.declared_map().iter().all(|(_, b)| *b < n));
    assert!(rig.metres_per_unit() > 0.0);
}

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = gltf_motion::read(data) {
        assert!(m.frames >= 1 && m.fps > 0.0);
        assert_eq!(m.features.len(), m.frames * 147);
        assert!(m.features.iter().all(|v| v.is_finite()));
    }
    if let Ok(rig) = gltf_rig::read(data, None) {
        check(&rig);
    }
    if let Some(at) = data.iter().rposition(|&b| b == 0xFF) {
        let name = String::from_utf8_lossy(&data[at + 1..]);
        if let Ok(rig) = gltf_rig::read(&data[..at], Some(&name)) {
            check(&rig);
        }
    }
    let text = String::from_utf8_lossy(data);
    if let Ok(rig) = bvh_rig::read(&text, None) {
        check(&rig);
        assert!(rig.metres_per_unit() == 0.01 || rig.metres_per_unit() == 1.0);
    }
});
