//! Shared pieces of the fuzz targets: the fixture model files, split into their safetensors
//! header and tensor data so a target can mutate one part and keep the other valid.

/// The three small model files of the test fixtures (FLAME, MDM, Motion Flow Matching).
pub static FIXTURES: [&[u8]; 3] = [
    include_bytes!("../../tests/fixtures/flame_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/mdm_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/motionfm_tiny.safetensors"),
];

/// Every fixture model family: [`FIXTURES`], the latent models (MLD, MoLA), FineMoGen, the
/// OMG-style model and MotionLCM v1 and v2, without and with a trajectory ControlNet. The model header targets pick from these; the others keep [`FIXTURES`],
/// which their seeds' pick bytes were made for.
pub static MODEL_FIXTURES: [&[u8]; 11] = [
    FIXTURES[0],
    FIXTURES[1],
    FIXTURES[2],
    include_bytes!("../../tests/fixtures/mld_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/mola_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/finemogen_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/omg_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/motionlcm_v1_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/motionlcm_v2_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/motionlcm_v1_control_tiny.safetensors"),
    include_bytes!("../../tests/fixtures/motionlcm_v2_control_tiny.safetensors"),
];

/// A safetensors file's header JSON text and its tensor data.
pub fn split(file: &[u8]) -> (&[u8], &[u8]) {
    let n = u64::from_le_bytes(file[..8].try_into().expect("8 bytes")) as usize;
    (&file[8..8 + n], &file[8 + n..])
}

/// A safetensors file from a header text and tensor data (the header is not checked).
pub fn join(header: &[u8], data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 + header.len() + data.len());
    out.extend_from_slice(&(header.len() as u64).to_le_bytes());
    out.extend_from_slice(header);
    out.extend_from_slice(data);
    out
}

/// [`join`] into a buffer kept across executions: a fresh 1 MB vector per input (pages mapped,
/// faulted in and unmapped again under AddressSanitizer) cost more than parsing the header.
pub fn join_into<'a>(buf: &'a mut Vec<u8>, header: &[u8], data: &[u8]) -> &'a [u8] {
    buf.clear();
    buf.extend_from_slice(&(header.len() as u64).to_le_bytes());
    buf.extend_from_slice(header);
    buf.extend_from_slice(data);
    buf
}

/// Fixture `i`'s file with its `flame.config` metadata replaced by `config`.
pub fn with_config(i: usize, config: &str) -> Vec<u8> {
    let (header, data) = split(FIXTURES[i]);
    let mut h: serde_json::Value = serde_json::from_slice(header).expect("fixture header is JSON");
    h["__metadata__"]["flame.config"] = serde_json::Value::String(config.to_string());
    let mut text = serde_json::to_vec(&h).expect("serialisable");
    // safetensors pads headers with spaces to 8 bytes; keep the data aligned the same way.
    while text.len() % 8 != 0 {
        text.push(b' ');
    }
    join(&text, data)
}

/// A mutated header (`data` after its first byte) followed by the tensor data of the fixture
/// the first byte picks, parsed as a whole file (`None` for empty input). The file is assembled
/// in a buffer kept across inputs: a fresh 1 MB vector per input is a large part of a run.
pub fn header_over_fixture(data: &[u8]) -> Option<flame::Result<flame::checkpoint::ModelFile>> {
    thread_local! {
        static FILE: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    let (&pick, header) = data.split_first()?;
    let (_, tensors) = split(MODEL_FIXTURES[pick as usize % MODEL_FIXTURES.len()]);
    Some(FILE.with_borrow_mut(|buf| {
        flame::checkpoint::ModelFile::from_bytes(join_into(buf, header, tensors))
    }))
}

/// Little-endian fields read off a fuzz input; zeros once it runs out.
pub struct Input<'a>(pub &'a [u8]);

impl Input<'_> {
    pub fn bytes<const N: usize>(&mut self) -> [u8; N] {
        let mut b = [0u8; N];
        let n = N.min(self.0.len());
        b[..n].copy_from_slice(&self.0[..n]);
        self.0 = &self.0[n..];
        b
    }
    pub fn u8(&mut self) -> u8 {
        self.bytes::<1>()[0]
    }
    pub fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.bytes())
    }
    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.bytes())
    }
    pub fn i32(&mut self) -> i32 {
        i32::from_le_bytes(self.bytes())
    }
    pub fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.bytes())
    }
    pub fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.bytes())
    }
}

/// Thread counts that start threads stay small (0 = one per core, 1 or 2): a count the library
/// accepts (up to `FLAME_MAX_THREADS`, 256) would start that many threads per execution. Counts
/// above the bound, which must be refused before any thread starts, are passed as fuzzed.
pub fn bounded_threads(raw: u32) -> u32 {
    if raw as usize > flame::pool::MAX_THREADS {
        raw
    } else {
        raw % 3
    }
}

/// True for `Ok`; a caught panic (`Internal`) is a finding.
pub fn ok(status: flame::ffi::FlameStatus) -> bool {
    assert_ne!(
        status,
        flame::ffi::FlameStatus::Internal,
        "a panic reached the C boundary"
    );
    status == flame::ffi::FlameStatus::Ok
}
