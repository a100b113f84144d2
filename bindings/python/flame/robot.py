"""Humanoid robots (flame_robot_*): a robot from its URDF, a retarget onto it with its
configuration, whole clips as the files robot-learning pipelines read, and the joint vector
frame by frame from a live session or stream.

    robot = flame.Robot.load("gr1t2.urdf")                       # path or bytes
    with flame.RobotRetarget(robot, "robots/gr1t2.json") as r:   # path, bytes or JSON text
        traj = r.retarget(session, cleanup=flame.Cleanup(fps=30))
        # GMR's dict: fps, root_pos [N, 3], root_rot [N, 4] x y z w, dof_pos [N, n], joint_names
        r.write(session, "walk.csv")                             # BeyondMimic's CSV
        state = r.state()
        pos, rot_xyzw, q, residual = r.read(session, state, 0, 10)   # frames 0..10, in order

Quaternion order is part of every name: x, y, z, w except in the qpos files (w first, MuJoCo).
Robots and retargets are immutable and may be shared by threads; a RobotState is one run's.
"""

from __future__ import annotations

import ctypes
import io
import os
import threading
from typing import Optional, Tuple, Union

import numpy as np

from . import Cleanup, ReadFlags, _P, _check, _cleanup_params, _lib, _ptr, _status

__all__ = ["Robot", "RobotRetarget", "RobotState", "RobotFile"]


class RobotFile:
    """`file` of flame_robot_retarget_write (FLAME_ROBOT_*), quaternion order in the name."""

    BEYONDMIMIC_CSV_XYZW = 0  # x, y, z, qx, qy, qz, qw, q_1 ... q_n
    GMR_NPZ_XYZW = 1  # fps, root_pos, root_rot (x, y, z, w), dof_pos, joint_names
    QPOS_CSV_WXYZ = 2  # MuJoCo qpos rows: x, y, z, qw, qx, qy, qz, joints in MuJoCo's order
    QPOS_NPY_WXYZ = 3  # the same rows as a float64 .npy


_CSV_HEADER = 1  # FLAME_ROBOT_CSV_HEADER
_BY_EXTENSION = {".csv": RobotFile.BEYONDMIMIC_CSV_XYZW, ".npz": RobotFile.GMR_NPZ_XYZW,
                 ".npy": RobotFile.QPOS_NPY_WXYZ}


def _signatures() -> dict:
    """(restype, argtypes) of the robot functions of flame.h, by name."""
    size_t, u32, i32 = ctypes.c_size_t, ctypes.c_uint32, ctypes.c_int32
    pf64, psize = ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_size_t)
    pstr = ctypes.POINTER(ctypes.c_char_p)
    return {
        "flame_robot_load": (_status, [ctypes.c_void_p, size_t, ctypes.POINTER(_P)]),
        "flame_robot_free": (None, [_P]),
        "flame_robot_dof_count": (_status, [_P, psize]),
        "flame_robot_dof_name": (_status, [_P, size_t, pstr]),
        "flame_robot_name": (_status, [_P, pstr]),
        "flame_robot_retarget_new": (_status, [_P, ctypes.c_void_p, size_t, ctypes.POINTER(_P)]),
        "flame_robot_retarget_free": (None, [_P]),
        "flame_robot_retarget_dof_count": (_status, [_P, psize]),
        "flame_robot_retarget_write": (_status, [_P, _P, i32, u32, ctypes.c_void_p, u32, u32,
                                                 ctypes.c_void_p, size_t, psize]),
        "flame_robot_state_new": (_status, [_P, ctypes.POINTER(_P)]),
        "flame_robot_state_free": (None, [_P]),
        "flame_robot_state_reset": (_status, [_P]),
        "flame_robot_retarget_read": (_status, [_P, _P, _P, i32, u32, ctypes.c_void_p, size_t,
                                                size_t, pf64, size_t, pf64, size_t, pf64, size_t,
                                                pf64, size_t, psize]),
        "flame_robot_retarget_read_stream": (_status, [_P, _P, _P, ctypes.c_uint64, u32,
                                                       ctypes.c_void_p, pf64, size_t, pf64,
                                                       size_t, pf64, size_t, pf64, size_t]),
    }


_bound = False
_bind_lock = threading.Lock()


def _L() -> ctypes.CDLL:
    """The library with the robot functions' signatures set (once)."""
    global _bound
    lib = _lib()
    with _bind_lock:
        if not _bound:
            for name, (restype, argtypes) in _signatures().items():
                fn = getattr(lib, name)
                fn.restype, fn.argtypes = restype, argtypes
            _bound = True
    return lib


def _bytes_of(source, what: str) -> bytes:
    """A file's bytes from a path, or the bytes (or text) themselves."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source)
    if isinstance(source, str) and source.lstrip().startswith(("{", "<")):
        return source.encode("utf-8")
    if isinstance(source, (str, os.PathLike)):
        with open(source, "rb") as f:
            return f.read()
    raise TypeError(f"{what}: a path, bytes or text, not {type(source).__name__}")


class _Handle:
    """An owned handle freed by `_free` on close, `with` exit or collection."""

    _free = ""

    def __init__(self, handle: int):
        self._handle: Optional[int] = handle

    def _h(self) -> int:
        if self._handle is None:
            raise ValueError(f"the {type(self).__name__} is closed")
        return self._handle

    def close(self) -> None:
        h, self._handle = self._handle, None
        if h:
            getattr(_L(), self._free)(h)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


class Robot(_Handle):
    """A robot from its URDF (flame_robot_load): links, joints, limits; immutable."""

    _free = "flame_robot_free"

    @classmethod
    def load(cls, source: Union[str, os.PathLike, bytes, bytearray, memoryview]) -> "Robot":
        """A robot from a URDF: a path, or the file's bytes or text. Raises FlameError
        (INVALID_ARGUMENT, naming the joint or link) for a malformed description."""
        data = _bytes_of(source, "Robot.load")
        buf = ctypes.create_string_buffer(data, len(data)) if data else None
        out = _P()
        _check(_L().flame_robot_load(buf, len(data), ctypes.byref(out)))
        return cls(out.value)

    @property
    def name(self) -> str:
        """The URDF's `<robot name>` (shipped configurations are robots/<name>.json)."""
        out = ctypes.c_char_p()
        _check(_L().flame_robot_name(self._h(), ctypes.byref(out)))
        return out.value.decode("utf-8")

    @property
    def dof_names(self) -> list:
        """The degrees of freedom's joint names: the order of every joint vector."""
        lib, h = _L(), self._h()
        n = ctypes.c_size_t()
        _check(lib.flame_robot_dof_count(h, ctypes.byref(n)))
        names = []
        for i in range(n.value):
            out = ctypes.c_char_p()
            _check(lib.flame_robot_dof_name(h, i, ctypes.byref(out)))
            names.append(out.value.decode("utf-8"))
        return names


class RobotState(_Handle):
    """One run's warm start for RobotRetarget.read / read_stream (flame_robot_state_*)."""

    _free = "flame_robot_state_free"

    def reset(self) -> None:
        """Back to the start of a run (before reading from anywhere but the next frame)."""
        _check(_L().flame_robot_state_reset(self._h()))


class RobotRetarget(_Handle):
    """Poses onto a robot with a retarget configuration (flame_robot_retarget_new). The robot
    is copied: it may be closed afterwards."""

    _free = "flame_robot_retarget_free"

    def __init__(self, robot: Robot,
                 config: Union[str, os.PathLike, bytes, bytearray, memoryview]):
        """`config`: the configuration's path, bytes or JSON text (libflame ships
        robots/<robot name>.json)."""
        data = _bytes_of(config, "RobotRetarget config")
        buf = ctypes.create_string_buffer(data, len(data)) if data else None
        out = _P()
        _check(_L().flame_robot_retarget_new(robot._h(), buf, len(data), ctypes.byref(out)))
        super().__init__(out.value)
        self.dof_names = robot.dof_names

    @property
    def dof_count(self) -> int:
        n = ctypes.c_size_t()
        _check(_L().flame_robot_retarget_dof_count(self._h(), ctypes.byref(n)))
        return n.value

    def state(self) -> RobotState:
        """A fresh RobotState for read / read_stream."""
        out = _P()
        _check(_L().flame_robot_state_new(self._h(), ctypes.byref(out)))
        return RobotState(out.value)

    def write(self, session, path: Union[None, str, os.PathLike] = None, *,
              file: Optional[int] = None, header: bool = False, which: Union[str, int] = "sample",
              smooth: bool = False, raw_signs: bool = False,
              cleanup: Optional[Cleanup] = None) -> bytes:
        """The session's whole clip retargeted and written as `file` (a RobotFile; None = from
        `path`'s extension: .csv BeyondMimic, .npz GMR's fields, .npy MuJoCo qpos), with a `# `
        header line of column names when `header` (CSVs only). `cleanup` (None = the raw poses)
        post-processes first, its fps (30 or 50 for trackers) giving the file's. Returns the
        bytes, and writes them to `path` when one is given."""
        if file is None:
            ext = os.path.splitext(os.fspath(path))[1].lower() if path is not None else ".npz"
            if ext not in _BY_EXTENSION:
                raise ValueError(f"cannot tell the robot file from {ext!r}: give file=RobotFile.*")
            file = _BY_EXTENSION[ext]
        w = session._which(which)
        flags = (ReadFlags.SMOOTH if smooth else 0) | (ReadFlags.RAW_SIGNS if raw_signs else 0)
        raw_cleanup = _cleanup_params(cleanup)
        cp = ctypes.byref(raw_cleanup) if raw_cleanup is not None else None
        options = _CSV_HEADER if header else 0
        lib = _L()
        n = ctypes.c_size_t()
        with session._lock:
            h = session._h()
            _check(lib.flame_robot_retarget_write(self._h(), h, w, flags, cp, file, options, None,
                                                  0, ctypes.byref(n)))
            buf = (ctypes.c_uint8 * max(n.value, 1))()
            _check(lib.flame_robot_retarget_write(self._h(), h, w, flags, cp, file, options, buf,
                                                  n.value, ctypes.byref(n)))
        data = ctypes.string_at(buf, n.value)
        if path is not None:
            with open(path, "wb") as f:
                f.write(data)
        return data

    def retarget(self, session, *, which: Union[str, int] = "sample", smooth: bool = False,
                 raw_signs: bool = False, cleanup: Optional[Cleanup] = None) -> dict:
        """The session's whole clip on the robot as GMR's dict (its pickle's fields, what its
        scripts and trackers read): `fps` (float), `root_pos` [N, 3], `root_rot` [N, 4]
        quaternion x, y, z, w, `dof_pos` [N, n] (float64 NumPy arrays) and `joint_names` (the
        columns of dof_pos). GMR's `local_body_pos` and `link_body_list` are None in its own
        files and are not given."""
        data = self.write(session, None, file=RobotFile.GMR_NPZ_XYZW, which=which, smooth=smooth,
                          raw_signs=raw_signs, cleanup=cleanup)
        with np.load(io.BytesIO(data)) as z:
            return {
                "fps": float(z["fps"]),
                "root_pos": z["root_pos"],
                "root_rot": z["root_rot"],
                "dof_pos": z["dof_pos"],
                "joint_names": [str(s) for s in z["joint_names"]],
            }

    def _buffers(self, count: int):
        n = self.dof_count
        return (np.empty((count, 3)), np.empty((count, 4)), np.empty((count, n)),
                np.empty(count))

    def read(self, session, state: RobotState, first: int, count: int, *,
             which: Union[str, int] = "sample", smooth: bool = False, raw_signs: bool = False,
             cleanup: Optional[Cleanup] = None
             ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Frames first..first+count of the session's motion (read as Session.read does with the
        same options), solved one after the other from `state` (warm start, velocity limits):
        (root_pos [count, 3], root_rot_xyzw [count, 4], q [count, n], residual [count])."""
        pos, rot, q, res = self._buffers(count)
        w = session._which(which)
        flags = (ReadFlags.SMOOTH if smooth else 0) | (ReadFlags.RAW_SIGNS if raw_signs else 0)
        raw_cleanup = _cleanup_params(cleanup)
        cp = ctypes.byref(raw_cleanup) if raw_cleanup is not None else None
        f64 = ctypes.c_double
        with session._lock:
            _check(_L().flame_robot_retarget_read(
                self._h(), state._h(), session._h(), w, flags, cp, first, count,
                _ptr(pos, f64), pos.size, _ptr(rot, f64), rot.size, _ptr(q, f64), q.size,
                _ptr(res, f64), res.size, None))
        return pos, rot, q, res

    def read_stream(self, stream, state: RobotState, first_frame: int, count: int, *,
                    cleanup: Optional[Cleanup] = None
                    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """read() for a stream's timeline frames (cleaned when `cleanup` is given): drive a
        robot at run time. Raises FlameError (WRONG_STATE) for frames not ready yet."""
        pos, rot, q, res = self._buffers(count)
        raw_cleanup = _cleanup_params(cleanup)
        cp = ctypes.byref(raw_cleanup) if raw_cleanup is not None else None
        f64 = ctypes.c_double
        with stream._lock:
            _check(_L().flame_robot_retarget_read_stream(
                self._h(), state._h(), stream._h(), first_frame, count, cp,
                _ptr(pos, f64), pos.size, _ptr(rot, f64), rot.size, _ptr(q, f64), q.size,
                _ptr(res, f64), res.size))
        return pos, rot, q, res
