//! `flame quantize`'s int8 files (src/quantize.rs) on the tiny FLAME and MDM fixtures: what the
//! file holds, that its integers load as written, and that bad files and bad calibrations are
//! refused with the tensor's name. Its accuracy on the trained demo model is measured by
//! crates/flame-demo/tests/demo_weights.rs.

use std::path::{Path, PathBuf};
use std::sync::Arc;

mod common;

use flame::models::{LoadOptions, Model, WeightType};
use flame::quantize::{quantize, QuantizeOptions, QUANTIZATION_KEY};
use flame::session::{Session, SessionParams, Which};
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;

fn fixture(name: &str) -> PathBuf {
    common::repo(&format!("tests/fixtures/{name}"))
}

fn tmp(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("quantize_{name}"))
}

fn small() -> QuantizeOptions {
    QuantizeOptions {
        prompts: vec!["a person walks forward.".into(), "a person jumps.".into()],
        frames: Some(40),
        threads: 2,
        ..Default::default()
    }
}

/// The quantised tiny FLAME fixture (written once per test binary run, by name).
fn quantized(name: &str) -> PathBuf {
    let out = tmp(name);
    quantize(&fixture("flame_tiny.safetensors"), &out, &small()).unwrap();
    out
}

/// `bytes` with tensor `name` replaced by `(dtype, data)` (same shape).
fn replaced(bytes: &[u8], name: &str, dtype: Dtype, data: Vec<u8>) -> Vec<u8> {
    let file = SafeTensors::deserialize(bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(bytes).unwrap();
    let shape = file.tensor(name).unwrap().shape().to_vec();
    let mut views: Vec<(String, TensorView<'_>)> = file
        .tensors()
        .into_iter()
        .filter(|(n, _)| n != name)
        .collect();
    views.push((name.into(), TensorView::new(dtype, shape, &data).unwrap()));
    safetensors::serialize(views, header.metadata()).unwrap()
}

fn x0(model: &Arc<Model>) -> Vec<f32> {
    let params = SessionParams {
        frames: Some(40),
        steps: Some(1),
        seed: 3,
        threads: 1,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(model), &params).unwrap();
    s.set_prompt("a person waves.").unwrap();
    s.run().unwrap().to_vec()
}

#[test]
fn the_file_holds_int8_weights_with_scales_and_keeps_the_feature_projections_f32() {
    let path = quantized("layout.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().as_ref().unwrap();
    let info: serde_json::Value = serde_json::from_str(&meta[QUANTIZATION_KEY]).unwrap();
    assert_eq!(info["calibration_runs"], 2);
    let original = std::fs::read(fixture("flame_tiny.safetensors")).unwrap();
    let original = SafeTensors::deserialize(&original).unwrap();
    let mut int8 = 0;
    for (name, view) in file.tensors() {
        if name.ends_with("_scale") {
            continue;
        }
        let was = original.tensor(&name).unwrap();
        assert_eq!(view.shape(), was.shape(), "{name}");
        if view.dtype() != Dtype::I8 {
            continue;
        }
        int8 += 1;
        let scale = file.tensor(&format!("{name}_scale")).unwrap();
        assert_eq!(scale.shape(), &view.shape()[..1], "{name}");
        // Each row's integers times its scale stay within a step of the original weights
        // (GPTQ carries errors along the row, so not within half a step).
        let w: Vec<f32> = was
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        let s: Vec<f32> = scale
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        let k = view.shape()[1];
        let mut worst = 0.0f32;
        for (i, &q) in view.data().iter().enumerate() {
            let (q, s) = (q as i8, s[i / k]);
            assert!(q != i8::MIN && s > 0.0 && s.is_finite());
            worst = worst.max((q as f32 * s - w[i]).abs() / s);
        }
        assert!(worst < 8.0, "{name}: {worst} steps");
    }
    assert!(int8 >= 10, "{int8} int8 weights");
    for kept in ["input_projection.weight", "last_projection.weight"] {
        assert_eq!(file.tensor(kept).unwrap().dtype(), Dtype::F32, "{kept}");
    }
}

/// The quantised file at `path` as an f32 file: every int8 weight multiplied out here, input
/// `i` of a row by its row's scale `i / group` (`group` = `k` for one scale per row).
fn multiplied_out(path: &Path, group: Option<usize>) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let mut meta = header.metadata().clone().unwrap();
    meta.remove(QUANTIZATION_KEY);
    let mut floats: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut views = Vec::new();
    for (name, view) in file.tensors() {
        if name.ends_with("_scale") {
            continue;
        }
        if view.dtype() != Dtype::I8 {
            views.push((name, view));
            continue;
        }
        let scale = file.tensor(&format!("{name}_scale")).unwrap();
        let k = view.shape()[1];
        let g = group.unwrap_or(k);
        let per_row = k.div_ceil(g);
        assert_eq!(scale.data().len(), 4 * view.shape()[0] * per_row, "{name}");
        let data = view
            .data()
            .iter()
            .enumerate()
            .flat_map(|(i, &q)| {
                let j = (i / k) * per_row + (i % k) / g;
                let s = &scale.data()[4 * j..4 * j + 4];
                (q as i8 as f32 * f32::from_le_bytes(s.try_into().unwrap())).to_le_bytes()
            })
            .collect();
        floats.push((name, view.shape().to_vec(), data));
    }
    views.extend(floats.iter().map(|(n, shape, data)| {
        (
            n.clone(),
            TensorView::new(Dtype::F32, shape.clone(), data).unwrap(),
        )
    }));
    safetensors::serialize(views, &Some(meta)).unwrap()
}

#[test]
fn int8_and_f32_loads_run_the_written_integers() {
    // The file loaded as f32 multiplies its integers back out: the same bits as an f32 file
    // holding q·s written here from the file's own tensors. Loaded as int8 it differs from that
    // only by the activations' rounding.
    let path = quantized("loads.safetensors");
    let plain = Arc::new(Model::from_bytes(&multiplied_out(&path, None)).unwrap());
    let load = |weights| Arc::new(Model::load_with(&path, &LoadOptions { weights }).unwrap());
    let want = x0(&plain);
    assert_eq!(x0(&load(WeightType::F32)), want);
    if WeightType::Int8.native_on_this_cpu() {
        let int8 = load(WeightType::Int8);
        assert_eq!(int8.weight_type(), WeightType::Int8);
        assert!(int8.linear_weight_bytes() < load(WeightType::F32).linear_weight_bytes());
        let got = x0(&int8);
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let diff = common::max_abs_diff(&got, &want);
        assert!(diff > 0.0 && diff < 0.05 * scale, "{diff} of {scale}");
    }
}

#[test]
fn a_file_with_a_scale_per_group_runs_with_float_activations_only() {
    // Groups of 12 inputs: most of the tiny model's widths are not multiples of 12, so their
    // rows end with a shorter group.
    let opts = QuantizeOptions {
        group: Some(12),
        ..small()
    };
    let path = tmp("group.safetensors");
    let r = quantize(&fixture("flame_tiny.safetensors"), &path, &opts).unwrap();
    let written = flame::checkpoint::ModelFile::open(&path).unwrap();
    assert_eq!(written.int8_group().unwrap(), Some(12));
    let (mut grouped, mut partial) = (0, 0);
    for l in r.layers.iter().filter(|l| l.int8) {
        let shape = written.shape(&l.tensor).unwrap().to_vec();
        let scale = written.shape(&format!("{}_scale", l.tensor)).unwrap();
        assert_eq!(scale, [shape[0], shape[1].div_ceil(12)], "{}", l.tensor);
        partial += usize::from(!shape[1].is_multiple_of(12));
        grouped += 1;
        // Finer scales: no worse on the calibration inputs than one scale per row.
        if l.rows_seen > 0 {
            assert!(l.error_written <= l.error_rounded, "{l:?}");
        }
    }
    assert!(grouped > 0 && partial > 0, "{grouped} {partial}");
    // As f32: the integers multiplied out by their group's scale, bit for bit.
    let plain = Arc::new(Model::from_bytes(&multiplied_out(&path, Some(12))).unwrap());
    let f32_load = Arc::new(
        Model::load_with(
            &path,
            &LoadOptions {
                weights: WeightType::F32,
            },
        )
        .unwrap(),
    );
    assert_eq!(x0(&f32_load), x0(&plain));
    // As int8: refused, saying why and what to do.
    let msg = Model::load_with(
        &path,
        &LoadOptions {
            weights: WeightType::Int8,
        },
    )
    .err()
    .unwrap()
    .to_string();
    assert!(
        msg.contains("one scale per group of 12 inputs") && msg.contains("load it as f32"),
        "{msg}"
    );
    // A group of 0 is refused before calibrating.
    let zero = QuantizeOptions {
        group: Some(0),
        ..small()
    };
    let msg = quantize(
        &fixture("flame_tiny.safetensors"),
        &tmp("g0.safetensors"),
        &zero,
    )
    .unwrap_err()
    .to_string();
    assert!(msg.contains("at least one input"), "{msg}");

    // Bad records: a group that is not a positive whole number, and per-row scales under a
    // group record, are refused at load.
    let bytes = std::fs::read(&path).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().clone().unwrap();
    for bad in ["0", "-3", "12.5", "\"12\""] {
        let mut m = meta.clone();
        let record = m[QUANTIZATION_KEY].replace("\"group\":12", &format!("\"group\":{bad}"));
        m.insert(QUANTIZATION_KEY.into(), record);
        let file = SafeTensors::deserialize(&bytes).unwrap();
        let again = safetensors::serialize(file.tensors(), &Some(m)).unwrap();
        let msg = Model::from_bytes(&again).err().unwrap().to_string();
        assert!(msg.contains("not a positive whole number"), "{bad}: {msg}");
    }
    let per_row = quantized("group_vs_row.safetensors");
    let rows = std::fs::read(&per_row).unwrap();
    let (_, rows_header) = SafeTensors::read_metadata(&rows).unwrap();
    let mut m = rows_header.metadata().clone().unwrap();
    m.insert(QUANTIZATION_KEY.into(), meta[QUANTIZATION_KEY].clone());
    let file = SafeTensors::deserialize(&rows).unwrap();
    let mixed = safetensors::serialize(file.tensors(), &Some(m)).unwrap();
    let msg = Model::from_bytes(&mixed).err().unwrap().to_string();
    assert!(msg.contains("_scale"), "{msg}");
}

#[test]
fn bad_scales_and_values_are_refused_with_the_tensor_name() {
    let path = quantized("bad.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    let name = "tf_decoder.layers.0.linear1.weight".to_string();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let n = file.tensor(&format!("{name}_scale")).unwrap().shape()[0];
    let q = file.tensor(&name).unwrap().data().to_vec();
    for bad in [f32::NAN, 0.0, -0.01, f32::INFINITY] {
        let mut scales = vec![0.01f32; n];
        scales[n - 1] = bad;
        let data = scales.iter().flat_map(|v| v.to_le_bytes()).collect();
        let edited = replaced(&bytes, &format!("{name}_scale"), Dtype::F32, data);
        for weights in [WeightType::F32, WeightType::Int8] {
            let err = Model::from_file_with(
                flame::checkpoint::ModelFile::from_bytes(&edited).unwrap(),
                &LoadOptions { weights },
            );
            let msg = err.err().map(|e| e.to_string()).unwrap_or_default();
            if weights == WeightType::Int8 && !weights.native_on_this_cpu() {
                continue;
            }
            assert!(
                msg.contains(&format!("{name}_scale")) && msg.contains("finite and positive"),
                "{bad}: {msg}"
            );
        }
    }
    let mut low = q.clone();
    low[0] = 0x80;
    let msg = Model::from_bytes(&replaced(&bytes, &name, Dtype::I8, low))
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains(&name) && msg.contains("-127..=127"), "{msg}");
    // A norm stored as int8 is not a quantised weight.
    let norm = "tf_decoder.layers.0.norm1.weight";
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let v = file.tensor(norm).unwrap();
    let data = vec![1u8; v.shape().iter().product()];
    let msg = Model::from_bytes(&replaced(&bytes, norm, Dtype::I8, data))
        .err()
        .unwrap()
        .to_string();
    assert!(msg.contains(norm) && msg.contains("int8"), "{msg}");
}

#[test]
fn bad_calibrations_are_refused() {
    let model = fixture("flame_tiny.safetensors");
    let none = QuantizeOptions {
        prompts: Vec::new(),
        ..small()
    };
    let msg = quantize(&model, &tmp("none.safetensors"), &none)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("at least one prompt"), "{msg}");
    let zero = QuantizeOptions {
        seeds: 0,
        ..small()
    };
    assert!(quantize(&model, &tmp("zero.safetensors"), &zero).is_err());
    // Quantising twice would round rounded weights.
    let once = quantized("once.safetensors");
    let msg = quantize(&once, &tmp("twice.safetensors"), &small())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("quantised already"), "{msg}");
    // A model whose runs are not finite has no calibration to give.
    let bytes = std::fs::read(&model).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    let (name, view) = file
        .tensors()
        .into_iter()
        .find(|(n, v)| n.ends_with("linear1.bias") && v.dtype() == Dtype::F32)
        .unwrap();
    let data = vec![0xffu8; view.data().len()];
    let broken = replaced(&bytes, &name, Dtype::F32, data);
    let path = tmp("nan_in.safetensors");
    std::fs::write(&path, broken).unwrap();
    assert!(quantize(&path, &tmp("nan_out.safetensors"), &small()).is_err());
}

#[test]
fn named_weights_stay_f32_and_unknown_names_are_refused() {
    let model = fixture("flame_tiny.safetensors");
    let keep = QuantizeOptions {
        keep_f32: vec![
            "tf_decoder.layers.1.".into(),
            "tf_decoder.layers.0.linear2.weight".into(),
        ],
        ..small()
    };
    let out = tmp("keep.safetensors");
    let r = quantize(&model, &out, &keep).unwrap();
    let original = std::fs::read(&model).unwrap();
    let original = flame::checkpoint::ModelFile::from_bytes(&original).unwrap();
    let written = flame::checkpoint::ModelFile::open(&out).unwrap();
    let mut kept = 0;
    for l in &r.layers {
        let named = l.tensor.starts_with("tf_decoder.layers.1.")
            || l.tensor == "tf_decoder.layers.0.linear2.weight";
        let feature = l.tensor.starts_with("input_projection") || l.tensor.starts_with("last_");
        assert_eq!(l.int8, !(named || feature), "{}", l.tensor);
        if named {
            kept += 1;
            // The original values, widened to f32 where the fixture stores f16.
            let want = original.tensor_any_shape(&l.tensor).unwrap();
            let got = written.tensor_any_shape(&l.tensor).unwrap();
            assert_eq!(
                written.dtype(&l.tensor).unwrap(),
                flame::checkpoint::StoredDtype::F32
            );
            assert_eq!(want.data(), got.data(), "{}", l.tensor);
            assert!(!written.contains(&format!("{}_scale", l.tensor)));
        }
    }
    // Layer 1's q/k/v, attention output, cross-attention q/k/v and output, and two FFN
    // weights, plus layer 0's linear2.
    assert_eq!(kept, 7);
    let model_int8 = if WeightType::Int8.native_on_this_cpu() {
        WeightType::Int8
    } else {
        WeightType::F32
    };
    let loaded = Arc::new(
        Model::load_with(
            &out,
            &LoadOptions {
                weights: model_int8,
            },
        )
        .unwrap(),
    );
    assert!(x0(&loaded).iter().all(|v| v.is_finite()));

    // A name the file does not have is refused before calibrating; a tensor that is not a
    // linear weight (a layer norm's) after.
    for (name, says) in [
        (
            "tf_decoder.layers.9.",
            "has no tensor named `tf_decoder.layers.9.`",
        ),
        (
            "tf_decoder.layers.0.norm1.weight",
            "no linear weight is named `tf_decoder.layers.0.norm1.weight`",
        ),
    ] {
        let bad = QuantizeOptions {
            keep_f32: vec![name.into()],
            ..small()
        };
        let msg = quantize(&model, &tmp("keep_bad.safetensors"), &bad)
            .unwrap_err()
            .to_string();
        assert!(msg.contains(says), "{msg}");
    }
}

#[test]
fn another_family_quantises_too() {
    // MDM: its pose embedding and final projection stay f32, the rest is int8, and the file
    // runs as int8 where the CPU can.
    let out = tmp("mdm.safetensors");
    let r = quantize(&fixture("mdm_tiny.safetensors"), &out, &small()).unwrap();
    assert!(r.layers.iter().any(|l| l.int8));
    for l in &r.layers {
        let feature = l.tensor.contains("poseEmbedding") || l.tensor.contains("poseFinal");
        assert_eq!(l.int8, !feature, "{}", l.tensor);
        if l.int8 && l.rows_seen > 0 {
            assert!(l.error_written <= l.error_rounded, "{l:?}");
        }
    }
    let weights = if WeightType::Int8.native_on_this_cpu() {
        WeightType::Int8
    } else {
        WeightType::F32
    };
    let model = Arc::new(Model::load_with(&out, &LoadOptions { weights }).unwrap());
    assert!(x0(&model).iter().all(|v| v.is_finite()));
}

#[test]
fn latent_models_quantise_their_stack_and_their_decoder() {
    // MotionLCM v1 samples a latent as wide as its skip stack, so no layer is told apart by
    // width: all stay int8 but the decoder's last layer (263 motion features out). v2's latent
    // has 32 channels against 256 (tiny: 8 against 32): its three latent projections stay f32
    // as well. Every int8 layer saw calibration rows, the VAE decoder's too (the decode runs
    // after each calibration run). A control file's ControlNet and trajectory encoder record
    // too (each run is repeated following its own pelvis path); v2's keeps the ControlNet's
    // projections from and to the 32 channels as well.
    for (release, f32_layers) in [
        ("v1", &["vae.final_layer.weight"][..]),
        (
            "v2",
            &[
                "denoiser.latent_pre.weight",
                "denoiser.latent_post.weight",
                "vae.latent_post.weight",
                "vae.final_layer.weight",
            ][..],
        ),
        ("v1_control", &["vae.final_layer.weight"][..]),
        (
            "v2_control",
            &[
                "denoiser.latent_pre.weight",
                "denoiser.latent_post.weight",
                "vae.latent_post.weight",
                "vae.final_layer.weight",
                "controlnet.latent_pre.weight",
                "controlnet.controlnet_cond_embedding.0.weight",
                "controlnet.controlnet_cond_embedding.4.weight",
                "traj_encoder.latent_proj.weight",
            ][..],
        ),
    ] {
        let out = tmp(&format!("motionlcm_{release}.safetensors"));
        let opts = QuantizeOptions {
            frames: Some(24),
            steps: Some(1),
            ..small()
        };
        let r = quantize(
            &fixture(&format!("motionlcm_{release}_tiny.safetensors")),
            &out,
            &opts,
        )
        .unwrap();
        let kept: Vec<&str> = r
            .layers
            .iter()
            .filter(|l| !l.int8)
            .map(|l| l.tensor.as_str())
            .collect();
        let mut want = f32_layers.to_vec();
        want.sort_unstable();
        let mut got = kept.clone();
        got.sort_unstable();
        assert_eq!(got, want, "{release}");
        assert!(r
            .layers
            .iter()
            .any(|l| l.tensor.starts_with("vae.decoder.") && l.int8));
        if release.ends_with("control") {
            for part in ["controlnet.encoder.", "traj_encoder."] {
                assert!(r
                    .layers
                    .iter()
                    .any(|l| l.tensor.starts_with(part) && l.int8));
            }
        }
        for l in r.layers.iter().filter(|l| l.int8) {
            assert!(
                l.rows_seen > 0,
                "{release}: {} saw no calibration rows",
                l.tensor
            );
            assert!(l.error_written <= l.error_rounded, "{release}: {l:?}");
        }
        let weights = if WeightType::Int8.native_on_this_cpu() {
            WeightType::Int8
        } else {
            WeightType::F32
        };
        let model = Arc::new(Model::load_with(&out, &LoadOptions { weights }).unwrap());
        let mut s = Session::new(
            Arc::clone(&model),
            &SessionParams {
                frames: Some(24),
                steps: Some(1),
                threads: 1,
                ..Default::default()
            },
        )
        .unwrap();
        s.set_prompt("a person waves.").unwrap();
        s.run().unwrap();
        let (features, _) = s.motion(Which::Sample).unwrap();
        assert!(features.iter().all(|v| v.is_finite()), "{release}");
    }
}

#[test]
fn the_command_line_writes_a_file_that_generates() {
    let flame = env!("CARGO_BIN_EXE_flame");
    let out = tmp("cli.safetensors");
    let run = |args: &[&str]| {
        std::process::Command::new(flame)
            .args(args)
            .output()
            .unwrap()
    };
    let model = fixture("flame_tiny.safetensors");
    let model = model.to_str().unwrap();
    let q = run(&[
        "quantize",
        "--model",
        model,
        "--out",
        out.to_str().unwrap(),
        "--frames",
        "40",
        "--steps",
        "2",
        "--threads",
        "1",
        "--keep-f32",
        "tf_decoder.layers.0.linear1.weight",
    ]);
    assert!(q.status.success(), "{}", String::from_utf8_lossy(&q.stderr));
    let said = String::from_utf8_lossy(&q.stderr);
    assert!(
        said.contains("weights int8, 3 kept f32; 16 calibration runs"),
        "{said}"
    );
    // `flame generate` on a quantised file, with `extra` options.
    let generate = |model: &str, npy: &Path, extra: &[&str]| {
        let npy = npy.to_str().unwrap();
        let args = [
            "generate",
            "--model",
            model,
            "--prompt",
            "a person waves",
            "--frames",
            "40",
            "--steps",
            "2",
            "--out",
            npy,
        ];
        run(&[&args[..], extra].concat())
    };
    let npy = tmp("cli.npy");
    let g = generate(out.to_str().unwrap(), &npy, &[]);
    assert!(g.status.success(), "{}", String::from_utf8_lossy(&g.stderr));
    assert!(npy.is_file());
    let info = run(&["info", out.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(
        text.contains("quantised:") && text.contains("GPTQ"),
        "{text}"
    );
    // `--group`: the file runs as f16 by default, and `--weights int8` is refused.
    let grouped = tmp("cli_group.safetensors");
    let g = grouped.to_str().unwrap();
    let q = run(&[
        "quantize", "--model", model, "--out", g, "--frames", "40", "--steps", "2", "--group", "16",
    ]);
    assert!(q.status.success(), "{}", String::from_utf8_lossy(&q.stderr));
    let info = run(&["info", g]);
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(
        text.contains("\"group\":16") && text.contains("runs as f16"),
        "{text}"
    );
    let npy = tmp("cli_group.npy");
    let ok = generate(g, &npy, &[]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let refused = generate(g, &npy, &["--weights", "int8"]);
    assert!(!refused.status.success());
    let said = String::from_utf8_lossy(&refused.stderr);
    if WeightType::Int8.native_on_this_cpu() {
        assert!(said.contains("one scale per group of 16 inputs"), "{said}");
    }
    // A prompts file with no prompt is refused before any work.
    let empty = tmp("empty_prompts.txt");
    std::fs::write(&empty, "# only a comment\n\n").unwrap();
    let e = run(&[
        "quantize",
        "--model",
        model,
        "--out",
        tmp("never.safetensors").to_str().unwrap(),
        "--prompts",
        empty.to_str().unwrap(),
    ]);
    assert!(!e.status.success());
    let said = String::from_utf8_lossy(&e.stderr);
    assert!(said.contains("holds no prompt"), "{said}");
}
