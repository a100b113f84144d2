//! `.npy` bytes through the decoder the CLI reads motions and noise with.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok((shape, values)) = flame::npy::decode_f32(data) {
        // A decoded array is self-consistent, and re-encoding it decodes to the same thing.
        assert_eq!(shape.iter().product::<usize>(), values.len());
        let again = flame::npy::decode_f32(&flame::npy::encode_f32(&shape, &values)).unwrap();
        assert_eq!(again.0, shape);
        assert_eq!(again.1.len(), values.len());
    }
});
