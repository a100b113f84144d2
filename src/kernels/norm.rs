//! Layer normalisation.
//!
//! Row statistics are accumulated in f64 (two passes: mean, then squared deviations), so the
//! result does not degrade when a row's mean is large relative to its spread. Rows are split
//! across the current rayon pool for large inputs; each row is independent, so the split never
//! changes the result.

use rayon::prelude::*;

/// Inputs shorter than this run on the calling thread.
const PAR_MIN_LEN: usize = 1 << 15;
/// Approximate elements per parallel task.
const PAR_CHUNK: usize = 1 << 13;

/// Row-wise LayerNorm in place: each row of `dim` values is normalised (biased variance) and
/// scaled by `gamma`, shifted by `beta`.
pub fn layer_norm(x: &mut [f32], dim: usize, gamma: &[f32], beta: &[f32], eps: f32) {
    check(x.len(), dim, gamma, beta);
    for_rows(x, dim, |row, _| normalize_row(row, gamma, beta, eps));
}

/// `x = LayerNorm(x + residual)` row-wise (the post-LN residual step).
pub fn add_layer_norm(
    x: &mut [f32],
    residual: &[f32],
    dim: usize,
    gamma: &[f32],
    beta: &[f32],
    eps: f32,
) {
    check(x.len(), dim, gamma, beta);
    assert_eq!(residual.len(), x.len(), "add_layer_norm: residual length");
    for_rows(x, dim, |row, r| {
        let res = &residual[r * dim..(r + 1) * dim];
        row.iter_mut().zip(res).for_each(|(v, &s)| *v += s);
        normalize_row(row, gamma, beta, eps);
    });
}

fn check(len: usize, dim: usize, gamma: &[f32], beta: &[f32]) {
    assert!(dim > 0, "layer_norm: dim is 0");
    assert_eq!(len % dim, 0, "layer_norm: length not a multiple of dim");
    assert_eq!(gamma.len(), dim, "layer_norm: gamma length");
    assert_eq!(beta.len(), dim, "layer_norm: beta length");
}

/// Calls `f(row, row_index)` for every row, in parallel for large inputs.
fn for_rows(x: &mut [f32], dim: usize, f: impl Fn(&mut [f32], usize) + Sync) {
    if x.len() < PAR_MIN_LEN || crate::kernels::threads() <= 1 {
        x.chunks_exact_mut(dim)
            .enumerate()
            .for_each(|(r, row)| f(row, r));
    } else {
        let rows_per_task = PAR_CHUNK.div_ceil(dim);
        x.par_chunks_mut(rows_per_task * dim)
            .enumerate()
            .for_each(|(t, chunk)| {
                chunk
                    .chunks_exact_mut(dim)
                    .enumerate()
                    .for_each(|(r, row)| f(row, t * rows_per_task + r));
            });
    }
}

/// Sum in f64 over four independent lanes, which lets the compiler vectorise it.
fn sum_f64(row: &[f32], f: impl Fn(f64) -> f64) -> f64 {
    let mut acc = [0.0f64; 4];
    let chunks = row.chunks_exact(4);
    let tail: f64 = chunks.remainder().iter().map(|&v| f(v as f64)).sum();
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a += f(v as f64);
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

fn normalize_row(row: &mut [f32], gamma: &[f32], beta: &[f32], eps: f32) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has avx.
        unsafe {
            let (mean, rstd) = row_stats_avx(row, eps);
            scale_row_avx(row, gamma, beta, mean, rstd);
        }
        return;
    }
    let (mean, rstd) = row_stats(row, eps);
    scale_row(row, gamma, beta, mean, rstd);
}

/// `row = ((row − mean)·rstd)·gamma + beta`, the first product in f64.
#[inline(always)]
fn scale_row(row: &mut [f32], gamma: &[f32], beta: &[f32], mean: f64, rstd: f64) {
    for ((v, &g), &b) in row.iter_mut().zip(gamma).zip(beta) {
        *v = ((*v as f64 - mean) * rstd) as f32 * g + b;
    }
}

/// [`scale_row`] compiled for 256-bit vectors (each value on its own: the same bits).
///
/// # Safety
/// The CPU supports avx.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn scale_row_avx(row: &mut [f32], gamma: &[f32], beta: &[f32], mean: f64, rstd: f64) {
    scale_row(row, gamma, beta, mean, rstd);
}

/// The row's mean and `1/sqrt(var + eps)` (biased variance), in f64.
fn row_stats(row: &[f32], eps: f32) -> (f64, f64) {
    let n = row.len() as f64;
    let mean = sum_f64(row, |v| v) / n;
    let var = sum_f64(row, |v| (v - mean) * (v - mean)) / n;
    (mean, 1.0 / (var + eps as f64).sqrt())
}

/// [`row_stats`] on 256-bit vectors: the same four f64 lanes (lane `j` sums the values at
/// `4i + j` in order) and the same final association, so the same bits. Left to the compiler,
/// the sums stayed on 128-bit halves with shuffles (LayerNorm was 3% of a Motion Flow
/// Matching step).
///
/// # Safety
/// The CPU supports avx.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn row_stats_avx(row: &[f32], eps: f32) -> (f64, f64) {
    use std::arch::x86_64::*;
    let main = row.len() - row.len() % 4;
    let n = row.len() as f64;
    let reduce = |acc: __m256d, tail: f64| {
        let mut lanes = [0.0f64; 4];
        // SAFETY: four f64 into a four-f64 array.
        unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), acc) };
        (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]) + tail
    };
    // SAFETY: i + 4 ≤ main ≤ row.len().
    let widen = |i: usize| unsafe { _mm256_cvtps_pd(_mm_loadu_ps(row.as_ptr().add(i))) };
    let mut acc = _mm256_setzero_pd();
    for i in (0..main).step_by(4) {
        acc = _mm256_add_pd(acc, widen(i));
    }
    let mean = reduce(acc, row[main..].iter().map(|&v| v as f64).sum()) / n;
    let m = _mm256_set1_pd(mean);
    let mut acc = _mm256_setzero_pd();
    for i in (0..main).step_by(4) {
        let d = _mm256_sub_pd(widen(i), m);
        acc = _mm256_add_pd(acc, _mm256_mul_pd(d, d));
    }
    let tail = row[main..]
        .iter()
        .map(|&v| (v as f64 - mean) * (v as f64 - mean))
        .sum();
    let var = reduce(acc, tail) / n;
    (mean, 1.0 / (var + eps as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, same_bits, Rng};

    fn ln_ref(x: &[f32], dim: usize, gamma: &[f32], beta: &[f32], eps: f32) -> Vec<f64> {
        let mut out = Vec::with_capacity(x.len());
        for row in x.chunks(dim) {
            let mean = row.iter().map(|&v| v as f64).sum::<f64>() / dim as f64;
            let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / dim as f64;
            let rstd = 1.0 / (var + eps as f64).sqrt();
            for (j, &v) in row.iter().enumerate() {
                out.push((v as f64 - mean) * rstd * gamma[j] as f64 + beta[j] as f64);
            }
        }
        out
    }

    fn assert_close(got: &[f32], want: &[f64], what: &str) {
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g as f64 - w).abs() <= 1e-5 * w.abs().max(1.0),
                "{what}[{i}]: {g} vs {w}"
            );
        }
    }

    #[test]
    fn layer_norm_matches_reference() {
        let mut rng = Rng::new(7);
        for (rows, dim, offset) in [
            (1, 1, 0.0),
            (3, 3, 0.0),
            (5, 7, 2.0),
            (197, 768, 0.0),
            (4, 512, 1000.0),
        ] {
            let x: Vec<f32> = rng
                .vec(rows * dim)
                .iter()
                .map(|v| v * 3.0 + offset)
                .collect();
            let gamma: Vec<f32> = rng.vec(dim).iter().map(|v| 1.0 + v).collect();
            let beta = rng.vec(dim);
            let mut y = x.clone();
            layer_norm(&mut y, dim, &gamma, &beta, 1e-5);
            assert_close(
                &y,
                &ln_ref(&x, dim, &gamma, &beta, 1e-5),
                &format!("ln {rows}x{dim}+{offset}"),
            );
        }
    }

    #[test]
    fn constant_row_gives_beta() {
        // Zero variance: eps inside the sqrt keeps it finite and the normalised value is 0.
        let mut x = vec![4.25f32; 6];
        layer_norm(&mut x, 3, &[2.0, 3.0, 4.0], &[0.5, -1.0, 0.0], 1e-5);
        assert_eq!(x, [0.5, -1.0, 0.0, 0.5, -1.0, 0.0]);
    }

    #[test]
    fn eps_is_inside_sqrt() {
        // Row [-1, 1]: biased var 1, so y = ±1/sqrt(1 + eps).
        let mut x = [-1.0f32, 1.0];
        layer_norm(&mut x, 2, &[1.0, 1.0], &[0.0, 0.0], 0.5);
        let want = 1.0 / 1.5f64.sqrt();
        assert!((x[1] as f64 - want).abs() < 1e-7 && (x[0] as f64 + want).abs() < 1e-7);
    }

    #[test]
    fn add_layer_norm_matches_reference() {
        let mut rng = Rng::new(8);
        for (rows, dim) in [(1, 5), (197, 768), (3, 1)] {
            let x = rng.vec(rows * dim);
            let r = rng.vec(rows * dim);
            let gamma = rng.vec(dim);
            let beta = rng.vec(dim);
            let sum: Vec<f32> = x.iter().zip(&r).map(|(a, b)| a + b).collect();
            let mut y = x.clone();
            add_layer_norm(&mut y, &r, dim, &gamma, &beta, 1e-6);
            assert_close(
                &y,
                &ln_ref(&sum, dim, &gamma, &beta, 1e-6),
                &format!("add_ln {rows}x{dim}"),
            );
        }
    }

    #[test]
    fn bit_identical_across_thread_counts() {
        let mut rng = Rng::new(9);
        let (rows, dim) = (301, 768);
        let x = rng.vec(rows * dim);
        let r = rng.vec(rows * dim);
        let gamma = rng.vec(dim);
        let beta = rng.vec(dim);
        let run = |t| {
            in_pool(t, || {
                let mut y = x.clone();
                add_layer_norm(&mut y, &r, dim, &gamma, &beta, 1e-5);
                layer_norm(&mut y, dim, &gamma, &beta, 1e-5);
                y
            })
        };
        let base = run(1);
        assert!(same_bits(&base, &run(2)) && same_bits(&base, &run(3)));
    }

    #[test]
    fn avx_row_statistics_are_the_same_bits_as_the_portable_ones() {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            let mut rng = Rng::new(10);
            // Lengths with and without a tail of 1 to 3; magnitudes from 2^-20 to 2^20, so the
            // f64 sums round and any other order of additions gives other bits.
            for dim in [1, 3, 4, 7, 512, 515, 768] {
                for _ in 0..20 {
                    let x: Vec<f32> = rng
                        .vec(dim)
                        .iter()
                        .zip(rng.vec(dim))
                        .map(|(v, e)| v * (e * 20.0).exp2() + 3.0)
                        .collect();
                    let want = row_stats(&x, 1e-5);
                    // SAFETY: the CPU has avx.
                    let got = unsafe { row_stats_avx(&x, 1e-5) };
                    assert_eq!(
                        (want.0.to_bits(), want.1.to_bits()),
                        (got.0.to_bits(), got.1.to_bits()),
                        "dim {dim}"
                    );
                }
            }
            return;
        }
        eprintln!("skipped: this CPU has no avx");
    }
}
