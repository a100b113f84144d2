//! `flame-bench attention`: GFLOP/s of multi-head attention on the shapes the models run.

use std::time::Instant;

use flame::kernels::{self, AttentionScratch};

/// (name, queries, keys, heads, head_dim, row stride of q/k/v, causal)
const SHAPES: [(&str, usize, usize, usize, usize, usize, bool); 5] = [
    // FLAME-base: 196 frames + 3 auxiliary tokens, 8 heads of 96, packed q|k|v rows.
    ("flame-base self 199", 199, 199, 8, 96, 3 * 768, false),
    // Its cross-attention: CLIP's 77 positions + 3 auxiliary rows of memory.
    ("flame-base cross 199x80", 199, 80, 8, 96, 2 * 768, false),
    ("flame-base self 395", 395, 395, 8, 96, 3 * 768, false),
    // MDM / Motion Flow Matching: 196 frames + the step token, 4 heads of 128.
    ("mdm self 197", 197, 197, 4, 128, 3 * 512, false),
    // A causal decoder's shape (OMG's ControlNet-free base runs non-causal; MLD's VAE is small).
    ("causal 199", 199, 199, 8, 96, 3 * 768, true),
];

pub fn attention_bench(threads: usize, runs: usize) {
    let pool = flame::pool::WorkerPool::new(threads).expect("pool");
    println!(
        "attention GFLOP/s (4·lq·lk·width per call), {threads} threads, {} kernel, median of {runs}:",
        kernels::kernel_name()
    );
    for (name, lq, lk, heads, hd, stride, causal) in SHAPES {
        let e = heads * hd;
        let rows = lq.max(lk);
        let data: Vec<f32> = (0..rows * stride)
            .map(|i| ((i * 7919) % 1000) as f32 * 2e-3 - 1.0)
            .collect();
        let (q, k, v) = (&data[..], &data[e..], &data[(stride - e).min(2 * e)..]);
        let mut out = vec![0f32; lq * e];
        let mut scratch = AttentionScratch::default();
        let mut call = || {
            scratch.attend(
                q, stride, k, stride, v, stride, lq, lk, heads, hd, None, causal, &mut out,
            )
        };
        let flop = (4 * lq * lk * e) as f64;
        let rate = pool.install(|| {
            call();
            let mut t: Vec<f64> = (0..runs)
                .map(|_| {
                    let s = Instant::now();
                    for _ in 0..10 {
                        call();
                    }
                    s.elapsed().as_secs_f64() / 10.0
                })
                .collect();
            t.sort_by(f64::total_cmp);
            flop / t[runs / 2] / 1e9
        });
        println!("  {name:<26} {rate:8.1}");
        println!("RESULT impl=attention shape=\"{name}\" gflops={rate:.1}");
    }
}
