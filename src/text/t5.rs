//! The T5 v1.0 encoder (Raffel et al. 2020, "Exploring the Limits of Transfer Learning with a
//! Unified Text-to-Text Transformer", JMLR 21; Hugging Face transformers' `modeling_t5.py`,
//! `T5EncoderModel`) and sentence-transformers' head on it (`Pooling` mean with the attention
//! mask, `Dense` without bias, `Normalize`), as sentence-t5 is published: MotionLCM's text
//! encoder (sentence-t5-large; Dai-Wenxun/MotionLCM v1.0 f534a7f, v2.0 086f8db).
//!
//! What sets T5 apart from the BERT family ([`crate::text::bert`]):
//! - RMSNorm before each sub-layer (weight only, no mean subtracted, no bias), a final RMSNorm;
//! - attention without the 1/√d scaling, bias-free q/k/v/o, plus a learned bias per head and
//!   relative-position bucket, held by block 0 alone and added in every layer;
//! - a feed-forward `wo(ReLU(wi·x))` without biases (v1.0; v1.1's gated GELU is refused by its
//!   tensor names);
//! - the token embedding unscaled, no position embedding.
//!
//! Every size comes from the tensors' shapes; the bucket's maximum distance (128 in every
//! released T5) is the one the shapes cannot tell.

use crate::checkpoint::{ModelFile, Tensor};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{Activation, WeightType};

use super::layers::Dense;

/// T5's `relative_attention_max_distance` in every released checkpoint.
pub const T5_MAX_DISTANCE: usize = 128;

/// The longest token sequence [`T5Encoder::hidden`] takes: attention is quadratic in it, and
/// sentence-t5 truncates at 256.
pub const T5_MAX_TOKENS: usize = 4096;

/// T5's `layer_norm_epsilon`.
const EPS: f32 = 1e-6;

/// The bidirectional bucket of a key at `rel = key − query` positions from its query
/// (`T5Attention._relative_position_bucket`): half the buckets for keys after the query; within
/// a half, distances below a quarter of the buckets get their own, longer ones share buckets
/// spaced logarithmically up to `max_distance`, and the last bucket takes everything past it.
/// The logarithm is taken in f32, as transformers does.
pub fn relative_position_bucket(rel: i64, num_buckets: usize, max_distance: usize) -> usize {
    let half = num_buckets / 2;
    let base = if rel > 0 { half } else { 0 };
    let n = rel.unsigned_abs() as usize;
    let exact = half / 2;
    if n < exact {
        return base + n;
    }
    let ratio = (n as f32 / exact as f32).ln() / ((max_distance as f64 / exact as f64).ln() as f32);
    let large = exact + (ratio * (half - exact) as f32) as usize;
    base + large.min(half - 1)
}

/// Sizes read from the tensors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct T5Dims {
    /// Token vocabulary (rows of `shared.weight`).
    pub vocab: usize,
    /// Model width.
    pub d_model: usize,
    /// Attention heads.
    pub heads: usize,
    /// Width per head.
    pub d_kv: usize,
    /// Feed-forward width.
    pub d_ff: usize,
    /// Encoder blocks.
    pub layers: usize,
    /// Relative-position buckets.
    pub buckets: usize,
    /// Width of the sentence vector (the Dense layer's outputs; `d_model` without one).
    pub out: usize,
}

struct Block {
    attn_norm: Tensor,
    /// q | k | v, bias-free.
    qkv: Dense,
    o: Dense,
    ff_norm: Tensor,
    wi: Dense,
    wo: Dense,
}

/// A T5 encoder with an optional sentence-transformers Dense head.
pub struct T5Encoder {
    dims: T5Dims,
    max_distance: usize,
    shared: Tensor,
    /// `[buckets, heads]`.
    position_bias: Tensor,
    blocks: Vec<Block>,
    final_norm: Tensor,
    dense: Option<Dense>,
}

impl T5Encoder {
    /// Reads `{prefix}shared.weight`, `{prefix}encoder.block.{i}.…` and
    /// `{prefix}encoder.final_layer_norm.weight` as `T5EncoderModel` names them, and the Dense
    /// head `dense` (`[out, d_model]`, no bias) when given. Linear weights are packed as `ty`.
    pub fn load(
        file: &ModelFile,
        prefix: &str,
        dense: Option<&str>,
        max_distance: usize,
        ty: WeightType,
    ) -> Result<T5Encoder> {
        let shape2 = |name: &str| -> Result<[usize; 2]> {
            match *file.shape(name)? {
                [a, b] => Ok([a, b]),
                ref other => Err(bad_file!("tensor `{name}`: shape {other:?}, expected 2-D")),
            }
        };
        let [vocab, d_model] = shape2(&format!("{prefix}shared.weight"))?;
        let p0 = format!("{prefix}encoder.block.0.layer.0.SelfAttention.");
        let [buckets, heads] = shape2(&format!("{p0}relative_attention_bias.weight"))?;
        let [inner, _] = shape2(&format!("{p0}q.weight"))?;
        let b0 = format!("{prefix}encoder.block.0.layer.1.DenseReluDense.");
        if file.contains(&format!("{b0}wi_0.weight")) {
            return Err(bad_file!(
                "`{b0}wi_0` is a gated feed-forward (T5 v1.1); this encoder is T5 v1.0's"
            ));
        }
        let [d_ff, _] = shape2(&format!("{b0}wi.weight"))?;
        if heads == 0 || inner % heads != 0 || buckets < 4 || buckets % 2 != 0 || d_model == 0 {
            return Err(bad_file!(
                "T5 sizes do not fit: width {d_model}, {heads} heads over {inner}, {buckets} \
                 buckets (even, at least 4)"
            ));
        }
        if max_distance < buckets / 4 + 1 {
            return Err(invalid_arg!(
                "max_distance {max_distance} must exceed the {} exact buckets",
                buckets / 4
            ));
        }
        let layers = (0..)
            .take_while(|i| file.has_prefix(&format!("{prefix}encoder.block.{i}.")))
            .count();
        let mut blocks = Vec::with_capacity(layers);
        for i in 0..layers {
            let p = format!("{prefix}encoder.block.{i}.layer.");
            let a = format!("{p}0.SelfAttention.");
            let qkv = ["q", "k", "v"].map(|n| format!("{a}{n}"));
            let ff = format!("{p}1.DenseReluDense.");
            blocks.push(Block {
                attn_norm: file.tensor(&format!("{p}0.layer_norm.weight"), &[d_model])?,
                qkv: Dense::load(
                    file,
                    &qkv.each_ref().map(String::as_str),
                    d_model,
                    inner,
                    false,
                    ty,
                )?,
                o: Dense::load(file, &[&format!("{a}o")], inner, d_model, false, ty)?,
                ff_norm: file.tensor(&format!("{p}1.layer_norm.weight"), &[d_model])?,
                wi: Dense::load(file, &[&format!("{ff}wi")], d_model, d_ff, false, ty)?,
                wo: Dense::load(file, &[&format!("{ff}wo")], d_ff, d_model, false, ty)?,
            });
        }
        let (dense, out) = match dense {
            Some(name) => {
                let [out, _] = shape2(&format!("{name}.weight"))?;
                (
                    Some(Dense::load(file, &[name], d_model, out, false, ty)?),
                    out,
                )
            }
            None => (None, d_model),
        };
        Ok(T5Encoder {
            dims: T5Dims {
                vocab,
                d_model,
                heads,
                d_kv: inner / heads,
                d_ff,
                layers,
                buckets,
                out,
            },
            max_distance,
            shared: file.tensor(&format!("{prefix}shared.weight"), &[vocab, d_model])?,
            position_bias: file.tensor(
                &format!("{p0}relative_attention_bias.weight"),
                &[buckets, heads],
            )?,
            blocks,
            final_norm: file.tensor(
                &format!("{prefix}encoder.final_layer_norm.weight"),
                &[d_model],
            )?,
            dense,
        })
    }

    /// The sizes read from the file.
    pub fn dims(&self) -> T5Dims {
        self.dims
    }

    /// Bytes of the packed linear weights.
    pub fn linear_weight_bytes(&self) -> usize {
        let block = |b: &Block| {
            [&b.qkv, &b.o, &b.wi, &b.wo]
                .iter()
                .map(|d| d.weight_bytes())
                .sum::<usize>()
        };
        self.blocks.iter().map(block).sum::<usize>()
            + self.dense.as_ref().map_or(0, |d| d.weight_bytes())
    }

    /// `last_hidden_state` (`[ids, d_model]`) of one unpadded token sequence.
    pub fn hidden(&self, ids: &[u32]) -> Result<Vec<f32>> {
        let (d, n) = (self.dims.d_model, ids.len());
        if n == 0 || n > T5_MAX_TOKENS {
            return Err(invalid_arg!(
                "T5 takes 1 to {T5_MAX_TOKENS} tokens, got {n}"
            ));
        }
        let mut x = Vec::with_capacity(n * d);
        for &id in ids {
            let id = id as usize;
            if id >= self.dims.vocab {
                return Err(invalid_arg!(
                    "token id {id} is outside the T5 vocabulary of {}",
                    self.dims.vocab
                ));
            }
            x.extend_from_slice(&self.shared.data()[id * d..(id + 1) * d]);
        }
        let bias = self.position_bias(n);
        for b in &self.blocks {
            let h = rms_norm(&x, d, b.attn_norm.data());
            let qkv = b.qkv.apply(&h, n, Activation::None);
            let ctx = self.attend(&qkv, n, &bias);
            let o = b.o.apply(&ctx, n, Activation::None);
            x.iter_mut().zip(&o).for_each(|(a, v)| *a += v);
            let h = rms_norm(&x, d, b.ff_norm.data());
            let f = b.wi.apply(&h, n, Activation::Relu);
            let f = b.wo.apply(&f, n, Activation::None);
            x.iter_mut().zip(&f).for_each(|(a, v)| *a += v);
        }
        Ok(rms_norm(&x, d, self.final_norm.data()))
    }

    /// sentence-transformers' vector: `hidden` averaged over the tokens whose `mask` is 1
    /// (divided by max(count, 1e-9)), through the Dense head, divided by max(‖·‖₂, 1e-12).
    /// `ids` and `mask` may carry padding; only mask-1 tokens are encoded.
    pub fn sentence_embedding(&self, ids: &[u32], mask: &[u8]) -> Result<Vec<f32>> {
        if ids.len() != mask.len() {
            return Err(invalid_arg!(
                "{} token ids but {} mask entries",
                ids.len(),
                mask.len()
            ));
        }
        // Padding is masked out of every attention and of the mean, so the unpadded sequence
        // gives the same vector.
        let kept: Vec<u32> = ids
            .iter()
            .zip(mask)
            .filter(|(_, &m)| m != 0)
            .map(|(&i, _)| i)
            .collect();
        let d = self.dims.d_model;
        let hidden = self.hidden(&kept)?;
        let mut mean = vec![0f32; d];
        for row in hidden.chunks_exact(d) {
            mean.iter_mut().zip(row).for_each(|(m, v)| *m += v);
        }
        let count = (kept.len() as f32).max(1e-9);
        mean.iter_mut().for_each(|m| *m /= count);
        let mut v = match &self.dense {
            Some(dense) => dense.apply(&mean, 1, Activation::None),
            None => mean,
        };
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        v.iter_mut().for_each(|x| *x /= norm);
        Ok(v)
    }

    /// The bias each head adds to the score of query `i`, key `j`: `[heads, n, n]`.
    fn position_bias(&self, n: usize) -> Vec<f32> {
        let h = self.dims.heads;
        let table = self.position_bias.data();
        let mut bias = vec![0f32; h * n * n];
        for i in 0..n {
            for j in 0..n {
                let b = relative_position_bucket(
                    j as i64 - i as i64,
                    self.dims.buckets,
                    self.max_distance,
                );
                for head in 0..h {
                    bias[(head * n + i) * n + j] = table[b * h + head];
                }
            }
        }
        bias
    }

    /// Unscaled attention with the position bias: softmax_j(q_i·k_j + bias) · v, per head;
    /// `qkv` is `[n, 3·inner]`, the result `[n, inner]`.
    fn attend(&self, qkv: &[f32], n: usize, bias: &[f32]) -> Vec<f32> {
        let (h, dk) = (self.dims.heads, self.dims.d_kv);
        let inner = h * dk;
        let mut out = vec![0f32; n * inner];
        let mut p = vec![0f32; n];
        for head in 0..h {
            let col = head * dk;
            for i in 0..n {
                let q = &qkv[i * 3 * inner + col..][..dk];
                for (j, s) in p.iter_mut().enumerate() {
                    let k = &qkv[j * 3 * inner + inner + col..][..dk];
                    *s = q.iter().zip(k).map(|(a, b)| a * b).sum::<f32>()
                        + bias[(head * n + i) * n + j];
                }
                let max = p.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
                let mut sum = 0.0;
                for s in p.iter_mut() {
                    *s = (*s - max).exp();
                    sum += *s;
                }
                p.iter_mut().for_each(|s| *s /= sum);
                let o = &mut out[i * inner + col..][..dk];
                for (j, &w) in p.iter().enumerate() {
                    let v = &qkv[j * 3 * inner + 2 * inner + col..][..dk];
                    o.iter_mut().zip(v).for_each(|(a, b)| *a += w * b);
                }
            }
        }
        out
    }
}

/// T5's RMSNorm per row of `dim`: `w · x / √(mean(x²) + 1e-6)`.
fn rms_norm(x: &[f32], dim: usize, w: &[f32]) -> Vec<f32> {
    let mut y = Vec::with_capacity(x.len());
    for row in x.chunks_exact(dim) {
        let var = row.iter().map(|v| v * v).sum::<f32>() / dim as f32;
        let r = 1.0 / (var + EPS).sqrt();
        y.extend(row.iter().zip(w).map(|(v, g)| g * (v * r)));
    }
    y
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_match_hand_derived_values() {
        // 32 buckets, max distance 128: 16 per direction, 8 exact; keys after the query
        // (rel > 0) start at 16. Distance n ≥ 8 goes to 8 + ⌊ln(n/8)/ln(16)·8⌋: 16 → 10,
        // 32 → 12, 127 → 15 (7.98), and everything from 128 on is clamped to 15.
        let b = |rel| relative_position_bucket(rel, 32, 128);
        assert_eq!([b(0), b(-1), b(-7), b(1), b(7)], [0, 1, 7, 17, 23]);
        assert_eq!([b(-8), b(-16), b(-32), b(-127)], [8, 10, 12, 15]);
        assert_eq!([b(-128), b(-5000), b(16), b(5000)], [15, 15, 26, 31]);
    }

    #[test]
    fn rms_norm_divides_by_the_root_mean_square() {
        // Row [3, 4]: mean square 12.5, so each value is divided by √12.5000010.
        let y = rms_norm(&[3.0, 4.0], 2, &[1.0, 2.0]);
        let r = (12.5f32 + 1e-6).sqrt();
        assert_eq!(y, [3.0 / r, 2.0 * (4.0 / r)]);
    }
}
