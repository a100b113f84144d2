//! The safetensors header (tensor table, metadata, configuration and tokenizer text) of a
//! fixture model mutated on its own, followed by that fixture's unchanged tensor data. The
//! first byte picks the fixture.
#![no_main]

use flame_fuzz::{join, split, FIXTURES};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, header)) = data.split_first() else {
        return;
    };
    let (_, tensors) = split(FIXTURES[pick as usize % FIXTURES.len()]);
    let _ = flame::models::Model::from_bytes(&join(header, tensors));
});
