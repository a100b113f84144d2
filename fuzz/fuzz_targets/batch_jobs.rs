//! A `flame batch` jobs file (text, lossy UTF-8): `batch::parse_jobs` with and without
//! defaults, and the same text as a prompts file through `batch::jobs_from_prompts`. Every
//! non-blank line becomes one entry, in order, with its line number; a job that parses
//! serialises back to a line that parses to the same job; names are never empty.
#![no_main]

use flame::batch::{self, Job};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let lines = text.lines().count();
    let blank = text.lines().filter(|l| l.trim().is_empty()).count();
    let defaults: serde_json::Map<String, serde_json::Value> =
        serde_json::from_str(r#"{"steps": 2, "feet": "off", "seed": 3}"#).unwrap();
    for d in [None, Some(&defaults)] {
        let entries = batch::parse_jobs(&text, d).expect("far fewer lines than the bound");
        assert_eq!(entries.len(), lines - blank);
        for pair in entries.windows(2) {
            assert!(pair[0].line < pair[1].line);
        }
        for e in &entries {
            assert!(e.line >= 1 && e.line <= lines);
            assert!(!e.key.is_empty());
            match &e.job {
                Ok(job) => {
                    let again = serde_json::to_string(job).unwrap();
                    let back = batch::parse_jobs(&again, None).unwrap();
                    assert_eq!(back.len(), 1);
                    // f32 values go through f64 when read, so only the rest must match exactly.
                    let without_f32 = |j: &Job| Job {
                        eta: None,
                        guidance: None,
                        smooth: None,
                        ..j.clone()
                    };
                    let got = without_f32(back[0].job.as_ref().unwrap());
                    assert_eq!(got, without_f32(job));
                }
                Err(msg) => assert!(msg.starts_with(&format!("line {}: ", e.line))),
            }
        }
    }
    let prompts = batch::jobs_from_prompts(&text, 2, "o/{line}_{seed}_{n}.bvh", &Job::default())
        .expect("seeds is not 0");
    assert!(prompts.len() <= 2 * lines);
    for (i, e) in prompts.iter().enumerate() {
        let job = e.job.as_ref().unwrap();
        assert_eq!(job.seed, i as u64 % 2);
        let want = format!("o/{}_{}_{}.bvh", e.line, job.seed, i + 1);
        assert_eq!(job.out.as_deref(), Some(std::path::Path::new(&want)));
    }
});
