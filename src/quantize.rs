//! `flame quantize`: an int8 model file calibrated on the model's own runs.
//!
//! The model samples a set of prompts in f32 while every linear layer records the Gram matrix
//! `XᵀX` of its inputs ([`crate::models::calibrate`]). Each layer's weight is then rounded to
//! int8 with one symmetric scale per output row by GPTQ (Frantar, Ashkboos, Hoefler and
//! Alistarh 2022, "GPTQ: Accurate Post-Training Quantization for Generative Pre-trained
//! Transformers", arXiv:2210.17323, Algorithm 1): inputs in order, each rounding error spread
//! over the inputs not yet rounded through the inverse Hessian `H = XᵀX`, so that `X·Wᵀ`
//! rather than `W` itself stays close. Each row's scale is the one of 41 shrinks of
//! `max|w|/127` (1.0 down to 0.6) whose plain rounding has the least squared error: the largest
//! weight then costs a little clipping so that every other weight gets a finer step.
//!
//! On the demo model this is what makes int8's weights close (docs/performance.md, "Where
//! int8's error comes from"): with f32 activations, the features after 10 steps move 0.26 from
//! f32 with weights rounded per row at load, 0.11 with this file's weights.
//!
//! A latent model (MoLA, MLD, MotionLCM) decodes each calibration run, so that its VAE
//! decoder's layers record too; a model with a trajectory ControlNet (a MotionLCM control file)
//! runs each prompt a second time following its own pelvis path, so that the ControlNet and
//! its trajectory encoder do. Where the network reads the latent at its own width (MLD's and
//! MotionLCM v1's 256 channels) no layer is a projection from the sampled space, and none is
//! kept for it.
//!
//! The projections from and to the sampled features (FLAME's `input_projection` and
//! `last_projection`, MDM's pose embedding and output) stay f32: their inputs are the noisy
//! sample itself and their outputs are the step's result. Rounding `last_projection`'s input
//! alone gave three quarters of int8's mean error on the demo model, and the two are under 1%
//! of FLAME-base's multiply-adds.
//! [`QuantizeOptions::keep_f32`](crate::quantize::QuantizeOptions::keep_f32) keeps more by
//! name: FLAME's last decoder layer kept f32 brings the demo model's held-out accuracy from
//! 91.3% to f32's 92.7% (mean feature error 0.0073 → 0.0020) for 15–25% of FLAME-base's int8
//! step.
//!
//! [`QuantizeOptions::group`](crate::quantize::QuantizeOptions::group) writes one scale per
//! group of inputs instead (GPTQ's `groupsize`): the int8 kernels take one scale per row, so
//! such a file runs with float activations (loaded as f16 by default); on the demo model groups
//! of 128 move the features 0.046 from f32 (one scale per row: 0.106), closer than bf16 weights
//! (0.057).
//!
//! The file keeps every other tensor as it was, stores each quantised weight as `I8` with its
//! scales beside it (`<weight>_scale`, `F32`, one per output row), and records what was done
//! under the [`QUANTIZATION_KEY`](crate::quantize::QUANTIZATION_KEY) metadata. Loading it as
//! int8 packs those integers as they are (no rounding at load, the same bits on every machine
//! that runs the same kernel path); loading it as f32, f16 or bf16 multiplies them back out.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

use crate::checkpoint::{dequantize_int8, ModelFile};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{PackedWeights, WeightType};
use crate::models::calibrate::{record_while, RecordedLayer, Recorder};
use crate::models::{LoadOptions, Model};
use crate::motion::Task;
use crate::session::{Session, SessionParams, Which};

pub use crate::checkpoint::QUANTIZATION_KEY;

/// The calibration prompts used when none are given: one per kind of motion, worded apart from
/// the demo's held-out evaluation prompts (tests/fixtures/demo_eval_prompts.tsv).
pub const DEFAULT_PROMPTS: [&str; 16] = [
    "a person walks forward.",
    "a person walks backwards slowly.",
    "a person runs in a circle.",
    "a person jumps in place.",
    "a person hops on the left foot.",
    "a person waves with the left hand.",
    "a person claps twice.",
    "a person throws a punch with the left hand.",
    "a person kicks with the left leg.",
    "a person squats down.",
    "a person crouches and stands back up.",
    "a person turns to the left.",
    "a person raises the right arm.",
    "a person bows.",
    "a person steps to the left.",
    "a person stands and looks around.",
];

/// The most steps a calibration run takes when the caller does not say.
pub const MAX_DEFAULT_STEPS: usize = 50;

/// How to calibrate.
#[derive(Clone, Debug)]
pub struct QuantizeOptions {
    /// Prompts the model samples while its layers record their inputs.
    pub prompts: Vec<String>,
    /// Seeds per prompt (0, 1, ...).
    pub seeds: u64,
    /// Frames per run (the model's default when `None`).
    pub frames: Option<usize>,
    /// Sampling steps per run (the model's default when `None`, at most
    /// [`MAX_DEFAULT_STEPS`]: a 1000-step DDPM default would take 100 times as long for the
    /// same spread of noise levels).
    pub steps: Option<usize>,
    /// Threads for the calibration runs (0: all).
    pub threads: usize,
    /// Weights kept f32 besides the feature projections: a tensor name, or a prefix of names
    /// (`tf_decoder.layers.3.` keeps that whole layer). Each must match a linear weight.
    pub keep_f32: Vec<String>,
    /// One scale per group of this many inputs of each row instead of one per row: a file for
    /// float activations (loaded as f32, f16 or bf16; the int8 kernels take one scale per row).
    pub group: Option<usize>,
}

impl Default for QuantizeOptions {
    fn default() -> Self {
        QuantizeOptions {
            prompts: DEFAULT_PROMPTS.iter().map(|s| s.to_string()).collect(),
            seeds: 1,
            frames: None,
            steps: None,
            threads: 0,
            keep_f32: Vec::new(),
            group: None,
        }
    }
}

/// What happened to one stored weight.
#[derive(Clone, Debug)]
pub struct LayerReport {
    /// The weight tensor.
    pub tensor: String,
    /// Whether it was quantised (false: kept f32).
    pub int8: bool,
    /// Calibration input rows its layers saw.
    pub rows_seen: usize,
    /// Relative output error `‖X(W−Q)ᵀ‖² / ‖XWᵀ‖²` on the calibration inputs, with the
    /// weights rounded per row at load (the `int8` load option of an f32 file) and as written.
    pub error_rounded: f64,
    /// As `error_rounded`, for the weights this file holds.
    pub error_written: f64,
}

/// What [`quantize`] did.
#[derive(Clone, Debug)]
pub struct QuantizeReport {
    /// Every linear weight, in load order.
    pub layers: Vec<LayerReport>,
    /// Calibration runs made.
    pub runs: usize,
    /// Bytes written.
    pub bytes: u64,
}

/// Calibrates the model at `model` on `opts`'s runs and writes its int8 file to `out`.
pub fn quantize(model: &Path, out: &Path, opts: &QuantizeOptions) -> Result<QuantizeReport> {
    if opts.group == Some(0) {
        return Err(invalid_arg!(
            "a scale group needs at least one input (got 0)"
        ));
    }
    if opts.prompts.is_empty() || opts.seeds == 0 {
        return Err(invalid_arg!(
            "calibration needs at least one prompt and one seed (got {} prompts, {} seeds)",
            opts.prompts.len(),
            opts.seeds
        ));
    }
    let bytes = std::fs::read(model).map_err(|source| crate::error::Error::Io {
        path: model.display().to_string(),
        source,
    })?;
    let file = ModelFile::from_bytes(&bytes)?;
    if file.metadata(QUANTIZATION_KEY).is_some() {
        return Err(invalid_arg!(
            "{} is quantised already; quantise its f32, f16 or bf16 original",
            model.display()
        ));
    }
    // A misspelt name is refused before the calibration runs (whether it is a linear weight is
    // known only after them).
    if let Some(p) = opts.keep_f32.iter().find(|p| !file.has_prefix(p)) {
        return Err(invalid_arg!(
            "{} has no tensor named `{p}` or starting with it",
            model.display()
        ));
    }
    let recorder = Arc::new(Recorder::default());
    let loaded = record_while(&recorder, || {
        Model::from_file_with(file, &LoadOptions::default())
    })?;
    let keep = kept_widths(&loaded, &opts.keep_f32);
    let steps = opts
        .steps
        .unwrap_or_else(|| loaded.config().defaults.steps.min(MAX_DEFAULT_STEPS));
    let loaded = Arc::new(loaded);
    let mut runs = 0;
    for prompt in &opts.prompts {
        for seed in 0..opts.seeds {
            let params = SessionParams {
                frames: opts.frames,
                steps: Some(steps),
                seed,
                threads: opts.threads,
                ..Default::default()
            };
            let mut session = Session::new(Arc::clone(&loaded), &params)?;
            session.set_prompt(prompt)?;
            session.run()?;
            if loaded.is_latent() {
                // A latent model's decoder runs when the motion is read: its layers record then.
                let (features, _) = session.motion(Which::Sample)?;
                if loaded.denoiser().takes_control() {
                    // A trajectory ControlNet and its encoder run only under a control: the
                    // same run again, following its own pelvis path (MotionLCM's v1 control
                    // task, every frame), so that they record inputs of a real hint.
                    let features = features.to_vec();
                    let mut controlled = Session::new(Arc::clone(&loaded), &params)?;
                    controlled.set_prompt(prompt)?;
                    controlled.set_task_targets(&features, Task::Path)?;
                    controlled.run()?;
                    controlled.motion(Which::Sample)?;
                }
            }
            runs += 1;
        }
    }
    drop(loaded);
    let recorded = recorder.take();
    let source =
        SafeTensors::deserialize(&bytes).map_err(|e| bad_file!("{}: {e:?}", model.display()))?;
    // The weights as floats, read as the model reads them (mapped, widened from f16/bf16).
    let reader = ModelFile::open(model)?;
    let (owned, layers) = quantized_tensors(&reader, &recorded, &keep, opts.group)?;
    let mut tensors: Vec<(String, TensorView<'_>)> = Vec::new();
    for (name, view) in source.tensors() {
        if !owned.contains_key(&name) {
            tensors.push((name, view));
        }
    }
    for (name, (dtype, shape, data)) in &owned {
        let view = TensorView::new(*dtype, shape.clone(), data)
            .map_err(|e| bad_file!("tensor `{name}`: {e:?}"))?;
        tensors.push((name.clone(), view));
    }
    let (_, header) =
        SafeTensors::read_metadata(&bytes).map_err(|e| bad_file!("{}: {e:?}", model.display()))?;
    let mut metadata: HashMap<String, String> = header.metadata().clone().unwrap_or_default();
    let quantised = layers.iter().filter(|l| l.int8).count();
    metadata.insert(
        QUANTIZATION_KEY.into(),
        format!(
            "{{\"weights\":\"int8, symmetric, one scale per {}\",\"method\":\"GPTQ \
             (arXiv:2210.17323) on the Gram matrix of each layer's inputs\",\
             \"calibration_runs\":{runs},\"int8_weights\":{quantised},\"f32_weights\":{}{}}}",
            match opts.group {
                Some(g) => format!("group of {g} inputs of each output row (float activations)"),
                None => "output row".into(),
            },
            layers.len() - quantised,
            opts.group
                .map(|g| format!(",\"group\":{g}"))
                .unwrap_or_default()
        ),
    );
    let bytes = crate::assemble::write_checked(tensors, metadata, out)?;
    Ok(QuantizeReport {
        layers,
        runs,
        bytes,
    })
}

/// What stays f32: layers by input width, by output width (the sampled features in and out,
/// and a latent decoder's motion features), and the caller's names or name prefixes. A network
/// whose every layer reads the sampled width (MLD's, MotionLCM v1's 256-wide latent) has no
/// projection to keep: its sampled width would keep everything.
fn kept_widths(model: &Model, names: &[String]) -> (Vec<usize>, Vec<usize>, Vec<String>) {
    let direct = model.denoiser().reads_sample_directly();
    let sampled = if direct {
        vec![]
    } else {
        vec![model.sample_dim()]
    };
    let mut outputs = sampled.clone();
    if !direct || model.output_dim() != model.sample_dim() {
        outputs.push(model.output_dim());
    }
    outputs.push(model.motion_dim());
    (sampled, outputs, names.to_vec())
}

type Owned = BTreeMap<String, (Dtype, Vec<usize>, Vec<u8>)>;

/// The new tensors (int8 weights and their scales) and a report per stored weight.
fn quantized_tensors(
    reader: &ModelFile,
    recorded: &[RecordedLayer],
    (keep_in, keep_out, keep_names): &(Vec<usize>, Vec<usize>, Vec<String>),
    group: Option<usize>,
) -> Result<(Owned, Vec<LayerReport>)> {
    let grouped = group.is_some();
    // The layers built from each stored weight (a packed q/k/v weight may give two).
    let mut by_tensor: Vec<(String, Vec<&RecordedLayer>)> = Vec::new();
    for layer in recorded {
        match by_tensor.iter_mut().find(|(t, _)| *t == layer.tensor) {
            Some((_, parts)) => parts.push(layer),
            None => by_tensor.push((layer.tensor.clone(), vec![layer])),
        }
    }
    if let Some(p) = keep_names
        .iter()
        .find(|p| !by_tensor.iter().any(|(t, _)| t.starts_with(p.as_str())))
    {
        return Err(invalid_arg!(
            "no linear weight is named `{p}` or starts with it (`flame quantize --verbose` \
             lists them)"
        ));
    }
    let mut owned = Owned::new();
    let mut reports = Vec::new();
    for (tensor, parts) in by_tensor {
        let k = parts[0].inputs;
        let w = reader.tensor_any_shape(&tensor)?.data().to_vec();
        let n = w.len() / k.max(1);
        let kept = keep_names.iter().any(|p| tensor.starts_with(p.as_str()))
            || parts
                .iter()
                .any(|p| keep_in.contains(&p.inputs) || keep_out.contains(&p.rows.len()));
        let group = group.unwrap_or(k).clamp(1, k.max(1));
        let per_row = k.div_ceil(group);
        let mut q = vec![0i8; n * k];
        let mut scales = vec![0.0f32; n * per_row];
        let (mut err_round, mut err_gptq, mut norm) = (0.0, 0.0, 0.0);
        for part in &parts {
            if let Some((i, v)) = part.gram.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(invalid_arg!(
                    "calibration inputs of `{tensor}` are not finite (Gram entry {i} is {v}): \
                     the model does not run cleanly on the calibration prompts"
                ));
            }
            let rows = &w[part.rows.start * k..part.rows.end * k];
            let (pq, ps) = gptq(rows, part.rows.len(), k, &part.gram, group)?;
            // Rounded at load: what the int8 load option does to an f32 file.
            let rounded = PackedWeights::pack(rows, part.rows.len(), k, WeightType::Int8).unpack();
            err_gptq += output_error(rows, &dequantize_int8(&pq, &ps, k, group), k, &part.gram);
            err_round += output_error(rows, &rounded, k, &part.gram);
            norm += quadratic(rows, k, &part.gram);
            q[part.rows.start * k..part.rows.end * k].copy_from_slice(&pq);
            scales[part.rows.start * per_row..part.rows.end * per_row].copy_from_slice(&ps);
        }
        let rel = |e: f64| if norm > 0.0 { e / norm } else { 0.0 };
        reports.push(LayerReport {
            tensor: tensor.clone(),
            int8: !kept,
            rows_seen: parts.iter().map(|p| p.rows_seen).sum(),
            error_rounded: rel(err_round),
            error_written: if kept { 0.0 } else { rel(err_gptq) },
        });
        if kept {
            // Stored as f32 so that an int8 load keeps it f32 (a float weight of a quantised
            // file is never rounded at load).
            let data = w.iter().flat_map(|v| v.to_le_bytes()).collect();
            owned.insert(tensor, (Dtype::F32, vec![n, k], data));
            continue;
        }
        owned.insert(
            tensor.clone(),
            (Dtype::I8, vec![n, k], q.iter().map(|&v| v as u8).collect()),
        );
        owned.insert(
            format!("{tensor}_scale"),
            (
                Dtype::F32,
                if grouped { vec![n, per_row] } else { vec![n] },
                scales.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
        );
    }
    Ok((owned, reports))
}

/// Rounds `v / scale` to the nearest integer (ties to even) within −127..=127.
fn round_to(v: f64, scale: f64) -> f64 {
    (v / scale).round_ties_even().clamp(-127.0, 127.0)
}

/// The scale of one row: of the shrinks `max|w|/127 · (1 − i/100)`, `i = 0..=40`, the one
/// whose rounding has the least squared error (the first on ties); 1 for an all-zero row.
fn row_scale(row: &[f32]) -> f32 {
    let max = row.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
    if max == 0.0 {
        return 1.0;
    }
    let mut best = (f64::INFINITY, 1.0f32);
    for i in 0..=40 {
        // Each candidate is judged as the f32 the file stores.
        let s = (max * (1.0 - i as f64 / 100.0) / 127.0) as f32;
        let sd = s as f64;
        let err: f64 = row
            .iter()
            .map(|&v| (v as f64 - round_to(v as f64, sd) * sd).powi(2))
            .sum();
        if err < best.0 {
            best = (err, s);
        }
    }
    best.1
}

/// GPTQ (arXiv:2210.17323, Algorithm 1, one block): `w` (`[n, k]`) rounded to int8 with a
/// scale per group of `group` inputs of each row (`group ≥ k`: one per row; returned as
/// `[n, ⌈k/group⌉]`), each the least-squares one of 41 shrinks of `max|w|/127`, each input's
/// rounding error carried onto the inputs after it through the upper Cholesky factor of `H⁻¹`,
/// `H = gram + λI` (λ 1% of the mean diagonal, as the paper's dampening). An input that was
/// zero in every calibration run gets `H_ii = 1` and its weights plain rounding: the paper's
/// implementation sets such weights to zero, which on the demo model moved the features by 1.5
/// after 10 steps, as inputs unused by the calibration prompts are used by others.
pub fn gptq(
    w: &[f32],
    n: usize,
    k: usize,
    gram: &[f64],
    group: usize,
) -> Result<(Vec<i8>, Vec<f32>)> {
    assert_eq!(w.len(), n * k);
    assert_eq!(gram.len(), k * k);
    let mut h = gram.to_vec();
    let dead: Vec<bool> = (0..k).map(|i| h[i * k + i] == 0.0).collect();
    for i in 0..k {
        if dead[i] {
            h[i * k + i] = 1.0;
        }
    }
    let mean_diag = (0..k).map(|i| h[i * k + i]).sum::<f64>() / k.max(1) as f64;
    let mut u = None;
    // Dampening grows tenfold until H is numerically positive definite.
    for damp in [0.01, 0.1, 1.0] {
        let mut hd = h.clone();
        for i in 0..k {
            hd[i * k + i] += damp * mean_diag;
        }
        if let Some(f) = inverse_cholesky_upper(&hd, k) {
            u = Some(f);
            break;
        }
    }
    let u = u.ok_or_else(|| {
        invalid_arg!("the inputs' Gram matrix is not positive definite even with dampening")
    })?;
    let group = group.clamp(1, k.max(1));
    let per_row = k.div_ceil(group);
    let mut q = vec![0i8; n * k];
    let mut scales = vec![0.0f32; n * per_row];
    let rows: Vec<(Vec<i8>, Vec<f32>)> = {
        use rayon::prelude::*;
        w.par_chunks_exact(k.max(1))
            .take(n)
            .map(|row| {
                let mut r: Vec<f64> = row.iter().map(|&v| v as f64).collect();
                let mut out = vec![0i8; k];
                let mut row_scales = Vec::with_capacity(per_row);
                let mut s = 1.0;
                for i in 0..k {
                    if i % group == 0 {
                        // A group's scale is chosen when GPTQ reaches it, from the weights as
                        // the earlier groups' errors left them (the paper's code does the same
                        // with `groupsize`); one group per row is the row's own scale.
                        let end = (i + group).min(k);
                        let g: Vec<f32> = r[i..end].iter().map(|&v| v as f32).collect();
                        let scale = row_scale(&g);
                        row_scales.push(scale);
                        s = scale as f64;
                    }
                    let qi = round_to(r[i], s);
                    out[i] = qi as i8;
                    let err = (r[i] - qi * s) / u[i * k + i];
                    for j in i + 1..k {
                        r[j] -= err * u[i * k + j];
                    }
                }
                (out, row_scales)
            })
            .collect()
    };
    for (i, (row, s)) in rows.into_iter().enumerate() {
        q[i * k..(i + 1) * k].copy_from_slice(&row);
        scales[i * per_row..(i + 1) * per_row].copy_from_slice(&s);
    }
    Ok((q, scales))
}

/// The upper Cholesky factor `U` of `a⁻¹` (`a⁻¹ = UᵀU`), or `None` when `a` is not positive
/// definite. With `J` the order reversal, `J a J = L̃L̃ᵀ` gives `a⁻¹ = (J L̃⁻¹ J)ᵀ (J L̃⁻¹ J)`,
/// and `J L̃⁻¹ J` is upper triangular: one Cholesky factorisation and one triangular inverse
/// (`k³/3` multiply-adds) instead of an inverse and a second factorisation.
fn inverse_cholesky_upper(a: &[f64], k: usize) -> Option<Vec<f64>> {
    let rev = |i: usize| k - 1 - i;
    let mut ar = vec![0.0; k * k];
    for i in 0..k {
        for j in 0..k {
            ar[i * k + j] = a[rev(i) * k + rev(j)];
        }
    }
    let l = cholesky(&ar, k)?;
    // L̃⁻¹ column by column (forward substitution on each unit vector), written transposed so
    // that each column is a contiguous row: inv_t[j][i] = (L̃⁻¹)[i][j].
    let mut inv_t = vec![0.0; k * k];
    for j in 0..k {
        let x = &mut inv_t[j * k..(j + 1) * k];
        for i in j..k {
            let rhs = if i == j { 1.0 } else { 0.0 };
            x[i] = (rhs - dot(&l[i * k + j..i * k + i], &x[j..i])) / l[i * k + i];
        }
    }
    // U[i][j] = (L̃⁻¹)[rev i][rev j], upper because L̃⁻¹ is lower.
    let mut u = vec![0.0; k * k];
    for i in 0..k {
        for j in i..k {
            u[i * k + j] = inv_t[rev(j) * k + rev(i)];
        }
    }
    Some(u)
}

/// The lower Cholesky factor of the symmetric `a`, or `None` when a pivot is not positive.
fn cholesky(a: &[f64], k: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; k * k];
    for i in 0..k {
        for j in 0..=i {
            let s = a[i * k + j] - dot(&l[i * k..i * k + j], &l[j * k..j * k + j]);
            if i == j {
                // Not positive, or NaN.
                if s.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                    return None;
                }
                l[i * k + i] = s.sqrt();
            } else {
                l[i * k + j] = s / l[j * k + j];
            }
        }
    }
    Some(l)
}

/// `Σ a·b` in four interleaved partial sums (which the compiler can keep in vector lanes).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] += x[l] * y[l];
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `Σ_rows (w − a) H (w − a)ᵀ` for an approximation `a` of `w`: the squared output error over
/// the calibration inputs.
fn output_error(w: &[f32], approx: &[f32], k: usize, gram: &[f64]) -> f64 {
    let d: Vec<f32> = w.iter().zip(approx).map(|(a, b)| a - b).collect();
    quadratic(&d, k, gram)
}

/// `Σ_rows w H wᵀ`.
fn quadratic(w: &[f32], k: usize, gram: &[f64]) -> f64 {
    w.chunks_exact(k.max(1))
        .map(|row| {
            let mut total = 0.0;
            for i in 0..k {
                if row[i] == 0.0 {
                    continue;
                }
                let hi = &gram[i * k..(i + 1) * k];
                let dot: f64 = hi.iter().zip(row).map(|(h, &v)| h * v as f64).sum();
                total += row[i] as f64 * dot;
            }
            total
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny generator for test data (xorshift).
    fn values(seed: u64, n: usize) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                ((x >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    fn gram_of(x: &[f32], rows: usize, k: usize) -> Vec<f64> {
        let mut g = vec![0.0; k * k];
        for r in x.chunks_exact(k).take(rows) {
            for i in 0..k {
                for j in 0..k {
                    g[i * k + j] += r[i] as f64 * r[j] as f64;
                }
            }
        }
        g
    }

    #[test]
    fn the_factor_is_upper_and_its_square_inverts_the_matrix() {
        // UᵀU·A = I for a random symmetric positive definite A (BᵀB + I), checked by
        // multiplying out; U is upper triangular.
        let k = 37;
        let b = values(9, k * k);
        let mut a = vec![0.0f64; k * k];
        for i in 0..k {
            for j in 0..k {
                a[i * k + j] = (0..k)
                    .map(|p| b[p * k + i] as f64 * b[p * k + j] as f64)
                    .sum();
            }
            a[i * k + i] += 1.0;
        }
        let u = inverse_cholesky_upper(&a, k).unwrap();
        for i in 0..k {
            for j in 0..i {
                assert_eq!(u[i * k + j], 0.0);
            }
        }
        for i in 0..k {
            for j in 0..k {
                // (UᵀU A)[i][j] = Σ_p Σ_q U[p][i] U[p][q] A[q][j]
                let mut v = 0.0;
                for p in 0..k {
                    let row: f64 = (0..k).map(|q| u[p * k + q] * a[q * k + j]).sum();
                    v += u[p * k + i] * row;
                }
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-9, "{i},{j}: {v}");
            }
        }
        // Not positive definite: refused.
        let mut bad = a.clone();
        bad[0] = -1.0;
        assert!(inverse_cholesky_upper(&bad, k).is_none());
    }

    #[test]
    fn with_uncorrelated_inputs_gptq_is_plain_rounding() {
        // H diagonal: U is diagonal too, so no error is carried and every weight is rounded on
        // its own with the row's scale.
        let (n, k) = (5, 9);
        let w = values(1, n * k);
        let mut gram = vec![0.0; k * k];
        for i in 0..k {
            gram[i * k + i] = 1.0 + i as f64;
        }
        let (q, s) = gptq(&w, n, k, &gram, k).unwrap();
        for r in 0..n {
            let scale = row_scale(&w[r * k..(r + 1) * k]);
            assert_eq!(s[r], scale);
            for i in 0..k {
                let want = round_to(w[r * k + i] as f64, scale as f64) as i8;
                assert_eq!(q[r * k + i], want, "row {r} input {i}");
            }
        }
    }

    #[test]
    fn with_uncorrelated_inputs_each_group_gets_its_own_scale() {
        // Groups of 4 over 9 inputs (4 + 4 + 1), the groups' magnitudes a hundredfold apart: each
        // group is rounded with its own least-squares scale, so the small weights keep their
        // precision (with one scale per row they would all round to 0 or ±1).
        let (n, k, g) = (3, 9, 4);
        let mut w = values(2, n * k);
        for r in 0..n {
            for i in 4..8 {
                w[r * k + i] *= 0.01;
            }
        }
        let mut gram = vec![0.0; k * k];
        for i in 0..k {
            gram[i * k + i] = 2.0;
        }
        let (q, s) = gptq(&w, n, k, &gram, g).unwrap();
        assert_eq!(s.len(), n * 3);
        for r in 0..n {
            for (j, range) in [0..4, 4..8, 8..9].into_iter().enumerate() {
                let scale = row_scale(&w[r * k + range.start..r * k + range.end]);
                assert_eq!(s[r * 3 + j], scale, "row {r} group {j}");
                for i in range {
                    let want = round_to(w[r * k + i] as f64, scale as f64) as i8;
                    assert_eq!(q[r * k + i], want, "row {r} input {i}");
                }
            }
            // The small group uses the int8 range, not a sliver of it.
            let small = q[r * k + 4..r * k + 8]
                .iter()
                .map(|v| v.unsigned_abs())
                .max();
            assert!(small.unwrap() > 60, "row {r}: {small:?}");
        }
        let back = dequantize_int8(&q, &s, k, g);
        for (a, b) in back.iter().zip(&w) {
            assert!(
                (a - b).abs() <= 0.6 * b.abs().max(1e-3) + 1e-3,
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn two_inputs_carry_the_error_as_derived_by_hand() {
        // Inputs always equal: H = c·[[1,1],[1,1]] + λI, whose inverse is
        // [[c+λ, −c], [−c, c+λ]] / det. The output depends on w₁ + w₂ only, so GPTQ moves the
        // first weight's rounding error onto the second: with H⁻¹ = UᵀU,
        // U₀₁/U₀₀ = (H⁻¹)₀₁/(H⁻¹)₀₀ = −c/(c+λ), and the update w₂ −= (w₁ − q₁·s)·U₀₁/U₀₀ is
        // w₂ + (w₁ − q₁·s)·c/(c+λ).
        let w = [0.30f32, 0.50];
        let c = 100.0;
        let gram = vec![c, c, c, c];
        let (q, s) = gptq(&w, 1, 2, &gram, 2).unwrap();
        let s = s[0] as f64;
        assert_eq!(s as f32, row_scale(&w));
        let q1 = round_to(0.30, s);
        assert_eq!(q[0] as f64, q1);
        let lambda = 0.01 * c;
        let carried = 0.50 + (0.30 - q1 * s) * c / (c + lambda);
        assert_eq!(q[1] as f64, round_to(carried, s));
        // And the sum the output depends on is closer than plain rounding's (or as close).
        let sum = |a: f64, b: f64| ((a + b) * s - 0.8).abs();
        let plain = sum(q1, round_to(0.5, s));
        assert!(sum(q[0] as f64, q[1] as f64) <= plain + 1e-12);
    }

    #[test]
    fn gptq_lowers_the_output_error_of_correlated_inputs() {
        // Inputs with a shared component (correlated features, as a LayerNorm's output has):
        // GPTQ's output error must be below plain rounding's with the same scales.
        let (n, k, rows) = (16, 32, 200);
        let w = values(2, n * k);
        let base = values(3, rows);
        let noise = values(4, rows * k);
        let x: Vec<f32> = (0..rows * k)
            .map(|i| base[i / k] + 0.3 * noise[i])
            .collect();
        let gram = gram_of(&x, rows, k);
        let (q, s) = gptq(&w, n, k, &gram, k).unwrap();
        let plain: Vec<i8> = (0..n * k)
            .map(|i| round_to(w[i] as f64, s[i / k] as f64) as i8)
            .collect();
        let e_gptq = output_error(&w, &dequantize_int8(&q, &s, k, k), k, &gram);
        let e_plain = output_error(&w, &dequantize_int8(&plain, &s, k, k), k, &gram);
        assert!(e_gptq < 0.5 * e_plain, "{e_gptq} vs {e_plain}");
    }

    #[test]
    fn the_row_scale_search_is_never_worse_than_the_largest_weight() {
        for seed in 0..20 {
            let row = values(seed, 64);
            let s = row_scale(&row) as f64;
            let max = (row.iter().fold(0.0f32, |m, v| m.max(v.abs())) / 127.0) as f64;
            let err = |s: f64| -> f64 {
                row.iter()
                    .map(|&v| (v as f64 - round_to(v as f64, s) * s).powi(2))
                    .sum()
            };
            assert!(s <= max && s >= 0.6 * max - 1e-12);
            assert!(err(s) <= err(max));
        }
    }
}
