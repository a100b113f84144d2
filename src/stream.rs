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

use std::collections::VecDeque;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use crate::error::{invalid_arg, Error, Result};
use crate::models::Model;
use crate::motion::humanml263::RootStart;
use crate::motion::{Convention, Format, Layout, Poses};
use crate::session::{Session, SessionParams, Which};
use crate::stages::{Stage, PART_COUNT};
use crate::targets::PositionTargets;

/// One prompt on the timeline, how many frames it lasts and, for families that read them
/// (FineMoGen), what single body parts do (`parts[BodyPart as usize]`, `None` = the part
/// follows `prompt`). Other families refuse part texts when the segment's first chunk starts.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Segment {
    pub prompt: String,
    pub frames: usize,
    pub parts: [Option<String>; PART_COUNT],
}

impl Segment {
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
}

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
        if model.is_latent() {
            crate::targets::supported(&model).map_err(|e| {
                invalid_arg!(
                    "a stream continues each chunk from the frames before it; this {} model \
                     samples a latent, so it can only steer towards them with position targets, \
                     and {}",
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
                "overlap {} must be in 1..{chunk} (the chunk's frames)",
                params.overlap
            ));
        }
        if params.session.frames.is_some() {
            return Err(invalid_arg!(
                "a stream's chunks set their own frame counts: leave SessionParams::frames unset"
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
            current: None,
            anchor: RootStart::ORIGIN,
            decoded: Default::default(),
            cancel: Arc::new(AtomicBool::new(false)),
            quats: Default::default(),
        })
    }

    /// A flag another thread may raise to abandon the step a [`Stream::pump`] is running: the
    /// pump returns [`Error::Cancelled`] within one transformer layer and the stream is as it
    /// was before that step, so pumping again gives the bits of a stream never cancelled. A
    /// flag raised between pumps cancels the next step.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.cancel)
    }

    pub fn model(&self) -> &Arc<Model> {
        &self.model
    }

    /// Frames per chunk.
    pub fn chunk_frames(&self) -> usize {
        self.chunk
    }

    /// Appends a segment to the timeline.
    pub fn push(&mut self, segment: Segment) -> Result<()> {
        segment.check()?;
        self.segments.push_back((segment, 0));
        Ok(())
    }

    /// Ends the current segment at the next chunk boundary (the end of the chunk being
    /// generated, or the frames ready when none is), drops the segments queued after it and
    /// pushes `segment` in their place.
    pub fn interrupt(&mut self, segment: Segment) -> Result<()> {
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
            return Ok(false);
        };
        let dim = self.model.motion_dim();
        let have = self.features.len() / dim;
        let kept = self.params.overlap.min(have);
        let new = (seg.frames - done).min(self.chunk - kept);
        let frames = kept + new;
        let params = SessionParams {
            frames: Some(frames),
            seed: chunk_seed(self.params.session.seed, self.chunks),
            ..self.params.session.clone()
        };
        let mut session = Session::new(Arc::clone(&self.model), &params)?;
        session.share_cancel_flag(Arc::clone(&self.cancel));
        if seg.has_parts() {
            session.set_prompt_stages(&[Stage {
                text: seg.prompt.clone(),
                frames,
                parts: seg.parts.clone(),
            }])?;
        } else {
            session.set_prompt(&seg.prompt)?;
        }
        let mut frame = Rebase::IDENTITY;
        if kept > 0 && self.model.is_latent() {
            // A latent cannot keep frames: the chunk is steered towards the kept frames' joint
            // positions (the family's position targets, MoLA's MPGD), and only its new frames
            // are appended. humanml263 decodes from the canonical start, as the chunk does.
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
            session.set_position_targets(targets)?;
        } else if kept > 0 {
            let mut reference = self.features[(have - kept) * dim..].to_vec();
            if self.model.motion_format() == Format::Smpl24Rot6d {
                let mut first = reference[..dim].to_vec();
                self.root_channels(&mut first, |rows| {
                    frame = Rebase::canonical(rows);
                });
                self.root_channels(&mut reference, |rows| frame.apply(rows, dim));
            }
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
        });
        Ok(true)
    }

    /// Appends the finished chunk's new frames, back in the stream's frame.
    fn finish_chunk(&mut self) -> Result<()> {
        let mut c = self.current.take().expect("a chunk is running");
        let dim = self.model.motion_dim();
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
        let added = frames - c.kept;
        self.features.extend_from_slice(&new);
        self.held_changed();
        if let Some((_, done)) = self.segments.front_mut() {
            *done += added;
        }
        self.chunks += 1;
        Ok(())
    }

    /// Runs `f` on `rows` with the root channels (0..9: translation and root rotation rows) in
    /// the format's own units: a normalised model's features are de-normalised around it.
    fn root_channels(&self, rows: &mut [f32], f: impl FnOnce(&mut [f32])) {
        const ROOT: usize = 9;
        let dim = self.model.motion_dim();
        let opts = self.model.read_options(0.0, true);
        let Some(norm) = opts.normalization else {
            return f(rows);
        };
        let (mean, std) = (&norm.mean[..ROOT], &norm.std[..ROOT]);
        for row in rows.chunks_exact_mut(dim) {
            for c in 0..ROOT {
                row[c] = (row[c] as f64 * std[c] as f64 + mean[c] as f64) as f32;
            }
        }
        f(rows);
        for row in rows.chunks_exact_mut(dim) {
            for c in 0..ROOT {
                row[c] = ((row[c] as f64 - mean[c] as f64) / std[c] as f64) as f32;
            }
        }
    }

    /// Drops frames more than `window` before the playhead (keeping the overlap the next chunk
    /// needs), re-anchoring relative formats.
    fn drop_old(&mut self) -> Result<()> {
        let dim = self.model.motion_dim();
        let keep_from = self
            .playhead
            .saturating_sub(self.params.window)
            .min(self.ready().saturating_sub(self.params.overlap));
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
        let Some(order) = layout.quat_order() else {
            return self.poses(first, count)?.layout(layout, convention);
        };
        self.check_range(first, count)?;
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
                "frames {first}..{end} are not generated yet ({} ready): pump more",
                self.ready()
            )));
        }
        Ok(())
    }
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
