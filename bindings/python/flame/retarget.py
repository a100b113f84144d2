"""Retargeting onto the user's character (flame_rig_*, flame_bone_map_*, flame_retarget_*).

    rig = flame.Rig.load("character.glb")              # glTF/GLB/VRM or BVH, path or bytes
    with model.retarget(rig, feet=True) as r:          # the automatic bone map
        rot, trans = r.read(session, cleanup=flame.Cleanup())
        # rot [frames, bones, 4] local quaternions x y z w, trans [frames, bones, 3]

Rigs and bone maps are immutable and may be shared by threads; a Retarget too (its calls run
one after another). Bones are numbered as Rig.names lists them.
"""

from __future__ import annotations

import ctypes
import os
import threading
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from . import Cleanup, Convention, FlameError, _P, _check, _cleanup_params, _lib, _ptr, _status

__all__ = ["Rig", "RigBone", "BoneMap", "Retarget", "RigFormat"]


class RigFormat:
    """`kind` of flame_rig_load (FLAME_RIG_FORMAT_*)."""

    GUESS = 0
    GLTF = 1  # glTF 2.0: .glb, .gltf with embedded buffers, VRM 0.x and 1.0
    BVH = 2


@dataclass
class RigBone:
    """One bone of Rig.from_bones: its rest transform relative to its parent (T·R·S) in the
    rig's convention; `parent` an index into the same list (-1 for a root), `rotation` a
    quaternion x, y, z, w."""

    name: str
    parent: int
    translation: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: Tuple[float, float, float] = (1.0, 1.0, 1.0)


class _RigBone(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("parent", ctypes.c_int32),
        ("name", ctypes.c_char_p),
        ("translation", ctypes.c_float * 3),
        ("rotation", ctypes.c_float * 4),
        ("scale", ctypes.c_float * 3),
    ]


class _RetargetParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("convention", ctypes.c_int32),
        ("feet", ctypes.c_uint32),
        ("hands", ctypes.c_uint32),
        ("map", ctypes.c_void_p),
    ]


def _signatures() -> dict:
    """(restype, argtypes) of the retarget functions of flame.h, by name."""
    size_t, u32, i32 = ctypes.c_size_t, ctypes.c_uint32, ctypes.c_int32
    pf32, psize = ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_size_t)
    return {
        "flame_rig_load": (_status, [ctypes.c_void_p, size_t, u32, ctypes.c_char_p,
                                     ctypes.POINTER(_P)]),
        "flame_rig_from_bones": (_status, [ctypes.POINTER(_RigBone), size_t, i32,
                                           ctypes.POINTER(_P)]),
        "flame_rig_free": (None, [_P]),
        "flame_rig_bone_count": (_status, [_P, psize]),
        "flame_rig_bone_name": (_status, [_P, size_t, ctypes.POINTER(ctypes.c_char_p)]),
        "flame_rig_bone_parent": (_status, [_P, size_t, ctypes.POINTER(i32)]),
        "flame_bone_map_auto": (_status, [_P, ctypes.POINTER(_P)]),
        "flame_bone_map_from_json": (_status, [_P, ctypes.c_char_p, _P,
                                               ctypes.POINTER(_P)]),
        "flame_bone_map_to_json": (_status, [_P, _P, ctypes.c_char_p, size_t, psize]),
        "flame_bone_map_free": (None, [_P]),
        "flame_retarget_params_default": (_status, [ctypes.POINTER(_RetargetParams)]),
        "flame_retarget_new": (_status, [_P, _P, ctypes.POINTER(_RetargetParams),
                                         ctypes.POINTER(_P)]),
        "flame_retarget_free": (None, [_P]),
        "flame_retarget_bone_count": (_status, [_P, psize]),
        "flame_retarget_read": (_status, [_P, _P, i32, u32, ctypes.c_void_p, size_t,
                                          size_t, pf32, size_t, pf32, size_t, psize]),
        "flame_retarget_read_stream": (_status, [_P, _P, ctypes.c_uint64, u32,
                                                 ctypes.c_void_p, pf32, size_t, pf32,
                                                 size_t]),
        "flame_retarget_pose": (_status, [_P, pf32, size_t, pf32, size_t, pf32, size_t,
                                          pf32, size_t]),
    }


_bound = False
_bind_lock = threading.Lock()


def _L() -> ctypes.CDLL:
    """The library with the retarget functions' signatures set (once)."""
    global _bound
    lib = _lib()
    with _bind_lock:
        if not _bound:
            sigs = _signatures()
            for name, (restype, argtypes) in sigs.items():
                fn = getattr(lib, name)
                fn.restype, fn.argtypes = restype, argtypes
            _bound = True
    return lib


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


class Rig(_Handle):
    """The user's skeleton: bone names, parents and rest pose (flame_rig_*)."""

    _free = "flame_rig_free"

    @classmethod
    def load(cls, source: Union[str, os.PathLike, bytes, bytearray, memoryview],
             kind: int = RigFormat.GUESS, skin: Optional[str] = None) -> "Rig":
        """A rig from a file: a path, or the file's bytes. `kind` a RigFormat (GUESS tells glTF
        from BVH by the content), `skin` the glTF skin's name (None: the only one, or a VRM
        file's humanoid one)."""
        if isinstance(source, (bytes, bytearray, memoryview)):
            data = bytes(source)
        else:
            with open(source, "rb") as f:
                data = f.read()
        buf = ctypes.create_string_buffer(data, len(data)) if data else None
        out = _P()
        _check(_L().flame_rig_load(buf, len(data), kind,
                                   skin.encode("utf-8") if skin is not None else None,
                                   ctypes.byref(out)))
        return cls(out.value)

    @classmethod
    def from_bones(cls, bones: Sequence[RigBone], convention: int = Convention.GLTF) -> "Rig":
        """A rig from bones an engine holds, in `convention` (Convention.UNITY, .UNREAL in
        centimetres, ...; not NATIVE). libflame carries them into right-handed glTF axes first
        so a left-handed rig is not driven mirrored, and gives its poses back in `convention`."""
        arr = (_RigBone * len(bones))()
        for i, b in enumerate(bones):
            if not isinstance(b, RigBone):
                raise TypeError(f"bones[{i}] is a {type(b).__name__}, not a flame.RigBone")
            r = arr[i]
            r.struct_size = ctypes.sizeof(_RigBone)
            r.parent = int(b.parent)
            r.name = b.name.encode("utf-8")
            r.translation[:] = [float(v) for v in b.translation]
            r.rotation[:] = [float(v) for v in b.rotation]
            r.scale[:] = [float(v) for v in b.scale]
        out = _P()
        _check(_L().flame_rig_from_bones(arr, len(bones), convention, ctypes.byref(out)))
        return cls(out.value)

    @property
    def bone_count(self) -> int:
        n = ctypes.c_size_t()
        _check(_L().flame_rig_bone_count(self._h(), ctypes.byref(n)))
        return n.value

    @property
    def names(self) -> list:
        lib, out = _L(), ctypes.c_char_p()
        names = []
        for b in range(self.bone_count):
            _check(lib.flame_rig_bone_name(self._h(), b, ctypes.byref(out)))
            names.append(out.value.decode("utf-8"))
        return names

    @property
    def parents(self) -> list:
        lib, out = _L(), ctypes.c_int32()
        parents = []
        for b in range(self.bone_count):
            _check(lib.flame_rig_bone_parent(self._h(), b, ctypes.byref(out)))
            parents.append(out.value)
        return parents


class BoneMap(_Handle):
    """Which bone of a rig is which humanoid bone (flame_bone_map_*); only for its own rig."""

    _free = "flame_bone_map_free"

    def __init__(self, handle: int, rig: Rig):
        super().__init__(handle)
        self.rig = rig

    @classmethod
    def auto(cls, rig: Rig) -> "BoneMap":
        """The file's declared map (VRM) or one read from the bone names."""
        out = _P()
        _check(_L().flame_bone_map_auto(rig._h(), ctypes.byref(out)))
        return cls(out.value, rig)

    @classmethod
    def from_json(cls, rig: Rig, json: str, base: Optional["BoneMap"] = None) -> "BoneMap":
        """A map from JSON ({"hips": "pelvis", "leftHand": "hand_l", ...}, VRM humanoid bone
        names to rig bone names or null) over `base`."""
        out = _P()
        _check(_L().flame_bone_map_from_json(rig._h(), json.encode("utf-8"),
                                             base._h() if base is not None else None,
                                             ctypes.byref(out)))
        return cls(out.value, rig)

    def to_json(self) -> str:
        lib, n = _L(), ctypes.c_size_t()
        _check(lib.flame_bone_map_to_json(self._h(), self.rig._h(), None, 0, ctypes.byref(n)))
        buf = ctypes.create_string_buffer(n.value)
        _check(lib.flame_bone_map_to_json(self._h(), self.rig._h(), buf, n.value,
                                          ctypes.byref(n)))
        return buf.value.decode("utf-8")


class Retarget(_Handle):
    """A model's poses onto a rig (flame_retarget_*). Made by Model.retarget."""

    _free = "flame_retarget_free"

    def __init__(self, model, rig: Rig, map: Optional[BoneMap] = None, feet: bool = True,
                 hands: bool = False, convention: int = Convention.NATIVE):
        p = _RetargetParams()
        lib = _L()
        _check(lib.flame_retarget_params_default(ctypes.byref(p)))
        p.convention = convention
        p.feet = 1 if feet else 0
        p.hands = 1 if hands else 0
        p.map = map._h() if map is not None else None
        out = _P()
        _check(lib.flame_retarget_new(model._h(), rig._h(), ctypes.byref(p), ctypes.byref(out)))
        super().__init__(out.value)
        self.joint_count = model.info.joint_count

    @property
    def bone_count(self) -> int:
        n = ctypes.c_size_t()
        _check(_L().flame_retarget_bone_count(self._h(), ctypes.byref(n)))
        return n.value

    def _buffers(self, frames: int):
        n = self.bone_count
        return (np.empty((frames, n, 4), dtype=np.float32),
                np.empty((frames, n, 3), dtype=np.float32))

    def read(self, session, first: int = 0, count: Optional[int] = None,
             which: Union[str, int] = "sample", flags: int = 0,
             cleanup: Optional[Cleanup] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Frames first..first+count (None: to the end) of the session's motion, as
        Session.read gives it with `which`, `flags` and `cleanup`, put onto the rig:
        (rotations [count, bones, 4] local quaternions x y z w, translations [count, bones, 3]
        local translations), in the retarget's convention."""
        lib = _L()
        raw = _cleanup_params(cleanup)
        cp = ctypes.byref(raw) if raw is not None else None
        w = session._which(which)
        with session._lock:
            h = session._h()
            if count is None:
                frames = ctypes.c_size_t()
                _check(lib.flame_retarget_read(self._h(), h, w, flags, cp, 0, 0, None, 0, None, 0,
                                               ctypes.byref(frames)))
                count = max(frames.value - first, 0)
            rot, tr = self._buffers(count)
            _check(lib.flame_retarget_read(self._h(), h, w, flags, cp, first, count,
                                           _ptr(rot, ctypes.c_float), rot.size,
                                           _ptr(tr, ctypes.c_float), tr.size, None))
        return rot, tr

    def read_stream(self, stream, first_frame: int, count: int,
                    cleanup: Optional[Cleanup] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Stream frames first_frame..first_frame+count (as Stream.read gives them with
        `cleanup`) put onto the rig, shaped as `read`'s."""
        raw = _cleanup_params(cleanup)
        cp = ctypes.byref(raw) if raw is not None else None
        rot, tr = self._buffers(count)
        _check(_L().flame_retarget_read_stream(self._h(), stream._h(), first_frame, count, cp,
                                               _ptr(rot, ctypes.c_float), rot.size,
                                               _ptr(tr, ctypes.c_float), tr.size))
        return rot, tr

    def pose(self, world_quats, positions) -> Tuple[np.ndarray, np.ndarray]:
        """One frame from any source: `world_quats` [joints, 4] world rotations x y z w and
        `positions` [joints, 3] joint positions of the model's skeleton, glTF axes in metres
        (Layout.GLOBAL_QUAT_XYZW and GLOBAL_POSITIONS read in Convention.GLTF). Returns
        (rotations [bones, 4], translations [bones, 3])."""
        q = np.ascontiguousarray(world_quats, dtype=np.float32)
        p = np.ascontiguousarray(positions, dtype=np.float32)
        rot, tr = self._buffers(1)
        _check(_L().flame_retarget_pose(self._h(), _ptr(q, ctypes.c_float), q.size,
                                        _ptr(p, ctypes.c_float), p.size,
                                        _ptr(rot, ctypes.c_float), rot.size,
                                        _ptr(tr, ctypes.c_float), tr.size))
        return rot[0], tr[0]
