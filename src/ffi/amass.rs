//! The C ABI of the AMASS export ([`crate::motion::amass`]): a session's motion as the `.npz`
//! bytes of AMASS SMPL parameters.

use super::cleanup::finish_arg;
use super::{copy_out, guard, session_ref, FlameSession, FlameStatus};
use crate::error::invalid_arg;
use crate::motion::amass::{self, AmassLayout};

/// `layout` of [`flame_session_write_amass`]: AMASS SMPL-H keys (`*_poses.npz`: `poses`
/// [N, 156] = root, 21 body joints, 30 hand joints at rest; `trans`, `betas`, `gender`,
/// `mocap_framerate`, `dmpls`), what PHC and human2humanoid read.
pub const FLAME_AMASS_SMPLH: i32 = 0;
/// `layout` of [`flame_session_write_amass`]: AMASS SMPL-X keys (`*_stageii.npz`:
/// `root_orient`, `pose_body` [N, 63], `pose_hand`, `pose_jaw`, `pose_eye`, `trans`, `betas`,
/// `num_betas`, `gender`, `surface_model_type`, `mocap_frame_rate`, `mocap_time_length`,
/// `poses` [N, 165]), what GMR reads.
pub const FLAME_AMASS_SMPLX: i32 = 1;

/// Writes the current sample or clean-motion estimate (`which`, a `FlameWhich`) as an
/// AMASS-style `.npz` (a ZIP of `.npy` arrays, what `numpy.load` reads) in `layout`
/// ([`FLAME_AMASS_SMPLH`] or [`FLAME_AMASS_SMPLX`]): SMPL axis-angles in radians
/// (parent-relative, the root's global), `trans` in metres, AMASS's Z-up world, every array
/// float64, `betas` 16 zeros, `gender` "neutral", the frame rate the cleanup's `fps` or the
/// model's (docs/amass.md). `flags` are read flags (`FLAME_READ_SMOOTH`,
/// `FLAME_READ_RAW_SIGNS`); `cleanup` NULL means the raw poses (its `fps` resamples,
/// 30 or 50 being what trackers expect).
///
/// With `out` NULL, `*out_len` receives the file's size in bytes and nothing else is done.
/// Otherwise `len` must be at least that (`BUFFER_TOO_SMALL` otherwise, with `*out_len` set to
/// the size) and `*out_len` receives the bytes written. Each call builds the file afresh. A
/// motion of no frames or with poses that are not finite is `INVALID_ARGUMENT`.
///
/// # Safety
/// `session` is a live session; `cleanup` is NULL or points to a valid `FlameCleanupParams`;
/// `out` is NULL or points to `len` writable bytes; `out_len` points to a writable `size_t`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_session_write_amass(
    session: *const FlameSession,
    which: i32,
    layout: i32,
    flags: u32,
    cleanup: *const super::FlameCleanupParams,
    out: *mut u8,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        let layout = match layout {
            FLAME_AMASS_SMPLH => AmassLayout::SmplH,
            FLAME_AMASS_SMPLX => AmassLayout::SmplX,
            l => return Err(invalid_arg!("unknown AMASS layout {l} (0 smplh, 1 smplx)").into()),
        };
        let finish = finish_arg(cleanup)?;
        s.with(|st| {
            let (poses, fps) = st.poses(which, flags, &finish)?;
            let bytes = amass::to_npz(&poses, fps, layout)?;
            copy_out(&bytes, out, len, out_len, "bytes")
        })
    })
}
