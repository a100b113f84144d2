//! Fine-grained prompts: a motion as consecutive time stages, each with a text and a frame
//! count, and optionally a text per body part (the HuMMan-MoGen annotation's fields). FineMoGen
//! takes them; other families take one stage without part texts (a plain prompt).

use serde::Deserialize;

use crate::error::{invalid_arg, Result};

/// Body parts a stage may describe, in FineMoGen's group order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BodyPart {
    /// The head.
    Head = 0,
    /// The spine.
    Stem = 1,
    /// The left arm.
    LeftArm = 2,
    /// The right arm.
    RightArm = 3,
    /// The left leg.
    LeftLeg = 4,
    /// The right leg.
    RightLeg = 5,
    /// The root's trajectory.
    Pelvis = 6,
}

/// Number of [`BodyPart`]s.
pub const PART_COUNT: usize = 7;

impl BodyPart {
    /// Every part, in FineMoGen's group order: `BodyPart::ALL[p as usize] == p`.
    pub const ALL: [BodyPart; PART_COUNT] = [
        BodyPart::Head,
        BodyPart::Stem,
        BodyPart::LeftArm,
        BodyPart::RightArm,
        BodyPart::LeftLeg,
        BodyPart::RightLeg,
        BodyPart::Pelvis,
    ];

    /// The HuMMan-MoGen field name (`head`, `stem`, `left_arm`, …, `pelvis`).
    pub fn name(self) -> &'static str {
        [
            "head",
            "stem",
            "left_arm",
            "right_arm",
            "left_leg",
            "right_leg",
            "pelvis",
        ][self as usize]
    }
}

impl std::str::FromStr for BodyPart {
    type Err = crate::Error;
    fn from_str(s: &str) -> Result<BodyPart> {
        BodyPart::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                invalid_arg!(
                    "unknown body part `{s}` (expected {})",
                    BodyPart::ALL.map(|p| p.name()).join(", ")
                )
            })
    }
}

/// One time stage: what the whole body does for `frames` frames, and optionally what single
/// parts do (`parts[BodyPart as usize]`; `None` = the part follows `text`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Stage {
    /// What the whole body does.
    pub text: String,
    /// How many frames the stage lasts.
    pub frames: usize,
    /// Texts of single parts, indexed by `BodyPart as usize`; `None` = the part follows `text`.
    pub parts: [Option<String>; PART_COUNT],
}

impl Stage {
    /// A stage without part texts.
    pub fn new(text: impl Into<String>, frames: usize) -> Stage {
        Stage {
            text: text.into(),
            frames,
            parts: Default::default(),
        }
    }

    /// The stage with `part` described by `text`.
    pub fn with_part(mut self, part: BodyPart, text: impl Into<String>) -> Stage {
        self.parts[part as usize] = Some(text.into());
        self
    }

    /// Whether any part has its own text.
    pub fn has_parts(&self) -> bool {
        self.parts.iter().any(Option::is_some)
    }
}

/// Checks stages against a session of `frames` frames: at least one, none empty or of 0
/// frames, the counts summing to `frames`, no NUL or non-text in the texts.
pub fn check(stages: &[Stage], frames: usize) -> Result<()> {
    if stages.is_empty() {
        return Err(invalid_arg!("no stages: give at least one"));
    }
    let mut total = 0usize;
    for (i, s) in stages.iter().enumerate() {
        if s.frames == 0 {
            return Err(invalid_arg!("stage {i} has 0 frames"));
        }
        if s.text.trim().is_empty() {
            return Err(invalid_arg!("stage {i} has no text"));
        }
        total = total.saturating_add(s.frames);
    }
    if total != frames {
        return Err(invalid_arg!(
            "the stages cover {total} frames, the session has {frames}: their frame counts must add up to the session's"
        ));
    }
    Ok(())
}

/// One stage of a HuMMan-MoGen annotation.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileStage {
    start_frame: f64,
    end_frame: f64,
    #[serde(default)]
    num_frames: Option<f64>,
    all: String,
    #[serde(default)]
    head: Option<String>,
    #[serde(default)]
    stem: Option<String>,
    #[serde(default)]
    left_arm: Option<String>,
    #[serde(default)]
    right_arm: Option<String>,
    #[serde(default)]
    left_leg: Option<String>,
    #[serde(default)]
    right_leg: Option<String>,
    #[serde(default)]
    pelvis: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PromptFile {
    /// Frames per second the frame numbers count (the paper's annotations: 30).
    #[serde(default)]
    fps: Option<f64>,
    stages: Vec<FileStage>,
}

/// Reads a prompt file in the HuMMan-MoGen layout (`{"fps": 30, "stages": [{"start_frame",
/// "end_frame", "all", "head", …, "pelvis"}]}`; `end_frame` exclusive; `fps` defaults to
/// `model_fps`) into stages at `model_fps`. Stage boundaries are converted and rounded (half
/// away from zero), so the stages stay contiguous; they must start at frame 0 and follow each
/// other without gaps. Empty part texts count as absent.
pub fn from_prompt_file(text: &str, model_fps: f32) -> Result<Vec<Stage>> {
    let file: PromptFile = serde_json::from_str(text)
        .map_err(|e| invalid_arg!("prompt file: {e} (expected {{\"stages\": [{{\"start_frame\", \"end_frame\", \"all\", ...}}]}})"))?;
    let fps = file.fps.unwrap_or(model_fps as f64);
    if !(fps.is_finite() && fps > 0.0 && fps <= 1000.0) {
        return Err(invalid_arg!(
            "prompt file: fps must be above 0 and at most 1000, got {fps}"
        ));
    }
    if file.stages.is_empty() || file.stages.len() > 1024 {
        return Err(invalid_arg!(
            "prompt file: {} stages (1 to 1024)",
            file.stages.len()
        ));
    }
    let ratio = model_fps as f64 / fps;
    let mut out = Vec::with_capacity(file.stages.len());
    let mut expect = 0.0;
    for (i, s) in file.stages.into_iter().enumerate() {
        let ok = |v: f64| (0.0..=1e7).contains(&v) && v.fract() == 0.0;
        if !ok(s.start_frame) || !ok(s.end_frame) || s.end_frame <= s.start_frame {
            return Err(invalid_arg!(
                "prompt file: stage {i} runs from frame {} to {}: whole frame numbers, start < end",
                s.start_frame,
                s.end_frame
            ));
        }
        if s.start_frame != expect {
            return Err(invalid_arg!(
                "prompt file: stage {i} starts at frame {} but the previous stage ended at {expect}",
                s.start_frame
            ));
        }
        if let Some(n) = s.num_frames {
            if n != s.end_frame - s.start_frame {
                return Err(invalid_arg!(
                    "prompt file: stage {i} has num_frames {n} but runs {} frames",
                    s.end_frame - s.start_frame
                ));
            }
        }
        expect = s.end_frame;
        let (a, b) = (
            (s.start_frame * ratio).round() as usize,
            (s.end_frame * ratio).round() as usize,
        );
        if b == a {
            return Err(invalid_arg!(
                "prompt file: stage {i} ({} frames at {fps} fps) is shorter than one frame at {model_fps} fps",
                s.end_frame - s.start_frame
            ));
        }
        let part = |p: Option<String>| p.filter(|t| !t.trim().is_empty());
        out.push(Stage {
            text: s.all,
            frames: b - a,
            parts: [
                part(s.head),
                part(s.stem),
                part(s.left_arm),
                part(s.right_arm),
                part(s.left_leg),
                part(s.right_leg),
                part(s.pelvis),
            ],
        });
    }
    Ok(out)
}

/// Parses the CLI's `TEXT@FRAMES` (the last `@` splits).
pub fn parse_stage(spec: &str) -> Result<Stage> {
    let (text, frames) = spec
        .rsplit_once('@')
        .ok_or_else(|| invalid_arg!("stage `{spec}`: expected TEXT@FRAMES"))?;
    let frames: usize = frames
        .trim()
        .parse()
        .map_err(|_| invalid_arg!("stage `{spec}`: `{frames}` is not a frame count"))?;
    Ok(Stage::new(text.trim(), frames))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prompt_file_converts_30_to_20_fps_contiguously() {
        let text = r#"{"fps": 30, "stages": [
            {"start_frame": 0, "end_frame": 45, "num_frames": 45, "all": "a person walks",
             "head": "", "left_arm": "the left arm waves", "pelvis": "moves forward"},
            {"start_frame": 45, "end_frame": 100, "all": "then sits down"}]}"#;
        let s = from_prompt_file(text, 20.0).unwrap();
        // 0..45 → 0..30, 45..100 → 30..67 (66.67 rounds to 67).
        assert_eq!(s.iter().map(|s| s.frames).collect::<Vec<_>>(), [30, 37]);
        assert_eq!(
            s[0].parts[BodyPart::LeftArm as usize].as_deref(),
            Some("the left arm waves")
        );
        assert_eq!(s[0].parts[BodyPart::Head as usize], None);
        assert_eq!(
            s[0].parts[BodyPart::Pelvis as usize].as_deref(),
            Some("moves forward")
        );
        assert!(!s[1].has_parts());
    }

    #[test]
    fn bad_prompt_files_are_named() {
        let cases = [
            (r#"{"stages": []}"#, "0 stages"),
            (
                r#"{"stages": [{"start_frame": 5, "end_frame": 9, "all": "x"}]}"#,
                "starts at frame 5",
            ),
            (
                r#"{"stages": [{"start_frame": 0, "end_frame": 0, "all": "x"}]}"#,
                "start < end",
            ),
            (
                r#"{"stages": [{"start_frame": 0, "end_frame": 4, "all": "x", "nose": "y"}]}"#,
                "unknown field `nose`",
            ),
            (
                r#"{"fps": 0, "stages": [{"start_frame": 0, "end_frame": 4, "all": "x"}]}"#,
                "fps must be above 0 and at most 1000, got 0",
            ),
            (
                r#"{"fps": 1000, "stages": [{"start_frame": 0, "end_frame": 1, "all": "x"}]}"#,
                "shorter than one frame",
            ),
            (
                r#"{"stages": [{"start_frame": 0, "end_frame": 4, "num_frames": 3, "all": "x"}]}"#,
                "num_frames 3",
            ),
            ("not json", "prompt file"),
        ];
        for (text, want) in cases {
            let e = from_prompt_file(text, 20.0).unwrap_err().to_string();
            assert!(e.contains(want), "{text}: {e}");
        }
    }

    #[test]
    fn stages_must_cover_the_session() {
        let s = [Stage::new("walk", 40), Stage::new("jump", 20)];
        check(&s, 60).unwrap();
        assert!(check(&s, 61)
            .unwrap_err()
            .to_string()
            .contains("cover 60 frames"));
        assert!(check(&[Stage::new("walk", 0)], 0)
            .unwrap_err()
            .to_string()
            .contains("0 frames"));
        assert!(check(&[], 10)
            .unwrap_err()
            .to_string()
            .contains("no stages"));
        assert!(check(&[Stage::new(" ", 10)], 10)
            .unwrap_err()
            .to_string()
            .contains("no text"));
        assert_eq!(
            parse_stage("a person walks @ 120").unwrap(),
            Stage::new("a person walks", 120)
        );
        assert!(parse_stage("walk").is_err());
        assert!(parse_stage("walk@x").is_err());
        assert!("nose"
            .parse::<BodyPart>()
            .unwrap_err()
            .to_string()
            .contains("left_arm"));
    }
}
