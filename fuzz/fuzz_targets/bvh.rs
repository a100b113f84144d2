//! BVH text through the parser and, when it parses, the conversion to model features in both
//! motion formats and every convention.
#![no_main]

use flame::motion::{bvh, Convention, Format};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let Ok(motion) = bvh::parse(&text) else {
        return;
    };
    assert!(motion.frame(motion.frames()).is_none());
    for format in Format::ALL {
        if let Ok((features, frames, _, fps)) = bvh::to_features(&motion, format) {
            assert_eq!(features.len(), frames * format.feature_dim());
            assert!(fps.is_finite() && fps > 0.0);
        }
        for convention in Convention::ALL {
            if let Ok(features) = bvh::to_features_in(&motion, format, convention) {
                assert_eq!(features.len(), motion.frames() * format.feature_dim());
            }
        }
    }
});
