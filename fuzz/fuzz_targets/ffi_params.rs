//! The C ABI's parameter structs filled with arbitrary field values (`struct_size` included,
//! smaller and larger than the struct) and its integer arguments: model params to a load,
//! session params to `flame_session_new`, edit params, keep/task masks and every argument of
//! `flame_session_read`. Every call must return a status; `FLAME_STATUS_INTERNAL` (a caught
//! panic) counts as a finding, as does any write past a buffer the caller declared.
#![no_main]

use std::collections::BTreeSet;
use std::ptr;
use std::sync::{Mutex, OnceLock};

use flame::ffi::*;
use flame_fuzz::{bounded_threads, ok, Input, FIXTURES};
use libfuzzer_sys::fuzz_target;

/// Sessions longer than this are created and read but not stepped (a step costs ~frames²).
const MAX_STEPPED_FRAMES: u32 = 24;

struct Models([*mut FlameModel; 3]);
// SAFETY: models are immutable after loading and documented as shareable across threads.
unsafe impl Send for Models {}
unsafe impl Sync for Models {}

fn models() -> &'static Models {
    static M: OnceLock<Models> = OnceLock::new();
    M.get_or_init(|| {
        let load = |bytes: &[u8]| {
            let mut m = ptr::null_mut();
            let s = unsafe {
                flame_model_load_from_memory(bytes.as_ptr(), bytes.len(), ptr::null(), &mut m)
            };
            assert_eq!(s, FlameStatus::Ok);
            m
        };
        Models(FIXTURES.map(load))
    })
}

fuzz_target!(|data: &[u8]| {
    let mut input = Input(data);
    let which_model = input.u8();
    let actions = input.u8();

    // Model params: the caller's struct is exactly as large as it says (at least its first
    // field, at most the current struct), so a read past the declared size is caught. A missing
    // file exercises the params' parsing and checks; a real load (slow) runs once per distinct
    // set of values that pass them.
    let declared = input.u32();
    let mut mp = vec![0u8; (declared as usize).clamp(4, std::mem::size_of::<FlameModelParams>())];
    let threads = bounded_threads(input.u32());
    let weights = input.i32();
    let fields = [
        declared.to_le_bytes(),
        threads.to_le_bytes(),
        weights.to_le_bytes(),
    ];
    for (dst, src) in mp.chunks_mut(4).zip(fields.iter()) {
        dst.copy_from_slice(&src[..dst.len()]);
    }
    let mut loaded = ptr::null_mut();
    let path = c"/nonexistent/model.safetensors".as_ptr();
    let status = unsafe { flame_model_load(path, mp.as_ptr().cast(), &mut loaded) };
    assert_ne!(status, FlameStatus::Ok);
    assert!(loaded.is_null());
    if ok(status) || status == FlameStatus::Io {
        static LOADED: Mutex<BTreeSet<(bool, u32, i32)>> = Mutex::new(BTreeSet::new());
        // Every count above the bound fails the same way: one class, so loads stay bounded.
        let class = threads.min(flame::pool::MAX_THREADS as u32 + 1);
        // Sizes 8 to 11 all read version 1 (whole fields only): one class too.
        let full = mp.len() == std::mem::size_of::<FlameModelParams>();
        let seen = (full, class, if full { weights } else { 0 });
        if LOADED.lock().unwrap().insert(seen) {
            let bytes = FIXTURES[which_model as usize % 3];
            if ok(unsafe {
                flame_model_load_from_memory(
                    bytes.as_ptr(),
                    bytes.len(),
                    mp.as_ptr().cast(),
                    &mut loaded,
                )
            }) {
                unsafe { flame_model_free(loaded) };
            }
        }
    }

    let model = models().0[which_model as usize % 3];
    let mut sp = FlameSessionParams {
        struct_size: input.u32(),
        frames: input.u32(),
        steps: input.u32(),
        sampler: input.i32(),
        eta: input.f32(),
        guidance: input.f32(),
        seed: input.u64(),
        threads: bounded_threads(input.u32()),
        respacing: ptr::null(),
        // 0 and 1, and one value refused.
        looped: input.u32() % 3,
    };
    // A short respacing string from the input (made of "ddim", digits, commas), or none.
    let spec: [u8; 8] = input.bytes();
    let alphabet = b"ddim0123456789,,x";
    let spec: Vec<u8> = spec
        .iter()
        .map(|&b| alphabet[b as usize % alphabet.len()])
        .collect();
    let spec = std::ffi::CString::new(spec).unwrap();
    if actions & 64 != 0 {
        sp.respacing = spec.as_ptr();
    }
    let mut session = ptr::null_mut();
    let params = if actions & 2 != 0 {
        ptr::null()
    } else {
        &sp as *const _
    };
    if !ok(unsafe { flame_session_new(model, params, &mut session) }) {
        assert!(session.is_null());
        return;
    }

    let ep = FlameEditParams {
        struct_size: input.u32(),
        method: input.i32(),
        edit_till: input.f32(),
        paste: input.u32(),
        seam_frames: input.u32(),
    };
    ok(unsafe { flame_session_set_edit_params(session, &ep) });
    let (a, b, c) = (input.u32(), input.u32(), input.i32());
    if actions & 4 != 0 {
        ok(unsafe { flame_session_keep_frames(session, a, b) });
    }
    if actions & 8 != 0 {
        ok(unsafe { flame_session_keep_part(session, c, a, b) });
    }
    if actions & 16 != 0 {
        ok(unsafe { flame_session_set_task_mask(session, c) });
    }
    if actions & 32 != 0
        && params == &sp as *const _
        && (1..=MAX_STEPPED_FRAMES).contains(&sp.frames)
    {
        if ok(unsafe { flame_session_set_prompt(session, c"a person walks".as_ptr()) }) {
            let mut left = 0u32;
            ok(unsafe { flame_session_step(session, &mut left) });
        }
    }
    if actions & 128 != 0 {
        // The session's prompt taken from itself, in whatever state it is (WRONG_STATE
        // without one); NULL sources.
        ok(unsafe { flame_session_set_prompt_from(session, session) });
        ok(unsafe { flame_session_set_prompt_from(session, ptr::null()) });
    }

    // Reads: first the length query, then into a buffer of exactly the declared length.
    let (which, layout, convention, flags) = (input.i32(), input.i32(), input.i32(), input.u32());
    let mut needed = 0usize;
    ok(unsafe {
        flame_session_read(
            session,
            which,
            layout,
            convention,
            flags,
            ptr::null_mut(),
            0,
            &mut needed,
        )
    });
    let len = input.u32() as usize % 200_000;
    let mut out = vec![0f32; len];
    let mut written = usize::MAX;
    if ok(unsafe {
        flame_session_read(
            session,
            which,
            layout,
            convention,
            flags,
            out.as_mut_ptr(),
            len,
            &mut written,
        )
    }) {
        assert!(written <= len);
        assert_eq!(written, needed);
    }
    unsafe { flame_session_free(session) };
});
