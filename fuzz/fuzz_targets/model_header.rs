//! The safetensors header of a fixture model mutated on its own, followed by that fixture's
//! unchanged tensor data, through what checks it: `ModelFile::from_bytes` (header length, JSON,
//! dtypes, shapes, data offsets against the data) and `Config::from_file` (the configuration
//! parsed, bounded and checked against the tensor table). The first byte picks the fixture
//! (any of the seven families).
//!
//! Parse and validate only: the whole build of a header that passes is `model_load`'s. Seeded
//! with the fixtures' headers without their `flame.tokenizer` text (~50 KB of the ~72 KB, a
//! JSON string here; what the build makes of it is `model_load`'s), so mutations land in the
//! tensor table and the configuration.
#![no_main]

use flame::config::Config;
use flame_fuzz::header_over_fixture;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Some(Ok(file)) = header_over_fixture(data) {
        let _ = Config::from_file(&file);
    }
});
