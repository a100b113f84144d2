//! The `flame.config` JSON of a fixture model mutated on its own (the rest of the file stays
//! valid), so configuration mutations reach the loaders quickly. The first byte picks the
//! fixture; the rest, made UTF-8 the lossy way, is the configuration text.
#![no_main]

use flame_fuzz::{with_config, FIXTURES};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, config)) = data.split_first() else {
        return;
    };
    let file = with_config(
        pick as usize % FIXTURES.len(),
        &String::from_utf8_lossy(config),
    );
    if let Ok(model) = flame::models::Model::from_bytes(&file) {
        // A model that loads can encode the empty prompt (its unconditional input).
        let _ = model.uncond();
    }
});
