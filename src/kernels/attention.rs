//! Multi-head scaled dot-product attention.

/// Multi-head attention over already-projected q, k, v.
///
/// `q` holds `lq` rows, row `i` starting at `i * q_stride`, each row `heads * head_dim` values
/// (head `h` at columns `h*head_dim..`); `k`, `v` likewise with `lk` rows and their own strides
/// (so q/k/v can be read straight out of a packed `[L, 3E]` projection). Scores are
/// `q_h · k_hᵀ / sqrt(head_dim)`; `key_padding[j] == true` excludes key `j` (weight exactly 0);
/// `causal` excludes keys `j > i`. A query row whose keys are all excluded yields zeros.
/// `out` is `[lq, heads * head_dim]`, heads concatenated in order.
#[allow(clippy::too_many_arguments)]
pub fn multi_head_attention(
    q: &[f32],
    q_stride: usize,
    k: &[f32],
    k_stride: usize,
    v: &[f32],
    v_stride: usize,
    lq: usize,
    lk: usize,
    heads: usize,
    head_dim: usize,
    key_padding: Option<&[bool]>,
    causal: bool,
    out: &mut [f32],
) {
    let _ = (q, q_stride, k, k_stride, v, v_stride, lq, lk, heads, head_dim, key_padding, causal, out);
    unimplemented!()
}
