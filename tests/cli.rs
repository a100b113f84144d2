//! The `flame` command line as a user meets it: help and version, usage errors (exit 2) with
//! suggestions, output paths checked before the model is loaded, upper-case extensions, folders
//! named as such, the BVH's default convention (Y up), the trained-action metadata of an
//! assembled model, glTF outputs and the two previews. Model:
//! tests/fixtures/flame_tiny.safetensors (random weights), and the demo model where assembled
//! (see tests/common) for the upright check.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;

use common::{demo_model, repo, split_denoiser_only};
use flame::motion::bvh;

fn flame(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .env_remove("FLAME_MODEL")
        .output()
        .unwrap()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A fresh, empty folder for one test.
fn scratch(test: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flame_cli_{}_{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn tiny() -> String {
    repo("tests/fixtures/flame_tiny.safetensors")
        .display()
        .to_string()
}

/// `flame generate` on `model` (2 steps, 16 frames, seed 3) with `extra` options.
fn generate_with(model: &str, prompt: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "generate",
        "--model",
        model,
        "--prompt",
        prompt,
        "--frames",
        "16",
        "--steps",
        "2",
        "--seed",
        "3",
        "--threads",
        "1",
    ];
    args.extend_from_slice(extra);
    flame(&args)
}

fn generate(extra: &[&str]) -> Output {
    generate_with(&tiny(), "a person walks", extra)
}

fn assert_ok(o: &Output) {
    assert!(o.status.success(), "{}", stderr(o));
}

fn files_in(d: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn help_on_every_subcommand_names_its_options() {
    let top = flame(&["--help"]);
    assert_ok(&top);
    for sub in ["generate", "edit", "stream", "info", "assemble"] {
        assert!(stdout(&top).contains(sub), "{}", stdout(&top));
    }
    let cases: [(&str, &[&str]); 5] = [
        (
            "generate",
            &[
                "--prompt",
                "--out",
                "--model",
                "--frames",
                "--steps",
                "--sampler",
                "--eta",
                "--guidance",
                "--seed",
                "--noise",
                "--threads",
                "--weights",
                "--convention",
                "--smooth",
                "--quat",
                "--positions",
                "--preview",
            ],
        ),
        (
            "edit",
            &[
                "--reference",
                "--prompt",
                "--out",
                "--task",
                "--keep-frames",
                "--keep-joints",
                "--method",
                "--edit-till",
                "--paste",
                "--seam-frames",
                "--reference-convention",
                "--steps",
                "--convention",
            ],
        ),
        (
            "stream",
            &[
                "--segment",
                "--chunk",
                "--overlap",
                "--out",
                "--model",
                "--steps",
                "--sampler",
                "--guidance",
                "--seed",
                "--threads",
                "--convention",
                "--smooth",
                "--quat",
                "--positions",
                "--preview",
            ],
        ),
        ("info", &["[MODEL]"]),
        (
            "assemble",
            &[
                "DENOISER.safetensors",
                "OUT.safetensors",
                "--actions",
                "--demo-actions",
            ],
        ),
    ];
    for (sub, options) in cases {
        for flag in ["--help", "-h"] {
            let o = flame(&[sub, flag]);
            assert_ok(&o);
            let text = stdout(&o);
            assert!(
                text.contains(&format!("Usage: flame {sub}")),
                "{sub} {flag}: {text}"
            );
            for opt in options {
                assert!(text.contains(opt), "{sub} {flag} lacks {opt}: {text}");
            }
        }
    }
    // The long help keeps the documentation of the writers and defaults.
    let long = stdout(&flame(&["generate", "--help"]));
    assert!(
        long.contains("default gltf") && long.contains("Euler ZXY"),
        "{long}"
    );
    let short = stdout(&flame(&["help", "edit"]));
    assert!(short.contains("--keep-frames"), "{short}");
}

#[test]
fn version_is_the_crate_version() {
    let o = flame(&["--version"]);
    assert_ok(&o);
    assert_eq!(stdout(&o), format!("flame {}\n", env!("CARGO_PKG_VERSION")));
    let sub = flame(&["info", "--version"]);
    assert_eq!(
        stdout(&sub),
        format!("flame-info {}\n", env!("CARGO_PKG_VERSION"))
    );
}

#[test]
fn usage_errors_exit_2_with_a_suggestion() {
    let o = flame(&["generate", "--promt", "a person walks", "--out", "x.bvh"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("unexpected argument '--promt'") && err.contains("'--prompt'"),
        "{err}"
    );
    let o = flame(&["generat"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("'generate'"), "{}", stderr(&o));
    // Named choices keep the library's message.
    let o = generate(&["--out", "x.bvh", "--sampler", "dpm"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("unknown sampler `dpm`"),
        "{}",
        stderr(&o)
    );
    // A missing required option.
    let o = flame(&["generate", "--out", "x.bvh"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("--prompt <TEXT>"), "{}", stderr(&o));
}

#[test]
fn outputs_into_a_missing_folder_fail_before_the_model_loads() {
    let d = scratch("missing");
    let missing = d.join("no-such-folder");
    let m = |name: &str| missing.join(name).display().to_string();
    let here = |name: &str| d.join(name).display().to_string();
    let cases = [
        vec!["--out".to_string(), m("x.bvh")],
        vec![
            "--out".into(),
            here("a.bvh"),
            "--preview".into(),
            m("p.png"),
        ],
        vec![
            "--out".into(),
            here("b.bvh"),
            "--positions".into(),
            m("p.npy"),
        ],
    ];
    for case in cases {
        let args: Vec<&str> = case.iter().map(String::as_str).collect();
        let o = generate(&args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        assert!(
            err.contains("cannot write") && err.contains("no-such-folder does not exist"),
            "{args:?}: {err}"
        );
        assert!(
            !err.contains("loaded "),
            "{args:?}: loaded the model first: {err}"
        );
    }
    // Nothing written: no --out file beside a refused --preview or --positions, no probe left.
    assert_eq!(files_in(&d), Vec::<String>::new());
    // A model that does not exist is not even looked at.
    let o = generate_with("/no/such/model.safetensors", "x", &["--out", &m("x.bvh")]);
    assert!(
        stderr(&o).contains("no-such-folder does not exist"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn folders_are_named_as_folders() {
    let d = scratch("folders");
    let dir = d.display().to_string();
    let o = generate(&["--out", &dir]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("is a folder"), "{}", stderr(&o));
    let folder_bvh = d.join("looks_like.bvh");
    std::fs::create_dir(&folder_bvh).unwrap();
    let o = generate(&["--out", folder_bvh.to_str().unwrap()]);
    assert!(
        stderr(&o).contains(&format!(
            "cannot write {}: it is a folder",
            folder_bvh.display()
        )),
        "{}",
        stderr(&o)
    );
    let o = flame(&["info", &dir]);
    assert_eq!(o.status.code(), Some(1));
    assert_eq!(
        stderr(&o),
        format!("flame: {dir} is a folder, not a model file\n")
    );
    // The library says the same (the C ABI's message, with status IO).
    let e = flame::models::Model::load(&d).err().unwrap();
    assert!(matches!(e, flame::Error::Io { .. }), "{e:?}");
    assert_eq!(
        e.to_string(),
        format!("cannot read {dir}: it is a folder, not a model file")
    );
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn upper_case_extensions_are_accepted() {
    let d = scratch("upper");
    let (bvh_path, npy, png) = (d.join("X.BVH"), d.join("P.Npy"), d.join("S.PNG"));
    let o = generate(&[
        "--out",
        bvh_path.to_str().unwrap(),
        "--positions",
        npy.to_str().unwrap(),
        "--preview",
        png.to_str().unwrap(),
    ]);
    assert_ok(&o);
    let text = std::fs::read_to_string(&bvh_path).unwrap();
    assert!(text.starts_with("HIERARCHY\nROOT Pelvis\n"), "{text:.40}");
    assert_eq!(flame::npy::read_f32(&npy).unwrap().0, vec![16, 24, 3]);
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn the_default_bvh_convention_is_gltf_and_native_stays_available() {
    let d = scratch("default");
    let path = |n: &str| d.join(n).display().to_string();
    assert_ok(&generate(&["--out", &path("default.bvh")]));
    assert_ok(&generate(&[
        "--out",
        &path("gltf.bvh"),
        "--convention",
        "gltf",
    ]));
    assert_ok(&generate(&[
        "--out",
        &path("native.bvh"),
        "--convention",
        "native",
    ]));
    let read = |n: &str| std::fs::read_to_string(d.join(n)).unwrap();
    assert_eq!(read("default.bvh"), read("gltf.bvh"));
    assert_ne!(read("default.bvh"), read("native.bvh"));
    // JSON keeps the model's own frame unless asked.
    assert_ok(&generate(&["--out", &path("m.json")]));
    let v: serde_json::Value = serde_json::from_str(&read("m.json")).unwrap();
    assert_eq!(v["convention"].as_str(), Some("native"));
    std::fs::remove_dir_all(&d).unwrap();
}

/// World joint positions of frame `t` of a BVH, posed the usual way (rotation channels composed
/// in the listed order, root position channels added to the root's offset).
fn bvh_positions(m: &bvh::BvhMotion, t: usize) -> Vec<(String, [f64; 3])> {
    type M = [[f64; 3]; 3];
    let mul = |a: &M, b: &M| -> M {
        let mut c = [[0.0; 3]; 3];
        for (r, row) in c.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|i| a[r][i] * b[i][k]).sum();
            }
        }
        c
    };
    let axis = |a: usize, deg: f64| -> M {
        let (s, c) = deg.to_radians().sin_cos();
        match a {
            0 => [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]],
            1 => [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
            _ => [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
        }
    };
    let values = m.frame(t).unwrap();
    let mut next = 0;
    let mut world: Vec<(M, [f64; 3])> = Vec::new();
    let mut out = Vec::new();
    for j in m.joints() {
        let mut rot: M = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let mut local = j.offset();
        for c in j.channels() {
            let v = values[next];
            next += 1;
            if c.is_rotation() {
                rot = mul(&rot, &axis(c.axis(), v));
            } else {
                local[c.axis()] += v;
            }
        }
        let (g, p) = match j.parent() {
            None => (rot, local),
            Some(parent) => {
                let (pg, pp) = world[parent];
                let d: Vec<f64> = (0..3)
                    .map(|r| (0..3).map(|k| pg[r][k] * local[k]).sum())
                    .collect();
                (mul(&pg, &rot), [pp[0] + d[0], pp[1] + d[1], pp[2] + d[2]])
            }
        };
        world.push((g, p));
        out.push((j.name().to_string(), p));
    }
    out
}

#[test]
fn a_default_bvh_of_the_demo_model_stands_up_along_y() {
    let Some(model) = demo_model() else {
        eprintln!("skipped: the demo model is not assembled (see tests/common)");
        return;
    };
    let d = scratch("upright");
    let out = d.join("walk.bvh");
    let o = generate_with(
        model.to_str().unwrap(),
        "a person walks forward",
        &["--out", out.to_str().unwrap()],
    );
    assert_ok(&o);
    let m = bvh::parse(&std::fs::read_to_string(&out).unwrap()).unwrap();
    for t in [0, m.frames() / 2, m.frames() - 1] {
        let p = bvh_positions(&m, t);
        let y = |name: &str| p.iter().find(|(n, _)| n == name).unwrap().1[1];
        // Head about 0.5 m above the pelvis in a standing SMPL body; native would put it on Z.
        assert!(
            y("Head") - y("Pelvis") > 0.35,
            "frame {t}: head y {} pelvis y {}",
            y("Head"),
            y("Pelvis")
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn assembled_actions_are_printed_and_checked_against_the_prompt() {
    let d = scratch("actions");
    let (den, text) = split_denoiser_only(&repo("tests/fixtures/flame_tiny.safetensors"), &d);
    let (den, text) = (den.display().to_string(), text.display().to_string());
    let demo = d.join("demo.safetensors").display().to_string();
    let o = flame(&["assemble", &den, &text, &demo, "--demo-actions"]);
    assert_ok(&o);
    let info = stdout(&flame(&["info", &demo]));
    let names: Vec<&str> = flame_demo::Family::ALL.iter().map(|f| f.name()).collect();
    assert!(
        info.contains(&format!("trained on:     {}\n", names.join(", "))),
        "{info}"
    );
    assert!(info.contains("trained on:     walk, run, jump, "), "{info}");

    let two = d.join("two.safetensors").display().to_string();
    assert_ok(&flame(&[
        "assemble",
        &den,
        &text,
        &two,
        "--actions",
        "walk,wave",
    ]));
    assert!(stdout(&flame(&["info", &two])).contains("trained on:     walk, wave\n"));
    let plain = d.join("plain.safetensors").display().to_string();
    assert_ok(&flame(&["assemble", &den, &text, &plain]));
    assert!(!stdout(&flame(&["info", &plain])).contains("trained on"));

    let bvh_out = d.join("m.bvh").display().to_string();
    let o = generate_with(&two, "a person plays the guitar", &["--out", &bvh_out]);
    assert_ok(&o);
    let notes: Vec<String> = stderr(&o)
        .lines()
        .filter(|l| l.starts_with("note:"))
        .map(str::to_string)
        .collect();
    assert_eq!(
        notes,
        vec![
            "note: this model knows only these actions: walk, wave; \"a person plays the guitar\" \
             names none of them, so expect one of them or standing still"
                .to_string()
        ]
    );
    for (model, prompt) in [
        (&two, "a woman is waving"),
        (&plain, "a person plays the guitar"),
    ] {
        let o = generate_with(model, prompt, &["--out", &bvh_out]);
        assert_ok(&o);
        assert!(!stderr(&o).contains("note:"), "{prompt}: {}", stderr(&o));
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn a_cut_prompt_is_reported_and_a_blank_one_is_unconditional() {
    let d = scratch("prompt_fit");
    let out = d.join("x.npy");
    let out = out.to_str().unwrap();
    // The tiny model's RoBERTa window is 20 tokens, <s> and </s> included.
    let long = "a person walks forward, turns left, raises both arms, waves with the right \
                hand, sits down on a chair and then kicks with the right leg";
    let o = generate_with(&tiny(), long, &["--out", out]);
    assert_ok(&o);
    let err = stderr(&o);
    let warning = err
        .lines()
        .find(|l| l.starts_with("warning: the prompt has"))
        .unwrap_or_else(|| panic!("no truncation warning in:\n{err}"));
    assert!(warning.contains("keeps its first 20"), "{warning}");
    assert!(warning.contains("kicks with the right leg\""), "{warning}");

    let o = generate_with(&tiny(), "a person walks", &["--out", out]);
    assert_ok(&o);
    assert!(
        !stderr(&o).contains("warning: the prompt"),
        "{}",
        stderr(&o)
    );

    let o = generate_with(&tiny(), "  ", &["--out", out]);
    assert_ok(&o);
    assert!(
        stderr(&o).contains("note: the prompt is empty: generating without a text condition"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn thread_counts_above_the_bound_are_refused() {
    let d = scratch("threads");
    let out = d.join("x.npy");
    let out = out.to_str().unwrap();
    let tiny = tiny();
    let run = |threads: &str| {
        flame(&[
            "generate",
            "--model",
            &tiny,
            "--prompt",
            "a person walks",
            "--frames",
            "16",
            "--steps",
            "2",
            "--threads",
            threads,
            "--out",
            out,
        ])
    };
    let o = run("257");
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("threads 257 is above the limit of 256"),
        "{}",
        stderr(&o)
    );
    assert!(!Path::new(out).exists(), "nothing written");
    assert_ok(&run("256"));
}

#[test]
fn latent_models_report_their_latent_and_the_frames_they_chose() {
    let mola = repo("tests/fixtures/mola_tiny.safetensors")
        .display()
        .to_string();
    let info = flame(&["info", &mola]);
    assert_ok(&info);
    let text = stdout(&info);
    assert!(text.contains("architecture:   mola\n"), "{text}");
    assert!(
        text.contains("sampled space:  latent of 50 rows x 16 channels for 196 frames"),
        "{text}"
    );
    assert!(text.contains("decoder:        MoLA VAE decoder"), "{text}");

    // 60 frames, 3 steps (generate_with's 16 frames would be 5 latent rows).
    let run = |extra: &[&str]| {
        let mut args = vec![
            "generate",
            "--model",
            &mola,
            "--prompt",
            "a person walks",
            "--frames",
            "60",
            "--steps",
            "3",
            "--seed",
            "3",
            "--threads",
            "1",
        ];
        args.extend_from_slice(extra);
        flame(&args)
    };
    let d = scratch("latent");
    let (out, latent) = (d.join("m.npy"), d.join("z.npy"));
    let o = run(&[
        "--out",
        out.to_str().unwrap(),
        "--latent",
        latent.to_str().unwrap(),
    ]);
    assert_ok(&o);
    let (zs, z) = flame::npy::read_f32(&latent).unwrap();
    assert_eq!(zs, vec![16, 16], "(60 + 4) // 4 latent rows of 16 channels");
    let (ms, _) = flame::npy::read_f32(&out).unwrap();
    assert_eq!(ms[1], 263);
    let note = format!(
        "{} frames (the length the model's decoder chose; 60 asked)",
        ms[0]
    );
    assert_eq!(stderr(&o).contains(&note), ms[0] != 60, "{}", stderr(&o));
    // The written latent goes back in as the initial noise; a wrong shape is refused.
    let o = run(&[
        "--noise",
        latent.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_ok(&o);
    flame::npy::write_f32(&latent, &[15, 16], &z[..15 * 16]).unwrap();
    let o = run(&[
        "--noise",
        latent.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("expected 256 (16 rows × 16)"),
        "{}",
        stderr(&o)
    );
    // --latent on a model that samples the motion itself.
    let o = generate(&[
        "--out",
        out.to_str().unwrap(),
        "--latent",
        latent.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("samples the motion itself"),
        "{}",
        stderr(&o)
    );
}

/// `--out x.glb|x.gltf`: the file is glTF 2.0 with the generation's metadata, its animation is
/// the motion `--positions` describes (root translation = the pelvis's position), and a glTF
/// always uses glTF's own convention.
#[test]
fn gltf_outputs_carry_the_motion_and_the_generation() {
    let d = scratch("gltf");
    let (glb, gltf, pos) = (d.join("x.glb"), d.join("x.GLTF"), d.join("p.npy"));
    let o = generate(&[
        "--out",
        glb.to_str().unwrap(),
        "--positions",
        pos.to_str().unwrap(),
    ]);
    assert_ok(&o);
    let bytes = std::fs::read(&glb).unwrap();
    assert_eq!(&bytes[..4], b"glTF");
    let jlen = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + jlen]).unwrap();
    let extras = &doc["asset"]["extras"];
    assert_eq!(extras["prompt"], "a person walks");
    assert_eq!(extras["model"], "flame_tiny.safetensors");
    assert_eq!(extras["seed"], 3);
    assert_eq!(extras["frames"], 16);
    assert_eq!(doc["animations"][0]["name"], "a_person_walks");
    assert_eq!(doc["nodes"][1]["name"], "Pelvis");
    // Root translation (sampler 0's output) = the pelvis's world position in the gltf convention.
    let bin = &bytes[20 + jlen + 8..];
    let acc = &doc["accessors"][doc["animations"][0]["samplers"][0]["output"]
        .as_u64()
        .unwrap() as usize];
    let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let off = view["byteOffset"].as_u64().unwrap() as usize;
    let root: Vec<f32> = bin[off..off + 16 * 12]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    let (shape, p) = flame::npy::read_f32(&pos).unwrap();
    assert_eq!(shape, [16, 24, 3]);
    for t in 0..16 {
        for k in 0..3 {
            assert!((root[t * 3 + k] - p[t * 72 + k]).abs() < 1e-6, "frame {t}");
        }
    }
    // The JSON container, upper-case extension; the same animation data.
    assert_ok(&generate(&["--out", gltf.to_str().unwrap()]));
    let doc2: serde_json::Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    assert_eq!(doc2["accessors"], doc["accessors"]);
    assert!(doc2["buffers"][0]["uri"]
        .as_str()
        .unwrap()
        .starts_with("data:application/octet-stream;base64,"));
    // Another convention is refused before the model loads; gltf is accepted.
    let o = generate(&["--out", glb.to_str().unwrap(), "--convention", "unity"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("always in glTF's own convention"),
        "{}",
        stderr(&o)
    );
    assert!(!stderr(&o).contains("loaded"), "{}", stderr(&o));
    assert_ok(&generate(&[
        "--out",
        glb.to_str().unwrap(),
        "--convention",
        "gltf",
    ]));
}

/// `--preview` twice writes a contact sheet and an animation; `--preview-fps` needs a GIF and a
/// rate the GIF can hold.
#[test]
fn previews_are_a_sheet_and_an_animation() {
    let d = scratch("previews");
    let (out, png, gif) = (d.join("x.bvh"), d.join("x.png"), d.join("x.gif"));
    let o = generate(&[
        "--out",
        out.to_str().unwrap(),
        "--preview",
        png.to_str().unwrap(),
        "--preview",
        gif.to_str().unwrap(),
        "--preview-fps",
        "10",
    ]);
    assert_ok(&o);
    assert_eq!(&std::fs::read(&png).unwrap()[..4], b"\x89PNG");
    let mut dec = gif::DecodeOptions::new();
    dec.set_color_output(gif::ColorOutput::Indexed);
    let mut r = dec.read_info(std::fs::File::open(&gif).unwrap()).unwrap();
    let mut frames = 0;
    while r.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    // 16 frames at 20 fps resampled to 10 fps: 8 frames.
    assert_eq!(frames, 8);
    let o = generate(&[
        "--out",
        out.to_str().unwrap(),
        "--preview",
        png.to_str().unwrap(),
        "--preview-fps",
        "10",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("--preview-fps needs --preview FILE.gif"),
        "{}",
        stderr(&o)
    );
    let o = generate(&[
        "--out",
        out.to_str().unwrap(),
        "--preview",
        d.join("x.apng").to_str().unwrap(),
    ]);
    assert!(
        stderr(&o).contains("--preview must end in .png"),
        "{}",
        stderr(&o)
    );
    let o = generate(&[
        "--out",
        out.to_str().unwrap(),
        "--preview",
        gif.to_str().unwrap(),
        "--preview-fps",
        "60",
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
}

/// `flame stream` on `model`: three segments of 50, 25 and 40 frames in chunks of 40 that keep
/// 10 (2 steps, seed 3), with `extra` options.
fn stream_with(model: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "stream",
        "--model",
        model,
        "--segment",
        "a person walks@50",
        "--segment",
        "then waves@25",
        "--segment",
        "sits down@40",
        "--steps",
        "2",
        "--chunk",
        "40",
        "--overlap",
        "10",
        "--seed",
        "3",
    ];
    args.extend_from_slice(extra);
    flame(&args)
}

/// `flame stream` writes the whole timeline in every format, the same bytes for every thread
/// count; bad segments and latent models are refused with their reason.
#[test]
fn stream_writes_the_whole_timeline() {
    let d = scratch("stream");
    let path = |name: &str| d.join(name).display().to_string();
    for fixture in ["flame_tiny", "mdm_tiny"] {
        let model = repo(&format!("tests/fixtures/{fixture}.safetensors"))
            .display()
            .to_string();
        let (npy, npy4) = (
            path(&format!("{fixture}.npy")),
            path(&format!("{fixture}_4.npy")),
        );
        let o = stream_with(&model, &["--threads", "1", "--out", &npy]);
        assert_ok(&o);
        assert_eq!(stdout(&o), format!("{npy}\n"));
        let err = stderr(&o);
        // One progress line per chunk: 40, 50 | 75 | 105, 115.
        for ready in [40, 50, 75, 105, 115] {
            assert!(
                err.contains(&format!("{ready}/115 frames ready")),
                "{fixture}: {err}"
            );
        }
        let (shape, x) = flame::npy::read_f32(Path::new(&npy)).unwrap();
        assert_eq!(shape[0], 115, "{fixture}: {shape:?}");
        assert!(x.iter().all(|v| v.is_finite()), "{fixture}");
        assert_ok(&stream_with(&model, &["--threads", "4", "--out", &npy4]));
        assert_eq!(
            std::fs::read(&npy).unwrap(),
            std::fs::read(&npy4).unwrap(),
            "{fixture}: --threads 1 and 4 differ"
        );

        let (bvh, glb, pos) = (
            path(&format!("{fixture}.bvh")),
            path(&format!("{fixture}.glb")),
            path(&format!("{fixture}_pos.npy")),
        );
        let o = stream_with(&model, &["--out", &bvh, "--positions", &pos]);
        assert_ok(&o);
        let text = std::fs::read_to_string(&bvh).unwrap();
        assert!(text.contains("Frames: 115\n"), "{fixture}");
        let (shape, _) = flame::npy::read_f32(Path::new(&pos)).unwrap();
        assert_eq!(shape[0], 115, "{fixture}: {shape:?}");
        assert_ok(&stream_with(&model, &["--out", &glb]));
        let bytes = std::fs::read(&glb).unwrap();
        assert_eq!(&bytes[..4], b"glTF", "{fixture}");
        let json = String::from_utf8_lossy(&bytes);
        assert!(
            json.contains("a person walks; then waves; sits down"),
            "{fixture}: the glTF names the segments"
        );
    }

    // Bad segments: no frame, no `@FRAMES`, no number; nothing is written.
    let tiny = tiny();
    let out = path("bad.npy");
    for (segment, message) in [
        ("x@0", "--segment `x@0`: a segment needs at least one frame"),
        ("x", "--segment `x`: expected TEXT@FRAMES"),
        ("x@two", "--segment `x@two`: `two` is not a frame count"),
    ] {
        let o = flame(&[
            "stream",
            "--model",
            &tiny,
            "--segment",
            segment,
            "--out",
            &out,
        ]);
        assert_eq!(o.status.code(), Some(1), "{segment}: {}", stderr(&o));
        assert!(stderr(&o).contains(message), "{segment}: {}", stderr(&o));
        assert!(!Path::new(&out).exists(), "{segment}: nothing written");
    }
    // No segment at all is a usage error.
    let o = flame(&["stream", "--model", &tiny, "--out", &out]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("--segment <TEXT@FRAMES>"),
        "{}",
        stderr(&o)
    );
    // An overlap that leaves no new frame in a chunk.
    let o = flame(&[
        "stream",
        "--model",
        &tiny,
        "--segment",
        "x@50",
        "--chunk",
        "10",
        "--overlap",
        "10",
        "--out",
        &out,
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("overlap 10 must be at least 1 and below the chunk's 10 frames"),
        "{}",
        stderr(&o)
    );
    // MLD can neither keep frames nor steer towards them.
    let mld = repo("tests/fixtures/mld_tiny.safetensors")
        .display()
        .to_string();
    let o = stream_with(&mld, &["--out", &out]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("gradient"), "{}", stderr(&o));
    assert!(!Path::new(&out).exists(), "nothing written");
    let _ = std::fs::remove_dir_all(&d);
}

/// `flame stream --prompt-file`: a HuMMan-MoGen file's stages are the timeline's segments, with
/// their part texts (FineMoGen reads them; FLAME refuses them with the reason).
#[test]
fn stream_takes_segments_with_part_texts_from_a_prompt_file() {
    let d = scratch("stream-prompt-file");
    let path = |n: &str| d.join(n).display().to_string();
    // 30 fps in the file: 0..30 → 20 frames, 30..75 → 30 frames at the model's 20 fps.
    let file = path("stages.json");
    std::fs::write(
        &file,
        r#"{"fps": 30, "stages": [
            {"start_frame": 0, "end_frame": 30, "all": "a person walks forward."},
            {"start_frame": 30, "end_frame": 75, "all": "a person waves.",
             "right_arm": "the right arm swings up and down."}]}"#,
    )
    .unwrap();
    let fmg = repo("tests/fixtures/finemogen_tiny.safetensors")
        .display()
        .to_string();
    let out = path("fmg.npy");
    let args = [
        "stream",
        "--model",
        &fmg,
        "--prompt-file",
        &file,
        "--steps",
        "2",
        "--chunk",
        "30",
        "--overlap",
        "8",
        "--out",
        &out,
    ];
    assert_ok(&flame(&args));
    let (shape, x) = flame::npy::read_f32(Path::new(&out)).unwrap();
    assert_eq!(shape, vec![50, 263]);
    assert!(x.iter().all(|v| v.is_finite()));
    // FLAME takes no part texts: the second segment's chunk says so.
    let tiny = tiny();
    let bad = path("flame.npy");
    let mut args = args.to_vec();
    args[2] = &tiny;
    args[12] = &bad;
    let o = flame(&args);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("part"), "{}", stderr(&o));
    assert!(!Path::new(&bad).exists(), "nothing written");
    // --segment and --prompt-file exclude each other.
    let o = flame(&[
        "stream",
        "--model",
        &tiny,
        "--segment",
        "x@10",
        "--prompt-file",
        &file,
        "--out",
        &bad,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&d);
}

/// The latent model at `model` run through the library: `frames` frames, `steps` steps (the
/// model's default when `None`), `seed`, the prompt, then `setup` (a control, a task); the
/// decoded features, to compare with what the CLI wrote.
fn library_motion(
    model: &str,
    frames: usize,
    steps: Option<usize>,
    seed: u64,
    prompt: &str,
    setup: impl FnOnce(&mut flame::session::Session),
) -> Vec<f32> {
    let model = std::sync::Arc::new(flame::models::Model::load(model).unwrap());
    let params = flame::session::SessionParams {
        frames: Some(frames),
        steps,
        seed,
        ..Default::default()
    };
    let mut s = flame::session::Session::new(model, &params).unwrap();
    s.set_prompt(prompt).unwrap();
    setup(&mut s);
    s.run().unwrap();
    s.motion(flame::session::Which::Sample).unwrap().0.to_vec()
}

/// `flame generate` on a MotionLCM file: the file's sampler (lcm) and v2's guidance for the step
/// count, a step count the release has no table for refused with the counts it has, and
/// `flame info` naming the T5 text encoder. A stream is refused (MLD's VAE has no gradient).
#[test]
fn motionlcm_generates_in_its_step_counts() {
    let d = scratch("motionlcm");
    let path = |n: &str| d.join(n).display().to_string();
    let v2 = repo("tests/fixtures/motionlcm_v2_tiny.safetensors")
        .display()
        .to_string();
    let out = path("m.npy");
    let generate = |steps: &str, out: &str| {
        flame(&[
            "generate",
            "--model",
            &v2,
            "--prompt",
            "a person walks forward and waves.",
            "--steps",
            steps,
            "--frames",
            "24",
            "--seed",
            "3",
            "--out",
            out,
        ])
    };
    assert_ok(&generate("2", &out));
    let (shape, x) = flame::npy::read_f32(Path::new(&out)).unwrap();
    assert_eq!(shape, vec![24, 263]);
    assert!(x.iter().all(|v| v.is_finite()));
    // The same run through the library: same bits.
    let features = library_motion(
        &v2,
        24,
        Some(2),
        3,
        "a person walks forward and waves.",
        |_| {},
    );
    assert_eq!(features, x);
    let bad = path("bad.npy");
    let o = generate("3", &bad);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("no 3-step schedule here; it samples 1, 2, 4 steps"),
        "{}",
        stderr(&o)
    );
    assert!(!Path::new(&bad).exists(), "nothing written");
    let info = stdout(&flame(&["info", &v2]));
    assert!(info.contains("architecture:   motionlcm"), "{info}");
    assert!(
        info.contains("text encoder:   t5 v1.0 + sentence head"),
        "{info}"
    );
    let o = flame(&[
        "stream",
        "--model",
        &v2,
        "--segment",
        "walk@30",
        "--out",
        &bad,
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("gradient"), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&d);
}

/// `flame generate --control`: a MotionLCM control file follows a pelvis path (the same bits
/// as the library's `Session::set_control_values`), with `--optimize` the tuned latent's (the
/// library's `Session::tune_latent`); files without a ControlNet, hints of the wrong joint
/// count and tuning a 2-step run are refused before sampling.
#[test]
fn motionlcm_control_follows_a_pelvis_path() {
    let d = scratch("motionlcm-control");
    let path = |n: &str| d.join(n).display().to_string();
    let control = repo("tests/fixtures/motionlcm_v2_control_tiny.safetensors")
        .display()
        .to_string();
    // A pelvis path (HumanML3D's native frame: Y up, metres) on every frame; the rest free.
    let mut hint = vec![f32::NAN; 24 * 22 * 3];
    for f in 0..24 {
        hint[f * 66..f * 66 + 3].copy_from_slice(&[0.05 * f as f32, 0.9, 0.02 * f as f32]);
    }
    let hint_path = path("hint.npy");
    flame::npy::write_f32(Path::new(&hint_path), &[24, 22, 3], &hint).unwrap();
    let run = |model: &str, extra: &[&str], out: &str| {
        let mut args = vec![
            "generate",
            "--model",
            model,
            "--prompt",
            "a person walks forward",
            "--frames",
            "24",
            "--seed",
            "5",
            "--convention",
            "native",
            "--out",
            out,
        ];
        args.extend_from_slice(extra);
        flame(&args)
    };
    let with = path("with.npy");
    assert_ok(&run(&control, &["--control", &hint_path], &with));
    let without = path("without.npy");
    assert_ok(&run(&control, &[], &without));
    let (_, a) = flame::npy::read_f32(Path::new(&with)).unwrap();
    let (_, b) = flame::npy::read_f32(Path::new(&without)).unwrap();
    assert!(a.iter().all(|v| v.is_finite()));
    assert_ne!(a, b, "the control changes the motion");
    let features = library_motion(&control, 24, None, 5, "a person walks forward", |s| {
        s.set_control_values(&hint, None, flame::motion::Convention::Native)
            .unwrap()
    });
    assert_eq!(features, a, "the CLI's bits are the library's");
    // Consistency latent tuning first: the library's bits too, and the hint followed closer.
    let tuned = path("tuned.npy");
    let o = run(
        &control,
        &["--control", &hint_path, "--optimize", "20", "--steps", "1"],
        &tuned,
    );
    assert_ok(&o);
    assert!(
        stderr(&o).contains("latent tuning: 20 iterations"),
        "{}",
        stderr(&o)
    );
    let (_, t) = flame::npy::read_f32(Path::new(&tuned)).unwrap();
    let mut report = None;
    let features = library_motion(&control, 24, Some(1), 5, "a person walks forward", |s| {
        s.set_control_values(&hint, None, flame::motion::Convention::Native)
            .unwrap();
        report = Some(
            s.tune_latent(&flame::tuning::TuningParams::new(20))
                .unwrap(),
        );
    });
    assert_eq!(features, t, "the CLI's bits are the library's");
    let r = report.unwrap();
    assert!(r.control_error[1] < r.control_error[0], "{r:?}");
    let o = run(
        &control,
        &["--control", &hint_path, "--optimize", "5", "--steps", "2"],
        &path("bad.npy"),
    );
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("1-step sampler"), "{}", stderr(&o));
    let o = run(&control, &["--optimize", "5"], &path("bad.npy"));
    assert_eq!(o.status.code(), Some(2), "clap: --optimize needs --control");
    // A file without a ControlNet.
    let plain = repo("tests/fixtures/motionlcm_v2_tiny.safetensors")
        .display()
        .to_string();
    let bad = path("bad.npy");
    let o = run(&plain, &["--control", &hint_path], &bad);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("no trajectory ControlNet"),
        "{}",
        stderr(&o)
    );
    // The wrong joint count.
    let short = path("short.npy");
    flame::npy::write_f32(Path::new(&short), &[24, 21, 3], &hint[..24 * 63]).unwrap();
    let o = run(&control, &["--control", &short], &bad);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("expected [frames, 22, 3]"),
        "{}",
        stderr(&o)
    );
    assert!(!Path::new(&bad).exists(), "nothing written");
    let _ = std::fs::remove_dir_all(&d);
}

/// `flame edit` on a MotionLCM control file: the task's kept joints become the ControlNet's
/// hint (the same bits as the library's `Session::set_task_targets`); `--method mpgd` (position
/// guidance, which needs a decoder gradient) and a file without a ControlNet are refused.
#[test]
fn motionlcm_control_files_edit_through_the_control_net() {
    let d = scratch("motionlcm-edit");
    let path = |n: &str| d.join(n).display().to_string();
    let control = repo("tests/fixtures/motionlcm_v2_control_tiny.safetensors")
        .display()
        .to_string();
    let prompt = "a person walks forward and waves.";
    let reference = path("ref.npy");
    assert_ok(&flame(&[
        "generate", "--model", &control, "--prompt", prompt, "--steps", "2", "--frames", "24",
        "--seed", "1", "--out", &reference,
    ]));
    let edit = |model: &str, out: &str, more: &[&str]| {
        let mut args = vec![
            "edit",
            "--model",
            model,
            "--reference",
            &reference,
            "--task",
            "predict",
            "--prompt",
            "then jumps.",
            "--steps",
            "2",
            "--frames",
            "24",
            "--seed",
            "3",
            "--out",
            out,
        ];
        args.extend_from_slice(more);
        flame(&args)
    };
    let out = path("edited.npy");
    let o = edit(&control, &out, &[]);
    assert_ok(&o);
    assert!(
        stderr(&o).contains("trajectory ControlNet"),
        "{}",
        stderr(&o)
    );
    let (_, edited) = flame::npy::read_f32(Path::new(&out)).unwrap();
    let (_, ref_features) = flame::npy::read_f32(Path::new(&reference)).unwrap();
    let features = library_motion(&control, 24, Some(2), 3, "then jumps.", |s| {
        s.set_task_targets(&ref_features, flame::motion::Task::Predict)
            .unwrap()
    });
    assert_eq!(features, edited);
    let bad = path("bad.npy");
    let o = edit(&control, &bad, &["--method", "mpgd"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("gradient"), "{}", stderr(&o));
    let plain = repo("tests/fixtures/motionlcm_v2_tiny.safetensors")
        .display()
        .to_string();
    let o = edit(&plain, &bad, &[]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("gradient"), "{}", stderr(&o));
    assert!(!Path::new(&bad).exists(), "nothing written");
    let _ = std::fs::remove_dir_all(&d);
}
