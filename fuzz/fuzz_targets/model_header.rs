//! The safetensors header (tensor table, metadata, configuration and tokenizer text) of a
//! fixture model mutated on its own, followed by that fixture's unchanged tensor data. The
//! first byte picks the fixture.
//!
//! Cheapest first: `ModelFile::from_bytes` (header length, JSON, dtypes, shapes, data
//! offsets against the data), then `Config::from_file` (the configuration parsed and checked
//! against the tensor table); only a header that passes both (its declared sizes are then
//! those of tensors in the fixture's ~1 MB of data) is built into a model, which reads the
//! tokenizer text and every tensor.
#![no_main]

use flame::checkpoint::ModelFile;
use flame::config::Config;
use flame_fuzz::{join, split, FIXTURES};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, header)) = data.split_first() else {
        return;
    };
    let (_, tensors) = split(FIXTURES[pick as usize % FIXTURES.len()]);
    let Ok(file) = ModelFile::from_bytes(&join(header, tensors)) else {
        return;
    };
    if Config::from_file(&file).is_err() {
        return;
    }
    let _ = flame::models::Model::from_file(file);
});
