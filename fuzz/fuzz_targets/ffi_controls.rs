//! The C ABI's controls added after `ffi_params`, with arbitrary field values: target params
//! and position/task targets, prompt stages (`FlameStage` arrays of any declared stride), glTF
//! export params, and streams (`FlameStreamParams`, then a fuzzed sequence of push, interrupt,
//! stage pushes, playhead moves, pumps, status and reads, cancel). Every model family of the
//! fixtures is used. Every call must return a status; `FLAME_STATUS_INTERNAL` (a caught panic)
//! counts as a finding, as does any read or write past a buffer the caller declared.
#![no_main]

use std::ffi::{c_char, CString};
use std::mem::{offset_of, size_of};
use std::ptr;
use std::sync::OnceLock;

use flame::ffi::*;
use flame_fuzz::{bounded_threads, ok, Input, MODEL_FIXTURES};
use libfuzzer_sys::fuzz_target;

/// Sessions and stream chunks longer than this are created but not stepped (a step costs
/// ~frames², and instrumented model arithmetic is most of an execution); pumps run at most 2
/// steps.
const MAX_STEPPED_FRAMES: u32 = 12;

struct Model {
    ptr: *mut FlameModel,
    feature_dim: u32,
    joints: u32,
}

struct Models(Vec<Model>);
// SAFETY: models are immutable after loading and documented as shareable across threads.
unsafe impl Send for Models {}
unsafe impl Sync for Models {}

fn models() -> &'static Models {
    static M: OnceLock<Models> = OnceLock::new();
    M.get_or_init(|| {
        let load = |bytes: &&[u8]| {
            let mut m = ptr::null_mut();
            let s = unsafe {
                flame_model_load_from_memory(bytes.as_ptr(), bytes.len(), ptr::null(), &mut m)
            };
            assert_eq!(s, FlameStatus::Ok);
            let mut info: FlameModelInfo = unsafe { std::mem::zeroed() };
            info.struct_size = size_of::<FlameModelInfo>() as u32;
            assert_eq!(unsafe { flame_model_info(m, &mut info) }, FlameStatus::Ok);
            Model {
                ptr: m,
                feature_dim: info.feature_dim,
                joints: info.joint_count,
            }
        };
        Models(MODEL_FIXTURES.iter().map(load).collect())
    })
}

/// A parameter struct as the caller lays it out: `declared` bytes (its `struct_size`, at least
/// 4 and at most 64 past this library's struct, so a read past what the caller declared is an
/// AddressSanitizer report), fields written at their offsets as far as they fit.
struct Declared(Vec<u8>);

impl Declared {
    fn new<T>(declared: u32) -> Self {
        let n = (declared as usize).clamp(4, size_of::<T>() + 64);
        let mut b = Declared(vec![0u8; n]);
        b.put(0, declared);
        b
    }
    fn put<V: Copy>(&mut self, offset: usize, value: V) {
        let bytes =
            unsafe { std::slice::from_raw_parts(&value as *const V as *const u8, size_of::<V>()) };
        if let Some(dst) = self.0.get_mut(offset..) {
            let n = dst.len().min(bytes.len());
            dst[..n].copy_from_slice(&bytes[..n]);
        }
    }
    fn ptr<T>(&self) -> *const T {
        self.0.as_ptr().cast()
    }
}

/// A declared size: mostly this library's (so the call gets past the size check), sometimes
/// a newer header's larger one, sometimes anything.
fn struct_size<T>(input: &mut Input) -> u32 {
    let raw = input.u32();
    match raw % 8 {
        0 => raw >> 3,
        1 => size_of::<T>() as u32 + 8,
        _ => size_of::<T>() as u32,
    }
}

/// Strings a field can point to: texts the models read, blanks, and one from the input
/// (any bytes up to the first NUL, so possibly not UTF-8).
struct Texts {
    fixed: [CString; 4],
    fuzzed: CString,
}

impl Texts {
    fn new(input: &mut Input) -> Self {
        let raw: [u8; 12] = input.bytes();
        let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
        Texts {
            fixed: [
                c"a person walks forward".into(),
                c"".into(),
                c"   ".into(),
                c"raises the right arm".into(),
            ],
            fuzzed: CString::new(&raw[..end]).unwrap(),
        }
    }
    /// NULL, one of the fixed texts or the fuzzed one.
    fn pick(&self, b: u8) -> *const c_char {
        match b % 6 {
            0 => ptr::null(),
            5 => self.fuzzed.as_ptr(),
            i => self.fixed[i as usize - 1].as_ptr(),
        }
    }
}

/// `FlameStage` fields at their offsets; the struct is written as far as `buf` declares.
fn put_stage(buf: &mut Declared, at: usize, input: &mut Input, texts: &Texts, frames: u32) {
    buf.put(at + offset_of!(FlameStage, frames), frames);
    let fields = [
        offset_of!(FlameStage, text),
        offset_of!(FlameStage, head),
        offset_of!(FlameStage, stem),
        offset_of!(FlameStage, left_arm),
        offset_of!(FlameStage, right_arm),
        offset_of!(FlameStage, left_leg),
        offset_of!(FlameStage, right_leg),
        offset_of!(FlameStage, pelvis),
    ];
    let picks = input.u32();
    for (i, off) in fields.into_iter().enumerate() {
        // The whole-body text is mostly a real one; parts are mostly NULL.
        let b = (picks >> (3 * i)) as u8 & 7;
        let b = if i == 0 {
            b.max(1)
        } else {
            b.saturating_sub(2)
        };
        buf.put(at + off, texts.pick(b));
    }
}

/// One stage for a stream push: the caller's struct as declared.
fn stage(input: &mut Input, texts: &Texts) -> Declared {
    let declared = struct_size::<FlameStage>(input);
    let frames = input.u16() as u32;
    let mut buf = Declared::new::<FlameStage>(declared);
    put_stage(&mut buf, 0, input, texts, frames);
    buf
}

fn targets(input: &mut Input, session: *mut FlameSession, m: &Model, frames: u32) {
    let declared = struct_size::<FlameTargetParams>(input);
    let mut tp = Declared::new::<FlameTargetParams>(declared);
    tp.put(offset_of!(FlameTargetParams, scale), input.f32());
    tp.put(offset_of!(FlameTargetParams, schedule), input.i32() % 4);
    ok(unsafe { flame_session_set_target_params(session, tp.ptr()) });
    let mut back = FlameTargetParams {
        struct_size: 0,
        scale: 0.0,
        schedule: 0,
    };
    ok(unsafe { flame_session_target_params(session, &mut back) });

    // Position targets: a frame count around the session's, values from the input (NaN frees
    // a value when no mask is given), a mask that may not match.
    let per_frame = m.joints as usize * 3;
    let n_frames = input.u8() as usize % (frames as usize + 2);
    let len = match input.u8() % 4 {
        0 => n_frames * per_frame + 1,
        _ => n_frames * per_frame,
    };
    let values: Vec<f32> = (0..len)
        .map(|i| match input.0.get(i % input.0.len().max(1)) {
            Some(&b) if b % 5 == 0 => f32::NAN,
            Some(&b) => b as f32 / 64.0 - 2.0,
            None => 0.5,
        })
        .collect();
    let mask_kind = input.u8();
    let mask: Vec<u8> = (0..len + (mask_kind as usize >> 6))
        .map(|i| (i as u8) & mask_kind)
        .collect();
    let (mask_ptr, mask_len) = match mask_kind % 3 {
        0 => (ptr::null(), 0),
        1 => (mask.as_ptr(), len),
        _ => (mask.as_ptr(), mask.len()),
    };
    let convention = input.i32() % 5;
    ok(unsafe {
        flame_session_set_position_targets(
            session,
            values.as_ptr(),
            values.len(),
            mask_ptr,
            mask_len,
            convention,
        )
    });

    // Task targets from a reference of the model's features (or a wrong width).
    let ref_frames = input.u8() as u32 % (frames + 2);
    let dim = match input.u8() % 4 {
        0 => m.feature_dim + 1,
        1 => 0,
        _ => m.feature_dim,
    };
    let features: Vec<f32> = (0..ref_frames * dim)
        .map(|i| (i % 17) as f32 * 0.1)
        .collect();
    ok(unsafe {
        flame_session_set_task_targets(session, features.as_ptr(), ref_frames, dim, input.i32())
    });
    let mut loss = 0f64;
    ok(unsafe { flame_session_target_loss(session, &mut loss) });
    if input.u8() & 1 != 0 {
        ok(unsafe { flame_session_clear_position_targets(session) });
    }
    // The same values as a trajectory control (MotionLCM control files follow them; every
    // other model refuses).
    ok(unsafe {
        flame_session_set_control(
            session,
            values.as_ptr(),
            values.len(),
            mask_ptr,
            mask_len,
            convention,
        )
    });
    // Consistency latent tuning on what is set (a 1-step MotionLCM control session with a prompt
    // and a control tunes; everything else refuses), 0 to 2 iterations, with a report of any
    // declared size or none.
    let iterations = u32::from(input.u8() % 3);
    let mut report = Declared::new::<FlameTuningReport>(struct_size::<FlameTuningReport>(input));
    let report_ptr = if input.u8() & 1 != 0 {
        report.0.as_mut_ptr() as *mut FlameTuningReport
    } else {
        ptr::null_mut()
    };
    ok(unsafe { flame_session_tune_latent(session, iterations, report_ptr) });
    if input.u8() & 1 != 0 {
        ok(unsafe { flame_session_clear_control(session) });
    }
}

fn stages(input: &mut Input, session: *mut FlameSession, texts: &Texts, frames: u32) {
    let count = input.u8() as usize % 5;
    let declared = struct_size::<FlameStage>(input);
    // Every stage of an array declares the same size and the library steps by any size from
    // its own to 64 KiB (so the caller's array holds `count` strides); a size it refuses is
    // read in the first stage only.
    let stride = declared as usize;
    let valid = stride >= size_of::<FlameStage>() && stride <= 1 << 16;
    let mut buf = Declared::new::<FlameStage>(declared);
    if valid {
        buf.0.resize(stride * count.max(1), 0);
    }
    let split = input.u8() as u32;
    for i in 0..if valid { count } else { 1 } {
        let at = i * stride;
        buf.put(at, declared);
        // Stage lengths that mostly add up to the session's frames.
        let f = match (i, split % 4) {
            (_, 0) => input.u16() as u32,
            (0, _) if count > 1 => (split % frames.max(1)).max(1),
            (0, _) => frames,
            _ => frames.saturating_sub((split % frames.max(1)).max(1)) / (count as u32 - 1).max(1),
        };
        put_stage(&mut buf, at, input, texts, f);
    }
    ok(unsafe { flame_session_set_prompt_stages(session, buf.ptr(), count) });
}

fn gltf(input: &mut Input, session: *mut FlameSession, texts: &Texts) {
    let declared = struct_size::<FlameGltfParams>(input);
    let mut gp = Declared::new::<FlameGltfParams>(declared);
    gp.put(offset_of!(FlameGltfParams, container), input.i32() % 3);
    gp.put(offset_of!(FlameGltfParams, flags), input.u32() % 5);
    gp.put(offset_of!(FlameGltfParams, fps), input.f32());
    gp.put(offset_of!(FlameGltfParams, name), texts.pick(input.u8()));
    let params = if input.u8() & 1 != 0 {
        ptr::null()
    } else {
        gp.ptr()
    };
    let which = input.i32() % 3;
    let mut needed = 0usize;
    if !ok(unsafe {
        flame_session_write_gltf(session, which, params, ptr::null_mut(), 0, &mut needed)
    }) {
        return;
    }
    let len = match input.u8() % 4 {
        0 => needed.saturating_sub(1 + input.u8() as usize),
        _ => needed,
    };
    let mut out = vec![0u8; len];
    let mut written = usize::MAX;
    if ok(unsafe {
        flame_session_write_gltf(session, which, params, out.as_mut_ptr(), len, &mut written)
    }) {
        assert_eq!(written, needed);
        assert!(out.starts_with(b"glTF") || out.starts_with(b"{"));
    }
}

/// A status struct for the library to fill, with a fuzzed `struct_size` and a nonzero `steps`
/// (which `flame_stream_status` must set to 0).
fn status_out(input: &mut Input) -> FlameStreamStatus {
    FlameStreamStatus {
        struct_size: struct_size::<FlameStreamStatus>(input),
        steps: 1,
        ready: 0,
        first_frame: 0,
        playhead: 0,
        starving: 0,
    }
}

fn stream(input: &mut Input, m: &Model, texts: &Texts) {
    let declared = struct_size::<FlameStreamParams>(input);
    let mut p = Declared::new::<FlameStreamParams>(declared);
    let chunk = match input.u8() % 4 {
        0 => input.u32(),
        _ => input.u8() as u32 % (MAX_STEPPED_FRAMES + 1),
    };
    let overlap = match input.u8() % 4 {
        0 => input.u32(),
        _ => input.u8() as u32 % chunk.max(1),
    };
    let steps = input.u8() as u32 % 5;
    p.put(offset_of!(FlameStreamParams, chunk), chunk);
    p.put(offset_of!(FlameStreamParams, overlap), overlap);
    p.put(offset_of!(FlameStreamParams, lookahead), input.u16() as u32);
    p.put(offset_of!(FlameStreamParams, window), input.u16() as u32);
    p.put(offset_of!(FlameStreamParams, steps), steps);
    p.put(offset_of!(FlameStreamParams, sampler), input.i32() % 4);
    p.put(offset_of!(FlameStreamParams, guidance), input.f32());
    p.put(offset_of!(FlameStreamParams, seed), input.u64());
    p.put(
        offset_of!(FlameStreamParams, threads),
        bounded_threads(input.u32()),
    );
    let params = if input.u8() & 1 != 0 {
        ptr::null()
    } else {
        p.ptr()
    };
    let mut s = ptr::null_mut();
    if !ok(unsafe { flame_stream_new(m.ptr, params, &mut s) }) {
        assert!(s.is_null());
        return;
    }
    // Steps only run on short chunks of few steps (the defaults are the model's: long).
    let pumpable = !params.is_null()
        && declared as usize >= size_of::<FlameStreamParams>()
        && (1..=MAX_STEPPED_FRAMES).contains(&chunk)
        && steps > 0;
    for _ in 0..8 {
        let op = input.u8();
        match op % 10 {
            0 => {
                ok(unsafe { flame_stream_push(s, texts.pick(op >> 4), input.u16() as u32) });
            }
            1 => {
                ok(unsafe { flame_stream_interrupt(s, texts.pick(op >> 4), input.u8() as u32) });
            }
            2 => {
                let st = stage(input, texts);
                ok(unsafe { flame_stream_push_stage(s, st.ptr()) });
            }
            3 => {
                let st = stage(input, texts);
                ok(unsafe { flame_stream_interrupt_stage(s, st.ptr()) });
            }
            4 => {
                let frame = match op >> 4 {
                    0 => input.u64(),
                    _ => input.u8() as u64,
                };
                ok(unsafe { flame_stream_set_playhead(s, frame) });
            }
            5 if pumpable => {
                let mut status = status_out(input);
                let sp = if op & 16 != 0 {
                    ptr::null_mut()
                } else {
                    &mut status as *mut _
                };
                if ok(unsafe { flame_stream_pump(s, (op >> 5) as u32 % 3, sp) }) && !sp.is_null() {
                    assert!(status.steps <= 2);
                    assert!(status.first_frame <= status.ready);
                }
            }
            6 => {
                let mut status = status_out(input);
                if ok(unsafe { flame_stream_status(s, &mut status) }) {
                    assert_eq!(status.steps, 0);
                }
            }
            7 => {
                let first = match op >> 4 {
                    0 => input.u64(),
                    _ => input.u8() as u64,
                };
                let count = match op >> 6 {
                    0 => input.u32(),
                    _ => input.u8() as u32,
                };
                let (layout, convention, flags) =
                    (input.i32() % 8, input.i32() % 5, input.u8() as u32 % 4);
                let read = |out: *mut f32, len: usize, out_len: &mut usize| unsafe {
                    flame_stream_read(
                        s, first, count, layout, convention, flags, out, len, out_len,
                    )
                };
                let mut needed = 0usize;
                if ok(read(ptr::null_mut(), 0, &mut needed)) {
                    let len = (needed + input.u8() as usize % 3)
                        .saturating_sub(1)
                        .min(1 << 20);
                    let mut out = vec![0f32; len];
                    let mut written = usize::MAX;
                    if ok(read(out.as_mut_ptr(), len, &mut written)) {
                        assert_eq!(written, needed);
                    }
                }
            }
            8 => {
                ok(unsafe { flame_stream_cancel(s) });
            }
            9 if op & 16 != 0 => {
                // Short bridges only (the frames of a bridge's two passes are stepped).
                ok(unsafe { flame_stream_close_looped(s, input.u8() as u32 % 48) });
            }
            9 => {
                ok(unsafe { flame_stream_close(s) });
            }
            _ => {}
        }
    }
    unsafe { flame_stream_free(s) };
}

fuzz_target!(|data: &[u8]| {
    let mut input = Input(data);
    let which = input.u8() as usize % MODEL_FIXTURES.len();
    let actions = input.u8();
    let m = &models().0[which];
    let texts = Texts::new(&mut input);

    if actions & 8 != 0 {
        stream(&mut input, m, &texts);
        return;
    }

    let frames = 1 + input.u8() as u32 % 40;
    let mut sp: FlameSessionParams = unsafe { std::mem::zeroed() };
    assert_eq!(
        unsafe { flame_session_params_default(&mut sp) },
        FlameStatus::Ok
    );
    sp.frames = frames;
    sp.steps = 2;
    sp.threads = 1;
    let mut session = ptr::null_mut();
    if !ok(unsafe { flame_session_new(m.ptr, &sp, &mut session) }) {
        return;
    }
    if actions & 1 != 0 {
        targets(&mut input, session, m, frames);
    }
    let step = actions & 16 != 0 && frames <= MAX_STEPPED_FRAMES;
    if actions & 2 != 0 {
        stages(&mut input, session, &texts, frames);
    } else if step {
        ok(unsafe { flame_session_set_prompt(session, texts.pick(actions >> 5)) });
    }
    if step {
        let mut left = 0u32;
        ok(unsafe { flame_session_step(session, &mut left) });
    }
    if actions & 4 != 0 {
        gltf(&mut input, session, &texts);
    }
    unsafe { flame_session_free(session) };
});
