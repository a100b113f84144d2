//! GEMM wrappers over `matrixmultiply::sgemm`, split by output rows or columns across the
//! current rayon pool, one single-threaded sgemm call per chunk.
//!
//! sgemm computes every output element as the same k-ordered chain of multiply-adds (its k
//! blocking does not depend on m or n, and edge tiles run the same micro-kernel), so any
//! split of the output gives the same bits as a single call.

use rayon::prelude::*;

/// Split granularity: the AVX/FMA micro-kernel's tile edge, so chunks are whole tiles (with the
/// 16-wide AVX-512 kernel a chunk may end in one partial tile).
const SPLIT_UNIT: usize = 8;

/// Below this many multiply-adds (m·k·n) the fork/join and the repeated packing cost more than
/// a second core saves.
const PAR_MIN_MACS: usize = 1 << 20;

/// `y[m, n] = x[m, k] · w[n, k]ᵀ + bias[n]` (PyTorch `Linear`). `y` is overwritten.
///
/// The bias is written into `y` first and sgemm accumulates onto it (β = 1), as PyTorch's
/// `addmm` does, so there is no second pass over the output.
pub fn linear(
    x: &[f32],
    w: &[f32],
    bias: Option<&[f32]>,
    y: &mut [f32],
    m: usize,
    k: usize,
    n: usize,
) {
    if let Some(b) = bias {
        assert_eq!(b.len(), n, "linear: bias length");
    }
    // w is [n, k] row-major, read as its transpose [k, n]: row stride 1, column stride k.
    gemm(m, k, n, x, k, 1, w, 1, k, bias, y);
}

/// `c[m, n] = a[m, k] · b[n, k]ᵀ`. `c` is overwritten.
pub fn matmul_nt(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize) {
    gemm(m, k, n, a, k, 1, b, 1, k, None, c);
}

/// `c[m, n] = a[m, k] · b[k, n]`. `c` is overwritten.
pub fn matmul_nn(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize) {
    gemm(m, k, n, a, k, 1, b, n, 1, None, c);
}

/// Largest index touched by a `rows × cols` strided view, plus one.
fn extent(rows: usize, cols: usize, rs: usize, cs: usize) -> usize {
    if rows == 0 || cols == 0 {
        0
    } else {
        (rows - 1) * rs + (cols - 1) * cs + 1
    }
}

/// `c[m, n] (row-major, contiguous) = a · b (+ bias)` with arbitrary non-negative strides for
/// `a` (`m × k`) and `b` (`k × n`). The bounds checks here are what make the sgemm calls sound.
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    rsa: usize,
    csa: usize,
    b: &[f32],
    rsb: usize,
    csb: usize,
    bias: Option<&[f32]>,
    c: &mut [f32],
) {
    assert!(
        a.len() >= extent(m, k, rsa, csa),
        "gemm: a too short for {m}x{k}"
    );
    assert!(
        b.len() >= extent(k, n, rsb, csb),
        "gemm: b too short for {k}x{n}"
    );
    assert!(c.len() >= m * n, "gemm: c too short for {m}x{n}");
    if let Some(bias) = bias {
        assert!(bias.len() >= n);
    }
    if m == 0 || n == 0 {
        return;
    }
    let c_ptr = SharedMut(c.as_mut_ptr());

    // C[r0..r1, c0..c1] = A[r0..r1, :] · B[:, c0..c1] (+ bias[c0..c1]).
    let block = |r0: usize, r1: usize, c0: usize, c1: usize| {
        let c = c_ptr.get();
        let beta = match bias {
            Some(bias) => {
                for r in r0..r1 {
                    // SAFETY: row r, columns c0..c1 of c, inside the checked m×n; no other
                    // task touches this block.
                    unsafe { std::slice::from_raw_parts_mut(c.add(r * n + c0), c1 - c0) }
                        .copy_from_slice(&bias[c0..c1]);
                }
                1.0
            }
            None => 0.0,
        };
        // SAFETY: the a, b and c extents were bounds-checked above; the offsets select a
        // sub-block of each, and this block of c is written by this call only.
        unsafe {
            matrixmultiply::sgemm(
                r1 - r0,
                k,
                c1 - c0,
                1.0,
                a.as_ptr().add(r0 * rsa),
                rsa as isize,
                csa as isize,
                b.as_ptr().add(c0 * csb),
                rsb as isize,
                csb as isize,
                beta,
                c.add(r0 * n + c0),
                n as isize,
                1,
            );
        }
    };

    let threads = crate::kernels::threads();
    let macs = m.saturating_mul(k).saturating_mul(n);
    // Each chunk packs its own slice of the split operand and all of the other one, so split
    // the larger output dimension: rows when m ≥ n, else columns (which is also what gives
    // short inputs like a 20-token text encoder any parallelism).
    let by_rows = m >= n;
    let len = if by_rows { m } else { n };
    let units = len.div_ceil(SPLIT_UNIT);
    if threads <= 1 || macs < PAR_MIN_MACS || units < 2 {
        block(0, m, 0, n);
        return;
    }
    // One chunk per thread, equal to within a tile: more chunks would only repeat packing.
    let tasks = threads.min(units);
    let edge = |t: usize| (units * t / tasks * SPLIT_UNIT).min(len);
    (0..tasks).into_par_iter().for_each(|t| {
        let (lo, hi) = (edge(t), edge(t + 1));
        if by_rows {
            block(lo, hi, 0, n);
        } else {
            block(0, m, lo, hi);
        }
    });
}

/// Output pointer shared by tasks that write disjoint blocks.
#[derive(Clone, Copy)]
pub(super) struct SharedMut(pub(super) *mut f32);
// SAFETY: only used to hand disjoint output blocks to parallel tasks.
unsafe impl Send for SharedMut {}
unsafe impl Sync for SharedMut {}
impl SharedMut {
    // A method (not field access) so closures capture the whole Send + Sync wrapper.
    pub(super) fn get(self) -> *mut f32 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, Rng};

    /// Reference `a · b (+ bias)` in f64 plus the bound `Σ|a||b| + |bias|` for error scaling.
    #[allow(clippy::too_many_arguments)]
    fn naive(
        m: usize,
        k: usize,
        n: usize,
        a: &[f32],
        rsa: usize,
        csa: usize,
        b: &[f32],
        rsb: usize,
        csb: usize,
        bias: Option<&[f32]>,
    ) -> (Vec<f64>, Vec<f64>) {
        let mut c = vec![0.0; m * n];
        let mut mag = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = bias.map_or(0.0, |b| b[j] as f64);
                let mut g = s.abs();
                for p in 0..k {
                    let t = a[i * rsa + p * csa] as f64 * b[p * rsb + j * csb] as f64;
                    s += t;
                    g += t.abs();
                }
                c[i * n + j] = s;
                mag[i * n + j] = g;
            }
        }
        (c, mag)
    }

    /// Forward-error bound of an f32 dot product of length k (plus one bias add), with slack.
    fn check(got: &[f32], want: &[f64], mag: &[f64], k: usize, what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: length");
        let u = f32::EPSILON as f64 / 2.0;
        for (i, ((&g, &w), &s)) in got.iter().zip(want).zip(mag).enumerate() {
            let tol = 2.0 * (k + 2) as f64 * u * s + 1e-30;
            assert!(
                (g as f64 - w).abs() <= tol,
                "{what}[{i}]: got {g}, want {w} (tol {tol:e})"
            );
        }
    }

    const SHAPES: &[(usize, usize, usize)] = &[
        (1, 1, 1),
        (1, 3, 5),
        (3, 1, 5),
        (5, 7, 1),
        (2, 0, 3),
        (197, 3, 5),
        (64, 65, 33),
        (197, 300, 70),
        (33, 768, 96),
    ];

    #[test]
    fn linear_matches_naive_with_and_without_bias() {
        let mut rng = Rng::new(1);
        for &(m, k, n) in SHAPES {
            let x = rng.vec(m * k);
            let w = rng.vec(n * k);
            let bias = rng.vec(n);
            for bias in [None, Some(&bias[..])] {
                let mut y = vec![f32::NAN; m * n];
                linear(&x, &w, bias, &mut y, m, k, n);
                let (want, mag) = naive(m, k, n, &x, k, 1, &w, 1, k, bias);
                check(
                    &y,
                    &want,
                    &mag,
                    k,
                    &format!("linear {m}x{k}x{n} bias={}", bias.is_some()),
                );
            }
        }
    }

    #[test]
    fn matmul_nt_and_nn_match_naive() {
        let mut rng = Rng::new(2);
        for &(m, k, n) in SHAPES {
            let a = rng.vec(m * k);
            let bt = rng.vec(n * k);
            let mut c = vec![f32::NAN; m * n];
            matmul_nt(&a, &bt, &mut c, m, k, n);
            let (want, mag) = naive(m, k, n, &a, k, 1, &bt, 1, k, None);
            check(&c, &want, &mag, k, &format!("nt {m}x{k}x{n}"));

            let b = rng.vec(k * n);
            let mut c = vec![f32::NAN; m * n];
            matmul_nn(&a, &b, &mut c, m, k, n);
            let (want, mag) = naive(m, k, n, &a, k, 1, &b, n, 1, None);
            check(&c, &want, &mag, k, &format!("nn {m}x{k}x{n}"));
        }
    }

    #[test]
    fn output_beyond_m_times_n_is_untouched() {
        let mut rng = Rng::new(3);
        let (m, k, n) = (3, 4, 5);
        let (x, w) = (rng.vec(m * k), rng.vec(n * k));
        let mut y = vec![7.0; m * n + 4];
        linear(&x, &w, None, &mut y, m, k, n);
        assert_eq!(&y[m * n..], &[7.0; 4]);
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let mut rng = Rng::new(4);
        for &(m, k, n) in &[
            (197, 300, 70),
            (400, 768, 97),
            (65, 1030, 48),
            (20, 384, 1536),
            (33, 768, 96),
            (1, 3072, 768),
        ] {
            let x = rng.vec(m * k);
            let w = rng.vec(n * k);
            let bias = rng.vec(n);
            let run = |threads: usize| {
                in_pool(threads, || {
                    let mut y = vec![0.0; m * n];
                    linear(&x, &w, Some(&bias), &mut y, m, k, n);
                    let mut c = vec![0.0; m * n];
                    matmul_nt(&x, &w, &mut c, m, k, n);
                    let mut d = vec![0.0; m * n];
                    matmul_nn(&x, &w, &mut d, m, k, n);
                    (y, c, d)
                })
            };
            let base = run(1);
            for threads in [2, 3] {
                let got = run(threads);
                assert!(
                    crate::kernels::testutil::same_bits(&base.0, &got.0)
                        && crate::kernels::testutil::same_bits(&base.1, &got.1)
                        && crate::kernels::testutil::same_bits(&base.2, &got.2),
                    "{m}x{k}x{n}: {threads} threads differ from 1"
                );
            }
        }
    }
}
