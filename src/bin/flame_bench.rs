//! `flame-bench`: times text encoding, one guided denoising step and a whole generation on a
//! model file, and prints medians over several runs.
//!
//! `flame-bench --model M [--frames 196] [--steps 10] [--sampler ddim] [--threads 2] [--runs 5]`

use std::sync::Arc;
use std::time::Instant;

use flame::models::Model;
use flame::session::{Sampler, Session, SessionParams};

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

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path: String = arg(&args, "--model", String::new());
    if path.is_empty() {
        eprintln!("usage: flame-bench --model M [--frames 196] [--steps 10] [--sampler ddim] [--threads 2] [--runs 5]");
        std::process::exit(2);
    }
    let frames: usize = arg(&args, "--frames", 196);
    let steps: usize = arg(&args, "--steps", 10);
    let threads: usize = arg(&args, "--threads", 2);
    let runs: usize = arg(&args, "--runs", 5);
    let sampler: Sampler = arg(&args, "--sampler", Sampler::Ddim);
    let prompt = "a person walks forward, turns around and waves with the right hand";

    let t = Instant::now();
    let model = Arc::new(Model::load(&path).unwrap_or_else(|e| panic!("cannot load {path}: {e}")));
    println!(
        "model {path}: loaded in {:.0} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let params = SessionParams {
        frames: Some(frames),
        steps: Some(steps),
        sampler: Some(sampler),
        eta: Some(0.0),
        guidance: None,
        clip_denoised: None,
        seed: 1,
        threads,
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
    for _ in 0..runs {
        session.reset();
        let g = Instant::now();
        while session.steps_left() > 0 {
            let t = Instant::now();
            session.step().expect("step");
            step_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        gen_ms.push(g.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "frames {frames}, {steps} {sampler:?} steps, guidance {}, {threads} threads, {runs} runs (medians):",
        model.config().defaults.guidance
    );
    println!("  text encoding      {:9.2} ms", median(text_ms));
    println!("  one guided step    {:9.2} ms", median(step_ms));
    println!("  whole generation   {:9.2} ms", median(gen_ms));
}
