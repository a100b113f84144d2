//! `flame-bench peak`: each compute path's own ceiling, from register-only loops of its product
//! instruction (twelve independent accumulators, no memory traffic), on one thread and on
//! `--threads` threads at once. The linear layers' GFLOP/s (`flame-bench gemm`) are read
//! against these.

use std::time::Instant;

/// Loop iterations per measurement (each runs 12 instructions).
const ITERS: usize = 20_000_000;

/// One path: its name, the operations (multiply and add counted apart) per instruction, and
/// its loop (`None` when this CPU lacks the instructions).
struct Path {
    name: &'static str,
    ops_per_instr: usize,
    run: Option<fn(usize) -> f32>,
}

#[cfg(target_arch = "x86_64")]
mod loops {
    use std::arch::x86_64::*;

    /// Sums the accumulators' lanes so that the loop's work is used.
    macro_rules! keep {
        ($acc:expr, $add:ident, $zero:expr) => {{
            let s = $acc.iter().fold($zero, |a, &b| $add(a, b));
            // SAFETY: any vector's bytes can be read as bytes.
            let bytes =
                std::slice::from_raw_parts(&s as *const _ as *const u8, std::mem::size_of_val(&s));
            bytes.iter().map(|&b| b as f32).sum()
        }};
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn fma256(n: usize) -> f32 {
        let (a, b) = (_mm256_set1_ps(1.000_001), _mm256_set1_ps(0.999_999));
        let mut acc = [_mm256_setzero_ps(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm256_fmadd_ps(a, b, *v);
            }
        }
        keep!(acc, _mm256_add_ps, _mm256_setzero_ps())
    }

    #[target_feature(enable = "avx512f")]
    pub unsafe fn fma512(n: usize) -> f32 {
        let (a, b) = (_mm512_set1_ps(1.000_001), _mm512_set1_ps(0.999_999));
        let mut acc = [_mm512_setzero_ps(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm512_fmadd_ps(a, b, *v);
            }
        }
        keep!(acc, _mm512_add_ps, _mm512_setzero_ps())
    }

    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn dpbf16(n: usize) -> f32 {
        let a: __m512bh = std::mem::transmute(_mm512_set1_epi32(0x3f80_3f80));
        let b: __m512bh = std::mem::transmute(_mm512_set1_epi32(0x3f00_3f00));
        let mut acc = [_mm512_setzero_ps(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm512_dpbf16_ps(*v, a, b);
            }
        }
        keep!(acc, _mm512_add_ps, _mm512_setzero_ps())
    }

    #[target_feature(enable = "avx512f,avx512vnni")]
    pub unsafe fn dpbusd(n: usize) -> f32 {
        let (a, b) = (_mm512_set1_epi8(3), _mm512_set1_epi8(-5));
        let mut acc = [_mm512_setzero_si512(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm512_dpbusd_epi32(*v, a, b);
            }
        }
        keep!(acc, _mm512_add_epi32, _mm512_setzero_si512())
    }

    /// `vpdpbusd` on 256 bits, VEX-encoded (AVX-VNNI).
    #[target_feature(enable = "avx2,avxvnni")]
    pub unsafe fn dpbusd256(n: usize) -> f32 {
        let (a, b) = (_mm256_set1_epi8(3), _mm256_set1_epi8(-5));
        let mut acc = [_mm256_setzero_si256(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm256_dpbusd_avx_epi32(*v, a, b);
            }
        }
        keep!(acc, _mm256_add_epi32, _mm256_setzero_si256())
    }

    /// `vpmaddubsw` + `vpmaddwd` + `vpaddd`, the AVX2 int8 step; each chain feeds its own
    /// accumulator back as the unsigned operand so nothing is loop-invariant.
    #[target_feature(enable = "avx2")]
    pub unsafe fn maddubs(n: usize) -> f32 {
        let (b, ones, one) = (
            _mm256_set1_epi8(-5),
            _mm256_set1_epi16(1),
            _mm256_set1_epi32(1),
        );
        let mut acc = [_mm256_setzero_si256(); 12];
        for _ in 0..n {
            for v in acc.iter_mut() {
                *v = _mm256_add_epi32(one, _mm256_madd_epi16(_mm256_maddubs_epi16(*v, b), ones));
            }
        }
        keep!(acc, _mm256_add_epi32, _mm256_setzero_si256())
    }
}

fn paths() -> Vec<Path> {
    #[cfg(target_arch = "x86_64")]
    {
        let has = |f: &str| match f {
            "avx2" => is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
            "avx512f" => is_x86_feature_detected!("avx512f"),
            "avx512bf16" => is_x86_feature_detected!("avx512bf16"),
            "avx512vnni" => is_x86_feature_detected!("avx512vnni"),
            "avxvnni" => is_x86_feature_detected!("avxvnni"),
            _ => false,
        };
        // SAFETY (each loop): called only when its features were detected just above.
        let path = |name, ops_per_instr, ok: bool, f: fn(usize) -> f32| Path {
            name,
            ops_per_instr,
            run: ok.then_some(f),
        };
        vec![
            path(
                "f32 FMA, 8 lanes (avx2 kernel)",
                16,
                has("avx2"),
                |n| unsafe { loops::fma256(n) },
            ),
            path(
                "f32 FMA, 16 lanes (avx512 kernel)",
                32,
                has("avx512f"),
                |n| unsafe { loops::fma512(n) },
            ),
            path(
                "vdpbf16ps (bf16-compute)",
                64,
                has("avx512f") && has("avx512bf16"),
                |n| unsafe { loops::dpbf16(n) },
            ),
            path(
                "vpdpbusd (int8, VNNI)",
                128,
                has("avx512f") && has("avx512vnni"),
                |n| unsafe { loops::dpbusd(n) },
            ),
            path(
                "vpdpbusd on 256 bits (int8, AVX-VNNI)",
                64,
                has("avx2") && has("avxvnni"),
                |n| unsafe { loops::dpbusd256(n) },
            ),
            path(
                "vpmaddubsw+vpmaddwd+vpaddd (int8, AVX2)",
                64,
                has("avx2"),
                |n| unsafe { loops::maddubs(n) },
            ),
        ]
    }
    #[cfg(not(target_arch = "x86_64"))]
    Vec::new()
}

/// GFLOP/s (GOP/s) of `threads` copies of `run` started together.
fn rate(run: fn(usize) -> f32, ops_per_instr: usize, threads: usize) -> f64 {
    let start = Instant::now();
    let sink: f32 = std::thread::scope(|s| {
        let hs: Vec<_> = (0..threads).map(|_| s.spawn(|| run(ITERS))).collect();
        hs.into_iter().map(|h| h.join().unwrap()).sum()
    });
    let secs = start.elapsed().as_secs_f64();
    std::hint::black_box(sink);
    (threads * ITERS * 12 * ops_per_instr) as f64 / secs / 1e9
}

pub fn peak_bench(threads: usize) {
    println!(
        "peak GFLOP/s (GOP/s for int8) of register-only loops, median of 3; 1 thread and {threads} at once:"
    );
    for p in paths() {
        let Some(run) = p.run else {
            println!("  {:<42} not supported by this CPU", p.name);
            continue;
        };
        let median = |t: usize| {
            let mut r: Vec<f64> = (0..3).map(|_| rate(run, p.ops_per_instr, t)).collect();
            r.sort_by(f64::total_cmp);
            r[1]
        };
        let one = median(1);
        let all = median(threads);
        println!("  {:<42} {one:8.1} {all:8.1}", p.name);
        println!(
            "RESULT impl=peak path=\"{}\" threads1={one:.1} threads{threads}={all:.1}",
            p.name
        );
    }
}
