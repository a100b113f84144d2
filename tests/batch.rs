//! `flame batch` against `flame generate`: every output of a batch is the same bytes as the
//! same job run alone by `flame generate` (each job also run here, one process per job, with
//! the command-line options the job's keys stand for); bad input (a malformed line, an unknown
//! key, a missing folder, a duplicate output) is reported in the manifest and at the end while
//! the other jobs run; `--resume` skips what is done; `--prompts` with `--seeds`; a cancelled
//! run leaves only whole outputs. Models: tests/fixtures/flame_tiny.safetensors (random
//! weights, smpl24_6d) and finemogen_tiny.safetensors (time stages).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;

mod common;

use common::repo;
use flame::batch::{self, RunOptions, Runner, Status};

fn flame(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flame"))
        .args(args)
        .env_remove("FLAME_MODEL")
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn scratch(test: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flame_batch_{}_{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn fixture(name: &str) -> String {
    repo(&format!("tests/fixtures/{name}"))
        .display()
        .to_string()
}

fn manifest(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The manifest's record of job `key`.
fn record<'a>(m: &'a [serde_json::Value], key: &str) -> &'a serde_json::Value {
    m.iter()
        .find(|r| r["job"] == key)
        .unwrap_or_else(|| panic!("no record of job {key} in {m:?}"))
}

/// A job as a JSONL line and as the `flame generate` options it stands for.
struct Case {
    json: String,
    args: Vec<String>,
    outputs: Vec<PathBuf>,
}

fn case(dir: &Path, name: &str, keys: &[(&str, &str)], out: &str, extra: &[(&str, &str)]) -> Case {
    let out = dir.join(format!("{name}.{out}"));
    let mut json = serde_json::Map::new();
    json.insert("out".into(), out.display().to_string().into());
    let mut args = vec!["--out".to_string(), out.display().to_string()];
    let mut outputs = vec![out];
    for (k, v) in keys.iter().chain(extra) {
        let flag = format!("--{}", k.replace('_', "-"));
        match *k {
            "positions" => {
                let p = dir.join(format!("{name}.{v}"));
                json.insert("positions".into(), p.display().to_string().into());
                args.extend([flag, p.display().to_string()]);
                outputs.push(p);
            }
            "stages" => {
                let stages: Vec<&str> = v.split('|').collect();
                json.insert("stages".into(), stages.clone().into());
                for s in stages {
                    args.extend(["--stage".to_string(), s.to_string()]);
                }
            }
            "remove_yaw" => {
                json.insert("remove_yaw".into(), true.into());
                args.push(flag);
            }
            "ground" => {
                json.insert("ground".into(), (*v == "on").into());
                args.extend([flag, v.to_string()]);
            }
            _ => {
                let value: serde_json::Value =
                    serde_json::from_str(v).unwrap_or_else(|_| v.to_string().into());
                json.insert(k.to_string(), value);
                args.extend([flag, v.to_string()]);
            }
        }
    }
    Case {
        json: serde_json::Value::Object(json).to_string(),
        args,
        outputs,
    }
}

/// Runs every case with `flame generate` into `alone/` and compares each batch output with it.
fn assert_same_as_generate(model: &str, cases: &[Case], dir: &Path) {
    let alone = dir.join("alone");
    std::fs::create_dir_all(&alone).unwrap();
    for c in cases {
        let mut args = vec!["generate", "--model", model];
        let moved: Vec<String> = c
            .args
            .iter()
            .map(|a| a.replace(&dir.display().to_string(), &alone.display().to_string()))
            .collect();
        args.extend(moved.iter().map(String::as_str));
        let o = flame(&args);
        assert!(o.status.success(), "{args:?}: {}", stderr(&o));
        for out in &c.outputs {
            let twin = alone.join(out.file_name().unwrap());
            let (got, want) = (std::fs::read(out).unwrap(), std::fs::read(&twin).unwrap());
            assert!(
                got == want,
                "{} differs from flame generate's",
                out.display()
            );
        }
    }
}

/// A job's name, its keys (`key`, value as on the command line) and its output's extension.
type Spec<'a> = (&'a str, Vec<(&'a str, &'a str)>, &'a str);

#[test]
fn every_output_is_the_bytes_flame_generate_writes() {
    let dir = scratch("same");
    let model = fixture("flame_tiny.safetensors");
    let base = [("frames", "16"), ("steps", "3")];
    let specs: Vec<Spec> = vec![
        (
            "walk",
            vec![("prompt", "a person walks"), ("seed", "1")],
            "bvh",
        ),
        (
            "json",
            vec![
                ("prompt", "a person waves"),
                ("seed", "2"),
                ("quat", "xyzw"),
                ("convention", "unity"),
                ("fps", "30"),
            ],
            "json",
        ),
        (
            "glb",
            vec![
                ("prompt", "a person jumps"),
                ("seed", "3"),
                ("positions", "pos.npy"),
                ("root_motion", "in-place"),
                ("remove_yaw", ""),
            ],
            "glb",
        ),
        (
            "gltf",
            vec![
                ("prompt", "kicks"),
                ("seed", "4"),
                ("feet", "off"),
                ("guidance", "2.5"),
            ],
            "gltf",
        ),
        (
            "feat",
            vec![("prompt", "a person runs"), ("seed", "5")],
            "npy",
        ),
        (
            "amass",
            vec![
                ("prompt", "a person bows"),
                ("amass", "smplx"),
                ("ground", "off"),
            ],
            "npz",
        ),
        (
            "ddim",
            vec![
                ("prompt", ""),
                ("seed", "7"),
                ("sampler", "ddim"),
                ("smooth", "0"),
                ("contact_height", "0.1"),
            ],
            "bvh",
        ),
    ];
    let cases: Vec<Case> = specs
        .iter()
        .map(|(name, keys, ext)| case(&dir, name, keys, ext, &base))
        .collect();
    let jobs = dir.join("jobs.jsonl");
    let text: Vec<&str> = cases.iter().map(|c| c.json.as_str()).collect();
    std::fs::write(&jobs, text.join("\n")).unwrap();
    let o = flame(&[
        "batch",
        "--model",
        &model,
        "--jobs",
        jobs.to_str().unwrap(),
        "--workers",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("7 written, 0 failed"), "{}", stderr(&o));
    let m = manifest(&dir.join("jobs.jsonl.manifest.jsonl"));
    assert_eq!(m.len(), 7);
    for (i, c) in cases.iter().enumerate() {
        let r = record(&m, &(i + 1).to_string());
        assert_eq!(r["status"], "ok");
        assert_eq!(r["line"], i + 1);
        let outs: Vec<String> = c.outputs.iter().map(|p| p.display().to_string()).collect();
        assert_eq!(r["outputs"], serde_json::json!(outs));
    }
    // The blank prompt runs unconditionally, and the manifest says so.
    assert_eq!(record(&m, "7")["prompt"]["unconditional"], true);
    assert_eq!(record(&m, "1")["prompt"]["unconditional"], false);
    assert_same_as_generate(&model, &cases, &dir);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn time_stages_match_flame_generate_too() {
    let dir = scratch("stages");
    let model = fixture("finemogen_tiny.safetensors");
    let cases = vec![
        case(
            &dir,
            "two",
            &[("stages", "a person walks@8|waves@8"), ("seed", "2")],
            "bvh",
            &[("steps", "2")],
        ),
        case(
            &dir,
            "one",
            &[("prompt", "a person jumps"), ("frames", "12")],
            "npy",
            &[("steps", "2")],
        ),
    ];
    let jobs = dir.join("jobs.jsonl");
    std::fs::write(&jobs, format!("{}\n{}\n", cases[0].json, cases[1].json)).unwrap();
    let o = flame(&["batch", "--model", &model, "--jobs", jobs.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_same_as_generate(&model, &cases, &dir);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_jobs_are_reported_and_the_others_run() {
    let dir = scratch("bad");
    let model = fixture("flame_tiny.safetensors");
    let good = dir.join("good.bvh");
    let lines = [
        format!(
            "{{\"prompt\": \"walks\", \"out\": \"{}\", \"frames\": 8, \"steps\": 2}}",
            good.display()
        ),
        "{\"prompt\": \"walks\", \"out\": ".to_string(),
        format!(
            "{{\"prompt\": \"walks\", \"out\": \"{}\", \"step\": 2}}",
            dir.join("u.bvh").display()
        ),
        format!(
            "{{\"prompt\": \"walks\", \"out\": \"{}\"}}",
            dir.join("nowhere/m.bvh").display()
        ),
        format!(
            "{{\"prompt\": \"runs\", \"out\": \"{}/./good.bvh\"}}",
            dir.display()
        ),
        format!(
            "{{\"prompt\": \"runs\", \"out\": \"{}\", \"frames\": 100000}}",
            dir.join("long.bvh").display()
        ),
    ];
    let jobs = dir.join("jobs.jsonl");
    std::fs::write(&jobs, lines.join("\n")).unwrap();
    let manifest_path = dir.join("m.jsonl");
    let o = flame(&[
        "batch",
        "--model",
        &model,
        "--jobs",
        jobs.to_str().unwrap(),
        "--manifest",
        manifest_path.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("1 written, 5 failed"), "{err}");
    assert!(err.contains("flame: 5 of 6 jobs not written"), "{err}");
    let m = manifest(&manifest_path);
    assert_eq!(m.len(), 6);
    assert_eq!(record(&m, "1")["status"], "ok");
    assert!(good.is_file());
    let expect = [
        ("2", "line 2: EOF while parsing a value at column 26"),
        ("3", "line 3: unknown field `step`, expected one of"),
        ("4", "the folder"),
        ("5", "is also an output of job 1"),
        (
            "6",
            "line 6: `frames` must be between 1 and 470 for this model, got 100000",
        ),
    ];
    for (key, msg) in expect {
        let r = record(&m, key);
        assert_eq!(r["status"], "failed");
        let e = r["error"].as_str().unwrap();
        assert!(e.contains(msg), "job {key}: {e}");
        assert!(err.contains(&format!("failed: {e}")), "{err}");
    }
    assert!(record(&m, "4")["error"]
        .as_str()
        .unwrap()
        .ends_with("nowhere does not exist"));
    assert!(!dir.join("u.bvh").exists() && !dir.join("long.bvh").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn resume_runs_only_what_is_not_done() {
    let dir = scratch("resume");
    let model = fixture("flame_tiny.safetensors");
    let lines: Vec<String> = (0..3)
        .map(|i| {
            format!(
                "{{\"id\": \"j{i}\", \"prompt\": \"walks\", \"seed\": {i}, \"out\": \"{}\", \
                 \"frames\": 8, \"steps\": 2}}",
                dir.join(format!("{i}.bvh")).display()
            )
        })
        .collect();
    let jobs = dir.join("jobs.jsonl");
    std::fs::write(&jobs, lines.join("\n")).unwrap();
    let run = |resume: bool| {
        let mut args = vec!["batch", "--model", &model, "--jobs", jobs.to_str().unwrap()];
        if resume {
            args.push("--resume");
        }
        let o = flame(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        stderr(&o)
    };
    run(false);
    let first = std::fs::read(dir.join("1.bvh")).unwrap();
    std::fs::remove_file(dir.join("1.bvh")).unwrap();
    let err = run(true);
    assert!(err.contains("1 written, 0 failed, 2 skipped"), "{err}");
    assert_eq!(std::fs::read(dir.join("1.bvh")).unwrap(), first);
    let m = manifest(&dir.join("jobs.jsonl.manifest.jsonl"));
    let keys: Vec<&str> = m.iter().map(|r| r["job"].as_str().unwrap()).collect();
    assert_eq!(keys.len(), 4, "3 records, then j1 again: {keys:?}");
    assert_eq!(keys[3], "j1");
    // Without --resume the manifest starts afresh and every job runs.
    let err = run(false);
    assert!(err.contains("3 written, 0 failed, 0 skipped"), "{err}");
    assert_eq!(manifest(&dir.join("jobs.jsonl.manifest.jsonl")).len(), 3);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn prompts_times_seeds_are_generate_runs() {
    let dir = scratch("prompts");
    let model = fixture("flame_tiny.safetensors");
    let prompts = dir.join("prompts.txt");
    std::fs::write(&prompts, "a person walks\n\n# a comment\na person waves\n").unwrap();
    let pattern = format!("{}/p{{line}}_s{{seed}}.bvh", dir.display());
    let o = flame(&[
        "batch",
        "--model",
        &model,
        "--prompts",
        prompts.to_str().unwrap(),
        "--seeds",
        "2",
        "--out-pattern",
        &pattern,
        "--defaults",
        "{\"frames\": 8, \"steps\": 2}",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for (line, prompt) in [(1, "a person walks"), (4, "a person waves")] {
        for seed in 0..2 {
            let got = dir.join(format!("p{line}_s{seed}.bvh"));
            let want = dir.join("alone.bvh");
            let o = flame(&[
                "generate",
                "--model",
                &model,
                "--prompt",
                prompt,
                "--seed",
                &seed.to_string(),
                "--frames",
                "8",
                "--steps",
                "2",
                "--out",
                want.to_str().unwrap(),
            ]);
            assert!(o.status.success(), "{}", stderr(&o));
            assert!(
                std::fs::read(&got).unwrap() == std::fs::read(&want).unwrap(),
                "{line}:{seed}"
            );
        }
    }
    let m = manifest(&dir.join("prompts.txt.manifest.jsonl"));
    assert_eq!(m.len(), 4);
    assert_eq!(record(&m, "4:1")["line"], 4);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Cancelled after the first record: whatever ran wrote whole files (the same bytes as an
/// uncancelled run), nothing else is there, no temporary file is left, and every job is counted.
#[test]
fn a_cancelled_run_leaves_only_whole_outputs() {
    let dir = scratch("cancel");
    let file =
        flame::checkpoint::ModelFile::open(Path::new(&fixture("flame_tiny.safetensors"))).unwrap();
    let model = Arc::new(flame::models::Model::from_file(file).unwrap());
    let text: Vec<String> = (0..6)
        .map(|i| {
            format!(
                "{{\"prompt\": \"walks\", \"seed\": {i}, \"out\": \"{i}.bvh\", \"frames\": 16, \
                 \"steps\": 40}}"
            )
        })
        .collect();
    let jobs = batch::parse_jobs(&text.join("\n"), None).unwrap();
    let opts = |sub: &str| {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
        RunOptions {
            manifest: dir.join(sub).join("m.jsonl"),
            base_dir: dir.join(sub),
            workers: 1,
            threads: 1,
            resume: false,
            model_name: "tiny".into(),
        }
    };
    let whole = Runner::new(Arc::clone(&model))
        .run(&jobs, &opts("whole"), &mut |_, _| {})
        .unwrap();
    assert_eq!(whole.ok, 6);
    let runner = Runner::new(model);
    let flag = runner.cancel_flag();
    let mut seen = Vec::new();
    let s = runner
        .run(&jobs, &opts("cut"), &mut |r, _| {
            seen.push(r.status);
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        })
        .unwrap();
    assert_eq!(seen[0], Status::Ok);
    assert!(s.not_run >= 4, "{s:?}");
    assert_eq!(s.ok + s.cancelled + s.not_run, 6, "{s:?}");
    let mut names: Vec<String> = std::fs::read_dir(dir.join("cut"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names.len(),
        s.ok + 1,
        "outputs and the manifest only: {names:?}"
    );
    for n in names.iter().filter(|n| n.ends_with(".bvh")) {
        let got = std::fs::read(dir.join("cut").join(n)).unwrap();
        assert!(
            got == std::fs::read(dir.join("whole").join(n)).unwrap(),
            "{n}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Ctrl-C (SIGINT) once the first job is recorded: the run stops, and whatever it wrote is
/// whole (the bytes of an uninterrupted run), recorded `ok` in the manifest, with no temporary
/// file left. Should every job finish before the signal lands, the same holds of all of them.
#[cfg(unix)]
#[test]
fn ctrl_c_leaves_only_whole_recorded_outputs() {
    let dir = scratch("sigint");
    let model = fixture("flame_tiny.safetensors");
    let jobs_text: Vec<String> = (0..12)
        .map(|i| {
            format!(
                "{{\"prompt\": \"walks\", \"seed\": {i}, \"out\": \"{i}.bvh\", \"frames\": 120, \
                 \"steps\": 100}}"
            )
        })
        .collect();
    for sub in ["whole", "cut"] {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
        std::fs::write(dir.join(sub).join("jobs.jsonl"), jobs_text.join("\n")).unwrap();
    }
    let run = |sub: &str| {
        Command::new(env!("CARGO_BIN_EXE_flame"))
            .args([
                "batch",
                "--model",
                &model,
                "--jobs",
                "jobs.jsonl",
                "--workers",
                "1",
            ])
            .current_dir(dir.join(sub))
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    assert!(run("whole").wait().unwrap().success());
    let mut child = run("cut");
    let manifest = dir.join("cut/jobs.jsonl.manifest.jsonl");
    // Waits for the first record (the handler is in place by then); a bounded wait, not a
    // timing assertion.
    for _ in 0..6000 {
        let started = std::fs::read_to_string(&manifest).is_ok_and(|t| !t.is_empty());
        if started || child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let _ = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status();
    let out = child.wait_with_output().unwrap();
    let err = stderr(&out);
    let m = manifest_records(&manifest);
    let ok: Vec<&serde_json::Value> = m.iter().filter(|r| r["status"] == "ok").collect();
    if out.status.success() {
        assert_eq!(ok.len(), 12, "{err}");
    } else {
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains("not written"), "{err}");
    }
    let mut names: Vec<String> = std::fs::read_dir(dir.join("cut"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".bvh") || n.starts_with('.'))
        .collect();
    names.sort();
    let mut recorded: Vec<String> = ok
        .iter()
        .map(|r| r["outputs"][0].as_str().unwrap().to_string())
        .collect();
    recorded.sort();
    assert_eq!(
        names, recorded,
        "every file is a recorded output; no temporary file"
    );
    for n in &names {
        let got = std::fs::read(dir.join("cut").join(n)).unwrap();
        assert!(
            got == std::fs::read(dir.join("whole").join(n)).unwrap(),
            "{n}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The manifest's lines, an empty list when there is none.
fn manifest_records(path: &Path) -> Vec<serde_json::Value> {
    if path.is_file() {
        manifest(path)
    } else {
        Vec::new()
    }
}
