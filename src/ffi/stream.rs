//! The C ABI of [`crate::stream`]: continuous motion from a timeline of prompts. A stream
//! generates chunk after chunk, each keeping the last frames of the one before, from segments
//! the caller pushes at any time; the caller spends a bounded number of denoiser steps per
//! [`flame_stream_pump`] (for example once per game frame) and reads frames by their position
//! on the timeline.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, TryLockError};

use super::cleanup::{finish_arg, FlameCleanupParams};
use super::errors::{catch_quietly, guard, Fail};
use super::handles::{model_ref, FlameModel};
use super::poses::FlameLayout;
use super::{
    check_size, default_session_params, session_params, stage_arg, str_arg, struct_arg, write_out,
    FlameSessionParams, FlameStage, FlameStatus,
};
use crate::error::{invalid_arg, Error};
use crate::motion::Layout;
use crate::stream::{PumpReport, Segment, Stream, StreamParams};

/// A stream: a timeline of prompt segments, the frames generated from it and the chunk being
/// generated. Used by one thread at a time: a call while another thread is inside a call on the
/// same stream fails with `FLAME_STATUS_WRONG_STATE` instead of waiting (only
/// [`flame_stream_cancel`] may run on another thread). The stream keeps its model alive.
pub struct FlameStream {
    stream: Mutex<Stream>,
    cancel: Arc<AtomicBool>,
}

/// Settings of a stream. Initialise with [`flame_stream_params_default`]; zero (or a negative
/// `guidance`) means the default.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameStreamParams {
    /// `sizeof(FlameStreamParams)`.
    pub struct_size: u32,
    /// Frames per chunk, the kept ones included; 0 = the model's default frame count (at most
    /// its maximum). More than `FlameModelInfo.max_frames` is `INVALID_ARGUMENT`.
    pub chunk: u32,
    /// Frames of the motion so far each chunk keeps (and continues from): 1 to `chunk` − 1;
    /// 0 = default (20, one second at 20 fps).
    pub overlap: u32,
    /// Frames [`flame_stream_pump`] keeps ready ahead of the playhead: it generates while fewer
    /// are; 0 = default (60).
    pub lookahead: u32,
    /// Frames kept behind the playhead; older ones are dropped (reading them is
    /// `INVALID_ARGUMENT`); 0 = default (1200).
    pub window: u32,
    /// Sampler steps of every chunk; 0 = model default.
    pub steps: u32,
    /// A `FlameSampler` value.
    pub sampler: i32,
    /// Classifier-free guidance scale; negative = model default.
    pub guidance: f32,
    /// Seed of the stream; each chunk's noise comes from it and the chunk's index.
    pub seed: u64,
    /// Worker threads the stream creates and owns: 1 to `FLAME_MAX_THREADS`, or 0 =
    /// one per core (at most `FLAME_MAX_THREADS`); more is `INVALID_ARGUMENT`. The
    /// frames do not depend on it.
    pub threads: u32,
}

/// Where a stream stands, from [`flame_stream_pump`] or [`flame_stream_status`]. Set
/// `struct_size = sizeof(FlameStreamStatus)` first.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameStreamStatus {
    /// Set by the caller to `sizeof(FlameStreamStatus)`.
    pub struct_size: u32,
    /// Denoiser steps run by this pump (0 from [`flame_stream_status`]).
    pub steps: u32,
    /// Frames generated on the timeline so far: frames `first_frame..ready` can be read.
    pub ready: u64,
    /// The first frame still held (older ones were dropped).
    pub first_frame: u64,
    /// The playhead ([`flame_stream_set_playhead`]).
    pub playhead: u64,
    /// 1 when fewer than `lookahead` frames are ready ahead of the playhead and no pushed
    /// segment is left to generate them from: push more.
    pub starving: u32,
}

impl FlameStream {
    /// Runs `f` on the stream; a stream busy on another thread is an error, not a wait.
    pub(super) fn with<R>(
        &self,
        f: impl FnOnce(&mut Stream) -> Result<R, Fail>,
    ) -> Result<R, Fail> {
        let mut s = match self.stream.try_lock() {
            Ok(g) => g,
            Err(TryLockError::WouldBlock) => {
                return Err(
                    Error::WrongState("the stream is in use by another thread".into()).into(),
                )
            }
            Err(TryLockError::Poisoned(_)) => {
                return Err(Error::WrongState(
                    "the stream is unusable after an internal error; free it".into(),
                )
                .into())
            }
        };
        f(&mut s)
    }
}

pub(super) unsafe fn stream_ref<'a>(stream: *const FlameStream) -> Result<&'a FlameStream, Fail> {
    stream
        .as_ref()
        .ok_or_else(|| invalid_arg!("`stream` is NULL").into())
}

fn default_stream_params() -> FlameStreamParams {
    let d = StreamParams::default();
    let s = default_session_params();
    FlameStreamParams {
        struct_size: std::mem::size_of::<FlameStreamParams>() as u32,
        chunk: 0,
        overlap: d.overlap as u32,
        lookahead: d.lookahead as u32,
        window: d.window as u32,
        steps: s.steps,
        sampler: s.sampler,
        guidance: s.guidance,
        seed: s.seed,
        threads: s.threads,
    }
}

/// The Rust parameters a C struct asks for: the session fields go through the translation of
/// `FlameSessionParams` (the frame count stays unset: chunks set their own).
fn stream_params(p: &FlameStreamParams) -> Result<StreamParams, Fail> {
    let d = StreamParams::default();
    let or_default = |v: u32, default: usize| if v == 0 { default } else { v as usize };
    let session = FlameSessionParams {
        frames: 0,
        steps: p.steps,
        sampler: p.sampler,
        guidance: p.guidance,
        seed: p.seed,
        threads: p.threads,
        ..default_session_params()
    };
    Ok(StreamParams {
        chunk: p.chunk as usize,
        overlap: or_default(p.overlap, d.overlap),
        lookahead: or_default(p.lookahead, d.lookahead),
        window: or_default(p.window, d.window),
        // SAFETY: `respacing` is NULL (the default's).
        session: unsafe { session_params(&session)? },
    })
}

fn status(r: PumpReport, s: &Stream) -> FlameStreamStatus {
    FlameStreamStatus {
        struct_size: std::mem::size_of::<FlameStreamStatus>() as u32,
        steps: u32::try_from(r.steps).unwrap_or(u32::MAX),
        ready: r.ready as u64,
        first_frame: s.first_frame() as u64,
        playhead: s.playhead() as u64,
        starving: r.starving as u32,
    }
}

/// Checks a caller's status struct before any work is done.
unsafe fn check_status_out(out: *const FlameStreamStatus) -> Result<(), Fail> {
    if let Some(o) = out.as_ref() {
        check_size(
            o.struct_size,
            std::mem::size_of::<FlameStreamStatus>(),
            "status",
        )?;
    }
    Ok(())
}

fn frame_arg(v: u64, name: &str) -> Result<usize, Fail> {
    usize::try_from(v).map_err(|_| invalid_arg!("`{name}` {v} is out of range").into())
}

/// Fills `*params` with the defaults: the model's default frame count per chunk, 20 frames of
/// overlap, 60 of lookahead, a window of 1200, the model file's steps, sampler and guidance,
/// seed 0, one thread per core.
///
/// # Safety
/// `params` points to writable memory for a `FlameStreamParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_params_default(
    params: *mut FlameStreamParams,
) -> FlameStatus {
    guard(|| write_out(params, default_stream_params(), "params"))
}

/// Starts a stream over `model` with an empty timeline. `params` may be NULL for the defaults.
/// Each chunk keeps the last `overlap` frames of the motion so far (the family's editing:
/// those frames exactly, the rest generated); a latent model (`FlameModelInfo.latent`: MoLA)
/// cannot keep frames and is steered towards their joint positions instead (position targets),
/// so its seams are not exact. `INVALID_ARGUMENT` when the model can do neither (MLD: no
/// gradient of its decoder), when `chunk` exceeds the model's maximum frames, when `overlap`
/// is not below `chunk`, or for settings a session would refuse (sampler, threads). Free it
/// with [`flame_stream_free`].
///
/// # Safety
/// `model` is a live model; `params` is NULL or a valid `FlameStreamParams`; `stream` points
/// to writable memory for a pointer.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_new(
    model: *const FlameModel,
    params: *const FlameStreamParams,
    stream: *mut *mut FlameStream,
) -> FlameStatus {
    guard(|| {
        let m = model_ref(model)?;
        if stream.is_null() {
            return Err(invalid_arg!("`stream` is NULL").into());
        }
        let p = if params.is_null() {
            stream_params(&default_stream_params())?
        } else {
            stream_params(struct_arg(params, |p| p.struct_size, "params")?)?
        };
        let s = Stream::new(Arc::clone(m.model()), &p)?;
        let handle = Box::new(FlameStream {
            cancel: s.cancel_flag(),
            stream: Mutex::new(s),
        });
        write_out(stream, Box::into_raw(handle), "stream")
    })
}

/// Hands the segment a `FlameStage` describes to `add` (push or interrupt).
///
/// # Safety
/// As [`flame_stream_push_stage`].
unsafe fn stage_segment(
    stream: *mut FlameStream,
    stage: *const FlameStage,
    add: fn(&mut Stream, Segment) -> crate::error::Result<()>,
) -> Result<(), Fail> {
    let s = stream_ref(stream)?;
    let seg = Segment::from_stage(stage_arg(
        struct_arg(stage, |st| st.struct_size, "stage")?,
        "stage",
    )?);
    s.with(|st| Ok(add(st, seg)?))
}

/// Frees a stream and joins its worker threads; NULL is ignored.
///
/// # Safety
/// `stream` is NULL or a live stream not in use by another thread.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_free(stream: *mut FlameStream) {
    catch_quietly(|| {
        if !stream.is_null() {
            drop(Box::from_raw(stream));
        }
    });
}

/// Appends a segment to the timeline: `prompt` (UTF-8, NUL-terminated) for `frames` frames
/// (at least 1), starting where the segments before it end.
///
/// # Safety
/// `stream` is a live stream; `prompt` a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_push(
    stream: *mut FlameStream,
    prompt: *const std::ffi::c_char,
    frames: u32,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        let prompt = str_arg(prompt, "prompt")?;
        s.with(|st| Ok(st.push(Segment::new(prompt, frames as usize))?))
    })
}

/// Ends the current segment at the next chunk boundary (the end of the chunk being generated,
/// or the frames ready when none is), drops the segments queued after it and appends `prompt`
/// for `frames` frames (at least 1) in their place: a change of action without waiting for the
/// rest of the current segment.
///
/// # Safety
/// `stream` is a live stream; `prompt` a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_interrupt(
    stream: *mut FlameStream,
    prompt: *const std::ffi::c_char,
    frames: u32,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        let prompt = str_arg(prompt, "prompt")?;
        s.with(|st| Ok(st.interrupt(Segment::new(prompt, frames as usize))?))
    })
}

/// [`flame_stream_push`] with part texts: a segment of `stage->frames` frames whose whole-body
/// text is `stage->text` and whose body parts may have their own texts (NULL or empty: the
/// part follows `text`). FineMoGen reads them; other families refuse part texts with
/// `INVALID_ARGUMENT` when the segment's first chunk starts (in [`flame_stream_pump`]), and
/// take a stage without them as a plain prompt. Set `stage->struct_size`.
///
/// # Safety
/// `stream` is a live stream; `stage` points to a `FlameStage` whose non-NULL strings are
/// NUL-terminated.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_push_stage(
    stream: *mut FlameStream,
    stage: *const FlameStage,
) -> FlameStatus {
    guard(|| stage_segment(stream, stage, Stream::push))
}

/// [`flame_stream_interrupt`] with part texts (see [`flame_stream_push_stage`]).
///
/// # Safety
/// `stream` is a live stream; `stage` points to a `FlameStage` whose non-NULL strings are
/// NUL-terminated.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_interrupt_stage(
    stream: *mut FlameStream,
    stage: *const FlameStage,
) -> FlameStatus {
    guard(|| stage_segment(stream, stage, Stream::interrupt))
}

/// Asks the [`flame_stream_pump`] running on another thread to stop: it returns
/// `FLAME_STATUS_CANCELLED` within one transformer layer, and the step it was running leaves
/// no trace, so pumping again gives the bits of a stream never cancelled. May be called from
/// any thread at any time; with no pump running, the next pump's first step is cancelled.
///
/// # Safety
/// `stream` is a live stream.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_cancel(stream: *const FlameStream) -> FlameStatus {
    guard(|| {
        stream_ref(stream)?.cancel.store(true, Ordering::SeqCst);
        Ok(())
    })
}

/// Moves the playhead (the frame being played) to timeline frame `frame`, at most the frames
/// ready (`INVALID_ARGUMENT` past them). Frames more than `window` before it are dropped, and
/// [`flame_stream_pump`] keeps `lookahead` frames ready after it.
///
/// # Safety
/// `stream` is a live stream.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_set_playhead(
    stream: *mut FlameStream,
    frame: u64,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        let frame = frame_arg(frame, "frame")?;
        s.with(|st| Ok(st.set_playhead(frame)?))
    })
}

/// Runs at most `max_steps` denoiser steps (`UINT32_MAX`: as many as needed) towards
/// `lookahead` frames ready ahead of the playhead, starting chunks as the pushed segments
/// allow; it returns early when that many are ready or no segment is left. A chunk's frames
/// become readable when its last step has run. `*status` (may be NULL; set its `struct_size`
/// first) receives the steps run and where the stream stands. The frames do not depend on how
/// the steps are spread over calls.
///
/// # Safety
/// `stream` is a live stream; `status` is NULL or points to a writable `FlameStreamStatus`.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_pump(
    stream: *mut FlameStream,
    max_steps: u32,
    status: *mut FlameStreamStatus,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        check_status_out(status)?;
        let st = s.with(|st| {
            let r = st.pump(max_steps as usize)?;
            Ok(self::status(r, st))
        })?;
        if !status.is_null() {
            status.write(st);
        }
        Ok(())
    })
}

/// Where the stream stands, without running a step (`steps` is 0).
///
/// # Safety
/// `stream` is a live stream; `status` points to a writable `FlameStreamStatus` whose
/// `struct_size` is set.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_status(
    stream: *const FlameStream,
    status: *mut FlameStreamStatus,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        if status.is_null() {
            return Err(invalid_arg!("`status` is NULL").into());
        }
        check_status_out(status)?;
        let st = s.with(|st| {
            let r = st.pump(0)?;
            Ok(self::status(r, st))
        })?;
        status.write(st);
        Ok(())
    })
}

/// Reads timeline frames `first_frame..first_frame + count` in a [`FlameLayout`] (0 = the
/// model's features, in the stream's frame: the root path continues across chunks), converted
/// to a `FlameConvention` (ignored for features). Quaternion layouts are sign-continuous over
/// the whole timeline, whatever ranges are read (one frame per call reads the values of one
/// whole read) and whatever frames were dropped. `flags` must be 0: the read flags of sessions
/// (`FLAME_READ_SMOOTH`, `FLAME_READ_RAW_SIGNS`) are not supported by streams.
///
/// Frames not generated yet are `WRONG_STATE` (pump more); frames dropped behind the playhead
/// are `INVALID_ARGUMENT` (the message names the window). The length protocol is
/// `flame_session_read`'s: with `out` NULL, `*out_len` receives the required number
/// of floats and nothing else is done; otherwise `len` must be at least that
/// (`BUFFER_TOO_SMALL` otherwise, with `*out_len` set to the required length) and `*out_len`
/// receives the number written.
///
/// # Safety
/// `stream` is a live stream; `out` is NULL or points to `len` writable floats; `out_len`
/// points to a writable `size_t`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_stream_read(
    stream: *const FlameStream,
    first_frame: u64,
    count: u32,
    layout: i32,
    convention: i32,
    flags: u32,
    out: *mut f32,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let s = stream_ref(stream)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        if flags != 0 {
            return Err(invalid_arg!(
                "read flags {flags:#x}: streams take none (smoothing and raw quaternion signs \
                 are not supported)"
            )
            .into());
        }
        let convention = super::poses::convention(convention)?;
        let layout = match layout {
            l if l == FlameLayout::Features as i32 => None,
            l => Some(
                usize::try_from(l)
                    .ok()
                    .and_then(|l| l.checked_sub(1))
                    .and_then(|l| Layout::ALL.get(l).copied())
                    .ok_or_else(|| invalid_arg!("unknown layout {l} (a FlameLayout, 0 to 9)"))?,
            ),
        };
        let first = frame_arg(first_frame, "first_frame")?;
        let count = count as usize;
        s.with(|st| {
            let values = match layout {
                // The range is checked either way (count 0 reads nothing).
                None => st.features(first, count)?.to_vec(),
                Some(_) if count == 0 => st.features(first, 0)?.to_vec(),
                Some(l) => st.read(first, count, l, convention)?,
            };
            if out.is_null() {
                out_len.write(values.len());
                return Ok(());
            }
            if len < values.len() {
                out_len.write(values.len());
                return Err(Fail::BufferTooSmall {
                    needed: values.len(),
                    given: len,
                    unit: "floats",
                });
            }
            std::ptr::copy_nonoverlapping(values.as_ptr(), out, values.len());
            out_len.write(values.len());
            Ok(())
        })
    })
}

/// Declares the stream's timeline complete: pushing or interrupting afterwards is
/// `WRONG_STATE`. Once the pushed segments are generated every frame's cleanup settles (the
/// last contact spans and swings end with the timeline); until then, the frames of an open
/// span or swing wait for it to end (see [`flame_stream_read_cleaned`]).
///
/// # Safety
/// `stream` is a live stream.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_close(stream: *const FlameStream) -> FlameStatus {
    guard(|| {
        stream_ref(stream)?.with(|st| {
            st.close();
            Ok(())
        })
    })
}

/// Declares the stream's timeline complete, as [`flame_stream_close`], and makes it loop: after
/// the pushed segments the stream generates a bridge of `bridge_frames` frames (the last
/// segment's prompt) whose end runs into the timeline's first frames, moved by the loop's root
/// motion (a walking loop walks on). It is made as `flame generate --loop` makes a clip: a
/// probe continues the timeline to see where it goes, then an edit keeps the timeline's last
/// `overlap` frames before the bridge and its first 0.5 s after it. The bridge costs two
/// chunks' steps; frames already generated never change, the timeline grows by
/// `bridge_frames`, and cleaned reads settle to its end as after [`flame_stream_close`].
/// Playing frame 0 after the last continues the motion (an engine moves the character by the
/// root travel of the timeline). `INVALID_ARGUMENT` for a latent model (MLD, MoLA) and for a
/// bridge shorter than 1 s or longer than the model's frames allow (overlap + bridge + 0.5 s);
/// `WRONG_STATE` when the stream is already closed, has no segment, or dropped frame 0.
///
/// # Safety
/// `stream` is a live stream.
#[no_mangle]
pub unsafe extern "C" fn flame_stream_close_looped(
    stream: *const FlameStream,
    bridge_frames: u32,
) -> FlameStatus {
    guard(|| stream_ref(stream)?.with(|st| Ok(st.close_looped(bridge_frames as usize)?)))
}

/// [`flame_stream_read`] with post-processing: frames `first_frame..first_frame + count` of
/// the timeline after `cleanup` (NULL = the raw poses, exactly `flame_stream_read`), at the
/// cleanup's frame rate: frame `k` is at `k / fps` seconds of the timeline (with `fps` 0, the
/// timeline's own frames). The first call that passes a cleanup sets the stream's, once: a
/// frame handed out never changes, so later calls must pass the same values
/// (`WRONG_STATE` otherwise), and frame 0 must still be held. A loop wrap is
/// `INVALID_ARGUMENT` (a stream has no end to wrap); so is layout 0 (features are never cleaned).
///
/// A frame is readable once its cleanup is final ("settled"): its foot contacts are decided,
/// and, with feet locked, its contact span has ended (its pin is the span's mean) and, in a
/// swing, the next span has ended (the swing is redrawn pin to pin). Frames not settled yet
/// are `WRONG_STATE` (pump more; the error message says how many are settled). After
/// [`flame_stream_close`], every generated frame settles. The floor (`ground`) is the lowest
/// contact point of the first chunk, fixed for the whole stream. Length protocol as
/// `flame_stream_read`.
///
/// # Safety
/// As `flame_stream_read`; `cleanup` is NULL or points to a valid `FlameCleanupParams`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_stream_read_cleaned(
    stream: *const FlameStream,
    first_frame: u64,
    count: u32,
    layout: i32,
    convention: i32,
    cleanup: *const FlameCleanupParams,
    out: *mut f32,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    if cleanup.is_null() {
        return flame_stream_read(
            stream,
            first_frame,
            count,
            layout,
            convention,
            0,
            out,
            len,
            out_len,
        );
    }
    guard(|| {
        let s = stream_ref(stream)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        let finish = finish_arg(cleanup)?;
        let convention = super::poses::convention(convention)?;
        let layout = usize::try_from(layout)
            .ok()
            .and_then(|l| l.checked_sub(1))
            .and_then(|l| Layout::ALL.get(l).copied())
            .ok_or_else(|| {
                invalid_arg!(
                    "layout {layout}: cleaned reads take a pose layout (1..=9); features are \
                     never cleaned (flame_stream_read)"
                )
            })?;
        let first = frame_arg(first_frame, "first_frame")?;
        s.with(|st| {
            st.set_finish(finish)?;
            let values = st.read_cleaned(first, count as usize, layout, convention)?;
            super::copy_out(&values, out, len, out_len, "floats")
        })
    })
}
