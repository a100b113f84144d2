//! The model file: a `.safetensors` file opened by memory-mapping (or from caller bytes),
//! validated, and read out as typed `f32` tensors.
//!
//! A libflame model file carries, in the safetensors metadata, `format = "libflame"`, the model
//! configuration as JSON under `flame.config` (see [`crate::config`]) and the tokenizer.json text
//! under `flame.tokenizer`. Plain safetensors files (for example a Hugging Face text encoder)
//! open too; only reading the configuration ([`Config::from_file`]) needs the metadata.
//!
//! f32 tensors are borrowed straight from the mapping (one copy of the weights, in the page
//! cache); f16 and bf16 tensors are widened to f32 once at load. Linear weights, which the models
//! pack into their own layout, are [released](crate::checkpoint::ModelFile::release) as soon as they are packed.
//!
//! [`Config::from_file`]: crate::config::Config::from_file

use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::Arc;

use half::{bf16, f16};
use memmap2::Mmap;
use safetensors::tensor::{Dtype, Metadata, SafeTensorError};
use safetensors::SafeTensors;

use crate::error::{bad_file, Error, Result};

/// Metadata key holding the JSON configuration.
pub const CONFIG_KEY: &str = "flame.config";
/// Metadata key holding the tokenizer.json text.
pub const TOKENIZER_KEY: &str = "flame.tokenizer";
/// Metadata key whose value `libflame` marks a libflame model file.
pub const FORMAT_KEY: &str = "format";

/// Where the file's bytes live.
enum Backing {
    Mapped(Mmap),
    /// Caller bytes copied into 8-byte-aligned storage so f32 data can be borrowed in place.
    Heap {
        words: Vec<u64>,
        len: usize,
    },
}

impl Backing {
    fn bytes(&self) -> &[u8] {
        match self {
            Backing::Mapped(m) => m,
            // SAFETY: `words` owns at least `len` initialised bytes; u8 has no alignment needs.
            Backing::Heap { words, len } => unsafe {
                std::slice::from_raw_parts(words.as_ptr() as *const u8, *len)
            },
        }
    }
}

/// Metadata key of a quantised model file (written by [`crate::quantize`]): a JSON object
/// saying how it was quantised. Its float linear weights stay f32 when it loads as int8.
pub const QUANTIZATION_KEY: &str = "flame.quantization";

/// The weights of a quantised file's int8 tensor multiplied back out: `q` is `[n, k]`, `scales`
/// `[n, ⌈k/group⌉]` (one per output row when `group ≥ k`), input `i` of row `r` scaled by
/// `scales[r][i / group]`.
pub(crate) fn dequantize_int8(q: &[i8], scales: &[f32], k: usize, group: usize) -> Vec<f32> {
    let (k, group) = (k.max(1), group.max(1));
    let per_row = k.div_ceil(group);
    q.chunks_exact(k)
        .zip(scales.chunks_exact(per_row))
        .flat_map(|(row, s)| {
            row.iter()
                .enumerate()
                .map(move |(i, &v)| v as f32 * s[i / group])
        })
        .collect()
}

/// Element type of a stored tensor, as far as libflame reads it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StoredDtype {
    /// 32-bit IEEE float, borrowed from the file as it is.
    F32,
    /// IEEE half precision, widened to f32 at load.
    F16,
    /// bfloat16, widened to f32 at load.
    Bf16,
    /// Signed 8-bit integers: the weights of a quantised linear layer, read with their scales
    /// ([`ModelFile::tensor_i8`]), never as f32 values.
    I8,
}

impl StoredDtype {
    /// The lower-case name messages and `flame info` print (`f32`, `f16`, `bf16`).
    pub fn name(self) -> &'static str {
        match self {
            StoredDtype::F32 => "f32",
            StoredDtype::F16 => "f16",
            StoredDtype::Bf16 => "bf16",
            StoredDtype::I8 => "i8",
        }
    }
}

struct Entry {
    dtype: Dtype,
    shape: Vec<usize>,
    /// Absolute byte range in the backing.
    start: usize,
    end: usize,
}

/// An opened, header-validated safetensors file.
pub struct ModelFile {
    backing: Arc<Backing>,
    entries: HashMap<String, Entry>,
    metadata: HashMap<String, String>,
    source: String,
}

/// A read-only `f32` tensor: borrowed from the file's mapping or owned after widening.
pub struct Tensor {
    data: TensorData,
    shape: Vec<usize>,
}

enum TensorData {
    Borrowed {
        backing: Arc<Backing>,
        offset: usize,
        len: usize,
    },
    Owned(Vec<f32>),
}

impl Tensor {
    /// An owned tensor (used for derived weights and in tests).
    pub fn from_vec(shape: Vec<usize>, data: Vec<f32>) -> Tensor {
        assert_eq!(
            shape.iter().product::<usize>(),
            data.len(),
            "shape does not match data"
        );
        Tensor {
            data: TensorData::Owned(data),
            shape,
        }
    }

    /// The values, row-major: borrowed from the file's mapping for f32 tensors, owned otherwise.
    pub fn data(&self) -> &[f32] {
        match &self.data {
            TensorData::Owned(v) => v,
            TensorData::Borrowed {
                backing,
                offset,
                len,
            } => {
                let bytes = &backing.bytes()[*offset..*offset + *len * 4];
                // SAFETY: alignment to 4 was checked when the tensor was created, the range lies
                // inside the backing (validated header), and any bit pattern is a valid f32.
                unsafe { std::slice::from_raw_parts(bytes.as_ptr() as *const f32, *len) }
            }
        }
    }

    /// The dimensions, outermost first.
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// Whether the data is read in place from the file (no copy).
    pub fn is_mapped(&self) -> bool {
        matches!(self.data, TensorData::Borrowed { .. })
    }
}

impl std::fmt::Debug for Tensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Tensor{:?}", self.shape)
    }
}

impl ModelFile {
    /// Memory-maps and validates `path`.
    pub fn open(path: &Path) -> Result<ModelFile> {
        let io = |source| Error::Io {
            path: path.display().to_string(),
            source,
        };
        let file = File::open(path).map_err(io)?;
        // A folder opens on Unix and then fails to map with "No such device": say what it is.
        if file.metadata().map_err(io)?.is_dir() {
            return Err(io(std::io::Error::other(
                "it is a folder, not a model file",
            )));
        }
        // SAFETY: the mapping is read-only; a file truncated by another process while mapped is
        // outside what any mmap-based loader can defend against and is documented as such.
        let map = unsafe { Mmap::map(&file) }.map_err(io)?;
        let header = parse_header(&map)?;
        Ok(Self::from_backing(
            Backing::Mapped(map),
            header,
            path.display().to_string(),
        ))
    }

    /// Validates `bytes` (the whole file) and copies them. The header is checked first, so
    /// bytes that are not a model file are refused without copying them.
    pub fn from_bytes(bytes: &[u8]) -> Result<ModelFile> {
        let header = parse_header(bytes)?;
        let mut words = vec![0u64; bytes.len().div_ceil(8)];
        // SAFETY: `words` has room for `bytes.len()` bytes and the regions do not overlap.
        unsafe {
            std::ptr::copy_nonoverlapping(
                bytes.as_ptr(),
                words.as_mut_ptr() as *mut u8,
                bytes.len(),
            )
        };
        Ok(Self::from_backing(
            Backing::Heap {
                words,
                len: bytes.len(),
            },
            header,
            "<memory>".into(),
        ))
    }

    /// The file over `backing`, whose bytes `parse_header` has validated as `(header_len, meta)`.
    fn from_backing(
        backing: Backing,
        (header_len, meta): (usize, Metadata),
        source: String,
    ) -> ModelFile {
        let data_start = 8 + header_len;
        let mut entries = HashMap::new();
        for (name, info) in meta.tensors() {
            let (s, e) = info.data_offsets;
            entries.insert(
                name,
                Entry {
                    dtype: info.dtype,
                    shape: info.shape.clone(),
                    start: data_start + s,
                    end: data_start + e,
                },
            );
        }
        let metadata = meta.metadata().clone().unwrap_or_default();
        ModelFile {
            backing: Arc::new(backing),
            entries,
            metadata,
            source,
        }
    }

    /// Where the file came from (a path, or `<memory>`).
    pub fn source(&self) -> &str {
        &self.source
    }

    /// A metadata value of the safetensors header.
    pub fn metadata(&self, key: &str) -> Option<&str> {
        self.metadata.get(key).map(String::as_str)
    }

    /// For a quantised file ([`QUANTIZATION_KEY`]) whose int8 weights have one scale per group of
    /// inputs rather than per output row, the group size; `None` for per-row scales or a file
    /// that is not quantised. A malformed record is an error.
    pub fn int8_group(&self) -> Result<Option<usize>> {
        let Some(text) = self.metadata(QUANTIZATION_KEY) else {
            return Ok(None);
        };
        let record: serde_json::Value = serde_json::from_str(text)
            .map_err(|e| bad_file!("metadata `{QUANTIZATION_KEY}` is not JSON: {e}"))?;
        match record.get("group") {
            None => Ok(None),
            Some(g) => match g.as_u64() {
                Some(g) if g >= 1 && g <= u32::MAX as u64 => Ok(Some(g as usize)),
                _ => Err(bad_file!(
                    "metadata `{QUANTIZATION_KEY}`: group {g} is not a positive whole number"
                )),
            },
        }
    }

    /// The tensor names, sorted.
    pub fn names(&self) -> Vec<&str> {
        let mut v: Vec<&str> = self.entries.keys().map(String::as_str).collect();
        v.sort_unstable();
        v
    }

    /// Whether any stored tensor's name starts with `prefix` (a layer of a stack, say).
    pub fn has_prefix(&self, prefix: &str) -> bool {
        self.entries.keys().any(|n| n.starts_with(prefix))
    }

    /// Whether a tensor of that name is stored.
    pub fn contains(&self, name: &str) -> bool {
        self.entries.contains_key(name)
    }

    /// The stored dtype of a tensor, or an error naming it when missing or unsupported.
    pub fn dtype(&self, name: &str) -> Result<StoredDtype> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| bad_file!("tensor `{name}` is missing"))?;
        stored_dtype(name, e.dtype)
    }

    /// The stored dtype most tensors use (for reporting).
    pub fn dominant_dtype(&self) -> Option<StoredDtype> {
        let mut counts = [0usize; 4];
        for e in self.entries.values() {
            match e.dtype {
                Dtype::F32 => counts[0] += e.end - e.start,
                Dtype::F16 => counts[1] += e.end - e.start,
                Dtype::BF16 => counts[2] += e.end - e.start,
                Dtype::I8 => counts[3] += e.end - e.start,
                _ => {}
            }
        }
        let (i, &n) = counts.iter().enumerate().max_by_key(|(_, n)| **n)?;
        (n > 0).then(|| {
            [
                StoredDtype::F32,
                StoredDtype::F16,
                StoredDtype::Bf16,
                StoredDtype::I8,
            ][i]
        })
    }

    /// Reads the int8 tensor `name` of shape `shape` (a quantised linear weight).
    pub fn tensor_i8(&self, name: &str, shape: &[usize]) -> Result<Vec<i8>> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| bad_file!("tensor `{name}` is missing"))?;
        if e.dtype != Dtype::I8 {
            return Err(bad_file!(
                "tensor `{name}` is {:?}, expected I8 (a quantised weight)",
                e.dtype
            ));
        }
        if e.shape != shape {
            return Err(bad_file!(
                "tensor `{name}` has shape {:?}, expected {:?}",
                e.shape,
                shape
            ));
        }
        Ok(self.backing.bytes()[e.start..e.end]
            .iter()
            .map(|&b| b as i8)
            .collect())
    }

    /// Reads tensor `name`, checking that its shape is exactly `shape`.
    pub fn tensor(&self, name: &str, shape: &[usize]) -> Result<Tensor> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| bad_file!("tensor `{name}` is missing"))?;
        if e.shape != shape {
            return Err(bad_file!(
                "tensor `{name}` has shape {:?}, expected {:?}",
                e.shape,
                shape
            ));
        }
        self.read(name, e)
    }

    /// Reads tensor `name` whatever its shape (the caller checks what it needs).
    pub fn tensor_any_shape(&self, name: &str) -> Result<Tensor> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| bad_file!("tensor `{name}` is missing"))?;
        self.read(name, e)
    }

    /// The stored shape of a tensor.
    pub fn shape(&self, name: &str) -> Result<&[usize]> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| bad_file!("tensor `{name}` is missing"))?;
        Ok(&e.shape)
    }

    /// Tells the OS that tensor `name`'s mapped pages will not be read again, once the caller has
    /// copied what it needs (linear weights packed at load). The pages leave the process's
    /// resident set, so a packed model does not hold the weights twice; should anything read
    /// them after all, they are read again from the file. A no-op for caller bytes, unknown names
    /// and non-Linux systems.
    pub fn release(&self, name: &str) {
        #[cfg(target_os = "linux")]
        if let (Backing::Mapped(map), Some(e)) = (&*self.backing, self.entries.get(name)) {
            // SAFETY: the mapping is read-only and backed by the file (shared), so MADV_DONTNEED
            // drops clean page-cache references only: a later read faults the same bytes back
            // in, and no borrowed tensor can observe a change. The range lies inside the map
            // (validated header). Failure only means the pages stay resident.
            let _ = unsafe {
                map.unchecked_advise_range(
                    memmap2::UncheckedAdvice::DontNeed,
                    e.start,
                    e.end - e.start,
                )
            };
        }
        #[cfg(not(target_os = "linux"))]
        let _ = name;
    }

    fn read(&self, name: &str, e: &Entry) -> Result<Tensor> {
        let bytes = &self.backing.bytes()[e.start..e.end];
        let shape = e.shape.clone();
        let data = match stored_dtype(name, e.dtype)? {
            StoredDtype::F32 => {
                let aligned = (bytes.as_ptr() as usize).is_multiple_of(4);
                if aligned && cfg!(target_endian = "little") {
                    TensorData::Borrowed {
                        backing: Arc::clone(&self.backing),
                        offset: e.start,
                        len: bytes.len() / 4,
                    }
                } else {
                    TensorData::Owned(
                        bytes
                            .chunks_exact(4)
                            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                            .collect(),
                    )
                }
            }
            StoredDtype::F16 => TensorData::Owned(
                bytes
                    .chunks_exact(2)
                    .map(|b| f16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32())
                    .collect(),
            ),
            StoredDtype::Bf16 => TensorData::Owned(
                bytes
                    .chunks_exact(2)
                    .map(|b| bf16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32())
                    .collect(),
            ),
            StoredDtype::I8 => {
                return Err(bad_file!(
                    "tensor `{name}` is int8, which libflame reads only as a quantised linear \
                     weight with its `{name}_scale`"
                ))
            }
        };
        Ok(Tensor { data, shape })
    }
}

fn stored_dtype(name: &str, d: Dtype) -> Result<StoredDtype> {
    match d {
        Dtype::F32 => Ok(StoredDtype::F32),
        Dtype::F16 => Ok(StoredDtype::F16),
        Dtype::BF16 => Ok(StoredDtype::Bf16),
        Dtype::I8 => Ok(StoredDtype::I8),
        other => Err(bad_file!(
            "tensor `{name}` has unsupported dtype {other:?} (supported: F32, F16, BF16, and I8 \
             for quantised weights)"
        )),
    }
}

/// Parses and validates the safetensors header, turning the crate's terse errors into messages
/// that say what is wrong with the file.
fn parse_header(bytes: &[u8]) -> Result<(usize, Metadata)> {
    if bytes.len() < 8 {
        return Err(bad_file!(
            "file is {} bytes long, too short for a safetensors header (truncated or not a model file)",
            bytes.len()
        ));
    }
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
    if n > (bytes.len() as u64).saturating_sub(8) {
        return Err(bad_file!(
            "header length {n} exceeds the file size {} (truncated or not a safetensors file)",
            bytes.len()
        ));
    }
    let header = &bytes[8..8 + n as usize];
    if header.first() != Some(&b'{') {
        return Err(bad_file!(
            "header does not start with '{{' (not a safetensors file)"
        ));
    }
    if std::str::from_utf8(header).is_err() {
        return Err(bad_file!("header is not valid UTF-8"));
    }
    SafeTensors::read_metadata(bytes).map_err(|e| match e {
        SafeTensorError::InvalidHeaderDeserialization | SafeTensorError::JsonError(_) => {
            match serde_json::from_slice::<serde_json::Value>(header) {
                Err(j) => bad_file!("header is not valid JSON: {j}"),
                Ok(_) => bad_file!("header JSON does not describe safetensors tensors"),
            }
        }
        SafeTensorError::MetadataIncompleteBuffer => {
            bad_file!("tensor data does not match the file size (truncated or padded file)")
        }
        SafeTensorError::InvalidOffset(t) => bad_file!("tensor `{t}` has invalid data offsets"),
        SafeTensorError::TensorInvalidInfo => {
            bad_file!("a tensor's byte size does not match its dtype and shape")
        }
        SafeTensorError::HeaderTooLarge => bad_file!("header is too large"),
        SafeTensorError::ValidationOverflow => {
            bad_file!("a tensor's shape overflows its byte size (corrupt header)")
        }
        other => bad_file!("invalid safetensors header: {other:?}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use safetensors::tensor::TensorView;

    fn write(
        tensors: &[(&str, Dtype, Vec<usize>, Vec<u8>)],
        meta: Option<HashMap<String, String>>,
    ) -> Vec<u8> {
        let views: Vec<(String, TensorView)> = tensors
            .iter()
            .map(|(n, d, s, b)| (n.to_string(), TensorView::new(*d, s.clone(), b).unwrap()))
            .collect();
        safetensors::serialize(views, &meta).unwrap()
    }

    fn f32_bytes(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn reads_f32_in_place_and_widens_half_types() {
        let vals = [1.5f32, -2.0, 0.25, 3.0];
        let h: Vec<u8> = vals
            .iter()
            .flat_map(|x| f16::from_f32(*x).to_bits().to_le_bytes())
            .collect();
        let b: Vec<u8> = vals
            .iter()
            .flat_map(|x| bf16::from_f32(*x).to_bits().to_le_bytes())
            .collect();
        let bytes = write(
            &[
                ("a", Dtype::F32, vec![2, 2], f32_bytes(&vals)),
                ("h", Dtype::F16, vec![4], h),
                ("b", Dtype::BF16, vec![4], b),
            ],
            None,
        );
        let f = ModelFile::from_bytes(&bytes).unwrap();
        let a = f.tensor("a", &[2, 2]).unwrap();
        assert!(a.is_mapped());
        assert_eq!(a.data(), &vals);
        assert_eq!(f.tensor("h", &[4]).unwrap().data(), &vals);
        assert_eq!(f.tensor("b", &[4]).unwrap().data(), &vals);
        assert_eq!(f.dtype("h").unwrap(), StoredDtype::F16);
    }

    #[test]
    fn names_the_bad_tensor() {
        let bytes = write(
            &[
                ("w", Dtype::F32, vec![2], f32_bytes(&[1.0, 2.0])),
                ("i", Dtype::I64, vec![1], vec![0; 8]),
            ],
            None,
        );
        let f = ModelFile::from_bytes(&bytes).unwrap();
        let e = f.tensor("w", &[3]).unwrap_err().to_string();
        assert_eq!(e, "bad model file: tensor `w` has shape [2], expected [3]");
        let e = f.tensor("x", &[3]).unwrap_err().to_string();
        assert_eq!(e, "bad model file: tensor `x` is missing");
        let e = f.tensor("i", &[1]).unwrap_err().to_string();
        assert!(e.contains("tensor `i` has unsupported dtype I64"), "{e}");
    }

    #[test]
    fn rejects_broken_headers() {
        let good = write(&[("w", Dtype::F32, vec![2], f32_bytes(&[1.0, 2.0]))], None);
        let msg = |b: &[u8]| {
            ModelFile::from_bytes(b)
                .err()
                .expect("must fail")
                .to_string()
        };
        assert!(msg(&good[..5]).contains("too short"));
        assert!(msg(&good[..good.len() - 1]).contains("truncated"));
        let mut huge = good.clone();
        huge[..8].copy_from_slice(&(1u64 << 40).to_le_bytes());
        assert!(msg(&huge).contains("exceeds the file size"));
        let mut not_json = good.clone();
        not_json[9] = b'#';
        assert!(
            msg(&not_json).contains("not valid JSON"),
            "{}",
            msg(&not_json)
        );
        let mut not_st = good.clone();
        not_st[8] = b'[';
        assert!(msg(&not_st).contains("does not start"));
        assert!(msg(b"hello world, this is text").contains("exceeds the file size"));
        let mut huge = good.clone();
        huge[..8].copy_from_slice(&(1u64 << 63).to_le_bytes());
        assert!(msg(&huge).contains("exceeds the file size"));
    }

    /// A header whose JSON is `json`, followed by `data` bytes of tensor data.
    fn raw(json: &str, data: usize) -> Vec<u8> {
        let mut b = (json.len() as u64).to_le_bytes().to_vec();
        b.extend_from_slice(json.as_bytes());
        b.resize(b.len() + data, 0);
        b
    }

    #[test]
    fn rejects_sizes_that_overflow_or_point_outside() {
        let msg = |b: &[u8]| {
            ModelFile::from_bytes(b)
                .err()
                .expect("must fail")
                .to_string()
        };
        // 2^32 × 2^32 elements overflow usize before any byte is counted.
        let e = msg(&raw(
            r#"{"w":{"dtype":"F32","shape":[4294967296,4294967296],"data_offsets":[0,8]}}"#,
            8,
        ));
        assert!(e.contains("overflows its byte size"), "{e}");
        // Offsets past the data, and a range whose size disagrees with the shape.
        let e = msg(&raw(
            r#"{"w":{"dtype":"F32","shape":[2],"data_offsets":[0,8000000000]}}"#,
            8,
        ));
        assert!(e.contains("does not match"), "{e}");
        let e = msg(&raw(
            r#"{"w":{"dtype":"F32","shape":[2],"data_offsets":[4,12]}}"#,
            12,
        ));
        assert!(e.contains("invalid data offsets"), "{e}");
    }
}
