//! The PyTorch layers the denoisers are built from, as read from a model file: `Linear`,
//! `nn.MultiheadAttention`'s packed projections and `LayerNorm`. Shared by every architecture.
//!
//! Linear weights are packed at load into the GEMM kernel's panel layout, in the weight type
//! the caller chose ([`WeightType`]); biases and norms stay f32.

use std::ops::Range;
use std::sync::OnceLock;

use super::calibrate::Probe;
use crate::checkpoint::{dequantize_int8, ModelFile, StoredDtype, Tensor, QUANTIZATION_KEY};
use crate::error::{bad_file, Result};
use crate::kernels::{self, Activation, AttentionScratch, PackedLinear, PackedWeights, WeightType};

/// A PyTorch `Linear`: weight `[out, in]`, bias `[out]`.
pub(crate) struct Linear {
    packed: PackedLinear,
    /// `Wᵀ` (`[in, out]`, no bias) for [`Linear::backward_input`], built on first use so only
    /// models that take gradients pay its memory; `OnceLock` because models are shared across
    /// threads.
    transposed: OnceLock<PackedLinear>,
    /// Where the layer's inputs are recorded while a quantiser calibrates (see
    /// [`super::calibrate`]).
    probe: Option<Probe>,
}

/// A linear weight as the file stores it: floats, or int8 values with one scale per output
/// row (a file written by `flame quantize`).
pub(crate) enum StoredWeight {
    Float(Tensor),
    /// `scales` holds `⌈k/group⌉` per row (`group` = `k`: one per row).
    Int8 {
        q: Vec<i8>,
        scales: Vec<f32>,
        group: usize,
    },
}

impl StoredWeight {
    /// Reads weight `name` (`[n, k]`) and, when it is int8, its scales `name_scale` (`[n]`, or
    /// `[n, ⌈k/g⌉]` in a file quantised per group of `g` inputs), each of which must be finite
    /// and positive.
    pub(crate) fn read(file: &ModelFile, name: &str, n: usize, k: usize) -> Result<StoredWeight> {
        if file.dtype(name)? != StoredDtype::I8 {
            return Ok(StoredWeight::Float(file.tensor(name, &[n, k])?));
        }
        let q = file.tensor_i8(name, &[n, k])?;
        let scale_name = format!("{name}_scale");
        let group = file.int8_group()?;
        let scales = match group {
            None => file.tensor(&scale_name, &[n])?,
            Some(g) => file.tensor(&scale_name, &[n, k.div_ceil(g)])?,
        };
        let scales = scales.data().to_vec();
        let group = group.unwrap_or(k).min(k.max(1));
        if let Some((i, v)) = scales
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v > 0.0))
        {
            return Err(bad_file!(
                "tensor `{scale_name}`: scale {i} is {v}; a quantised weight's scales must be \
                 finite and positive"
            ));
        }
        if let Some(i) = q.iter().position(|&v| v == i8::MIN) {
            return Err(bad_file!(
                "tensor `{name}`: value {i} is -128; quantised weights lie in -127..=127"
            ));
        }
        Ok(StoredWeight::Int8 { q, scales, group })
    }

    /// Rows `rows` of the weight (`k` inputs) and `bias` as one layer of type `ty`. Int8 rows
    /// keep their integers and scales when `ty` is int8 and are dequantised otherwise; float
    /// rows of a quantised file stay f32 under int8 (the layers its quantiser kept).
    fn layer(
        &self,
        file: &ModelFile,
        tensor: &str,
        k: usize,
        rows: Range<usize>,
        bias: Option<&[f32]>,
        ty: WeightType,
    ) -> Linear {
        let probe = Probe::attach(tensor, rows.clone(), k);
        let n = rows.len();
        let packed = match self {
            // Per-row scales are what the int8 kernels take; a per-group file is refused for
            // int8 at load (`Model::from_file_with`) and would be multiplied out here.
            StoredWeight::Int8 { q, scales, group } if ty == WeightType::Int8 && *group >= k => {
                PackedLinear::from_packed(
                    PackedWeights::from_int8(&q[rows.start * k..rows.end * k], &scales[rows], n, k),
                    bias,
                )
            }
            StoredWeight::Int8 { q, scales, group } => {
                let per_row = k.div_ceil((*group).max(1));
                let w = dequantize_int8(
                    &q[rows.start * k..rows.end * k],
                    &scales[rows.start * per_row..rows.end * per_row],
                    k,
                    *group,
                );
                let ty = if ty == WeightType::Int8 {
                    WeightType::F32
                } else {
                    ty
                };
                PackedLinear::new(&w, bias, k, n, ty)
            }
            StoredWeight::Float(w) => {
                let ty = if ty == WeightType::Int8 && file.metadata(QUANTIZATION_KEY).is_some() {
                    WeightType::F32
                } else {
                    ty
                };
                PackedLinear::new(&w.data()[rows.start * k..rows.end * k], bias, k, n, ty)
            }
        };
        Linear {
            packed,
            transposed: OnceLock::new(),
            probe,
        }
    }
}

impl Linear {
    pub(crate) fn load(
        file: &ModelFile,
        name: &str,
        n_in: usize,
        n_out: usize,
        ty: WeightType,
    ) -> Result<Linear> {
        let tensor = format!("{name}.weight");
        let w = StoredWeight::read(file, &tensor, n_out, n_in)?;
        let b = file.tensor(&format!("{name}.bias"), &[n_out])?;
        let layer = w.layer(file, &tensor, n_in, 0..n_out, Some(b.data()), ty);
        file.release(&tensor);
        Ok(layer)
    }

    /// A `Linear(bias=False)`: weight `[out, in]` only.
    pub(crate) fn load_no_bias(
        file: &ModelFile,
        name: &str,
        n_in: usize,
        n_out: usize,
        ty: WeightType,
    ) -> Result<Linear> {
        let tensor = format!("{name}.weight");
        let w = StoredWeight::read(file, &tensor, n_out, n_in)?;
        let layer = w.layer(file, &tensor, n_in, 0..n_out, None, ty);
        file.release(&tensor);
        Ok(layer)
    }

    /// A layer from a weight `[n_out, n_in]` already in memory.
    pub(crate) fn from_weight(
        weight: &[f32],
        bias: Option<&[f32]>,
        n_in: usize,
        n_out: usize,
        ty: WeightType,
    ) -> Linear {
        Linear::new(PackedLinear::new(weight, bias, n_in, n_out, ty))
    }

    fn new(packed: PackedLinear) -> Linear {
        Linear {
            packed,
            transposed: OnceLock::new(),
            probe: None,
        }
    }

    /// Output width.
    pub(crate) fn outputs(&self) -> usize {
        self.packed.outputs()
    }

    /// `y[rows, out] = x[rows, in] · Wᵀ + b`.
    pub(crate) fn forward(&self, x: &[f32], rows: usize, y: &mut [f32]) {
        self.forward_act(x, rows, y, Activation::None);
    }

    /// `y = act(x · Wᵀ + b)`, the activation applied as each output tile is finished.
    pub(crate) fn forward_act(&self, x: &[f32], rows: usize, y: &mut [f32], act: Activation) {
        if let Some(probe) = &self.probe {
            probe.record(x, rows);
        }
        self.packed.forward(x, rows, y, act);
    }

    /// The vector-Jacobian product with respect to the input: `dx[rows, in] = dy[rows, out] · W`
    /// (overwritten). The bias does not enter it.
    pub(crate) fn backward_input(&self, dy: &[f32], rows: usize, dx: &mut [f32]) {
        let t = self.transposed.get_or_init(|| {
            let w = self.packed.weights();
            let (n_in, n_out) = (w.inputs(), w.outputs());
            let wt = transpose(&w.unpack(), n_out, n_in);
            PackedLinear::new(&wt, None, n_out, n_in, w.weight_type())
        });
        t.forward(dy, rows, dx, Activation::None);
    }

    /// Bytes of packed weights.
    pub(crate) fn weight_bytes(&self) -> usize {
        self.packed.weights().bytes()
    }
}

/// `[rows, cols]` row-major → `[cols, rows]`.
pub(crate) fn transpose(m: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; m.len()];
    for r in 0..rows {
        for c in 0..cols {
            t[c * rows + r] = m[r * cols + c];
        }
    }
    t
}

/// Reads `nn.MultiheadAttention`'s packed `in_proj_weight` `[3E, E]` (rows q, k, v) and bias,
/// as one layer per range of `rows`.
fn in_proj<const N: usize>(
    file: &ModelFile,
    name: &str,
    e: usize,
    ty: WeightType,
    rows: [Range<usize>; N],
) -> Result<[Linear; N]> {
    let tensor = format!("{name}.in_proj_weight");
    let w = StoredWeight::read(file, &tensor, 3 * e, e)?;
    let b = file.tensor(&format!("{name}.in_proj_bias"), &[3 * e])?;
    let layers = rows.map(|r| w.layer(file, &tensor, e, r.clone(), Some(&b.data()[r]), ty));
    file.release(&tensor);
    Ok(layers)
}

/// `nn.MultiheadAttention` used as self-attention: q, k and v projected in one GEMM.
pub(crate) struct Attention {
    pub(crate) qkv: Linear,
    pub(crate) out_proj: Linear,
}

impl Attention {
    pub(crate) fn load(
        file: &ModelFile,
        name: &str,
        e: usize,
        ty: WeightType,
    ) -> Result<Attention> {
        // One range: q, k and v in one GEMM.
        #[allow(clippy::single_range_in_vec_init)]
        let [qkv] = in_proj(file, name, e, ty, [0..3 * e])?;
        Ok(Attention {
            qkv,
            out_proj: Linear::load(file, &format!("{name}.out_proj"), e, e, ty)?,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.qkv.weight_bytes() + self.out_proj.weight_bytes()
    }

    /// `out = out_proj(MultiHeadAttention(x, x, x))` over `batch` independent blocks of `seq`
    /// rows of width `e` (no masks: every position is valid at sampling).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn self_attention(
        &self,
        x: &[f32],
        batch: usize,
        seq: usize,
        e: usize,
        heads: usize,
        qkv: &mut Vec<f32>,
        attn: &mut Vec<f32>,
        out: &mut Vec<f32>,
        scratch: &mut AttentionScratch,
    ) {
        self.self_attention_padded(x, batch, seq, e, heads, None, qkv, attn, out, scratch)
    }

    /// [`Attention::self_attention`] where `key_padding[j]` (one flag per row of a block, the
    /// same for every block) excludes key `j`, as PyTorch's `src_key_padding_mask`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn self_attention_padded(
        &self,
        x: &[f32],
        batch: usize,
        seq: usize,
        e: usize,
        heads: usize,
        key_padding: Option<&[bool]>,
        qkv: &mut Vec<f32>,
        attn: &mut Vec<f32>,
        out: &mut Vec<f32>,
        scratch: &mut AttentionScratch,
    ) {
        let rows = batch * seq;
        let qkv = sized(qkv, rows * 3 * e);
        self.qkv.forward(x, rows, qkv);
        let attn = sized(attn, rows * e);
        for (i, o) in attn.chunks_exact_mut(seq * e).enumerate() {
            let block = &qkv[i * seq * 3 * e..(i + 1) * seq * 3 * e];
            let (k, v) = (&block[e..], &block[2 * e..]);
            scratch.attend(
                block,
                3 * e,
                k,
                3 * e,
                v,
                3 * e,
                seq,
                seq,
                heads,
                e / heads,
                key_padding,
                false,
                o,
            );
        }
        self.out_proj.forward(attn, rows, sized(out, rows * e));
    }
}

/// `nn.MultiheadAttention` used as cross-attention: the query projection apart from the
/// key/value projection, so keys and values of a fixed memory can be computed once.
pub(crate) struct CrossAttention {
    pub(crate) q: Linear,
    /// Rows k then v of `in_proj`: `[memory rows, 2E]` out.
    pub(crate) kv: Linear,
    pub(crate) out_proj: Linear,
}

impl CrossAttention {
    pub(crate) fn load(
        file: &ModelFile,
        name: &str,
        e: usize,
        ty: WeightType,
    ) -> Result<CrossAttention> {
        let [q, kv] = in_proj(file, name, e, ty, [0..e, e..3 * e])?;
        Ok(CrossAttention {
            q,
            kv,
            out_proj: Linear::load(file, &format!("{name}.out_proj"), e, e, ty)?,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.q.weight_bytes() + self.kv.weight_bytes() + self.out_proj.weight_bytes()
    }
}

/// A PyTorch `Conv1d` with "same" padding (`dilation · (k − 1) / 2` on each side, k odd) over
/// frame-major `[frames, in]` rows: gathered into `[frames, k · in]` rows (the k taps side by
/// side, zeros past either end) and multiplied as one linear layer.
pub(crate) struct Conv1d {
    linear: Linear,
    n_in: usize,
    n_out: usize,
    kernel: usize,
    dilation: usize,
}

impl Conv1d {
    /// Reads `{name}.weight` `[out, in, k]` and `{name}.bias` `[out]`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn load(
        file: &ModelFile,
        name: &str,
        n_in: usize,
        n_out: usize,
        kernel: usize,
        dilation: usize,
        bias: bool,
        ty: WeightType,
    ) -> Result<Conv1d> {
        let w = file.tensor(&format!("{name}.weight"), &[n_out, n_in, kernel])?;
        let b = if bias {
            Some(file.tensor(&format!("{name}.bias"), &[n_out])?)
        } else {
            None
        };
        // [out, in, k] → [out, k, in]: tap j of input channel i at column j · in + i.
        let src = w.data();
        let mut packed = vec![0.0f32; n_out * kernel * n_in];
        for o in 0..n_out {
            for i in 0..n_in {
                for j in 0..kernel {
                    packed[(o * kernel + j) * n_in + i] = src[(o * n_in + i) * kernel + j];
                }
            }
        }
        file.release(&format!("{name}.weight"));
        Ok(Conv1d {
            linear: Linear::from_weight(
                &packed,
                b.as_ref().map(|b| b.data()),
                kernel * n_in,
                n_out,
                ty,
            ),
            n_in,
            n_out,
            kernel,
            dilation,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.linear.weight_bytes()
    }

    /// `y[frames, out] = act(conv(x[frames, in]))`; `cols` is scratch.
    pub(crate) fn forward(
        &self,
        x: &[f32],
        frames: usize,
        y: &mut Vec<f32>,
        cols: &mut Vec<f32>,
        act: Activation,
    ) {
        let (n, k) = (self.n_in, self.kernel);
        let half = (k - 1) / 2 * self.dilation;
        let y = sized(y, frames * self.n_out);
        if k == 1 {
            self.linear.forward_act(x, frames, y, act);
            return;
        }
        let c = sized(cols, frames * k * n);
        for (t, row) in c.chunks_exact_mut(k * n).enumerate() {
            for (j, tap) in row.chunks_exact_mut(n).enumerate() {
                match (t + j * self.dilation).checked_sub(half) {
                    Some(s) if s < frames => tap.copy_from_slice(&x[s * n..(s + 1) * n]),
                    _ => tap.fill(0.0),
                }
            }
        }
        self.linear.forward_act(c, frames, y, act);
    }

    /// The vector-Jacobian product with respect to the input `x [frames, in]` for an upstream
    /// gradient `dy [frames, out]` of the convolution before any activation (the caller applies
    /// the activation's backward first). The transpose of [`Conv1d::forward`]'s gather: the
    /// column gradient `dy · W` is scattered back onto the frames each tap read (col2im), taps
    /// that fell into the padding dropped. `dx` is resized to `frames · in` and overwritten;
    /// `cols` is scratch.
    // Until a decoder's backward chain calls it, only the tests do.
    pub(crate) fn backward_input(
        &self,
        dy: &[f32],
        frames: usize,
        dx: &mut Vec<f32>,
        cols: &mut Vec<f32>,
    ) {
        let (n, k) = (self.n_in, self.kernel);
        let dx = sized(dx, frames * n);
        if k == 1 {
            self.linear.backward_input(dy, frames, dx);
            return;
        }
        let half = (k - 1) / 2 * self.dilation;
        let dcols = sized(cols, frames * k * n);
        self.linear.backward_input(dy, frames, dcols);
        dx.fill(0.0);
        for (t, row) in dcols.chunks_exact(k * n).enumerate() {
            for (j, tap) in row.chunks_exact(n).enumerate() {
                if let Some(s) = (t + j * self.dilation).checked_sub(half) {
                    if s < frames {
                        for (d, &g) in dx[s * n..(s + 1) * n].iter_mut().zip(tap) {
                            *d += g;
                        }
                    }
                }
            }
        }
    }
}

/// Buffers of the post-LN layers below, grown once and reused.
#[derive(Default)]
pub(crate) struct LayerBuffers {
    pub(crate) qkv: Vec<f32>,
    pub(crate) q: Vec<f32>,
    pub(crate) kv: Vec<f32>,
    pub(crate) attn: Vec<f32>,
    pub(crate) proj: Vec<f32>,
    pub(crate) hidden: Vec<f32>,
    pub(crate) scratch: AttentionScratch,
}

/// The sizes a post-LN layer runs with.
#[derive(Clone, Copy)]
pub(crate) struct LayerShape {
    pub(crate) width: usize,
    pub(crate) heads: usize,
    pub(crate) ff: usize,
    pub(crate) act: Activation,
    pub(crate) eps: f32,
}

/// One `nn.TransformerEncoderLayer` (post-LN): self-attention, then the feed-forward.
pub(crate) struct EncoderLayer {
    pub(crate) self_attn: Attention,
    pub(crate) linear1: Linear,
    pub(crate) linear2: Linear,
    pub(crate) norm1: LayerNorm,
    pub(crate) norm2: LayerNorm,
}

impl EncoderLayer {
    /// Reads `{p}.self_attn`, `{p}.linear1`, `{p}.linear2`, `{p}.norm1`, `{p}.norm2`.
    pub(crate) fn load(
        file: &ModelFile,
        p: &str,
        e: usize,
        ff: usize,
        ty: WeightType,
    ) -> Result<EncoderLayer> {
        Ok(EncoderLayer {
            self_attn: Attention::load(file, &format!("{p}.self_attn"), e, ty)?,
            linear1: Linear::load(file, &format!("{p}.linear1"), e, ff, ty)?,
            linear2: Linear::load(file, &format!("{p}.linear2"), ff, e, ty)?,
            norm1: LayerNorm::load(file, &format!("{p}.norm1"), e)?,
            norm2: LayerNorm::load(file, &format!("{p}.norm2"), e)?,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.self_attn.weight_bytes() + self.linear1.weight_bytes() + self.linear2.weight_bytes()
    }

    /// `x ← norm1(x + SelfAttn(x)); x ← norm2(x + FF(x))` over `batch` blocks of `seq` rows.
    pub(crate) fn forward(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        s: LayerShape,
        b: &mut LayerBuffers,
    ) {
        self.forward_padded(x, batch, seq, None, s, b)
    }

    /// [`EncoderLayer::forward`] with keys excluded by `key_padding` (one flag per row of a
    /// block).
    pub(crate) fn forward_padded(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        key_padding: Option<&[bool]>,
        s: LayerShape,
        b: &mut LayerBuffers,
    ) {
        let rows = batch * seq;
        self.self_attn.self_attention_padded(
            x,
            batch,
            seq,
            s.width,
            s.heads,
            key_padding,
            &mut b.qkv,
            &mut b.attn,
            &mut b.proj,
            &mut b.scratch,
        );
        self.norm1.add_norm(x, &b.proj[..rows * s.width], s.eps);
        feed_forward(&self.linear1, &self.linear2, &self.norm2, x, rows, s, b);
    }
}

/// `x ← norm(x + linear2(act(linear1(x))))`.
fn feed_forward(
    linear1: &Linear,
    linear2: &Linear,
    norm: &LayerNorm,
    x: &mut [f32],
    rows: usize,
    s: LayerShape,
    b: &mut LayerBuffers,
) {
    let hidden = sized(&mut b.hidden, rows * s.ff);
    linear1.forward_act(x, rows, hidden, s.act);
    let proj = sized(&mut b.proj, rows * s.width);
    linear2.forward(hidden, rows, proj);
    norm.add_norm(x, proj, s.eps);
}

/// One `nn.TransformerDecoderLayer` (post-LN): self-attention, cross-attention to a memory,
/// then the feed-forward.
pub(crate) struct DecoderLayer {
    pub(crate) self_attn: Attention,
    pub(crate) cross_attn: CrossAttention,
    pub(crate) linear1: Linear,
    pub(crate) linear2: Linear,
    pub(crate) norm1: LayerNorm,
    pub(crate) norm2: LayerNorm,
    pub(crate) norm3: LayerNorm,
}

impl DecoderLayer {
    /// Reads `{p}.self_attn`, `{p}.multihead_attn`, `{p}.linear1/2`, `{p}.norm1/2/3`.
    pub(crate) fn load(
        file: &ModelFile,
        p: &str,
        e: usize,
        ff: usize,
        ty: WeightType,
    ) -> Result<DecoderLayer> {
        Ok(DecoderLayer {
            self_attn: Attention::load(file, &format!("{p}.self_attn"), e, ty)?,
            cross_attn: CrossAttention::load(file, &format!("{p}.multihead_attn"), e, ty)?,
            linear1: Linear::load(file, &format!("{p}.linear1"), e, ff, ty)?,
            linear2: Linear::load(file, &format!("{p}.linear2"), ff, e, ty)?,
            norm1: LayerNorm::load(file, &format!("{p}.norm1"), e)?,
            norm2: LayerNorm::load(file, &format!("{p}.norm2"), e)?,
            norm3: LayerNorm::load(file, &format!("{p}.norm3"), e)?,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.self_attn.weight_bytes()
            + self.cross_attn.weight_bytes()
            + self.linear1.weight_bytes()
            + self.linear2.weight_bytes()
    }

    /// The layer over `batch` blocks of `seq` rows; block `i` attends to rows
    /// `memory[i · mem_len ..][..mem_len]` (no masks).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        s: LayerShape,
        b: &mut LayerBuffers,
    ) {
        let (e, rows) = (s.width, batch * seq);
        self.self_attn.self_attention(
            x,
            batch,
            seq,
            e,
            s.heads,
            &mut b.qkv,
            &mut b.attn,
            &mut b.proj,
            &mut b.scratch,
        );
        self.norm1.add_norm(x, &b.proj[..rows * e], s.eps);
        self.cross_attention(x, batch, seq, memory, mem_len, s, b, mem_len == 1);
        self.norm2.add_norm(x, &b.proj[..rows * e], s.eps);
        feed_forward(&self.linear1, &self.linear2, &self.norm3, x, rows, s, b);
    }

    /// The cross-attention's projected output into `b.proj` `[rows, e]`. With one memory row
    /// (`single_key`: MLD's one-token latent) every query's softmax weight is exactly 1, so
    /// each query's output is that row's value and the projected row is the same for the
    /// whole block: it is made once per block, and the query projection is skipped (the same
    /// bits as the general path: the weighted sum is 1·v, and each output row of a linear
    /// layer is the same chain of operations whatever the other rows).
    #[allow(clippy::too_many_arguments)]
    fn cross_attention(
        &self,
        x: &[f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        s: LayerShape,
        b: &mut LayerBuffers,
        single_key: bool,
    ) {
        let (e, rows) = (s.width, batch * seq);
        let ca = &self.cross_attn;
        let kv = sized(&mut b.kv, batch * mem_len * 2 * e);
        ca.kv.forward(memory, batch * mem_len, kv);
        if single_key {
            let v = sized(&mut b.q, batch * e);
            for (vi, kvi) in v.chunks_exact_mut(e).zip(kv.chunks_exact(2 * e)) {
                vi.copy_from_slice(&kvi[e..]);
            }
            let once = sized(&mut b.attn, batch * e);
            ca.out_proj.forward(v, batch, once);
            let proj = sized(&mut b.proj, rows * e);
            for (block, o) in proj.chunks_exact_mut(seq * e).zip(once.chunks_exact(e)) {
                for row in block.chunks_exact_mut(e) {
                    row.copy_from_slice(o);
                }
            }
            return;
        }
        let q = sized(&mut b.q, rows * e);
        ca.q.forward(x, rows, q);
        let attn = sized(&mut b.attn, rows * e);
        for (i, o) in attn.chunks_exact_mut(seq * e).enumerate() {
            let kv_i = &kv[i * mem_len * 2 * e..(i + 1) * mem_len * 2 * e];
            b.scratch.attend(
                &q[i * seq * e..(i + 1) * seq * e],
                e,
                kv_i,
                2 * e,
                &kv_i[e..],
                2 * e,
                seq,
                mem_len,
                s.heads,
                e / s.heads,
                None,
                false,
                o,
            );
        }
        ca.out_proj
            .forward(attn, rows, sized(&mut b.proj, rows * e));
    }
}

pub(crate) struct LayerNorm {
    pub(crate) weight: Tensor,
    pub(crate) bias: Tensor,
}

impl LayerNorm {
    pub(crate) fn load(file: &ModelFile, name: &str, e: usize) -> Result<LayerNorm> {
        Ok(LayerNorm {
            weight: file.tensor(&format!("{name}.weight"), &[e])?,
            bias: file.tensor(&format!("{name}.bias"), &[e])?,
        })
    }
}

impl LayerNorm {
    /// `x ← LayerNorm(x + residual)` row-wise: the post-LN residual step.
    pub(crate) fn add_norm(&self, x: &mut [f32], residual: &[f32], eps: f32) {
        let (g, b) = (self.weight.data(), self.bias.data());
        kernels::add_layer_norm(x, residual, g.len(), g, b, eps);
    }
}

/// The fused activation for a configuration's name (`gelu` = exact erf GELU, else ReLU).
pub(crate) fn activation(name: &str) -> Activation {
    if name == "gelu" {
        Activation::Gelu
    } else {
        Activation::Relu
    }
}

/// Rotary positions (rotate-half) on the q and k of packed `[rows, 3·e]` qkv rows: in every
/// head of `hd` dims, the pairs (i, i + half) of its first 2·half dims turn by the angle of
/// the row's position `row % seq`; `cos` and `sin` are `[seq, half]`.
pub(crate) fn rotate_qk(
    qkv: &mut [f32],
    e: usize,
    hd: usize,
    seq: usize,
    cos: &[f32],
    sin: &[f32],
) {
    let half = cos.len().checked_div(seq).unwrap_or(0);
    for (r, row) in qkv.chunks_exact_mut(3 * e).enumerate() {
        let p = r % seq;
        let (cos, sin) = (&cos[p * half..][..half], &sin[p * half..][..half]);
        for head in row[..2 * e].chunks_exact_mut(hd) {
            for i in 0..half {
                let (a, b) = (head[i], head[i + half]);
                head[i] = a * cos[i] - b * sin[i];
                head[i + half] = b * cos[i] + a * sin[i];
            }
        }
    }
}

/// Unmasked self-attention of packed `[rows, 3·e]` qkv rows in blocks of `seq` rows, into
/// `out` `[rows, e]`.
pub(crate) fn self_attend(
    scratch: &mut AttentionScratch,
    qkv: &[f32],
    e: usize,
    heads: usize,
    seq: usize,
    out: &mut [f32],
) {
    for (i, o) in out.chunks_exact_mut(seq * e).enumerate() {
        let q = &qkv[i * seq * 3 * e..(i + 1) * seq * 3 * e];
        scratch.attend(
            q,
            3 * e,
            &q[e..],
            3 * e,
            &q[2 * e..],
            3 * e,
            seq,
            seq,
            heads,
            e / heads,
            None,
            false,
            o,
        );
    }
}

/// A scratch buffer grown to `n` values (never shrunk, so later steps do not allocate).
pub(crate) fn sized(v: &mut Vec<f32>, n: usize) -> &mut [f32] {
    v.resize(n, 0.0);
    &mut v[..n]
}

#[cfg(test)]
mod tests {
    use super::*;
    use safetensors::tensor::{Dtype, TensorView};

    fn file(tensors: &[(&str, Vec<usize>, Vec<f32>)]) -> ModelFile {
        let bytes: Vec<Vec<u8>> = tensors
            .iter()
            .map(|(_, _, v)| v.iter().flat_map(|x| x.to_le_bytes()).collect())
            .collect();
        let views: Vec<(String, TensorView)> = tensors
            .iter()
            .zip(&bytes)
            .map(|((n, s, _), b)| {
                (
                    n.to_string(),
                    TensorView::new(Dtype::F32, s.clone(), b).unwrap(),
                )
            })
            .collect();
        ModelFile::from_bytes(&safetensors::serialize(views, &None).unwrap()).unwrap()
    }

    /// Values that differ everywhere, none zero.
    fn values(n: usize, seed: f32) -> Vec<f32> {
        (0..n)
            .map(|i| ((i as f32 + seed) * 0.7311).sin() + 0.01)
            .collect()
    }

    #[test]
    fn the_transpose_is_built_once_on_first_use_in_the_weight_type() {
        let (n_in, n_out, rows) = (3, 17, 2);
        let w = values(n_out * n_in, 4.0);
        for ty in [WeightType::F32, WeightType::F16, WeightType::Bf16] {
            let layer = Linear::from_weight(&w, None, n_in, n_out, ty);
            assert!(layer.transposed.get().is_none());
            let dy = values(rows * n_out, 5.0);
            let mut dx = vec![0.0; rows * n_in];
            layer.backward_input(&dy, rows, &mut dx);
            let t = layer.transposed.get().expect("built by the first call");
            assert_eq!(t.weights().weight_type(), ty);
            assert_eq!((t.inputs(), t.outputs()), (n_out, n_in));
            let first = t as *const PackedLinear;
            layer.backward_input(&dy, rows, &mut dx);
            assert_eq!(
                layer.transposed.get().unwrap() as *const PackedLinear,
                first
            );
        }
    }

    /// With one memory row the cross-attention is made once per block and broadcast; the
    /// general path (queries, scores, softmax over the one key, weighted value) gives the
    /// same bits, for every row of every block.
    #[test]
    fn cross_attention_over_one_memory_row_is_its_projected_value() {
        let (e, ff, heads, batch, seq) = (8, 12, 2, 2, 5);
        let mut t = Vec::new();
        for (i, (name, shape)) in [
            ("self_attn.in_proj_weight", vec![3 * e, e]),
            ("self_attn.in_proj_bias", vec![3 * e]),
            ("self_attn.out_proj.weight", vec![e, e]),
            ("self_attn.out_proj.bias", vec![e]),
            ("multihead_attn.in_proj_weight", vec![3 * e, e]),
            ("multihead_attn.in_proj_bias", vec![3 * e]),
            ("multihead_attn.out_proj.weight", vec![e, e]),
            ("multihead_attn.out_proj.bias", vec![e]),
            ("linear1.weight", vec![ff, e]),
            ("linear1.bias", vec![ff]),
            ("linear2.weight", vec![e, ff]),
            ("linear2.bias", vec![e]),
            ("norm1.weight", vec![e]),
            ("norm1.bias", vec![e]),
            ("norm2.weight", vec![e]),
            ("norm2.bias", vec![e]),
            ("norm3.weight", vec![e]),
            ("norm3.bias", vec![e]),
        ]
        .into_iter()
        .enumerate()
        {
            let n = shape.iter().product();
            t.push((format!("d.{name}"), shape, values(n, i as f32 * 3.0)));
        }
        let named: Vec<(&str, Vec<usize>, Vec<f32>)> = t
            .iter()
            .map(|(n, s, v)| (n.as_str(), s.clone(), v.clone()))
            .collect();
        let f = file(&named);
        let layer = DecoderLayer::load(&f, "d", e, ff, WeightType::F32).unwrap();
        let shape = LayerShape {
            width: e,
            heads,
            ff,
            act: Activation::Gelu,
            eps: 1e-5,
        };
        let x = values(batch * seq * e, 7.0);
        let memory = values(batch * e, 9.0);
        let run = |single_key: bool| {
            let mut b = LayerBuffers::default();
            layer.cross_attention(&x, batch, seq, &memory, 1, shape, &mut b, single_key);
            b.proj[..batch * seq * e].to_vec()
        };
        let (general, once) = (run(false), run(true));
        assert!(general
            .iter()
            .zip(&once)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        // The blocks differ (each has its own memory row); the rows of a block do not.
        assert_ne!(once[..e], once[seq * e..seq * e + e]);
        assert_eq!(once[..e], once[(seq - 1) * e..seq * e]);
    }

    #[test]
    fn conv1d_matches_the_definition() {
        // PyTorch Conv1d(in, out, k, dilation=d, padding=d·(k−1)/2) on [in, T], written out.
        let (n_in, n_out, frames) = (3, 5, 11);
        for (k, d) in [(3, 1), (3, 4), (3, 9), (1, 1), (5, 2)] {
            let w = values(n_out * n_in * k, 1.0);
            let b = values(n_out, 2.0);
            let f = file(&[
                ("c.weight", vec![n_out, n_in, k], w.clone()),
                ("c.bias", vec![n_out], b.clone()),
            ]);
            let conv = Conv1d::load(&f, "c", n_in, n_out, k, d, true, WeightType::F32).unwrap();
            let x = values(frames * n_in, 3.0); // frame-major [T, in]
            let (mut y, mut cols) = (Vec::new(), Vec::new());
            conv.forward(&x, frames, &mut y, &mut cols, Activation::None);
            let pad = (d * (k - 1) / 2) as isize;
            for t in 0..frames {
                for o in 0..n_out {
                    let mut want = b[o] as f64;
                    for i in 0..n_in {
                        for j in 0..k {
                            let s = t as isize + (j * d) as isize - pad;
                            if (0..frames as isize).contains(&s) {
                                want +=
                                    (w[(o * n_in + i) * k + j] * x[s as usize * n_in + i]) as f64;
                            }
                        }
                    }
                    let got = y[t * n_out + o] as f64;
                    assert!(
                        (got - want).abs() < 1e-5,
                        "k {k} d {d} t {t} o {o}: {got} vs {want}"
                    );
                }
            }
        }
    }
}
