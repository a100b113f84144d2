"""Session.write_gltf (flame_session_write_gltf) through the Python bindings, the files read back
with pygltflib (an independent glTF 2.0 reader, from PyPI: tests/bindings/run_python.sh installs
it).

What the header promises and these tests check: nodes[0] is the skeleton's root and nodes[1 + j]
joint j, named as ModelInfo.joint_names; the animation's node-1 "translation" channel and every
node's "rotation" channel hold exactly what Session.read gives for Layout.ROOT_TRANSLATION and
Layout.LOCAL_QUAT_XYZW in Convention.GLTF with the same flags; humanml263 models also animate
the other joints' translations; the times are t / fps; asset.extras names the prompt, the seed
and the libflame version. Both containers (GLB, and JSON with the buffer as a base64 data URI),
on a smpl24_6d fixture (FLAME) and a humanml263 one (MDM).
"""

import ctypes
import os
import re
from pathlib import Path

import numpy as np
import pytest
from pygltflib import GLTF2

import flame
from flame import Convention, FlameError, GltfContainer, Layout, ReadFlags, Status

ROOT = Path(__file__).resolve().parents[3]
FIXTURES = ROOT / "tests/fixtures"
PROMPT = "a person walks forward and waves."
SEED = 5
FRAMES = 16
# (fixture, motion format, joints, the skeleton root node's name)
MODELS = [
    ("flame_tiny.safetensors", "smpl24_6d", 24, "smpl24"),
    ("mdm_tiny.safetensors", "humanml263", 22, "humanml22"),
]
GLB_MAGIC = b"glTF"


def expect_error(status, fragment, fn, *args, **kwargs):
    with pytest.raises(FlameError) as e:
        fn(*args, **kwargs)
    assert e.value.status == status, str(e.value)
    assert fragment in e.value.message, e.value.message
    return e.value


@pytest.fixture(scope="module", params=MODELS, ids=[m[1] for m in MODELS])
def stepped(request):
    """(model, session, expected format, joints, root name): a session two steps into four, so
    the sample is generic (the tiny models' final motions saturate, see test_pose_layouts)."""
    name, fmt, joints, root = request.param
    with flame.Model.load(FIXTURES / name) as model, \
            model.session(frames=FRAMES, steps=4, sampler="ddim", seed=SEED, threads=1) as s:
        s.set_prompt(PROMPT)
        s.step()
        s.step()
        yield model, s, fmt, joints, root


def as_in_file(q: np.ndarray) -> np.ndarray:
    """What the file holds for quaternions read from the session: glTF needs unit quaternions,
    so a degenerate rotation (parallel or zero 6D vectors, which clamped random-weight models
    output) is normalised, in double, and a zero one becomes the identity."""
    q = q.copy()
    flat = q.reshape(-1, 4)
    n = np.sqrt((flat.astype(np.float64) ** 2).sum(axis=1))
    off = np.abs(n - 1.0) > 1e-6
    for i in np.nonzero(off)[0]:
        if n[i] > 1e-12:
            flat[i] = (flat[i].astype(np.float64) / n[i]).astype(np.float32)
        else:
            flat[i] = np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32)
    return q


def load(data: bytes, container: int) -> GLTF2:
    """The file parsed by pygltflib, from GLB bytes or from JSON text."""
    if container == GltfContainer.GLB:
        assert data[:4] == GLB_MAGIC
        g = GLTF2.load_from_bytes(data)
    else:
        assert data[:1] == b"{", data[:20]
        g = GLTF2.gltf_from_json(data.decode("utf-8"))
    assert g is not None and g.asset.version == "2.0"
    return g


def accessor(g: GLTF2, index: int) -> np.ndarray:
    """Accessor `index`'s float32 values, [count, components], through pygltflib's buffer."""
    a = g.accessors[index]
    assert a.componentType == 5126, "FLOAT"
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
    view = g.bufferViews[a.bufferView]
    blob = g.get_data_from_buffer_uri(g.buffers[view.buffer].uri)
    start = (view.byteOffset or 0) + (a.byteOffset or 0)
    stride = view.byteStride or 4 * width
    assert stride == 4 * width, "tightly packed"
    values = np.frombuffer(blob, dtype="<f4", count=a.count * width, offset=start)
    return values.reshape(a.count, width)


def tracks(g: GLTF2):
    """{(node, path): (times, values)} of the one animation."""
    assert len(g.animations) == 1
    anim = g.animations[0]
    out = {}
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        assert sampler.interpolation == "LINEAR"
        key = (ch.target.node, ch.target.path)
        assert key not in out, f"two channels for {key}"
        out[key] = (accessor(g, sampler.input)[:, 0], accessor(g, sampler.output))
    return out


def flags_of(smooth, raw_signs):
    return (ReadFlags.SMOOTH if smooth else 0) | (ReadFlags.RAW_SIGNS if raw_signs else 0)


# --- the named values and the struct ---------------------------------------------------------


def test_container_values_match_the_header():
    header = (ROOT / "include/flame.h").read_text()
    theirs = {n.replace("_", "").lower(): int(v)
              for n, v in re.findall(r"FLAME_GLTF_CONTAINER_(\w+)\s*=\s*(-?\d+)", header)}
    ours = {n.lower(): v for n, v in vars(GltfContainer).items() if n.isupper()}
    assert theirs and ours == theirs


def test_gltf_params_default_through_ctypes():
    raw = flame._GltfParams()
    assert flame._lib().flame_gltf_params_default(ctypes.byref(raw)) == Status.OK
    assert raw.struct_size == ctypes.sizeof(flame._GltfParams)
    # Three u32, a float, then two pointers (the name, and since ABI 3 the cleanup): 16 + 16
    # bytes on 64-bit targets, 16 + 8 on 32-bit.
    assert ctypes.sizeof(raw) == 16 + 2 * ctypes.sizeof(ctypes.c_void_p)
    assert flame._GltfParams.cleanup.offset == 16 + ctypes.sizeof(ctypes.c_void_p)
    assert (raw.container, raw.flags, raw.fps, raw.name) == (GltfContainer.GLB, 0, 0.0, None)
    assert not raw.cleanup  # NULL: the raw poses
    assert flame._lib().flame_gltf_params_default(None) == Status.INVALID_ARGUMENT


# --- the animation is what read() gives ------------------------------------------------------


@pytest.mark.parametrize("container", [GltfContainer.GLB, GltfContainer.GLTF], ids=["glb", "gltf"])
@pytest.mark.parametrize("smooth, raw_signs", [(False, False), (True, False), (False, True)],
                         ids=["plain", "smooth", "raw-signs"])
def test_animation_equals_read(stepped, container, smooth, raw_signs):
    model, s, fmt, joints, root_name = stepped
    info = model.info
    assert (info.motion_format, info.joint_count) == (fmt, joints)
    flags = flags_of(smooth, raw_signs)
    data = s.write_gltf(container=container, smooth=smooth, raw_signs=raw_signs)
    assert isinstance(data, bytes)
    g = load(data, container)

    # Nodes: the skeleton's root, then joint j at 1 + j with the model's names and hierarchy.
    names = [n.name for n in g.nodes]
    assert names[0] == root_name and g.nodes[0].children == [1]
    assert names[1:1 + joints] == info.joint_names
    for j, parent in enumerate(info.joint_parents):
        if parent >= 0:
            assert 1 + j in (g.nodes[1 + parent].children or []), (j, parent)
    assert g.skins[0].joints == list(range(1, 1 + joints))
    assert g.skins[0].skeleton == 0

    root = s.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF, flags)
    quats = s.read("sample", Layout.LOCAL_QUAT_XYZW, Convention.GLTF, flags)
    assert root.shape == (FRAMES, 3) and quats.shape == (FRAMES, joints, 4)
    got = tracks(g)
    times, translation = got[(1, "translation")]
    np.testing.assert_allclose(translation, root, rtol=0, atol=1e-6)
    assert translation.tobytes() == root.tobytes(), "bit for bit"
    np.testing.assert_allclose(times, np.arange(FRAMES) / info.fps, rtol=0, atol=1e-6)
    for j in range(joints):
        t, q = got[(1 + j, "rotation")]
        assert t.tobytes() == times.tobytes()
        np.testing.assert_allclose(q, quats[:, j], rtol=0, atol=1e-6, err_msg=info.joint_names[j])
        assert q.tobytes() == as_in_file(quats[:, j]).tobytes(), f"{info.joint_names[j]}: bit for bit"
    if raw_signs:
        assert all((got[(1 + j, "rotation")][1][:, 3] >= 0).all() for j in range(joints))

    # humanml263 animates every other joint's translation too (its positions are its own
    # features, not the rotations' forward kinematics); smpl24_6d keeps the rest offsets.
    moved = sorted(node for node, path in got if path == "translation" and node != 1)
    if fmt == "humanml263":
        assert moved == list(range(2, 1 + joints))
        assert all(np.isfinite(got[(n, "translation")][1]).all() for n in moved)
    else:
        assert moved == []
    assert len(got) == 1 + joints + len(moved)

    extras = g.asset.extras
    assert extras["prompt"] == PROMPT and extras["seed"] == SEED
    assert extras["libflame"] == flame.version() and extras["format"] == fmt
    assert extras["frames"] == FRAMES and extras["fps"] == info.fps
    assert g.asset.generator == "libflame " + flame.version()
    assert g.animations[0].name == "a_person_walks_forward_and_waves"


def test_both_containers_hold_the_same_buffer(stepped):
    _, s, _, _, _ = stepped
    glb = GLTF2.load_from_bytes(s.write_gltf())
    gltf = GLTF2.gltf_from_json(s.write_gltf(container="gltf").decode())
    assert glb.binary_blob() == gltf.get_data_from_buffer_uri(gltf.buffers[0].uri)
    assert gltf.buffers[0].uri.startswith("data:application/octet-stream;base64,")
    assert glb.buffers[0].byteLength == gltf.buffers[0].byteLength == len(glb.binary_blob())
    assert [a.to_dict() for a in glb.accessors] == [a.to_dict() for a in gltf.accessors]


def test_glb_header(stepped):
    _, s, _, _, _ = stepped
    data = s.write_gltf()
    magic, version, length = data[:4], *np.frombuffer(data[4:12], dtype="<u4")
    assert (magic, version, length) == (GLB_MAGIC, 2, len(data))
    assert data[16:20] == b"JSON" and int(np.frombuffer(data[12:16], dtype="<u4")[0]) % 4 == 0
    assert s.write_gltf() == data, "the same motion and parameters give the same bytes"


def test_estimate_fps_and_name(stepped):
    model, s, _, joints, _ = stepped
    g = load(s.write_gltf(which="estimate", fps=30.0, name="my walk, take 2!"), GltfContainer.GLB)
    got = tracks(g)
    times, translation = got[(1, "translation")]
    np.testing.assert_allclose(times, np.arange(FRAMES) / 30.0, rtol=0, atol=1e-6)
    assert g.asset.extras["fps"] == 30.0
    est = s.read("estimate", Layout.ROOT_TRANSLATION, Convention.GLTF)
    assert translation.tobytes() == est.tobytes()
    q = s.read(flame.Which.ESTIMATE, Layout.LOCAL_QUAT_XYZW, Convention.GLTF)
    assert got[(joints, "rotation")][1].tobytes() == as_in_file(q[:, joints - 1]).tobytes()
    assert g.animations[0].name == "my_walk_take_2"
    assert s.write_gltf(which=flame.Which.ESTIMATE) != s.write_gltf(), "estimate is not the sample"


def test_write_to_a_path(stepped, tmp_path):
    _, s, _, _, _ = stepped
    # The container follows the extension (any case); none, or no path, is GLB.
    for file, magic in [("m.glb", GLB_MAGIC), ("m.GLTF", b"{"), ("m", GLB_MAGIC)]:
        path = tmp_path / file
        data = s.write_gltf(path)
        assert data[:len(magic)] == magic, file
        assert path.read_bytes() == data, file
    assert s.write_gltf(str(tmp_path / "a.gltf")) == s.write_gltf(container="gltf")
    assert s.write_gltf(os.fsencode(tmp_path / "b.glb")) == s.write_gltf()
    # pygltflib's own loader reads both files (it picks the container by extension too).
    assert GLTF2.load(str(tmp_path / "m.glb")).asset.extras["seed"] == SEED
    assert GLTF2.load(str(tmp_path / "a.gltf")).asset.extras["seed"] == SEED
    # An explicit container wins over the extension.
    assert s.write_gltf(tmp_path / "c.gltf", container="glb")[:4] == GLB_MAGIC
    assert s.write_gltf(tmp_path / "d.glb", container=GltfContainer.GLTF)[:1] == b"{"
    with pytest.raises(ValueError, match="glTF container"):
        s.write_gltf(tmp_path / "e.bvh")
    assert not (tmp_path / "e.bvh").exists()


def test_latent_model_exports_the_decoded_frames():
    with flame.Model.load(FIXTURES / "mola_tiny.safetensors") as m, \
            m.session(frames=60, steps=4, sampler="ddim", seed=3, threads=1) as s:
        s.set_prompt(PROMPT)
        s.run()
        frames = s.read_frames()
        g = load(s.write_gltf(), GltfContainer.GLB)
        times, translation = tracks(g)[(1, "translation")]
        assert len(times) == frames == g.asset.extras["frames"]
        assert translation.tobytes() == s.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF).tobytes()


# --- errors ----------------------------------------------------------------------------------


def test_errors():
    with flame.Model.load(FIXTURES / "flame_tiny.safetensors") as m, \
            m.session(frames=FRAMES, steps=4, sampler="ddim", seed=SEED, threads=1) as s:
        # Before the first step there is nothing to export: the WRONG_STATE FlameError.
        expect_error(Status.WRONG_STATE, "no sample yet", s.write_gltf)
        s.set_prompt(PROMPT)
        expect_error(Status.WRONG_STATE, "no sample yet", s.write_gltf)
        expect_error(Status.WRONG_STATE, "no clean-motion estimate", s.write_gltf, which="estimate")
        s.step()
        assert s.write_gltf()[:4] == GLB_MAGIC
        # A container the binding does not name: ValueError; a value libflame does not know:
        # its INVALID_ARGUMENT.
        with pytest.raises(ValueError, match="unknown glTF container 'fbx'"):
            s.write_gltf(container="fbx")
        expect_error(Status.INVALID_ARGUMENT, "unknown glTF container 7", s.write_gltf, container=7)
        expect_error(Status.INVALID_ARGUMENT, "unknown glTF container -1", s.write_gltf, container=-1)
        expect_error(Status.INVALID_ARGUMENT, "frame rate must be positive", s.write_gltf, fps=-1.0)
        expect_error(Status.INVALID_ARGUMENT, "frame rate must be positive", s.write_gltf, fps=float("nan"))
        expect_error(Status.INVALID_ARGUMENT, "unknown `which` 3", s.write_gltf, which=3)
        with pytest.raises(ValueError):
            s.write_gltf(which="noisy")
        with pytest.raises(ValueError, match="NUL"):
            s.write_gltf(name="a\0b")
        with pytest.raises(TypeError):
            s.write_gltf(name=b"bytes")
        s.reset()
        expect_error(Status.WRONG_STATE, "no sample yet", s.write_gltf)
        s.close()
        with pytest.raises(ValueError, match="closed"):
            s.write_gltf()


def test_raw_buffer_too_small():
    """The length protocol of flame_session_write_gltf through the raw ctypes call: NULL asks
    for the size, a short buffer gets BUFFER_TOO_SMALL with the size in *out_len."""
    lib = flame._lib()
    with flame.Model.load(FIXTURES / "flame_tiny.safetensors") as m, \
            m.session(frames=FRAMES, steps=4, sampler="ddim", seed=SEED, threads=1) as s:
        s.set_prompt(PROMPT)
        s.step()
        h = s._h()
        n = ctypes.c_size_t()
        assert lib.flame_session_write_gltf(h, 0, None, None, 0, ctypes.byref(n)) == Status.OK
        needed = n.value
        expected = s.write_gltf()
        assert needed == len(expected) > 1000
        small = (ctypes.c_uint8 * 16)()
        n.value = 0
        st = lib.flame_session_write_gltf(h, 0, None, small, len(small), ctypes.byref(n))
        assert st == Status.BUFFER_TOO_SMALL and n.value == needed
        assert "buffer too small" in lib.flame_last_error().decode()
        assert bytes(small) == bytes(16), "nothing written on failure"
        st = lib.flame_session_write_gltf(h, 0, None, small, 0, ctypes.byref(n))
        assert st == Status.BUFFER_TOO_SMALL and n.value == needed
        # One byte short, then exactly the size, then more: NULL params = the defaults.
        short = (ctypes.c_uint8 * (needed - 1))()
        assert lib.flame_session_write_gltf(h, 0, None, short, needed - 1, ctypes.byref(n)) == Status.BUFFER_TOO_SMALL
        assert n.value == needed
        big = (ctypes.c_uint8 * (needed + 8))()
        n.value = 0
        assert lib.flame_session_write_gltf(h, 0, None, big, len(big), ctypes.byref(n)) == Status.OK
        assert n.value == needed and ctypes.string_at(big, needed) == expected
        assert bytes(big)[needed:] == bytes(8)
        # Params through the struct: the JSON container has another size.
        raw = flame._GltfParams()
        lib.flame_gltf_params_default(ctypes.byref(raw))
        raw.container = GltfContainer.GLTF
        assert lib.flame_session_write_gltf(h, 0, ctypes.byref(raw), None, 0, ctypes.byref(n)) == Status.OK
        assert n.value == len(s.write_gltf(container="gltf")) != needed
        # Version 1 of the struct ended before `cleanup`: its size is still accepted (no
        # cleanup), one byte less is not.
        raw.struct_size = flame._GltfParams.cleanup.offset
        assert lib.flame_session_write_gltf(h, 0, ctypes.byref(raw), None, 0, ctypes.byref(n)) == Status.OK
        assert n.value == len(s.write_gltf(container="gltf"))
        raw.struct_size -= 1
        assert lib.flame_session_write_gltf(h, 0, ctypes.byref(raw), None, 0, ctypes.byref(n)) == Status.INVALID_ARGUMENT
        assert b"struct_size" in lib.flame_last_error()
        assert lib.flame_session_write_gltf(h, 0, None, None, 0, None) == Status.INVALID_ARGUMENT
        assert b"out_len" in lib.flame_last_error()
        assert lib.flame_session_write_gltf(None, 0, None, None, 0, ctypes.byref(n)) == Status.INVALID_ARGUMENT
        assert b"`session` is NULL" in lib.flame_last_error()
