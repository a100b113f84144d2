//! The safetensors header of a fixture model mutated on its own, followed by that fixture's
//! unchanged tensor data, through what checks it: `ModelFile::from_bytes` (header length, JSON,
//! dtypes, shapes, data offsets against the data) and `Config::from_file` (the configuration
//! parsed, bounded and checked against the tensor table). The first byte picks the fixture
//! (any of the five families).
//!
//! Parse and validate only: the whole build of a header that passes is `model_load`'s. Seeded
//! with the fixtures' headers without their `flame.tokenizer` text (~50 KB of the ~72 KB, a
//! JSON string here; what the build makes of it is `model_load`'s), so mutations land in the
//! tensor table and the configuration.
#![no_main]

use std::cell::RefCell;

use flame::checkpoint::ModelFile;
use flame::config::Config;
use flame_fuzz::{join_into, split, MODEL_FIXTURES};
use libfuzzer_sys::fuzz_target;

thread_local! {
    static FILE: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, header)) = data.split_first() else {
        return;
    };
    let (_, tensors) = split(MODEL_FIXTURES[pick as usize % MODEL_FIXTURES.len()]);
    FILE.with_borrow_mut(|buf| {
        if let Ok(file) = ModelFile::from_bytes(join_into(buf, header, tensors)) {
            let _ = Config::from_file(&file);
        }
    });
});
