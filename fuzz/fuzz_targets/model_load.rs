//! The safetensors header of a fixture model (tensor table, metadata, configuration and the
//! `flame.tokenizer` text) mutated on its own, followed by that fixture's unchanged tensor data,
//! through the whole load: `ModelFile::from_bytes`, `Config::from_file` and, for a header that
//! passes both, `Model::from_file` (the tokenizer built from the text, every tensor read,
//! checked and packed). The first byte picks the fixture (any of the seven families).
//!
//! The validated header's sizes are those of tensors inside the fixture's ~1 MB of data, so a
//! configuration size that escaped validation and drives an allocation shows up here as an
//! allocation beyond the memory cap. `model_header` runs the parse and validation alone, much
//! faster; this target is the build behind them. Seeded at run time with the fixtures' whole
//! headers (~37 to 72 KB each).
#![no_main]

use flame::config::Config;
use flame_fuzz::header_over_fixture;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some(Ok(file)) = header_over_fixture(data) else {
        return;
    };
    if Config::from_file(&file).is_err() {
        return;
    }
    let _ = flame::models::Model::from_file(file);
});
