//! Reverse-mode passes through MLD's post-LN transformer layers and skip stacks: the denoiser,
//! a ControlNet's copy of it and the VAE decoder. MotionLCM's consistency latent tuning
//! (Dai-Wenxun/MotionLCM v2.0, `mld/models/modeltype/mld.py` `_optimize_latents`) moves the
//! initial latent along the gradient of a loss on the decoded joints, through one consistency
//! step; these are the products it needs, with respect to the inputs only (no weight
//! gradients: the weights do not move).
//!
//! A recorded forward keeps what each backward reads (softmax weights, normalised rows and
//! their 1/σ, the feed-forward's pre-activation): it runs the layers' own packed GEMMs, but its
//! attention and norms are written out here so their intermediate values can be kept. Its
//! values therefore agree with the sampling path's to rounding, not bit for bit: the tuning
//! loop only follows the gradient, and the motion is made by the sampling path afterwards.
//! Every backward below is checked against PyTorch autograd (`tests/motionlcm_tuning.rs`).

use crate::error::{invalid_arg, Result};
use crate::kernels::{self, Activation};

use super::layers::{DecoderLayer, EncoderLayer, LayerNorm, LayerShape, Linear};
use super::mld::{LatentIo, MldDenoiser, MldWorkspace, SkipStack, VaeDecoder};

/// What the backward of one post-LN layer reads from its forward.
#[derive(Default)]
pub(crate) struct LayerTape {
    /// Self-attention: the packed q, k, v rows `[rows, 3e]` and the softmax weights
    /// `[batch, heads, seq, seq]`.
    qkv: Vec<f32>,
    self_p: Vec<f32>,
    /// Cross-attention (decoder layers): q `[rows, e]`, the memory's k and v `[batch · mem,
    /// 2e]` and the weights `[batch, heads, seq, mem]`.
    q: Vec<f32>,
    kv: Vec<f32>,
    cross_p: Vec<f32>,
    /// The post-LN norms in order (two in an encoder layer, three in a decoder layer).
    norms: [NormTape; 3],
    /// The feed-forward's input to its activation `[rows, ff]`.
    pre: Vec<f32>,
}

/// A LayerNorm's normalised rows `x̂` and `1/σ` per row.
#[derive(Default)]
struct NormTape {
    xhat: Vec<f32>,
    rstd: Vec<f32>,
}

/// A skip stack's recorded forward: one tape per layer in run order (input blocks, middle,
/// output blocks) and the final norm's.
#[derive(Default)]
pub(crate) struct StackTape {
    layers: Vec<LayerTape>,
    norm: NormTape,
}

/// Sizes of one stack pass: `batch` blocks of `seq` rows, each attending (decoder layers) to
/// `mem_len` rows of the memory.
#[derive(Clone, Copy)]
pub(crate) struct Blocks {
    pub batch: usize,
    pub seq: usize,
    pub mem_len: usize,
}

/// `x ← LayerNorm(x + residual)` row-wise (biased variance, f64 statistics as the sampling
/// kernel), keeping `x̂` and `1/σ`.
fn norm_recorded(
    n: &LayerNorm,
    x: &mut [f32],
    residual: Option<&[f32]>,
    eps: f32,
    t: &mut NormTape,
) {
    let (g, b) = (n.weight.data(), n.bias.data());
    let e = g.len();
    if let Some(r) = residual {
        kernels::add_inplace(x, r);
    }
    t.xhat.resize(x.len(), 0.0);
    t.rstd.resize(x.len() / e, 0.0);
    for ((row, xh), rstd) in x
        .chunks_exact_mut(e)
        .zip(t.xhat.chunks_exact_mut(e))
        .zip(t.rstd.iter_mut())
    {
        let mean = row.iter().map(|&v| v as f64).sum::<f64>() / e as f64;
        let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / e as f64;
        let r = 1.0 / (var + eps as f64).sqrt();
        *rstd = r as f32;
        for (((v, h), &gi), &bi) in row.iter_mut().zip(xh.iter_mut()).zip(g).zip(b) {
            *h = ((*v as f64 - mean) * r) as f32;
            *v = *h * gi + bi;
        }
    }
}

/// The LayerNorm's backward in place: `d` (gradient at its output) becomes the gradient at its
/// input, `σ⁻¹ (d̂ − mean(d̂) − x̂ · mean(d̂ ⊙ x̂))` with `d̂ = d ⊙ γ`.
fn norm_backward(n: &LayerNorm, t: &NormTape, d: &mut [f32]) {
    let g = n.weight.data();
    let e = g.len();
    for ((row, xh), &rstd) in d
        .chunks_exact_mut(e)
        .zip(t.xhat.chunks_exact(e))
        .zip(&t.rstd)
    {
        let (mut m1, mut m2) = (0.0f64, 0.0f64);
        for ((v, &gi), &h) in row.iter().zip(g).zip(xh) {
            let dh = (*v * gi) as f64;
            m1 += dh;
            m2 += dh * h as f64;
        }
        let (m1, m2) = (m1 / e as f64, m2 / e as f64);
        for ((v, &gi), &h) in row.iter_mut().zip(g).zip(xh) {
            let dh = (*v * gi) as f64;
            *v = (rstd as f64 * (dh - m1 - h as f64 * m2)) as f32;
        }
    }
}

/// `act'(pre) ⊙ d` in place: ReLU's step, or exact GELU's `Φ(x) + x·φ(x)`.
fn activation_backward(act: Activation, pre: &[f32], d: &mut [f32]) {
    match act {
        Activation::None => {}
        Activation::Relu => crate::grad::relu_backward(pre, d),
        Activation::Gelu => {
            const FRAC_1_SQRT_2PI: f32 = 0.398_942_3;
            for (g, &x) in d.iter_mut().zip(pre) {
                let cdf = 0.5 * (1.0 + kernels::erf(x * std::f32::consts::FRAC_1_SQRT_2));
                let pdf = FRAC_1_SQRT_2PI * (-0.5 * x * x).exp();
                *g *= cdf + x * pdf;
            }
        }
    }
}

/// Rows `[n, hd]` of head `h` out of strided rows (`stride` values apart, head width `hd`).
fn gather(src: &[f32], stride: usize, n: usize, h: usize, hd: usize, out: &mut Vec<f32>) {
    out.clear();
    for r in 0..n {
        out.extend_from_slice(&src[r * stride + h * hd..][..hd]);
    }
}

/// Adds rows `[n, hd]` into head `h` of strided rows.
fn scatter_add(rows: &[f32], stride: usize, n: usize, h: usize, hd: usize, dst: &mut [f32]) {
    for r in 0..n {
        kernels::add_inplace(&mut dst[r * stride + h * hd..][..hd], &rows[r * hd..][..hd]);
    }
}

/// Where the q, k and v rows of one attention call sit: `(values, offset, stride)`.
type Rows<'a> = (&'a [f32], usize, usize);

/// Block `b` of `n` rows of `r`.
fn block<'a>(r: Rows<'a>, b: usize, n: usize) -> &'a [f32] {
    &r.0[r.1 + b * n * r.2..]
}

/// Multi-head attention of `lq` query rows over `lk` key/value rows in each of `batch` blocks
/// (`softmax(q kᵀ/√d) v`, PyTorch's `nn.MultiheadAttention` between its projections), into
/// `out` `[batch · lq, e]`; `p` receives the weights `[batch, heads, lq, lk]`. Keys flagged in
/// `key_padding` (one flag per key row of a block) get weight 0.
#[allow(clippy::too_many_arguments)]
fn attend_recorded(
    q: Rows<'_>,
    k: Rows<'_>,
    v: Rows<'_>,
    batch: usize,
    lq: usize,
    lk: usize,
    heads: usize,
    key_padding: Option<&[bool]>,
    p: &mut Vec<f32>,
    out: &mut [f32],
) {
    let e = out.len() / (batch * lq).max(1);
    let hd = e / heads;
    let scale = 1.0 / (hd as f32).sqrt();
    p.resize(batch * heads * lq * lk, 0.0);
    let (mut qh, mut kh, mut vh, mut oh) = (Vec::new(), Vec::new(), Vec::new(), vec![0.0; lq * hd]);
    for b in 0..batch {
        for h in 0..heads {
            gather(block(q, b, lq), q.2, lq, h, hd, &mut qh);
            gather(block(k, b, lk), k.2, lk, h, hd, &mut kh);
            gather(block(v, b, lk), v.2, lk, h, hd, &mut vh);
            let w = &mut p[(b * heads + h) * lq * lk..][..lq * lk];
            kernels::matmul_nt(&qh, &kh, w, lq, hd, lk);
            for row in w.chunks_exact_mut(lk) {
                let mut max = f32::NEG_INFINITY;
                for (j, s) in row.iter_mut().enumerate() {
                    if key_padding.is_some_and(|m| m[j]) {
                        *s = f32::NEG_INFINITY;
                    } else {
                        *s *= scale;
                        max = max.max(*s);
                    }
                }
                if max == f32::NEG_INFINITY {
                    row.fill(0.0);
                    continue;
                }
                let mut sum = 0.0f32;
                for s in row.iter_mut() {
                    *s = (*s - max).exp();
                    sum += *s;
                }
                row.iter_mut().for_each(|s| *s /= sum);
            }
            kernels::matmul_nn(w, &vh, &mut oh, lq, lk, hd);
            let o = &mut out[b * lq * e..];
            for r in 0..lq {
                o[r * e + h * hd..][..hd].copy_from_slice(&oh[r * hd..][..hd]);
            }
        }
    }
}

/// The backward of [`attend_recorded`]: from `d_out` `[batch · lq, e]`, ADDS the gradients
/// with respect to q, k and v into `dq`, `dk`, `dv` (laid out as the q, k, v rows: the same
/// offsets and strides).
#[allow(clippy::too_many_arguments)]
fn attend_backward(
    q: Rows<'_>,
    k: Rows<'_>,
    v: Rows<'_>,
    p: &[f32],
    d_out: &[f32],
    batch: usize,
    lq: usize,
    lk: usize,
    heads: usize,
    dq: &mut [f32],
    dk: &mut [f32],
    dv: &mut [f32],
) {
    let e = d_out.len() / (batch * lq).max(1);
    let hd = e / heads;
    let scale = 1.0 / (hd as f32).sqrt();
    let mut qh = Vec::new();
    let (mut kh, mut vh, mut doh) = (Vec::new(), Vec::new(), Vec::new());
    let mut dp = vec![0.0; lq * lk];
    let mut pt = vec![0.0; lk * lq];
    let (mut dqh, mut dkh, mut dvh) = (vec![0.0; lq * hd], vec![0.0; lk * hd], vec![0.0; lk * hd]);
    for b in 0..batch {
        for h in 0..heads {
            gather(block(q, b, lq), q.2, lq, h, hd, &mut qh);
            gather(block(k, b, lk), k.2, lk, h, hd, &mut kh);
            gather(block(v, b, lk), v.2, lk, h, hd, &mut vh);
            gather(&d_out[b * lq * e..], e, lq, h, hd, &mut doh);
            let w = &p[(b * heads + h) * lq * lk..][..lq * lk];
            // dV = Pᵀ dO; dP = dO Vᵀ.
            for i in 0..lq {
                for j in 0..lk {
                    pt[j * lq + i] = w[i * lk + j];
                }
            }
            kernels::matmul_nn(&pt, &doh, &mut dvh, lk, lq, hd);
            kernels::matmul_nt(&doh, &vh, &mut dp, lq, hd, lk);
            // The softmax's backward, with the score scale folded in: dS = P ⊙ (dP − Σ P dP)/√d.
            for (dr, pr) in dp.chunks_exact_mut(lk).zip(w.chunks_exact(lk)) {
                let dot: f32 = dr.iter().zip(pr).map(|(a, b)| a * b).sum();
                for (d, &pv) in dr.iter_mut().zip(pr) {
                    *d = pv * (*d - dot) * scale;
                }
            }
            kernels::matmul_nn(&dp, &kh, &mut dqh, lq, lk, hd);
            for i in 0..lq {
                for j in 0..lk {
                    pt[j * lq + i] = dp[i * lk + j];
                }
            }
            kernels::matmul_nn(&pt, &qh, &mut dkh, lk, lq, hd);
            scatter_add(&dqh, q.2, lq, h, hd, &mut dq[q.1 + b * lq * q.2..]);
            scatter_add(&dkh, k.2, lk, h, hd, &mut dk[k.1 + b * lk * k.2..]);
            scatter_add(&dvh, v.2, lk, h, hd, &mut dv[v.1 + b * lk * v.2..]);
        }
    }
}

/// `d += layer.backward_input(g)`: the gradient through a Linear added to `d`.
fn add_backward(layer: &Linear, g: &[f32], rows: usize, d: &mut [f32], scratch: &mut Vec<f32>) {
    let tmp = super::layers::sized(scratch, d.len());
    layer.backward_input(g, rows, tmp);
    kernels::add_inplace(d, tmp);
}

/// The feed-forward `x ← norm(x + linear2(act(linear1(x))))`, recorded.
#[allow(clippy::too_many_arguments)]
fn feed_forward_recorded(
    l1: &Linear,
    l2: &Linear,
    norm: &LayerNorm,
    x: &mut [f32],
    rows: usize,
    s: LayerShape,
    pre: &mut Vec<f32>,
    nt: &mut NormTape,
) {
    let h = super::layers::sized(pre, rows * s.ff);
    l1.forward(x, rows, h);
    let mut act = h.to_vec();
    match s.act {
        Activation::Gelu => kernels::gelu_erf(&mut act),
        Activation::Relu => kernels::relu(&mut act),
        Activation::None => {}
    }
    let mut f = vec![0.0; rows * s.width];
    l2.forward(&act, rows, &mut f);
    norm_recorded(norm, x, Some(&f), s.eps, nt);
}

/// The feed-forward's backward: `d` at its output becomes the gradient at its input.
#[allow(clippy::too_many_arguments)]
fn feed_forward_backward(
    l1: &Linear,
    l2: &Linear,
    norm: &LayerNorm,
    d: &mut [f32],
    rows: usize,
    s: LayerShape,
    pre: &[f32],
    nt: &NormTape,
) {
    norm_backward(norm, nt, d);
    let mut dh = vec![0.0; rows * s.ff];
    l2.backward_input(d, rows, &mut dh);
    activation_backward(s.act, pre, &mut dh);
    add_backward(l1, &dh, rows, d, &mut Vec::new());
}

/// A layer of a skip stack with a recorded forward and its backward.
pub(crate) trait RecordedLayer {
    /// The layer's forward on `x` (`[batch · seq, e]`), keeping what the backward reads.
    fn forward_recorded(
        &self,
        x: &mut [f32],
        n: Blocks,
        memory: &[f32],
        key_padding: Option<&[bool]>,
        s: LayerShape,
        t: &mut LayerTape,
    );
    /// `d` at the layer's output becomes the gradient at its input; the gradient with respect
    /// to the memory is ADDED to `d_memory` (decoder layers).
    fn backward(
        &self,
        t: &LayerTape,
        d: &mut [f32],
        n: Blocks,
        s: LayerShape,
        d_memory: &mut [f32],
    );
}

/// The self-attention sublayer `x ← norm(x + out_proj(attn(qkv(x))))`, recorded.
#[allow(clippy::too_many_arguments)]
fn self_attention_recorded(
    qkv: &Linear,
    out_proj: &Linear,
    norm: &LayerNorm,
    x: &mut [f32],
    n: Blocks,
    key_padding: Option<&[bool]>,
    s: LayerShape,
    t: &mut LayerTape,
) {
    let (e, rows) = (s.width, n.batch * n.seq);
    let packed = super::layers::sized(&mut t.qkv, rows * 3 * e);
    qkv.forward(x, rows, packed);
    let mut attn = vec![0.0; rows * e];
    let qkv_rows = &t.qkv[..];
    attend_recorded(
        (qkv_rows, 0, 3 * e),
        (qkv_rows, e, 3 * e),
        (qkv_rows, 2 * e, 3 * e),
        n.batch,
        n.seq,
        n.seq,
        s.heads,
        key_padding,
        &mut t.self_p,
        &mut attn,
    );
    let mut proj = vec![0.0; rows * e];
    out_proj.forward(&attn, rows, &mut proj);
    norm_recorded(norm, x, Some(&proj), s.eps, &mut t.norms[0]);
}

/// The self-attention sublayer's backward.
fn self_attention_backward(
    qkv: &Linear,
    out_proj: &Linear,
    norm: &LayerNorm,
    t: &LayerTape,
    d: &mut [f32],
    n: Blocks,
    s: LayerShape,
) {
    let (e, rows) = (s.width, n.batch * n.seq);
    norm_backward(norm, &t.norms[0], d);
    let mut d_attn = vec![0.0; rows * e];
    out_proj.backward_input(d, rows, &mut d_attn);
    let mut d_qkv = vec![0.0; rows * 3 * e];
    let r = &t.qkv[..];
    // dq, dk and dv are disjoint column ranges of the same rows: split them apart.
    let mut dq = vec![0.0; rows * 3 * e];
    let mut dk = vec![0.0; rows * 3 * e];
    attend_backward(
        (r, 0, 3 * e),
        (r, e, 3 * e),
        (r, 2 * e, 3 * e),
        &t.self_p,
        &d_attn,
        n.batch,
        n.seq,
        n.seq,
        s.heads,
        &mut dq,
        &mut dk,
        &mut d_qkv,
    );
    kernels::add_inplace(&mut d_qkv, &dq);
    kernels::add_inplace(&mut d_qkv, &dk);
    add_backward(qkv, &d_qkv, rows, d, &mut Vec::new());
}

impl RecordedLayer for EncoderLayer {
    fn forward_recorded(
        &self,
        x: &mut [f32],
        n: Blocks,
        _memory: &[f32],
        key_padding: Option<&[bool]>,
        s: LayerShape,
        t: &mut LayerTape,
    ) {
        let a = &self.self_attn;
        self_attention_recorded(&a.qkv, &a.out_proj, &self.norm1, x, n, key_padding, s, t);
        let [_, n2, _] = &mut t.norms;
        let rows = n.batch * n.seq;
        feed_forward_recorded(
            &self.linear1,
            &self.linear2,
            &self.norm2,
            x,
            rows,
            s,
            &mut t.pre,
            n2,
        );
    }

    fn backward(
        &self,
        t: &LayerTape,
        d: &mut [f32],
        n: Blocks,
        s: LayerShape,
        _d_memory: &mut [f32],
    ) {
        let rows = n.batch * n.seq;
        feed_forward_backward(
            &self.linear1,
            &self.linear2,
            &self.norm2,
            d,
            rows,
            s,
            &t.pre,
            &t.norms[1],
        );
        let a = &self.self_attn;
        self_attention_backward(&a.qkv, &a.out_proj, &self.norm1, t, d, n, s);
    }
}

impl RecordedLayer for DecoderLayer {
    fn forward_recorded(
        &self,
        x: &mut [f32],
        n: Blocks,
        memory: &[f32],
        key_padding: Option<&[bool]>,
        s: LayerShape,
        t: &mut LayerTape,
    ) {
        debug_assert!(key_padding.is_none(), "decoder stacks run unmasked");
        let (e, rows) = (s.width, n.batch * n.seq);
        let a = &self.self_attn;
        self_attention_recorded(&a.qkv, &a.out_proj, &self.norm1, x, n, None, s, t);
        let ca = &self.cross_attn;
        ca.q.forward(x, rows, super::layers::sized(&mut t.q, rows * e));
        let mem_rows = n.batch * n.mem_len;
        ca.kv.forward(
            memory,
            mem_rows,
            super::layers::sized(&mut t.kv, mem_rows * 2 * e),
        );
        let mut attn = vec![0.0; rows * e];
        let (q, kv) = (&t.q[..], &t.kv[..]);
        attend_recorded(
            (q, 0, e),
            (kv, 0, 2 * e),
            (kv, e, 2 * e),
            n.batch,
            n.seq,
            n.mem_len,
            s.heads,
            None,
            &mut t.cross_p,
            &mut attn,
        );
        let mut proj = vec![0.0; rows * e];
        ca.out_proj.forward(&attn, rows, &mut proj);
        let [_, n2, n3] = &mut t.norms;
        norm_recorded(&self.norm2, x, Some(&proj), s.eps, n2);
        feed_forward_recorded(
            &self.linear1,
            &self.linear2,
            &self.norm3,
            x,
            rows,
            s,
            &mut t.pre,
            n3,
        );
    }

    fn backward(
        &self,
        t: &LayerTape,
        d: &mut [f32],
        n: Blocks,
        s: LayerShape,
        d_memory: &mut [f32],
    ) {
        let (e, rows) = (s.width, n.batch * n.seq);
        feed_forward_backward(
            &self.linear1,
            &self.linear2,
            &self.norm3,
            d,
            rows,
            s,
            &t.pre,
            &t.norms[2],
        );
        norm_backward(&self.norm2, &t.norms[1], d);
        let ca = &self.cross_attn;
        let mut d_attn = vec![0.0; rows * e];
        ca.out_proj.backward_input(d, rows, &mut d_attn);
        let mem_rows = n.batch * n.mem_len;
        let mut dq = vec![0.0; rows * e];
        let mut dk = vec![0.0; mem_rows * 2 * e];
        let mut dv = vec![0.0; mem_rows * 2 * e];
        let (q, kv) = (&t.q[..], &t.kv[..]);
        attend_backward(
            (q, 0, e),
            (kv, 0, 2 * e),
            (kv, e, 2 * e),
            &t.cross_p,
            &d_attn,
            n.batch,
            n.seq,
            n.mem_len,
            s.heads,
            &mut dq,
            &mut dk,
            &mut dv,
        );
        kernels::add_inplace(&mut dk, &dv);
        add_backward(&ca.kv, &dk, mem_rows, d_memory, &mut Vec::new());
        add_backward(&ca.q, &dq, rows, d, &mut Vec::new());
        let a = &self.self_attn;
        self_attention_backward(&a.qkv, &a.out_proj, &self.norm1, t, d, n, s);
    }
}

impl<L: RecordedLayer> SkipStack<L> {
    /// [`SkipStack::forward_taps`], recorded into `tape`: `residuals` (`[blocks, rows, e]`)
    /// added after block i, every block's output (after its residual) into `collect`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_recorded(
        &self,
        x: &mut [f32],
        n: Blocks,
        memory: &[f32],
        key_padding: Option<&[bool]>,
        residuals: Option<&[f32]>,
        mut collect: Option<&mut Vec<f32>>,
        tape: &mut StackTape,
    ) {
        let s = self.shape;
        let (e, rows) = (s.width, n.batch * n.seq);
        let size = rows * e;
        let layers = 2 * self.input.len() + 1;
        tape.layers.resize_with(layers, LayerTape::default);
        if let Some(c) = collect.as_deref_mut() {
            c.clear();
        }
        let mut tap = |block: usize, x: &mut [f32]| {
            if let Some(r) = residuals {
                kernels::add_inplace(x, &r[block * size..(block + 1) * size]);
            }
            if let Some(c) = collect.as_deref_mut() {
                c.extend_from_slice(x);
            }
        };
        let blocks = self.input.iter().chain([&self.middle]).enumerate();
        let mut skips = Vec::with_capacity(self.input.len());
        for (i, layer) in blocks {
            layer.forward_recorded(x, n, memory, key_padding, s, &mut tape.layers[i]);
            tap(i, x);
            if i < self.input.len() {
                skips.push(x.to_vec());
            }
        }
        let mut cat = vec![0.0; rows * 2 * e];
        for (i, (layer, join)) in self.output.iter().zip(&self.joins).enumerate() {
            let skip = skips.pop().expect("one skip per input block");
            for ((c, xr), sr) in cat
                .chunks_exact_mut(2 * e)
                .zip(x.chunks_exact(e))
                .zip(skip.chunks_exact(e))
            {
                c[..e].copy_from_slice(xr);
                c[e..].copy_from_slice(sr);
            }
            join.forward(&cat, rows, x);
            let b = self.input.len() + 1 + i;
            layer.forward_recorded(x, n, memory, key_padding, s, &mut tape.layers[b]);
            tap(b, x);
        }
        if let Some(norm) = &self.norm {
            norm_recorded(norm, x, None, s.eps, &mut tape.norm);
        }
    }

    /// The backward of [`SkipStack::forward_recorded`]: `d` at the stack's output becomes the
    /// gradient at its input. `inject` (`[blocks, rows, e]`) is a gradient arriving at each
    /// block's output from outside (a ControlNet copy's collected outputs); `d_residuals`
    /// receives the gradient with respect to each block's residual (`[blocks, rows, e]`); the
    /// memory's gradient is ADDED to `d_memory`.
    pub(crate) fn backward(
        &self,
        tape: &StackTape,
        d: &mut [f32],
        n: Blocks,
        inject: Option<&[f32]>,
        mut d_residuals: Option<&mut Vec<f32>>,
        d_memory: &mut [f32],
    ) {
        let s = self.shape;
        let (e, rows) = (s.width, n.batch * n.seq);
        let size = rows * e;
        let inputs = self.input.len();
        if let Some(norm) = &self.norm {
            norm_backward(norm, &tape.norm, d);
        }
        if let Some(r) = d_residuals.as_deref_mut() {
            r.clear();
            r.resize((2 * inputs + 1) * size, 0.0);
        }
        let mut tap = |block: usize, d: &mut [f32]| {
            if let Some(g) = inject {
                kernels::add_inplace(d, &g[block * size..(block + 1) * size]);
            }
            if let Some(r) = d_residuals.as_deref_mut() {
                r[block * size..(block + 1) * size].copy_from_slice(d);
            }
        };
        let mut d_skips = vec![vec![0.0; size]; inputs];
        let mut d_cat = vec![0.0; rows * 2 * e];
        for (i, (layer, join)) in self.output.iter().zip(&self.joins).enumerate().rev() {
            let b = inputs + 1 + i;
            tap(b, d);
            layer.backward(&tape.layers[b], d, n, s, d_memory);
            join.backward_input(d, rows, &mut d_cat);
            // Output block i joined the output of input block n − 1 − i.
            let skip = &mut d_skips[inputs - 1 - i];
            for ((c, dr), sr) in d_cat
                .chunks_exact(2 * e)
                .zip(d.chunks_exact_mut(e))
                .zip(skip.chunks_exact_mut(e))
            {
                dr.copy_from_slice(&c[..e]);
                kernels::add_inplace(sr, &c[e..]);
            }
        }
        tap(inputs, d);
        self.middle
            .backward(&tape.layers[inputs], d, n, s, d_memory);
        for j in (0..inputs).rev() {
            // Input block j's output went on to block j + 1 and into its skip.
            kernels::add_inplace(d, &d_skips[j]);
            tap(j, d);
            self.input[j].backward(&tape.layers[j], d, n, s, d_memory);
        }
    }
}

/// One recorded pass of an MLD denoiser (or a ControlNet's copy) over one sample.
#[derive(Default)]
pub(crate) struct DenoiserTape {
    stack: StackTape,
    ws: MldWorkspace,
}

impl MldDenoiser {
    /// [`MldDenoiser::sequence`] for one sample `z` (`[latent_tokens, channels]`), recorded;
    /// the sequence after the stack is then [`DenoiserTape::sequence`].
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn sequence_recorded(
        &self,
        z: &[f32],
        t: f32,
        w: Option<f32>,
        text: &[f32],
        residuals: Option<&[f32]>,
        collect: Option<&mut Vec<f32>>,
        tape: &mut DenoiserTape,
    ) -> Result<()> {
        let d = &self.cfg.denoiser;
        let (l, e) = (d.latent_tokens, d.latent_dim);
        self.embed_sequence(z, l, t, w, &[text], &mut tape.ws)?;
        let n = Blocks {
            batch: 1,
            seq: l + 2,
            mem_len: 0,
        };
        if let Some(r) = residuals {
            let need = self.encoder.blocks() * n.seq * e;
            if r.len() != need {
                return Err(invalid_arg!(
                    "ControlNet residuals hold {} values, the stack takes {need}",
                    r.len()
                ));
            }
        }
        let xs = &mut tape.ws.x[..n.seq * e];
        self.encoder
            .forward_recorded(xs, n, &[], None, residuals, collect, &mut tape.stack);
        Ok(())
    }

    /// The backward of [`MldDenoiser::sequence_recorded`]: from the gradient at the whole
    /// sequence after the stack (`d_seq`, `[latent_tokens + 2, width]`, used as scratch), with
    /// gradients arriving at the blocks' outputs (`inject`) and the residuals' gradients out
    /// (`d_residuals`), ADDS the gradient with respect to `z` to `d_z`.
    pub(crate) fn sequence_backward(
        &self,
        tape: &DenoiserTape,
        d_seq: &mut [f32],
        inject: Option<&[f32]>,
        d_residuals: Option<&mut Vec<f32>>,
        d_z: &mut [f32],
    ) {
        let d = &self.cfg.denoiser;
        let (l, e) = (d.latent_tokens, d.latent_dim);
        let n = Blocks {
            batch: 1,
            seq: l + 2,
            mem_len: 0,
        };
        self.encoder
            .backward(&tape.stack, d_seq, n, inject, d_residuals, &mut []);
        // The learned positions and the time and text tokens do not depend on z.
        let d_tokens = &d_seq[..l * e];
        match &self.latent_io {
            Some(io) => {
                let mut tmp = vec![0.0; d_z.len()];
                io.pre.backward_input(d_tokens, l, &mut tmp);
                kernels::add_inplace(d_z, &tmp);
            }
            None => kernels::add_inplace(d_z, d_tokens),
        }
    }

    /// ε̂ at `z` (one sample) as [`MldDenoiser::forward_guided`] gives it, recorded.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn eps_recorded(
        &self,
        z: &[f32],
        t: f32,
        w: Option<f32>,
        text: &[f32],
        residuals: Option<&[f32]>,
        eps: &mut [f32],
        tape: &mut DenoiserTape,
    ) -> Result<()> {
        self.sequence_recorded(z, t, w, text, residuals, None, tape)?;
        let d = &self.cfg.denoiser;
        let (l, e) = (d.latent_tokens, d.latent_dim);
        let tokens = &tape.ws.x[..l * e];
        match &self.latent_io {
            Some(LatentIo {
                post: Some(post), ..
            }) => post.forward(tokens, l, eps),
            _ => eps.copy_from_slice(tokens),
        }
        Ok(())
    }

    /// The backward of [`MldDenoiser::eps_recorded`]: ADDS `(∂ε̂/∂z)ᵀ d_eps` to `d_z`; the
    /// residuals' gradients into `d_residuals`.
    pub(crate) fn eps_backward(
        &self,
        tape: &DenoiserTape,
        d_eps: &[f32],
        d_residuals: Option<&mut Vec<f32>>,
        d_z: &mut [f32],
    ) {
        let d = &self.cfg.denoiser;
        let (l, e) = (d.latent_tokens, d.latent_dim);
        let mut d_seq = vec![0.0; (l + 2) * e];
        match &self.latent_io {
            Some(LatentIo {
                post: Some(post), ..
            }) => post.backward_input(d_eps, l, &mut d_seq[..l * e]),
            _ => d_seq[..l * e].copy_from_slice(d_eps),
        }
        self.sequence_backward(tape, &mut d_seq, None, d_residuals, d_z);
    }
}

/// One recorded pass of MLD's VAE decoder.
#[derive(Default)]
pub(crate) struct VaeTape {
    stack: StackTape,
    rows: usize,
    frames: usize,
}

impl VaeDecoder {
    /// [`VaeDecoder::decode_frames`], recorded.
    pub(crate) fn decode_recorded_into(
        &self,
        latent: &[f32],
        rows: usize,
        frames: usize,
        out: &mut Vec<f32>,
        tape: &mut VaeTape,
    ) -> Result<()> {
        let e = self.cfg.latent_dim;
        self.check_decode(latent, rows, frames)?;
        let mut buf = Vec::new();
        let memory = self.memory(latent, rows, &mut buf);
        let mut x = self.pe.data()[..frames * e].to_vec();
        let n = Blocks {
            batch: 1,
            seq: frames,
            mem_len: rows,
        };
        self.decoder
            .forward_recorded(&mut x, n, memory, None, None, None, &mut tape.stack);
        out.resize(frames * self.cfg.nfeats, 0.0);
        self.final_layer.forward(&x, frames, out);
        (tape.rows, tape.frames) = (rows, frames);
        Ok(())
    }

    /// The backward of [`VaeDecoder::decode_recorded`]: `d_latent` (overwritten) from the
    /// gradient at the features `[frames, nfeats]`.
    pub(crate) fn decode_backward(
        &self,
        tape: &VaeTape,
        d_features: &[f32],
        d_latent: &mut [f32],
    ) -> Result<()> {
        let e = self.cfg.latent_dim;
        let (rows, frames) = (tape.rows, tape.frames);
        if frames == 0
            || d_features.len() != frames * self.cfg.nfeats
            || d_latent.len() != rows * self.channels
        {
            return Err(invalid_arg!(
                "the decoder's backward needs its recorded pass and gradients of {frames} frames \
                 × {} features into {rows} × {} latent values",
                self.cfg.nfeats,
                self.channels
            ));
        }
        let mut d = vec![0.0; frames * e];
        self.final_layer.backward_input(d_features, frames, &mut d);
        let mut d_memory = vec![0.0; rows * e];
        let n = Blocks {
            batch: 1,
            seq: frames,
            mem_len: rows,
        };
        self.decoder
            .backward(&tape.stack, &mut d, n, None, None, &mut d_memory);
        match &self.latent_post {
            Some(post) => post.backward_input(&d_memory, rows, d_latent),
            None => d_latent.copy_from_slice(&d_memory),
        }
        Ok(())
    }
}
