//! Assembling a complete model file from a denoiser-only file and a text encoder shipped
//! elsewhere (the demo model: its denoiser lives in the repository, all-MiniLM-L6-v2 comes from
//! the package registry at set-up).
//!
//! A denoiser-only file is a libflame file written by `tools/convert.py flame --denoiser-only`:
//! configuration, tokenizer and denoiser tensors, no `text.*` tensors, and a `flame.text_source`
//! metadata entry (JSON) saying which text encoder belongs there. [`assemble`] adds the text
//! encoder's tensors from a Hugging Face `model.safetensors` under `text.`, each checked against
//! the configuration, keeping every tensor's stored dtype, and writes the result through a
//! temporary file that is loaded as a [`Model`] before it is renamed into place, so a failure
//! never leaves a half-written or unloadable model behind.
//!
//! The written file is the same bytes on every run: safetensors orders tensors by dtype and name,
//! and [`assemble`] writes the header's metadata sorted by key (the `safetensors` crate keeps it
//! in a `HashMap`, whose order changes from one process to the next).
//!
//! [`AssembleOptions::actions`] records the action families the denoiser was trained on under
//! [`ACTIONS_KEY`] (the CLI passes the demo corpus's families, `flame_demo::Family::ALL`, when it
//! assembles the demo model); `flame info` prints them and `flame generate` warns about prompts
//! that name none of them.
//!
//! Not here: fetching the text encoder (the set-up scripts do that) or checking its hash (the
//! `sha256` in `flame.text_source` is recorded for them).
//!
//! [`Model`]: crate::models::Model
//! [`AssembleOptions::actions`]: crate::assemble::AssembleOptions::actions
//! [`ACTIONS_KEY`]: crate::assemble::ACTIONS_KEY

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

use crate::checkpoint::{ModelFile, CONFIG_KEY, FORMAT_KEY};
use crate::config::{Config, TextConfig, TextEncoderConfig};
use crate::error::{bad_file, invalid_arg, Error, Result};
use crate::models::{Model, TEXT_PREFIX};

/// Metadata key of a denoiser-only file: JSON describing the text encoder to add.
pub const TEXT_SOURCE_KEY: &str = "flame.text_source";
/// Metadata key of an assembled file: the `flame.text_source` it was assembled from.
pub const TEXT_ASSEMBLED_KEY: &str = "flame.text_assembled";

/// Metadata key of an assembled file: the action families its denoiser was trained on, a JSON
/// list of names (`["walk", "run", ...]`). Absent when the assembler was not told.
pub const ACTIONS_KEY: &str = "flame.actions";

/// What [`assemble_with`] adds beyond the two input files.
#[derive(Clone, Debug, Default)]
pub struct AssembleOptions {
    /// The action families the denoiser was trained on, stored under [`ACTIONS_KEY`] when not
    /// empty. Names must be non-empty and free of commas and surrounding spaces.
    pub actions: Vec<String>,
}

/// Hugging Face prefixes of task-model checkpoints around the bare encoder.
const HF_PREFIXES: &[&str] = &["bert.", "roberta."];
/// Buffers and heads a Hugging Face file may hold that the runtime does not run.
const DROP_SUFFIXES: &[&str] = &["embeddings.position_ids", "embeddings.token_type_ids"];
const DROP_PREFIXES: &[&str] = &["lm_head.", "cls."];

/// What [`assemble`] wrote.
#[derive(Clone, Debug)]
pub struct AssembleReport {
    /// Tensors taken from the denoiser-only file.
    pub denoiser_tensors: usize,
    /// Text encoder tensors added under `text.`.
    pub text_tensors: usize,
    /// Tensors of the text weights file that were left out (buffers, heads, unknown names).
    pub dropped: Vec<String>,
    /// Size of the written file in bytes.
    pub bytes: u64,
}

/// Writes `out`: the denoiser-only file `denoiser` plus the text encoder of `text_weights` (a
/// Hugging Face `model.safetensors`). See the module documentation.
pub fn assemble(denoiser: &Path, text_weights: &Path, out: &Path) -> Result<AssembleReport> {
    assemble_with(denoiser, text_weights, out, &AssembleOptions::default())
}

/// [`assemble`] with `opts` (the trained action families).
pub fn assemble_with(
    denoiser: &Path,
    text_weights: &Path,
    out: &Path,
    opts: &AssembleOptions,
) -> Result<AssembleReport> {
    if let Some(bad) = opts
        .actions
        .iter()
        .find(|a| a.is_empty() || a.contains(',') || a.trim() != a.as_str())
    {
        return Err(invalid_arg!(
            "action name {bad:?}: names must be non-empty, without commas or surrounding spaces"
        ));
    }
    let den_bytes = read(denoiser)?;
    let den = parse(&den_bytes, denoiser)?;
    let (config, mut metadata) = denoiser_only(&den_bytes, &den, denoiser)?;
    let text_cfg = match &config.text_encoder {
        TextConfig::Bert(t) => t,
        other @ (TextConfig::Clip(_) | TextConfig::T5(_)) => {
            return Err(bad_file!(
                "{}: assembling a {} text encoder is not supported",
                denoiser.display(),
                other.kind()
            ))
        }
    };
    let text_bytes = read(text_weights)?;
    let text = parse(&text_bytes, text_weights)?;
    let (text_tensors, dropped) = text_encoder_tensors(&text, text_cfg, text_weights)?;

    let source = metadata.remove(TEXT_SOURCE_KEY).unwrap_or_default();
    metadata.insert(TEXT_ASSEMBLED_KEY.to_string(), source);
    metadata.remove(ACTIONS_KEY);
    if !opts.actions.is_empty() {
        let list = serde_json::to_string(&opts.actions).expect("a list of strings serialises");
        metadata.insert(ACTIONS_KEY.to_string(), list);
    }
    let mut tensors: Named = den.tensors();
    let denoiser_tensors = tensors.len();
    let text_count = text_tensors.len();
    tensors.extend(
        text_tensors
            .into_iter()
            .map(|(name, view)| (format!("{TEXT_PREFIX}{name}"), view)),
    );
    let bytes = write_checked(tensors, metadata, out)?;
    Ok(AssembleReport {
        denoiser_tensors,
        text_tensors: text_count,
        dropped,
        bytes,
    })
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

fn parse<'a>(bytes: &'a [u8], path: &Path) -> Result<SafeTensors<'a>> {
    SafeTensors::deserialize(bytes)
        .map_err(|e| bad_file!("{}: not a safetensors file: {e:?}", path.display()))
}

/// The configuration and metadata of a denoiser-only file, or why `path` is not one.
fn denoiser_only(
    bytes: &[u8],
    file: &SafeTensors,
    path: &Path,
) -> Result<(Config, HashMap<String, String>)> {
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| bad_file!("{}: not a safetensors file: {e:?}", path.display()))?;
    let metadata = header.metadata().clone().unwrap_or_default();
    let p = path.display();
    if metadata.get(FORMAT_KEY).map(String::as_str) != Some("libflame") {
        return Err(bad_file!(
            "{p}: not a libflame file (no `{FORMAT_KEY}: libflame` metadata)"
        ));
    }
    if !metadata.contains_key(TEXT_SOURCE_KEY) {
        return Err(bad_file!(
            "{p}: not a denoiser-only file (no `{TEXT_SOURCE_KEY}` metadata; write one with \
             tools/convert.py --denoiser-only)"
        ));
    }
    if let Some(name) = file
        .names()
        .into_iter()
        .find(|n| n.starts_with(TEXT_PREFIX))
    {
        return Err(bad_file!(
            "{p}: not a denoiser-only file: it already holds text encoder tensor `{name}`"
        ));
    }
    let json = metadata
        .get(CONFIG_KEY)
        .ok_or_else(|| bad_file!("{p}: no `{CONFIG_KEY}` metadata"))?;
    let config = Config::from_json(json).map_err(|e| bad_file!("{p}: {e}"))?;
    Ok((config, metadata))
}

/// The tensors a BERT/RoBERTa encoder of `cfg` consists of (Hugging Face names, no prefix),
/// with their shapes.
pub fn text_encoder_shapes(cfg: &TextEncoderConfig) -> Vec<(String, Vec<usize>)> {
    let (h, i) = (cfg.hidden_size, cfg.intermediate_size);
    let mut shapes: Vec<(String, Vec<usize>)> = vec![
        (
            "embeddings.word_embeddings.weight".into(),
            vec![cfg.vocab_size, h],
        ),
        (
            "embeddings.position_embeddings.weight".into(),
            vec![cfg.max_position_embeddings, h],
        ),
        (
            "embeddings.token_type_embeddings.weight".into(),
            vec![cfg.type_vocab_size, h],
        ),
        ("embeddings.LayerNorm.weight".into(), vec![h]),
        ("embeddings.LayerNorm.bias".into(), vec![h]),
    ];
    for n in 0..cfg.num_layers {
        let linears = [
            ("attention.self.query", h, h),
            ("attention.self.key", h, h),
            ("attention.self.value", h, h),
            ("attention.output.dense", h, h),
            ("intermediate.dense", i, h),
            ("output.dense", h, i),
        ];
        for (name, rows, cols) in linears {
            shapes.push((format!("encoder.layer.{n}.{name}.weight"), vec![rows, cols]));
            shapes.push((format!("encoder.layer.{n}.{name}.bias"), vec![rows]));
        }
        for norm in ["attention.output.LayerNorm", "output.LayerNorm"] {
            shapes.push((format!("encoder.layer.{n}.{norm}.weight"), vec![h]));
            shapes.push((format!("encoder.layer.{n}.{norm}.bias"), vec![h]));
        }
    }
    shapes.push(("pooler.dense.weight".into(), vec![h, h]));
    shapes.push(("pooler.dense.bias".into(), vec![h]));
    shapes
}

/// Tensors by name, in file order.
pub(crate) type Named<'a> = Vec<(String, TensorView<'a>)>;

/// The encoder's tensors from a Hugging Face file (a `bert.`/`roberta.` prefix stripped),
/// checked against `cfg`, and the names left out.
fn text_encoder_tensors<'a>(
    file: &SafeTensors<'a>,
    cfg: &TextEncoderConfig,
    path: &Path,
) -> Result<(Named<'a>, Vec<String>)> {
    let all = file.tensors();
    let prefix = HF_PREFIXES
        .iter()
        .find(|p| all.iter().any(|(n, _)| n.starts_with(*p)))
        .copied()
        .unwrap_or("");
    let mut by_name: HashMap<String, TensorView<'a>> = HashMap::new();
    let mut dropped = Vec::new();
    for (name, view) in all {
        match name.strip_prefix(prefix) {
            Some(bare)
                if !DROP_SUFFIXES.iter().any(|s| bare.ends_with(s))
                    && !DROP_PREFIXES.iter().any(|s| bare.starts_with(s)) =>
            {
                by_name.insert(bare.to_string(), view);
            }
            _ => dropped.push(name),
        }
    }
    let p = path.display();
    let mut kept = Vec::new();
    for (name, shape) in text_encoder_shapes(cfg) {
        let view = by_name.remove(&name).ok_or_else(|| {
            bad_file!("{p}: missing text encoder tensor `{prefix}{name}` (the denoiser's config wants a {} with {} layers of {})",
                cfg.kind, cfg.num_layers, cfg.hidden_size)
        })?;
        if view.shape() != shape.as_slice() {
            return Err(bad_file!(
                "{p}: text encoder tensor `{prefix}{name}` has shape {:?}, the denoiser's config wants {shape:?}",
                view.shape()
            ));
        }
        if !matches!(view.dtype(), Dtype::F32 | Dtype::F16 | Dtype::BF16) {
            return Err(bad_file!(
                "{p}: text encoder tensor `{prefix}{name}` has dtype {:?} (want F32, F16 or BF16)",
                view.dtype()
            ));
        }
        kept.push((name, view));
    }
    dropped.extend(by_name.into_keys().map(|n| format!("{prefix}{n}")));
    dropped.sort();
    Ok((kept, dropped))
}

/// Writes the tensors to a temporary file next to `out`, loads it as a model, then renames it
/// to `out`. Returns the file size.
pub(crate) fn write_checked(
    tensors: Named,
    metadata: HashMap<String, String>,
    out: &Path,
) -> Result<u64> {
    let tmp = temp_path(out);
    let written = safetensors::serialize(tensors, &Some(metadata))
        .map_err(|e| bad_file!("cannot write {}: {e:?}", tmp.display()))
        .and_then(|bytes| sorted_metadata(bytes, &tmp))
        .and_then(|bytes| {
            std::fs::write(&tmp, &bytes)
                .map(|()| bytes.len() as u64)
                .map_err(|source| write_err(&tmp, source))
        })
        .and_then(|len| {
            Model::load(&tmp)
                .map(|_| len)
                .map_err(|e| bad_file!("the assembled model does not load: {e}"))
        })
        .and_then(|len| {
            std::fs::rename(&tmp, out)
                .map(|()| len)
                .map_err(|source| write_err(out, source))
        });
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

fn write_err(path: &Path, source: std::io::Error) -> Error {
    Error::Write {
        path: path.display().to_string(),
        source,
    }
}

/// `bytes` (a serialised safetensors file) with the header's `__metadata__` sorted by key. The
/// header keeps its length (the same entries in another order), so the data offsets stand.
fn sorted_metadata(mut bytes: Vec<u8>, path: &Path) -> Result<Vec<u8>> {
    let bad = |what: &str| bad_file!("cannot write {}: {what}", path.display());
    let n = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")) as usize)
        .filter(|&n| 8 + n <= bytes.len())
        .ok_or_else(|| bad("header length out of range"))?;
    let mut header: BTreeMap<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).map_err(|e| bad(&e.to_string()))?;
    if let Some(meta) = header.get_mut("__metadata__") {
        let sorted: BTreeMap<String, String> =
            serde_json::from_value(meta.take()).map_err(|e| bad(&e.to_string()))?;
        *meta = serde_json::to_value(sorted).map_err(|e| bad(&e.to_string()))?;
    }
    let mut text = serde_json::to_vec(&header).map_err(|e| bad(&e.to_string()))?;
    text.resize(n.max(text.len()), b' ');
    if text.len() != n {
        return Err(bad("the sorted header changed length"));
    }
    bytes[8..8 + n].copy_from_slice(&text);
    Ok(bytes)
}

/// The action families recorded under [`ACTIONS_KEY`] in `file`, if any.
pub fn trained_actions(file: &ModelFile) -> Result<Option<Vec<String>>> {
    file.metadata(ACTIONS_KEY)
        .map(|v| {
            serde_json::from_str(v)
                .map_err(|e| bad_file!("`{ACTIONS_KEY}` metadata is not a JSON list of names: {e}"))
        })
        .transpose()
}

fn temp_path(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".tmp-{}", std::process::id()));
    out.with_file_name(name)
}
