//! `flame_stream_read_cleaned` through the C ABI: the same bits as the Rust API's
//! `Stream::read_cleaned` on the same timeline, the cleanup set once by the first cleaned read,
//! NULL cleanup = `flame_stream_read`, and the errors (wrap, unsettled frames, another cleanup,
//! layout 0, pushing after `flame_stream_close`). The cleanup's semantics (seams, settling,
//! equality with the whole-clip cleanup) are tested beside the code in `src/stream.rs`.

use std::ffi::CString;
use std::sync::Arc;

use flame::ffi::*;
use flame::models::Model;
use flame::motion::{ContactParams, Convention, Finish, Layout};
use flame::session::{Sampler, SessionParams};
use flame::stream::{Segment, Stream, StreamParams};

const MODEL: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/fixtures/flame_tiny.safetensors"
);

/// The random-weight fixture's feet are fast and high: the widest contact detection (see
/// `src/stream.rs`'s tests) gives it contact spans, so the feet are locked for real.
fn cleanup() -> FlameCleanupParams {
    let mut c = unsafe { std::mem::zeroed::<FlameCleanupParams>() };
    assert_eq!(
        unsafe { flame_cleanup_params_default(&mut c) },
        FlameStatus::Ok
    );
    c.contact_height = 1.0;
    c.contact_speed = 20.0;
    c.contact_release = 1.0;
    c.contact_min_span = 0.0;
    c.fps = 30.0;
    c.root_motion = FlameRootMotion::Separate as i32;
    c
}

fn finish() -> Finish {
    Finish {
        contacts: ContactParams {
            height: 1.0,
            speed: 20.0,
            release: 1.0,
            min_span: 0.0,
        },
        fps: Some(30.0),
        root_motion: flame::motion::RootMotion::Separate,
        ..Finish::game_ready()
    }
}

unsafe fn read(
    s: *const FlameStream,
    first: u64,
    count: u32,
    layout: i32,
    c: *const FlameCleanupParams,
) -> (FlameStatus, Vec<f32>) {
    let mut n = 0usize;
    let conv = FlameConvention::Unity as i32;
    let st = flame_stream_read_cleaned(
        s,
        first,
        count,
        layout,
        conv,
        c,
        std::ptr::null_mut(),
        0,
        &mut n,
    );
    if st != FlameStatus::Ok {
        return (st, Vec::new());
    }
    let mut out = vec![0.0f32; n];
    let st = flame_stream_read_cleaned(
        s,
        first,
        count,
        layout,
        conv,
        c,
        out.as_mut_ptr(),
        n,
        &mut n,
    );
    (st, out)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn cleaned_stream_reads_match_the_rust_api_and_refuse_what_they_must() {
    let path = CString::new(MODEL).unwrap();
    let mut model: *mut FlameModel = std::ptr::null_mut();
    let mut stream: *mut FlameStream = std::ptr::null_mut();
    let mut p = unsafe { std::mem::zeroed::<FlameStreamParams>() };
    unsafe {
        assert_eq!(
            flame_model_load(path.as_ptr(), std::ptr::null(), &mut model),
            FlameStatus::Ok
        );
        assert_eq!(flame_stream_params_default(&mut p), FlameStatus::Ok);
    }
    (p.chunk, p.overlap, p.lookahead, p.window) = (40, 10, 1000, 10_000);
    (p.steps, p.sampler, p.seed, p.threads) = (2, FlameSampler::Ddim as i32, 7, 1);
    unsafe {
        assert_eq!(flame_stream_new(model, &p, &mut stream), FlameStatus::Ok);
    }
    let prompt = CString::new("a person walks forward.").unwrap();
    let c = cleanup();
    let positions = FlameLayout::GlobalPositions as i32;
    unsafe {
        assert_eq!(
            flame_stream_push(stream, prompt.as_ptr(), 100),
            FlameStatus::Ok
        );
        // Nothing generated: the first cleaned read sets the cleanup, frame 0 is not settled.
        assert_eq!(read(stream, 0, 1, positions, &c).0, FlameStatus::WrongState);
        let mut wrap = c;
        wrap.wrap = 1;
        assert_eq!(
            read(stream, 0, 1, positions, &wrap).0,
            FlameStatus::InvalidArgument
        );
        let mut other = c;
        other.fps = 0.0;
        assert_eq!(
            read(stream, 0, 1, positions, &other).0,
            FlameStatus::WrongState
        );
        assert_eq!(read(stream, 0, 1, 0, &c).0, FlameStatus::InvalidArgument);
        let mut st = std::mem::zeroed::<FlameStreamStatus>();
        st.struct_size = std::mem::size_of::<FlameStreamStatus>() as u32;
        assert_eq!(flame_stream_pump(stream, 2, &mut st), FlameStatus::Ok);
        assert_eq!(st.ready, 40);
        // The raw read: NULL cleanup is flame_stream_read.
        let raw = read(stream, 0, 40, positions, std::ptr::null());
        assert_eq!((raw.0, raw.1.len()), (FlameStatus::Ok, 40 * 24 * 3));
        assert_eq!(flame_stream_close(stream), FlameStatus::Ok);
        assert_eq!(
            flame_stream_push(stream, prompt.as_ptr(), 10),
            FlameStatus::WrongState
        );
        while flame_stream_pump(stream, 1, &mut st) == FlameStatus::Ok && st.steps > 0 {}
        assert_eq!(st.ready, 100);
    }

    // The same timeline through the Rust API.
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
    let mut s = Stream::new(Arc::new(Model::load(MODEL).unwrap()), &params).unwrap();
    s.push(Segment::new("a person walks forward.", 100))
        .unwrap();
    s.close();
    s.set_finish(finish()).unwrap();
    while s.pump(usize::MAX).unwrap().steps > 0 {}
    // 100 frames at 20 fps span 4.95 s: 149 frames at 30 fps.
    assert_eq!(s.settled(), 149);
    for (layout, l) in [
        (positions, Layout::GlobalPositions),
        (FlameLayout::LocalQuatXyzw as i32, Layout::LocalQuatXyzw),
        (FlameLayout::RootBone as i32, Layout::RootBone),
        (FlameLayout::FootContacts as i32, Layout::FootContacts),
    ] {
        let (st, got) = unsafe { read(stream, 0, 149, layout, &c) };
        assert_eq!(st, FlameStatus::Ok, "{l:?}");
        let want = s.read_cleaned(0, 149, l, Convention::Unity).unwrap();
        assert_eq!(bits(&got), bits(&want), "{l:?}");
    }
    // Past the timeline's end: never settles.
    assert_eq!(
        unsafe { read(stream, 149, 1, positions, &c).0 },
        FlameStatus::WrongState
    );
    unsafe {
        flame_stream_free(stream);
        flame_model_free(model);
    }
}

mod common;

/// The latency the cleanup adds on the demo model (chunks of 120 frames keeping 20, as the
/// demo streams): after every chunk lands, how many generated frames are not settled yet. The
/// game-ready cleanup (contacts, floor, feet locked) on a walk then a jump.
#[test]
fn demo_model_latency_of_the_cleanup() {
    let Some(path) = common::demo_model() else {
        return;
    };
    let params = StreamParams {
        chunk: 120,
        overlap: 20,
        lookahead: 10_000,
        window: 10_000,
        session: SessionParams {
            steps: Some(10),
            sampler: Some(Sampler::Ddim),
            seed: 1,
            threads: 2,
            ..Default::default()
        },
    };
    let mut s = Stream::new(Arc::new(Model::load(&path).unwrap()), &params).unwrap();
    s.push(Segment::new("a person walks forward.", 300))
        .unwrap();
    s.push(Segment::new("a person jumps.", 100)).unwrap();
    s.close();
    s.set_finish(Finish::game_ready()).unwrap();
    let mut lags = Vec::new();
    let mut ready = 0;
    while s.pump(1).unwrap().steps > 0 {
        if s.ready() != ready && !s.is_complete() {
            ready = s.ready();
            lags.push(ready - s.settled());
        }
    }
    assert_eq!((s.ready(), s.settled()), (400, 400));
    let worst = *lags.iter().max().unwrap();
    eprintln!("demo: frames generated but not settled after each chunk {lags:?}, worst {worst}");
    // Frames settle while the stream runs (not only at its end), within 3 s of the newest.
    assert!(worst < 60, "{lags:?}");
}
