"""Python bindings of libflame (text-to-motion diffusion on the CPU) over its C ABI, via ctypes.

    import flame
    with flame.Model.load("models/demo/flame_demo.safetensors") as model:
        with model.session(frames=120, steps=50, sampler="ddim", seed=1) as s:
            s.set_prompt("a person jumps twice")
            motion = s.run()                     # numpy float32 [frames, feature_dim]

The shared library is found through, in order: the environment variable FLAME_LIBRARY (a path to
the file), a copy next to this package, the repository's target/release and target/debug (for a
checkout), and the system's library search path.

Threads: a Model is immutable and may be shared; a Session is used by one thread at a time, except
`cancel()`, which any thread may call while another is inside `step()`. The C calls release the
GIL, so sessions in different Python threads run in parallel.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple, Union

import numpy as np

__all__ = [
    "ABI_VERSION",
    "FlameError",
    "Model",
    "ModelInfo",
    "PromptInfo",
    "TuningReport",
    "PromptTruncatedWarning",
    "Session",
    "Stage",
    "Stream",
    "StreamStatus",
    "Status",
    "Sampler",
    "Which",
    "Weights",
    "Layout",
    "Convention",
    "ReadFlags",
    "EditMethod",
    "EditParams",
    "BodyPart",
    "EditTask",
    "TargetSchedule",
    "GltfContainer",
    "AmassLayout",
    "Feet",
    "RootMotion",
    "Cleanup",
    "cleanup_params_default",
    "Rig",
    "RigBone",
    "RigFormat",
    "BoneMap",
    "Retarget",
    "Robot",
    "RobotFile",
    "RobotRetarget",
    "RobotState",
    "MAX_THREADS",
    "ROOT_TRANSLATION",
    "batch",
    "read_manifest",
    "edit_params_default",
    "library_path",
    "version",
]

# The ABI version these bindings were written against (FLAME_ABI_VERSION in flame.h).
ABI_VERSION = 4

# The most worker threads a load or a session may ask for (FLAME_MAX_THREADS); more is refused
# with Status.INVALID_ARGUMENT. 0 means one per core, capped at this bound.
MAX_THREADS = 256

# Passed to Session.keep_joints to keep the root translation channels (FLAME_ROOT_TRANSLATION).
ROOT_TRANSLATION = -1


class Status:
    """FlameStatus values."""

    OK = 0
    INVALID_ARGUMENT = 1
    IO = 2
    BAD_MODEL_FILE = 3
    WRONG_STATE = 4
    CANCELLED = 5
    TOKENIZER = 6
    BUFFER_TOO_SMALL = 7
    INTERNAL = 8
    NOT_FINITE = 9


class Sampler:
    """FlameSampler values (FlameSessionParams.sampler)."""

    DEFAULT = 0
    DDPM = 1
    DDIM = 2
    EULER = 3
    HEUN = 4
    MIDPOINT = 5
    LCM = 6


class Which:
    """FlameWhich values: which motion Session.read returns."""

    SAMPLE = 0
    ESTIMATE = 1


class Layout:
    """FlameLayout values: what Session.read returns per frame (J = ModelInfo.joint_count).
    Passed to the library as plain integers, so a layout it adds later works before it is
    named here."""

    FEATURES = 0  # [frames, feature_dim] the raw features (convention and flags ignored)
    ROOT_TRANSLATION = 1  # [frames, 3]
    LOCAL_QUAT_XYZW = 2  # [frames, J, 4] parent-relative
    LOCAL_QUAT_WXYZ = 3  # [frames, J, 4]
    LOCAL_MATRIX = 4  # [frames, J, 3, 3] row-major
    LOCAL_6D = 5  # [frames, J, 6] first two matrix rows
    GLOBAL_POSITIONS = 6  # [frames, J, 3]
    GLOBAL_QUAT_XYZW = 7  # [frames, J, 4] world
    GLOBAL_QUAT_WXYZ = 8  # [frames, J, 4]
    FOOT_CONTACTS = 9  # [frames, 4] left ankle, left foot, right ankle, right foot: 0 or 1
    ROOT_BONE = 10  # [frames, 3] the root bone's position (only with RootMotion.SEPARATE)


class Convention:
    """FlameConvention values: the coordinate frame of Session.read (plain integers too)."""

    NATIVE = 0  # the motion format's own frame, untouched
    UNITY = 1  # left-handed, Y up, Z forward, metres
    UNREAL = 2  # left-handed, Z up, X forward, centimetres
    ROS = 3  # right-handed, Z up, X forward, metres
    BLENDER = 4  # right-handed, Z up, -Y forward, metres
    GLTF = 5  # right-handed, Y up, Z forward, metres


class ReadFlags:
    """Bits of Session.read's `flags`."""

    SMOOTH = 1  # FLAME's temporal Gaussian smoothing (sigma = 1 frame) before posing
    RAW_SIGNS = 2  # quaternions as computed (w >= 0), not made sign-continuous per track


class EditMethod:
    """FlameEditMethod values: how a session imposes the kept reference values."""

    AUTO = 0  # the model family's own method
    NOISED_REFERENCE = 1  # FLAME: the reference, noised to the step's level, overwrites x_t
    REPLACE_X0 = 2  # MDM: the reference overwrites the kept values of the clean-motion estimate
    REWRITE_TRAJECTORY = 3  # Motion Flow Matching (flow models), while step / steps <= edit_till


class BodyPart:
    """FlameBodyPart values for Session.keep_part (or their names: "root-path", ...)."""

    ROOT_PATH = 0  # the root's trajectory
    LOWER_BODY = 1  # root path, pelvis and legs
    UPPER_BODY = 2  # spine, neck, head, collars and arms
    ARMS = 3  # collars, shoulders, elbows, wrists (and hands)
    LEGS = 4  # hips, knees, ankles and feet (and foot contacts)


class Weights:
    """FlameWeights values for Model.load(weights=...) (or their names: "f32", "f16", "bf16",
    "bf16-compute", "int8"): what the linear layers are held and multiplied in."""

    F32 = 0  # exact; the fastest on CPUs without half-precision arithmetic
    F16 = 1  # half the memory
    BF16 = 2  # half the memory, coarser than f16
    BF16_COMPUTE = 3  # bf16 products (AVX512_BF16; refused at load without it)
    INT8 = 4  # 8-bit integer products, a quarter of the memory (AVX512_VNNI or AVX2; refused without)


class EditTask:
    """FlameEditTask values for Session.set_task_mask (or their names: "inbetween", ...)."""

    INBETWEEN = 0  # keep all but frames [L/4, 3L/4)
    PREDICT = 1  # keep frames [0, L/4)
    UPPER_BODY = 2  # keep the lower body on every frame
    PATH = 3  # keep the root path on every frame


class TargetSchedule:
    """FlameTargetSchedule values for Session.set_target_params (or their names: "mpgd",
    "constant"): how the pull of position targets changes with the noise level τ (1 = noise)."""

    MPGD = 0  # 4·τ·(1 − τ): nothing at either end, full strength half way (MoLA's MPGD)
    CONSTANT = 1  # the same weight at every step


class GltfContainer:
    """FlameGltfContainer values for Session.write_gltf (or their names: "glb", "gltf")."""

    GLB = 0  # binary glTF (.glb)
    GLTF = 1  # JSON glTF (.gltf), the buffer embedded as a base64 data URI


class AmassLayout:
    """FLAME_AMASS_* values for Session.write_amass (or their names: "smplh", "smplx")."""

    SMPLH = 0  # AMASS SMPL-H *_poses.npz: poses [N, 156], trans, mocap_framerate (PHC, human2humanoid)
    SMPLX = 1  # AMASS SMPL-X *_stageii.npz: root_orient, pose_body, trans, mocap_frame_rate (GMR)


class Feet:
    """FlameFeet values for Cleanup.feet (or their names: "off", "lock")."""

    OFF = 0  # the raw poses: feet may slide
    LOCK = 1  # each planted foot pinned where it stands, the leg solved by two-bone IK


class RootMotion:
    """FlameRootMotion values for Cleanup.root_motion (or their names: "keep", "in-place",
    "separate"): where the clip's horizontal travel goes."""

    KEEP = 0  # on the pelvis, as the model made it
    IN_PLACE = 1  # removed: the pelvis stays over the origin
    SEPARATE = 2  # on a root bone under the pelvis: Layout.ROOT_BONE, and a "root" node in glTF


@dataclass
class Cleanup:
    """FlameCleanupParams: the post-processing Session.read(cleanup=...) and
    Session.write_gltf(cleanup=...) apply to the poses. The defaults are
    flame_cleanup_params_default's, game-ready: feet locked, the floor at height 0, root motion
    kept, no wrap, the model's frame rate. Cleanup.raw() starts from every step off.

    `feet` is a Feet value or name; `ground` puts the clip's lowest foot contact at height 0;
    `root_motion` a RootMotion value or name; `remove_yaw` (with in-place or separate root
    motion) also removes the heading's drift; `wrap` cross-fades the clip's end into its start
    so it loops; `fps` the output frame rate, 1 to 240 (0 = the model's: the frame count changes
    with it). The contact_* fields tune foot-contact detection (smpl24 models): height above the
    standing level in metres, the speed in m/s below which a foot may be planted, the
    hysteresis ratio (>= 1) for leaving a contact, and the shortest span and gap kept in
    seconds. libflame checks every value (FlameError INVALID_ARGUMENT naming it)."""

    feet: Union[int, str] = Feet.LOCK
    ground: bool = True
    root_motion: Union[int, str] = RootMotion.KEEP
    remove_yaw: bool = False
    wrap: bool = False
    fps: float = 0.0
    contact_height: float = 0.05
    contact_speed: float = 0.8944272  # sqrt(0.8), HumanML3D's velocity threshold
    contact_release: float = 1.5
    contact_min_span: float = 0.1

    @classmethod
    def raw(cls, **fields) -> "Cleanup":
        """Every step off (feet free, no floor), then `fields`: with only `fps` or
        `root_motion` set, the poses change in that one way."""
        return cls(**{"feet": Feet.OFF, "ground": False, **fields})


@dataclass
class Stage:
    """One time stage of a prompt (FlameStage) for Session.set_prompt_stages, or one segment of
    a stream's timeline for Stream.push_stage and Stream.interrupt_stage: what the whole body
    does (`text`) for `frames` frames, and optionally what single body parts do (the HuMMan-MoGen
    annotation's fields; None or "" = the part follows `text`). FineMoGen models compose
    stages and read the part texts; other models take one stage without part texts."""

    text: str
    frames: int
    head: Optional[str] = None
    stem: Optional[str] = None  # the spine
    left_arm: Optional[str] = None
    right_arm: Optional[str] = None
    left_leg: Optional[str] = None
    right_leg: Optional[str] = None
    pelvis: Optional[str] = None  # the root's trajectory


# The body-part fields of Stage, in FlameStage's order.
_STAGE_PARTS = ("head", "stem", "left_arm", "right_arm", "left_leg", "right_leg", "pelvis")


def _fill_stage(r, st, what: str) -> None:
    """Fills the _Stage `r` from the Stage `st` (`what` names it in errors). The encoded texts
    stay referenced by `r` (ctypes keeps them) as long as it lives."""
    if not isinstance(st, Stage):
        raise TypeError(f"{what} is a {type(st).__name__}, not a flame.Stage")
    if not isinstance(st.frames, int) or not 0 <= st.frames <= 0xFFFFFFFF:
        raise ValueError(f"{what}.frames {st.frames!r} is not a uint32")
    r.struct_size = ctypes.sizeof(_Stage)
    r.frames = st.frames
    for name in ("text",) + _STAGE_PARTS:
        value = getattr(st, name)
        if value is None:
            continue
        if not isinstance(value, str):
            raise TypeError(f"{what}.{name} is a {type(value).__name__}, not a str")
        if "\0" in value:
            raise ValueError(f"{what}.{name} contains a NUL character")
        setattr(r, name, value.encode("utf-8"))


@dataclass
class EditParams:
    """FlameEditParams: the editing algorithm (an EditMethod value or its name, "auto",
    "noised-reference", "replace-x0", "rewrite-trajectory"), `edit_till` (flow models: the
    fraction of the steps, from the noise end, that rewrite the trajectory, in [0, 1]), `paste`
    (copy the kept values exactly into the final result and blend the seams; False = the
    official behaviour) and `seam_frames` (frames over which a seam fades, 0..=1000). The
    defaults are flame_edit_params_default's."""

    method: Union[int, str] = EditMethod.AUTO
    edit_till: float = 0.2
    paste: bool = True
    seam_frames: int = 4


# --- the shared library ------------------------------------------------------------------------


def _library_names() -> List[str]:
    if sys.platform == "win32":
        return ["flame.dll"]
    if sys.platform == "darwin":
        return ["libflame.dylib"]
    return ["libflame.so"]


def _candidate_paths() -> List[Path]:
    here = Path(__file__).resolve().parent
    found = [here / n for n in _library_names()]
    # A checkout: bindings/python/flame/ -> the repository root is three levels up.
    root = here.parents[2] if len(here.parents) > 2 else here
    for profile in ("release", "debug"):
        found += [root / "target" / profile / n for n in _library_names()]
    return found


def library_path() -> str:
    """Where the shared library is loaded from (see the module doc for the search order)."""
    env = os.environ.get("FLAME_LIBRARY")
    if env:
        if not Path(env).is_file():
            raise OSError(f"FLAME_LIBRARY={env!r} is not a file")
        return env
    for p in _candidate_paths():
        if p.is_file():
            return str(p)
    system = ctypes.util.find_library("flame")
    if system:
        return system
    tried = ", ".join(str(p) for p in _candidate_paths())
    raise OSError(
        "libflame not found: set FLAME_LIBRARY to the library's path, or build it with "
        f"`cargo build --release` (tried {tried} and the system library path)"
    )


class _ModelParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("threads", ctypes.c_uint32),
        ("weights", ctypes.c_int32),
    ]



class _ModelInfo(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("feature_dim", ctypes.c_uint32),
        ("joint_count", ctypes.c_uint32),
        ("max_frames", ctypes.c_uint32),
        ("default_frames", ctypes.c_uint32),
        ("default_steps", ctypes.c_uint32),
        ("num_timesteps", ctypes.c_uint32),
        ("default_sampler", ctypes.c_int32),
        ("fps", ctypes.c_float),
        ("default_guidance", ctypes.c_float),
        ("default_eta", ctypes.c_float),
        ("architecture", ctypes.c_char_p),
        ("motion_format", ctypes.c_char_p),
        ("text_encoder", ctypes.c_char_p),
        ("joint_names", ctypes.POINTER(ctypes.c_char_p)),
        ("joint_parents", ctypes.POINTER(ctypes.c_int32)),
        ("latent", ctypes.c_uint32),
        ("sample_dim", ctypes.c_uint32),
        ("control", ctypes.c_uint32),
    ]


class _Stage(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("frames", ctypes.c_uint32),
        ("text", ctypes.c_char_p),
        ("head", ctypes.c_char_p),
        ("stem", ctypes.c_char_p),
        ("left_arm", ctypes.c_char_p),
        ("right_arm", ctypes.c_char_p),
        ("left_leg", ctypes.c_char_p),
        ("right_leg", ctypes.c_char_p),
        ("pelvis", ctypes.c_char_p),
    ]


class _PromptInfo(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("tokens", ctypes.c_uint32),
        ("kept", ctypes.c_uint32),
        ("window", ctypes.c_uint32),
        ("truncated", ctypes.c_uint32),
        ("unconditional", ctypes.c_uint32),
        ("dropped", ctypes.c_char_p),
    ]


class _TuningReport(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("iterations", ctypes.c_uint32),
        ("hint_loss_before", ctypes.c_double),
        ("hint_loss_after", ctypes.c_double),
        ("control_error_before", ctypes.c_double),
        ("control_error_after", ctypes.c_double),
    ]


class _SessionParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("frames", ctypes.c_uint32),
        ("steps", ctypes.c_uint32),
        ("sampler", ctypes.c_int32),
        ("eta", ctypes.c_float),
        ("guidance", ctypes.c_float),
        ("seed", ctypes.c_uint64),
        ("threads", ctypes.c_uint32),
        ("respacing", ctypes.c_char_p),
        ("looped", ctypes.c_uint32),  # since version 3 of the struct (ABI 4)
    ]


class _EditParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("method", ctypes.c_int32),
        ("edit_till", ctypes.c_float),
        ("paste", ctypes.c_uint32),
        ("seam_frames", ctypes.c_uint32),
    ]


class _TargetParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("scale", ctypes.c_float),
        ("schedule", ctypes.c_int32),
    ]


class _CleanupParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("feet", ctypes.c_int32),
        ("ground", ctypes.c_uint32),
        ("root_motion", ctypes.c_int32),
        ("remove_yaw", ctypes.c_uint32),
        ("wrap", ctypes.c_uint32),
        ("fps", ctypes.c_float),
        ("contact_height", ctypes.c_float),
        ("contact_speed", ctypes.c_float),
        ("contact_release", ctypes.c_float),
        ("contact_min_span", ctypes.c_float),
    ]


class _GltfParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("container", ctypes.c_int32),
        ("flags", ctypes.c_uint32),
        ("fps", ctypes.c_float),
        ("name", ctypes.c_char_p),
        ("cleanup", ctypes.POINTER(_CleanupParams)),  # since version 2 of the struct (ABI 3)
    ]


class _StreamParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("chunk", ctypes.c_uint32),
        ("overlap", ctypes.c_uint32),
        ("lookahead", ctypes.c_uint32),
        ("window", ctypes.c_uint32),
        ("steps", ctypes.c_uint32),
        ("sampler", ctypes.c_int32),
        ("guidance", ctypes.c_float),
        ("seed", ctypes.c_uint64),
        ("threads", ctypes.c_uint32),
    ]


class _StreamStatus(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("steps", ctypes.c_uint32),
        ("ready", ctypes.c_uint64),
        ("first_frame", ctypes.c_uint64),
        ("playhead", ctypes.c_uint64),
        ("starving", ctypes.c_uint32),
    ]


_ProgressCallback = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32)

_P = ctypes.c_void_p  # opaque FlameModel* / FlameSession*
_status = ctypes.c_int  # enum FlameStatus


def _signatures():
    """(restype, argtypes) of every function of flame.h, by name (the retarget functions'
    from flame.retarget, the robot ones' from flame.robot, the batch ones' from flame._batch)."""
    from . import _batch
    from . import retarget as _retarget
    from . import robot as _robot

    return {**_core_signatures(), **_retarget._signatures(), **_robot._signatures(),
            **_batch._signatures()}


def _core_signatures():
    u32, i32, size_t = ctypes.c_uint32, ctypes.c_int32, ctypes.c_size_t
    pu32 = ctypes.POINTER(u32)
    pf32 = ctypes.POINTER(ctypes.c_float)
    return {
        "flame_abi_version": (u32, []),
        "flame_version_string": (ctypes.c_char_p, []),
        "flame_model_params_default": (_status, [ctypes.POINTER(_ModelParams)]),
        "flame_model_load": (
            _status,
            [ctypes.c_char_p, ctypes.POINTER(_ModelParams), ctypes.POINTER(_P)],
        ),
        "flame_model_load_from_memory": (
            _status,
            [ctypes.c_void_p, size_t, ctypes.POINTER(_ModelParams), ctypes.POINTER(_P)],
        ),
        "flame_model_free": (None, [_P]),
        "flame_model_info": (_status, [_P, ctypes.POINTER(_ModelInfo)]),
        "flame_session_params_default": (_status, [ctypes.POINTER(_SessionParams)]),
        "flame_edit_params_default": (_status, [ctypes.POINTER(_EditParams)]),
        "flame_session_set_edit_params": (_status, [_P, ctypes.POINTER(_EditParams)]),
        "flame_target_params_default": (_status, [ctypes.POINTER(_TargetParams)]),
        "flame_session_set_target_params": (_status, [_P, ctypes.POINTER(_TargetParams)]),
        "flame_session_target_params": (_status, [_P, ctypes.POINTER(_TargetParams)]),
        "flame_session_set_position_targets": (
            _status,
            [_P, pf32, size_t, ctypes.POINTER(ctypes.c_uint8), size_t, i32],
        ),
        "flame_session_clear_position_targets": (_status, [_P]),
        "flame_session_set_control": (
            _status,
            [_P, pf32, size_t, ctypes.POINTER(ctypes.c_uint8), size_t, i32],
        ),
        "flame_session_clear_control": (_status, [_P]),
        "flame_session_tune_latent": (
            _status,
            [_P, ctypes.c_uint32, ctypes.POINTER(_TuningReport)],
        ),
        "flame_session_target_loss": (_status, [_P, ctypes.POINTER(ctypes.c_double)]),
        "flame_session_new": (
            _status,
            [_P, ctypes.POINTER(_SessionParams), ctypes.POINTER(_P)],
        ),
        "flame_session_free": (None, [_P]),
        "flame_session_reset": (_status, [_P]),
        "flame_session_set_prompt": (_status, [_P, ctypes.c_char_p]),
        "flame_session_set_prompt_from": (_status, [_P, _P]),
        "flame_session_set_prompt_stages": (_status, [_P, ctypes.POINTER(_Stage), size_t]),
        "flame_session_prompt_info": (_status, [_P, ctypes.POINTER(_PromptInfo)]),
        "flame_session_set_noise": (_status, [_P, pf32, size_t]),
        "flame_session_set_reference": (_status, [_P, pf32, u32, u32]),
        "flame_session_set_mask": (_status, [_P, ctypes.POINTER(ctypes.c_uint8), u32, u32]),
        "flame_session_keep_frames": (_status, [_P, u32, u32]),
        "flame_session_keep_joints": (_status, [_P, ctypes.POINTER(i32), size_t]),
        "flame_session_keep_part": (_status, [_P, i32, u32, u32]),
        "flame_session_set_task_mask": (_status, [_P, i32]),
        "flame_session_set_task_targets": (_status, [_P, pf32, u32, u32, i32]),
        "flame_session_set_reference_poses": (
            _status,
            [_P, pf32, size_t, pf32, size_t, u32, i32, i32],
        ),
        "flame_session_clear_edit": (_status, [_P]),
        "flame_session_set_progress_callback": (_status, [_P, _ProgressCallback, ctypes.c_void_p]),
        "flame_session_step": (_status, [_P, pu32]),
        "flame_session_cancel": (_status, [_P]),
        "flame_session_progress": (_status, [_P, pu32, pu32]),
        "flame_session_read": (
            _status,
            [_P, i32, i32, i32, u32, pf32, size_t, ctypes.POINTER(size_t)],
        ),
        "flame_gltf_params_default": (_status, [ctypes.POINTER(_GltfParams)]),
        "flame_session_write_gltf": (
            _status,
            [_P, i32, ctypes.POINTER(_GltfParams), ctypes.POINTER(ctypes.c_uint8), size_t,
             ctypes.POINTER(size_t)],
        ),
        "flame_session_write_amass": (
            _status,
            [_P, i32, i32, u32, ctypes.POINTER(_CleanupParams), ctypes.POINTER(ctypes.c_uint8),
             size_t, ctypes.POINTER(size_t)],
        ),
        "flame_stream_params_default": (_status, [ctypes.POINTER(_StreamParams)]),
        "flame_stream_new": (_status, [_P, ctypes.POINTER(_StreamParams), ctypes.POINTER(_P)]),
        "flame_stream_free": (None, [_P]),
        "flame_stream_push": (_status, [_P, ctypes.c_char_p, u32]),
        "flame_stream_interrupt": (_status, [_P, ctypes.c_char_p, u32]),
        "flame_stream_push_stage": (_status, [_P, ctypes.POINTER(_Stage)]),
        "flame_stream_interrupt_stage": (_status, [_P, ctypes.POINTER(_Stage)]),
        "flame_stream_cancel": (_status, [_P]),
        "flame_stream_set_playhead": (_status, [_P, ctypes.c_uint64]),
        "flame_stream_pump": (_status, [_P, u32, ctypes.POINTER(_StreamStatus)]),
        "flame_stream_status": (_status, [_P, ctypes.POINTER(_StreamStatus)]),
        "flame_stream_read": (
            _status,
            [_P, ctypes.c_uint64, u32, i32, i32, u32, pf32, size_t, ctypes.POINTER(size_t)],
        ),
        "flame_stream_read_cleaned": (
            _status,
            [_P, ctypes.c_uint64, u32, i32, i32, ctypes.POINTER(_CleanupParams), pf32, size_t,
             ctypes.POINTER(size_t)],
        ),
        "flame_stream_close": (_status, [_P]),
        "flame_stream_close_looped": (_status, [_P, u32]),
        "flame_cleanup_params_default": (_status, [ctypes.POINTER(_CleanupParams)]),
        "flame_session_read_cleaned": (
            _status,
            [_P, i32, i32, i32, u32, ctypes.POINTER(_CleanupParams), pf32, size_t,
             ctypes.POINTER(size_t)],
        ),
        "flame_session_sample_shape": (_status, [_P, pu32, pu32]),
        "flame_session_read_frames": (_status, [_P, i32, pu32]),
        "flame_last_error": (ctypes.c_char_p, []),
        "flame_status_string": (ctypes.c_char_p, [i32]),
    }


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    for name, (restype, argtypes) in _signatures().items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


_lib_lock = threading.Lock()
_lib_handle: Optional[ctypes.CDLL] = None


def _lib() -> ctypes.CDLL:
    """The bound library, loaded on first use (so importing never fails for a missing library)."""
    global _lib_handle
    with _lib_lock:
        if _lib_handle is None:
            lib = _bind(ctypes.CDLL(library_path()))
            abi = lib.flame_abi_version()
            if abi != ABI_VERSION:
                raise OSError(
                    f"libflame ABI version {abi} does not match these bindings' {ABI_VERSION}"
                )
            _lib_handle = lib
        return _lib_handle


def version() -> str:
    """The library's version string, e.g. "0.1.0"."""
    return _lib().flame_version_string().decode()


# --- errors ------------------------------------------------------------------------------------


class PromptTruncatedWarning(UserWarning):
    """Issued by Session.set_prompt when the prompt is longer than the text encoder's window:
    the encoder saw only its first tokens. The message names the kept and total tokens and the
    dropped text; Session.prompt_info() has the same as values. Silence it with
    `warnings.simplefilter("ignore", flame.PromptTruncatedWarning)`."""


class FlameError(Exception):
    """A failed libflame call: `status` is a Status value, `message` flame_last_error()."""

    def __init__(self, status: int, message: str):
        self.status = status
        self.message = message
        name = _lib().flame_status_string(status).decode()
        self.status_name = name
        super().__init__(f"{name}: {message}")


def _check(status: int) -> None:
    # flame_last_error is per OS thread and valid until the next call on it: read it right away,
    # on the thread that made the failing call (the one running this function).
    if status != Status.OK:
        raw = _lib().flame_last_error()
        raise FlameError(status, raw.decode("utf-8", "replace") if raw else "")


# --- numpy helpers -----------------------------------------------------------------------------


def _f32(array, name: str) -> np.ndarray:
    a = np.ascontiguousarray(array, dtype=np.float32)
    if a.ndim == 0:
        raise ValueError(f"{name} must be an array, not a scalar")
    return a


def _frames_by_dim(a: np.ndarray, dim: int, name: str):
    """(frames, dim) of a 2-D array, or of a flat one whose length is a multiple of dim."""
    if a.ndim == 2:
        return a.shape[0], a.shape[1]
    if a.ndim == 1 and dim and a.size % dim == 0:
        return a.size // dim, dim
    raise ValueError(f"{name} must be shaped [frames, {dim}], got {a.shape}")


def _ptr(a: np.ndarray, ctype):
    return a.ctypes.data_as(ctypes.POINTER(ctype))


# --- model -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelInfo:
    """What flame_model_info reports, copied into Python values."""

    feature_dim: int
    joint_count: int
    max_frames: int
    default_frames: int
    default_steps: int
    num_timesteps: int
    default_sampler: int
    fps: float
    default_guidance: float
    default_eta: float
    architecture: str
    motion_format: str
    text_encoder: str
    joint_names: List[str]
    joint_parents: List[int]
    # True when the model samples a latent that its decoder turns into motion (MoLA): a read's
    # frames are then the length the decoder decides (Session.read_frames), and masks and
    # reference motions do not apply.
    latent: bool
    # Channels per row of the sampled space (feature_dim, or the latent's channels): the width
    # of Session.set_noise's rows.
    sample_dim: int
    # True when the model has a trajectory ControlNet (MotionLCM control files):
    # Session.set_control makes its motion follow joint positions.
    control: bool = False


def _mask_arg(mask):
    """A per-value mask as (array kept alive, pointer, length): None for no mask (NULL, 0)."""
    if mask is None:
        return None, None, 0
    m = np.asarray(mask)
    m = np.ascontiguousarray((m != 0) if m.dtype != np.uint8 else m, dtype=np.uint8)
    # An empty mask is still a mask (libflame refuses its length), not "no mask" (NULL).
    return m, _ptr(m if m.size else np.zeros(1, dtype=np.uint8), ctypes.c_uint8), m.size


def _text(p: Optional[bytes]) -> str:
    return p.decode("utf-8", "replace") if p else ""


@dataclass(frozen=True)
class PromptInfo:
    """What flame_session_prompt_info reports about the last prompt: `tokens` of the whole
    prompt and `kept` of them by the text encoder (special tokens included), its `window`,
    whether the window cut the prompt (`truncated`), whether the prompt was empty or blank
    (`unconditional`: generation without text) and the `dropped` text ("" when nothing was)."""

    tokens: int
    kept: int
    window: int
    truncated: bool
    unconditional: bool
    dropped: str


@dataclass(frozen=True)
class TuningReport:
    """What Session.tune_latent did: the `iterations` run, the hint loss (mean squared distance
    over the hinted coordinates, m²) and the control error (mean distance of a hinted joint from
    its target, m), each (at the first latent, at the tuned one)."""

    iterations: int
    hint_loss: Tuple[float, float]
    control_error: Tuple[float, float]


def _uint32(name: str, value: int) -> int:
    """`value` for a uint32 field: ctypes would silently wrap a negative or larger one."""
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError(f"{name} {value} is not a uint32 (threads: 0 to {MAX_THREADS})")
    return value


def _model_params(threads: int, weights: Union[str, int]) -> _ModelParams:
    names = {n.lower(): v for n, v in vars(Weights).items() if n.isupper()}
    if isinstance(weights, str):
        key = weights.lower().replace("-", "_")
        if key not in names:
            raise ValueError(f"weights must be one of {sorted(names)}, not {weights!r}")
        weights = names[key]
    p = _ModelParams()
    _check(_lib().flame_model_params_default(ctypes.byref(p)))
    p.threads = _uint32("threads", threads)
    p.weights = weights
    return p


class Model:
    """A loaded model: immutable, shareable by any number of sessions and threads. Close it (or
    use `with`) to release it early; its sessions keep it alive natively, so closing a model does
    not invalidate them."""

    def __init__(self, handle: int):
        if not handle:
            raise ValueError("Model() takes a handle; use Model.load or Model.from_bytes")
        self._handle: Optional[int] = handle
        self._info: Optional[ModelInfo] = None

    @classmethod
    def load(
        cls, path: Union[str, os.PathLike], threads: int = 0, weights: Union[str, int] = "f32"
    ) -> "Model":
        """Loads a model file. `threads` is for work done at load (0 = one per core, at most
        MAX_THREADS); `weights`
        ("f32", "f16", "bf16", "bf16-compute", "int8" or a `Weights` value) is what the linear
        layers are held and multiplied in."""
        out = _P()
        params = _model_params(threads, weights)
        _check(_lib().flame_model_load(os.fsencode(path), ctypes.byref(params), ctypes.byref(out)))
        m = cls(out.value)
        # What `flame.batch` records in glTF outputs, as `flame batch` records the file's name.
        m._file_name = Path(path).name
        return m

    @classmethod
    def from_bytes(
        cls,
        data: Union[bytes, bytearray, memoryview],
        threads: int = 0,
        weights: Union[str, int] = "f32",
    ) -> "Model":
        """Loads a model from the bytes of a model file (libflame copies them); `threads` and
        `weights` as in `load`."""
        buf = np.frombuffer(data, dtype=np.uint8)
        out = _P()
        params = _model_params(threads, weights)
        _check(
            _lib().flame_model_load_from_memory(
                buf.ctypes.data if buf.size else None,
                buf.size,
                ctypes.byref(params),
                ctypes.byref(out),
            )
        )
        return cls(out.value)

    def _h(self) -> int:
        if self._handle is None:
            raise ValueError("the model is closed")
        return self._handle

    @property
    def info(self) -> ModelInfo:
        if self._info is None:
            raw = _ModelInfo()
            raw.struct_size = ctypes.sizeof(_ModelInfo)
            _check(_lib().flame_model_info(self._h(), ctypes.byref(raw)))
            n = raw.joint_count
            names = [_text(raw.joint_names[i]) for i in range(n)] if raw.joint_names else []
            parents = [int(raw.joint_parents[i]) for i in range(n)] if raw.joint_parents else []
            self._info = ModelInfo(
                feature_dim=raw.feature_dim,
                joint_count=n,
                max_frames=raw.max_frames,
                default_frames=raw.default_frames,
                default_steps=raw.default_steps,
                num_timesteps=raw.num_timesteps,
                default_sampler=raw.default_sampler,
                fps=raw.fps,
                default_guidance=raw.default_guidance,
                default_eta=raw.default_eta,
                architecture=_text(raw.architecture),
                motion_format=_text(raw.motion_format),
                text_encoder=_text(raw.text_encoder),
                joint_names=names,
                joint_parents=parents,
                latent=bool(raw.latent),
                sample_dim=raw.sample_dim,
                control=bool(raw.control),
            )
        return self._info

    @property
    def latent(self) -> bool:
        """Whether the model samples a latent that its decoder turns into motion (ModelInfo.latent)."""
        return self.info.latent

    @property
    def sample_dim(self) -> int:
        """Channels per row of the sampled space (ModelInfo.sample_dim)."""
        return self.info.sample_dim

    def session(
        self,
        frames: Optional[int] = None,
        steps: Optional[int] = None,
        sampler: Union[None, str, int] = None,
        eta: Optional[float] = None,
        guidance: Optional[float] = None,
        seed: int = 0,
        threads: int = 0,
        respacing: Optional[str] = None,
        looped: bool = False,
    ) -> "Session":
        """Starts a generation. None takes the model file's default; `sampler` is "ddpm",
        "ddim", "euler", "heun", "midpoint" or a Sampler value; `threads` 0 = one per core, at most
        MAX_THREADS (the session owns its threads). `respacing` is a guided-diffusion respacing
        string ("ddim50", "50", "15,15,8,6,6") choosing which training steps to sample; it sets
        the step count (`steps`, if given, must agree) and is refused by flow models and models
        with diffusers spacing.

        `looped=True` generates a loop of `frames` frames whose end flows into its start
        (FlameSessionParams.looped, as `flame generate --loop`): the session samples twice, a
        generation of `frames` plus a lead of 0.5 s, then an edit of it that keeps the lead on
        both sides of the wrap. step() and `progress` count both passes (`steps=4` is 8 steps
        in all). The finished sample reads as the cycle's `frames` frames: every pose read
        applies the wrap's correction (a Cleanup's `wrap` is taken as on), the raw features
        drop the next cycle's first frame. FlameError INVALID_ARGUMENT for a latent model
        (Model.latent: use Cleanup(wrap=True) on a plain session) and a cycle too short or too
        long for the model; a loop session refuses time stages, references, masks and position
        targets."""
        return Session(self, frames, steps, sampler, eta, guidance, seed, threads, respacing,
                       looped=looped)

    def retarget(self, rig: "Rig", map: Optional["BoneMap"] = None, feet: bool = True,
                 hands: bool = False, convention: int = Convention.NATIVE) -> "Retarget":
        """A Retarget of this model's poses onto `rig` (flame_retarget_new): `map` None = the
        automatic bone map; `feet` / `hands` two-bone IK on the legs / arms; `convention` of
        the poses read (NATIVE = the rig's own)."""
        return Retarget(self, rig, map, feet, hands, convention)

    def close(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            _lib().flame_model_free(handle)

    def __enter__(self) -> "Model":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may already be gone
            pass


# --- session -----------------------------------------------------------------------------------

# Per-frame shape of each named layout, from (feature_dim, joint_count).
_LAYOUT_SHAPES = {
    Layout.FEATURES: lambda d, j: (d,),
    Layout.ROOT_TRANSLATION: lambda d, j: (3,),
    Layout.LOCAL_QUAT_XYZW: lambda d, j: (j, 4),
    Layout.LOCAL_QUAT_WXYZ: lambda d, j: (j, 4),
    Layout.LOCAL_MATRIX: lambda d, j: (j, 3, 3),
    Layout.LOCAL_6D: lambda d, j: (j, 6),
    Layout.GLOBAL_POSITIONS: lambda d, j: (j, 3),
    Layout.GLOBAL_QUAT_XYZW: lambda d, j: (j, 4),
    Layout.GLOBAL_QUAT_WXYZ: lambda d, j: (j, 4),
    Layout.FOOT_CONTACTS: lambda d, j: (4,),
    Layout.ROOT_BONE: lambda d, j: (3,),
}

_SAMPLERS = {None: Sampler.DEFAULT, "default": Sampler.DEFAULT, "ddpm": Sampler.DDPM, "ddim": Sampler.DDIM,
             "euler": Sampler.EULER, "heun": Sampler.HEUN, "midpoint": Sampler.MIDPOINT,
             "lcm": Sampler.LCM}
_WHICH = {"sample": Which.SAMPLE, "estimate": Which.ESTIMATE}
_EDIT_METHODS = {"auto": EditMethod.AUTO, "noised-reference": EditMethod.NOISED_REFERENCE,
                 "replace-x0": EditMethod.REPLACE_X0, "rewrite-trajectory": EditMethod.REWRITE_TRAJECTORY}
_BODY_PARTS = {"root-path": BodyPart.ROOT_PATH, "lower-body": BodyPart.LOWER_BODY,
               "upper-body": BodyPart.UPPER_BODY, "arms": BodyPart.ARMS, "legs": BodyPart.LEGS}
_TARGET_SCHEDULES = {"mpgd": TargetSchedule.MPGD, "constant": TargetSchedule.CONSTANT}
_GLTF_CONTAINERS = {"glb": GltfContainer.GLB, "gltf": GltfContainer.GLTF}
_FEET = {"off": Feet.OFF, "lock": Feet.LOCK}
_ROOT_MOTIONS = {"keep": RootMotion.KEEP, "in-place": RootMotion.IN_PLACE,
                 "separate": RootMotion.SEPARATE}
_TASKS = {"inbetween": EditTask.INBETWEEN, "predict": EditTask.PREDICT,
          "upper-body": EditTask.UPPER_BODY, "path": EditTask.PATH}


def _named(value, names: dict, what: str) -> int:
    """A named value by its name (case-insensitive, '_' or '-') or as a plain integer."""
    if isinstance(value, str):
        key = value.strip().lower().replace("_", "-")
        if key not in names:
            raise ValueError(f"unknown {what} {value!r} ({', '.join(names)})")
        return names[key]
    return int(value)


_AMASS_LAYOUTS = {"smplh": AmassLayout.SMPLH, "smplx": AmassLayout.SMPLX}


def _gltf_container(container, path) -> int:
    """A GltfContainer value: `container` by name or value, else from the extension of `path`."""
    if container is not None:
        return _named(container, _GLTF_CONTAINERS, "glTF container")
    if path is None:
        return GltfContainer.GLB
    ext = os.path.splitext(os.fsdecode(path))[1].lower()
    if ext in ("", ".glb"):
        return GltfContainer.GLB
    if ext == ".gltf":
        return GltfContainer.GLTF
    raise ValueError(f"cannot tell the glTF container from {os.fsdecode(path)!r}: name it .glb or "
                     ".gltf, or pass container=\"glb\" or \"gltf\"")


def _sampler_value(sampler: Union[None, str, int]) -> int:
    """A FlameSampler value from a name (any case), None (the model's default) or an int."""
    if isinstance(sampler, str) or sampler is None:
        key = sampler.lower() if isinstance(sampler, str) else None
        if key not in _SAMPLERS:
            raise ValueError(f"unknown sampler {sampler!r} (ddpm, ddim, euler, heun, midpoint)")
        return _SAMPLERS[key]
    return int(sampler)


def _shortest(x: float) -> float:
    """The shortest decimal that is the same float32 (0.05, not 0.0500000007...)."""
    return float(str(np.float32(x)))


def cleanup_params_default() -> Cleanup:
    """The library's cleanup defaults (flame_cleanup_params_default): what Cleanup() holds."""
    raw = _CleanupParams()
    _check(_lib().flame_cleanup_params_default(ctypes.byref(raw)))
    return Cleanup(feet=raw.feet, ground=bool(raw.ground), root_motion=raw.root_motion,
                   remove_yaw=bool(raw.remove_yaw), wrap=bool(raw.wrap), fps=_shortest(raw.fps),
                   contact_height=_shortest(raw.contact_height),
                   contact_speed=_shortest(raw.contact_speed),
                   contact_release=_shortest(raw.contact_release),
                   contact_min_span=_shortest(raw.contact_min_span))


def _cleanup_params(cleanup: Optional[Cleanup]) -> Optional[_CleanupParams]:
    """The C struct of a Cleanup (None stays None: the raw poses). Ranges are libflame's to
    check, so its messages name the value; only types are checked here."""
    if cleanup is None:
        return None
    if not isinstance(cleanup, Cleanup):
        raise TypeError(f"cleanup is a {type(cleanup).__name__}, not a flame.Cleanup")
    raw = _CleanupParams()
    raw.struct_size = ctypes.sizeof(_CleanupParams)
    raw.feet = _named(cleanup.feet, _FEET, "feet")
    raw.ground = 1 if cleanup.ground else 0
    raw.root_motion = _named(cleanup.root_motion, _ROOT_MOTIONS, "root motion")
    raw.remove_yaw = 1 if cleanup.remove_yaw else 0
    raw.wrap = int(cleanup.wrap)  # a bool, or a later ABI's wrap mode number
    for name in ("fps", "contact_height", "contact_speed", "contact_release", "contact_min_span"):
        setattr(raw, name, float(getattr(cleanup, name)))
    return raw


def edit_params_default() -> EditParams:
    """The library's editing defaults (flame_edit_params_default)."""
    raw = _EditParams()
    _check(_lib().flame_edit_params_default(ctypes.byref(raw)))
    # The shortest decimal that is the same float32 (0.2, not 0.20000000298...).
    edit_till = float(str(np.float32(raw.edit_till)))
    return EditParams(raw.method, edit_till, bool(raw.paste), raw.seam_frames)

ProgressFn = Callable[[int, int], None]


@dataclass(frozen=True)
class StreamStatus:
    """What Stream.pump did (steps) and where the stream stands: frames first_frame..ready
    can be read; starving = fewer than lookahead frames ahead of the playhead and nothing left
    to generate them from (push more)."""
    steps: int
    ready: int
    first_frame: int
    playhead: int
    starving: bool


class Stream:
    """Continuous motion from a timeline of prompts (flame_stream_*, docs/streams.md): push
    segments, pump a bounded number of denoiser steps at a time, move the playhead, read
    frames. A latent model whose decoder has a gradient (MoLA) streams through position
    targets; MLD is refused at creation. Methods raise FlameError when libflame reports a
    failure (frames not generated yet: Status.WRONG_STATE; dropped: INVALID_ARGUMENT; a
    cancelled pump: CANCELLED).

    Threads: used by one thread at a time, except cancel(), which any thread may call while
    another is inside pump(). The C calls release the GIL."""

    def __init__(self, model: "Model", *, chunk: int = 0, overlap: int = 0, lookahead: int = 0,
                 window: int = 0, steps: int = 0, sampler: Union[None, str, int] = None,
                 guidance: Optional[float] = None, seed: int = 0, threads: int = 0):
        self._handle: Optional[int] = None
        # Held by every call but cancel(), so close() from another thread waits for a running
        # pump instead of freeing the stream under it; cancel() holds only _cancel_lock.
        self._lock = threading.RLock()
        self._cancel_lock = threading.Lock()
        info = model.info
        p = _StreamParams()
        _check(_lib().flame_stream_params_default(ctypes.byref(p)))
        for name, value in (("chunk", chunk), ("overlap", overlap), ("lookahead", lookahead),
                            ("window", window), ("steps", steps), ("threads", threads)):
            if value:
                setattr(p, name, _uint32(name, value))
        p.sampler = _sampler_value(sampler)
        p.guidance = -1.0 if guidance is None else guidance
        p.seed = seed
        out = _P()
        _check(_lib().flame_stream_new(model._h(), ctypes.byref(p), ctypes.byref(out)))
        self._handle = out.value
        self._model = model  # the stream keeps its model alive; this keeps the Python object
        self.feature_dim = info.feature_dim
        self.joint_count = info.joint_count

    def _h(self) -> int:
        if self._handle is None:
            raise ValueError("the stream is closed")
        return self._handle

    @staticmethod
    def _text(prompt: str) -> bytes:
        if "\0" in prompt:
            raise ValueError("prompt contains a NUL character")
        return prompt.encode("utf-8")

    def push(self, prompt: str, frames: int) -> None:
        """Appends a segment of `frames` frames to the timeline."""
        with self._lock:
            _check(_lib().flame_stream_push(self._h(), self._text(prompt), _uint32("frames", frames)))

    def interrupt(self, prompt: str, frames: int) -> None:
        """Ends the current segment at the next chunk boundary and replaces the queued ones."""
        with self._lock:
            _check(_lib().flame_stream_interrupt(self._h(), self._text(prompt),
                                                 _uint32("frames", frames)))

    def push_stage(self, stage: Stage) -> None:
        """Appends a segment with part texts: a Stage (as Session.set_prompt_stages takes them)
        of `stage.frames` frames. FineMoGen reads the part texts (each chunk of the segment is
        one stage with them); other models take a stage without part texts as push(stage.text,
        stage.frames) and refuse part texts with FlameError (INVALID_ARGUMENT) from the pump()
        that starts the segment."""
        raw = _Stage()
        _fill_stage(raw, stage, "stage")
        with self._lock:
            _check(_lib().flame_stream_push_stage(self._h(), ctypes.byref(raw)))

    def interrupt_stage(self, stage: Stage) -> None:
        """interrupt() with part texts (see push_stage)."""
        raw = _Stage()
        _fill_stage(raw, stage, "stage")
        with self._lock:
            _check(_lib().flame_stream_interrupt_stage(self._h(), ctypes.byref(raw)))

    def cancel(self) -> None:
        """Abandons the step a pump() on another thread is running: that pump raises FlameError
        with status CANCELLED within one transformer layer, and the step leaves no trace, so
        pumping again gives the frames of a stream never cancelled. With no pump running, the
        next pump's first step is cancelled. Thread-safe; a no-op on a closed stream."""
        with self._cancel_lock:  # close() frees the handle only under it
            handle = self._handle
            if handle is not None:
                _check(_lib().flame_stream_cancel(handle))

    def set_playhead(self, frame: int) -> None:
        with self._lock:
            _check(_lib().flame_stream_set_playhead(self._h(), frame))

    @staticmethod
    def _status(raw: _StreamStatus) -> StreamStatus:
        return StreamStatus(raw.steps, raw.ready, raw.first_frame, raw.playhead, bool(raw.starving))

    def pump(self, max_steps: int = 0xFFFFFFFF) -> StreamStatus:
        """Runs at most `max_steps` denoiser steps towards the lookahead. Raises FlameError with
        status CANCELLED when cancel() stopped it; pump again to go on."""
        raw = _StreamStatus(struct_size=ctypes.sizeof(_StreamStatus))
        with self._lock:
            _check(_lib().flame_stream_pump(self._h(), _uint32("max_steps", max_steps),
                                            ctypes.byref(raw)))
        return self._status(raw)

    def status(self) -> StreamStatus:
        raw = _StreamStatus(struct_size=ctypes.sizeof(_StreamStatus))
        with self._lock:
            _check(_lib().flame_stream_status(self._h(), ctypes.byref(raw)))
        return self._status(raw)

    def read(self, first_frame: int, count: int, layout: int, convention: int = 0,
             cleanup: Optional["Cleanup"] = None) -> np.ndarray:
        """Timeline frames first_frame..first_frame+count as float32, [count, ...] as the layout
        says (Layout.FEATURES: model-space features). With a cleanup
        (flame_stream_read_cleaned): the post-processed poses, a frame readable once its cleanup
        is final (WRONG_STATE before: pump more, or end_timeline()); the first cleaned read sets
        the stream's cleanup for good; with a frame rate, frames count at that rate."""
        lib = _lib()
        n = ctypes.c_size_t()
        count = _uint32("count", count)
        raw_cleanup = _cleanup_params(cleanup)
        with self._lock:
            h = self._h()
            if raw_cleanup is None:
                _check(lib.flame_stream_read(h, first_frame, count, layout, convention, 0, None,
                                             0, ctypes.byref(n)))
                out = np.empty(n.value, dtype=np.float32)
                _check(lib.flame_stream_read(h, first_frame, count, layout, convention, 0,
                                             _ptr(out, ctypes.c_float), out.size,
                                             ctypes.byref(n)))
            else:
                cp = ctypes.byref(raw_cleanup)
                _check(lib.flame_stream_read_cleaned(h, first_frame, count, layout, convention,
                                                     cp, None, 0, ctypes.byref(n)))
                out = np.empty(n.value, dtype=np.float32)
                _check(lib.flame_stream_read_cleaned(h, first_frame, count, layout, convention,
                                                     cp, _ptr(out, ctypes.c_float), out.size,
                                                     ctypes.byref(n)))
        trailing = _LAYOUT_SHAPES.get(layout, lambda d, j: (-1,))(self.feature_dim, self.joint_count)
        if count and -1 not in trailing and out.size == count * int(np.prod(trailing)):
            return out.reshape((count,) + trailing)
        return out.reshape(count, -1) if count else out

    def end_timeline(self) -> None:
        """flame_stream_close: the timeline is complete (push and interrupt are WRONG_STATE
        afterwards); once the pushed segments are generated, every frame's cleanup settles."""
        with self._lock:
            _check(_lib().flame_stream_close(self._h()))

    def end_timeline_looped(self, bridge_frames: int) -> None:
        """flame_stream_close_looped: end_timeline(), and the timeline loops. After the pushed
        segments the stream generates a bridge of `bridge_frames` frames (the last segment's
        prompt) whose end runs into the timeline's first frames, moved by the loop's root
        motion, as `flame generate --loop` closes a clip: playing frame 0 after the last
        continues the motion. Frames already generated never change; the timeline grows by
        `bridge_frames` (two chunks' steps more to pump), and cleaned reads settle to its end.

        Raises FlameError with INVALID_ARGUMENT for a latent model (MLD, MoLA) and for a bridge
        shorter than 1 s or longer than the model's frames allow (overlap + bridge + 0.5 s),
        WRONG_STATE when the stream is already closed, has no segment or dropped frame 0."""
        with self._lock:
            _check(_lib().flame_stream_close_looped(self._h(),
                                                    _uint32("bridge_frames", bridge_frames)))

    def close(self) -> None:
        """Frees the stream (cancelling and waiting for a pump running on another thread)."""
        if self._handle is None:
            return
        self.cancel()
        with self._lock, self._cancel_lock:
            handle, self._handle = self._handle, None
            if handle is not None:
                _lib().flame_stream_free(handle)

    def __enter__(self) -> "Stream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class Session:
    """One generation on a model. Methods raise FlameError when libflame reports a failure."""

    def __init__(self, model: Model, frames, steps, sampler, eta, guidance, seed, threads,
                 respacing=None, *, looped: bool = False):
        """Prefer Model.session(...), which documents the settings. `looped` makes a loop
        session: `frames` is then the cycle's length, what reads return once it is finished."""
        self._handle: Optional[int] = None
        # Held by every call but cancel(), so close() from another thread waits for a running
        # step instead of freeing the session under it. Reentrant: a progress callback may call
        # back into the session (libflame then answers WRONG_STATE for most calls).
        self._lock = threading.RLock()
        self._callback = None  # the CFUNCTYPE object must outlive its registration
        self._callback_error: Optional[BaseException] = None
        info = model.info
        p = _SessionParams()
        _check(_lib().flame_session_params_default(ctypes.byref(p)))
        p.frames = frames or 0
        p.steps = steps or 0
        p.sampler = _sampler_value(sampler)
        p.eta = -1.0 if eta is None else eta
        p.guidance = -1.0 if guidance is None else guidance
        p.seed = seed
        p.threads = _uint32("threads", threads)
        if respacing is not None:
            if "\0" in respacing:
                raise ValueError("respacing contains a NUL character")
            p.respacing = respacing.encode("utf-8")  # kept alive by `p` until the call returns
        p.looped = 1 if looped else 0
        out = _P()
        _check(_lib().flame_session_new(model._h(), ctypes.byref(p), ctypes.byref(out)))
        self._handle = out.value
        # The frames asked for: a loop's cycle, which is also what its finished sample reads as
        # (the lead the loop samples beyond it is not part of the session's frames).
        self.frames = frames or info.default_frames
        self.looped = bool(looped)
        self.feature_dim = info.feature_dim
        self.joint_count = info.joint_count

    def _h(self) -> int:
        if self._handle is None:
            raise ValueError("the session is closed")
        return self._handle

    def _call(self, fn, *args) -> None:
        with self._lock:
            _check(fn(self._h(), *args))

    def set_prompt(self, prompt: str) -> None:
        """Sets the text; "" (or blank) = generation without text. May change between steps.
        A prompt longer than the text encoder's window issues a PromptTruncatedWarning (see
        prompt_info())."""
        with self._lock:
            self._call(_lib().flame_session_set_prompt, prompt.encode("utf-8"))
            info = self.prompt_info()
        if info.truncated:
            warnings.warn(
                f"the prompt has {info.tokens} tokens; the text encoder keeps its first "
                f"{info.kept} and ignores {info.dropped!r}",
                PromptTruncatedWarning,
                stacklevel=2,
            )

    def set_prompt_from(self, other: "Session") -> None:
        """Sets the prompt `other` was given, as encoded there, without running the text encoder
        again: a prompt used for many generations is encoded once (MotionLCM's T5-large takes
        75-85 ms a prompt on 2 cores). `other` must be a session of the same Model with a prompt
        (FlameError: INVALID_ARGUMENT for another model, WRONG_STATE without a prompt)."""
        if not isinstance(other, Session):
            raise TypeError(f"other must be a flame.Session, not {type(other).__name__}")
        self._call(_lib().flame_session_set_prompt_from, other._h())

    def set_prompt_stages(self, stages: Sequence[Stage]) -> None:
        """Sets prompts per time stage (a sequence of Stage), in order; their frames must add up
        to the session's. A FineMoGen model composes them: its sample is then laid out
        [len(stages), longest stage, sample_dim] (sample_shape, and what set_noise takes), while
        read() still returns the session's frames, the stages one after the other. Any other
        model takes exactly one stage without part texts, as set_prompt(stage.text), and refuses
        more (FlameError, INVALID_ARGUMENT). Stage frame counts can change only before the first
        step (WRONG_STATE after; reset() first); texts may change between steps."""
        stages = list(stages)
        raw = (_Stage * max(len(stages), 1))()
        for i, st in enumerate(stages):
            _fill_stage(raw[i], st, f"stages[{i}]")
        self._call(_lib().flame_session_set_prompt_stages, raw if stages else None, len(stages))

    def prompt_info(self) -> PromptInfo:
        """How the last prompt fitted the text encoder's window (a PromptInfo). Raises
        FlameError (WRONG_STATE) before a prompt is set."""
        raw = _PromptInfo()
        raw.struct_size = ctypes.sizeof(_PromptInfo)
        with self._lock:
            # The session owns `dropped` until its next prompt: copy it while holding the lock.
            _check(_lib().flame_session_prompt_info(self._h(), ctypes.byref(raw)))
            return PromptInfo(
                tokens=raw.tokens,
                kept=raw.kept,
                window=raw.window,
                truncated=bool(raw.truncated),
                unconditional=bool(raw.unconditional),
                dropped=_text(raw.dropped),
            )

    @property
    def sample_shape(self) -> Tuple[int, int]:
        """(rows, dim) of the sampled space, what set_noise takes: (frames, feature_dim), or a
        latent model's latent rows and channels."""
        rows, dim = ctypes.c_uint32(), ctypes.c_uint32()
        self._call(_lib().flame_session_sample_shape, ctypes.byref(rows), ctypes.byref(dim))
        return rows.value, dim.value

    def set_noise(self, noise) -> None:
        """Sets x_T explicitly: sample_shape values, [rows, dim] or flat ([frames, feature_dim]
        for models that sample the motion itself); before the first step only. A 2-D array of
        another shape is refused with ValueError, a flat one of another length by libflame."""
        a = _f32(noise, "noise")
        if a.ndim != 1:
            shape = self.sample_shape
            if a.shape != shape:
                raise ValueError(f"noise must be shaped {list(shape)} (Session.sample_shape), got {a.shape}")
        self._call(_lib().flame_session_set_noise, _ptr(a, ctypes.c_float), a.size)

    def set_reference(self, features) -> None:
        """The reference motion for editing, [frames, feature_dim] float32, with 1 <= frames <=
        the session's frames (the frames past a shorter reference cannot be kept)."""
        a = _f32(features, "features")
        frames, dim = _frames_by_dim(a, self.feature_dim, "features")
        self._call(_lib().flame_session_set_reference, _ptr(a, ctypes.c_float), frames, dim)

    def set_mask(self, mask) -> None:
        """The keep-mask, [frames, feature_dim]; nonzero/True = keep the reference value."""
        m = np.asarray(mask)
        if m.dtype != np.uint8:
            m = (m != 0).astype(np.uint8)
        m = np.ascontiguousarray(m)
        frames, dim = _frames_by_dim(m, self.feature_dim, "mask")
        self._call(_lib().flame_session_set_mask, _ptr(m, ctypes.c_uint8), frames, dim)

    def keep_frames(self, start: int, end: int) -> None:
        """Keeps every feature of frames start..end (end exclusive), adding to the mask."""
        self._call(_lib().flame_session_keep_frames, start, end)

    def keep_joints(self, joints: Sequence[int]) -> None:
        """Keeps the channels of these joints (ROOT_TRANSLATION for the root path) in every frame."""
        j = np.ascontiguousarray(list(joints), dtype=np.int32)
        self._call(_lib().flame_session_keep_joints, _ptr(j, ctypes.c_int32) if j.size else None, j.size)

    def keep_part(self, part: Union[int, str], start: int = 0, end: Optional[int] = None) -> None:
        """Keeps a body part's channels (a BodyPart value or name) on frames start..end (end
        exclusive; None = the last frame), adding to the mask."""
        p = _named(part, _BODY_PARTS, "body part")
        self._call(_lib().flame_session_keep_part, p, start, self.frames if end is None else end)

    def set_task_mask(self, task: Union[int, str]) -> None:
        """Replaces the mask with a standard editing task's (an EditTask value or name)."""
        self._call(_lib().flame_session_set_task_mask, _named(task, _TASKS, "editing task"))

    def set_task_targets(self, features, task: Union[int, str]) -> None:
        """Position targets for an editing task (an EditTask value or name) from a reference
        motion, [frames, feature_dim] model-space features: its joint positions where the task
        keeps them (path: the pelvis; upper-body: pelvis and legs; inbetween/predict: every
        joint on the kept frames). MoLA's MPGD tasks; how a latent model edits. On a model with
        a trajectory ControlNet (ModelInfo.control: a MotionLCM control file) the same joints
        become the control hint instead, replacing one set by set_control."""
        a = _f32(features, "features")
        frames, dim = _frames_by_dim(a, self.feature_dim, "features")
        self._call(_lib().flame_session_set_task_targets, _ptr(a, ctypes.c_float), frames, dim,
                   _named(task, _TASKS, "editing task"))

    def set_reference_poses(self, root, rotations, layout: int, convention: int = Convention.NATIVE) -> None:
        """A smpl24_6d reference from poses, the inverse of read(): `root` [frames, 3] pelvis
        positions, `rotations` [frames, 24, ...] local rotations in `layout` (Layout.LOCAL_QUAT_XYZW,
        LOCAL_QUAT_WXYZ, LOCAL_MATRIX or LOCAL_6D), both in `convention`. Frames come from `root`."""
        r = _f32(root, "root")
        q = _f32(rotations, "rotations")
        if r.size % 3:
            raise ValueError(f"root must be shaped [frames, 3], got {r.shape}")
        self._call(
            _lib().flame_session_set_reference_poses,
            _ptr(r, ctypes.c_float), r.size, _ptr(q, ctypes.c_float), q.size, r.size // 3, layout, convention,
        )

    def set_edit_params(self, params: Optional[EditParams] = None, **fields) -> None:
        """How the session edits: an EditParams, or its fields as keywords (method, edit_till,
        paste, seam_frames) over the defaults. The library checks the method against the model
        (FLAME's and MDM's need a diffusion model, trajectory rewriting a flow model)."""
        p = params if params is not None else EditParams()
        if fields:
            p = EditParams(**{**vars(p), **fields})
        raw = _EditParams()
        _check(_lib().flame_edit_params_default(ctypes.byref(raw)))
        raw.method = _named(p.method, _EDIT_METHODS, "edit method")
        raw.edit_till = p.edit_till
        raw.paste = 1 if p.paste else 0
        raw.seam_frames = p.seam_frames
        self._call(_lib().flame_session_set_edit_params, ctypes.byref(raw))

    def clear_edit(self) -> None:
        self._call(_lib().flame_session_clear_edit)

    def set_position_targets(self, targets, mask=None, convention: int = Convention.NATIVE) -> None:
        """Steers the following steps toward joint positions: `targets` [frames, joint_count, 3]
        (or flat) x, y, z per joint in `convention` and its unit (metres, or centimetres for
        Convention.UNREAL), covering the motion's first frames (1 to the session's). `mask`, of
        the same shape, says which values are constrained (nonzero/True); without one a NaN is
        free and every other value constrained. Constrained values must be finite and something
        must be constrained. Replaces earlier targets; on error nothing changes."""
        a = _f32(targets, "targets")
        if a.ndim != 1 and (a.ndim != 3 or a.shape[1:] != (self.joint_count, 3)):
            raise ValueError(f"targets must be shaped [frames, {self.joint_count}, 3], got {a.shape}")
        m, m_ptr, m_len = _mask_arg(mask)
        self._call(
            _lib().flame_session_set_position_targets,
            _ptr(a, ctypes.c_float), a.size, m_ptr, m_len, convention,
        )

    def clear_position_targets(self) -> None:
        """Removes the position targets: unguided from the next step on."""
        self._call(_lib().flame_session_clear_position_targets)

    def set_control(self, positions, mask=None, convention: int = Convention.NATIVE) -> None:
        """Makes the following steps follow joint positions through the model's trajectory
        ControlNet (MotionLCM control files; ModelInfo.control): `positions` [frames,
        joint_count, 3] (or flat) in `convention` and its unit, covering the motion's first
        frames (later ones are free); `mask` as for set_position_targets (without one, NaN is
        free). Encoded once; every later step takes it. On error the earlier control stays."""
        a = _f32(positions, "positions")
        if a.ndim != 1 and (a.ndim != 3 or a.shape[1:] != (self.joint_count, 3)):
            raise ValueError(f"positions must be shaped [frames, {self.joint_count}, 3], got {a.shape}")
        m, m_ptr, m_len = _mask_arg(mask)
        self._call(
            _lib().flame_session_set_control,
            _ptr(a, ctypes.c_float), a.size, m_ptr, m_len, convention,
        )

    def clear_control(self) -> None:
        """Removes the trajectory control: the prompt alone from the next step on."""
        self._call(_lib().flame_session_clear_control)

    def tune_latent(self, iterations: int = 400) -> TuningReport:
        """Consistency latent tuning (MotionLCM's --optimize): before the first step,
        `iterations` Adam iterations (the release runs 400) move the initial latent so that the
        1-step motion made from it follows the control (set_control) more closely; the tuned
        latent becomes the session's initial noise. Needs a prompt, a control and a 1-step
        MotionLCM session; cancel() is seen before every iteration."""
        raw = _TuningReport()
        raw.struct_size = ctypes.sizeof(_TuningReport)
        self._call(_lib().flame_session_tune_latent,
                   _uint32("iterations", iterations), ctypes.byref(raw))
        return TuningReport(
            iterations=raw.iterations,
            hint_loss=(raw.hint_loss_before, raw.hint_loss_after),
            control_error=(raw.control_error_before, raw.control_error_after),
        )

    def set_target_params(self, scale: Optional[float] = None,
                          schedule: Union[None, int, str] = None) -> None:
        """How strongly position targets steer: `scale` s of ρ = s·w(τ), in [0, 100] (0 = off),
        and the `schedule` w (a TargetSchedule value or name). None keeps the session's current
        value (at first the family's default: 0.6, "mpgd" for latent models, "constant" for the
        others)."""
        raw = _TargetParams()
        self._call(_lib().flame_session_target_params, ctypes.byref(raw))
        if scale is not None:
            raw.scale = scale
        if schedule is not None:
            raw.schedule = _named(schedule, _TARGET_SCHEDULES, "target schedule")
        self._call(_lib().flame_session_set_target_params, ctypes.byref(raw))

    def target_params(self) -> Tuple[float, int]:
        """The session's (scale, schedule) for position targets (a TargetSchedule value): the
        family's defaults until set_target_params changes them."""
        raw = _TargetParams()
        self._call(_lib().flame_session_target_params, ctypes.byref(raw))
        return raw.scale, raw.schedule

    def target_loss(self) -> float:
        """The position targets' loss at the latest step's clean-motion estimate, before that
        step's pull: the sum over constrained joints and frames of their distance to the
        target, in metres. Raises FlameError (WRONG_STATE) before a guided step (none yet since
        the targets were set or the session reset, or scale 0)."""
        loss = ctypes.c_double()
        self._call(_lib().flame_session_target_loss, ctypes.byref(loss))
        return loss.value

    def set_progress(self, callback: Optional[ProgressFn]) -> None:
        """Calls `callback(steps_done, steps_total)` after every step, on the stepping thread.
        An exception it raises is re-raised by the step() that ran it. None removes it."""
        if callback is None:
            self._call(_lib().flame_session_set_progress_callback, _ProgressCallback(), None)
            self._callback = None
            return

        def trampoline(_user_data, done, total):
            try:
                callback(done, total)
            except BaseException as e:  # ctypes would only print it; keep it for step()
                self._callback_error = e

        c_fn = _ProgressCallback(trampoline)
        self._call(_lib().flame_session_set_progress_callback, c_fn, None)
        self._callback = c_fn

    def step(self) -> int:
        """Runs one sampler step; returns the steps left. A cancelled step raises FlameError with
        status CANCELLED and may be retried."""
        left = ctypes.c_uint32()
        with self._lock:
            self._callback_error = None
            _check(_lib().flame_session_step(self._h(), ctypes.byref(left)))
            err, self._callback_error = self._callback_error, None
        if err is not None:
            raise err
        return left.value

    def run(self) -> np.ndarray:
        """Runs every remaining step and returns the final motion's features,
        [read_frames(), feature_dim]."""
        while self.steps_left > 0:
            self.step()
        return self.read()

    def cancel(self) -> None:
        """Abandons the step running on another thread (or the next one). Thread-safe."""
        handle = self._handle
        if handle is not None:
            _check(_lib().flame_session_cancel(handle))

    def reset(self) -> None:
        """Starts over with the same prompt, settings and edit; the same output follows."""
        self._call(_lib().flame_session_reset)

    @property
    def progress(self):
        """(steps_done, steps_total)."""
        done, total = ctypes.c_uint32(), ctypes.c_uint32()
        self._call(_lib().flame_session_progress, ctypes.byref(done), ctypes.byref(total))
        return done.value, total.value

    @property
    def steps_left(self) -> int:
        done, total = self.progress
        return total - done

    @staticmethod
    def _which(which: Union[str, int]) -> int:
        if isinstance(which, str):
            if which not in _WHICH:
                raise ValueError(f"unknown which {which!r} (sample, estimate)")
            return _WHICH[which]
        return int(which)

    def read_frames(self, which: Union[str, int] = "sample") -> int:
        """How many frames read(which) returns now: the session's frames (a finished loop's
        sample: the cycle, without the lead it sampled), or a latent model's valid length, which
        its decoder decides anew after every step. Raises FlameError
        (WRONG_STATE) before there is anything to read."""
        frames = ctypes.c_uint32()
        self._call(_lib().flame_session_read_frames, self._which(which), ctypes.byref(frames))
        return frames.value

    def read(
        self,
        which: Union[str, int] = "sample",
        layout: int = Layout.FEATURES,
        convention: int = Convention.NATIVE,
        flags: int = 0,
        cleanup: Optional[Cleanup] = None,
    ) -> np.ndarray:
        """The current sample ("sample") or clean-motion estimate ("estimate") as float32 in a
        Layout, Convention and ReadFlags, which go to libflame as plain integers. Shaped
        [read_frames(which), ...] as the layout says (Layout.FEATURES: [frames, feature_dim]); a
        layout not named in Layout comes back [frames, -1]. The frames are the session's, except
        for a latent model (Model.latent), whose decoder decides the valid length.

        `cleanup` (a Cleanup; None = the raw poses) post-processes the poses
        (flame_session_read_cleaned): feet, floor, loop, root motion, frame rate. Its `fps`
        changes the frame count (the first and last frames' times kept: 40 frames at 20 fps
        are 59 at 30). Layout.ROOT_BONE needs root_motion=RootMotion.SEPARATE. The raw
        features (Layout.FEATURES) are never post-processed."""
        w = self._which(which)
        raw_cleanup = _cleanup_params(cleanup)
        cp = ctypes.byref(raw_cleanup) if raw_cleanup is not None else None
        lib = _lib()
        n = ctypes.c_size_t()
        frames = ctypes.c_uint32()
        with self._lock:
            h = self._h()
            _check(lib.flame_session_read_cleaned(h, w, layout, convention, flags, cp, None, 0,
                                                  ctypes.byref(n)))
            _check(lib.flame_session_read_frames(h, w, ctypes.byref(frames)))
            out = np.empty(n.value, dtype=np.float32)
            _check(
                lib.flame_session_read_cleaned(
                    h, w, layout, convention, flags, cp, _ptr(out, ctypes.c_float), out.size,
                    ctypes.byref(n)
                )
            )
            per_frame = None
            if raw_cleanup is not None and layout not in _LAYOUT_SHAPES:
                # A layout these bindings do not name: its width from the raw read, whose frames
                # are read_frames (a cleanup's frame rate changes only the frame count).
                m = ctypes.c_size_t()
                if frames.value and lib.flame_session_read(h, w, layout, convention, flags, None, 0,
                                                           ctypes.byref(m)) == Status.OK:
                    per_frame = m.value // frames.value
        values = out[: n.value]
        if raw_cleanup is not None and layout != Layout.FEATURES:
            # A cleanup's frame rate changes the frame count: it follows from the values.
            trailing = _LAYOUT_SHAPES.get(layout, lambda d, j: (-1,))(self.feature_dim, self.joint_count)
            width = int(np.prod(trailing)) if -1 not in trailing else per_frame
            if not width or values.size % width:
                return values
            return self._shaped(values, values.size // width, layout)
        return self._shaped(values, frames.value, layout)

    def _shaped(self, values: np.ndarray, frames: int, layout: int) -> np.ndarray:
        """[frames, ...] with the layout's trailing shape when the count agrees with it."""
        trailing = _LAYOUT_SHAPES.get(layout, lambda d, j: (-1,))(self.feature_dim, self.joint_count)
        if -1 not in trailing and values.size == frames * int(np.prod(trailing)):
            return values.reshape((frames,) + trailing)
        if frames and values.size % frames == 0:
            return values.reshape(frames, -1)
        return values

    def write_gltf(
        self,
        path: Union[None, str, bytes, os.PathLike] = None,
        *,
        which: Union[str, int] = "sample",
        container: Union[None, str, int] = None,
        smooth: bool = False,
        raw_signs: bool = False,
        fps: float = 0.0,
        name: Optional[str] = None,
        cleanup: Optional[Cleanup] = None,
    ) -> bytes:
        """The current sample ("sample") or clean-motion estimate ("estimate") as a glTF 2.0 file
        (flame_session_write_gltf): the skeleton as nodes named after model.info.joint_names, a
        skinned box figure and one animation, in glTF's convention (Convention.GLTF: Y up,
        metres). Its root translation and joint rotations are what read() gives for
        Layout.ROOT_TRANSLATION and Layout.LOCAL_QUAT_XYZW in Convention.GLTF with the same
        flags, bit for bit. Returns the file's bytes, and writes them to `path` when one is
        given.

        `container` is "glb" (binary), "gltf" (JSON, the buffer embedded as base64) or a
        GltfContainer value; None takes it from the extension of `path` (.glb or .gltf; GLB
        without a path or an extension). `smooth` and `raw_signs` are ReadFlags.SMOOTH and
        ReadFlags.RAW_SIGNS; `fps` is the animation's frame rate (0 = the model's); `name` the
        animation's (sanitised by libflame; None = the prompt). `cleanup` (a Cleanup; None = the
        raw poses) post-processes the poses first, as read(cleanup=...) does; its `fps`, when
        set, overrides `fps`, and RootMotion.SEPARATE adds a node named "root" (the pelvis's
        parent) carrying the horizontal travel. Raises FlameError (WRONG_STATE) before there is
        anything to read, and ValueError for a container or an extension it does not know."""
        raw = _GltfParams()
        _check(_lib().flame_gltf_params_default(ctypes.byref(raw)))
        raw.container = _gltf_container(container, path)
        raw.flags = (ReadFlags.SMOOTH if smooth else 0) | (ReadFlags.RAW_SIGNS if raw_signs else 0)
        raw.fps = float(fps)
        if name is not None:
            if not isinstance(name, str):
                raise TypeError(f"name is a {type(name).__name__}, not a str")
            if "\0" in name:
                raise ValueError("name contains a NUL character")
            raw.name = name.encode("utf-8")  # kept alive by `raw` until the calls return
        raw_cleanup = _cleanup_params(cleanup)
        if raw_cleanup is not None:
            raw.cleanup = ctypes.pointer(raw_cleanup)  # `raw` keeps it alive
        w = self._which(which)
        lib = _lib()
        n = ctypes.c_size_t()
        with self._lock:
            h = self._h()
            _check(lib.flame_session_write_gltf(h, w, ctypes.byref(raw), None, 0, ctypes.byref(n)))
            buf = (ctypes.c_uint8 * max(n.value, 1))()
            _check(lib.flame_session_write_gltf(h, w, ctypes.byref(raw), buf, n.value, ctypes.byref(n)))
        data = ctypes.string_at(buf, n.value)
        if path is not None:
            with open(path, "wb") as f:
                f.write(data)
        return data

    def write_amass(
        self,
        path: Union[None, str, bytes, os.PathLike] = None,
        *,
        which: Union[str, int] = "sample",
        layout: Union[str, int] = "smplh",
        smooth: bool = False,
        raw_signs: bool = False,
        cleanup: Optional[Cleanup] = None,
    ) -> bytes:
        """The current sample ("sample") or clean-motion estimate ("estimate") as an AMASS-style
        .npz (flame_session_write_amass), what np.load reads: SMPL axis-angles (radians,
        parent-relative, the root's global) and `trans` (metres) in AMASS's Z-up world, float64,
        betas 16 zeros, gender "neutral" (docs/amass.md). `layout` "smplh" (AmassLayout.SMPLH:
        `poses` [N, 156], `trans`, `betas`, `gender`, `mocap_framerate`, `dmpls`; PHC,
        human2humanoid) or "smplx" (AmassLayout.SMPLX: `root_orient`, `pose_body`, `pose_hand`,
        `pose_jaw`, `pose_eye`, `trans`, `betas`, `num_betas`, `gender`, `surface_model_type`,
        `mocap_frame_rate`, `mocap_time_length`, `poses` [N, 165]; GMR). `smooth` and
        `raw_signs` are ReadFlags.SMOOTH and ReadFlags.RAW_SIGNS; `cleanup` (a Cleanup; None =
        the raw poses) post-processes first, its `fps` (30 or 50 for trackers) giving the file's
        rate. Returns the file's bytes, and writes them to `path` when one is given. Raises
        FlameError (WRONG_STATE) before there is anything to read."""
        w = self._which(which)
        lay = _named(layout, _AMASS_LAYOUTS, "AMASS layout")
        flags = (ReadFlags.SMOOTH if smooth else 0) | (ReadFlags.RAW_SIGNS if raw_signs else 0)
        raw_cleanup = _cleanup_params(cleanup)
        cp = ctypes.byref(raw_cleanup) if raw_cleanup is not None else None
        lib = _lib()
        n = ctypes.c_size_t()
        with self._lock:
            h = self._h()
            _check(lib.flame_session_write_amass(h, w, lay, flags, cp, None, 0, ctypes.byref(n)))
            buf = (ctypes.c_uint8 * max(n.value, 1))()
            _check(lib.flame_session_write_amass(h, w, lay, flags, cp, buf, n.value,
                                                 ctypes.byref(n)))
        data = ctypes.string_at(buf, n.value)
        if path is not None:
            with open(path, "wb") as f:
                f.write(data)
        return data

    def close(self) -> None:
        """Frees the session (cancelling and waiting for a step running on another thread)."""
        if self._handle is None:
            return
        self.cancel()
        with self._lock:
            handle, self._handle = self._handle, None
            if handle is not None:
                _lib().flame_session_free(handle)
            self._callback = None

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


# Retargeting lives in its own module; imported last, as it builds on the names above.
from .retarget import BoneMap, Retarget, Rig, RigBone, RigFormat  # noqa: E402
from .robot import Robot, RobotFile, RobotRetarget, RobotState  # noqa: E402
from ._batch import batch, read_manifest  # noqa: E402
