//! `flame-bench`: times text encoding, one guided denoising step and a whole generation on a
//! model file, and prints medians over several runs.
//!
//! `flame-bench --model M [--frames 49,98,196,392] [--steps 10] [--sampler S (default: the model's)] [--threads 2]
//!  [--runs 5] [--weights f32|f16|bf16|bf16-compute|int8]` also prints GFLOP/s of a step (linear layers and
//! attention counted from the configuration) and the peak resident memory (VmHWM), and one
//! `RESULT` line per frame count for tools/bench.sh. For a latent model (MoLA, MLD, MotionLCM)
//! the whole generation also decodes the final latent through the family's VAE decoder, and that
//! decode is timed on its own as well (`decode_ms`). A step is what the session runs: the
//! conditional and unconditional rows as one batch of two for classifier-free guidance, one row
//! for MotionLCM (its guidance scale is embedded; `--guidance` does not change its time).
//!
//! `--targets` adds the cost of position targets: the same steps with a pelvis path on every
//! frame, interleaved run by run with the plain ones.
//!
//! `flame-bench gemm [--threads 2] [--weights f32]`: GFLOP/s of the packed linear kernel and the
//! matrixmultiply path on FLAME-base's shapes and a square problem (the machine's practical peak).
//!
//! `flame-bench attention [--threads 2] [--runs 7]`: GFLOP/s of multi-head attention on
//! FLAME-base's and MDM's shapes.
//!
//! `flame-bench peak [--threads 2]`: each compute path's ceiling on this CPU (f32 FMA on 8 and
//! 16 lanes, `vdpbf16ps`, `vpdpbusd`, AVX2's int8 step), from register-only loops.
//!
//! `flame-bench cancel (--model M | --random-base) [--frames 196] [--threads 2] [--trials 15]
//!  [--guidance 2.5] [--sampler S]`: cancel latency. A worker thread runs one step while the
//! main thread raises the session's cancel flag at a spread of fractions of the full step time;
//! prints the time from raising the flag to the step returning (median, max) next to the full
//! step. `--random-base` builds FLAME-base's denoiser (8 × 768, 8 heads, feed-forward 2048) with
//! random weights in memory, with the tiny test fixture's text encoder (the step's cost is the
//! denoiser's).
//!
//! `flame-bench retarget --rig FILE [--frames 200] [--runs 7]`: microseconds per frame of
//! carrying a pose onto a user's rig (see `flame_bench/retarget.rs`).
//!
//! `flame-bench robot [--urdf FILE] [--link NAME] [--calls 20000] [--runs 7]`: microseconds per
//! call of a robot's forward kinematics and of forward plus one Jacobian (see
//! `flame_bench/robot.rs`).
//!
//! `flame-bench robot-retarget --urdf FILE --config FILE --model M [--frames 120] [--dir D]
//! [--runs 1]`: frames per second of retargeting the demo model's motions onto a robot, one
//! thread; writes the human frames and trajectories tools/robot_bench.py compares with mink's
//! (see `flame_bench/robot_retarget.rs`).
//!
//! `flame-bench stream --model M [--chunk N (default: the model's default frames)] [--overlap 20]
//!  [--steps S (default: the model's)] [--threads 2] [--runs 5] [--seconds 30]
//!  [--segment-seconds T (default: one chunk's new frames)] [--weights W]`: a [`flame::stream::Stream`]'s
//! latency and steady-state cost.
//! Latency: per run a fresh stream (seed = run index), the time from just before `push` of
//! the first segment to 20 frames ready, pumping one step at a time. The first chunk has nothing
//! to keep, so no frame is ready before the whole first chunk (`--chunk` frames) is done: the
//! latency is a whole chunk's generation (prompt encoding and every step). `StreamParams` has no
//! separate first-chunk size; the same is also measured with the first segment split into 20
//! frames and the rest (same prompt), which makes the first chunk 20 frames long (a timeline
//! workaround; a model may make poorer motion at that length). Steady state: `--seconds` of
//! motion (the model's fps) pushed as segments cycling through four prompts, lookahead = all
//! of it, pumped to the end; the time after the first chunk over the frames generated after it
//! gives the cost per generated second of motion and the real-time factor (seconds of motion
//! per wall second). A chunk never spans two segments, so a segment's last chunk may be short:
//! by default every segment is one chunk's new frames (`chunk − overlap`), so every chunk after
//! the first is full; `--segment-seconds` sets another length (e.g. 6 s on a 120-frame chunk
//! with overlap 20: chunks of 100 and 20 new frames in turn). Medians over the runs; one
//! `RESULT` line.

use std::sync::Arc;
use std::time::Instant;

use flame::config::TextConfig;
use flame::kernels::{self, linear_packed, Activation, PackedWeights, WeightType};
use flame::models::mld::MldConfig;
use flame::models::{
    FinemogenFamily, FlameConfig, MdmConfig, MldFamily, MolaFamily, MotionLcmFamily, OmgFamily,
};
use flame::models::{LoadOptions, Model, Workspace};
use flame::session::{Sampler, Session, SessionParams};
use flame::stream::{Segment, Stream, StreamParams};

#[path = "flame_bench/attention.rs"]
mod attention;
#[path = "flame_bench/peak.rs"]
mod peak;
#[path = "flame_bench/retarget.rs"]
mod retarget;
#[path = "flame_bench/robot.rs"]
mod robot;
#[path = "flame_bench/robot_retarget.rs"]
mod robot_retarget;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn arg<T: std::str::FromStr>(args: &[String], key: &str, default: T) -> T {
    match args.iter().position(|a| a == key) {
        Some(i) => args
            .get(i + 1)
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{key} needs a valid value")),
        None => default,
    }
}

/// GFLOP/s of the packed linear kernel and the older matrixmultiply path on the shapes
/// FLAME-base (M = 2 × (196 + 3) rows) and MDM (M = 2 × (196 + 1)) run at 196 frames, plus a
/// large square problem as the peak.
fn gemm_bench(args: &[String]) {
    let threads: usize = arg(args, "--threads", 2);
    let runs: usize = arg(args, "--runs", 7);
    let ty: WeightType = arg(args, "--weights", WeightType::F32);
    let pool = flame::pool::WorkerPool::new(threads).expect("pool");
    let m = 2 * (196 + 3);
    let shapes = [
        ("attn qkv", m, 768, 2304),
        ("attn q/out", m, 768, 768),
        ("ffn up", m, 768, 2048),
        ("ffn down", m, 2048, 768),
        ("mdm qkv", 394, 512, 1536),
        ("mdm out", 394, 512, 512),
        ("mdm ffn up", 394, 512, 1024),
        ("mdm ffn down", 394, 1024, 512),
        // MoLA at 200 frames: 2 × (51 latent rows + 1 token).
        ("mola qkv", 104, 512, 1536),
        ("mola ffn in", 104, 512, 4096),
        ("mola ffn out", 104, 2048, 512),
        ("text 20x768x3072", 20, 768, 3072),
        ("square 1536", 1536, 1536, 1536),
    ];
    println!(
        "linear GFLOP/s, {threads} threads, {ty:?} weights, {} kernel (f32 tile {}), median of {runs}:",
        kernels::kernel_name(),
        kernels::f32_tile()
    );
    println!(
        "  {:<18} {:>16} {:>10} {:>10} {:>10}",
        "shape", "MxKxN", "packed", "cold", "sgemm"
    );
    // `--only NAME` runs one shape (e.g. under `perf stat`).
    let only: String = arg(args, "--only", String::new());
    for (name, m, k, n) in shapes {
        if !only.is_empty() && name != only {
            continue;
        }
        let x: Vec<f32> = (0..m * k)
            .map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.5)
            .collect();
        let w: Vec<f32> = (0..n * k)
            .map(|i| ((i * 104729) % 997) as f32 * 1e-3 - 0.5)
            .collect();
        let b = vec![0.1f32; n];
        let mut y = vec![0.0f32; m * n];
        let packed = PackedWeights::pack(&w, n, k, ty);
        let flops = 2.0 * (m * k * n) as f64;
        let time = |f: &mut dyn FnMut()| {
            f();
            let v = (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    f();
                    t.elapsed().as_secs_f64()
                })
                .collect();
            flops / median(v) / 1e9
        };
        let p = pool.install(|| {
            time(&mut || linear_packed(&x, &packed, Some(&b), Activation::None, &mut y, m))
        });
        // As in a model, where each layer's weights were last used a whole step ago: cycle
        // through copies that together exceed the last-level cache.
        let copies: Vec<PackedWeights> = (0..(64 << 20) / (n * k * 4).max(1) + 2)
            .map(|_| PackedWeights::pack(&w, n, k, ty))
            .collect();
        let mut next = 0;
        let cold = pool.install(|| {
            time(&mut || {
                next = (next + 1) % copies.len();
                linear_packed(&x, &copies[next], Some(&b), Activation::None, &mut y, m)
            })
        });
        let s = pool.install(|| time(&mut || kernels::linear(&x, &w, Some(&b), &mut y, m, k, n)));
        println!(
            "  {name:<18} {:>16} {p:>10.1} {cold:>10.1} {s:>10.1}",
            format!("{m}x{k}x{n}")
        );
    }
}

/// Multiply-adds of MLD's skip transformer on `b` rows of `s` tokens each (latent tokens, time,
/// text): the layers' in/out projections and feed-forward, the skip joins (2D -> D), and the
/// attention products.
fn mld_stack_macs(d: &MldConfig, b: f64) -> (f64, f64) {
    let (e, ff) = (d.latent_dim as f64, d.ff_size as f64);
    // The latent tokens, then the time and the text tokens.
    let s = d.latent_tokens as f64 + 2.0;
    let r = b * s;
    let joins = (d.layers / 2) as f64;
    let lin = d.layers as f64 * r * e * (4.0 * e + 2.0 * ff) + joins * r * 2.0 * e * e;
    let attn = d.layers as f64 * b * 2.0 * s * s * e;
    (lin, attn)
}

/// Multiply-adds of one guided step in linear layers and in attention, from the configuration:
/// batch 2 (conditional and unconditional rows), except MotionLCM's one pass per step with the
/// guidance embedded.
fn step_macs(model: &Model, frames: usize) -> (f64, f64) {
    let b = 2.0;
    let f = frames as f64;
    let any = model.config().denoiser.as_any();
    if let Some(d) = any.downcast_ref::<FlameConfig>() {
        {
            let (c, ff, dm) = (
                d.model_channels as f64,
                d.dim_feedforward as f64,
                d.motion_dim as f64,
            );
            let text = match &model.config().text_encoder {
                TextConfig::Bert(t) => t.max_length as f64,
                TextConfig::Clip(_) | TextConfig::T5(_) => 0.0,
            };
            let (s, mem) = (f + 3.0, text + 3.0);
            let r = b * s;
            // qkv, self out, cross q, cross out, ffn; cross k/v of the 2 per-step memory rows.
            let layer = r * c * (3.0 * c + c + c + c + 2.0 * ff) + 2.0 * c * 2.0 * c;
            let lin = d.num_layers as f64 * layer + b * f * (dm * c + c * 2.0 * dm);
            let attn = d.num_layers as f64 * b * 2.0 * (s * s + s * mem) * c;
            (lin, attn)
        }
    } else if let Some(d) = any.downcast_ref::<MdmConfig>() {
        {
            let (c, ff, nj) = (d.latent_dim as f64, d.ff_size as f64, d.njoints as f64);
            let s = f + 1.0;
            let r = b * s;
            let layer = r * c * (4.0 * c + 2.0 * ff);
            let lin = d.layers as f64 * layer + b * f * 2.0 * nj * c;
            let attn = d.layers as f64 * b * 2.0 * s * s * c;
            (lin, attn)
        }
    } else if let Some(m) = any.downcast_ref::<MolaFamily>() {
        let d = &m.denoiser;
        let (e, ff, c) = (
            d.embed_dim as f64,
            d.ff_dim as f64,
            d.latent_channels as f64,
        );
        // Four frames per latent row, the global token in front
        // (docs/official/mola-mld.md#mola-denoiser).
        let s = ((frames + 4) / 4) as f64 + 1.0;
        let r = b * s;
        // qkv, out, SwiGLU in (value + gate rows) and out.
        let layer = r * e * (3.0 * e + e + 2.0 * ff + ff);
        let lin = d.depth as f64 * layer + b * (s - 1.0) * (2.0 * c * c + 2.0 * c * e);
        let attn = d.depth as f64 * b * 2.0 * s * s * e;
        (lin, attn)
    } else if let Some(m) = any.downcast_ref::<MldFamily>() {
        mld_stack_macs(&m.denoiser, b)
    } else if let Some(m) = any.downcast_ref::<MotionLcmFamily>() {
        // MLD's network, one row: the guidance is embedded (no unconditional pass).
        let d = &m.denoiser;
        let (lin, attn) = mld_stack_macs(&d.mld, 1.0);
        let (e, c, t) = (
            d.mld.latent_dim as f64,
            d.latent_channels as f64,
            d.mld.text_dim as f64,
        );
        // The time token (cond_proj, linear_1, linear_2) and the text token (emb_proj).
        let tokens = d.cond_dim as f64 * t + t * e + e * e + t * e;
        // v2's latent_pre (C -> D) and latent_post (D -> C) on every latent token.
        let proj = if d.latent_channels != d.mld.latent_dim {
            d.mld.latent_tokens as f64 * 2.0 * c * e
        } else {
            0.0
        };
        (lin + tokens + proj, attn)
    } else if let Some(m) = any.downcast_ref::<FinemogenFamily>() {
        let d = &m.denoiser;
        let (p, ffn, te) = (d.part_dim as f64, d.ffn_dim as f64, d.time_embed_dim as f64);
        let (l, tokens, rows) = (8.0 * p, b * f * 8.0, b * f);
        // One prompt: the text MoE runs once per prompt, not per step. Mixtures counted as if
        // no choice were dropped.
        let moe = tokens
            * (p * d.gate_dim as f64
                + d.gate_dim as f64 * d.num_experts as f64
                + d.topk as f64 * 2.0 * p * d.motion_expert_hidden as f64
                + p * 3.0 * p);
        let templates = b * 8.0 * p * (5.0 * p * ffn + 4.0 * ffn * p + ffn);
        let styl = 2.0 * (rows * l * l + te * 2.0 * l);
        let sffn = tokens * 2.0 * p * ffn;
        let lin = d.num_layers as f64 * (moe + templates + styl + sffn) + rows * 2.0 * 526.0 * p;
        // The templates (key softmax · values) and the per-frame read-back: attention-like.
        let attn =
            d.num_layers as f64 * b * 8.0 * ((d.max_text_len as f64 + f) * p * p + f * p * 4.0 * p);
        (lin, attn)
    } else if let Some(m) = any.downcast_ref::<OmgFamily>() {
        let d = &m.denoiser;
        let (e, ff) = (d.d_model as f64, d.ff_size as f64);
        // Two rows through the backbone (D_c's and D_u's), one through the ControlNet copies;
        // the MoC with a 16-token prompt (its experts run per token on every frame).
        let block = f * e * (4.0 * e + 2.0 * ff);
        let mut lin = d.layers as f64 * b * block + b * f * 2.0 * e * d.input_feats as f64;
        let mut attn = d.layers as f64 * b * 2.0 * f * f * e;
        if let Some(c) = &d.control {
            let (dm, eh, k, n) = (
                c.control_dim as f64,
                c.expert_hidden as f64,
                c.conv_kernel as f64,
                16.0,
            );
            let moc = f * (dm * dm + n * 2.0 * dm * eh) + 2.0 * f * k * e * dm;
            lin += d.layers as f64 * (block + moc);
            attn += d.layers as f64 * 2.0 * f * n * dm;
        }
        (lin, attn)
    } else {
        // A family this count does not know: no GFLOP/s figures.
        (0.0, 0.0)
    }
}

/// A `/proc/self/status` field in MiB (Linux; 0 elsewhere).
fn status_mib(key: &str) -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix(key))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// `--targets`: the cost of position targets (the pelvis on a straight path on every frame,
/// the session's target defaults) next to the same steps without them, interleaved run by run.
fn target_bench(model: &Model, session: &mut Session, runs: usize) {
    let format = model.motion_format();
    let joints = format.skeleton().joint_count();
    let frames = session.frames();
    let mut values = vec![f32::NAN; frames * joints * 3];
    for f in 0..frames {
        values[f * joints * 3..f * joints * 3 + 3].copy_from_slice(&[0.05 * f as f32, 0.9, 0.0]);
    }
    let (mut plain, mut guided) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        for with_targets in [false, true] {
            session.clear_position_targets();
            if with_targets {
                session
                    .set_position_target_values(&values, None, flame::motion::Convention::Native)
                    .expect("targets");
            }
            session.reset();
            while session.steps_left() > 0 {
                let t = Instant::now();
                session.step().expect("step");
                let ms = t.elapsed().as_secs_f64() * 1e3;
                if with_targets {
                    guided.push(ms)
                } else {
                    plain.push(ms)
                }
            }
        }
    }
    session.clear_position_targets();
    let (p, g) = (median(plain), median(guided));
    println!(
        "  step with targets  {g:9.2} ms  (pelvis path on every frame, {} schedule; without: {p:.2} ms, x{:.2})",
        session.target_params().schedule.name(),
        g / p
    );
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("gemm") {
        gemm_bench(&args);
        return;
    }
    if args.first().map(String::as_str) == Some("cancel") {
        cancel_bench(&args);
        return;
    }
    if args.first().map(String::as_str) == Some("attention") {
        attention::attention_bench(arg(&args, "--threads", 2), arg(&args, "--runs", 7));
        return;
    }
    if args.first().map(String::as_str) == Some("peak") {
        peak::peak_bench(arg(&args, "--threads", 2));
        return;
    }
    if args.first().map(String::as_str) == Some("stream") {
        stream_bench(&args);
        return;
    }
    if args.first().map(String::as_str) == Some("retarget") {
        retarget::retarget_bench(&args);
        return;
    }
    if args.first().map(String::as_str) == Some("robot") {
        robot::robot_bench(&args);
        return;
    }
    if args.first().map(String::as_str) == Some("robot-retarget") {
        robot_retarget::robot_retarget_bench(&args);
        return;
    }
    let path: String = arg(&args, "--model", String::new());
    if path.is_empty() {
        eprintln!(
            "usage: flame-bench --model M [--frames 49,98,196,392] [--steps 10] [--sampler S (default: the model's)] \
             [--threads 2] [--runs 5] [--weights f32|f16|bf16|bf16-compute|int8]\n       flame-bench gemm [--threads 2] [--weights f32] [--only SHAPE]\n       \
             flame-bench peak [--threads 2]\n       \
             flame-bench cancel (--model M | --random-base) [--frames 196] [--threads 2] [--trials 15]\n       \
             flame-bench stream --model M [--chunk N] [--overlap 20] [--steps S] [--threads 2] [--runs 5] \
             [--seconds 30] [--segment-seconds T]\n       \
             flame-bench retarget --rig FILE [--rig FILE ...] [--frames 200] [--runs 7]"
        );
        std::process::exit(2);
    }
    let frames_list: String = arg(&args, "--frames", "196".to_string());
    let steps: usize = arg(&args, "--steps", 10);
    let threads: usize = arg(&args, "--threads", 2);
    let runs: usize = arg(&args, "--runs", 5);
    // The model's own sampler unless asked (DDIM for diffusion, Euler for flow matching).
    let sampler: Option<Sampler> = args
        .iter()
        .any(|a| a == "--sampler")
        .then(|| arg(&args, "--sampler", Sampler::Ddim));
    let weights: WeightType = arg(&args, "--weights", WeightType::F32);
    // A guided step runs the conditional and unconditional rows as one batch of two; the value
    // itself does not change the time (tools/bench_torch.py uses the same default).
    let guidance: f32 = arg(&args, "--guidance", 2.5);
    let prompt = "a person walks forward, turns around and waves with the right hand";

    let t = Instant::now();
    let opts = LoadOptions { weights };
    let model = Arc::new(
        Model::load_with(&path, &opts).unwrap_or_else(|e| panic!("cannot load {path}: {e}")),
    );
    println!(
        "model {path}: {} weights, loaded in {:.0} ms, linear weights {:.1} MiB, RSS after load {:.1} MiB",
        weights.name(),
        t.elapsed().as_secs_f64() * 1e3,
        model.linear_weight_bytes() as f64 / (1 << 20) as f64,
        status_mib("VmRSS:"),
    );
    for frames in frames_list
        .split(',')
        .map(|f| f.trim().parse::<usize>().expect("--frames"))
    {
        let params = SessionParams {
            frames: Some(frames),
            steps: Some(steps),
            sampler,
            eta: Some(0.0),
            guidance: Some(guidance),
            clip_denoised: None,
            seed: 1,
            threads,
            respacing: None,
            looped: false,
        };
        let mut session = Session::new(Arc::clone(&model), &params).expect("session");
        let mut text_ms = Vec::new();
        for _ in 0..runs {
            let t = Instant::now();
            session.set_prompt(prompt).expect("prompt");
            text_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let mut step_ms = Vec::new();
        let mut gen_ms = Vec::new();
        let mut decode_ms = Vec::new();
        // The decode runs on a pool of the same size as the session's (whose pool is its own).
        let latent = model.is_latent();
        let pool = flame::pool::WorkerPool::new(threads).expect("pool");
        let (mut decoded, mut ws) = (Vec::new(), Workspace::default());
        let mut decode = |session: &Session| {
            let t = Instant::now();
            let sample = session.sample().expect("sample");
            pool.install(|| model.decode(sample, frames, &mut decoded, &mut ws))
                .expect("decode");
            t.elapsed().as_secs_f64() * 1e3
        };
        for _ in 0..runs {
            session.reset();
            let g = Instant::now();
            while session.steps_left() > 0 {
                let t = Instant::now();
                session.step().expect("step");
                step_ms.push(t.elapsed().as_secs_f64() * 1e3);
            }
            if latent {
                decode_ms.push(decode(&session));
            }
            gen_ms.push(g.elapsed().as_secs_f64() * 1e3);
        }
        // One more generation with the kernel accounting on (kept out of the timings above).
        session.reset();
        kernels::profile::enable(true);
        let g = Instant::now();
        while session.steps_left() > 0 {
            session.step().expect("step");
        }
        let profiled = g.elapsed().as_secs_f64();
        let prof = kernels::profile::take();
        // The decode's own accounting.
        let decode_prof = latent.then(|| {
            let ms = decode(&session);
            (ms, kernels::profile::take())
        });
        kernels::profile::enable(false);
        let lin_gflops = prof.linear_flop / prof.linear_seconds / 1e9;
        let attn_gflops = prof.attention_flop / prof.attention_seconds / 1e9;
        let lin_share = prof.linear_seconds / profiled;
        let attn_share = prof.attention_seconds / profiled;
        let (text, step, gen) = (median(text_ms), median(step_ms), median(gen_ms));
        let (lin, attn) = step_macs(&model, frames);
        let gflops = 2.0 * (lin + attn) / (step * 1e-3) / 1e9;
        println!(
            "frames {frames}, {steps} {} steps, guidance {}, {threads} threads, {} kernel (f32 tile {}), {runs} runs (medians):",
            sampler.map_or("default-sampler".to_string(), |s| format!("{s:?}")),
            guidance,
            kernels::kernel_name(),
            kernels::f32_tile()
        );
        println!("  text encoding      {text:9.2} ms");
        println!("  one guided step    {step:9.2} ms  ({:.2} GFLOP: {:.2} linear + {:.2} attention; {gflops:.1} GFLOP/s)",
            2.0 * (lin + attn) / 1e9, 2.0 * lin / 1e9, 2.0 * attn / 1e9);
        if args.iter().any(|a| a == "--targets") {
            target_bench(&model, &mut session, runs);
        }
        let decode_med = (!decode_ms.is_empty()).then(|| median(decode_ms));
        if let Some(d) = decode_med {
            println!("  VAE decode         {d:9.2} ms  (once, after the last step)");
            println!("  whole generation   {gen:9.2} ms  ({steps} steps and the decode)");
        } else {
            println!("  whole generation   {gen:9.2} ms");
        }
        println!(
            "  inside the kernels {lin_gflops:9.1} GFLOP/s in linear layers ({:.0}% of the time), \
             {attn_gflops:.1} GFLOP/s in attention ({:.0}%)",
            lin_share * 100.0,
            attn_share * 100.0
        );
        if prof.moe_seconds > 0.0 {
            let per_step = prof.moe_seconds * 1e3 / steps as f64;
            println!(
                "  mixture of experts {per_step:9.2} ms per step ({:.0}% of the time: gate, routing, experts; {:.1} GFLOP/s)",
                prof.moe_seconds / profiled * 100.0,
                prof.moe_flop / prof.moe_seconds / 1e9
            );
        }
        if let Some((ms, p)) = decode_prof {
            let (lin, attn) = (p.linear_seconds * 1e3, p.attention_seconds * 1e3);
            println!(
                "  inside the decode  {:9.1} GFLOP/s in linear layers and convolutions ({lin:.1} of \
                 {ms:.1} ms), {:.1} GFLOP/s in attention ({attn:.1} ms); {:.2} GFLOP",
                p.linear_flop / p.linear_seconds / 1e9,
                p.attention_flop / p.attention_seconds.max(1e-12) / 1e9,
                (p.linear_flop + p.attention_flop) / 1e9
            );
        }
        println!("  peak RSS (VmHWM)   {:9.1} MiB", status_mib("VmHWM:"));
        let decode_field = decode_med.map_or(String::new(), |d| format!(" decode_ms={d:.2}"));
        println!(
            "RESULT impl=flame weights={} frames={frames} text_ms={text:.2} step_ms={step:.2} gen_ms={gen:.2} gflops={gflops:.1} linear_gflops={lin_gflops:.1} linear_share={lin_share:.3} attention_gflops={attn_gflops:.1} moe_ms={:.2} hwm_mib={:.1}{decode_field}",
            weights.name(),
            prof.moe_seconds * 1e3 / steps as f64,
            status_mib("VmHWM:")
        );
    }
}

/// Cancel latency: the time from raising the cancel flag, at fractions (i + ½) / trials of a
/// full step, to the step returning.
fn cancel_bench(args: &[String]) {
    let frames: usize = arg(args, "--frames", 196);
    let threads: usize = arg(args, "--threads", 2);
    let trials: usize = arg(args, "--trials", 15);
    let guidance: f32 = arg(args, "--guidance", 2.5);
    let sampler: Option<Sampler> = args
        .iter()
        .any(|a| a == "--sampler")
        .then(|| arg(args, "--sampler", Sampler::Ddim));
    let (model, name) = if args.iter().any(|a| a == "--random-base") {
        (
            random_flame_base(),
            "random FLAME-base denoiser".to_string(),
        )
    } else {
        let path: String = arg(args, "--model", String::new());
        if path.is_empty() {
            eprintln!("usage: flame-bench cancel (--model M | --random-base) [--frames 196] [--threads 2] [--trials 15] [--guidance 2.5] [--sampler S]");
            std::process::exit(2);
        }
        let m = Model::load(&path).unwrap_or_else(|e| panic!("cannot load {path}: {e}"));
        (m, path)
    };
    let params = SessionParams {
        frames: Some(frames),
        steps: Some(50),
        sampler,
        eta: Some(0.0),
        guidance: Some(guidance),
        seed: 1,
        threads,
        ..Default::default()
    };
    let mut session = Session::new(Arc::new(model), &params).expect("session");
    session
        .set_prompt("a person walks forward, turns around and waves with the right hand")
        .expect("prompt");
    let flag = session.cancel_flag();
    let next_step = |session: &mut Session| {
        if session.steps_left() == 0 {
            session.reset();
        }
    };
    let mut full = Vec::new();
    for i in 0..7 {
        next_step(&mut session);
        let t = Instant::now();
        session.step().expect("step");
        if i >= 2 {
            full.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    let step_ms = median(full);
    let (mut latency, mut finished_first) = (Vec::new(), 0);
    for i in 0..trials {
        next_step(&mut session);
        let delay =
            std::time::Duration::from_secs_f64(step_ms * 1e-3 * (i as f64 + 0.5) / trials as f64);
        let (tx, rx) = std::sync::mpsc::channel();
        let (result, raised, end) = std::thread::scope(|s| {
            let session = &mut session;
            let worker = s.spawn(move || {
                tx.send(Instant::now()).unwrap();
                let r = session.step();
                (r, Instant::now())
            });
            let start = rx.recv().unwrap();
            std::thread::sleep((start + delay).saturating_duration_since(Instant::now()));
            let raised = Instant::now();
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
            let (r, end) = worker.join().unwrap();
            (r, raised, end)
        });
        match result {
            Err(flame::Error::Cancelled) => {
                latency.push(end.saturating_duration_since(raised).as_secs_f64() * 1e3)
            }
            Ok(_) => {
                // The step ended before it saw the flag; the flag would cancel the next one.
                finished_first += 1;
                flag.store(false, std::sync::atomic::Ordering::SeqCst);
            }
            Err(e) => panic!("step: {e}"),
        }
    }
    let max = latency.iter().copied().fold(0.0, f64::max);
    let cancelled = latency.len();
    let lat = if cancelled > 0 {
        median(latency)
    } else {
        f64::NAN
    };
    println!(
        "model {name}: {frames} frames, {} sampler, guidance {guidance}, {threads} threads",
        sampler.map_or("default".to_string(), |s| format!("{s:?}"))
    );
    println!("  full step (median of 5)        {step_ms:9.2} ms");
    println!(
        "  cancel latency (median of {cancelled}) {lat:9.2} ms, max {max:.2} ms; flag raised at \
         (i + 0.5) / {trials} of a step; {finished_first} steps ended before seeing it"
    );
    println!(
        "RESULT impl=flame bench=cancel frames={frames} threads={threads} step_ms={step_ms:.2} cancel_median_ms={lat:.2} cancel_max_ms={max:.2} cancelled={cancelled} finished_first={finished_first}"
    );
}

/// Frames that must be ready for the stream's latency (1 s at 20 fps).
const FIRST_READY: usize = 20;

/// Prompts the steady-state timeline cycles through.
const STREAM_PROMPTS: [&str; 4] = [
    "a person walks forward.",
    "a person waves with the right hand.",
    "a person jogs in a circle.",
    "a person jumps twice.",
];

/// One steady-state run: the whole timeline pumped one step at a time.
struct SteadyRun {
    /// Frames of the first chunk (excluded from the steady state) and seconds until it was done.
    first_frames: usize,
    first_s: f64,
    /// Seconds and new frames after the first chunk.
    rest_s: f64,
    rest_frames: usize,
    /// Per later chunk: seconds and new frames.
    chunks: Vec<(f64, usize)>,
    /// Denoiser steps of the first chunk.
    steps: usize,
}

/// Pumps `stream` one step at a time until `target` frames are ready; returns the time of
/// every change of `ready` (seconds since `t0`), the frames ready then, and the steps before it.
fn pump_until(stream: &mut Stream, target: usize, t0: Instant) -> Vec<(f64, usize, usize)> {
    let (mut marks, mut ready, mut steps) = (Vec::new(), stream.ready(), 0);
    while ready < target {
        let r = stream.pump(1).unwrap_or_else(|e| {
            eprintln!("flame-bench stream: pump at {ready} of {target} frames: {e}");
            std::process::exit(1)
        });
        steps += r.steps;
        if r.ready != ready {
            ready = r.ready;
            marks.push((t0.elapsed().as_secs_f64(), ready, steps));
        }
        if r.steps == 0 {
            eprintln!(
                "flame-bench stream: the stream stopped at {ready} of {target} frames (starving: {})",
                r.starving
            );
            std::process::exit(1)
        }
    }
    marks
}

/// Latency to the first frames and steady-state cost of a [`Stream`] (see the module doc).
fn stream_bench(args: &[String]) {
    let path: String = arg(args, "--model", String::new());
    if path.is_empty() {
        eprintln!(
            "usage: flame-bench stream --model M [--chunk N] [--overlap 20] [--steps S] [--threads 2] [--runs 5] \
             [--seconds 30] [--segment-seconds T]\n       \
             flame-bench retarget --rig FILE [--rig FILE ...] [--frames 200] [--runs 7]"
        );
        std::process::exit(2);
    }
    let chunk: usize = arg(args, "--chunk", 0);
    let overlap: usize = arg(args, "--overlap", 20);
    let steps: Option<usize> = args
        .iter()
        .any(|a| a == "--steps")
        .then(|| arg(args, "--steps", 0));
    let threads: usize = arg(args, "--threads", 2);
    let runs: usize = arg(args, "--runs", 5);
    let seconds: f64 = arg(args, "--seconds", 30.0);
    let segment_seconds: f64 = arg(args, "--segment-seconds", 0.0);
    let weights: WeightType = arg(args, "--weights", WeightType::F32);
    let model = Arc::new(
        Model::load_with(&path, &LoadOptions { weights })
            .unwrap_or_else(|e| panic!("cannot load {path}: {e}")),
    );
    let fps = model.config().motion.fps as f64;
    let total = (seconds * fps).round() as usize;
    if total == 0 {
        eprintln!("flame-bench stream: --seconds {seconds} is no frame at {fps} fps");
        std::process::exit(2);
    }
    let params = |seed: u64, lookahead: usize| StreamParams {
        chunk,
        overlap,
        lookahead,
        window: lookahead.max(StreamParams::default().window),
        session: SessionParams {
            steps,
            seed,
            threads,
            ..Default::default()
        },
    };
    let new_stream = |seed: u64, lookahead: usize| {
        Stream::new(Arc::clone(&model), &params(seed, lookahead)).unwrap_or_else(|e| {
            eprintln!("flame-bench stream: {path}: {e}");
            std::process::exit(1)
        })
    };
    let chunk = new_stream(0, total).chunk_frames();
    let segment = match (segment_seconds * fps).round() as usize {
        0 => chunk - overlap,
        s => s,
    };

    // Latency: push, then one step per pump until FIRST_READY frames are ready; with the first
    // segment whole, and split into FIRST_READY frames and the rest.
    let first_len = total.max(chunk);
    let latency = |split: bool| {
        let mut ms = Vec::new();
        let mut first = 0;
        for run in 0..runs {
            let mut stream = new_stream(run as u64, StreamParams::default().lookahead);
            let t = Instant::now();
            if split {
                stream
                    .push(Segment::new(STREAM_PROMPTS[0], FIRST_READY))
                    .expect("push");
                stream
                    .push(Segment::new(STREAM_PROMPTS[0], first_len - FIRST_READY))
                    .expect("push");
            } else {
                stream
                    .push(Segment::new(STREAM_PROMPTS[0], first_len))
                    .expect("push");
            }
            let marks = pump_until(&mut stream, FIRST_READY, t);
            ms.push(t.elapsed().as_secs_f64() * 1e3);
            first = marks[0].1;
        }
        let (min, max) = (
            ms.iter().copied().fold(f64::INFINITY, f64::min),
            ms.iter().copied().fold(0.0, f64::max),
        );
        (median(ms), min, max, first)
    };
    let (lat, lat_min, lat_max, lat_first) = latency(false);
    let short = (chunk > FIRST_READY && first_len > FIRST_READY).then(|| latency(true));

    // Steady state: the whole timeline, everything ahead.
    let mut steady = Vec::new();
    for run in 0..runs {
        let mut stream = new_stream(run as u64, total);
        let t = Instant::now();
        let mut pushed = 0;
        for i in 0.. {
            if pushed == total {
                break;
            }
            let frames = segment.min(total - pushed);
            let prompt = STREAM_PROMPTS[i % STREAM_PROMPTS.len()];
            stream.push(Segment::new(prompt, frames)).expect("push");
            pushed += frames;
        }
        let marks = pump_until(&mut stream, total, t);
        let (first_s, first_frames, first_steps) = marks[0];
        let (end_s, _, _) = *marks.last().expect("at least one chunk");
        let chunks = marks
            .windows(2)
            .map(|w| (w[1].0 - w[0].0, w[1].1 - w[0].1))
            .collect();
        steady.push(SteadyRun {
            first_frames,
            first_s,
            rest_s: end_s - first_s,
            rest_frames: total - first_frames,
            chunks,
            steps: first_steps,
        });
    }
    let s0 = &steady[0];
    let (first_frames, chunk_steps, later) = (s0.first_frames, s0.steps, s0.chunks.len());
    let lo = s0.chunks.iter().map(|c| c.1).min().unwrap_or(0);
    let hi = s0.chunks.iter().map(|c| c.1).max().unwrap_or(0);
    let (ms_per_s, rtf, chunk_ms, first_ms) = if later > 0 {
        (
            median(
                steady
                    .iter()
                    .map(|r| r.rest_s * 1e3 / r.rest_frames as f64 * fps)
                    .collect(),
            ),
            median(
                steady
                    .iter()
                    .map(|r| r.rest_frames as f64 / fps / r.rest_s)
                    .collect(),
            ),
            median(
                steady
                    .iter()
                    .flat_map(|r| r.chunks.iter().map(|c| c.0 * 1e3))
                    .collect(),
            ),
            median(steady.iter().map(|r| r.first_s * 1e3).collect()),
        )
    } else {
        (f64::NAN, f64::NAN, f64::NAN, f64::NAN)
    };

    println!(
        "model {path}: stream, {} weights, {fps} fps, {} kernel, {threads} threads, chunk {chunk} \
         frames, overlap {overlap}, {chunk_steps} steps per chunk{}, {runs} runs (medians)",
        weights.name(),
        kernels::kernel_name(),
        if steps.is_none() {
            " (model default)"
        } else {
            ""
        }
    );
    println!(
        "  latency            {lat:9.1} ms  (push to {FIRST_READY} frames ready; min {lat_min:.1}, max \
         {lat_max:.1}); the first chunk keeps nothing, so its {lat_first} frames come at once, \
         when the whole chunk is done"
    );
    match short {
        Some((ms, min, max, first)) => println!(
            "  short first chunk  {ms:9.1} ms  (first segment split into {FIRST_READY} frames and \
             the rest, same prompt: a {first}-frame first chunk; min {min:.1}, max {max:.1})"
        ),
        None => println!("  short first chunk        n/a     (the chunk is at most {FIRST_READY} frames already)"),
    }
    println!(
        "  steady state       {ms_per_s:9.1} ms per second of motion, real-time factor \
         {rtf:.2} (seconds of motion per wall second)"
    );
    println!(
        "                     {seconds} s = {total} frames in segments of {segment} frames over \
         {} prompts; first chunk {first_frames} frames ({first_ms:.0} ms, excluded), then \
         {later} chunks of {lo}..={hi} new frames, {chunk_ms:.0} ms each",
        STREAM_PROMPTS.len(),
    );
    let short_field = short.map_or(String::new(), |s| {
        format!(" latency_short_first_ms={:.1}", s.0)
    });
    println!(
        "RESULT impl=flame bench=stream latency_ms={lat:.1} ms_per_motion_second={ms_per_s:.1} \
         realtime_factor={rtf:.3} chunk={chunk} overlap={overlap} steps={chunk_steps} \
         threads={threads} first_chunk={lat_first} segment={segment} fps={fps} seconds={seconds}{short_field}"
    );
}

/// FLAME-base's denoiser (8 layers × 768 channels, 8 heads, feed-forward 2048, FLAME's 471
/// motion lengths) with random weights, and the tiny test fixture's text encoder and tokenizer.
/// Shapes come from the fixture's denoiser with its sizes scaled (64 → 768 channels, 128 → 2048
/// feed-forward, 2 → 8 layers).
fn random_flame_base() -> Model {
    use safetensors::tensor::{Dtype, TensorView};
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/flame_tiny.safetensors"
    );
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let st = safetensors::SafeTensors::deserialize(&bytes).expect("fixture");
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).expect("fixture");
    let mut meta = header.metadata().clone().expect("fixture metadata");
    let mut cfg: serde_json::Value =
        serde_json::from_str(&meta["flame.config"]).expect("fixture config");
    let den = &mut cfg["denoiser"];
    den["model_channels"] = 768.into();
    den["num_layers"] = 8.into();
    den["num_heads"] = 8.into();
    den["dim_feedforward"] = 2048.into();
    meta.insert("flame.config".into(), cfg.to_string());
    let scale = |d: usize| match d {
        64 => 768,
        128 => 2048,
        192 => 3 * 768,
        d => d,
    };
    let mut rng = flame::rng::GaussianRng::new(7);
    let mut list: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    for (name, view) in st.tensors() {
        if name.starts_with("text.") {
            list.push((name, view.shape().to_vec(), view.data().to_vec()));
            continue;
        }
        let names: Vec<String> = match name.strip_prefix("tf_decoder.layers.0.") {
            Some(rest) => (0..8)
                .map(|l| format!("tf_decoder.layers.{l}.{rest}"))
                .collect(),
            None if name.starts_with("tf_decoder.layers.") => continue,
            None => vec![name.clone()],
        };
        let shape: Vec<usize> = view.shape().iter().map(|&d| scale(d)).collect();
        for n in names {
            let count: usize = shape.iter().product();
            // PyTorch-like magnitudes: norms start at 1 / 0, linear weights ~ 1/sqrt(fan-in).
            let bound = if shape.len() == 2 {
                (shape[1] as f64).sqrt().recip()
            } else {
                0.02
            };
            let values: Vec<f32> = if n.contains(".norm") {
                vec![if n.ends_with("weight") { 1.0 } else { 0.0 }; count]
            } else {
                (0..count)
                    .map(|_| ((rng.next_uniform() * 2.0 - 1.0) * bound) as f32)
                    .collect()
            };
            let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            list.push((n, shape.clone(), data));
        }
    }
    let views: Vec<(String, TensorView)> = list
        .iter()
        .map(|(n, s, b)| {
            (
                n.clone(),
                TensorView::new(Dtype::F32, s.clone(), b).expect("view"),
            )
        })
        .collect();
    let file = safetensors::serialize(views, &Some(meta)).expect("serialize");
    drop(list);
    Model::from_bytes(&file).expect("random FLAME-base")
}
