//! Continuous motion from a timeline of prompts: a [`Stream`] generates chunk after chunk, each
//! one an edit that keeps the last `overlap` frames of what came before (the family's own
//! editing algorithm, with its exact paste and blended seam) and generates the rest from the
//! prompt of the segment it belongs to. The caller pushes segments at any time, moves the
//! playhead, spends a bounded number of denoiser steps per [`Stream::pump`], and reads frames.
//!
//! # The timeline
//!
//! Segments follow each other on one timeline of frames: segment `i` covers `frames_i` frames
//! from where segment `i − 1` ended. A chunk never spans two segments: it takes at most
//! `chunk − overlap` new frames of one segment (`chunk` for the first chunk, which has nothing to
//! keep). [`Stream::interrupt`] ends the current segment where the chunk being generated ends
//! (or at the frames ready, when none is), so the next segment starts at that chunk boundary
//! without waiting for the rest of the current one.
//!
//! # Root motion
//!
//! Every chunk is generated in a canonical frame: the kept frames are moved so that the first
//! of them stands at the horizontal origin facing the format's native forward, and the chunk is
//! moved back after. For `smpl24_6d` (absolute root translation and root rotation) this is a
//! linear map of the root channels in the format's units (a rotation about the world up axis
//! and a horizontal shift; a normalised model's channels are de-normalised around it); `humanml263` features are already relative to the root's heading and position, so
//! its chunks need no change and its root path integrates across seams by itself. Each chunk's
//! root path therefore starts where the previous one ended, in translation and heading.
//!
//! # Determinism
//!
//! A chunk's content depends only on the timeline (segments and interrupt positions), the
//! kept frames and its seed (the stream's seed mixed with the chunk's index), never on how the
//! work was spread over `pump` calls or on the thread count: the same segments pushed at the
//! same frame positions give bit-identical frames.
//!
//! # Window
//!
//! Frames older than `window` frames before the playhead are dropped; reading them is an
//! error naming the window, as is reading frames not generated yet (a status, never a wait).
//!
//! # Cleanup
//!
//! [`Stream::read_cleaned`] reads frames after the hand-over post-processing
//! ([`Finish`]: contacts, floor, foot locking, root motion, frame rate), consistent across chunk
//! seams: a frame handed out never changes, and reading frame `t` alone gives the bits reading
//! the whole timeline gives. The cleanup is set once ([`Stream::set_finish`], before frame 0 is
//! dropped; the C ABI's first cleaned read sets it), so a frame's cleaned pose never depends on
//! which ranges were read or when. Cleaned frames are made incrementally, each exactly once,
//! and cached ("settled"): after every [`Stream::pump`] and before every cleaned read, the
//! frames whose cleanup can no longer change are cleaned and kept; later frames are
//! [`Error::WrongState`] ("not settled yet: pump more"), like frames not generated yet.
//!
//! - **Contacts** (smpl24_6d, detected) are followed from frame 0 exactly as
//!   [`crate::motion::contacts`] detects them on a whole clip: the hysteresis state carries
//!   over from frame to frame; a frame's raw contact waits for the next frame (the speed's
//!   central difference); the minimum span's gap closing and span dropping are decided per
//!   slot as soon as the gap or span is long enough or has ended. humanml263's own contacts
//!   are final at once.
//! - **Floor**: the detection floor (the lowest foot joint) and the contact floor (the lowest
//!   contact point, which `ground` puts at 0 and locking keeps feet above) cannot come from a
//!   whole clip: both are the first chunk's, as if it were a clip on its own, fixed for the
//!   stream. A later frame may go below it (the floor is not re-fitted).
//! - **Feet** (lock): a frame settles when its contact span has ended (its pins are the span's
//!   means); a frame in a swing when the next span has ended (the swing is redrawn pin to pin)
//!   and every span whose [`feet::FADE_SECONDS`] fade reaches it has ended. Each settle runs
//!   [`feet`]'s lock over a working window from the start of the spans the first unsettled
//!   frame depends on to the last frame whose contacts are final, and keeps only the frames
//!   before the horizon: those get the bits the whole clip's lock gives them.
//! - **Root motion**: per frame; `remove_yaw` turns every frame to frame 0's heading.
//! - **Frame rate**: cleaned frames are indexed at the cleanup's rate: cleaned frame `k` is at
//!   `k / fps` seconds of the timeline (timeline frame `t` at `t / model fps`), resampled from
//!   settled frames only ([`resample`]'s exact arithmetic: frames on a source frame's time are
//!   its bits). Without `fps`, cleaned frame `k` is timeline frame `k`.
//! - **Loop wrap** joins a clip's end to its start: a stream has no end, so it is refused. A
//!   looping timeline is generated instead ([`Stream::close_looped`]: a bridge from the
//!   timeline's end into its first frames), so no frame handed out has to change.
//! - **End**: [`Stream::close`] declares the timeline complete; once its frames are generated,
//!   every frame settles (the last spans and swings end with the timeline, as a clip's do).
//!   Without it the stream cannot know a span at the newest frame is the last.
//!
//! **Latency** (frames generated but not settled yet): with contacts only (no locking), one
//! frame plus the minimum span (2 frames at 20 fps) at most. With locking, until the newest
//! contact span and the swing before it have ended: on the demo model (chunks of 120 frames
//! keeping 20, a walk then a jump, game-ready cleanup) 28, 34 and 21 frames after each chunk
//! landed, at most 1.7 s at 20 fps (`tests/stream_cleaned.rs`); an engine keeps that much more
//! lookahead. A leg that stays in the air (never planted) holds its frames back until a span
//! ends or the stream is closed: the whole-clip cleanup treats a swing before its first span,
//! and a leg never planted, differently, and only the future tells which it is.
//!
//! Memory: settled frames behind the window are dropped with the held ones; the held frames a
//! settle still reads (back to the start of the spans the first unsettled frame depends on)
//! are kept past the window until settled. Bit-for-bit equality with a whole read assumes no
//! humanml263 frame was dropped before its settle (dropping re-anchors the root path, as for
//! raw reads).
//!
//! [`Stream`]: crate::stream::Stream
//! [`Stream::pump`]: crate::stream::Stream::pump
//! [`Stream::interrupt`]: crate::stream::Stream::interrupt
//! [`Stream::read_cleaned`]: crate::stream::Stream::read_cleaned
//! [`Finish`]: crate::motion::Finish
//! [`Stream::set_finish`]: crate::stream::Stream::set_finish
//! [`feet::FADE_SECONDS`]: crate::motion::feet::FADE_SECONDS
//! [`feet`]: crate::motion::feet
//! [`resample`]: crate::motion::resample
//! [`Stream::close_looped`]: crate::stream::Stream::close_looped
//! [`Stream::close`]: crate::stream::Stream::close

use std::collections::VecDeque;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use crate::error::{invalid_arg, Error, Result};
use crate::models::{Condition, Model};
use crate::motion::humanml263::RootStart;
use crate::motion::{contacts, feet, resample, root_motion};
use crate::motion::{Convention, Feet, Finish, Format, Layout, Poses, RootMotion};
use crate::session::{Session, SessionParams, Which};
use crate::stages::{Stage, PART_COUNT};
use crate::targets::PositionTargets;
use crate::text::PromptInfo;

/// One prompt on the timeline, how many frames it lasts and, for families that read them
/// (FineMoGen), what single body parts do (`parts[BodyPart as usize]`, `None` = the part
/// follows `prompt`). Other families refuse part texts when the segment's first chunk starts.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Segment {
    /// What the whole body does during the segment.
    pub prompt: String,
    /// How many frames the segment lasts.
    pub frames: usize,
    /// Texts of single parts, indexed by `BodyPart as usize`; `None` = the part follows
    /// `prompt`.
    pub parts: [Option<String>; PART_COUNT],
}

impl Segment {
    /// A segment of `frames` frames with one prompt for the whole body.
    pub fn new(prompt: impl Into<String>, frames: usize) -> Segment {
        Segment {
            prompt: prompt.into(),
            frames,
            parts: Default::default(),
        }
    }

    /// The segment a time stage describes (its text, frames and part texts).
    pub fn from_stage(stage: Stage) -> Segment {
        Segment {
            prompt: stage.text,
            frames: stage.frames,
            parts: stage.parts,
        }
    }

    fn has_parts(&self) -> bool {
        self.parts.iter().any(Option::is_some)
    }

    fn check(&self) -> Result<()> {
        if self.frames == 0 {
            return Err(invalid_arg!("a segment needs at least one frame"));
        }
        if self.parts.iter().flatten().any(|t| t.trim().is_empty()) {
            return Err(invalid_arg!(
                "a segment's part text is empty: leave the part out (None) to have it follow \
                 the segment's prompt"
            ));
        }
        Ok(())
    }
}

/// How a stream generates.
#[derive(Clone, Debug)]
pub struct StreamParams {
    /// Frames per chunk (kept + new); 0 = the model's default frame count (at most its maximum).
    pub chunk: usize,
    /// Frames of the previous chunk each chunk keeps (default 20, 1 s at 20 fps).
    pub overlap: usize,
    /// Frames the stream keeps ready ahead of the playhead: `pump` generates while fewer are.
    pub lookahead: usize,
    /// Frames kept behind the playhead; older ones are dropped.
    pub window: usize,
    /// Steps, sampler, guidance, threads and seed of every chunk (`frames` is the stream's).
    pub session: SessionParams,
}

impl Default for StreamParams {
    fn default() -> Self {
        StreamParams {
            chunk: 0,
            overlap: 20,
            lookahead: 60,
            window: 1200,
            session: SessionParams::default(),
        }
    }
}

/// What a [`Stream::pump`] did and where the stream stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PumpReport {
    /// Denoiser steps run by this call.
    pub steps: usize,
    /// Frames generated so far on the timeline (frames `0..ready` exist, minus the dropped).
    pub ready: usize,
    /// Fewer than `lookahead` frames are ready ahead of the playhead and no segment is left to
    /// generate them from.
    pub starving: bool,
}

/// A chunk being generated.
struct Chunk {
    session: Session,
    /// Timeline frame of the chunk's first frame (kept frames first).
    start: usize,
    /// Frames kept from before.
    kept: usize,
    /// The canonical frame's change for `smpl24_6d` (identity otherwise).
    frame: Rebase,
    /// Which pass of a loop's bridge this chunk is, if it is one.
    bridge: Option<Bridge>,
}

/// The two passes of a looped timeline's bridge ([`Stream::close_looped`]), as a loop clip's
/// are ([`crate::cycle`]): a probe continues the timeline `frames` + the lead frames to see
/// where the motion goes after the bridge (heading and horizontal position: the loop's root
/// motion `T`); the final pass keeps the timeline's last frames at its start and the
/// timeline's first frames moved by `T` at its end, and generates the bridge between.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Bridge {
    Probe,
    Final,
}

/// Seconds of the timeline's start kept at a bridge's end (as [`crate::cycle::LEAD_SECONDS`]).
const BRIDGE_LEAD_SECONDS: f64 = crate::cycle::LEAD_SECONDS;

/// A heading change about the world up axis and a horizontal shift, applied to the root
/// channels of absolute formats.
#[derive(Clone, Copy, Debug)]
struct Rebase {
    cos: f64,
    sin: f64,
    shift: [f64; 2],
}

impl Rebase {
    const IDENTITY: Rebase = Rebase {
        cos: 1.0,
        sin: 0.0,
        shift: [0.0; 2],
    };

    /// The change that takes `row`'s root to the horizontal origin, facing the native forward
    /// (−Y; `smpl24_6d` only: Z up, translation in channels 0..3, root rotation rows in 3..9).
    fn canonical(row: &[f32]) -> Rebase {
        // Forward = the root rotation's third column (body +Z); its horizontal direction is
        // (R[0][2], R[1][2]) = channels 5 and 8.
        let (fx, fy) = (row[5] as f64, row[8] as f64);
        let heading = fy.atan2(fx);
        let target = -std::f64::consts::FRAC_PI_2;
        let (sin, cos) = if fx.hypot(fy) > 1e-9 {
            (target - heading).sin_cos()
        } else {
            (0.0, 1.0)
        };
        let (x, y) = (row[0] as f64, row[1] as f64);
        // p' = Rz (p − c): shift = −Rz c.
        Rebase {
            cos,
            sin,
            shift: [-(cos * x - sin * y), -(sin * x + cos * y)],
        }
    }

    fn inverse(&self) -> Rebase {
        // p = Rzᵀ (p' − shift).
        let (c, s) = (self.cos, -self.sin);
        let (x, y) = (-self.shift[0], -self.shift[1]);
        Rebase {
            cos: c,
            sin: s,
            shift: [c * x - s * y, s * x + c * y],
        }
    }

    /// Applies the change to the root channels of `smpl24_6d` rows.
    fn apply(&self, rows: &mut [f32], dim: usize) {
        let (c, s) = (self.cos, self.sin);
        for row in rows.chunks_exact_mut(dim) {
            let (x, y) = (row[0] as f64, row[1] as f64);
            row[0] = (c * x - s * y + self.shift[0]) as f32;
            row[1] = (s * x + c * y + self.shift[1]) as f32;
            // Root rotation R' = Rz·R: rows 0 and 1 mix, row 2 stays (6D holds rows 0 and 1).
            for k in 0..3 {
                let (a, b) = (row[3 + k] as f64, row[6 + k] as f64);
                row[3 + k] = (c * a - s * b) as f32;
                row[6 + k] = (s * a + c * b) as f32;
            }
        }
    }
}

/// A motion that goes on as long as segments come (see the module doc).
pub struct Stream {
    model: Arc<Model>,
    params: StreamParams,
    chunk: usize,
    /// Pushed segments not yet fully generated, with the frames of each already generated.
    segments: VecDeque<(Segment, usize)>,
    /// Model-space features of timeline frames `first..ready`, in the stream's own frame.
    features: Vec<f32>,
    first: usize,
    playhead: usize,
    /// Chunks finished so far (the next chunk's seed index).
    chunks: u64,
    current: Option<Chunk>,
    /// Where the root path of the held frames starts (relative formats, once frames were
    /// dropped).
    anchor: RootStart,
    /// The held frames decoded, kept until they change: an engine reads every frame, and a
    /// relative format's root path has to be integrated from the window's start.
    decoded: std::cell::RefCell<Option<Arc<Poses>>>,
    /// Raised by another thread to abandon the step being run (every chunk's session shares it).
    cancel: Arc<AtomicBool>,
    /// Quaternion tracks of the held frames (see [`QuatTracks`]).
    quats: std::cell::RefCell<QuatTracks>,
    /// The cleanup of [`Stream::read_cleaned`], once set.
    cleanup: Option<Cleanup>,
    /// No segment comes after the pushed ones ([`Stream::close`]).
    closed: bool,
    /// Where the first chunk ended (the cleanup's floors come from its frames).
    first_chunk: Option<usize>,
    /// A looped close: the bridge's frames, once [`Stream::close_looped`] asked for one.
    bridge: Option<usize>,
    /// The timeline's first [`Stream::bridge_lead`] frames, kept for the bridge's end (in the
    /// stream's frame; captured before any frame is dropped).
    start_rows: Vec<f32>,
    /// After a finished bridge: the frame after the timeline's last, the first frame of the
    /// next cycle (the timeline's frame 0 moved by the loop's root motion).
    loop_end: Option<Vec<f32>>,
    /// The prompt of the last segment generated (a bridge's).
    last_prompt: String,
    /// The last plain prompt a chunk encoded, with its condition and report: the next chunk of
    /// the same segment reuses them (a prompt is the same condition every time, and a large
    /// text encoder such as MotionLCM's T5-large costs as much as the chunk's sampling).
    encoded: Option<(String, Condition, Option<PromptInfo>)>,
}

/// Sign-continuous quaternion tracks of the held frames, one per (local or world rotations,
/// convention), made on first read and dropped when the held frames change. Each track's
/// quaternions at the first held frame are kept (the anchor), so its signs never depend on how
/// the frames were read: a track made again after frames were appended or dropped continues
/// from the same signs (an engine reading one frame per tick gets the track a whole read gives).
#[derive(Default)]
struct QuatTracks {
    tracks: [Option<Arc<Vec<[f64; 4]>>>; 12],
    anchors: [Option<Vec<[f64; 4]>>; 12],
}

/// The slot of a quaternion track.
fn track_slot(world: bool, convention: Convention) -> usize {
    let c = Convention::ALL
        .iter()
        .position(|&k| k == convention)
        .expect("every convention is in ALL");
    usize::from(world) * Convention::ALL.len() + c
}

impl Stream {
    /// A stream over `model`. Fails when the model cannot continue a motion (a latent model
    /// whose decoder has no gradient, such as MLD's: latent models continue through position
    /// targets), or when the chunk and overlap do not fit its frame range.
    pub fn new(model: Arc<Model>, params: &StreamParams) -> Result<Stream> {
        // A latent model continues through its trajectory ControlNet, else position targets.
        if model.is_latent() && !model.denoiser().takes_control() {
            crate::targets::supported(&model).map_err(|e| {
                invalid_arg!(
                    "a stream continues each chunk from the frames before it; this {} model \
                     samples a latent, so it can only steer towards them with position targets \
                     or a trajectory ControlNet (a MotionLCM control file), and {}",
                    model.config().architecture,
                    e.to_string().trim_start_matches("invalid argument: ")
                )
            })?;
        }
        let max = model.max_frames();
        let chunk = match params.chunk {
            0 => model.config().defaults.frames.min(max),
            c => c,
        };
        if chunk > max {
            return Err(invalid_arg!(
                "chunk of {chunk} frames exceeds the model's {max}"
            ));
        }
        if params.overlap == 0 || params.overlap >= chunk {
            return Err(invalid_arg!(
                "overlap {} must be at least 1 and below the chunk's {chunk} frames",
                params.overlap
            ));
        }
        if params.session.frames.is_some() {
            return Err(invalid_arg!(
                "a stream's chunks set their own frame counts: leave the session parameters' frame count unset"
            ));
        }
        // Validate the rest of the session parameters now, not at the first chunk.
        let probe = SessionParams {
            frames: Some(chunk),
            ..params.session.clone()
        };
        Session::new(Arc::clone(&model), &probe)?;
        Ok(Stream {
            model,
            params: params.clone(),
            chunk,
            segments: VecDeque::new(),
            features: Vec::new(),
            first: 0,
            playhead: 0,
            chunks: 0,
            encoded: None,
            current: None,
            anchor: RootStart::ORIGIN,
            decoded: Default::default(),
            cancel: Arc::new(AtomicBool::new(false)),
            quats: Default::default(),
            cleanup: None,
            closed: false,
            first_chunk: None,
            bridge: None,
            start_rows: Vec::new(),
            loop_end: None,
            last_prompt: String::new(),
        })
    }

    /// A flag another thread may raise to abandon the step a [`Stream::pump`] is running: the
    /// pump returns [`Error::Cancelled`] within one transformer layer and the stream is as it
    /// was before that step, so pumping again gives the bits of a stream never cancelled. A
    /// flag raised between pumps cancels the next step.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.cancel)
    }

    /// The model the stream generates with.
    pub fn model(&self) -> &Arc<Model> {
        &self.model
    }

    /// Frames per chunk.
    pub fn chunk_frames(&self) -> usize {
        self.chunk
    }

    /// Appends a segment to the timeline.
    pub fn push(&mut self, segment: Segment) -> Result<()> {
        self.check_open()?;
        segment.check()?;
        self.segments.push_back((segment, 0));
        Ok(())
    }

    /// Ends the current segment at the next chunk boundary (the end of the chunk being
    /// generated, or the frames ready when none is), drops the segments queued after it and
    /// pushes `segment` in their place.
    pub fn interrupt(&mut self, segment: Segment) -> Result<()> {
        self.check_open()?;
        segment.check()?;
        let in_flight = self
            .current
            .as_ref()
            .map_or(0, |c| c.session.frames() - c.kept);
        // The current segment ends with the frames generated or in flight; the queued ones
        // after it are replaced by `segment`.
        self.segments.truncate(1);
        if let Some((seg, done)) = self.segments.front_mut() {
            let end = *done + in_flight;
            if end == 0 {
                self.segments.clear();
            } else {
                seg.frames = end.min(seg.frames);
            }
        }
        self.segments.push_back((segment, 0));
        Ok(())
    }

    fn check_open(&self) -> Result<()> {
        if self.closed {
            return Err(Error::WrongState(
                "the stream was closed: its timeline takes no more segments".into(),
            ));
        }
        Ok(())
    }

    /// Moves the playhead (the frame being played); frames more than `window` before it are
    /// dropped.
    pub fn set_playhead(&mut self, frame: usize) -> Result<()> {
        if frame > self.ready() {
            return Err(invalid_arg!(
                "playhead {frame} is past the {} frames generated",
                self.ready()
            ));
        }
        self.playhead = frame;
        self.drop_old()?;
        Ok(())
    }

    /// The frame being played, as last set by [`Stream::set_playhead`] (0 at the start).
    pub fn playhead(&self) -> usize {
        self.playhead
    }

    /// Frames generated on the timeline so far.
    pub fn ready(&self) -> usize {
        self.first + self.features.len() / self.model.motion_dim()
    }

    /// The first frame still held (older ones were dropped).
    pub fn first_frame(&self) -> usize {
        self.first
    }

    /// Runs at most `max_steps` denoiser steps towards `lookahead` frames ahead of the
    /// playhead, starting chunks as segments allow.
    pub fn pump(&mut self, max_steps: usize) -> Result<PumpReport> {
        let mut steps = 0;
        while steps < max_steps {
            if self.current.is_none() {
                if self.ready() >= self.playhead + self.params.lookahead {
                    break;
                }
                if !self.start_chunk()? {
                    break;
                }
            }
            let chunk = self.current.as_mut().expect("started above");
            let left = chunk.session.step()?;
            steps += 1;
            if left == 0 {
                self.finish_chunk()?;
            }
        }
        // Settled as frames come, whether or not cleaned frames are read, so the frames a
        // settle needs are never held longer than that.
        self.settle()?;
        Ok(self.report(steps))
    }

    fn report(&self, steps: usize) -> PumpReport {
        let short = self.ready() < self.playhead + self.params.lookahead;
        PumpReport {
            steps,
            ready: self.ready(),
            starving: short && self.current.is_none() && self.segments.is_empty(),
        }
    }

    /// Starts the next chunk of the first unfinished segment; `false` when there is none.
    fn start_chunk(&mut self) -> Result<bool> {
        while self
            .segments
            .front()
            .is_some_and(|(s, done)| *done >= s.frames)
        {
            self.segments.pop_front();
        }
        let Some((seg, done)) = self.segments.front() else {
            return match self.bridge {
                Some(frames) if self.loop_end.is_none() => self.start_bridge(frames, Bridge::Probe),
                _ => Ok(false),
            };
        };
        let dim = self.model.motion_dim();
        let have = self.features.len() / dim;
        let kept = self.params.overlap.min(have);
        let new = (seg.frames - done).min(self.chunk - kept);
        let frames = kept + new;
        let mut session = self.chunk_session(frames)?;
        if seg.has_parts() {
            session.set_prompt_stages(&[Stage {
                text: seg.prompt.clone(),
                frames,
                parts: seg.parts.clone(),
            }])?;
        } else {
            match &self.encoded {
                Some((prompt, cond, info)) if *prompt == seg.prompt => {
                    session.take_prompt(&self.model, Some((cond.clone(), info.clone())))?;
                }
                _ => {
                    session.set_prompt(&seg.prompt)?;
                    self.encoded = session
                        .encoded_prompt()
                        .map(|(cond, info)| (seg.prompt.clone(), cond, info));
                }
            }
        }
        let mut frame = Rebase::IDENTITY;
        if kept > 0 && self.model.is_latent() {
            // A latent cannot keep frames: the chunk is steered towards the kept frames' joint
            // positions (through the model's trajectory ControlNet when it has one, MotionLCM's
            // temporal control; else the family's position targets, MoLA's MPGD), and only its
            // new frames are appended. humanml263 decodes from the canonical start, as the
            // chunk does.
            let reference = &self.features[(have - kept) * dim..];
            let format = self.model.motion_format();
            let poses =
                Poses::decode(format, reference, kept, &self.model.read_options(0.0, true))?;
            let values: Vec<f32> = poses
                .positions(Convention::Native)
                .iter()
                .flatten()
                .map(|&v| v as f32)
                .collect();
            let targets = PositionTargets::new(format, &values, None, Convention::Native)?;
            if self.model.denoiser().takes_control() {
                session.set_control(&targets)?;
            } else {
                session.set_position_targets(targets)?;
            }
        } else if kept > 0 {
            let mut reference = self.features[(have - kept) * dim..].to_vec();
            frame = self.to_canonical(&mut reference);
            session.set_reference(&reference)?;
            let mut keep = vec![false; frames * dim];
            keep[..kept * dim].fill(true);
            session.set_keep(keep)?;
        }
        self.current = Some(Chunk {
            session,
            start: self.ready() - kept,
            kept,
            frame,
            bridge: None,
        });
        Ok(true)
    }

    /// The session of the next chunk: `frames` frames, the chunk's seed, the stream's cancel
    /// flag.
    fn chunk_session(&self, frames: usize) -> Result<Session> {
        let params = SessionParams {
            frames: Some(frames),
            seed: chunk_seed(self.params.session.seed, self.chunks),
            ..self.params.session.clone()
        };
        let mut session = Session::new(Arc::clone(&self.model), &params)?;
        session.share_cancel_flag(Arc::clone(&self.cancel));
        Ok(session)
    }

    /// Frames of the timeline's start a bridge keeps at its end.
    fn bridge_lead(&self) -> usize {
        let fps = self.model.config().motion.fps as f64;
        ((BRIDGE_LEAD_SECONDS * fps).round() as usize).max(2)
    }

    /// Starts a pass of the bridge of `frames` frames: the timeline's last `overlap` frames
    /// kept at the start, then `frames` generated, then the lead (see [`Bridge`]).
    fn start_bridge(&mut self, frames: usize, pass: Bridge) -> Result<bool> {
        self.start_bridge_with(frames, pass, None)
    }

    /// [`Stream::start_bridge`]; the final pass takes the probe's frame after the bridge (the
    /// canonical frame's, model space).
    fn start_bridge_with(
        &mut self,
        frames: usize,
        pass: Bridge,
        after: Option<&[f32]>,
    ) -> Result<bool> {
        let dim = self.model.motion_dim();
        let have = self.features.len() / dim;
        let kept = self.params.overlap.min(have);
        let lead = self.bridge_lead();
        if self.start_rows.len() < lead * dim {
            return Err(Error::WrongState(format!(
                "the timeline has {have} frames: a loop's bridge runs into its first {lead}, so \
                 it needs at least that many"
            )));
        }
        let total = kept + frames + lead;
        let mut session = self.chunk_session(total)?;
        session.set_prompt(&self.last_prompt)?;
        let mut reference = vec![0.0; total * dim];
        reference[..kept * dim].copy_from_slice(&self.features[(have - kept) * dim..]);
        let frame = self.to_canonical(&mut reference[..kept * dim]);
        let absolute = self.model.motion_format() == Format::Smpl24Rot6d;
        let mut keep = vec![false; total * dim];
        keep[..kept * dim].fill(true);
        if let Some(after) = after {
            // The timeline's start, moved by the loop's root motion T (the turn and shift
            // taking frame 0's root onto the probe's frame after the bridge), in the canonical
            // frame; humanml263's relative features continue the path by themselves.
            let end = &mut reference[(kept + frames) * dim..];
            end.copy_from_slice(&self.start_rows[..lead * dim]);
            if absolute {
                let mut b = after.to_vec();
                let back = frame.inverse();
                self.root_channels(&mut b, |rows| back.apply(rows, dim));
                let t = crate::cycle::root_move(&self.model, &self.start_rows[..dim], &b);
                self.root_channels(end, |rows| {
                    t.apply(rows, dim);
                    frame.apply(rows, dim);
                });
            }
            keep[(kept + frames) * dim..].fill(true);
        }
        session.set_reference(&reference)?;
        session.set_keep(keep)?;
        self.current = Some(Chunk {
            session,
            start: self.ready() - kept,
            kept,
            frame,
            bridge: Some(pass),
        });
        Ok(true)
    }

    /// Declares the timeline complete and makes it loop: after the pushed segments, a bridge
    /// of `frames` frames (the last segment's prompt) is generated that runs from the
    /// timeline's end into its start, as `flame generate --loop` makes a clip's end run into
    /// its start. Frames already generated never change; the bridge adds `frames` frames, and
    /// [`Stream::loop_end`] then holds the frame after the last (the next cycle's first).
    /// Needs the timeline's first frames (refused once they were dropped), a model that keeps
    /// frames (not latent), and `frames` of at least two leads (1 s) with the overlap and the
    /// lead fitting in the model's frames.
    pub fn close_looped(&mut self, frames: usize) -> Result<()> {
        self.check_open()?;
        if self.model.is_latent() {
            return Err(invalid_arg!(
                "a looped stream generates a bridge that keeps frames at both ends, and this {} \
                 model samples a latent",
                self.model.config().architecture
            ));
        }
        let lead = self.bridge_lead();
        let max = self.model.max_frames();
        if frames < 2 * lead || self.params.overlap + frames + lead > max {
            return Err(invalid_arg!(
                "a loop's bridge of {frames} frames: it needs {}..={} frames ({lead} of the \
                 start kept after it and the {}-frame overlap before it, at most the model's \
                 {max} in all)",
                2 * lead,
                max.saturating_sub(self.params.overlap + lead),
                self.params.overlap
            ));
        }
        if self.first > 0 {
            return Err(Error::WrongState(format!(
                "frames before {} were dropped: a loop runs into the timeline's first frames",
                self.first
            )));
        }
        if self.segments.is_empty() && self.ready() == 0 {
            return Err(Error::WrongState(
                "push a segment before closing the stream into a loop".into(),
            ));
        }
        self.bridge = Some(frames);
        self.closed = true;
        Ok(())
    }

    /// The frame after the timeline's last once a looped timeline is complete: the next
    /// cycle's first frame (frame 0 moved by the loop's root motion), model-space features.
    pub fn loop_end(&self) -> Option<&[f32]> {
        self.loop_end.as_deref()
    }

    /// Appends the finished chunk's new frames, back in the stream's frame.
    fn finish_chunk(&mut self) -> Result<()> {
        let mut c = self.current.take().expect("a chunk is running");
        let dim = self.model.motion_dim();
        if let (Some(Bridge::Probe), Some(frames)) = (c.bridge, self.bridge) {
            let (x, _) = c.session.motion(Which::Sample)?;
            let at = c.kept + frames;
            let after = x[at * dim..(at + 1) * dim].to_vec();
            self.start_bridge_with(frames, Bridge::Final, Some(&after))?;
            return Ok(());
        }
        // A latent model decides its decoded length itself (MoLA's valid flag, at least 10
        // frames): the chunk adds what it decoded past the kept frames, up to what was asked.
        let asked = c.session.frames();
        let (x, decoded) = c.session.motion(Which::Sample)?;
        let frames = decoded.min(asked);
        if frames <= c.kept {
            return Err(Error::WrongState(format!(
                "the model ended the chunk after {decoded} frames (its own length), within the \
                 {} kept ones: the stream cannot advance; use a smaller overlap",
                c.kept
            )));
        }
        debug_assert_eq!(c.start + c.kept, self.ready());
        let mut new = x[c.kept * dim..frames * dim].to_vec();
        if self.model.motion_format() == Format::Smpl24Rot6d {
            let back = c.frame.inverse();
            self.root_channels(&mut new, |rows| back.apply(rows, dim));
        }
        let mut added = frames - c.kept;
        if let (Some(Bridge::Final), Some(bridge)) = (c.bridge, self.bridge) {
            // The bridge's frames are the timeline's; the lead after them is the next cycle's
            // start, of which the first frame is kept.
            added = bridge;
            self.loop_end = Some(new[bridge * dim..(bridge + 1) * dim].to_vec());
            new.truncate(bridge * dim);
        }
        self.features.extend_from_slice(&new);
        if self.start_rows.is_empty() && self.first == 0 {
            let lead = self.bridge_lead();
            if self.ready() >= lead {
                self.start_rows = self.features[..lead * dim].to_vec();
            }
        }
        if self.first_chunk.is_none() {
            self.first_chunk = Some(self.ready());
        }
        self.held_changed();
        if c.bridge.is_none() {
            if let Some((seg, done)) = self.segments.front_mut() {
                *done += added;
                self.last_prompt.clone_from(&seg.prompt);
            }
        }
        self.chunks += 1;
        Ok(())
    }

    /// Moves smpl24_6d `rows` (model space) into the canonical frame of their first row (at the
    /// horizontal origin, facing the native forward) and returns that change; other formats
    /// are left as they are (identity).
    fn to_canonical(&self, rows: &mut [f32]) -> Rebase {
        let mut frame = Rebase::IDENTITY;
        if self.model.motion_format() == Format::Smpl24Rot6d && !rows.is_empty() {
            let dim = self.model.motion_dim();
            let mut first = rows[..dim].to_vec();
            self.root_channels(&mut first, |r| frame = Rebase::canonical(r));
            self.root_channels(rows, |r| frame.apply(r, dim));
        }
        frame
    }

    /// Runs `f` on `rows` with the root channels in the format's own units
    /// ([`crate::cycle::in_root_units`]).
    fn root_channels(&self, rows: &mut [f32], f: impl FnOnce(&mut [f32])) {
        crate::cycle::in_root_units(&self.model, rows, f)
    }

    /// Drops frames more than `window` before the playhead (keeping the overlap the next chunk
    /// needs), re-anchoring relative formats.
    fn drop_old(&mut self) -> Result<()> {
        let dim = self.model.motion_dim();
        let window_from = self.playhead.saturating_sub(self.params.window);
        self.drop_cleaned(window_from)?;
        let mut keep_from = window_from.min(self.ready().saturating_sub(self.params.overlap));
        if let Some(c) = &self.cleanup {
            // The frames the next settle reads stay (module doc, "Cleanup").
            keep_from = keep_from.min(c.context);
        }
        if keep_from <= self.first {
            return Ok(());
        }
        if self.model.motion_format() == Format::HumanMl263 {
            self.anchor = RootStart::at(&*self.decode()?, keep_from - self.first);
        }
        // Quaternion tracks already read keep their signs: their anchor moves to the new first
        // frame.
        let joints = self.model.motion_format().skeleton().joint_count();
        let at = (keep_from - self.first) * joints;
        for slot in 0..12 {
            if self.quats.borrow().anchors[slot].is_some() {
                let track = self.quat_track(slot)?;
                self.quats.borrow_mut().anchors[slot] = Some(track[at..at + joints].to_vec());
            }
        }
        self.features.drain(..(keep_from - self.first) * dim);
        self.held_changed();
        self.first = keep_from;
        Ok(())
    }

    /// Forgets what was computed from the held frames (decoded poses, quaternion tracks).
    fn held_changed(&mut self) {
        self.decoded.take();
        self.quats.get_mut().tracks = Default::default();
    }

    /// The quaternion track of `slot` (w first, `[held frames × joints]`), continuous from its
    /// anchor.
    fn quat_track(&self, slot: usize) -> Result<Arc<Vec<[f64; 4]>>> {
        if let Some(t) = &self.quats.borrow().tracks[slot] {
            return Ok(Arc::clone(t));
        }
        let poses = self.decode()?;
        let convention = Convention::ALL[slot % Convention::ALL.len()];
        let rotations = if slot >= Convention::ALL.len() {
            poses.global_rotations(convention)
        } else {
            poses.local_rotations(convention)
        };
        let joints = poses.joint_count();
        let mut q = self.quats.borrow().anchors[slot]
            .clone()
            .unwrap_or_default();
        let anchored = !q.is_empty();
        q.extend(rotations.iter().map(crate::motion::rotation::to_quat));
        let frames = q.len() / joints;
        crate::motion::postprocess::make_continuous(&mut q, frames, joints);
        let mut quats = self.quats.borrow_mut();
        if anchored {
            q.drain(..joints);
        } else {
            quats.anchors[slot] = Some(q[..joints].to_vec());
        }
        let track = Arc::new(q);
        quats.tracks[slot] = Some(Arc::clone(&track));
        Ok(track)
    }

    /// The held frames decoded (native frame), anchored where the dropped frames left off;
    /// decoded once per change of the held frames.
    fn decode(&self) -> Result<Arc<Poses>> {
        if let Some(p) = self.decoded.borrow().as_ref() {
            return Ok(Arc::clone(p));
        }
        let dim = self.model.motion_dim();
        let frames = self.features.len() / dim;
        let opts = self.model.read_options(0.0, true);
        let format = self.model.motion_format();
        let poses = Arc::new(Poses::decode_from(
            format,
            &self.features,
            frames,
            &opts,
            self.anchor,
        )?);
        *self.decoded.borrow_mut() = Some(Arc::clone(&poses));
        Ok(poses)
    }

    /// Poses of timeline frames `first..first + count`.
    pub fn poses(&self, first: usize, count: usize) -> Result<Poses> {
        self.check_range(first, count)?;
        Ok(self.decode()?.frames_range(first - self.first, count))
    }

    /// Timeline frames `first..first + count` in one layout and convention. Quaternion tracks
    /// are sign-continuous over the whole timeline, whatever ranges they are read in.
    pub fn read(
        &self,
        first: usize,
        count: usize,
        layout: Layout,
        convention: Convention,
    ) -> Result<Vec<f32>> {
        self.check_range(first, count)?;
        // Nothing may be held yet (before the first pump), and an empty range needs no decode.
        if count == 0 {
            return Ok(Vec::new());
        }
        let Some(order) = layout.quat_order() else {
            return self.poses(first, count)?.layout(layout, convention);
        };
        let world = matches!(layout, Layout::GlobalQuatXyzw | Layout::GlobalQuatWxyz);
        let track = self.quat_track(track_slot(world, convention))?;
        let joints = self.model.motion_format().skeleton().joint_count();
        let a = (first - self.first) * joints;
        Ok(track[a..a + count * joints]
            .iter()
            .flat_map(|q| order.arrange(q))
            .map(|v| v as f32)
            .collect())
    }

    /// Model-space features of timeline frames `first..first + count` (for `smpl24_6d` in the
    /// stream's frame: the root path continues across chunks).
    pub fn features(&self, first: usize, count: usize) -> Result<&[f32]> {
        self.check_range(first, count)?;
        let dim = self.model.motion_dim();
        let a = (first - self.first) * dim;
        Ok(&self.features[a..a + count * dim])
    }

    fn check_range(&self, first: usize, count: usize) -> Result<()> {
        let end = first
            .checked_add(count)
            .ok_or_else(|| invalid_arg!("frames {first} + {count} overflow"))?;
        if first < self.first {
            return Err(invalid_arg!(
                "frames before {} were dropped (the stream keeps {} frames behind the playhead {})",
                self.first,
                self.params.window,
                self.playhead
            ));
        }
        if end > self.ready() {
            return Err(Error::WrongState(format!(
                "frames from {first} to {end} (end excluded) are not generated yet ({} ready): pump more",
                self.ready()
            )));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Cleaned reads (module doc, "Cleanup").

/// The foot contact slots of each leg (ankle, toe), as in [`crate::motion::contacts`].
const LEG_SLOTS: [(usize, usize); 2] = [(0, 1), (2, 3)];

/// The cleanup of a stream: what is final so far and the cleaned frames (module doc).
struct Cleanup {
    finish: Finish,
    /// The model's frame rate (the timeline's).
    fps: f64,
    /// The detection floor (lowest foot joint) and the contact floor (lowest contact point) of
    /// the first chunk, fixed once.
    floors: Option<(f64, f64)>,
    /// Hysteresis contacts of frames `raw_first..`, and each slot's state after the last.
    raw: VecDeque<[bool; 4]>,
    raw_first: usize,
    on: [bool; 4],
    /// Final contacts of frames `fin_first..`; slot `s` is final up to `done[s]` (exclusive);
    /// `cut[s]`: where its next scan starts (0 or the start of a surviving gap).
    fin: VecDeque<[bool; 4]>,
    fin_first: usize,
    done: [usize; 4],
    cut: [usize; 4],
    /// Source frames `0..settled` are cleaned (before resampling).
    settled: usize,
    /// The heading of frame 0 and of frame `settled − 1` (remove_yaw).
    psi0: Option<f64>,
    last_psi: f64,
    /// Cleaned source frames `src_first..settled` kept for resampling (empty without it).
    src: Option<Poses>,
    src_first: usize,
    /// Cleaned output frames `out_first..out_first + out.frames`.
    out: Option<Poses>,
    out_first: usize,
    /// Sign-continuous quaternion tracks per [`track_slot`]: the first output frame each
    /// holds, and its quaternions (`[frames × joints]`); made on first read, then extended.
    quats: [(usize, Vec<[f64; 4]>); 12],
    /// The first frame the next settle reads (held frames before it may be dropped).
    context: usize,
}

impl Cleanup {
    fn resampling(&self) -> Option<f64> {
        self.finish.fps.filter(|&f| f != self.fps)
    }

    fn out_end(&self) -> usize {
        self.out_first + self.out.as_ref().map_or(0, |p| p.frames)
    }

    fn planted(&self, t: usize, (a, f): (usize, usize)) -> bool {
        let c = self.fin[t - self.fin_first];
        c[a] || c[f]
    }

    /// The first frame whose cleanup a settle at `u` (the first unsettled frame) reads, given
    /// final contacts up to `c` (module doc: the span of `u`, the span before its swing and
    /// every span whose fade reaches `u`).
    fn context_start(&self, u: usize, c: usize, fade: usize) -> usize {
        if self.finish.feet != Feet::Lock || u >= c {
            return u.min(c).max(self.fin_first);
        }
        let mut w0 = u;
        for leg in LEG_SLOTS {
            let start_of = |mut t: usize, v: bool| {
                while t > self.fin_first && self.planted(t - 1, leg) == v {
                    t -= 1;
                }
                t
            };
            let bound = if self.planted(u, leg) {
                u
            } else {
                let s = start_of(u, false);
                if s == 0 {
                    w0 = 0;
                    continue;
                }
                s - 1
            };
            let bound = bound.min(u.saturating_sub(fade)).max(self.fin_first);
            let leg_w0 = if self.planted(bound, leg) {
                start_of(bound, true)
            } else {
                bound
            };
            w0 = w0.min(leg_w0);
        }
        w0
    }
}

/// One slot's final contacts ([`contacts`]' `clean_spans` on the whole timeline, decided as far
/// as the raw track `raw(t)`, `from..known`, allows): the values of frames `from..` and where
/// the next scan may start. `from` is 0 or the start of a gap that survives; `end` is the
/// timeline's length once it has one.
fn settle_slot(
    raw: impl Fn(usize) -> bool,
    from: usize,
    known: usize,
    end: Option<usize>,
    min: usize,
) -> (Vec<bool>, usize) {
    #[derive(PartialEq)]
    enum Gap {
        Survives,
        Filled,
        Undecided,
    }
    let mut runs: Vec<(bool, usize, usize)> = Vec::new();
    for t in from..known {
        let v = raw(t);
        match runs.last_mut() {
            Some(r) if r.0 == v => r.2 = t + 1,
            _ => runs.push((v, t, t + 1)),
        }
    }
    let gap = |i: usize| {
        let (_, s, e) = runs[i];
        let complete = i + 1 < runs.len() || end.is_some();
        if s == 0 || (complete && Some(e) == end) || e - s >= min {
            Gap::Survives
        } else if complete {
            Gap::Filled
        } else {
            Gap::Undecided
        }
    };
    let (mut vals, mut cut) = (Vec::new(), from);
    let mut i = 0;
    while i < runs.len() {
        let (v, s, e) = runs[i];
        if !v {
            match gap(i) {
                Gap::Survives => {
                    vals.resize(vals.len() + (e - s), false);
                    cut = s;
                    i += 1;
                    continue;
                }
                Gap::Undecided => break,
                Gap::Filled => {}
            }
        }
        // A contact span: runs joined by filled gaps, up to a surviving gap.
        let (mut j, mut len, mut bounded) = (i, 0, false);
        while j < runs.len() {
            let (v, s2, e2) = runs[j];
            if v || gap(j) == Gap::Filled {
                len += e2 - s2;
                j += 1;
                continue;
            }
            bounded = gap(j) == Gap::Survives;
            break;
        }
        let complete = bounded || (j == runs.len() && end.is_some());
        if complete {
            let keep = len >= min || (s == 0 && Some(s + len) == end);
            vals.resize(vals.len() + len, keep);
            i = j;
            continue;
        }
        if len >= min {
            vals.resize(vals.len() + len, true);
        }
        break;
    }
    (vals, cut)
}

/// Appends `b`'s frames to `a`.
fn append(a: &mut Poses, b: &Poses) {
    a.frames += b.frames;
    a.root.extend_from_slice(&b.root);
    a.local.extend_from_slice(&b.local);
    a.global.extend_from_slice(&b.global);
    a.positions.extend_from_slice(&b.positions);
    a.contacts.extend_from_slice(&b.contacts);
    a.root_bone.extend_from_slice(&b.root_bone);
}

/// Drops `a`'s first `n` frames.
fn drain_front(a: &mut Poses, n: usize) {
    let n = n.min(a.frames);
    let j = a.joint_count();
    a.frames -= n;
    a.root.drain(..n);
    a.local.drain(..n * j);
    a.global.drain(..n * j);
    a.positions.drain(..n * j);
    if !a.contacts.is_empty() {
        a.contacts.drain(..n);
    }
    if !a.root_bone.is_empty() {
        a.root_bone.drain(..n);
    }
}

impl Stream {
    /// Sets the cleanup of [`Stream::read_cleaned`] (module doc, "Cleanup"), once: again with
    /// the same value is a no-op, another value is [`Error::WrongState`]. Refuses a loop wrap
    /// (a stream has no end to wrap) and, once frame 0 was dropped, any cleanup (contacts are
    /// tracked from frame 0 on).
    pub fn set_finish(&mut self, finish: Finish) -> Result<()> {
        finish.validate()?;
        if finish.wrap || finish.wrap_to_last {
            return Err(invalid_arg!(
                "a stream cannot wrap: a loop's wrap joins a clip's end to its start, and a \
                 stream's timeline goes on (turn wrap off, or finish the whole timeline as a clip)"
            ));
        }
        if let Some(c) = &self.cleanup {
            if c.finish == finish {
                return Ok(());
            }
            return Err(Error::WrongState(
                "the stream's cleanup is set once (frames handed out never change): it is \
                 already set to other values"
                    .into(),
            ));
        }
        if self.first > 0 {
            return Err(Error::WrongState(format!(
                "frames before {} were dropped: the cleanup follows contacts from frame 0, so \
                 set it before the playhead moves {} frames on",
                self.first, self.params.window
            )));
        }
        self.cleanup = Some(Cleanup {
            finish,
            fps: self.model.read_options(0.0, true).fps as f64,
            floors: None,
            raw: VecDeque::new(),
            raw_first: 0,
            on: [false; 4],
            fin: VecDeque::new(),
            fin_first: 0,
            done: [0; 4],
            cut: [0; 4],
            settled: 0,
            psi0: None,
            last_psi: 0.0,
            src: None,
            src_first: 0,
            out: None,
            out_first: 0,
            quats: Default::default(),
            context: 0,
        });
        self.settle()
    }

    /// The cleanup set by [`Stream::set_finish`].
    pub fn finish(&self) -> Option<&Finish> {
        self.cleanup.as_ref().map(|c| &c.finish)
    }

    /// Declares the timeline complete: no segment is pushed after this one. Once the pushed
    /// segments are generated, every frame settles (module doc).
    pub fn close(&mut self) {
        self.closed = true;
    }

    /// Whether [`Stream::close`] (or a looping close) declared the timeline complete.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Closed and every pushed frame generated (and a looped close's bridge): the timeline's
    /// length is [`Stream::ready`].
    pub fn is_complete(&self) -> bool {
        self.closed
            && self.current.is_none()
            && self.segments.iter().all(|(s, d)| *d >= s.frames)
            && (self.bridge.is_none() || self.loop_end.is_some())
    }

    /// Output frames of [`Stream::read_cleaned`] settled so far (frames `..settled` exist,
    /// minus the dropped), at the cleanup's frame rate.
    pub fn settled(&self) -> usize {
        self.cleanup.as_ref().map_or(0, |c| {
            if c.finish.is_identity() {
                self.ready()
            } else {
                c.out_end()
            }
        })
    }

    /// The first cleaned output frame still held.
    pub fn first_settled(&self) -> usize {
        self.cleanup.as_ref().map_or(0, |c| {
            if c.finish.is_identity() {
                self.first
            } else {
                c.out_first
            }
        })
    }

    /// Cleaned frames `first..first + count` in one layout and convention (module doc,
    /// "Cleanup"). Frames are at the cleanup's frame rate: frame `k` is at `k / fps` seconds of
    /// the timeline. Frames not settled yet are [`Error::WrongState`] (pump more); a frame
    /// read once reads the same bits whatever was pumped or read since.
    pub fn read_cleaned(
        &mut self,
        first: usize,
        count: usize,
        layout: Layout,
        convention: Convention,
    ) -> Result<Vec<f32>> {
        let Some(c) = &self.cleanup else {
            return Err(Error::WrongState(
                "the stream has no cleanup: set it first (set_finish)".into(),
            ));
        };
        if c.finish.is_identity() {
            return self.read(first, count, layout, convention);
        }
        self.settle()?;
        let joints = self.model.motion_format().skeleton().joint_count();
        let c = self.cleanup.as_mut().expect("checked above");
        let end = first
            .checked_add(count)
            .ok_or_else(|| invalid_arg!("frames {first} + {count} overflow"))?;
        if first < c.out_first {
            return Err(invalid_arg!(
                "cleaned frames before {} were dropped (the stream keeps {} frames behind the \
                 playhead {})",
                c.out_first,
                self.params.window,
                self.playhead
            ));
        }
        if end > c.out_end() {
            return Err(Error::WrongState(format!(
                "cleaned frames {first}..{end} are not settled yet ({} settled, {} frames \
                 generated): pump more",
                c.out_end(),
                self.ready()
            )));
        }
        if count == 0 {
            // Nothing to read (and, before the first frame settles, nothing cleaned yet).
            return Ok(Vec::new());
        }
        let Some(order) = layout.quat_order() else {
            let out = c.out.as_ref().expect("frames are settled");
            return out
                .frames_range(first - c.out_first, count)
                .layout(layout, convention);
        };
        let world = matches!(layout, Layout::GlobalQuatXyzw | Layout::GlobalQuatWxyz);
        let slot = track_slot(world, convention);
        extend_track(c, slot, joints);
        let (track_first, track) = &c.quats[slot];
        let a = (first - track_first) * joints;
        Ok(track[a..a + count * joints]
            .iter()
            .flat_map(|q| order.arrange(q))
            .map(|v| v as f32)
            .collect())
    }

    /// Settles what the frames generated allow (module doc): final contacts, then the cleanup
    /// of the frames whose spans are final, then the resampled frames they cover.
    fn settle(&mut self) -> Result<()> {
        let Some(mut c) = self.cleanup.take() else {
            return Ok(());
        };
        let r = self.settle_with(&mut c);
        self.cleanup = Some(c);
        r
    }

    fn settle_with(&self, c: &mut Cleanup) -> Result<()> {
        if c.finish.is_identity() {
            return Ok(());
        }
        let Some(first_chunk) = self.first_chunk else {
            return Ok(());
        };
        let ready = self.ready();
        let complete = self.is_complete();
        let poses = self.decode()?;
        let held = |t: usize| t - self.first;
        let format = self.model.motion_format();
        let joints = format.skeleton().joint_count();
        let up = format.up_axis();
        let params = c.finish.contacts;
        if c.floors.is_none() {
            if self.first > 0 {
                return Err(Error::WrongState(format!(
                    "the cleanup's floor comes from the first chunk, and frames before {} were \
                     dropped",
                    self.first
                )));
            }
            let chunk = poses.frames_range(0, first_chunk);
            let detection = (0..chunk.frames)
                .flat_map(|t| contacts::SLOT_JOINTS.iter().map(move |&j| (t, j)))
                .map(|(t, j)| chunk.positions[t * joints + j][up])
                .fold(f64::INFINITY, f64::min);
            let on = contacts::of(&chunk, c.fps, &params);
            let contact = feet::floor_height(&chunk, &on).unwrap_or(0.0);
            c.floors = Some((detection, contact));
        }
        let (detection, contact) = c.floors.expect("set above");

        // 1. Hysteresis contacts (stored ones are final as they are).
        let stored = poses.contacts.len() == poses.frames && poses.frames > 0;
        let limit = if complete || stored {
            ready
        } else {
            ready.saturating_sub(1)
        };
        let levels = contacts::standing_levels(format);
        for t in c.raw_first + c.raw.len()..limit {
            if stored {
                c.raw.push_back(poses.contacts[held(t)].map(|v| v > 0.5));
                continue;
            }
            let mut row = [false; 4];
            for (slot, &j) in contacts::SLOT_JOINTS.iter().enumerate() {
                let at = |i: usize| &poses.positions[held(i) * joints + j];
                // As `contacts::detect`, with the floor fixed.
                let height = at(t)[up] - detection - levels[slot];
                let speed = contacts::speed_at(t, ready, c.fps, at);
                c.on[slot] = contacts::next_state(c.on[slot], height, speed, &params);
                row[slot] = c.on[slot];
            }
            c.raw.push_back(row);
        }
        // 2. Final contacts.
        let known = c.raw_first + c.raw.len();
        let end = complete.then_some(known);
        let min = params.min_frames(c.fps);
        for slot in 0..4 {
            let (vals, cut) = if stored {
                let from = c.done[slot];
                let v = (from..known)
                    .map(|t| c.raw[t - c.raw_first][slot])
                    .collect();
                (v, from)
            } else {
                settle_slot(
                    |t| c.raw[t - c.raw_first][slot],
                    c.cut[slot],
                    known,
                    end,
                    min,
                )
            };
            let from = if stored { c.done[slot] } else { c.cut[slot] };
            let upto = from + vals.len();
            for t in c.done[slot].max(from)..upto {
                while c.fin_first + c.fin.len() <= t {
                    c.fin.push_back([false; 4]);
                }
                c.fin[t - c.fin_first][slot] = vals[t - from];
            }
            c.done[slot] = c.done[slot].max(upto);
            c.cut[slot] = cut;
        }
        let fin_end = *c.done.iter().min().expect("four slots");
        let fade = ((feet::FADE_SECONDS * c.fps).round() as usize).max(1);

        // 3. The settle horizon.
        let u = c.settled;
        let mut h = fin_end;
        if c.finish.feet == Feet::Lock && !complete && fin_end > u {
            for leg in LEG_SLOTS {
                let mut t = fin_end - 1;
                let open_start = if c.planted(t, leg) {
                    while t > u && c.planted(t - 1, leg) {
                        t -= 1;
                    }
                    t
                } else {
                    fin_end
                };
                // The swing before the open span (or the open swing) waits for it.
                let mut region = open_start;
                while region > u && !c.planted(region - 1, leg) {
                    region -= 1;
                }
                // Swing frames a fade away from the open span wait too.
                let mut leg_h = region;
                for t in open_start.saturating_sub(fade).max(u)..region {
                    if !c.planted(t, leg) {
                        leg_h = t;
                        break;
                    }
                }
                h = h.min(leg_h);
            }
        }

        // 4. The cleanup of frames u..h over the window w0..fin_end.
        if h > u {
            let w0 = c.context_start(u, fin_end, fade);
            let mut w = poses.frames_range(held(w0), fin_end - w0);
            let on: Vec<[bool; 4]> = (w0..fin_end).map(|t| c.fin[t - c.fin_first]).collect();
            w.contacts = on
                .iter()
                .map(|r| r.map(|v| f64::from(u8::from(v))))
                .collect();
            if c.finish.ground {
                for p in w.root.iter_mut().chain(w.positions.iter_mut()) {
                    p[up] -= contact;
                }
            }
            if c.finish.feet == Feet::Lock {
                let floor = if c.finish.ground { 0.0 } else { contact };
                feet::lock_on(&mut w, &on, c.fps, Some(floor))?;
            }
            let mut new = w.frames_range(u - w0, h - u);
            if c.finish.root_motion != RootMotion::Keep {
                let psi = root_motion::headings_after(&new, up, c.last_psi);
                let psi0 = *c.psi0.get_or_insert(psi[0]);
                root_motion::apply_after(
                    &mut new,
                    c.finish.root_motion,
                    c.finish.remove_yaw,
                    Some((psi0, c.last_psi)),
                );
                c.last_psi = *psi.last().expect("h > u");
            }
            c.settled = h;
            let store = if c.resampling().is_some() {
                &mut c.src
            } else {
                &mut c.out
            };
            match store {
                Some(p) => append(p, &new),
                None => *store = Some(new),
            }
        }

        // 5. Resampled frames whose source frames are settled.
        if let Some(to) = c.resampling() {
            let from = c.out_end();
            let mut k = from;
            loop {
                let (a, exact) = resample::source_of(k, c.fps, to)?;
                if a + usize::from(!exact) >= c.settled {
                    break;
                }
                k += 1;
            }
            if k > from {
                let src = c.src.as_ref().expect("source frames are settled");
                let new = resample::resample_range(src, c.fps, to, c.src_first, from..k)?;
                match &mut c.out {
                    Some(p) => append(p, &new),
                    None => c.out = Some(new),
                }
            }
            // Source frames before the next output frame's are no longer needed.
            let (a, _) = resample::source_of(k, c.fps, to)?;
            let drop = a.min(c.settled).saturating_sub(c.src_first);
            if let Some(src) = &mut c.src {
                drain_front(src, drop);
                c.src_first += drop;
            }
        }

        // 6. What the next settle reads; older bookkeeping goes.
        let w0 = if c.settled < fin_end {
            c.context_start(c.settled, fin_end, fade)
        } else {
            c.settled.min(fin_end)
        };
        let cut = *c.cut.iter().min().expect("four slots");
        let raw_keep = cut.min(known);
        let fin_keep = w0.min(cut).min(fin_end);
        c.raw
            .drain(..raw_keep.saturating_sub(c.raw_first).min(c.raw.len()));
        c.raw_first = c.raw_first.max(raw_keep);
        let n = fin_keep.saturating_sub(c.fin_first).min(c.fin.len());
        c.fin.drain(..n);
        c.fin_first += n;
        c.context = w0.min(known.saturating_sub(1)).min(c.settled);
        Ok(())
    }

    /// Drops cleaned frames whose time is before timeline frame `frame`.
    fn drop_cleaned(&mut self, frame: usize) -> Result<()> {
        let Some(c) = &mut self.cleanup else {
            return Ok(());
        };
        let joints = self.model.motion_format().skeleton().joint_count();
        let out_frame = match c.resampling() {
            None => frame,
            Some(to) => {
                // The first output frame at or after the time of `frame`.
                let mut k = (frame as f64 * to / c.fps).floor() as usize;
                while k > 0 && resample::source_of(k - 1, c.fps, to)?.0 >= frame {
                    k -= 1;
                }
                while resample::source_of(k, c.fps, to)?.0 < frame {
                    k += 1;
                }
                k
            }
        };
        let n = out_frame
            .saturating_sub(c.out_first)
            .min(c.out.as_ref().map_or(0, |p| p.frames));
        if n == 0 {
            return Ok(());
        }
        // Tracks already read keep their signs: extended first, each keeps at least its last
        // frame (the next frames' signs continue from it).
        for slot in 0..c.quats.len() {
            if c.quats[slot].1.is_empty() {
                continue;
            }
            extend_track(c, slot, joints);
            let (track_first, track) = &mut c.quats[slot];
            let drop = (c.out_first + n - *track_first).min(track.len() / joints - 1);
            track.drain(..drop * joints);
            *track_first += drop;
        }
        if let Some(p) = &mut c.out {
            drain_front(p, n);
        }
        c.out_first += n;
        Ok(())
    }
}

/// Extends `c`'s quaternion track `slot` to every cleaned output frame, its signs continuing
/// from its last frame (the first frame's as [`crate::motion::rotation::to_quat`] gives them).
fn extend_track(c: &mut Cleanup, slot: usize, joints: usize) {
    let out_end = c.out_end();
    let Some(out) = c.out.as_ref() else {
        return;
    };
    let (track_first, track) = &mut c.quats[slot];
    if track.is_empty() {
        *track_first = c.out_first;
    }
    let have = *track_first + track.len() / joints;
    if have >= out_end {
        return;
    }
    let convention = Convention::ALL[slot % Convention::ALL.len()];
    let new = out.frames_range(have - c.out_first, out_end - have);
    let rotations = if slot >= Convention::ALL.len() {
        new.global_rotations(convention)
    } else {
        new.local_rotations(convention)
    };
    let lead = track.len().saturating_sub(joints);
    let mut q: Vec<[f64; 4]> = track[lead..].to_vec();
    let led = q.len();
    q.extend(rotations.iter().map(crate::motion::rotation::to_quat));
    let frames = q.len() / joints;
    crate::motion::postprocess::make_continuous(&mut q, frames, joints);
    track.extend_from_slice(&q[led..]);
}

/// The seed of chunk `k`: the stream's seed and the index through splitmix64's finaliser, so
/// neighbouring chunks draw unrelated noise.
fn chunk_seed(seed: u64, k: u64) -> u64 {
    let mut z = seed ^ k.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::Sampler;

    /// Mean distance (m) of the chunk's first `kept` frames' joints to the kept frames'.
    fn kept_distance(stream: &Stream, session: &mut Session, kept: usize) -> f64 {
        let model = Arc::clone(stream.model());
        let (format, dim) = (model.motion_format(), model.motion_dim());
        let opts = model.read_options(0.0, true);
        let have = stream.features.len() / dim;
        let want = Poses::decode(format, &stream.features[(have - kept) * dim..], kept, &opts)
            .unwrap()
            .positions(Convention::Native);
        let (x, _) = session.motion(Which::Sample).unwrap();
        let got = Poses::decode(format, &x[..kept * dim], kept, &opts)
            .unwrap()
            .positions(Convention::Native);
        let d: f64 = want
            .iter()
            .zip(&got)
            .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt())
            .sum();
        d / want.len() as f64
    }

    /// A MoLA chunk is steered towards the kept frames: its first frames land nearer their joint
    /// positions than the same chunk generated without the targets (same seed and prompt).
    #[test]
    fn latent_chunks_are_steered_towards_the_kept_frames() {
        let model = Arc::new(
            Model::load(
                std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("tests/fixtures/mola_tiny.safetensors"),
            )
            .unwrap(),
        );
        let params = StreamParams {
            chunk: 32,
            overlap: 8,
            lookahead: 1000,
            window: 1000,
            session: SessionParams {
                steps: Some(10),
                sampler: Some(Sampler::Ddim),
                seed: 3,
                threads: 1,
                ..Default::default()
            },
        };
        let mut s = Stream::new(model, &params).unwrap();
        s.push(Segment::new("a person walks forward.", 60)).unwrap();
        s.pump(10).unwrap();
        assert!(s.ready() > 8 && s.current.is_none());
        assert!(s.start_chunk().unwrap());
        let mut steered = s.current.take().unwrap().session;
        let mut free =
            Session::new(Arc::clone(s.model()), &steered_params(&steered, &params)).unwrap();
        free.set_prompt("a person walks forward.").unwrap();
        assert!(steered.position_targets().is_some());
        steered.run().unwrap();
        free.run().unwrap();
        let (a, b) = (
            kept_distance(&s, &mut steered, 8),
            kept_distance(&s, &mut free, 8),
        );
        eprintln!("steered {a} m, free {b} m");
        assert!(a < 0.8 * b, "steered {a} m, free {b} m");
    }

    fn steered_params(steered: &Session, params: &StreamParams) -> SessionParams {
        SessionParams {
            frames: Some(steered.frames()),
            seed: steered.seed(),
            ..params.session.clone()
        }
    }
}

#[cfg(test)]
mod cleanup_tests {
    //! Cleaned reads on the tiny fixtures: frames read one at a time as they settle are the bits
    //! of one read at the end, never change, and equal the whole-clip cleanup on the same floors.
    use super::*;
    use crate::session::Sampler;

    fn model(name: &str) -> Arc<Model> {
        Arc::new(
            Model::load(
                std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join(format!("tests/fixtures/{name}.safetensors")),
            )
            .unwrap(),
        )
    }

    fn stream(name: &str, frames: &[usize]) -> Stream {
        let params = StreamParams {
            chunk: 40,
            overlap: 10,
            lookahead: 1000,
            window: 10_000,
            session: SessionParams {
                steps: Some(2),
                sampler: Some(Sampler::Ddim),
                seed: 7,
                threads: 1,
                ..Default::default()
            },
        };
        let mut s = Stream::new(model(name), &params).unwrap();
        for (i, &n) in frames.iter().enumerate() {
            let prompt = [
                "a person walks forward.",
                "a person runs.",
                "a person jumps.",
            ][i % 3];
            s.push(Segment::new(prompt, n)).unwrap();
        }
        s.close();
        s
    }

    /// Every option that has a stream meaning: contacts, floor, feet, root bone, no yaw drift.
    /// The random-weight fixture's feet move at 6 to 31 m/s (10th to 90th percentile) at
    /// heights spread over 2 m, so the default detection finds no contact: the widest values
    /// [`ContactParams::validate`] allows, and no minimum span (its rare slow frames are single),
    /// give it spans on both legs. `settle_slot_decides_what_clean_spans_gives` covers the
    /// minimum span.
    fn finish(fps: Option<f64>) -> Finish {
        Finish {
            root_motion: RootMotion::Separate,
            remove_yaw: true,
            fps,
            contacts: crate::motion::ContactParams {
                height: 1.0,
                speed: 20.0,
                release: 1.0,
                min_span: 0.0,
            },
            ..Finish::game_ready()
        }
    }

    const LAYOUTS: [Layout; 4] = [
        Layout::GlobalPositions,
        Layout::LocalQuatWxyz,
        Layout::FootContacts,
        Layout::RootBone,
    ];

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Pumps one step at a time; after each pump reads every newly settled frame alone (and
    /// re-reads the first one, which must not have changed). Returns per layout the frames read
    /// one by one, and the lag (frames generated but not settled) after each pump.
    fn one_by_one(s: &mut Stream) -> (Vec<Vec<u32>>, Vec<usize>) {
        let mut got = vec![Vec::new(); LAYOUTS.len()];
        let (mut next, mut lags) = (0, Vec::new());
        let mut first_read: Option<Vec<u32>> = None;
        loop {
            let r = s.pump(1).unwrap();
            while next < s.settled() {
                for (l, g) in LAYOUTS.iter().zip(&mut got) {
                    g.extend(bits(
                        &s.read_cleaned(next, 1, *l, Convention::Unity).unwrap(),
                    ));
                }
                next += 1;
            }
            // The next frame is not settled yet: a status, not a value.
            match s.read_cleaned(next, 1, Layout::GlobalPositions, Convention::Unity) {
                Err(Error::WrongState(m)) => assert!(m.contains("not settled yet"), "{m}"),
                other => assert!(s.is_complete(), "{other:?}"),
            }
            let f0 = bits(
                &s.read_cleaned(0, 1, Layout::GlobalPositions, Convention::Unity)
                    .unwrap_or_default(),
            );
            match &first_read {
                Some(f) if !f0.is_empty() => assert_eq!(f, &f0, "frame 0 changed"),
                None if !f0.is_empty() => first_read = Some(f0),
                _ => {}
            }
            let settled_time = s.settled() as f64 / s.finish().unwrap().output_fps(20.0);
            lags.push(s.ready() - (settled_time * 20.0).ceil() as usize);
            if r.steps == 0 {
                return (got, lags);
            }
        }
    }

    #[test]
    fn frames_read_as_they_settle_are_the_bits_of_one_read_at_the_end() {
        for (name, fps) in [
            ("flame_tiny", None),
            ("mdm_tiny", Some(30.0)),
            ("flame_tiny", Some(24.0)),
        ] {
            let mut s = stream(name, &[70, 45]);
            s.set_finish(finish(fps)).unwrap();
            let (got, lags) = one_by_one(&mut s);
            assert!(s.is_complete());
            assert_eq!(s.ready(), 115);
            let n = s.settled();
            // Every frame settles once the timeline is complete: 115 at 20 fps, ⌊114·r/20⌋ + 1.
            let want_n = fps.map_or(115, |r| (114.0 * r / 20.0).floor() as usize + 1);
            assert_eq!(n, want_n, "{name}");
            // The same timeline generated and settled in one pump: one settle over the whole.
            let mut whole = stream(name, &[70, 45]);
            whole.set_finish(finish(fps)).unwrap();
            whole.pump(usize::MAX).unwrap();
            assert_eq!(whole.settled(), n);
            for (l, g) in LAYOUTS.iter().zip(&got) {
                let at_end = s.read_cleaned(0, n, *l, Convention::Unity).unwrap();
                assert_eq!(g, &bits(&at_end), "{name} {l:?}");
                let at_once = whole.read_cleaned(0, n, *l, Convention::Unity).unwrap();
                assert_eq!(g, &bits(&at_once), "{name} {l:?}");
            }
            let max_lag = lags.iter().max().unwrap();
            eprintln!("{name} at {fps:?}: lag after each pump {lags:?} (max {max_lag})");
        }
    }

    /// The whole clip finished as a clip (`Finish::apply`'s steps) on the stream's floors gives
    /// the stream's cleaned frames bit for bit, across chunk seams.
    #[test]
    fn cleaned_frames_equal_the_whole_clip_cleanup_on_the_same_floors() {
        for (name, fps) in [("flame_tiny", Some(30.0)), ("mdm_tiny", None)] {
            let mut s = stream(name, &[70, 45]);
            let f = finish(fps);
            s.set_finish(f).unwrap();
            // One step per pump: many settles, each over its own window.
            while s.pump(1).unwrap().steps > 0 {}
            let n = s.settled();
            let raw = s.poses(0, 115).unwrap();
            let (detection, contact) = s.cleanup.as_ref().unwrap().floors.unwrap();
            let mut want = raw.clone();
            let on = contacts::detect_on(&raw, 20.0, &f.contacts, Some(detection));
            let on = if raw.contacts.is_empty() {
                on
            } else {
                contacts::of(&raw, 20.0, &f.contacts)
            };
            want.contacts = on
                .iter()
                .map(|c| c.map(|v| f64::from(u8::from(v))))
                .collect();
            for p in want.root.iter_mut().chain(want.positions.iter_mut()) {
                p[raw.format.up_axis()] -= contact;
            }
            feet::lock_on(&mut want, &on, 20.0, Some(0.0)).unwrap();
            root_motion::apply(&mut want, f.root_motion, f.remove_yaw);
            if let Some(to) = fps {
                want = resample::resample(&want, 20.0, to).unwrap();
            }
            assert_eq!(want.frames, n);
            for l in LAYOUTS {
                let got = s.read_cleaned(0, n, l, Convention::Native).unwrap();
                assert_eq!(
                    bits(&got),
                    bits(&want.layout(l, Convention::Native).unwrap()),
                    "{name} {l:?}"
                );
            }
            // The locking did something: some contact frames moved.
            assert_ne!(
                bits(
                    &raw.layout(Layout::GlobalPositions, Convention::Native)
                        .unwrap()
                ),
                bits(
                    &s.read_cleaned(0, 115.min(n), Layout::GlobalPositions, Convention::Native)
                        .unwrap()
                ),
            );
        }
    }

    /// One chunk is the whole timeline: its floors are the clip's, so `Finish::apply` itself
    /// gives the cleaned frames.
    #[test]
    fn a_one_chunk_stream_reads_what_finish_apply_gives() {
        for name in ["flame_tiny", "mdm_tiny"] {
            let mut s = stream(name, &[40]);
            let f = finish(Some(30.0));
            s.set_finish(f).unwrap();
            while s.pump(usize::MAX).unwrap().steps > 0 {}
            let want = f.apply(&s.poses(0, 40).unwrap(), 20.0).unwrap();
            assert_eq!(s.settled(), want.frames);
            for l in LAYOUTS {
                let got = s.read_cleaned(0, want.frames, l, Convention::Gltf).unwrap();
                assert_eq!(
                    bits(&got),
                    bits(&want.layout(l, Convention::Gltf).unwrap()),
                    "{name} {l:?}"
                );
            }
        }
    }

    #[test]
    fn an_empty_cleaned_read_before_anything_settled_is_empty() {
        // Found by the Unreal component's tests: a read of 0 frames in a layout without
        // quaternions, before any frame settled, panicked on the missing cleaned poses.
        let mut s = stream("flame_tiny", &[40]);
        s.set_finish(finish(None)).unwrap();
        for layout in [
            Layout::RootTranslation,
            Layout::GlobalPositions,
            Layout::LocalQuatXyzw,
        ] {
            let v = s.read_cleaned(0, 0, layout, Convention::Gltf).unwrap();
            assert!(v.is_empty());
        }
        s.pump(1000).unwrap();
        assert!(s
            .read_cleaned(0, 0, Layout::RootBone, Convention::Gltf)
            .unwrap()
            .is_empty());
    }

    #[test]
    fn wrap_unsettled_frames_and_bad_values_are_clear_errors() {
        let mut s = stream("flame_tiny", &[70]);
        let e = s
            .read_cleaned(0, 1, Layout::GlobalPositions, Convention::Native)
            .unwrap_err();
        assert!(e.to_string().contains("set_finish"), "{e}");
        let wrap = Finish {
            wrap: true,
            ..Finish::game_ready()
        };
        let e = s.set_finish(wrap).unwrap_err();
        assert!(
            matches!(e, Error::InvalidArgument(_)) && e.to_string().contains("cannot wrap"),
            "{e}"
        );
        let mut bad = Finish::game_ready();
        bad.contacts.height = 5.0;
        assert!(s
            .set_finish(bad)
            .unwrap_err()
            .to_string()
            .contains("contact height"));
        bad = Finish {
            fps: Some(500.0),
            ..Finish::game_ready()
        };
        assert!(s
            .set_finish(bad)
            .unwrap_err()
            .to_string()
            .contains("frame rate"));
        s.set_finish(Finish::game_ready()).unwrap();
        s.set_finish(Finish::game_ready()).unwrap();
        let e = s.set_finish(finish(None)).unwrap_err();
        assert!(matches!(e, Error::WrongState(_)), "{e}");
        let e = s
            .read_cleaned(0, 1, Layout::GlobalPositions, Convention::Native)
            .unwrap_err();
        assert!(
            matches!(&e, Error::WrongState(m) if m.contains("not settled yet")),
            "{e}"
        );
        s.pump(2).unwrap();
        assert_eq!(s.ready(), 40);
        // Before the timeline is complete the last frames wait for their contacts.
        assert!(s.settled() < 40, "{}", s.settled());
        let e = s
            .read_cleaned(0, 41, Layout::GlobalPositions, Convention::Native)
            .unwrap_err();
        assert!(matches!(e, Error::WrongState(_)), "{e}");
        assert!(matches!(
            s.push(Segment::new("a person waves.", 10)),
            Err(Error::WrongState(_))
        ));
    }

    /// Fed a track frame by frame, the slot settler decides only values the whole track's
    /// `clean_spans` gives, and everything once the track's end is known.
    #[test]
    fn settle_slot_decides_what_clean_spans_gives() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut decided = 0;
        for case in 0..400 {
            let n = 1 + case % 37;
            let min = 1 + case % 4;
            // Runs of random lengths 1..=4, so short spans and gaps are frequent.
            let mut track = Vec::new();
            let mut v = case % 2 == 0;
            while track.len() < n {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                track.extend(std::iter::repeat_n(v, 1 + (state % 4) as usize));
                v = !v;
            }
            track.truncate(n);
            let mut want = track.clone();
            contacts::clean_spans(&mut want, min);
            let (mut cut, mut done) = (0, 0);
            for known in 0..=n {
                let end = (known == n).then_some(n);
                let (vals, next) = settle_slot(|t| track[t], cut, known, end, min);
                assert!(cut + vals.len() >= done, "{track:?} {min}: undecided again");
                assert_eq!(
                    vals[..],
                    want[cut..cut + vals.len()],
                    "{track:?} min {min} known {known}"
                );
                done = cut + vals.len();
                cut = next;
            }
            assert_eq!(done, n, "{track:?} {min}");
            decided += n;
        }
        assert!(decided > 5000);
    }

    /// A playhead that follows the settled frames with a window of 5 frames drops the held and
    /// the cleaned frames behind it, keeps what the next settle reads, and changes no bit of the
    /// frames read (flame_tiny: absolute root, so the held frames decode the same after drops).
    #[test]
    fn a_short_window_drops_behind_the_playhead_and_changes_nothing() {
        let mut full = stream("flame_tiny", &[70, 45]);
        full.set_finish(finish(Some(30.0))).unwrap();
        full.pump(usize::MAX).unwrap();
        let mut s = stream("flame_tiny", &[70, 45]);
        s.params.window = 5;
        s.set_finish(finish(Some(30.0))).unwrap();
        let (mut next, mut dropped) = (0, 0);
        while s.pump(1).unwrap().steps > 0 {
            while next < s.settled() {
                for l in [Layout::GlobalPositions, Layout::GlobalQuatXyzw] {
                    let a = s.read_cleaned(next, 1, l, Convention::Unity).unwrap();
                    let b = full.read_cleaned(next, 1, l, Convention::Unity).unwrap();
                    assert_eq!(bits(&a), bits(&b), "frame {next} {l:?}");
                }
                next += 1;
            }
            // The playhead at the last settled frame's time, in timeline frames.
            s.set_playhead((next * 2 / 3).min(s.ready())).unwrap();
            dropped = dropped.max(s.first_settled());
        }
        assert_eq!(next, full.settled());
        assert!(dropped > 100, "{dropped}");
        let e = s
            .read_cleaned(0, 1, Layout::GlobalPositions, Convention::Unity)
            .unwrap_err();
        assert!(e.to_string().contains("were dropped"), "{e}");
    }
}
