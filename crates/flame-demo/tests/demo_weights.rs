//! Accuracy of every weight type on the trained demo model: the features after the model's 10
//! DDIM steps (120 frames, guidance 2, three prompts × two seeds) against the f32 run, max and
//! mean absolute difference, printed as a table (`cargo test -p flame-demo --test demo_weights
//! -- --nocapture`; docs/performance.md quotes it). Types the CPU cannot run (bf16-compute
//! without AVX512_BF16, int8 without AVX2) are refused at load with the instruction's name,
//! and the test says it skipped them. Int8 runs on the kernel in use (`FLAME_KERNEL=avx2`
//! measures the AVX2 path, whose activations have 63 levels).
//!
//! Five more rows measure the int8 file `flame quantize` writes from this model (GPTQ-rounded
//! weights calibrated on its own runs, feature projections kept f32; src/quantize.rs), loaded
//! as int8 and multiplied back out to f32 and f16 (int8 weights, float activations), and the
//! file written with the last decoder layer kept f32 (`--keep-f32 tf_decoder.layers.3.`), and
//! one row for the file with a scale per group of 128 inputs (`--group 128`) loaded as f16.
//!
//! A second test shows where the reduced types' error comes from: the same features with the
//! weights themselves rounded to fewer significant bits and run in f32 (bf16 storage gives
//! exactly those bits at 8).
//!
//! The bounds are this model's measured errors with room (a regression guard, not a goal):
//! f16 and the bf16 types only round weights (and, for bf16-compute, each layer's input) to
//! 11 or 8 significant bits; int8 quantises weights per output and activations per row to 8
//! bits, which a 10-step sampler amplifies.

use std::sync::Arc;

#[path = "../../../tests/common/mod.rs"]
mod common;

use common::{demo_model, skip};
use flame::kernels::WeightType;
use flame::models::{LoadOptions, Model};
use flame::session::{Session, SessionParams, Which};

const PROMPTS: [&str; 3] = [
    "a person walks forward.",
    "a person jumps twice.",
    "a person waves with the right hand.",
];
const SEEDS: [u64; 2] = [0, 1];

fn features(model: &Arc<Model>, prompt: &str, seed: u64) -> Vec<f32> {
    let params = SessionParams {
        frames: Some(120),
        seed,
        threads: 2,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt(prompt).unwrap();
    s.run().unwrap();
    s.motion(Which::Sample).unwrap().0.to_vec()
}

#[test]
fn every_weight_type_is_close_to_f32_on_the_demo_model() {
    let Some(path) = demo_model() else {
        skip("demo_weights", "no demo model (set FLAME_MINILM_DIR)");
        return;
    };
    let load = |weights| Model::load_with(&path, &LoadOptions { weights }).map(Arc::new);
    let f32_model = load(WeightType::F32).unwrap();
    let want: Vec<Vec<f32>> = PROMPTS
        .iter()
        .flat_map(|p| SEEDS.map(|s| features(&f32_model, p, s)))
        .collect();
    println!("weights        max |Δ|   mean |Δ|   (features after 10 steps vs f32, 6 runs)");
    // (type, bound on max, bound on mean)
    let bounds = [
        (WeightType::F16, 0.02, 1e-3),
        (WeightType::Bf16, 0.15, 4e-3),
        (WeightType::Bf16Compute, 0.08, 2e-3),
        (WeightType::Int8, 0.8, 0.05),
    ];
    // The int8 file `flame quantize` writes (GPTQ on the model's own runs), as int8 and
    // multiplied back out to f32.
    let quantized =
        std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("flame_demo_int8.safetensors");
    // Written on every run, so that a change to the quantiser is what gets measured.
    flame::quantize::quantize(&path, &quantized, &Default::default()).unwrap();
    // The same with the last decoder layer kept f32 (`--keep-f32 tf_decoder.layers.3.`).
    let quantized_last = quantized.with_file_name("flame_demo_int8_last_f32.safetensors");
    let keep_last = flame::quantize::QuantizeOptions {
        keep_f32: vec!["tf_decoder.layers.3.".into()],
        ..Default::default()
    };
    flame::quantize::quantize(&path, &quantized_last, &keep_last).unwrap();
    // And with one scale per group of 128 inputs (`--group 128`), for float activations.
    let quantized_group = quantized.with_file_name("flame_demo_int8_g128.safetensors");
    let group = flame::quantize::QuantizeOptions {
        group: Some(128),
        ..Default::default()
    };
    flame::quantize::quantize(&path, &quantized_group, &group).unwrap();
    let load_group =
        |weights| Model::load_with(&quantized_group, &LoadOptions { weights }).map(Arc::new);
    // AVX2's vpmaddubsw path quantises activations to 63 levels (0.53 / 0.014 measured with
    // tools/avx2_only.sh), VNNI to 127 (0.19 / 0.0073; the last layer f32: 0.165 / 0.0020).
    let avx2 = WeightType::Int8.compute_path().contains("vpmaddubsw");
    let (file_max, file_mean) = if avx2 { (0.8, 0.025) } else { (0.35, 0.012) };
    let (last_max, last_mean) = if avx2 { (0.8, 0.012) } else { (0.3, 0.004) };
    let load_q = |weights| Model::load_with(&quantized, &LoadOptions { weights }).map(Arc::new);
    let load_last =
        |weights| Model::load_with(&quantized_last, &LoadOptions { weights }).map(Arc::new);
    // Which file: 0 the f32 original, 1 the int8 file, 2 the int8 file with its last layer f32,
    // 3 the int8 file with a scale per group of 128 inputs.
    let rows: Vec<(&str, WeightType, u8, f64, f64)> = bounds
        .iter()
        .map(|&(ty, a, b)| (ty.name(), ty, 0, a, b))
        .chain([
            ("int8 file", WeightType::Int8, 1, file_max, file_mean),
            ("int8 file→f32", WeightType::F32, 1, 0.2, 0.002),
            ("int8 file→f16", WeightType::F16, 1, 0.2, 0.002),
            ("int8 last f32", WeightType::Int8, 2, last_max, last_mean),
            // 0.046 / 0.00063 measured.
            ("int8 g128→f16", WeightType::F16, 3, 0.1, 0.0012),
        ])
        .collect();
    for (label, ty, file, max_bound, mean_bound) in rows {
        let loaded = match file {
            0 => load(ty),
            1 => load_q(ty),
            2 => load_last(ty),
            _ => load_group(ty),
        };
        let model = match loaded {
            Ok(m) => m,
            Err(e) => {
                assert!(!ty.native_on_this_cpu(), "{ty:?}: {e}");
                assert!(e.to_string().contains("AVX512_"), "{e}");
                println!("{:<14} skipped: {e}", ty.name());
                continue;
            }
        };
        let (mut max, mut sum, mut count) = (0.0f64, 0.0f64, 0usize);
        for (i, p) in PROMPTS.iter().enumerate() {
            for (j, &s) in SEEDS.iter().enumerate() {
                let got = features(&model, p, s);
                let w = &want[i * SEEDS.len() + j];
                assert_eq!(got.len(), w.len());
                for (a, b) in got.iter().zip(w) {
                    let d = (a - b).abs() as f64;
                    max = max.max(d);
                    sum += d;
                    count += 1;
                }
            }
        }
        let mean = sum / count as f64;
        println!("{label:<14} {max:>8.4}   {mean:>8.5}");
        assert!(
            max > 0.0,
            "{ty:?} gave the f32 bits: the type is not in effect"
        );
        assert!(
            max <= max_bound && mean <= mean_bound,
            "{ty:?}: max {max}, mean {mean}"
        );
    }
}

/// `v` rounded to its `bits` most significant bits (the implicit one included), to nearest,
/// ties to even: bf16 keeps 8, f16 11 (for normal numbers), f32 24.
fn round_to_bits(v: f32, bits: u32) -> f32 {
    let drop = 24 - bits;
    if drop == 0 || !v.is_finite() {
        return v;
    }
    let b = v.to_bits();
    let keep_odd = (b >> drop) & 1;
    f32::from_bits(((b + (1 << (drop - 1)) - 1 + keep_odd) >> drop) << drop)
}

/// A copy of the model file `bytes` whose linear layers' weight matrices (the tensors the
/// reduced types pack: 2-D `…weight`s other than embedding tables), in the denoiser only or in
/// the text encoder too, are rounded to `bits` significant bits and stored as f32.
fn rounded_copy(bytes: &[u8], bits: u32, text_too: bool) -> Vec<u8> {
    use safetensors::{tensor::TensorView, Dtype, SafeTensors};
    let file = SafeTensors::deserialize(bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(bytes).unwrap();
    let linear = |name: &str, shape: &[usize]| {
        shape.len() == 2
            && name.ends_with("weight")
            && !name.contains("emb")
            && (text_too || !name.starts_with("text."))
    };
    let mut rounded: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut kept = Vec::new();
    for (name, view) in file.tensors() {
        if !linear(&name, view.shape()) {
            kept.push((name, view));
            continue;
        }
        let values: Vec<f32> = match view.dtype() {
            Dtype::F32 => view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .collect(),
            Dtype::F16 => view
                .data()
                .chunks_exact(2)
                .map(|c| half::f16::from_le_bytes(c.try_into().unwrap()).to_f32())
                .collect(),
            other => panic!("{name}: {other:?}"),
        };
        let data = values
            .iter()
            .flat_map(|&v| round_to_bits(v, bits).to_le_bytes())
            .collect();
        rounded.push((name, view.shape().to_vec(), data));
    }
    let views = kept
        .into_iter()
        .chain(rounded.iter().map(|(name, shape, data)| {
            let view = TensorView::new(Dtype::F32, shape.clone(), data).unwrap();
            (name.clone(), view)
        }));
    safetensors::serialize(views, header.metadata()).unwrap()
}

#[test]
fn rounding_to_bits_matches_hand_derived_values_and_the_half_crate() {
    // Hand-derived: 1 + 2^-8 is a tie between 1 and 1 + 2^-7 at 8 bits (to even: 1); 1 + 3·2^-8
    // rounds up.
    assert_eq!(round_to_bits(1.0 + (-8f32).exp2(), 8), 1.0);
    assert_eq!(
        round_to_bits(-1.0 - 3.0 * (-8f32).exp2(), 8),
        -1.0 - (-6f32).exp2()
    );
    assert_eq!(round_to_bits(0.1, 24), 0.1);
    // At 8 and 11 bits it is bf16's and (for normal numbers) f16's rounding.
    for i in 0..20_000u32 {
        let v = f32::from_bits(0x3a80_0000 + i.wrapping_mul(2_654_435_761) % 0x0900_0000);
        for v in [v, -v] {
            assert_eq!(round_to_bits(v, 8), half::bf16::from_f32(v).to_f32(), "{v}");
            assert_eq!(round_to_bits(v, 11), half::f16::from_f32(v).to_f32(), "{v}");
        }
    }
}

/// What limits the reduced types is the weights' precision, not libflame's arithmetic: the
/// demo model with its linear weights rounded to k significant bits, run in f32, against the
/// f32 run (the same features as above). bf16 keeps 8 bits: the `bf16` weight type must give
/// the same bits as the f32 run of weights rounded to 8 bits (it widens them exactly), and the
/// table shows how many bits a 2e-2 bound on this model needs.
#[test]
fn weights_rounded_to_fewer_bits() {
    let Some(path) = demo_model() else {
        skip("demo_weights", "no demo model (set FLAME_MINILM_DIR)");
        return;
    };
    use flame::checkpoint::ModelFile;
    let bytes = std::fs::read(&path).unwrap();
    let load = |bytes: &[u8], weights| {
        let file = ModelFile::from_bytes(bytes).unwrap();
        Arc::new(Model::from_file_with(file, &LoadOptions { weights }).unwrap())
    };
    let run_all = |model: &Arc<Model>| -> Vec<Vec<f32>> {
        PROMPTS
            .iter()
            .flat_map(|p| SEEDS.map(|s| features(model, p, s)))
            .collect()
    };
    let want = run_all(&load(&bytes, WeightType::F32));
    let stats = |got: &[Vec<f32>]| {
        let d: Vec<f64> = got
            .iter()
            .flatten()
            .zip(want.iter().flatten())
            .map(|(a, b)| (a - b).abs() as f64)
            .collect();
        let max = d.iter().cloned().fold(0.0, f64::max);
        (max, d.iter().sum::<f64>() / d.len() as f64)
    };

    // The bf16 type rounds the text encoder's layers too (only the compute types keep it f32).
    let bf16 = run_all(&load(&bytes, WeightType::Bf16));
    let eight = run_all(&load(&rounded_copy(&bytes, 8, true), WeightType::F32));
    assert!(
        bf16.iter()
            .flatten()
            .zip(eight.iter().flatten())
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "bf16 weights differ from f32 arithmetic on weights rounded to 8 bits"
    );

    println!(
        "denoiser weights rounded to   max |Δ|   mean |Δ|   (text encoder f32, as in bf16-compute)"
    );
    let mut errors = Vec::new();
    for bits in [12, 11, 10, 9, 8] {
        let got = run_all(&load(&rounded_copy(&bytes, bits, false), WeightType::F32));
        let (max, mean) = stats(&got);
        println!("{bits:>2} bits                       {max:>8.4}   {mean:>8.5}");
        errors.push((bits, max));
    }
    // The demo denoiser is stored in f16: its weights already have at most 11 significant bits
    // (f16 subnormals fewer), so rounding to 11 or more changes nothing.
    for &(bits, max) in &errors[..2] {
        assert_eq!(max, 0.0, "{bits} bits changed an f16 weight");
    }
    for &(bits, max) in &errors[2..] {
        assert!(max > 0.0, "{bits} bits changed nothing");
    }
}
