//! Element-wise activations and softmax, in place.
//!
//! Large buffers are split across the current rayon pool; each element is computed
//! independently, so the split never changes the result.

use rayon::prelude::*;

use super::packed::Isa;

/// Buffers shorter than this run on the calling thread: a fork/join costs a few µs.
const PAR_MIN_LEN: usize = 1 << 15;
/// Elements per parallel task.
const PAR_CHUNK: usize = 1 << 13;

/// Applies `f` to every element, in parallel for large buffers, on the CPU's kernel path.
fn map_inplace(x: &mut [f32], f: impl Fn(f32) -> f32 + Sync + Copy) {
    let isa = super::packed::detected_isa();
    if x.len() < PAR_MIN_LEN || crate::kernels::threads() <= 1 {
        map_on(isa, x, f);
    } else {
        x.par_chunks_mut(PAR_CHUNK).for_each(|c| map_on(isa, c, f));
    }
}

/// `f` over a slice on the given kernel path (one the CPU runs): the same f32 operations 16
/// (AVX-512), 8 (AVX2) or 4 (SSE2) lanes wide. The crate targets baseline x86-64, so only code
/// under a `target_feature` gets the wider vectors. No FMA is enabled, so nothing is
/// contracted and every path gives the same bits (`pointwise_gives_the_same_bits_on_every_
/// kernel_path`). A function calling into a library (`f32::tanh`) stays scalar on every path.
#[inline(always)]
fn map_on(isa: Isa, x: &mut [f32], f: impl Fn(f32) -> f32 + Copy) {
    #[cfg(target_arch = "x86_64")]
    match isa {
        // SAFETY: the CPU has AVX-512F (the caller's path is one it runs).
        Isa::Avx512 => return unsafe { map_avx512(x, f) },
        // SAFETY: the CPU has AVX2 (likewise).
        Isa::Avx2 => return unsafe { map_avx2(x, f) },
        Isa::Portable => {}
    }
    let _ = isa;
    x.iter_mut().for_each(|v| *v = f(*v));
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
unsafe fn map_avx512(x: &mut [f32], f: impl Fn(f32) -> f32) {
    x.iter_mut().for_each(|v| *v = f(*v));
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn map_avx2(x: &mut [f32], f: impl Fn(f32) -> f32) {
    x.iter_mut().for_each(|v| *v = f(*v));
}

/// ReLU in place, `max(x, 0)`; NaN stays NaN, as in PyTorch (FLAME's and MDM's feed-forward
/// layers when `activation` is `relu`).
pub fn relu(x: &mut [f32]) {
    // Memory-bound: never worth a fork. A comparison (not `f32::max`) so NaN propagates as in
    // PyTorch; every element is stored so the loop vectorises into a select (a conditional
    // store compiles to a branch, mispredicted on half the elements of random-sign data).
    x.iter_mut()
        .for_each(|v| *v = if *v < 0.0 { 0.0 } else { *v });
}

/// Exact GELU, `x · Φ(x)` with the error function.
///
/// In f32 with `erf`: within 2e-7·(1 + |x|) of the true value (PyTorch's CPU GELU is up to
/// 1e-6 off on [-8, 8]). Vectorised 16 lanes wide it went from 15% to 6% of a FineMoGen step
/// (evaluated in f64, 4 lanes).
pub fn gelu_erf(x: &mut [f32]) {
    map_inplace(x, gelu_one);
}

#[inline(always)]
fn gelu_one(v: f32) -> f32 {
    0.5 * v * (1.0 + erf(v * std::f32::consts::FRAC_1_SQRT_2))
}

/// GELU's tanh approximation (PyTorch `approximate="tanh"`, DiT's MLP):
/// `0.5·x·(1 + tanh(u))` with `u = √(2/π)·(x + 0.044715·x³)`, computed as the equal
/// `x / (1 + e^(−2u))` in f32: within 1e-7·(1 + |x|) of the f64 formula (PyTorch's: 8e-8).
pub fn gelu_tanh(x: &mut [f32]) {
    map_inplace(x, gelu_tanh_one);
}

#[inline(always)]
fn gelu_tanh_one(v: f32) -> f32 {
    // √(2/π)
    const C: f32 = 0.797_884_560_802_865_4_f64 as f32;
    // e^(−2u) overflowing to +inf for very negative x gives x / inf = -0, the correct limit.
    v / (1.0 + exp_fast(-2.0 * C * (v + 0.044715 * v * v * v)))
}

/// CLIP's `x · sigmoid(1.702 x)`.
pub fn quick_gelu(x: &mut [f32]) {
    map_inplace(x, quick_gelu_one);
}

#[inline(always)]
fn quick_gelu_one(v: f32) -> f32 {
    // exp overflowing to +inf for very negative x gives x / inf = -0, the correct limit.
    v / (1.0 + exp_fast(-1.702 * v))
}

/// SiLU (swish) in place, `x · sigmoid(x)` = `x / (1 + e^(−x))` in f32 (the timestep MLPs of
/// MDM, MoLA and FineMoGen).
pub fn silu(x: &mut [f32]) {
    map_inplace(x, silu_one);
}

#[inline(always)]
fn silu_one(v: f32) -> f32 {
    v / (1.0 + exp_fast(-v))
}

/// `tanh` in place, with the standard library's `f32::tanh` (the BERT pooler's activation).
pub fn tanh(x: &mut [f32]) {
    map_inplace(x, f32::tanh);
}

/// Softmax over each row of `n` values.
///
/// A row whose entries are all `-inf` (nothing to attend to) becomes all zeros rather than
/// PyTorch's NaNs, matching how attention treats fully-masked rows.
pub fn softmax_rows(x: &mut [f32], n: usize) {
    if n == 0 {
        return;
    }
    assert_eq!(x.len() % n, 0, "softmax_rows: length not a multiple of n");
    if x.len() < PAR_MIN_LEN || crate::kernels::threads() <= 1 {
        x.chunks_exact_mut(n).for_each(|r| {
            softmax_row(r);
        });
    } else {
        let rows_per_task = PAR_CHUNK.div_ceil(n);
        x.par_chunks_mut(rows_per_task * n).for_each(|c| {
            c.chunks_exact_mut(n).for_each(|r| {
                softmax_row(r);
            })
        });
    }
}

/// Softmax of one row in place, max-subtracted so large scores cannot overflow. Returns false
/// (and zeros the row) when every entry is `-inf`.
///
/// With AVX2 (or AVX-512) the same arithmetic runs 8 (16) lanes wide instead of SSE2's 4: no
/// FMA is used, the maximum is exact in any order and the sum's lanes are fixed, so every path
/// gives the same bits.
pub(crate) fn softmax_row(row: &mut [f32]) -> bool {
    softmax_row_on(super::packed::detected_isa(), row)
}

/// [`softmax_row`] on the given kernel path (one the CPU runs).
pub(crate) fn softmax_row_on(isa: Isa, row: &mut [f32]) -> bool {
    #[cfg(target_arch = "x86_64")]
    match isa {
        // SAFETY: the CPU has AVX-512F (the caller's path is one it runs).
        Isa::Avx512 => return unsafe { softmax_row_avx512(row) },
        // SAFETY: the CPU has AVX2 (likewise).
        Isa::Avx2 => return unsafe { softmax_row_avx2(row) },
        Isa::Portable => {}
    }
    let _ = isa;
    softmax_row_any(row)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
unsafe fn softmax_row_avx512(row: &mut [f32]) -> bool {
    softmax_row_any(row)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn softmax_row_avx2(row: &mut [f32]) -> bool {
    softmax_row_any(row)
}

#[inline(always)]
fn softmax_row_any(row: &mut [f32]) -> bool {
    let max = max_lanes(row);
    if max == f32::NEG_INFINITY {
        row.fill(0.0);
        return false;
    }
    // -inf (masked) entries map to exactly 0.
    row.iter_mut().for_each(|v| *v = exp_fast(*v - max));
    let inv = 1.0 / sum_lanes(row);
    row.iter_mut().for_each(|v| *v *= inv);
    true
}

/// The largest non-NaN entry (`-inf` if none), over sixteen lanes: the maximum is exact, so
/// the lanes only let the compiler vectorise (a left-to-right `f32::max` fold is scalar).
#[inline(always)]
fn max_lanes(x: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 16];
    let chunks = x.chunks_exact(16);
    let tail = chunks
        .remainder()
        .iter()
        .fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m });
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a = if v > *a { v } else { *a };
        }
    }
    acc.iter().fold(tail, |m, &v| if v > m { v } else { m })
}

/// Sum over eight independent lanes: a fixed order (so still deterministic) that the compiler
/// can vectorise, unlike a strict left-to-right f32 sum.
#[inline(always)]
fn sum_lanes(x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let tail: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// `e^x` in f32 within 1 ulp, branch-free so loops over it vectorise (libm's `expf` is a call
/// per element and dominated softmax).
///
/// Cephes' range reduction `x = n·ln2 + r` (ln2 split so `n·LN2_HI` is exact) with its degree-7
/// polynomial for `e^r`, then `2^n` built directly in the exponent bits. Results below
/// `e^-87.3` (the smallest normal) are exactly 0, so `-inf` gives 0; above 88.37 (where `2^n`
/// would overflow the exponent field, true value > 2.4e38) it returns `+inf`; NaN stays NaN.
#[inline(always)]
pub(crate) fn exp_fast(x: f32) -> f32 {
    const LO: f32 = -87.3;
    const HI: f32 = 88.37;
    // Adding 1.5·2²³ rounds to an integer in the low mantissa bits; the +127 pre-biases it so
    // those bits shifted left by 23 are the exponent field of 2^n.
    const SHIFT: f32 = 12_582_912.0 + 127.0;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const P: [f32; 6] = [
        1.987_569_2e-4,
        1.398_199_9e-3,
        8.333_452e-3,
        4.166_579_6e-2,
        1.666_666_5e-1,
        0.5,
    ];
    let t = x * std::f32::consts::LOG2_E + SHIFT;
    let n = t - SHIFT;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = P[1..].iter().fold(P[0], |acc, &c| acc * r + c);
    let y = p * (r * r) + r + 1.0;
    let e = y * f32::from_bits(t.to_bits() << 23);
    if x < LO {
        0.0
    } else if x > HI {
        f32::INFINITY
    } else {
        e
    }
}

/// Error function in f32, max abs. error 4.2e-7 over the reals.
///
/// The odd rational fit on [-4, 4] that Eigen and XLA use for f32 erf (beyond ±4 erf is 1 to
/// within 1.6e-8). It needs no `exp` and has no branches (clamps lower to selects), so GELU
/// loops vectorise. (In f64 the same fit is 6.5e-8 off, but 4 lanes of f64 with a division
/// cost ~6× 16 lanes of f32.)
#[inline(always)]
pub(crate) fn erf(x: f32) -> f32 {
    // Eigen's coefficients, rounded once to f32 (as f64 literals, so no digit is dropped).
    const ALPHA: [f32; 7] = [
        -2.726_142_258_013_06e-10_f64 as f32,
        2.770_681_424_959_02e-8_f64 as f32,
        -2.101_024_020_825_08e-6_f64 as f32,
        -5.692_506_394_623_46e-5_f64 as f32,
        -7.349_906_303_268_55e-4_f64 as f32,
        -2.954_599_808_540_25e-3_f64 as f32,
        -1.609_603_332_624_15e-2_f64 as f32,
    ];
    const BETA: [f32; 5] = [
        -1.456_607_184_649_96e-5_f64 as f32,
        -2.133_740_552_789_05e-4_f64 as f32,
        -1.682_826_974_382_03e-3_f64 as f32,
        -7.373_329_167_204_68e-3_f64 as f32,
        -1.426_473_905_141_89e-2_f64 as f32,
    ];
    let t = x.clamp(-4.0, 4.0);
    let t2 = t * t;
    let p = ALPHA.iter().fold(0.0, |acc, &c| acc * t2 + c);
    let q = BETA.iter().fold(0.0, |acc, &c| acc * t2 + c);
    let r = (t * p / q).clamp(-1.0, 1.0);
    // Exactly ±1 outside the fit, so GELU's `x·(1+erf)` is exactly 0 for very negative x
    // instead of x times the fit's residual.
    if x.abs() >= 4.0 {
        1f32.copysign(x)
    } else {
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{in_pool, isas, same_bits, Rng};

    /// `f` on every kernel path against the plain loop. `f` is passed as its own function
    /// item (not a function pointer), so each path's copy inlines and vectorises it as the
    /// library's calls do.
    fn same_bits_on_every_path(name: &str, f: impl Fn(f32) -> f32 + Copy) {
        let mut rng = Rng::new(22);
        // Lengths around every vector width (4, 8, 16 lanes) and their tails; values over the
        // erf fit's whole range, past its ±4·√2 clamp, past exp's overflow, and the special
        // values.
        for n in [1, 3, 4, 5, 8, 15, 16, 17, 31, 33, 100, 1031] {
            let mut x: Vec<f32> = rng.vec(n).iter().map(|v| v * 12.0).collect();
            if n > 4 {
                x[0] = f32::INFINITY;
                x[1] = -200.0;
                x[2] = -0.0;
                x[n - 1] = 1e-30;
            }
            let want: Vec<f32> = x.iter().map(|&v| f(v)).collect();
            for isa in isas() {
                let mut got = x.clone();
                map_on(isa, &mut got, f);
                assert!(same_bits(&got, &want), "{name} {isa:?} n={n}");
            }
        }
    }

    #[test]
    fn pointwise_gives_the_same_bits_on_every_kernel_path() {
        same_bits_on_every_path("gelu", gelu_one);
        same_bits_on_every_path("gelu_tanh", gelu_tanh_one);
        same_bits_on_every_path("quick_gelu", quick_gelu_one);
        same_bits_on_every_path("silu", silu_one);
        same_bits_on_every_path("tanh", f32::tanh);
    }

    /// `f` on every `x` of `[-limit, limit]` in steps of 1e-3 is within `coef · (1 + |x|)` of
    /// `reference(x)` in f64.
    fn assert_sweep(
        name: &str,
        f: fn(&mut [f32]),
        limit: i32,
        reference: fn(f64) -> f64,
        coef: f64,
    ) {
        let xs: Vec<f32> = (-limit..=limit).map(|i| i as f32 * 1e-3).collect();
        let mut y = xs.clone();
        f(&mut y);
        for (&x, &g) in xs.iter().zip(&y) {
            let want = reference(x as f64);
            assert!(
                (g as f64 - want).abs() <= coef * (1.0 + x.abs() as f64),
                "{name}({x}) = {g}, want {want}"
            );
        }
    }

    #[test]
    fn gelu_tanh_sweep() {
        let reference = |x: f64| {
            let u = 0.797_884_560_802_865_4 * (x + 0.044715 * x * x * x);
            0.5 * x * (1.0 + u.tanh())
        };
        assert_sweep("gelu_tanh", gelu_tanh, 12_000, reference, 1e-7);
        let mut v = [-200.0f32, 0.0, 200.0];
        gelu_tanh(&mut v);
        assert_eq!(v, [0.0, 0.0, 200.0]);
    }

    #[test]
    fn softmax_gives_the_same_bits_on_every_kernel_path() {
        let mut rng = Rng::new(21);
        for n in [1, 2, 7, 15, 16, 17, 33, 80, 199, 256] {
            let mut row: Vec<f32> = rng.vec(n).iter().map(|x| x * 12.0).collect();
            // Masked entries, and a NaN-free row whose maximum sits in the tail.
            if n > 3 {
                row[1] = f32::NEG_INFINITY;
                row[n - 1] = 20.0;
            }
            let mut want = row.clone();
            assert!(softmax_row_any(&mut want));
            for isa in isas() {
                let mut got = row.clone();
                assert!(softmax_row_on(isa, &mut got));
                assert!(same_bits(&got, &want), "{isa:?} n={n}");
            }
            // Every entry masked: zeros and `false` on every path.
            for isa in isas() {
                let mut dead = vec![f32::NEG_INFINITY; n];
                assert!(!softmax_row_on(isa, &mut dead));
                assert!(dead.iter().all(|&x| x == 0.0), "{isa:?}");
            }
        }
        // An independent check of the values: e^x / Σ e^x in f64.
        let row = [0.5f32, -1.0, 3.0, 2.25, -7.0];
        let mut got = row;
        softmax_row(&mut got);
        let sum: f64 = row.iter().map(|&x| (x as f64).exp()).sum();
        for (g, &x) in got.iter().zip(&row) {
            assert!((*g as f64 - (x as f64).exp() / sum).abs() < 1e-7, "{g}");
        }
    }

    /// Slow reference erf good to ~1e-14: Maclaurin series below 2.5, erfc continued fraction
    /// above.
    fn erf_ref(x: f64) -> f64 {
        let a = x.abs();
        let r = if a < 2.5 {
            // erf(x) = 2/√π Σ (-1)^n x^(2n+1) / (n! (2n+1))
            let (mut term, mut sum, mut n) = (a, a, 0.0);
            while term.abs() > 1e-17 * sum.abs() {
                n += 1.0;
                term *= -a * a / n;
                sum += term / (2.0 * n + 1.0);
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc(x) = e^{-x²}/√π · 1/(x + (1/2)/(x + 1/(x + (3/2)/(x + ...)))), evaluated backward.
            let mut t = a;
            for n in (1..=300).rev() {
                t = a + (n as f64 / 2.0) / t;
            }
            1.0 - (-a * a).exp() / (std::f64::consts::PI.sqrt() * t)
        };
        r.copysign(x)
    }

    #[test]
    fn reference_erf_matches_table() {
        for (x, want) in [
            (0.1, 0.1124629160182849),
            (0.5, 0.5204998778130465),
            (1.0, 0.8427007929497149),
            (2.0, 0.9953222650189527),
            (3.0, 0.9999779095030014),
            (3.5, 0.9999992569016276),
            (4.0, 0.9999999845827421),
        ] {
            assert!((erf_ref(x) - want).abs() < 1e-13, "erf_ref({x})");
            assert!((erf_ref(-x) + want).abs() < 1e-13, "erf_ref(-{x})");
        }
    }

    #[test]
    fn erf_accuracy() {
        assert_eq!(erf(0.0), 0.0);
        assert_eq!(erf(10.0), 1.0);
        assert_eq!(erf(-10.0), -1.0);
        assert_eq!(erf(f32::INFINITY), 1.0);
        let mut worst = 0.0f64;
        for i in -60_000..=60_000 {
            let x = i as f32 * 1e-4;
            worst = worst.max((erf(x) as f64 - erf_ref(x as f64)).abs());
        }
        assert!(worst < 4.5e-7, "max erf error {worst:e}");
    }

    #[test]
    fn exp_fast_within_one_ulp() {
        let mut worst = 0.0f64;
        let mut check = |x: f32| {
            let (got, want) = (exp_fast(x) as f64, (x as f64).exp());
            if want >= f32::MIN_POSITIVE as f64 && want <= f32::MAX as f64 {
                let ulp = (want as f32).abs() * f32::EPSILON; // >= one ulp at `want`
                worst = worst.max((got - want).abs() / ulp as f64);
            }
        };
        for i in 0..=2_000_000 {
            check((-87.3 + i as f64 * (88.36 + 87.3) / 2e6) as f32);
            check(-1.0 + i as f32 * 1e-6);
        }
        assert!(worst <= 1.0, "exp_fast error {worst} ulp");
        assert_eq!(exp_fast(0.0), 1.0);
        assert_eq!(exp_fast(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_fast(-100.0), 0.0);
        assert_eq!(exp_fast(89.0), f32::INFINITY);
        assert_eq!(exp_fast(f32::INFINITY), f32::INFINITY);
        assert!(exp_fast(f32::NAN).is_nan());
    }

    fn gelu_ref(x: f64) -> f64 {
        0.5 * x * (1.0 + erf_ref(x / std::f64::consts::SQRT_2))
    }

    #[test]
    fn gelu_erf_known_points() {
        for (x, want) in [
            (0.0f32, 0.0f64),
            (1.0, 0.8413447460685429),
            (-1.0, -0.15865525393145707),
            (0.5, 0.34573123063700656),
            (2.0, 1.9544997361036416),
            (-3.0, -0.0040496940948902835),
            (5.0, 4.999998566742141),
            (-5.5, -1.0444259356238245e-07),
        ] {
            let mut v = [x];
            gelu_erf(&mut v);
            let tol = 2e-7 * (1.0 + x.abs() as f64);
            assert!(
                (v[0] as f64 - want).abs() <= tol,
                "gelu({x}) = {}, want {want}",
                v[0]
            );
        }
        let mut v = [-20.0f32, 20.0, -1e30, 1e30, f32::INFINITY];
        gelu_erf(&mut v);
        assert_eq!(v, [0.0, 20.0, 0.0, 1e30, f32::INFINITY]);
    }

    #[test]
    fn gelu_erf_sweep() {
        assert_sweep("gelu", gelu_erf, 8000, gelu_ref, 2e-7);
    }

    #[test]
    fn pointwise_known_points() {
        type Kernel = fn(&mut [f32]);
        let cases: [(Kernel, f32, f64); 14] = [
            (relu, 1.5, 1.5),
            (relu, -2.0, 0.0),
            (quick_gelu, 1.0, 0.8457957659328212),
            (quick_gelu, -1.0, -0.1542042340671787),
            (quick_gelu, 2.0, 1.9356586231442081),
            (quick_gelu, -4.0, -0.004414724139581062),
            (silu, 1.0, 0.7310585786300049),
            (silu, -1.0, -0.2689414213699951),
            (silu, 2.0, 1.7615941559557649),
            (silu, -4.0, -0.07194483984836623),
            (tanh, 1.0, 0.7615941559557649),
            (tanh, -1.0, -0.7615941559557649),
            (tanh, 2.0, 0.9640275800758169),
            (tanh, -4.0, -0.999329299739067),
        ];
        for (f, x, want) in cases {
            let mut v = [x];
            f(&mut v);
            assert!(
                (v[0] as f64 - want).abs() <= 2e-7 * want.abs().max(1e-2),
                "f({x}) = {}, want {want}",
                v[0]
            );
        }
        let mut v = [f32::NAN, -0.5, 0.5];
        relu(&mut v);
        assert!(v[0].is_nan() && v[1..] == [0.0, 0.5]);
        for f in [quick_gelu as fn(&mut [f32]), silu] {
            let mut v = [-200.0f32, 0.0, 200.0];
            f(&mut v);
            assert_eq!(v, [0.0, 0.0, 200.0]);
        }
    }

    #[test]
    fn softmax_rows_match_reference_and_sum_to_one() {
        let mut rng = Rng::new(5);
        for n in [1usize, 3, 5, 77, 200] {
            let rows = 7;
            let x: Vec<f32> = rng.vec(rows * n).iter().map(|v| v * 20.0).collect();
            let mut y = x.clone();
            softmax_rows(&mut y, n);
            for (xr, yr) in x.chunks(n).zip(y.chunks(n)) {
                let max = xr.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
                let e: Vec<f64> = xr.iter().map(|&v| (v as f64 - max).exp()).collect();
                let s: f64 = e.iter().sum();
                for (&g, &w) in yr.iter().zip(&e) {
                    assert!((g as f64 - w / s).abs() < 1e-6, "softmax n={n}");
                }
                let total: f64 = yr.iter().map(|&v| v as f64).sum();
                assert!((total - 1.0).abs() < 1e-5, "row sum {total}");
            }
        }
    }

    #[test]
    fn softmax_masked_and_extreme_rows() {
        let ninf = f32::NEG_INFINITY;
        let mut x = [1000.0, 1001.0, ninf, ninf, ninf, ninf, 0.0, ninf, 5.0];
        softmax_rows(&mut x, 3);
        let e = (-1.0f64).exp();
        assert!((x[0] as f64 - e / (1.0 + e)).abs() < 1e-7);
        assert!((x[1] as f64 - 1.0 / (1.0 + e)).abs() < 1e-7);
        assert_eq!(x[2..6], [0.0; 4]);
        assert_eq!(x[7], 0.0);
        assert!((x[6] as f64 - 1.0 / (1.0 + 5f64.exp())).abs() < 1e-7);
    }

    #[test]
    fn parallel_split_is_bit_identical() {
        let mut rng = Rng::new(6);
        let x: Vec<f32> = rng.vec(97 * 1031).iter().map(|v| v * 6.0).collect();
        let fs: [fn(&mut [f32]); 5] = [gelu_erf, quick_gelu, silu, tanh, |v| softmax_rows(v, 1031)];
        for f in fs {
            let run = |t| {
                in_pool(t, || {
                    let mut y = x[..97 * 1031].to_vec();
                    f(&mut y);
                    y
                })
            };
            let base = run(1);
            assert!(same_bits(&base, &run(2)) && same_bits(&base, &run(3)));
        }
    }
}
