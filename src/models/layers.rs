//! The PyTorch layers the denoisers are built from, as read from a model file: `Linear`,
//! `nn.MultiheadAttention`'s packed projections and `LayerNorm`. Shared by every architecture.

use crate::checkpoint::{ModelFile, Tensor};
use crate::error::Result;
use crate::kernels;

/// A PyTorch `Linear`: weight `[out, in]`, bias `[out]`.
pub(crate) struct Linear {
    pub(crate) weight: Tensor,
    pub(crate) bias: Tensor,
    n_in: usize,
    n_out: usize,
}

impl Linear {
    pub(crate) fn load(file: &ModelFile, name: &str, n_in: usize, n_out: usize) -> Result<Linear> {
        Ok(Linear {
            weight: file.tensor(&format!("{name}.weight"), &[n_out, n_in])?,
            bias: file.tensor(&format!("{name}.bias"), &[n_out])?,
            n_in,
            n_out,
        })
    }

    /// `y[rows, out] = x[rows, in] · Wᵀ + b`.
    pub(crate) fn forward(&self, x: &[f32], rows: usize, y: &mut [f32]) {
        kernels::linear(
            x,
            self.weight.data(),
            Some(self.bias.data()),
            y,
            rows,
            self.n_in,
            self.n_out,
        );
    }
}

/// `nn.MultiheadAttention` with packed `in_proj_weight` `[3E, E]` (rows q, k, v).
pub(crate) struct Attention {
    pub(crate) in_proj_weight: Tensor,
    pub(crate) in_proj_bias: Tensor,
    pub(crate) out_proj: Linear,
}

impl Attention {
    pub(crate) fn load(file: &ModelFile, name: &str, e: usize) -> Result<Attention> {
        Ok(Attention {
            in_proj_weight: file.tensor(&format!("{name}.in_proj_weight"), &[3 * e, e])?,
            in_proj_bias: file.tensor(&format!("{name}.in_proj_bias"), &[3 * e])?,
            out_proj: Linear::load(file, &format!("{name}.out_proj"), e, e)?,
        })
    }
}

impl Attention {
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
    ) {
        let rows = batch * seq;
        let qkv = sized(qkv, rows * 3 * e);
        let (w, b) = (self.in_proj_weight.data(), self.in_proj_bias.data());
        kernels::linear(x, w, Some(b), qkv, rows, e, 3 * e);
        let attn = sized(attn, rows * e);
        for (i, o) in attn.chunks_exact_mut(seq * e).enumerate() {
            let block = &qkv[i * seq * 3 * e..(i + 1) * seq * 3 * e];
            let (k, v) = (&block[e..], &block[2 * e..]);
            kernels::multi_head_attention(
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
                None,
                false,
                o,
            );
        }
        self.out_proj.forward(attn, rows, sized(out, rows * e));
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

/// A scratch buffer grown to `n` values (never shrunk, so later steps do not allocate).
pub(crate) fn sized(v: &mut Vec<f32>, n: usize) -> &mut [f32] {
    v.resize(n, 0.0);
    &mut v[..n]
}
