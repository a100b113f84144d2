//! The C ABI of the hand-over post-processing ([`crate::motion::Finish`]): its parameter struct,
//! the enums it names, and the reads that take it.

use super::{guard, session_ref, struct_arg, write_out, Fail, FlameSession, FlameStatus};
use crate::error::invalid_arg;
use crate::motion::{ContactParams, Feet, Finish, RootMotion};

/// What happens to the feet during their contact spans ([`FlameCleanupParams::feet`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameFeet {
    /// The raw poses: feet may slide.
    Off = 0,
    /// Each planted foot pinned where it stands, the leg solved by two-bone IK; bone lengths and
    /// everything above the knees unchanged.
    Lock = 1,
}

/// Where the clip's horizontal travel goes ([`FlameCleanupParams::root_motion`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameRootMotion {
    /// On the pelvis, as the model made it.
    Keep = 0,
    /// Removed: the pelvis stays over the origin.
    InPlace = 1,
    /// On a `root` bone on the ground under the pelvis: the pelvis reads as in-place, the
    /// bone's track as `FLAME_LAYOUT_ROOT_BONE`, and glTF exports write the bone.
    Separate = 2,
}

/// Post-processing applied when poses are read: foot contacts, the floor, foot locking, a loop's
/// wrap, root motion and the frame rate. Initialise with [`flame_cleanup_params_default`]. A read
/// that takes a NULL `FlameCleanupParams *` gives the raw poses.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameCleanupParams {
    /// `sizeof(FlameCleanupParams)`.
    pub struct_size: u32,
    /// A [`FlameFeet`] value (default lock).
    pub feet: i32,
    /// Nonzero: the lowest foot contact of the clip put at height 0 (default 1).
    pub ground: u32,
    /// A [`FlameRootMotion`] value (default keep).
    pub root_motion: i32,
    /// Nonzero with in-place or separate root motion: also remove the heading's drift (default 0).
    pub remove_yaw: u32,
    /// 1: correct the frames on both sides of the wrap so the clip loops, the next cycle's
    /// start estimated from the clip's average travel; 2: the same, the clip's last frame being
    /// the next cycle's first (it is then dropped: one frame fewer); 0: no wrap (default).
    pub wrap: u32,
    /// Output frame rate, 1 to 240; 0 = the model's (default 0). Changes the frame count a read
    /// returns: ask with `out` NULL first.
    pub fps: f32,
    /// Contact detection (smpl24_6d models): height above the standing level, metres (default 0.05).
    pub contact_height: f32,
    /// Contact detection: speed below which a foot joint may be planted, m/s (default 0.894).
    pub contact_speed: f32,
    /// Contact detection: hysteresis ratio ≥ 1 for leaving a contact (default 1.5).
    pub contact_release: f32,
    /// Contact detection: shortest contact span and gap kept, seconds (default 0.1).
    pub contact_min_span: f32,
}

/// Fills `*params` with the game-ready defaults: feet locked, the floor at 0, root motion kept,
/// no wrap, the model's frame rate, the default contact detection.
///
/// # Safety
/// `params` points to writable memory for a `FlameCleanupParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_cleanup_params_default(
    params: *mut FlameCleanupParams,
) -> FlameStatus {
    guard(|| write_out(params, to_c(&Finish::game_ready()), "params"))
}

fn to_c(f: &Finish) -> FlameCleanupParams {
    FlameCleanupParams {
        struct_size: std::mem::size_of::<FlameCleanupParams>() as u32,
        feet: f.feet as i32,
        ground: f.ground as u32,
        root_motion: f.root_motion as i32,
        remove_yaw: f.remove_yaw as u32,
        wrap: if f.wrap_to_last { 2 } else { f.wrap as u32 },
        fps: f.fps.unwrap_or(0.0) as f32,
        contact_height: f.contacts.height as f32,
        contact_speed: f.contacts.speed as f32,
        contact_release: f.contacts.release as f32,
        contact_min_span: f.contacts.min_span as f32,
    }
}

/// The [`Finish`] a caller's params ask for (NULL = none), every value checked.
pub(crate) unsafe fn finish_arg(params: *const FlameCleanupParams) -> Result<Finish, Fail> {
    if params.is_null() {
        return Ok(Finish::default());
    }
    let p = struct_arg(params, |p| p.struct_size, "cleanup")?;
    let enum_value = |v: i32, what: &str| {
        u32::try_from(v).map_err(|_| Fail::from(invalid_arg!("cleanup.{what} is {v}")))
    };
    let finish = Finish {
        contacts: ContactParams {
            height: p.contact_height as f64,
            speed: p.contact_speed as f64,
            release: p.contact_release as f64,
            min_span: p.contact_min_span as f64,
        },
        ground: p.ground != 0,
        feet: Feet::from_u32(enum_value(p.feet, "feet")?)?,
        wrap: match p.wrap {
            0..=2 => p.wrap != 0,
            w => {
                return Err(invalid_arg!(
                    "cleanup.wrap is {w} (0 off, 1 wrap, 2 wrap to the last frame)"
                )
                .into())
            }
        },
        wrap_to_last: p.wrap == 2,
        root_motion: RootMotion::from_u32(enum_value(p.root_motion, "root_motion")?)?,
        remove_yaw: p.remove_yaw != 0,
        fps: (p.fps != 0.0).then_some(p.fps as f64),
    };
    finish.validate()?;
    Ok(finish)
}

/// [`super::flame_session_read`] with post-processing: the poses of `which` in `layout` and
/// `convention` after `cleanup` (NULL = the raw poses, exactly `flame_session_read`). With a
/// frame rate other than the model's, the frame count changes: call with `out` NULL for the
/// length. The raw features (layout 0) are never post-processed.
///
/// # Safety
/// As `flame_session_read`; `cleanup` is NULL or points to a valid `FlameCleanupParams`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_session_read_cleaned(
    session: *const FlameSession,
    which: i32,
    layout: i32,
    convention: i32,
    flags: u32,
    cleanup: *const FlameCleanupParams,
    out: *mut f32,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        let finish = finish_arg(cleanup)?;
        s.with(|st| {
            let values = st.read(which, layout, convention, flags, &finish)?;
            super::copy_out(&values, out, len, out_len, "floats")
        })
    })
}
