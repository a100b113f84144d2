//! The `flame.config` JSON of a fixture model mutated on its own. The first byte picks the
//! fixture; the rest, made UTF-8 the lossy way, is the configuration text. It goes through
//! what a load does with it, cheapest first: `Config::from_json` (parsing, bounds, the fields
//! against each other), then `Config::validate` against the fixture's parsed tensor table
//! (parsed once), and, for a configuration that passes both, the whole load with that text in
//! the file, then the unconditional prompt.
//!
//! A whole load runs once per distinct set of the fields it reads after validation
//! (architecture, denoiser, text encoder, motion format, unconditional input): a second
//! configuration that differs only elsewhere (fps, defaults, schedule) takes the same path
//! through the loaders, which is what keeps this target at thousands of executions a second.
#![no_main]

use std::collections::HashSet;
use std::sync::{Mutex, OnceLock};

use flame::checkpoint::ModelFile;
use flame::config::Config;
use flame_fuzz::{with_config, FIXTURES};
use libfuzzer_sys::fuzz_target;

fn files() -> &'static [ModelFile] {
    static F: OnceLock<Vec<ModelFile>> = OnceLock::new();
    F.get_or_init(|| {
        FIXTURES
            .iter()
            .map(|b| ModelFile::from_bytes(b).expect("fixture parses"))
            .collect()
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, config)) = data.split_first() else {
        return;
    };
    let i = pick as usize % FIXTURES.len();
    let text = String::from_utf8_lossy(config);
    let Ok(cfg) = Config::from_json(&text) else {
        return;
    };
    if cfg.validate(&files()[i]).is_err() {
        return;
    }
    static LOADED: Mutex<Option<HashSet<String>>> = Mutex::new(None);
    let key = format!(
        "{i}|{}|{:?}|{:?}|{}|{}",
        cfg.architecture, cfg.denoiser, cfg.text_encoder, cfg.motion.format, cfg.diffusion.uncond
    );
    if !LOADED
        .lock()
        .unwrap()
        .get_or_insert_with(HashSet::new)
        .insert(key)
    {
        return;
    }
    // A load may still refuse the file (an error, as any), but must not crash.
    if let Ok(model) = flame::models::Model::from_bytes(&with_config(i, &text)) {
        let _ = model.uncond();
    }
});
