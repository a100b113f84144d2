//! The C ABI of [`crate::robot`]: a robot from its URDF ([`FlameRobot`]), a retarget onto it
//! with its configuration ([`FlameRobotRetarget`]), the per-run state of a frame-by-frame drive
//! ([`FlameRobotState`]), the whole clip of a session as a trajectory file
//! ([`flame_robot_retarget_write`]) and the joint vector frame after frame from a live session or
//! stream ([`flame_robot_retarget_read`], [`flame_robot_retarget_read_stream`]).
//!
//! **Quaternion order** is in every name: `root_rot_xyzw` is x, y, z, w (ROS, BeyondMimic, GMR);
//! the qpos files put w first (MuJoCo). Units: metres and radians, the robot's world (URDF: Z
//! up), `double` throughout.
//!
//! **Threads.** Robots and retargets are immutable: any thread, any number at once (a retarget
//! holds its own copy of the robot, so the robot may be freed after
//! [`flame_robot_retarget_new`]). A state is one run's warm start: calls on one state from
//! several threads at once get `WRONG_STATE` for all but one.

use std::ffi::{c_char, CString};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, TryLockError};

use super::cleanup::{finish_arg, FlameCleanupParams};
use super::errors::{catch_quietly, guard, Fail};
use super::handles::{session_ref, FlameSession};
use super::poses::{FlameConvention, FlameLayout};
use super::stream::{flame_stream_read_cleaned, stream_ref, FlameStream};
use super::{copy_out, flame_last_error, slice_arg, write_out, FlameStatus};
use crate::error::{invalid_arg, Error};
use crate::motion::contacts;
use crate::motion::rotation::{Mat3, Vec3};
use crate::motion::Convention;
use crate::robot::export::{self, RobotFile};
use crate::robot::{HumanFrame, RetargetConfig, RetargetState, Retargeter, Robot};

/// `file` of `flame_robot_retarget_write`: BeyondMimic's CSV, rows `x, y, z, qx, qy, qz, qw,
/// q_1 … q_n` (base quaternion x, y, z, w; joints in the robot's degree-of-freedom order).
pub const FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW: u32 = 0;
/// `file` of `flame_robot_retarget_write`: GMR's fields as an `.npz`: `fps`, `root_pos`
/// [N, 3], `root_rot` [N, 4] x, y, z, w, `dof_pos` [N, n], `joint_names` `[n]`.
pub const FLAME_ROBOT_GMR_NPZ_XYZW: u32 = 1;
/// `file` of `flame_robot_retarget_write`: MuJoCo qpos rows as a CSV, `x, y, z, qw, qx, qy,
/// qz` then the joints in MuJoCo's order of the compiled URDF (mimic joints included).
pub const FLAME_ROBOT_QPOS_CSV_WXYZ: u32 = 2;
/// `file` of `flame_robot_retarget_write`: the same qpos rows as an `.npy` [N, 7 + joints]
/// of float64.
pub const FLAME_ROBOT_QPOS_NPY_WXYZ: u32 = 3;
/// `options` flag of `flame_robot_retarget_write`: start a CSV with a `# ` line of column
/// names (a comment to `np.loadtxt`). `INVALID_ARGUMENT` with the `.npz` and `.npy` files.
pub const FLAME_ROBOT_CSV_HEADER: u32 = 1;

/// A robot: its URDF's kinematic tree, joint limits and collision primitives. Immutable.
pub struct FlameRobot {
    robot: Robot,
    name: CString,
    dof_names: Vec<CString>,
}

/// A retarget onto one robot: the robot (copied) and its configuration. Immutable and
/// shareable; per-run state lives in [`FlameRobotState`].
pub struct FlameRobotRetarget {
    retargeter: Retargeter,
    /// Tells states made for this retarget from those of others.
    id: u64,
}

/// One run's state for `flame_robot_retarget_read` and
/// `flame_robot_retarget_read_stream`: the configuration the next frame starts from (warm
/// start, velocity limits) and the feet's anchors during a contact.
pub struct FlameRobotState {
    state: Mutex<RetargetState>,
    retarget_id: u64,
}

fn next_retarget_id() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

fn c_string(s: &str) -> CString {
    CString::new(s.replace('\0', " ")).unwrap_or_default()
}

unsafe fn robot_ref<'a>(robot: *const FlameRobot) -> Result<&'a FlameRobot, Fail> {
    robot
        .as_ref()
        .ok_or_else(|| invalid_arg!("`robot` is NULL").into())
}

unsafe fn retarget_ref<'a>(r: *const FlameRobotRetarget) -> Result<&'a FlameRobotRetarget, Fail> {
    r.as_ref()
        .ok_or_else(|| invalid_arg!("`retarget` is NULL").into())
}

/// UTF-8 text of `len` bytes (not NUL-terminated).
unsafe fn text_arg<'a>(ptr: *const u8, len: usize, name: &str) -> Result<&'a str, Fail> {
    let bytes = slice_arg(ptr, len, name)?;
    std::str::from_utf8(bytes).map_err(|e| invalid_arg!("`{name}` is not UTF-8 ({e})").into())
}

/// Reads a robot from a URDF's text (`urdf`, `len` bytes, UTF-8; read only during the call):
/// links, joints (revolute, continuous, prismatic, fixed; mimic joints followed), limits,
/// collision primitives; a floating base at the root link. Errors (`INVALID_ARGUMENT`, the
/// message naming the joint or link and its line): malformed XML, a cycle, a missing parent
/// link, a zero axis, lower limit above upper, several roots. Free with [`flame_robot_free`].
///
/// # Safety
/// `urdf` points to `len` readable bytes; `out` points to a writable `FlameRobot *`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_load(
    urdf: *const u8,
    len: usize,
    out: *mut *mut FlameRobot,
) -> FlameStatus {
    guard(|| {
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let robot = Robot::from_urdf(text_arg(urdf, len, "urdf")?)?;
        let handle = FlameRobot {
            name: c_string(robot.name()),
            dof_names: robot.dof_names().iter().map(|n| c_string(n)).collect(),
            robot,
        };
        out.write(Box::into_raw(Box::new(handle)));
        Ok(())
    })
}

/// Frees a robot (NULL is fine). Retargets made from it stay valid (they hold a copy).
///
/// # Safety
/// `robot` is NULL or a robot not yet freed; its name pointers die with it.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_free(robot: *mut FlameRobot) {
    if !robot.is_null() {
        catch_quietly(|| drop(Box::from_raw(robot)));
    }
}

/// The robot's degrees of freedom `n` (its joint vector's length: revolute, continuous and
/// prismatic joints that mimic no other, in URDF document order).
///
/// # Safety
/// `robot` is live; `out` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_dof_count(
    robot: *const FlameRobot,
    out: *mut usize,
) -> FlameStatus {
    guard(|| write_out(out, robot_ref(robot)?.robot.dof_count(), "out"))
}

/// Degree of freedom `index`'s joint name (UTF-8, NUL-terminated) into `*out`, owned by the
/// robot and valid until [`flame_robot_free`]. The order of every joint vector of this ABI.
///
/// # Safety
/// `robot` is live; `out` points to a writable `const char *`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_dof_name(
    robot: *const FlameRobot,
    index: usize,
    out: *mut *const c_char,
) -> FlameStatus {
    guard(|| {
        let r = robot_ref(robot)?;
        let name = r
            .dof_names
            .get(index)
            .ok_or_else(|| invalid_arg!("dof {index} is past the robot's {}", r.dof_names.len()))?;
        write_out(out, name.as_ptr(), "out")
    })
}

/// The robot's name (`<robot name>`), owned by the robot, into `*out`. The shipped
/// configurations are named after it (`robots/<name>.json`).
///
/// # Safety
/// `robot` is live; `out` points to a writable `const char *`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_name(
    robot: *const FlameRobot,
    out: *mut *const c_char,
) -> FlameStatus {
    guard(|| write_out(out, robot_ref(robot)?.name.as_ptr(), "out"))
}

/// A retarget onto `robot` with the configuration `config_json` (`len` bytes of UTF-8 JSON:
/// GMR's IK tables plus libflame's feet and solver keys, docs/robots.md; libflame ships
/// `robots/<robot name>.json`). The robot is copied. Errors (`INVALID_ARGUMENT`): malformed
/// JSON, an unknown key, a body or human joint that does not exist (named), negative weights.
/// Free with [`flame_robot_retarget_free`].
///
/// # Safety
/// `robot` is live; `config_json` points to `len` readable bytes; `out` points to a writable
/// `FlameRobotRetarget *`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_retarget_new(
    robot: *const FlameRobot,
    config_json: *const u8,
    len: usize,
    out: *mut *mut FlameRobotRetarget,
) -> FlameStatus {
    guard(|| {
        let r = robot_ref(robot)?;
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let config =
            RetargetConfig::from_json(text_arg(config_json, len, "config_json")?, &r.robot)?;
        let retargeter = Retargeter::new(r.robot.clone(), config)?;
        let handle = FlameRobotRetarget {
            retargeter,
            id: next_retarget_id(),
        };
        out.write(Box::into_raw(Box::new(handle)));
        Ok(())
    })
}

/// Frees a retarget (NULL is fine). States made for it can no longer be used.
///
/// # Safety
/// `retarget` is NULL or a retarget not yet freed, used by no other call.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_retarget_free(retarget: *mut FlameRobotRetarget) {
    if !retarget.is_null() {
        catch_quietly(|| drop(Box::from_raw(retarget)));
    }
}

/// The retarget's robot's degrees of freedom (the `q` width of the reads).
///
/// # Safety
/// `retarget` is live; `out` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_retarget_dof_count(
    retarget: *const FlameRobotRetarget,
    out: *mut usize,
) -> FlameStatus {
    guard(|| {
        let n = retarget_ref(retarget)?.retargeter.robot().dof_count();
        write_out(out, n, "out")
    })
}

/// Retargets the whole current sample or clean-motion estimate (`which`, a `FlameWhich`) of a
/// session, read with `flags` (`FLAME_READ_SMOOTH`, `FLAME_READ_RAW_SIGNS`) and `cleanup`
/// (NULL = the raw poses; its `fps` resamples, 30 or 50 being what trackers expect), and writes
/// it as `file` (a `FLAME_ROBOT_*` value); `options` may hold [`FLAME_ROBOT_CSV_HEADER`]. The
/// clip is put on the floor, its contacts found, the feet planted for each contact span, then
/// every frame solved from a fresh state (the CLI's `--robot`).
///
/// With `out` NULL, `*out_len` receives the file's size in bytes and nothing else is done (the
/// retargeting runs either way). Otherwise `len` must be at least that (`BUFFER_TOO_SMALL`,
/// with `*out_len` set) and `*out_len` receives the bytes written.
///
/// # Safety
/// `retarget` and `session` are live; `cleanup` is NULL or a valid `FlameCleanupParams`; `out`
/// is NULL or points to `len` writable bytes; `out_len` points to a writable `size_t`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_robot_retarget_write(
    retarget: *const FlameRobotRetarget,
    session: *const FlameSession,
    which: i32,
    flags: u32,
    cleanup: *const FlameCleanupParams,
    file: u32,
    options: u32,
    out: *mut u8,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        let s = session_ref(session)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        let file = RobotFile::from_u32(file)?;
        if options & !FLAME_ROBOT_CSV_HEADER != 0 {
            return Err(invalid_arg!("unknown robot write options {options:#x}").into());
        }
        let header = options & FLAME_ROBOT_CSV_HEADER != 0;
        let finish = finish_arg(cleanup)?;
        s.with(|st| {
            let (poses, fps) = st.poses(which, flags, &finish)?;
            let traj = r.retargeter.motion(&poses, fps)?;
            let bytes = export::to_bytes(&traj, r.retargeter.robot(), file, header)?;
            copy_out(&bytes, out, len, out_len, "bytes")
        })
    })
}

/// A fresh state for frame-by-frame reads through `retarget` (the robot at its configured
/// initial configuration, no contacts). Free with [`flame_robot_state_free`].
///
/// # Safety
/// `retarget` is live; `out` points to a writable `FlameRobotState *`.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_state_new(
    retarget: *const FlameRobotRetarget,
    out: *mut *mut FlameRobotState,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let handle = FlameRobotState {
            state: Mutex::new(r.retargeter.state()),
            retarget_id: r.id,
        };
        out.write(Box::into_raw(Box::new(handle)));
        Ok(())
    })
}

/// Frees a state (NULL is fine).
///
/// # Safety
/// `state` is NULL or a state not yet freed, used by no other call.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_state_free(state: *mut FlameRobotState) {
    if !state.is_null() {
        catch_quietly(|| drop(Box::from_raw(state)));
    }
}

/// Puts a state back to the start of a run (call it before reading from another place than
/// the frame after the last one read: the velocity limits hold between consecutive reads).
///
/// # Safety
/// `state` is live.
#[no_mangle]
pub unsafe extern "C" fn flame_robot_state_reset(state: *const FlameRobotState) -> FlameStatus {
    guard(|| {
        let s = state
            .as_ref()
            .ok_or_else(|| Fail::from(invalid_arg!("`state` is NULL")))?;
        lock(s)?.reset();
        Ok(())
    })
}

fn lock(s: &FlameRobotState) -> Result<std::sync::MutexGuard<'_, RetargetState>, Fail> {
    match s.state.try_lock() {
        Ok(g) => Ok(g),
        Err(TryLockError::WouldBlock) => {
            Err(Error::WrongState("the robot state is in use by another thread".into()).into())
        }
        // A panic inside a solve: the state may be half-written; start it again.
        Err(TryLockError::Poisoned(p)) => {
            let mut g = p.into_inner();
            g.reset();
            Ok(g)
        }
    }
}

/// `state`, checked to be `retarget`'s.
unsafe fn state_ref<'a>(
    state: *const FlameRobotState,
    r: &FlameRobotRetarget,
) -> Result<&'a FlameRobotState, Fail> {
    let s = state
        .as_ref()
        .ok_or_else(|| Fail::from(invalid_arg!("`state` is NULL")))?;
    if s.retarget_id != r.id {
        return Err(invalid_arg!("`state` was made for another retarget").into());
    }
    Ok(s)
}

/// The caller's per-frame output buffers, each NULL or holding `count` frames.
struct FrameOutputs {
    root_pos: *mut f64,
    root_rot_xyzw: *mut f64,
    q: *mut f64,
    residual: *mut f64,
}

impl FrameOutputs {
    /// Checks every given buffer's length for `count` frames of `n` degrees of freedom.
    fn new(
        count: usize,
        n: usize,
        root_pos: (*mut f64, usize),
        root_rot_xyzw: (*mut f64, usize),
        q: (*mut f64, usize),
        residual: (*mut f64, usize),
    ) -> Result<FrameOutputs, Fail> {
        for ((ptr, len), per) in [(root_pos, 3), (root_rot_xyzw, 4), (q, n), (residual, 1)] {
            let needed = count
                .checked_mul(per)
                .ok_or_else(|| invalid_arg!("{count} frames overflow"))?;
            if !ptr.is_null() && len < needed {
                return Err(Fail::BufferTooSmall {
                    needed,
                    given: len,
                    unit: "doubles",
                });
            }
        }
        Ok(FrameOutputs {
            root_pos: root_pos.0,
            root_rot_xyzw: root_rot_xyzw.0,
            q: q.0,
            residual: residual.0,
        })
    }

    /// Copies the solved frames out (only once every frame succeeded).
    unsafe fn write(&self, solved: &Solved) {
        for (ptr, values) in [
            (self.root_pos, &solved.root_pos),
            (self.root_rot_xyzw, &solved.root_rot_xyzw),
            (self.q, &solved.q),
            (self.residual, &solved.residual),
        ] {
            if !ptr.is_null() {
                std::ptr::copy_nonoverlapping(values.as_ptr(), ptr, values.len());
            }
        }
    }
}

/// Frames solved by one read, flat.
#[derive(Default)]
struct Solved {
    root_pos: Vec<f64>,
    root_rot_xyzw: Vec<f64>,
    q: Vec<f64>,
    residual: Vec<f64>,
}

/// Steps `state` through `count` frames of `joints` joints (`positions`, `rotations` flat in
/// ROS axes, `contacts` per frame), `dt` apart. On an error the state is reset.
fn solve_frames(
    r: &FlameRobotRetarget,
    state: &mut RetargetState,
    positions: &[Vec3],
    rotations: &[Mat3],
    contacts: &[[bool; 4]],
    dt: f64,
) -> Result<Solved, Fail> {
    let joints = positions.len() / contacts.len().max(1);
    let mut out = Solved::default();
    for (t, c) in contacts.iter().enumerate() {
        let frame = HumanFrame {
            positions: &positions[t * joints..(t + 1) * joints],
            rotations: &rotations[t * joints..(t + 1) * joints],
            contacts: *c,
        };
        match r.retargeter.step(state, &frame, dt) {
            Ok(residual) => {
                out.root_pos.extend_from_slice(&state.base().translation);
                out.root_rot_xyzw.extend_from_slice(&state.root_rot_xyzw());
                out.q.extend_from_slice(state.q());
                out.residual.push(residual);
            }
            Err(e) => {
                state.reset();
                return Err(e.into());
            }
        }
    }
    Ok(out)
}

/// Robot frames from a live session, one after the other: frames `first..first + count` of the
/// motion [`super::flame_session_read_cleaned`] reads with the same `which`, `flags` and
/// `cleanup` (the read's floor is the robot's floor: pass a cleanup with its ground on, the
/// default of `flame_cleanup_params_default`, for a motion standing on z = 0), each solved from
/// where `state` left the previous one (warm start; joint velocity limits over 1 / fps; a foot
/// in contact held where it was set down). Contacts are those of the whole read. Per frame:
/// `out_root_pos` [3] the base (root link) position, `out_root_rot_xyzw` [4] its quaternion
/// x, y, z, w, `out_q` [n] the joint positions in the robot's degree-of-freedom order,
/// `out_residual` [1] the weighted task residual (large when the robot cannot reach). Each
/// buffer may be NULL; a given one holds `count` frames (`BUFFER_TOO_SMALL`). Outputs are
/// written only on success; on an error the state is reset. `*out_frames` (may be NULL)
/// receives the read's frame count (call with `count` 0 to learn it).
///
/// Errors: a range past the frames, a motion of another skeleton than the configuration needs
/// (`INVALID_ARGUMENT`); no sample yet, or the session busy (`WRONG_STATE`).
///
/// # Safety
/// `retarget`, `state` and `session` are live; `cleanup` is NULL or a valid
/// `FlameCleanupParams`; non-NULL buffers point to their lengths' writable doubles;
/// `out_frames` is NULL or writable.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_robot_retarget_read(
    retarget: *const FlameRobotRetarget,
    state: *const FlameRobotState,
    session: *const FlameSession,
    which: i32,
    flags: u32,
    cleanup: *const FlameCleanupParams,
    first: usize,
    count: usize,
    out_root_pos: *mut f64,
    root_pos_len: usize,
    out_root_rot_xyzw: *mut f64,
    root_rot_len: usize,
    out_q: *mut f64,
    q_len: usize,
    out_residual: *mut f64,
    residual_len: usize,
    out_frames: *mut usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        let st_handle = state_ref(state, r)?;
        let s = session_ref(session)?;
        let outs = FrameOutputs::new(
            count,
            r.retargeter.robot().dof_count(),
            (out_root_pos, root_pos_len),
            (out_root_rot_xyzw, root_rot_len),
            (out_q, q_len),
            (out_residual, residual_len),
        )?;
        let finish = finish_arg(cleanup)?;
        s.with(|st| {
            let (poses, fps) = st.poses(which, flags, &finish)?;
            let have = poses.frames();
            if first.checked_add(count).is_none_or(|end| end > have) {
                return Err(invalid_arg!(
                    "{count} frames from frame {first} run past the read's {have} frames"
                )
                .into());
            }
            let part = poses.frames_range(first, count);
            let contact = contacts::of(&poses, fps, &finish.contacts);
            let solved = solve_frames(
                r,
                &mut *lock(st_handle)?,
                &part.positions(Convention::Ros),
                &part.global_rotations(Convention::Ros),
                &contact[first..first + count],
                1.0 / fps,
            )?;
            outs.write(&solved);
            if !out_frames.is_null() {
                out_frames.write(have);
            }
            Ok(())
        })
    })
}

/// One layout of stream frames through the stream's own read in ROS axes, `per` floats a frame.
unsafe fn stream_values(
    stream: *const FlameStream,
    first: u64,
    count: u32,
    layout: FlameLayout,
    cleanup: *const FlameCleanupParams,
    per: usize,
) -> Result<Vec<f32>, Fail> {
    let want = count as usize * per;
    let mut values = vec![0.0f32; want];
    let mut len = 0usize;
    let status = flame_stream_read_cleaned(
        stream,
        first,
        count,
        layout as i32,
        FlameConvention::Ros as i32,
        cleanup,
        values.as_mut_ptr(),
        want,
        &mut len,
    );
    match status {
        FlameStatus::Ok if len == want => Ok(values),
        FlameStatus::Ok | FlameStatus::BufferTooSmall => {
            Err(invalid_arg!("the stream's frames have {} floats, expected {want}", len).into())
        }
        s => {
            let text = std::ffi::CStr::from_ptr(flame_last_error()).to_string_lossy();
            // The inner call's message carries its kind; the status says it again.
            let msg = ["wrong state: ", "invalid argument: "]
                .iter()
                .find_map(|p| text.strip_prefix(p))
                .unwrap_or(&text)
                .to_string();
            Err(match s {
                FlameStatus::WrongState => Error::WrongState(msg),
                _ => Error::InvalidArgument(msg),
            }
            .into())
        }
    }
}

/// [`flame_robot_retarget_read`] for a stream: timeline frames `first_frame..first_frame +
/// count` as [`super::flame_stream_read_cleaned`] gives them with `cleanup` (NULL = the raw
/// frames; the first cleanup passed sets the stream's, as there), with the stream's foot
/// contacts (`FLAME_LAYOUT_FOOT_CONTACTS`), one after the other from `state`: read the
/// timeline in order, a few frames per call, to drive a robot at run time. The frame rate is
/// the cleanup's or the model's. Buffers as `flame_robot_retarget_read` (no `out_frames`).
/// Frames not generated or settled yet are `WRONG_STATE` (pump more), dropped ones
/// `INVALID_ARGUMENT`.
///
/// # Safety
/// `retarget`, `state` and `stream` are live; `cleanup` is NULL or a valid
/// `FlameCleanupParams`; non-NULL buffers point to their lengths' writable doubles.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_robot_retarget_read_stream(
    retarget: *const FlameRobotRetarget,
    state: *const FlameRobotState,
    stream: *const FlameStream,
    first_frame: u64,
    count: u32,
    cleanup: *const FlameCleanupParams,
    out_root_pos: *mut f64,
    root_pos_len: usize,
    out_root_rot_xyzw: *mut f64,
    root_rot_len: usize,
    out_q: *mut f64,
    q_len: usize,
    out_residual: *mut f64,
    residual_len: usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        let st_handle = state_ref(state, r)?;
        let n = count as usize;
        let outs = FrameOutputs::new(
            n,
            r.retargeter.robot().dof_count(),
            (out_root_pos, root_pos_len),
            (out_root_rot_xyzw, root_rot_len),
            (out_q, q_len),
            (out_residual, residual_len),
        )?;
        let (joints, model_fps) = stream_ref(stream)?.with(|st| {
            let model = st.model();
            Ok((
                model.motion_format().skeleton().joint_count(),
                model.config().motion.fps as f64,
            ))
        })?;
        let fps = finish_arg(cleanup)?.output_fps(model_fps);
        let quats = stream_values(
            stream,
            first_frame,
            count,
            FlameLayout::GlobalQuatXyzw,
            cleanup,
            joints * 4,
        )?;
        let pos = stream_values(
            stream,
            first_frame,
            count,
            FlameLayout::GlobalPositions,
            cleanup,
            joints * 3,
        )?;
        let feet = stream_values(
            stream,
            first_frame,
            count,
            FlameLayout::FootContacts,
            cleanup,
            4,
        )?;
        let rotations: Vec<Mat3> = quats
            .chunks_exact(4)
            .map(|q| {
                let [x, y, z, w] = [0, 1, 2, 3].map(|i| q[i] as f64);
                crate::motion::rotation::quat_to_matrix(&[w, x, y, z])
            })
            .collect();
        let positions: Vec<Vec3> = pos
            .chunks_exact(3)
            .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
            .collect();
        let contact: Vec<[bool; 4]> = feet
            .chunks_exact(4)
            .map(|c| [0, 1, 2, 3].map(|i| c[i] > 0.5))
            .collect();
        let solved = solve_frames(
            r,
            &mut *lock(st_handle)?,
            &positions,
            &rotations,
            &contact,
            1.0 / fps,
        )?;
        outs.write(&solved);
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_constants_are_the_rust_discriminants() {
        for (c, f) in [
            (FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, RobotFile::BeyondMimicCsv),
            (FLAME_ROBOT_GMR_NPZ_XYZW, RobotFile::GmrNpz),
            (FLAME_ROBOT_QPOS_CSV_WXYZ, RobotFile::QposCsv),
            (FLAME_ROBOT_QPOS_NPY_WXYZ, RobotFile::QposNpy),
        ] {
            assert_eq!(RobotFile::from_u32(c).unwrap(), f);
        }
    }
}
