//! Reference poses (root positions plus local rotations, as a caller of
//! `flame_session_set_reference_poses` gives them) turned back into `smpl24_6d` features:
//! arbitrary floats, layouts, conventions and lengths.
#![no_main]

use flame::motion::{reference, Convention, Layout};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if data.len() < 4 {
        return;
    }
    let layout = Layout::ALL[data[0] as usize % Layout::ALL.len()];
    let convention = Convention::ALL[data[1] as usize % Convention::ALL.len()];
    let frames = data[2] as usize % 5;
    // Root values first, then rotations; the split point is fuzzed so lengths can be wrong.
    let floats: Vec<f32> = data[4..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let split = (data[3] as usize).min(floats.len());
    let (root, rotations) = floats.split_at(split);
    if let Ok(features) = reference::smpl24_features(root, rotations, layout, convention, frames) {
        assert_eq!(features.len(), frames * 147);
        assert!(features.iter().all(|v| v.is_finite()));
    }
});
