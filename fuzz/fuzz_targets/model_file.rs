//! Whole model files through the whole load path: safetensors header, metadata, configuration,
//! tensor table and shapes, tokenizer, weight packing.
//!
//! Cheapest first: `ModelFile::from_bytes` (header and tensor table against the file size),
//! `Config::from_file` (configuration against the table), then the whole build. The build
//! reads tensor values only to convert them (f16/bf16 to f32, defined for every bit pattern)
//! and pack them, and int8 weights' values and scales to check them, so its path is mostly set
//! by the header and the file length: it runs for every
//! header (with length) not built before, and for one in 16 of the inputs that change only
//! the tensor data of a header already built (most mutations of a 1 MB file land there).
#![no_main]

use std::collections::HashSet;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::Mutex;

use flame::checkpoint::ModelFile;
use flame::config::Config;
use libfuzzer_sys::fuzz_target;

fn hash(parts: &[&[u8]]) -> u64 {
    let mut h = DefaultHasher::new();
    parts.hash(&mut h);
    h.finish()
}

fuzz_target!(|data: &[u8]| {
    let Ok(file) = ModelFile::from_bytes(data) else {
        return;
    };
    if Config::from_file(&file).is_err() {
        return;
    }
    // A valid file has an 8-byte header length and that many header bytes.
    let n = u64::from_le_bytes(data[..8].try_into().unwrap()) as usize;
    let (header, tensors) = data.split_at(8 + n);
    let len = (data.len() as u64).to_le_bytes();
    static BUILT: Mutex<Option<HashSet<u64>>> = Mutex::new(None);
    let new_header = BUILT
        .lock()
        .unwrap()
        .get_or_insert_with(HashSet::new)
        .insert(hash(&[header, &len]));
    if new_header || hash(&[tensors]) % 16 == 0 {
        // A quantised file (`flame quantize`) is also built as int8, which packs its integers
        // and scales as stored rather than multiplying them out.
        let quantized = file.metadata(flame::quantize::QUANTIZATION_KEY).is_some();
        let int8 = flame::kernels::WeightType::Int8;
        if quantized && int8.native_on_this_cpu() {
            let opts = flame::models::LoadOptions { weights: int8 };
            if let Ok(again) = ModelFile::from_bytes(data) {
                let _ = flame::models::Model::from_file_with(again, &opts);
            }
        }
        let _ = flame::models::Model::from_file(file);
    }
});
