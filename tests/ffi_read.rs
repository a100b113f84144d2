//! `flame_session_read` through the C ABI returns exactly what the Rust API's motion module
//! gives for every layout and convention (the C tests in tests/c/ cover the rest of the ABI).

use std::ffi::CString;
use std::sync::Arc;

use flame::ffi::*;
use flame::models::Model;
use flame::motion::{self, Convention, Layout};
use flame::session::{Session, SessionParams};

const MODEL: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/fixtures/flame_tiny.safetensors"
);

fn read(
    s: *const FlameSession,
    layout: i32,
    convention: i32,
    flags: u32,
) -> (FlameStatus, Vec<f32>) {
    let mut n = 0usize;
    let st = unsafe {
        flame_session_read(
            s,
            0,
            layout,
            convention,
            flags,
            std::ptr::null_mut(),
            0,
            &mut n,
        )
    };
    if st != FlameStatus::Ok {
        return (st, Vec::new());
    }
    let mut out = vec![0.0f32; n];
    let st =
        unsafe { flame_session_read(s, 0, layout, convention, flags, out.as_mut_ptr(), n, &mut n) };
    (st, out)
}

#[test]
fn every_layout_and_convention_matches_the_motion_module() {
    let path = CString::new(MODEL).unwrap();
    let mut model: *mut FlameModel = std::ptr::null_mut();
    let mut session: *mut FlameSession = std::ptr::null_mut();
    let mut params = unsafe { std::mem::zeroed::<FlameSessionParams>() };
    unsafe {
        assert_eq!(
            flame_model_load(path.as_ptr(), std::ptr::null(), &mut model),
            FlameStatus::Ok
        );
        assert_eq!(flame_session_params_default(&mut params), FlameStatus::Ok);
    }
    params.frames = 12;
    params.steps = 3;
    params.sampler = FlameSampler::Ddim as i32;
    params.seed = 5;
    params.threads = 1;
    let prompt = CString::new("a person waves").unwrap();
    unsafe {
        assert_eq!(
            flame_session_new(model, &params, &mut session),
            FlameStatus::Ok
        );
        assert_eq!(
            flame_session_set_prompt(session, prompt.as_ptr()),
            FlameStatus::Ok
        );
        while flame_session_step(session, std::ptr::null_mut()) == FlameStatus::Ok {}
    }

    // The same generation through the Rust API.
    let m = Arc::new(Model::load(MODEL).unwrap());
    let p = SessionParams {
        frames: Some(12),
        steps: Some(3),
        sampler: Some(flame::session::Sampler::Ddim),
        seed: 5,
        threads: 1,
        ..Default::default()
    };
    let mut s = Session::new(Arc::clone(&m), &p).unwrap();
    s.set_prompt("a person waves").unwrap();
    let features = s.run().unwrap().to_vec();

    let (st, raw) = read(session, FlameLayout::Features as i32, 0, 0);
    assert_eq!(st, FlameStatus::Ok);
    assert_eq!(
        raw, features,
        "raw features equal the Rust API's bit for bit"
    );

    let layouts = [
        (FlameLayout::RootTranslation, Layout::RootTranslation),
        (FlameLayout::LocalQuatXyzw, Layout::LocalQuatXyzw),
        (FlameLayout::LocalQuatWxyz, Layout::LocalQuatWxyz),
        (FlameLayout::LocalMatrix, Layout::LocalMatrix),
        (FlameLayout::Local6d, Layout::Local6d),
        (FlameLayout::GlobalPositions, Layout::GlobalPositions),
        (FlameLayout::GlobalQuatXyzw, Layout::GlobalQuatXyzw),
        (FlameLayout::GlobalQuatWxyz, Layout::GlobalQuatWxyz),
    ];
    let conventions = [
        (FlameConvention::Native, Convention::Native),
        (FlameConvention::Unity, Convention::Unity),
        (FlameConvention::Unreal, Convention::Unreal),
        (FlameConvention::Ros, Convention::Ros),
        (FlameConvention::Blender, Convention::Blender),
        (FlameConvention::Gltf, Convention::Gltf),
    ];
    for (fl, l) in layouts {
        for (fc, c) in conventions {
            for (flags, smooth, continuous) in [
                (0, 0.0, true),
                (FLAME_READ_SMOOTH, 1.0, true),
                (FLAME_READ_RAW_SIGNS, 0.0, false),
            ] {
                let want = motion::read_layout(
                    m.motion_format(),
                    &features,
                    12,
                    l,
                    c,
                    &m.read_options(smooth, continuous),
                )
                .unwrap();
                let (st, got) = read(session, fl as i32, fc as i32, flags);
                assert_eq!(st, FlameStatus::Ok, "{fl:?} {fc:?}");
                assert_eq!(got, want, "{fl:?} {fc:?} flags {flags}");
            }
        }
    }
    // FLAME's features carry no foot contacts: a read detects them (0 or 1), as the motion
    // module does; raw poses have no root bone; unknown values are errors.
    let (st, contacts) = read(session, FlameLayout::FootContacts as i32, 0, 0);
    assert_eq!(st, FlameStatus::Ok);
    assert_eq!(
        contacts,
        motion::read_layout(
            m.motion_format(),
            &features,
            12,
            Layout::FootContacts,
            Convention::Native,
            &m.read_options(0.0, true)
        )
        .unwrap()
    );
    assert!(contacts.iter().all(|&c| c == 0.0 || c == 1.0));
    assert_eq!(
        read(session, FlameLayout::RootBone as i32, 0, 0).0,
        FlameStatus::InvalidArgument
    );
    assert_eq!(read(session, 11, 0, 0).0, FlameStatus::InvalidArgument);
    assert_eq!(read(session, 1, 6, 0).0, FlameStatus::InvalidArgument);
    assert_eq!(read(session, 1, 0, 4).0, FlameStatus::InvalidArgument);

    let mut info = unsafe { std::mem::zeroed::<FlameModelInfo>() };
    info.struct_size = std::mem::size_of::<FlameModelInfo>() as u32;
    unsafe {
        assert_eq!(flame_model_info(model, &mut info), FlameStatus::Ok);
        assert_eq!(info.joint_count, 24);
        let names = std::slice::from_raw_parts(info.joint_names, 24);
        assert_eq!(
            std::ffi::CStr::from_ptr(names[20]).to_str().unwrap(),
            motion::Format::Smpl24Rot6d.skeleton().joint_names()[20]
        );
        assert_eq!(
            std::slice::from_raw_parts(info.joint_parents, 24)[..4],
            [-1, 0, 0, 0]
        );
        flame_session_free(session);
        flame_model_free(model);
    }
}

#[test]
fn a_flow_matching_model_through_the_c_abi() {
    let path = CString::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/motionfm_tiny.safetensors"
    ))
    .unwrap();
    let mut model: *mut FlameModel = std::ptr::null_mut();
    let mut session: *mut FlameSession = std::ptr::null_mut();
    let mut params = unsafe { std::mem::zeroed::<FlameSessionParams>() };
    let mut info = unsafe { std::mem::zeroed::<FlameModelInfo>() };
    info.struct_size = std::mem::size_of::<FlameModelInfo>() as u32;
    let prompt = CString::new("a person jumps").unwrap();
    unsafe {
        assert_eq!(
            flame_model_load(path.as_ptr(), std::ptr::null(), &mut model),
            FlameStatus::Ok
        );
        assert_eq!(flame_model_info(model, &mut info), FlameStatus::Ok);
        assert_eq!(
            std::ffi::CStr::from_ptr(info.architecture)
                .to_str()
                .unwrap(),
            "motionfm"
        );
        assert_eq!(
            std::ffi::CStr::from_ptr(info.motion_format)
                .to_str()
                .unwrap(),
            "humanml263"
        );
        assert_eq!(
            (info.feature_dim, info.joint_count, info.default_sampler),
            (263, 22, FlameSampler::Euler as i32)
        );
        assert_eq!(flame_session_params_default(&mut params), FlameStatus::Ok);
        params.frames = 10;
        params.steps = 4;
        params.sampler = FlameSampler::Ddim as i32;
        assert_eq!(
            flame_session_new(model, &params, &mut session),
            FlameStatus::InvalidArgument
        );
        params.sampler = FlameSampler::Heun as i32;
        assert_eq!(
            flame_session_new(model, &params, &mut session),
            FlameStatus::Ok
        );
        assert_eq!(
            flame_session_set_prompt(session, prompt.as_ptr()),
            FlameStatus::Ok
        );
        let mut left = 9;
        while left > 0 {
            assert_eq!(flame_session_step(session, &mut left), FlameStatus::Ok);
        }
    }
    let (st, raw) = read(session, FlameLayout::Features as i32, 0, 0);
    assert_eq!((st, raw.len()), (FlameStatus::Ok, 10 * 263));
    let (st, pos) = read(
        session,
        FlameLayout::GlobalPositions as i32,
        FlameConvention::Unity as i32,
        0,
    );
    assert_eq!((st, pos.len()), (FlameStatus::Ok, 10 * 22 * 3));
    let (st, contacts) = read(session, FlameLayout::FootContacts as i32, 0, 0);
    assert_eq!((st, contacts.len()), (FlameStatus::Ok, 10 * 4));
    // Editing a flow model (trajectory rewriting, then the paste): the kept frames come back as
    // the reference exactly.
    unsafe {
        assert_eq!(flame_session_reset(session), FlameStatus::Ok);
        assert_eq!(flame_session_keep_frames(session, 0, 2), FlameStatus::Ok);
        let reference = vec![0.25f32; 10 * 263];
        assert_eq!(
            flame_session_set_reference(session, reference.as_ptr(), 10, 263),
            FlameStatus::Ok
        );
        let mut left = 0u32;
        loop {
            assert_eq!(flame_session_step(session, &mut left), FlameStatus::Ok);
            if left == 0 {
                break;
            }
        }
    }
    let (st, x) = read(session, FlameLayout::Features as i32, 0, 0);
    assert_eq!(st, FlameStatus::Ok);
    assert!(x[..2 * 263].iter().all(|&v| v == 0.25));
    assert!(x[2 * 263..].iter().any(|&v| v != 0.25));
    unsafe {
        flame_session_free(session);
        flame_model_free(model);
    }
}

/// `flame_session_read_cleaned` with a session's `FlameCleanupParams`.
fn read_cleaned(
    s: *const FlameSession,
    layout: FlameLayout,
    cleanup: *const FlameCleanupParams,
) -> (FlameStatus, Vec<f32>) {
    let mut n = 0usize;
    let layout = layout as i32;
    let gltf = FlameConvention::Gltf as i32;
    let st = unsafe {
        flame_session_read_cleaned(
            s,
            0,
            layout,
            gltf,
            0,
            cleanup,
            std::ptr::null_mut(),
            0,
            &mut n,
        )
    };
    if st != FlameStatus::Ok {
        return (st, Vec::new());
    }
    let mut out = vec![0.0f32; n];
    let st = unsafe {
        flame_session_read_cleaned(s, 0, layout, gltf, 0, cleanup, out.as_mut_ptr(), n, &mut n)
    };
    (st, out)
}

#[test]
fn cleaned_reads_match_the_rust_read_options_and_refuse_bad_values() {
    let path = CString::new(MODEL).unwrap();
    let mut model: *mut FlameModel = std::ptr::null_mut();
    let mut session: *mut FlameSession = std::ptr::null_mut();
    let mut params = unsafe { std::mem::zeroed::<FlameSessionParams>() };
    let mut cleanup = unsafe { std::mem::zeroed::<FlameCleanupParams>() };
    let prompt = CString::new("a person walks").unwrap();
    unsafe {
        assert_eq!(
            flame_model_load(path.as_ptr(), std::ptr::null(), &mut model),
            FlameStatus::Ok
        );
        assert_eq!(flame_session_params_default(&mut params), FlameStatus::Ok);
        assert_eq!(flame_cleanup_params_default(&mut cleanup), FlameStatus::Ok);
    }
    params.frames = 30;
    params.steps = 3;
    params.seed = 2;
    params.threads = 1;
    unsafe {
        assert_eq!(
            flame_session_new(model, &params, &mut session),
            FlameStatus::Ok
        );
        assert_eq!(
            flame_session_set_prompt(session, prompt.as_ptr()),
            FlameStatus::Ok
        );
        while flame_session_step(session, std::ptr::null_mut()) == FlameStatus::Ok {}
    }
    let (_, features) = read(session, FlameLayout::Features as i32, 0, 0);
    let m = Arc::new(Model::load(MODEL).unwrap());

    // The defaults are the game-ready finish; NULL is the raw read.
    assert_eq!(cleanup.feet, FlameFeet::Lock as i32);
    assert_eq!((cleanup.ground, cleanup.fps), (1, 0.0));
    cleanup.fps = 30.0;
    cleanup.root_motion = FlameRootMotion::Separate as i32;
    let finish = motion::Finish {
        fps: Some(30.0),
        root_motion: motion::RootMotion::Separate,
        ..motion::Finish::game_ready()
    };
    let opts = motion::ReadOptions {
        finish,
        ..m.read_options(0.0, true)
    };
    for (fl, l) in [
        (FlameLayout::GlobalPositions, Layout::GlobalPositions),
        (FlameLayout::LocalQuatXyzw, Layout::LocalQuatXyzw),
        (FlameLayout::FootContacts, Layout::FootContacts),
        (FlameLayout::RootBone, Layout::RootBone),
    ] {
        let want =
            motion::read_layout(m.motion_format(), &features, 30, l, Convention::Gltf, &opts)
                .unwrap();
        let (st, got) = read_cleaned(session, fl, &cleanup);
        assert_eq!(st, FlameStatus::Ok, "{fl:?}");
        assert_eq!(got, want, "{fl:?}");
    }
    // 30 frames at 20 fps end at 1.45 s: 44 frames at 30 fps.
    let (_, bone) = read_cleaned(session, FlameLayout::RootBone, &cleanup);
    assert_eq!(bone.len(), 44 * 3);
    let (_, raw) = read_cleaned(session, FlameLayout::GlobalPositions, std::ptr::null());
    let (_, plain) = read(
        session,
        FlameLayout::GlobalPositions as i32,
        FlameConvention::Gltf as i32,
        0,
    );
    assert_eq!(raw, plain);

    // Bad values are errors naming the value, never a crash.
    let bad = |edit: &dyn Fn(&mut FlameCleanupParams), needle: &str| {
        let mut p = cleanup;
        edit(&mut p);
        let (st, _) = read_cleaned(session, FlameLayout::GlobalPositions, &p);
        assert_eq!(st, FlameStatus::InvalidArgument, "{needle}");
        let msg = unsafe { std::ffi::CStr::from_ptr(flame_last_error()) }
            .to_str()
            .unwrap()
            .to_string();
        assert!(msg.contains(needle), "{needle}: {msg}");
    };
    bad(&|p| p.fps = f32::NAN, "frame rate");
    bad(&|p| p.fps = 1e9, "1000000000");
    bad(&|p| p.fps = -20.0, "-20");
    bad(&|p| p.contact_height = -0.1, "-0.1");
    bad(&|p| p.contact_speed = f32::INFINITY, "inf");
    bad(&|p| p.feet = 7, "feet");
    bad(&|p| p.root_motion = -1, "root_motion");
    bad(&|p| p.struct_size = 4, "struct_size");
    unsafe {
        flame_session_free(session);
        flame_model_free(model);
    }
}
