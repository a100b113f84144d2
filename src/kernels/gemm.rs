//! GEMM wrappers over `matrixmultiply::sgemm`, split by output rows across the current rayon pool.
//!
//! Every output element is produced by one sgemm call whose k-blocking does not depend on how
//! many rows that call covers, so any row split gives the same bits as a single call.

use rayon::prelude::*;

/// Row granularity of a parallel chunk: a multiple of every sgemm micro-kernel height (8 or 16)
/// so only the last chunk ends in a partial panel.
const ROW_BLOCK: usize = 32;

/// Below this many multiply-adds (m·k·n) the fork/join and the extra packing of `b` cost more
/// than a second core saves.
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
    let c = &mut c[..m * n];

    // One chunk of output rows starting at `row0`; `c` holds exactly those rows.
    let run = |row0: usize, c: &mut [f32]| {
        let rows = c.len() / n;
        let beta = match bias {
            Some(bias) => {
                for row in c.chunks_exact_mut(n) {
                    row.copy_from_slice(&bias[..n]);
                }
                1.0
            }
            None => 0.0,
        };
        let a = &a[row0 * rsa..];
        // SAFETY: `a[row0..row0+rows]`, `b` and `c` were bounds-checked above for the full
        // extent the strides reach; sgemm reads only those elements and writes only `c`.
        unsafe {
            matrixmultiply::sgemm(
                rows,
                k,
                n,
                1.0,
                a.as_ptr(),
                rsa as isize,
                csa as isize,
                b.as_ptr(),
                rsb as isize,
                csb as isize,
                beta,
                c.as_mut_ptr(),
                n as isize,
                1,
            );
        }
    };

    let threads = rayon::current_num_threads();
    if threads <= 1 || m < 2 * ROW_BLOCK || m.saturating_mul(k).saturating_mul(n) < PAR_MIN_MACS {
        run(0, c);
        return;
    }
    // One chunk per thread: every sgemm call packs all of `b`, so more chunks only repeat work.
    let tasks = threads.min(m.div_ceil(ROW_BLOCK));
    let rows_per_task = m.div_ceil(tasks).next_multiple_of(ROW_BLOCK);
    c.par_chunks_mut(rows_per_task * n)
        .enumerate()
        .for_each(|(i, chunk)| run(i * rows_per_task, chunk));
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
        for &(m, k, n) in &[(197, 300, 70), (400, 768, 97), (65, 1030, 48)] {
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
