//! Whole model files through the whole load path: safetensors header, metadata, configuration,
//! tensor table and shapes, tokenizer, weight packing.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = flame::models::Model::from_bytes(data);
});
