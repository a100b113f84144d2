//! Whole files through the T5 encoder's reader (`T5Encoder::load`: sizes from the tensors'
//! shapes, the v1.1 refusal, the Dense head) and, for a file that loads, one short sequence
//! through the encoder and its sentence vector. Seeded with tests/fixtures/t5_tiny.safetensors.
#![no_main]

use flame::checkpoint::ModelFile;
use flame::kernels::WeightType;
use flame::text::t5::{T5Encoder, T5_MAX_DISTANCE};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(file) = ModelFile::from_bytes(data) else {
        return;
    };
    let Ok(t5) = T5Encoder::load(&file, "", Some("dense"), T5_MAX_DISTANCE, WeightType::F32)
    else {
        return;
    };
    let ids = [0, 1, 2, 1];
    let _ = t5.hidden(&ids);
    let _ = t5.sentence_embedding(&ids, &[1, 1, 1, 0]);
});
