//! Multi-head scaled dot-product attention.
//!
//! Work is split into (query block, head) tasks that write disjoint `[rows, head_dim]` blocks
//! of `out`. The block size is fixed (not derived from the thread count) and every output
//! element comes from one task, so results are bit-identical for any pool size.

use rayon::prelude::*;

use super::activation::softmax_row;

/// Query rows per task: bounds the score buffer at `Q_BLOCK × lk` and gives 2 cores enough
/// tasks to balance at the sequence lengths we run (~200-400).
const Q_BLOCK: usize = 32;
const _: () = assert!(Q_BLOCK <= 64, "dead-row mask is a u64");

/// Below this many score entries × head_dim, run on the calling thread.
const PAR_MIN_WORK: usize = 1 << 16;

/// Raw output pointer shared by tasks that write disjoint blocks.
#[derive(Clone, Copy)]
struct OutPtr(*mut f32);
// SAFETY: tasks write disjoint (row block, head) regions; see `multi_head_attention`.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}
impl OutPtr {
    fn get(self) -> *mut f32 {
        self.0
    }
}

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
    let e = heads * head_dim;
    assert!(out.len() >= lq * e, "attention: out too short");
    let rows_fit =
        |len: usize, rows: usize, stride: usize| rows == 0 || len >= (rows - 1) * stride + e;
    assert!(rows_fit(q.len(), lq, q_stride), "attention: q too short");
    assert!(rows_fit(k.len(), lk, k_stride), "attention: k too short");
    assert!(rows_fit(v.len(), lk, v_stride), "attention: v too short");
    if let Some(p) = key_padding {
        assert_eq!(p.len(), lk, "attention: key_padding length");
    }
    if lq == 0 || e == 0 {
        return;
    }
    if lk == 0 {
        out[..lq * e].fill(0.0);
        return;
    }

    // PyTorch computes head_dim ** -0.5 in double and applies it as an f32 scalar.
    let scale = (1.0 / (head_dim as f64).sqrt()) as f32;
    let blocks = lq.div_ceil(Q_BLOCK);
    let tasks = blocks * heads;
    let out_ptr = OutPtr(out.as_mut_ptr());

    let task = |scores: &mut Vec<f32>, t: usize| {
        let (block, h) = (t / heads, t % heads);
        let i0 = block * Q_BLOCK;
        let rows = Q_BLOCK.min(lq - i0);
        // Causal rows of this block see at most keys 0..i0+rows; the rest would be masked anyway.
        let keys = if causal { lk.min(i0 + rows) } else { lk };
        let col = h * head_dim;
        scores.clear();
        scores.resize(rows * keys, 0.0);

        // SAFETY (both sgemm calls): q rows i0..i0+rows, and k/v rows 0..keys, at columns
        // col..col+head_dim lie within the slices (asserted above); `scores` holds rows×keys.
        unsafe {
            matrixmultiply::sgemm(
                rows,
                head_dim,
                keys,
                scale,
                q.as_ptr().add(i0 * q_stride + col),
                q_stride as isize,
                1,
                k.as_ptr().add(col),
                1,
                k_stride as isize,
                0.0,
                scores.as_mut_ptr(),
                keys as isize,
                1,
            );
        }

        let mut dead_rows = 0u64; // bit r: row r has no visible key (Q_BLOCK <= 64)
        for (r, row) in scores.chunks_exact_mut(keys).enumerate() {
            if let Some(p) = key_padding {
                for (s, &pad) in row.iter_mut().zip(p) {
                    if pad {
                        *s = f32::NEG_INFINITY;
                    }
                }
            }
            if causal {
                row[(i0 + r + 1).min(keys)..].fill(f32::NEG_INFINITY);
            }
            if !softmax_row(row) {
                dead_rows |= 1 << r;
            }
        }

        let out = out_ptr.get();
        // SAFETY: this task alone writes rows i0..i0+rows, columns col..col+head_dim of `out`
        // (bounds asserted above); no other reference to `out` is used while tasks run.
        unsafe {
            let dst = out.add(i0 * e + col);
            matrixmultiply::sgemm(
                rows,
                keys,
                head_dim,
                1.0,
                scores.as_ptr(),
                keys as isize,
                1,
                v.as_ptr().add(col),
                v_stride as isize,
                1,
                0.0,
                dst,
                e as isize,
                1,
            );
            // All-zero weights already give zeros unless v holds inf/NaN; make it exact.
            for r in (0..rows).filter(|r| dead_rows >> r & 1 == 1) {
                std::slice::from_raw_parts_mut(dst.add(r * e), head_dim).fill(0.0);
            }
        }
    };

    let work = lq.saturating_mul(lk).saturating_mul(e);
    if tasks == 1 || work < PAR_MIN_WORK || rayon::current_num_threads() <= 1 {
        let mut scores = Vec::new();
        (0..tasks).for_each(|t| task(&mut scores, t));
    } else {
        (0..tasks).into_par_iter().for_each_init(Vec::new, task);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, same_bits, Rng};

    /// Naive f64 attention; returns `[lq, heads*head_dim]`.
    #[allow(clippy::too_many_arguments)]
    fn naive(
        q: &[f32],
        qs: usize,
        k: &[f32],
        ks: usize,
        v: &[f32],
        vs: usize,
        lq: usize,
        lk: usize,
        heads: usize,
        hd: usize,
        pad: Option<&[bool]>,
        causal: bool,
    ) -> Vec<f64> {
        let e = heads * hd;
        let mut out = vec![0.0; lq * e];
        for h in 0..heads {
            for i in 0..lq {
                let visible: Vec<usize> = (0..lk)
                    .filter(|&j| !(pad.is_some_and(|p| p[j]) || (causal && j > i)))
                    .collect();
                if visible.is_empty() {
                    continue;
                }
                let s: Vec<f64> = visible
                    .iter()
                    .map(|&j| {
                        (0..hd)
                            .map(|d| q[i * qs + h * hd + d] as f64 * k[j * ks + h * hd + d] as f64)
                            .sum::<f64>()
                            / (hd as f64).sqrt()
                    })
                    .collect();
                let max = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let w: Vec<f64> = s.iter().map(|x| (x - max).exp()).collect();
                let sum: f64 = w.iter().sum();
                for d in 0..hd {
                    out[i * e + h * hd + d] = visible
                        .iter()
                        .zip(&w)
                        .map(|(&j, &wj)| wj / sum * v[j * vs + h * hd + d] as f64)
                        .sum();
                }
            }
        }
        out
    }

    fn assert_close(got: &[f32], want: &[f64], what: &str) {
        assert_eq!(got.len(), want.len());
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g as f64 - w).abs() <= 2e-6 * (1.0 + w.abs()),
                "{what}[{i}]: {g} vs {w}"
            );
        }
    }

    /// Separate contiguous q, k, v; scaled so softmax is far from uniform.
    fn qkv(rng: &mut Rng, lq: usize, lk: usize, e: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let q = rng.vec(lq * e).iter().map(|x| x * 3.0).collect();
        (q, rng.vec(lk * e), rng.vec(lk * e))
    }

    #[test]
    fn plain_cross_attention() {
        let mut rng = Rng::new(10);
        for (lq, lk, heads, hd) in [
            (1, 1, 1, 1),
            (5, 7, 3, 4),
            (1, 77, 8, 64),
            (70, 3, 2, 5),
            (197, 50, 4, 16),
        ] {
            let e = heads * hd;
            let (q, k, v) = qkv(&mut rng, lq, lk, e);
            let mut out = vec![f32::NAN; lq * e];
            multi_head_attention(
                &q, e, &k, e, &v, e, lq, lk, heads, hd, None, false, &mut out,
            );
            let want = naive(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, false);
            assert_close(&out, &want, &format!("cross {lq}x{lk} h{heads} d{hd}"));
        }
    }

    #[test]
    fn packed_qkv_with_key_padding() {
        let mut rng = Rng::new(11);
        let (l, heads, hd) = (37, 2, 5);
        let e = heads * hd;
        let mut packed = rng.vec(l * 3 * e);
        let pad: Vec<bool> = (0..l).map(|j| j % 5 == 2 || j >= 33).collect();
        // Padded keys/values hold huge numbers: any nonzero weight on them would show.
        for j in (0..l).filter(|&j| pad[j]) {
            packed[j * 3 * e + e..j * 3 * e + 3 * e].fill(1e30);
        }
        let (q, k, v) = (&packed[..], &packed[e..], &packed[2 * e..]);
        let s = 3 * e;
        let mut out = vec![f32::NAN; l * e];
        multi_head_attention(
            q,
            s,
            k,
            s,
            v,
            s,
            l,
            l,
            heads,
            hd,
            Some(&pad),
            false,
            &mut out,
        );
        assert_close(
            &out,
            &naive(q, s, k, s, v, s, l, l, heads, hd, Some(&pad), false),
            "packed+pad",
        );
    }

    #[test]
    fn causal_self_attention() {
        let mut rng = Rng::new(12);
        for (l, heads, hd) in [(1, 1, 3), (70, 4, 8), (33, 3, 1)] {
            let e = heads * hd;
            let (q, k, v) = qkv(&mut rng, l, l, e);
            let mut out = vec![f32::NAN; l * e];
            multi_head_attention(&q, e, &k, e, &v, e, l, l, heads, hd, None, true, &mut out);
            let want = naive(&q, e, &k, e, &v, e, l, l, heads, hd, None, true);
            assert_close(&out, &want, &format!("causal {l} h{heads} d{hd}"));
            // Row 0 sees only key 0: exactly v[0].
            assert_eq!(&out[..e], &v[..e]);
        }
    }

    #[test]
    fn causal_with_more_queries_than_keys() {
        let mut rng = Rng::new(13);
        let (lq, lk, heads, hd) = (45, 20, 2, 3);
        let e = heads * hd;
        let (q, k, v) = qkv(&mut rng, lq, lk, e);
        let mut out = vec![f32::NAN; lq * e];
        multi_head_attention(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, true, &mut out);
        assert_close(
            &out,
            &naive(&q, e, &k, e, &v, e, lq, lk, heads, hd, None, true),
            "causal lq>lk",
        );
    }

    #[test]
    fn fully_masked_rows_are_zero() {
        let mut rng = Rng::new(14);
        let (l, heads, hd) = (40, 2, 4);
        let e = heads * hd;
        let (q, k, v) = qkv(&mut rng, l, l, e);
        // Key 0 padded: under causal masking query 0 has nothing left to attend to.
        let pad: Vec<bool> = (0..l).map(|j| j == 0 || j == 7).collect();
        let mut out = vec![f32::NAN; l * e];
        multi_head_attention(
            &q,
            e,
            &k,
            e,
            &v,
            e,
            l,
            l,
            heads,
            hd,
            Some(&pad),
            true,
            &mut out,
        );
        assert_eq!(&out[..e], &vec![0.0; e][..]);
        assert_close(
            &out,
            &naive(&q, e, &k, e, &v, e, l, l, heads, hd, Some(&pad), true),
            "masked row",
        );

        let all = vec![true; l];
        multi_head_attention(
            &q,
            e,
            &k,
            e,
            &v,
            e,
            l,
            l,
            heads,
            hd,
            Some(&all),
            false,
            &mut out,
        );
        assert!(out.iter().all(|&x| x == 0.0));

        let mut out = vec![f32::NAN; 3 * e];
        multi_head_attention(
            &q,
            e,
            &[],
            e,
            &[],
            e,
            3,
            0,
            heads,
            hd,
            None,
            false,
            &mut out,
        );
        assert!(out.iter().all(|&x| x == 0.0));
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let mut rng = Rng::new(15);
        let (l, heads, hd) = (203, 4, 64);
        let e = heads * hd;
        let packed = rng.vec(l * 3 * e);
        let pad: Vec<bool> = (0..l).map(|j| j > 190).collect();
        let s = 3 * e;
        for causal in [false, true] {
            let run = |t| {
                in_pool(t, || {
                    let mut out = vec![0.0; l * e];
                    let (q, k, v) = (&packed[..], &packed[e..], &packed[2 * e..]);
                    multi_head_attention(
                        q,
                        s,
                        k,
                        s,
                        v,
                        s,
                        l,
                        l,
                        heads,
                        hd,
                        Some(&pad),
                        causal,
                        &mut out,
                    );
                    out
                })
            };
            let base = run(1);
            assert!(
                same_bits(&base, &run(2)) && same_bits(&base, &run(3)),
                "causal={causal}"
            );
        }
    }
}
