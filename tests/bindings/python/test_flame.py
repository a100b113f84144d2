"""The Python bindings (bindings/python/flame) against libflame's C ABI.

Reference: the `flame generate` CLI (the Rust API) — the features it writes for REF_PROMPT with
REF_SETTINGS must equal, bit for bit, what the bindings generate. Fixture:
tests/fixtures/flame_tiny.safetensors (147 features per frame, at most 470 frames, defaults
ddpm / 1000 steps / guidance 8).

Environment (all optional; tests/bindings/run_python.sh sets them):
  FLAME_LIBRARY     the shared library (else the bindings' own search: next to the package, then
                    target/release, target/debug); run_python.sh leaves it unset, so the installed
                    wheel's own library is tested
  FLAME_CLI         the `flame` executable (else next to the library)
  FLAME_MODEL       the model file (else the fixture)
  FLAME_TEST_WHEEL  1: the package under test is an installed wheel (checked by a test)
"""

import ctypes
import dataclasses
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import flame
from flame import Convention, FlameError, Layout, ReadFlags, Status

ROOT = Path(__file__).resolve().parents[3]
MODEL = os.environ.get("FLAME_MODEL", str(ROOT / "tests/fixtures/flame_tiny.safetensors"))
REF_PROMPT = "a person walks forward and waves."
REF_SETTINGS = dict(frames=24, steps=10, sampler="ddim", seed=3, threads=1)
DIM = 147


def cli_path() -> str:
    env = os.environ.get("FLAME_CLI")
    if env:
        return env
    exe = Path(flame.library_path()).with_name("flame")
    if not exe.is_file():
        pytest.skip(f"no flame CLI next to {flame.library_path()} (set FLAME_CLI)")
    return str(exe)


def cli_generate(out: Path, noise: Path = None) -> np.ndarray:
    s = REF_SETTINGS
    cmd = [cli_path(), "generate", "--model", MODEL, "--prompt", REF_PROMPT,
           "--frames", str(s["frames"]), "--steps", str(s["steps"]), "--sampler", s["sampler"],
           "--seed", str(s["seed"]), "--threads", str(s["threads"]), "--out", str(out)]
    if noise is not None:
        cmd += ["--noise", str(noise)]
    subprocess.run(cmd, check=True, capture_output=True)
    return np.load(out)


@pytest.fixture(scope="module")
def model():
    with flame.Model.load(MODEL) as m:
        yield m


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return cli_generate(tmp_path_factory.mktemp("cli") / "ref.npy")


def ref_session(model, **overrides):
    s = model.session(**{**REF_SETTINGS, **overrides})
    s.set_prompt(REF_PROMPT)
    return s


def expect_error(status, fragment, fn, *args, **kwargs):
    with pytest.raises(FlameError) as e:
        fn(*args, **kwargs)
    assert e.value.status == status, str(e.value)
    assert fragment in e.value.message, e.value.message
    return e.value


# --- the header ------------------------------------------------------------------------------

HEADER = (ROOT / "include/flame.h").read_text()


def _key(name):
    return name.replace("_", "").lower()


def test_every_header_function_is_bound():
    import re

    declared = set(re.findall(r"^[a-z][^;()]*?\b(flame_\w+)\(", HEADER, re.M))
    assert len(declared) >= 25
    assert declared == set(flame._signatures()), declared ^ set(flame._signatures())


@pytest.mark.parametrize(
    "prefix, names",
    [("FLAME_STATUS_", Status), ("FLAME_SAMPLER_", flame.Sampler), ("FLAME_WHICH_", flame.Which),
     ("FLAME_LAYOUT_", Layout), ("FLAME_CONVENTION_", Convention), ("FLAME_READ_", ReadFlags),
     ("FLAME_EDIT_METHOD_", flame.EditMethod), ("FLAME_BODY_PART_", flame.BodyPart),
     ("FLAME_EDIT_TASK_", flame.EditTask), ("FLAME_WEIGHTS_", flame.Weights),
     ("FLAME_TARGET_SCHEDULE_", flame.TargetSchedule)],
)
def test_named_values_match_the_header(prefix, names):
    import re

    header = {_key(n): int(v) for n, v in re.findall(prefix + r"(\w+)\s*=?\s*(-?\d+)", HEADER)}
    ours = {_key(n): v for n, v in vars(names).items() if n.isupper()}
    assert header and ours == header


def test_constants_match_the_header():
    assert f"#define FLAME_ABI_VERSION {flame.ABI_VERSION}\n" in HEADER
    assert f"#define FLAME_ROOT_TRANSLATION {flame.ROOT_TRANSLATION}\n" in HEADER
    assert f"#define FLAME_MAX_THREADS {flame.MAX_THREADS}\n" in HEADER


def test_thread_bound_is_relayed(model):
    limit = flame.MAX_THREADS
    expect_error(Status.INVALID_ARGUMENT, f"threads {limit + 1} is above the limit of {limit}",
                 flame.Model.load, MODEL, threads=limit + 1)
    expect_error(Status.INVALID_ARGUMENT, f"threads {limit + 1} is above the limit of {limit}",
                 model.session, threads=limit + 1)
    with pytest.raises(ValueError):
        model.session(threads=-1)
    with model.session(threads=limit):
        pass


# --- library and model ------------------------------------------------------------------------


def test_version_and_abi():
    assert flame.version().count(".") == 2
    assert flame._lib().flame_abi_version() == flame.ABI_VERSION


@pytest.mark.skipif(os.environ.get("FLAME_TEST_WHEEL") != "1", reason="not testing an installed wheel")
def test_installed_wheel_loads_its_own_library():
    package = Path(flame.__file__).resolve().parent
    assert ROOT not in package.parents, f"flame imported from the checkout: {package}"
    assert "FLAME_LIBRARY" not in os.environ
    assert Path(flame.library_path()) == package / flame._library_names()[0]


def test_info(model):
    i = model.info
    assert (i.feature_dim, i.max_frames, i.num_timesteps) == (DIM, 470, 1000)
    assert (i.default_steps, i.default_sampler, i.default_guidance) == (1000, flame.Sampler.DDPM, 8.0)
    assert 1 <= i.default_frames <= i.max_frames
    assert (i.architecture, i.motion_format, i.text_encoder) == ("flame", "smpl24_6d", "roberta")
    assert i.fps == 20.0
    assert i.joint_count == 24 and i.joint_names[0] == "Pelvis", i.joint_names  # SMPL-24
    assert len(i.joint_names) == len(i.joint_parents) == i.joint_count
    for j, p in enumerate(i.joint_parents):
        assert (p == -1) if j == 0 else (0 <= p < j), (j, p)
    assert all(i.joint_names), i.joint_names


def test_load_errors(tmp_path):
    expect_error(Status.IO, "no_such_model.safetensors", flame.Model.load, tmp_path / "no_such_model.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a model")
    expect_error(Status.BAD_MODEL_FILE, "bad model file", flame.Model.load, bad)
    expect_error(Status.BAD_MODEL_FILE, "too short", flame.Model.from_bytes, b"")
    truncated = Path(MODEL).read_bytes()[:5000]
    expect_error(Status.BAD_MODEL_FILE, "bad model file", flame.Model.from_bytes, truncated)


def test_error_has_status_name():
    e = expect_error(Status.IO, "cannot read", flame.Model.load, "/nonexistent/x.safetensors")
    assert e.status_name == "FLAME_STATUS_IO"
    assert str(e).startswith("FLAME_STATUS_IO: ")


# --- generation -------------------------------------------------------------------------------


def test_matches_cli_bit_for_bit(model, reference):
    with ref_session(model) as s:
        out = s.run()
    assert out.dtype == np.float32 and out.shape == (24, DIM)
    assert out.tobytes() == reference.tobytes()


def test_from_bytes_matches_cli(reference):
    with flame.Model.from_bytes(Path(MODEL).read_bytes()) as m, ref_session(m) as s:
        assert s.run().tobytes() == reference.tobytes()


def test_half_precision_weights(reference):
    # The same generation with the linear layers in f16 / bf16: finite, close, not identical
    # (the tiny random fixture amplifies rounding, so "close" is loose here; tests/weights_half.rs
    # measures a trained model).
    for weights in ("f16", flame.Weights.BF16):
        with flame.Model.load(MODEL, weights=weights) as m, ref_session(m) as s:
            out = s.run()
        assert np.isfinite(out).all(), weights
        assert out.tobytes() != reference.tobytes(), weights
    with pytest.raises(ValueError, match="weights"):
        flame.Model.load(MODEL, weights="f8")
    expect_error(Status.INVALID_ARGUMENT, "params.weights is 7", flame.Model.load, MODEL, weights=7)


def _cpu_runs(weights):
    # bf16-compute: AVX512_BF16 on the AVX-512 kernel; int8: AVX2 (or VNNI) on any kernel but the
    # portable one.
    with open("/proc/cpuinfo") as f:
        words = f.read().split()
    kernel = os.environ.get("FLAME_KERNEL", "avx512")
    if weights == "bf16-compute":
        return "avx512f" in words and "avx512_bf16" in words and kernel == "avx512"
    return all(w in words for w in ("avx2", "fma", "f16c")) and kernel != "portable"


@pytest.mark.parametrize(
    "weights,instruction",
    [("bf16-compute", "AVX512_BF16"), (flame.Weights.INT8, "AVX2")],
)
def test_reduced_precision_compute(reference, weights, instruction):
    # Loads and runs where the CPU has the instructions (finite, not the f32 bits); refused at load
    # with the instruction's name elsewhere.
    if not _cpu_runs("bf16-compute" if weights == "bf16-compute" else "int8"):
        expect_error(Status.INVALID_ARGUMENT, instruction, flame.Model.load, MODEL, weights=weights)
        return
    with flame.Model.load(MODEL, weights=weights) as m, ref_session(m) as s:
        out = s.run()
    assert np.isfinite(out).all() and out.tobytes() != reference.tobytes()


def test_steps_left_estimate_and_reset(model, reference):
    with ref_session(model) as s:
        assert s.progress == (0, 10)
        assert s.step() == 9
        est = s.read("estimate")
        assert est.shape == (24, DIM) and np.isfinite(est).all()
        assert not np.array_equal(est, s.read("sample"))
        lefts = [s.step() for _ in range(9)]
        assert lefts == list(range(8, -1, -1))
        assert s.read(flame.Which.SAMPLE, Layout.FEATURES, Convention.NATIVE, 0).tobytes() == reference.tobytes()
        expect_error(Status.WRONG_STATE, "finished", s.step)
        s.reset()
        assert s.run().tobytes() == reference.tobytes()


def test_set_noise_matches_cli(model, tmp_path):
    noise = np.random.default_rng(7).standard_normal((24, DIM)).astype(np.float32)
    np.save(tmp_path / "noise.npy", noise)
    expected = cli_generate(tmp_path / "out.npy", noise=tmp_path / "noise.npy")
    with ref_session(model) as s:
        s.set_noise(noise.astype(np.float64))  # converted to float32 by the bindings
        s.step()
        s.set_prompt(REF_PROMPT)  # the prompt may change between steps
        assert s.run().tobytes() == expected.tobytes()
        expect_error(Status.WRONG_STATE, "before the first step", s.set_noise, noise)
    with ref_session(model) as s:
        s.set_noise(np.asfortranarray(noise))  # non-contiguous input is copied
        assert s.run().tobytes() == expected.tobytes()


def test_session_errors(model):
    with model.session(**REF_SETTINGS) as s:
        expect_error(Status.WRONG_STATE, "set a prompt", s.step)
        expect_error(Status.WRONG_STATE, "no sample yet", s.read)
        s.set_prompt(REF_PROMPT)
        expect_error(Status.WRONG_STATE, "no clean-motion estimate", s.read, "estimate")
        expect_error(Status.INVALID_ARGUMENT, "initial noise has 10 values", s.set_noise, np.zeros(10))
        expect_error(Status.INVALID_ARGUMENT, "NaN", s.set_noise, np.full((24, DIM), np.nan))
        s.step()
        expect_error(Status.INVALID_ARGUMENT, "unknown layout 999", s.read, "sample", 999)
        expect_error(Status.INVALID_ARGUMENT, "unknown layout -1", s.read, "sample", -1)
        expect_error(Status.INVALID_ARGUMENT, "unknown `which` 5", s.read, 5)
        with pytest.raises(ValueError):
            s.read("noisy")
        expect_error(Status.INVALID_ARGUMENT, "frame range from 5 to 5", s.keep_frames, 5, 5)
        expect_error(Status.INVALID_ARGUMENT, "past the session's 24 frames", s.keep_frames, 0, 25)
        expect_error(Status.INVALID_ARGUMENT, "joint 24", s.keep_joints, [24])
        expect_error(Status.INVALID_ARGUMENT, "want 1 to 24 frames", s.set_reference, np.zeros((25, DIM)))
        expect_error(Status.INVALID_ARGUMENT, "does not match", s.set_mask, np.zeros((24, 146)))
    for kwargs, fragment in [
        (dict(frames=471), "frames must be between 1 and 470 for this model, got 471"),
        (dict(steps=1001), "steps must be between 1 and 1000 for this model, got 1001"),
        (dict(sampler=7), "unknown sampler 7"),
        (dict(guidance=float("nan")), "`guidance` is NaN"),
        (dict(eta=float("nan")), "`eta` is NaN"),
    ]:
        expect_error(Status.INVALID_ARGUMENT, fragment, model.session, **kwargs)
    with pytest.raises(ValueError):
        model.session(sampler="rk4")
    # FLAME is a diffusion model: the flow-matching samplers are refused by the library.
    expect_error(Status.INVALID_ARGUMENT, "needs a flow-matching model", model.session, sampler="euler")


def test_respacing_picks_the_training_steps(model):
    # "ddim4" keeps {0, 250, 500, 750} of the 1000 steps, as do four one-step sections
    # "1,1,1,1"; "4" keeps {0, 333, 666, 999}, as `steps=4` does.
    def run(**kw):
        with model.session(frames=8, sampler="ddim", seed=5, threads=1, **kw) as s:
            assert s.progress == (0, 4)
            s.set_prompt(REF_PROMPT)
            return s.run().tobytes()
    stride = run(respacing="ddim4")
    assert stride == run(respacing="1,1,1,1") == run(respacing="ddim4", steps=4)
    assert run(respacing="4") == run(steps=4) != stride
    expect_error(Status.INVALID_ARGUMENT, "steps 5 disagrees with respacing \"ddim4\"",
                 model.session, respacing="ddim4", steps=5)
    expect_error(Status.INVALID_ARGUMENT, "cannot create exactly 999 steps", model.session,
                 respacing="ddim999")
    with pytest.raises(ValueError):
        model.session(respacing="ddim4\0")


# The fixture's RoBERTa window is 20 tokens, <s> and </s> included (its config).
WINDOW = 20
LONG_PROMPT = ("a person walks forward, turns left, raises both arms, waves with the right hand, "
               "sits down on a chair and then kicks with the right leg")


def test_prompt_info(model):
    import warnings

    with model.session(**REF_SETTINGS) as s:
        expect_error(Status.WRONG_STATE, "no prompt", s.prompt_info)
        with pytest.warns(flame.PromptTruncatedWarning) as caught:
            s.set_prompt(LONG_PROMPT)
        info = s.prompt_info()
        assert isinstance(info, flame.PromptInfo)
        assert (info.window, info.kept) == (WINDOW, WINDOW) and info.tokens > WINDOW, info
        assert info.truncated is True and info.unconditional is False
        assert info.dropped and LONG_PROMPT.endswith(info.dropped), info
        assert info.dropped.endswith("kicks with the right leg")
        # The warning names the kept and total tokens and the dropped text.
        message = str(caught[0].message)
        assert len(caught) == 1 and caught[0].filename == __file__, "it points at the caller"
        assert f"{info.tokens} tokens" in message and f"first {WINDOW}" in message, message
        assert repr(info.dropped) in message, message
        with pytest.raises(dataclasses.FrozenInstanceError):
            info.kept = 1
        # What was kept, on its own, fits the window as the cut prompt did.
        kept_text = LONG_PROMPT[: len(LONG_PROMPT) - len(info.dropped)].rstrip()
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no warning for a prompt that fits
            s.set_prompt(kept_text)
            rest = s.prompt_info()
            assert WINDOW - 1 <= rest.tokens <= WINDOW and not rest.truncated, rest
            s.set_prompt("a person walks")
            short = s.prompt_info()
            assert not short.truncated and short.dropped == "" and short.kept == short.tokens < WINDOW
            assert not short.unconditional
            for blank in ["", "  \t "]:
                s.set_prompt(blank)
                none = s.prompt_info()
                assert none.unconditional and not none.truncated and none.dropped == "", none
        # Non-ASCII text in the dropped tail comes back as the same str.
        accented = LONG_PROMPT + " près du café à l'été"
        with pytest.warns(flame.PromptTruncatedWarning):
            s.set_prompt(accented)
        info = s.prompt_info()
        assert accented.endswith(info.dropped) and info.dropped.endswith("café à l'été"), info
        s.close()
        with pytest.raises(ValueError):
            s.prompt_info()


def test_prompt_info_struct_size_through_ctypes(model):
    """The raw call checks struct_size, so a struct from an older header is refused, not overrun."""
    import ctypes

    lib = flame._lib()
    with ref_session(model) as s:
        raw = flame._PromptInfo()
        raw.struct_size = ctypes.sizeof(raw) - 1
        assert lib.flame_session_prompt_info(s._h(), ctypes.byref(raw)) == Status.INVALID_ARGUMENT
        assert b"struct_size" in lib.flame_last_error()
        assert lib.flame_session_prompt_info(s._h(), None) == Status.INVALID_ARGUMENT
        # Six u32 and a pointer, no padding on 32- or 64-bit targets.
        assert ctypes.sizeof(raw) == 24 + ctypes.sizeof(ctypes.c_void_p)


def test_raw_read_buffer_too_small(model):
    """The NULL-buffer length query and BUFFER_TOO_SMALL, through the raw C functions."""
    import ctypes

    lib = flame._lib()
    with ref_session(model) as s:
        s.step()
        n = ctypes.c_size_t()
        assert lib.flame_session_read(s._h(), 0, 0, 0, 0, None, 0, ctypes.byref(n)) == Status.OK
        assert n.value == 24 * DIM
        small = (ctypes.c_float * 10)()
        n.value = 0
        st = lib.flame_session_read(s._h(), 0, 0, 0, 0, small, 10, ctypes.byref(n))
        assert st == Status.BUFFER_TOO_SMALL and n.value == 24 * DIM
        assert "buffer too small" in lib.flame_last_error().decode()
        st = lib.flame_session_read(s._h(), 0, 0, 0, 0, None, 0, None)
        assert st == Status.INVALID_ARGUMENT and b"out_len" in lib.flame_last_error()
        assert lib.flame_session_step(None, None) == Status.INVALID_ARGUMENT
        assert b"`session` is NULL" in lib.flame_last_error()
        assert lib.flame_session_set_prompt(s._h(), None) == Status.INVALID_ARGUMENT
        assert b"`prompt` is NULL" in lib.flame_last_error()
        assert lib.flame_session_set_prompt(s._h(), b"\xff\xfe") == Status.INVALID_ARGUMENT
        assert b"UTF-8" in lib.flame_last_error()
        assert lib.flame_session_progress(s._h(), None, None) == Status.OK
        assert lib.flame_last_error() == b"", "a successful call clears the message"
    lib.flame_model_free(None)
    lib.flame_session_free(None)


def test_closed_handles(model):
    s = ref_session(model)
    s.close()
    s.close()  # twice is fine
    with pytest.raises(ValueError):
        s.step()
    s.cancel()  # a no-op on a closed session
    m = flame.Model.load(MODEL)
    s = ref_session(m)
    m.close()  # the session keeps the model alive natively
    s.step()
    s.close()
    assert m.info.feature_dim == DIM, "info was copied while the model was open"
    with pytest.raises(ValueError):
        m.session()


# --- pose layouts -----------------------------------------------------------------------------


def test_pose_layouts(model, reference):
    J = model.info.joint_count
    with ref_session(model) as s:
        s.run()
        # Raw features ignore convention and flags.
        assert s.read("sample", Layout.FEATURES, Convention.UNITY, ReadFlags.SMOOTH).tobytes() == reference.tobytes()
        # The tiny model's final motion saturates at ±1, where some 6D rotations are degenerate
        # (parallel rows; libflame follows pytorch3d there and yields singular matrices). The
        # sample after one step is generic, so the pose checks use it.
        s.reset()
        s.step()
        shapes = {
            Layout.ROOT_TRANSLATION: (24, 3),
            Layout.LOCAL_QUAT_XYZW: (24, J, 4),
            Layout.LOCAL_QUAT_WXYZ: (24, J, 4),
            Layout.LOCAL_MATRIX: (24, J, 3, 3),
            Layout.LOCAL_6D: (24, J, 6),
            Layout.GLOBAL_POSITIONS: (24, J, 3),
            Layout.GLOBAL_QUAT_XYZW: (24, J, 4),
            Layout.GLOBAL_QUAT_WXYZ: (24, J, 4),
        }
        for convention in (Convention.NATIVE, Convention.UNITY, Convention.UNREAL, Convention.GLTF):
            poses = {layout: s.read("sample", layout, convention) for layout in shapes}
            for layout, shape in shapes.items():
                assert poses[layout].shape == shape and np.isfinite(poses[layout]).all(), (layout, convention)
            xyzw, wxyz = poses[Layout.LOCAL_QUAT_XYZW], poses[Layout.LOCAL_QUAT_WXYZ]
            np.testing.assert_allclose(np.linalg.norm(xyzw, axis=-1), 1, atol=1e-5)
            np.testing.assert_array_equal(wxyz, xyzw[..., [3, 0, 1, 2]])
            np.testing.assert_array_equal(poses[Layout.LOCAL_6D], poses[Layout.LOCAL_MATRIX][..., :2, :].reshape(24, J, 6))
        # Conventions move and scale positions but keep distances (centimetres in Unreal).
        native = s.read("sample", Layout.GLOBAL_POSITIONS, Convention.NATIVE)
        unreal = s.read("sample", Layout.GLOBAL_POSITIONS, Convention.UNREAL)
        bone = lambda p: np.linalg.norm(p[:, 1:] - p[:, :1], axis=-1)  # noqa: E731
        np.testing.assert_allclose(bone(unreal), 100 * bone(native), rtol=1e-4, atol=1e-3)
        # Flags: smoothing changes the poses; raw signs keep w >= 0.
        q = s.read("sample", Layout.LOCAL_QUAT_XYZW, Convention.UNITY)
        assert not np.array_equal(q, s.read("sample", Layout.LOCAL_QUAT_XYZW, Convention.UNITY, ReadFlags.SMOOTH))
        assert (s.read("sample", Layout.LOCAL_QUAT_XYZW, Convention.UNITY, ReadFlags.RAW_SIGNS)[..., 3] >= 0).all()
        # Foot contacts: detected for smpl24 models (ABI 3), 0 or 1 per foot joint and frame.
        contacts = s.read("sample", Layout.FOOT_CONTACTS)
        assert contacts.shape == (24, 4) and set(np.unique(contacts)) <= {0.0, 1.0}
        expect_error(Status.INVALID_ARGUMENT, "unknown convention 9", s.read, "sample", Layout.LOCAL_QUAT_XYZW, 9)
        expect_error(Status.INVALID_ARGUMENT, "unknown read flags", s.read, "sample", Layout.LOCAL_QUAT_XYZW, 0, 4)
        # The estimate reads in any layout too.
        assert s.read("estimate", Layout.GLOBAL_QUAT_WXYZ, Convention.ROS).shape == (24, J, 4)


# --- progress and cancel ----------------------------------------------------------------------


def test_progress_callback(model, reference):
    seen = []
    with ref_session(model) as s:
        s.set_progress(lambda done, total: seen.append((done, total, threading.get_ident())))
        out = s.run()
        assert [(d, t) for d, t, _ in seen] == [(i, 10) for i in range(1, 11)]
        assert {tid for *_, tid in seen} == {threading.get_ident()}, "runs on the stepping thread"
        assert out.tobytes() == reference.tobytes()
        s.set_progress(None)
        s.reset()
        s.step()
        assert len(seen) == 10


def test_progress_callback_may_read_the_session(model):
    """The callback runs after the session's lock is released, so it can read the preview."""
    previews = []
    with ref_session(model) as s:
        s.set_progress(lambda done, total: previews.append(s.read("estimate")))
        s.run()
        assert len(previews) == 10
        assert previews[-1].tobytes() == s.read("estimate").tobytes()


def test_progress_callback_exception_is_raised_by_step(model):
    def boom(done, total):
        raise RuntimeError(f"boom at {done}")

    with ref_session(model) as s:
        s.set_progress(boom)
        with pytest.raises(RuntimeError, match="boom at 1"):
            s.step()
        assert s.progress == (1, 10), "the step itself completed"


def test_cancel_from_callback_then_retry_is_bit_identical(model, reference):
    """A cancel raised between steps fails the next step with CANCELLED; retrying it continues the
    same generation."""
    with ref_session(model) as s:
        s.set_progress(lambda done, total: s.cancel() if done in (3, 7) else None)
        cancelled = 0
        while s.steps_left:
            try:
                s.step()
            except FlameError as e:
                assert e.status == Status.CANCELLED and e.message == "cancelled"
                cancelled += 1
        assert cancelled == 2
        assert s.read().tobytes() == reference.tobytes()


def test_cancel_from_another_thread(model):
    """A long generation stepped on a worker thread, cancelled from this one."""
    with model.session(frames=470, steps=1000, seed=1, threads=1) as s:
        s.set_prompt(REF_PROMPT)
        started = threading.Event()
        s.set_progress(lambda done, total: started.set())
        result = {}

        def worker():
            try:
                while s.steps_left:
                    s.step()
                result["finished"] = True
            except FlameError as e:
                result["error"] = e

        t = threading.Thread(target=worker)
        t.start()
        assert started.wait(30)
        t0 = time.perf_counter()
        s.cancel()
        t.join(30)
        assert not t.is_alive()
        assert result["error"].status == Status.CANCELLED, result
        assert time.perf_counter() - t0 < 5
        done, total = s.progress
        assert 1 <= done < total == 1000
        assert s.step() == total - done - 1, "a cancelled session keeps stepping"


def test_close_from_another_thread_waits_for_step(model):
    s = model.session(frames=470, steps=1000, seed=1, threads=1)
    s.set_prompt(REF_PROMPT)
    started = threading.Event()
    s.set_progress(lambda done, total: started.set())
    errors = []

    def worker():
        try:
            while True:
                s.step()
        except (FlameError, ValueError) as e:
            errors.append(e)

    t = threading.Thread(target=worker)
    t.start()
    assert started.wait(30)
    s.close()  # cancels, waits for the running step, frees
    t.join(30)
    assert not t.is_alive() and errors


# --- editing ----------------------------------------------------------------------------------


def test_editing(model, reference):
    motion = reference.copy()
    with ref_session(model) as s:
        s.set_reference(motion)
        s.set_mask(np.zeros((24, DIM), dtype=bool))  # keeps nothing: plain generation
        assert s.run().tobytes() == reference.tobytes()

        s.reset()
        s.keep_frames(0, 6)
        edited = s.run()
        assert not np.array_equal(edited, reference)
        s.reset()
        assert s.run().tobytes() == edited.tobytes(), "editing is deterministic"

        s.clear_edit()
        s.reset()
        assert s.run().tobytes() == reference.tobytes()

        s.set_reference(motion.ravel())  # flat input is accepted
        s.keep_joints([flame.ROOT_TRANSLATION, 0])
        s.reset()
        joints = s.run()
        assert not np.array_equal(joints, reference)
        s.keep_joints([])  # adds nothing

        mask = np.zeros((24, DIM), dtype=np.uint8)
        mask[:, 0:3] = 1
        mask[:, 3:9] = 1
        s.clear_edit()
        s.set_reference(motion)
        s.set_mask(mask)
        s.reset()
        assert s.run().tobytes() == joints.tobytes(), "keep_joints([-1, 0]) = that mask"


def test_cancel_mid_step_with_edit_then_retry_is_bit_identical(model):
    """Like test_cancel_from_callback_then_retry_is_bit_identical, but the cancel lands inside
    the denoiser call of an editing step (470 frames: a step takes tens of milliseconds)."""

    def generate(cancel_after_step=None):
        with model.session(frames=470, steps=12, sampler="ddim", seed=5, threads=1) as s:
            s.set_prompt(REF_PROMPT)
            s.set_reference(np.zeros((470, DIM), np.float32))
            s.keep_frames(0, 100)
            stepped = threading.Event()
            s.set_progress(lambda done, total: stepped.set() if done == cancel_after_step else None)
            if cancel_after_step:
                threading.Thread(target=lambda: (stepped.wait(), time.sleep(0.02), s.cancel())).start()
            cancelled = 0
            while s.steps_left:
                try:
                    s.step()
                except FlameError as e:
                    assert e.status == Status.CANCELLED
                    cancelled += 1
            return s.read(), cancelled

    expected, _ = generate()
    out, cancelled = generate(cancel_after_step=4)
    assert cancelled == 1
    assert out.tobytes() == expected.tobytes()


# --- threads ----------------------------------------------------------------------------------


def test_two_sessions_in_two_threads_match_sequential(model):
    jobs = [("a person walks forward and waves.", 3), ("a person jumps twice.", 11)]

    def generate(prompt, seed):
        with model.session(frames=48, steps=20, sampler="ddpm", seed=seed, threads=1) as s:
            s.set_prompt(prompt)
            return s.run()

    sequential = [generate(*j) for j in jobs]
    results = [None, None]

    def worker(i):
        results[i] = generate(*jobs[i])

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for seq, par in zip(sequential, results):
        assert par is not None and par.tobytes() == seq.tobytes()
    assert not np.array_equal(sequential[0], sequential[1])


def test_thread_count_does_not_change_output(model, reference):
    with ref_session(model, threads=2) as s:
        assert s.run().tobytes() == reference.tobytes()


# --- editing: parameters, tasks, body parts, pose references -------------------------------------

FIXTURES = ROOT / "tests/fixtures"


def smooth_reference(frames=24, dim=DIM):
    i = np.arange(frames * dim, dtype=np.float32)
    return (0.5 * np.sin(0.01 * i) + 0.25).astype(np.float32).reshape(frames, dim)


def test_edit_params_defaults_and_errors(model, reference):
    d = flame.edit_params_default()
    assert (d.method, d.paste, d.seam_frames) == (flame.EditMethod.AUTO, True, 4)
    assert np.float32(d.edit_till) == np.float32(0.2)
    assert flame.EditParams() == d
    with ref_session(model) as s:
        s.set_edit_params()
        s.set_edit_params(flame.EditParams(method="noised-reference", paste=False, seam_frames=0))
        s.set_edit_params(method=flame.EditMethod.REPLACE_X0, edit_till=1.0)
        expect_error(Status.INVALID_ARGUMENT, "does not apply", s.set_edit_params, method="rewrite-trajectory")
        expect_error(Status.INVALID_ARGUMENT, "edit method 4", s.set_edit_params, method=4)
        expect_error(Status.INVALID_ARGUMENT, "edit method -1", s.set_edit_params, method=-1)
        expect_error(Status.INVALID_ARGUMENT, "edit_till", s.set_edit_params, edit_till=float("nan"))
        expect_error(Status.INVALID_ARGUMENT, "edit_till", s.set_edit_params, edit_till=1.5)
        expect_error(Status.INVALID_ARGUMENT, "edit_till", s.set_edit_params, edit_till=-0.1)
        expect_error(Status.INVALID_ARGUMENT, "seam_frames", s.set_edit_params, seam_frames=1001)
        with pytest.raises(ValueError):
            s.set_edit_params(method="x0")
        with pytest.raises(TypeError):
            s.set_edit_params(steps=3)
        s.set_edit_params()
        assert s.run().tobytes() == reference.tobytes(), "settings alone edit nothing"


def test_edit_params_struct_size_through_ctypes(model):
    import ctypes

    lib = flame._lib()
    raw = flame._EditParams()
    assert lib.flame_edit_params_default(ctypes.byref(raw)) == Status.OK
    assert raw.struct_size == ctypes.sizeof(flame._EditParams) == 20
    with ref_session(model) as s:
        raw.struct_size = 8
        assert lib.flame_session_set_edit_params(s._h(), ctypes.byref(raw)) == Status.INVALID_ARGUMENT
        assert b"struct_size" in lib.flame_last_error()
        assert lib.flame_session_set_edit_params(s._h(), None) == Status.INVALID_ARGUMENT
        assert lib.flame_edit_params_default(None) == Status.INVALID_ARGUMENT


def test_task_masks_paste_kept_values(model):
    r = smooth_reference()
    quarter = slice(0, 6)
    with ref_session(model) as s:
        s.set_reference(r)
        s.set_task_mask("inbetween")
        x = s.run()
        assert x[:6].tobytes() == r[:6].tobytes() and x[18:].tobytes() == r[18:].tobytes()
        assert not np.array_equal(x[6:18], r[6:18])

        s.set_task_mask(flame.EditTask.PREDICT)  # replaces the mask
        s.reset()
        x = s.run()
        assert x[quarter].tobytes() == r[quarter].tobytes() and not np.array_equal(x[6:], r[6:])

        s.set_task_mask("path")
        s.reset()
        path = s.run()
        assert path[:, :3].tobytes() == r[:, :3].tobytes() and not np.array_equal(path[:, 3:], r[:, 3:])
        s.clear_edit()
        s.set_reference(r)
        s.keep_part("root-path")
        s.reset()
        assert s.run().tobytes() == path.tobytes(), "PATH = keep_part(ROOT_PATH) on every frame"

        s.set_task_mask(flame.EditTask.UPPER_BODY)
        s.reset()
        upper = s.run()
        lower = [0, 1, 2, 4, 5, 7, 8, 10, 11]  # pelvis and legs
        kept = np.r_[0:3, [3 + 6 * j + k for j in lower for k in range(6)]]
        assert upper[:, kept].tobytes() == r[:, kept].tobytes()

        s.set_edit_params(paste=False)
        s.set_task_mask("inbetween")
        s.reset()
        x = s.run()
        assert not np.array_equal(x[:6], r[:6]), "paste off: the kept values are only close"

        expect_error(Status.INVALID_ARGUMENT, "unknown editing task 4", s.set_task_mask, 4)
        with pytest.raises(ValueError):
            s.set_task_mask("dance")


def test_keep_part(model):
    r = smooth_reference()
    with ref_session(model) as s:
        s.set_reference(r)
        s.keep_part(flame.BodyPart.ARMS, 12)  # to the last frame
        x = s.run()
        arms = np.r_[[3 + 6 * j + k for j in (13, 14, 16, 17, 18, 19, 20, 21, 22, 23) for k in range(6)]]
        assert x[12:, arms].tobytes() == r[12:, arms].tobytes()
        assert not np.array_equal(x[:12, arms], r[:12, arms])
        for part in ("root-path", "lower_body", "UPPER-BODY", "legs", 3):
            s.keep_part(part, 0, 24)
        expect_error(Status.INVALID_ARGUMENT, "unknown body part 5", s.keep_part, 5)
        expect_error(Status.INVALID_ARGUMENT, "unknown body part -1", s.keep_part, -1)
        expect_error(Status.INVALID_ARGUMENT, "from 3 to 3", s.keep_part, "arms", 3, 3)
        expect_error(Status.INVALID_ARGUMENT, "from 0 to 25", s.keep_part, "arms", 0, 25)
        with pytest.raises(ValueError):
            s.keep_part("tail")


def test_mask_without_reference_and_short_reference(model):
    r = smooth_reference()
    with ref_session(model) as s:
        s.set_task_mask("path")
        expect_error(Status.WRONG_STATE, "no reference", s.step)
        s.clear_edit()
        s.set_reference(r[:6])  # a shorter reference: its frames can be kept
        expect_error(Status.INVALID_ARGUMENT, "keeps frame 6", s.keep_frames, 0, 7)
        expect_error(Status.INVALID_ARGUMENT, "keeps frame", s.set_task_mask, "inbetween")
        s.set_task_mask("predict")
        x = s.run()
        assert x[:6].tobytes() == r[:6].tobytes()
    with ref_session(model) as s:
        s.keep_frames(0, 24)
        expect_error(Status.INVALID_ARGUMENT, "keeps frame 6", s.set_reference, r[:6])


def test_reference_poses_round_trip(model):
    """set_reference_poses is read()'s inverse (poses of a generic, one-step sample: the tiny
    model's final motions hold degenerate 6D rotations)."""
    with ref_session(model) as g:
        g.step()
        root = g.read("sample", Layout.ROOT_TRANSLATION, Convention.UNITY)
        rot6d = g.read("sample", Layout.LOCAL_6D, Convention.UNITY)
        results = {}
        for layout in (Layout.LOCAL_6D, Layout.LOCAL_QUAT_XYZW, Layout.LOCAL_QUAT_WXYZ, Layout.LOCAL_MATRIX):
            rotations = g.read("sample", layout, Convention.UNITY)
            with ref_session(model) as s:
                s.set_reference_poses(root, rotations, layout, Convention.UNITY)
                s.keep_frames(0, 24)
                results[layout] = s.run()
                np.testing.assert_allclose(s.read("sample", Layout.ROOT_TRANSLATION, Convention.UNITY), root, atol=1e-4)
                np.testing.assert_allclose(s.read("sample", Layout.LOCAL_6D, Convention.UNITY), rot6d, atol=1e-4)
        for x in results.values():
            np.testing.assert_allclose(x, results[Layout.LOCAL_6D], atol=1e-4)
        # features -> poses -> features
        with ref_session(model) as s:
            s.set_reference(results[Layout.LOCAL_6D])
            s.keep_frames(0, 24)
            x = s.run()
            again_root = s.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF)
            again_rot = s.read("sample", Layout.LOCAL_QUAT_WXYZ, Convention.GLTF)
        with ref_session(model) as s:
            s.set_reference_poses(again_root, again_rot, Layout.LOCAL_QUAT_WXYZ, Convention.GLTF)
            s.keep_frames(0, 24)
            np.testing.assert_allclose(s.run(), x, atol=1e-4)
            expect_error(Status.INVALID_ARGUMENT, "layout", s.set_reference_poses, root, rot6d, Layout.GLOBAL_QUAT_XYZW)
            expect_error(Status.INVALID_ARGUMENT, "convention", s.set_reference_poses, root, rot6d, Layout.LOCAL_6D, 6)
            expect_error(Status.INVALID_ARGUMENT, "rotations", s.set_reference_poses, root, rot6d, Layout.LOCAL_QUAT_XYZW)
            expect_error(Status.INVALID_ARGUMENT, "between 1 and 24 (the session's frames), got 25", s.set_reference_poses,
                         np.zeros((25, 3)), np.zeros((25, 24, 6)), Layout.LOCAL_6D)
            bad = root.copy()
            bad[2, 1] = np.nan
            expect_error(Status.INVALID_ARGUMENT, "not finite", s.set_reference_poses, bad, rot6d, Layout.LOCAL_6D)
            with pytest.raises(ValueError):
                s.set_reference_poses(np.zeros(5), rot6d, Layout.LOCAL_6D)


def test_editing_other_families():
    """MDM (humanml263): keep_joints and parts; Motion Flow Matching: trajectory rewriting. The
    fixtures' text towers are placeholders: prompts encode, meaninglessly."""
    with flame.Model.load(FIXTURES / "mdm_tiny.safetensors") as mdm, \
            mdm.session(frames=16, steps=3, sampler="ddim", seed=1, threads=1) as s:
        d = mdm.info.feature_dim
        r = smooth_reference(16, d)
        s.set_prompt(REF_PROMPT)
        s.set_reference(r)
        s.keep_joints([flame.ROOT_TRANSLATION])
        x = s.run()
        assert x[:, :4].tobytes() == r[:, :4].tobytes() and not np.array_equal(x[:, 4:], r[:, 4:])
        s.clear_edit()
        s.set_reference(r)
        s.keep_part("root-path")
        s.reset()
        assert s.run().tobytes() == x.tobytes(), "keep_joints([ROOT]) = the root path"
        expect_error(Status.INVALID_ARGUMENT, "joint 22", s.keep_joints, [22])
        expect_error(Status.INVALID_ARGUMENT, "does not apply", s.set_edit_params, method="rewrite-trajectory")
        expect_error(Status.INVALID_ARGUMENT, "smpl24_6d", s.set_reference_poses,
                     np.zeros((1, 3)), np.tile([1, 0, 0, 0], (1, 24, 1)), Layout.LOCAL_QUAT_WXYZ)
    with flame.Model.load(FIXTURES / "motionfm_tiny.safetensors") as fm, \
            fm.session(frames=16, steps=4, seed=1, threads=1) as s:
        r = smooth_reference(16, fm.info.feature_dim)
        expect_error(Status.INVALID_ARGUMENT, "does not apply", s.set_edit_params, method="noised-reference")
        s.set_edit_params(method="rewrite-trajectory", edit_till=0.5)
        s.set_prompt(REF_PROMPT)
        s.set_reference(r)
        s.set_task_mask("predict")
        x = s.run()
        assert x[:4].tobytes() == r[:4].tobytes() and not np.array_equal(x[4:], r[4:])


# --- position targets ---------------------------------------------------------------------------

TARGET_SETTINGS = dict(frames=16, steps=20, sampler="ddim", guidance=2.5, seed=7, threads=1)


def target_session(model):
    s = model.session(**TARGET_SETTINGS)
    s.set_prompt("a person walks forward.")
    return s


def pelvis_path(unguided):
    """From where the unguided pelvis starts, a line across the ground in the Unreal convention
    (Z up, centimetres: +5 cm in X, -4 cm in Y per frame) at the unguided height; every other
    joint NaN (free)."""
    frames = unguided.shape[0]
    t = np.full(unguided.shape, np.nan, dtype=np.float32)
    f = np.arange(frames, dtype=np.float32)
    t[:, 0, 0] = unguided[0, 0, 0] + 5.0 * f
    t[:, 0, 1] = unguided[0, 0, 1] - 4.0 * f
    t[:, 0, 2] = unguided[:, 0, 2]
    return t


def median_pelvis_error(positions, target):
    return float(np.median(np.linalg.norm(positions[:, 0] - target[:, 0], axis=1)))


def test_position_targets_steer(model):
    with target_session(model) as plain:
        unguided = plain.run()
        p_unguided = plain.read("sample", Layout.GLOBAL_POSITIONS, Convention.UNREAL)
    target = pelvis_path(p_unguided)
    with target_session(model) as s:
        s.set_position_targets(target, convention=Convention.UNREAL)
        expect_error(Status.WRONG_STATE, "no step has been guided", s.target_loss)
        guided = s.run()
        loss = s.target_loss()
        assert np.isfinite(loss) and loss > 0
        p_guided = s.read("sample", Layout.GLOBAL_POSITIONS, Convention.UNREAL)
        before, after = median_pelvis_error(p_unguided, target), median_pelvis_error(p_guided, target)
        assert before > 5.0, before  # centimetres: the path is off the unguided motion
        assert after < 0.5 * before, (before, after)
        # reset replays it; cleared targets then reset: the unguided run, bit for bit
        s.reset()
        expect_error(Status.WRONG_STATE, "guided", s.target_loss)
        assert s.run().tobytes() == guided.tobytes()
        s.clear_position_targets()
        expect_error(Status.WRONG_STATE, "guided", s.target_loss)
        s.reset()
        assert s.run().tobytes() == unguided.tobytes()
    # scale 0: the unguided run, bit for bit, and no loss
    with target_session(model) as s:
        s.set_position_targets(target.reshape(-1), convention=Convention.UNREAL)  # flat
        s.set_target_params(scale=0.0, schedule="constant")
        assert s.run().tobytes() == unguided.tobytes()
        expect_error(Status.WRONG_STATE, "guided", s.target_loss)
    # the same constraint as a mask (free values arbitrary) = the NaN form
    with target_session(model) as s:
        mask = ~np.isnan(target)
        s.set_position_targets(np.where(mask, target, 123.0), mask=mask, convention=Convention.UNREAL)
        # this family's session defaults
        assert s.target_params() == (pytest.approx(0.6), flame.TargetSchedule.CONSTANT)
        s.set_target_params(scale=0.6, schedule=flame.TargetSchedule.CONSTANT)
        assert s.run().tobytes() == guided.tobytes()
        s.set_target_params(schedule="mpgd")
        s.reset()
        mpgd = s.run()
        assert mpgd.tobytes() not in (guided.tobytes(), unguided.tobytes())


def test_task_targets(model):
    with target_session(model) as plain:
        reference = plain.run()
    with target_session(model) as s:
        for task in ("path", "upper-body", "inbetween", "predict"):
            s.set_task_targets(reference, task)
            s.reset()
            s.run()
            loss = s.target_loss()
            assert np.isfinite(loss) and loss >= 0, (task, loss)
        expect_error(Status.INVALID_ARGUMENT, "reference shape", s.set_task_targets,
                     np.zeros((s.frames + 1, s.feature_dim), np.float32), "path")
        bad = reference.copy()
        bad[0, 0] = np.nan
        expect_error(Status.INVALID_ARGUMENT, "not finite", s.set_task_targets, bad, "path")
        with pytest.raises((ValueError, FlameError)):
            s.set_task_targets(reference, "fly")


def test_position_target_errors(model):
    j = model.info.joint_count
    t = np.full((2, j, 3), 0.1, dtype=np.float32)
    with target_session(model) as s:
        bad = t.copy()
        bad[1, 5, 1] = np.nan
        mask = np.ones(t.shape, dtype=bool)
        expect_error(Status.INVALID_ARGUMENT, "frame 1, joint 5, axis 1 is NaN but constrained",
                     s.set_position_targets, bad, mask)
        mask[1, 5, 1] = False
        s.set_position_targets(bad, mask)  # masked out: its value does not matter
        bad[0, 2, 1] = np.inf
        expect_error(Status.INVALID_ARGUMENT, "frame 0, joint 2, axis 1 is inf but constrained",
                     s.set_position_targets, bad)
        expect_error(Status.INVALID_ARGUMENT, "multiple of 72", s.set_position_targets, t.reshape(-1)[:-1])
        expect_error(Status.INVALID_ARGUMENT, "hold 0 values", s.set_position_targets, np.zeros(0))
        expect_error(Status.INVALID_ARGUMENT, "the target mask has 143 flags",
                     s.set_position_targets, t, np.ones(143))
        expect_error(Status.INVALID_ARGUMENT, "the target mask has 0 flags",
                     s.set_position_targets, t, np.ones(0))
        expect_error(Status.INVALID_ARGUMENT, "constrain nothing", s.set_position_targets, t, np.zeros(t.shape))
        expect_error(Status.INVALID_ARGUMENT, "constrain nothing", s.set_position_targets, np.full(t.shape, np.nan))
        expect_error(Status.INVALID_ARGUMENT, "cover 17 frames; the session has 16",
                     s.set_position_targets, np.zeros((17, j, 3)))
        expect_error(Status.INVALID_ARGUMENT, "convention", s.set_position_targets, t, convention=6)
        with pytest.raises(ValueError):
            s.set_position_targets(np.zeros((2, j - 1, 3)))
        with pytest.raises(ValueError):
            s.set_position_targets(np.zeros((2, j * 3)))
        for scale in (-0.1, float("nan"), 100.5, float("inf")):
            expect_error(Status.INVALID_ARGUMENT, "target scale", s.set_target_params, scale=scale)
        expect_error(Status.INVALID_ARGUMENT, "unknown target schedule 2", s.set_target_params, schedule=2)
        expect_error(Status.INVALID_ARGUMENT, "unknown target schedule -1", s.set_target_params, schedule=-1)
        with pytest.raises(ValueError):
            s.set_target_params(schedule="linear")
        s.set_target_params(scale=0.0)
        s.set_target_params(scale=100.0, schedule="CONSTANT")
        s.clear_position_targets()
        s.clear_position_targets()


def test_target_params_struct_through_ctypes(model):
    import ctypes

    lib = flame._lib()
    raw = flame._TargetParams()
    assert lib.flame_target_params_default(ctypes.byref(raw)) == Status.OK
    assert raw.struct_size == ctypes.sizeof(flame._TargetParams) == 12
    assert raw.scale == np.float32(0.6) and raw.schedule == flame.TargetSchedule.MPGD
    assert lib.flame_target_params_default(None) == Status.INVALID_ARGUMENT
    with target_session(model) as s:
        raw.struct_size = 8
        assert lib.flame_session_set_target_params(s._h(), ctypes.byref(raw)) == Status.INVALID_ARGUMENT
        assert b"struct_size" in lib.flame_last_error()
        assert lib.flame_session_set_target_params(s._h(), None) == Status.INVALID_ARGUMENT
        assert lib.flame_session_set_position_targets(s._h(), None, 72, None, 0, 0) == Status.INVALID_ARGUMENT
        assert b"`targets` is NULL" in lib.flame_last_error()
        t = np.zeros(72, dtype=np.float32)
        assert lib.flame_session_set_position_targets(
            s._h(), flame._ptr(t, ctypes.c_float), 72, None, 72, 0) == Status.INVALID_ARGUMENT
        assert b"`mask` is NULL" in lib.flame_last_error()
        assert lib.flame_session_target_loss(s._h(), None) == Status.WRONG_STATE
    assert lib.flame_session_clear_position_targets(None) == Status.INVALID_ARGUMENT


# --- the sampled space and the frames of a read (ABI 2) ---------------------------------------
# The families that sample the motion itself: the sampled space is frames × feature_dim and a
# read has the session's frames (the latent model's tests follow).


@pytest.mark.parametrize(
    "name, dim, joints, sampler",
    [("flame_tiny.safetensors", DIM, 24, "ddim"), ("mdm_tiny.safetensors", 263, 22, "ddim"),
     ("motionfm_tiny.safetensors", None, None, "euler")],
)
def test_sample_shape_and_read_frames(name, dim, joints, sampler):
    with flame.Model.load(FIXTURES / name) as m, \
            m.session(frames=12, steps=2, sampler=sampler, seed=1, threads=1) as s:
        i = m.info
        dim = dim or i.feature_dim
        assert i.feature_dim == dim and (joints is None or i.joint_count == joints)
        assert (i.latent, i.sample_dim) == (False, dim)
        assert (m.latent, m.sample_dim) == (False, dim)
        assert s.sample_shape == (12, dim)
        expect_error(Status.WRONG_STATE, "no sample yet", s.read_frames)
        expect_error(Status.WRONG_STATE, "no clean-motion estimate", s.read_frames, "estimate")
        expect_error(Status.INVALID_ARGUMENT, "unknown `which` 2", s.read_frames, 2)
        with pytest.raises(ValueError):
            s.read_frames("noisy")
        noise = np.random.default_rng(2).standard_normal((12, dim)).astype(np.float32)
        # The same number of values in another 2-D shape is refused by the binding...
        with pytest.raises(ValueError, match=r"\[12, %d\]" % dim):
            s.set_noise(noise.T)
        # ... a flat array of another length by libflame.
        expect_error(Status.INVALID_ARGUMENT, "12 rows", s.set_noise, noise.ravel()[:-1])
        s.set_noise(noise.ravel())
        s.set_prompt(REF_PROMPT)
        s.step()
        assert s.read_frames() == s.read_frames("estimate") == s.read_frames(flame.Which.SAMPLE) == 12
        assert s.read().shape == (12, dim)
        assert s.read("estimate", Layout.GLOBAL_POSITIONS).shape == (12, i.joint_count, 3)
        s.reset()
        expect_error(Status.WRONG_STATE, "no sample yet", s.read_frames)
        assert s.sample_shape == (12, dim)
    with flame.Model.load(FIXTURES / name) as m, m.session(sampler=sampler, steps=1) as s:
        assert s.sample_shape == (m.info.default_frames, dim)  # frames=None: the model's default


def test_read_is_shaped_by_the_frames_libflame_reports(model, reference):
    """read() shapes by flame_session_read_frames, not by the frames the session was made with
    (a latent model's decoder decides its own length): a wrong Session.frames changes nothing."""
    with ref_session(model) as s:
        s.run()
        s.frames = 5
        out = s.read()
        assert out.shape == (24, DIM) and out.tobytes() == reference.tobytes()
        assert s.read("sample", Layout.LOCAL_QUAT_XYZW).shape == (24, 24, 4)


# --- a latent model (MoLA): tests/fixtures/mola_tiny.safetensors ------------------------------
# Random weights; a CLIP text tower of one layer, so prompts encode, meaninglessly. 60 frames
# are a latent of 60 / 4 + 1 = 16 rows of 16 channels (tests/fixtures/mola_expected.json:
# frames 60, latent_frames 16); its VAE decoder writes 4 × 16 = 64 frames and cuts them to the
# valid length at its flag (at least 10, at most 63). Reference: the `flame generate` CLI.

MOLA = FIXTURES / "mola_tiny.safetensors"
MOLA_SETTINGS = dict(frames=60, steps=4, sampler="ddim", seed=3, threads=1)


def mola_cli(tmp_path, noise=None, prompt=REF_PROMPT):
    s = MOLA_SETTINGS
    cmd = [cli_path(), "generate", "--model", str(MOLA), "--prompt", prompt,
           "--frames", str(s["frames"]), "--steps", str(s["steps"]), "--sampler", s["sampler"],
           "--seed", str(s["seed"]), "--threads", str(s["threads"]), "--out", str(tmp_path / "out.npy")]
    if noise is not None:
        np.save(tmp_path / "noise.npy", noise)
        cmd += ["--noise", str(tmp_path / "noise.npy")]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return np.load(tmp_path / "out.npy"), done.stdout + done.stderr


@pytest.fixture(scope="module")
def mola():
    with flame.Model.load(MOLA) as m:
        yield m


def test_latent_model_info(mola):
    i = mola.info
    assert (i.architecture, i.motion_format, i.feature_dim, i.joint_count) == ("mola", "humanml263", 263, 22)
    assert (i.latent, i.sample_dim) == (True, 16)
    assert (mola.latent, mola.sample_dim) == (True, 16)
    with mola.session(**MOLA_SETTINGS) as s:
        assert s.sample_shape == (16, 16)
    with mola.session(steps=1) as s:
        assert s.sample_shape == (i.default_frames // 4 + 1, 16)  # 196 frames: 50 rows


@pytest.mark.parametrize("noise_seed", [None, 1, 4])
def test_latent_read_matches_cli(mola, tmp_path, noise_seed):
    """The frames of a read are the decoder's, not the session's: read() is the CLI's output,
    bit for bit, with its frame count, and every layout has read_frames() frames."""
    noise = None
    if noise_seed is not None:
        noise = np.random.default_rng(noise_seed).standard_normal((16, 16)).astype(np.float32)
    expected, log = mola_cli(tmp_path, noise)
    assert f"{expected.shape[0]} frames (the length the model's decoder chose; 60 asked)" in log
    with mola.session(**MOLA_SETTINGS) as s:
        if noise is not None:
            s.set_noise(noise)
        s.set_prompt(REF_PROMPT)
        out = s.run()
        frames = s.read_frames()
        assert out.dtype == np.float32 and out.shape == expected.shape == (frames, 263)
        assert out.tobytes() == expected.tobytes()
        assert 10 <= frames <= 63
        assert frames != 60  # the session's frames would give another shape (these decode to 63, 11)
        assert s.read("sample", Layout.GLOBAL_POSITIONS).shape == (frames, 22, 3)
        assert s.read("sample", Layout.FOOT_CONTACTS).shape == (frames, 4)
        est = s.read("estimate")
        assert est.shape == (s.read_frames("estimate"), 263) and np.isfinite(est).all()


def test_latent_noise_and_editing_errors(mola):
    with mola.session(**MOLA_SETTINGS) as s:
        with pytest.raises(ValueError, match=r"\[16, 16\]"):
            s.set_noise(np.zeros((60, 263)))  # the motion's shape is not the sampled space
        expect_error(Status.INVALID_ARGUMENT, "16 rows", s.set_noise, np.zeros(60 * 263))
        expect_error(Status.WRONG_STATE, "no sample yet", s.read_frames)
        expect_error(Status.INVALID_ARGUMENT, "samples a latent", s.set_reference, np.zeros((60, 263)))
        expect_error(Status.INVALID_ARGUMENT, "samples a latent", s.set_mask, np.ones((60, 263)))


def test_latent_read_after_reset_is_the_new_generation(mola):
    noise = np.random.default_rng(4).standard_normal((16, 16)).astype(np.float32)
    with mola.session(**MOLA_SETTINGS) as s, mola.session(**MOLA_SETTINGS) as fresh:
        s.set_prompt(REF_PROMPT)
        s.step()
        s.read()
        s.reset()
        s.set_noise(noise)
        s.step()
        fresh.set_prompt(REF_PROMPT)
        fresh.set_noise(noise)
        fresh.step()
        assert s.read().tobytes() == fresh.read().tobytes()


# --- loops made by the session (looped, ABI 4) ------------------------------------------------
# A loop session samples twice (a generation, then an edit of it across the wrap); the finished
# sample reads as the cycle. Reference: `flame generate --loop --feet off --ground off
# --positions` (as tests/c/run.sh's loop_positions and test_cleanup.c's test_loop).

LOOP_SETTINGS = dict(frames=40, steps=4, sampler="ddim", seed=5, threads=1)


def loop_cli_positions(out_dir: Path) -> np.ndarray:
    s = LOOP_SETTINGS
    positions = out_dir / "loop_positions.npy"
    cmd = [cli_path(), "generate", "--model", MODEL, "--prompt", REF_PROMPT,
           "--frames", str(s["frames"]), "--steps", str(s["steps"]), "--sampler", s["sampler"],
           "--seed", str(s["seed"]), "--threads", str(s["threads"]), "--loop", "--feet", "off",
           "--ground", "off", "--positions", str(positions), "--out", str(out_dir / "loop.json")]
    subprocess.run(cmd, check=True, capture_output=True)
    return np.load(positions)


def test_session_params_struct_through_ctypes():
    """libflame writes sizeof(FlameSessionParams) into struct_size (and the whole struct): the
    ctypes mirror must be as large, `looped` after `respacing`."""
    raw = flame._SessionParams()
    assert flame._lib().flame_session_params_default(ctypes.byref(raw)) == Status.OK
    assert raw.struct_size == ctypes.sizeof(flame._SessionParams)
    fields = flame._SessionParams
    assert fields.looped.offset == fields.respacing.offset + ctypes.sizeof(ctypes.c_void_p)
    assert raw.looped == 0 and not raw.respacing
    if ctypes.sizeof(ctypes.c_void_p) == 8:
        assert (raw.struct_size, fields.looped.offset) == (56, 48)


def test_loop_session_matches_cli(model, tmp_path):
    cli = loop_cli_positions(tmp_path)
    assert cli.shape == (40, 24, 3) and cli.dtype == np.float32
    seen = []
    with model.session(**LOOP_SETTINGS, looped=True) as s:
        assert s.looped and s.frames == 40  # the cycle asked for
        s.set_prompt(REF_PROMPT)
        s.set_progress(lambda done, total: seen.append((done, total)))
        # Both passes: 8 steps, counted down across the edit.
        assert s.progress == (0, 8) and s.steps_left == 8
        assert [s.step() for _ in range(8)] == list(range(7, -1, -1))
        assert s.progress == (8, 8)
        assert seen == [(k, 8) for k in range(1, 9)]
        # The cycle's frames; the raw features without the next cycle's first frame.
        assert s.read_frames() == 40
        features = s.read()
        assert features.shape == (40, DIM) and np.isfinite(features).all()
        # A read with no cleanup still wraps: what the CLI wrote, bit for bit.
        pos = s.read("sample", Layout.GLOBAL_POSITIONS, Convention.NATIVE, ReadFlags.SMOOTH)
        assert pos.shape == (40, 24, 3)
        assert pos.tobytes() == cli.tobytes()
        # The loop's edit is its own.
        expect_error(Status.INVALID_ARGUMENT, "its own edit", s.set_reference, np.zeros((1, DIM)))


def test_loop_session_refusals(model):
    expect_error(Status.INVALID_ARGUMENT, "at least 40 frames", model.session,
                 **{**LOOP_SETTINGS, "frames": 12}, looped=True)
    with flame.Model.load(MOLA) as mola:
        expect_error(Status.INVALID_ARGUMENT, "samples a latent", mola.session,
                     **{**LOOP_SETTINGS, "frames": 60}, looped=True)
        with mola.session(**{**LOOP_SETTINGS, "frames": 60}) as plain:  # looped=False: fine
            assert not plain.looped and plain.progress == (0, 4)
    # looped=False is the plain session of before (4 steps).
    with model.session(**LOOP_SETTINGS) as plain:
        assert not plain.looped and plain.progress == (0, 4)


# --- prompts per time stage ------------------------------------------------------------------

STAGE_SETTINGS = dict(frames=16, steps=3, sampler="ddim", seed=5, threads=1)


@pytest.fixture(scope="module")
def mdm():
    with flame.Model.load(FIXTURES / "mdm_tiny.safetensors") as m:
        yield m


def mdm_run(mdm, set_prompt):
    with mdm.session(**STAGE_SETTINGS) as s:
        set_prompt(s)
        assert s.sample_shape == (16, 263)
        return s.run()


def test_stage_fields_match_the_header():
    import re

    body = re.search(r"typedef struct FlameStage \{(.*?)\} FlameStage;", HEADER, re.S).group(1)
    fields = re.findall(r"^\s*(?:const )?\w+ \*?(\w+);", body, re.M)
    assert fields == [name for name, _ in flame._Stage._fields_]
    assert [f.name for f in dataclasses.fields(flame.Stage)] == ["text", "frames", *fields[3:]]


def test_one_stage_is_the_prompt(mdm):
    """A model that takes one prompt (MDM): one stage without part texts is set_prompt with its
    text, bit for bit; empty part texts are none."""
    plain = mdm_run(mdm, lambda s: s.set_prompt(REF_PROMPT))
    staged = mdm_run(mdm, lambda s: s.set_prompt_stages([flame.Stage(REF_PROMPT, 16)]))
    assert staged.tobytes() == plain.tobytes()
    empty = flame.Stage(REF_PROMPT, 16, head="", left_arm="", pelvis="")
    assert mdm_run(mdm, lambda s: s.set_prompt_stages([empty])).tobytes() == plain.tobytes()
    other = mdm_run(mdm, lambda s: s.set_prompt_stages([flame.Stage("a person jumps", 16)]))
    assert other.tobytes() != plain.tobytes()


@pytest.mark.parametrize("name, arch", [("mdm_tiny.safetensors", "mdm"), ("flame_tiny.safetensors", "flame")])
def test_stages_refused_by_one_prompt_families(name, arch):
    with flame.Model.load(FIXTURES / name) as m, m.session(frames=16, steps=2, threads=1) as s:
        two = [flame.Stage("a person walks", 8), flame.Stage("a person jumps", 8)]
        e = expect_error(Status.INVALID_ARGUMENT, "a single stage without part texts", s.set_prompt_stages, two)
        assert f"this {arch} model" in e.message
        expect_error(Status.INVALID_ARGUMENT, "a single stage without part texts", s.set_prompt_stages,
                     [flame.Stage("a person walks", 16, right_arm="waves")])
        expect_error(Status.WRONG_STATE, "prompt", s.step)  # nothing was set


def test_stage_errors(mdm):
    with mdm.session(**STAGE_SETTINGS) as s:
        expect_error(Status.INVALID_ARGUMENT, "0 stages", s.set_prompt_stages, [])
        expect_error(Status.INVALID_ARGUMENT, "`stages[0].text` is NULL", s.set_prompt_stages,
                     [flame.Stage(None, 16)])
        expect_error(Status.INVALID_ARGUMENT, "stage 0 has no text", s.set_prompt_stages, [flame.Stage(" ", 16)])
        expect_error(Status.INVALID_ARGUMENT, "stage 1 has 0 frames", s.set_prompt_stages,
                     [flame.Stage("a", 16), flame.Stage("b", 0)])
        expect_error(Status.INVALID_ARGUMENT, "the stages cover 15 frames, the session has 16",
                     s.set_prompt_stages, [flame.Stage(REF_PROMPT, 15)])
        with pytest.raises(ValueError, match="NUL"):
            s.set_prompt_stages([flame.Stage("a\0b", 16)])
        with pytest.raises(ValueError, match="uint32"):
            s.set_prompt_stages([flame.Stage(REF_PROMPT, -1)])
        with pytest.raises(TypeError, match="flame.Stage"):
            s.set_prompt_stages([(REF_PROMPT, 16)])
        with pytest.raises(TypeError, match="head"):
            s.set_prompt_stages([flame.Stage(REF_PROMPT, 16, head=3)])
        # A failed call changes nothing: still the prompt set before it.
        s.set_prompt(REF_PROMPT)
        expect_error(Status.INVALID_ARGUMENT, "add up", s.set_prompt_stages, [flame.Stage(REF_PROMPT, 17)])
        x = s.run()
    assert x.tobytes() == mdm_run(mdm, lambda s: s.set_prompt(REF_PROMPT)).tobytes()


def test_stage_struct_size_through_ctypes(mdm):
    """A caller built against a newer header passes a larger FlameStage: accepted, the same
    generation; one smaller than the struct is refused."""
    import ctypes

    class Newer(ctypes.Structure):
        _fields_ = [("stage", flame._Stage), ("future", ctypes.c_uint64 * 2)]

    plain = mdm_run(mdm, lambda s: s.set_prompt(REF_PROMPT))
    for size, ok in ((ctypes.sizeof(Newer), True), (ctypes.sizeof(flame._Stage) - 8, False)):
        raw = Newer()
        raw.future[0] = raw.future[1] = 0xA5A5A5A5A5A5A5A5
        text = REF_PROMPT.encode()
        raw.stage.struct_size, raw.stage.frames, raw.stage.text = size, 16, text
        with mdm.session(**STAGE_SETTINGS) as s:
            status = flame._lib().flame_session_set_prompt_stages(
                s._h(), ctypes.cast(ctypes.pointer(raw), ctypes.POINTER(flame._Stage)), 1)
            if ok:
                assert status == Status.OK
                assert s.run().tobytes() == plain.tobytes()
            else:
                assert status == Status.INVALID_ARGUMENT
                assert b"struct_size" in flame._lib().flame_last_error()


FMG_MODEL = FIXTURES / "finemogen_tiny.safetensors"
FMG_STAGES = [("a person walks forward", 24), ("a person jumps", 31)]
FMG_SETTINGS = dict(frames=55, steps=4, sampler="ddim", seed=1, threads=1)


@pytest.mark.skipif(not FMG_MODEL.is_file(), reason="no tests/fixtures/finemogen_tiny.safetensors")
def test_finemogen_stages(tmp_path):
    """FineMoGen composes the stages: 2 × 31 sample rows, 55 frames read back, the CLI's
    --stage output bit for bit; stage frame counts are fixed once stepping started."""
    out = tmp_path / "stages.npy"
    cmd = [cli_path(), "generate", "--model", str(FMG_MODEL), "--frames", "55", "--steps", "4",
           "--sampler", "ddim", "--seed", "1", "--threads", "1", "--out", str(out)]
    for text, frames in FMG_STAGES:
        cmd += ["--stage", f"{text}@{frames}"]
    subprocess.run(cmd, check=True, capture_output=True)
    expected = np.load(out)
    with flame.Model.load(FMG_MODEL) as m, m.session(**FMG_SETTINGS) as s:
        assert s.sample_shape == (55, 263)
        s.set_prompt_stages([flame.Stage(t, f) for t, f in FMG_STAGES])
        assert s.sample_shape == (2 * 31, 263)
        x = s.run()
        assert x.shape == (55, 263) and np.isfinite(x).all()
        assert s.read_frames() == 55
        assert x.tobytes() == expected.tobytes()
        # Part texts change the motion.
        s.set_prompt_stages([flame.Stage(FMG_STAGES[0][0], 24, left_arm="raises the left arm"),
                             flame.Stage(*FMG_STAGES[1])])
        s.reset()
        parts = s.run()
        assert np.isfinite(parts).all() and parts.tobytes() != x.tobytes()
        # After the first step: new texts yes, new frame counts no (until a reset).
        s.reset()
        s.step()
        expect_error(Status.WRONG_STATE, "before the first step", s.set_prompt_stages,
                     [flame.Stage("a person walks", 25), flame.Stage("a person jumps", 30)])
        s.set_prompt_stages([flame.Stage("a person jumps", 24), flame.Stage("a person walks", 31)])
        s.reset()
        s.set_prompt_stages([flame.Stage("a person walks", 25), flame.Stage("a person jumps", 30)])
        assert s.sample_shape == (2 * 30, 263)


# --- cleanup (flame_session_read_cleaned) ----------------------------------------------------
# A 40-frame motion of the smpl24 fixture at its 20 fps, read after two of ten steps (generic
# poses: the tiny model's final motion saturates, see test_pose_layouts). No Rust result is at
# hand here, so the tests check what a cleanup promises: exact frames kept by a resample, zero
# horizontal travel in place, a root bone that carries exactly the travel the pelvis lost.

CLEAN_FRAMES = 40
# Convention.GLTF: Y up, so x and z are the horizontal axes.
HORIZONTAL = [0, 2]


@pytest.fixture(scope="module")
def stepped40(model):
    with model.session(frames=CLEAN_FRAMES, steps=10, sampler="ddim", seed=5, threads=1) as s:
        s.set_prompt(REF_PROMPT)
        s.step()
        s.step()
        yield s


def _rust_enum(name):
    """{variant: value} of a `#[repr(C)] pub enum` in src/ffi/cleanup.rs (the header does not
    list the cleanup enums: no C function takes them by type)."""
    import re

    src = (ROOT / "src/ffi/cleanup.rs").read_text()
    body = re.search(r"pub enum %s \{(.*?)\n\}" % name, src, re.S).group(1)
    return {_key(n): int(v) for n, v in re.findall(r"^\s*(\w+) = (\d+),", body, re.M)}


def test_cleanup_values_match_the_library():
    assert _rust_enum("FlameFeet") == {_key(n): v for n, v in vars(flame.Feet).items() if n.isupper()}
    assert _rust_enum("FlameRootMotion") == {
        _key(n): v for n, v in vars(flame.RootMotion).items() if n.isupper()}
    assert "FLAME_LAYOUT_ROOT_BONE = 10," in HEADER and Layout.ROOT_BONE == 10
    # The dataclass's defaults are flame_cleanup_params_default's (game-ready).
    assert flame.Cleanup() == flame.cleanup_params_default()
    assert flame.cleanup_params_default() == flame.Cleanup(
        feet=flame.Feet.LOCK, ground=True, root_motion=flame.RootMotion.KEEP, remove_yaw=False,
        wrap=False, fps=0.0, contact_height=0.05, contact_speed=0.8944272, contact_release=1.5,
        contact_min_span=0.1)
    # The struct's layout: eleven 4-byte fields; FlameGltfParams ends with the cleanup pointer.
    assert ctypes.sizeof(flame._CleanupParams) == 44
    assert flame._GltfParams.cleanup.offset == 24 and ctypes.sizeof(flame._GltfParams) == 32


POSE_LAYOUTS = (Layout.ROOT_TRANSLATION, Layout.LOCAL_QUAT_XYZW, Layout.LOCAL_MATRIX,
                Layout.GLOBAL_POSITIONS)


def test_cleanup_off_is_the_raw_read(stepped40):
    raw_off = flame.Cleanup.raw()
    for layout in POSE_LAYOUTS + (Layout.FEATURES,):
        raw = stepped40.read("sample", layout, Convention.GLTF)
        assert stepped40.read("sample", layout, Convention.GLTF, cleanup=raw_off).tobytes() == raw.tobytes()
        # The model's own frame rate asked for explicitly: no resample either.
        assert stepped40.read("sample", layout, Convention.GLTF,
                              cleanup=flame.Cleanup.raw(fps=20)).tobytes() == raw.tobytes()
    # Features are never post-processed, whatever the cleanup.
    assert stepped40.read(cleanup=flame.Cleanup(fps=30, root_motion="separate")).tobytes() == \
        stepped40.read().tobytes()


def test_cleanup_fps_resamples_keeping_common_frames(model, stepped40):
    assert model.info.fps == 20
    thirty = flame.Cleanup.raw(fps=30)
    for layout in POSE_LAYOUTS:
        raw = stepped40.read("sample", layout, Convention.GLTF)
        out = stepped40.read("sample", layout, Convention.GLTF, cleanup=thirty)
        # 39 intervals of 1/20 s = 1.95 s; at 30 fps frames 0..58 (the last frame's time kept).
        assert out.shape == (59,) + raw.shape[1:], (layout, out.shape)
        assert np.isfinite(out).all()
        # Output frame 3k is at the time of input frame 2k: copied, bit for bit.
        np.testing.assert_array_equal(out[0::3], raw[0::2][:20], err_msg=str(layout))
        # The frames between are new: frame 1 (t = 1/30 s) is neither input frame 0 nor 1.
        assert not np.array_equal(out[1], raw[0]) and not np.array_equal(out[1], raw[1])
    # World quaternions are made sign-continuous along each track after posing, and the frames
    # in between can change which sign a track ends up with (q and -q are the same rotation):
    # with RAW_SIGNS (w >= 0 as computed) the common frames are bit for bit the same too.
    raw = stepped40.read("sample", Layout.GLOBAL_QUAT_WXYZ, Convention.GLTF, ReadFlags.RAW_SIGNS)
    out = stepped40.read("sample", Layout.GLOBAL_QUAT_WXYZ, Convention.GLTF, ReadFlags.RAW_SIGNS,
                         cleanup=thirty)
    assert out.shape == (59, 24, 4)
    np.testing.assert_array_equal(out[0::3], raw[0::2][:20])
    # Translations between are linear: frame 3k+1 = raw[2k] + (raw[2k+1] - raw[2k]) * 2/3.
    raw = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF)
    out = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF, cleanup=thirty)
    np.testing.assert_allclose(out[1::3][:19], raw[0:38:2] + (raw[1:39:2] - raw[0:38:2]) * 2 / 3,
                               atol=1e-6)
    # Foot contacts are resampled with the poses.
    assert stepped40.read("sample", Layout.FOOT_CONTACTS, cleanup=flame.Cleanup(fps=30)).shape == (59, 4)


def test_cleanup_in_place_removes_horizontal_travel(stepped40):
    keep = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF)
    travel = np.abs(keep[:, HORIZONTAL] - keep[0, HORIZONTAL]).max()
    assert travel > 1e-3, travel  # there is something to remove
    in_place = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF,
                              cleanup=flame.Cleanup.raw(root_motion=flame.RootMotion.IN_PLACE))
    assert np.abs(in_place[:, HORIZONTAL]).max() < 1e-6
    np.testing.assert_array_equal(in_place[:, 1], keep[:, 1])  # the height is kept
    # The joints move with the pelvis: the pelvis is joint 0 of GLOBAL_POSITIONS.
    positions = stepped40.read("sample", Layout.GLOBAL_POSITIONS, Convention.GLTF,
                               cleanup=flame.Cleanup.raw(root_motion="in-place"))
    assert np.abs(positions[:, 0, HORIZONTAL]).max() < 1e-6


def test_cleanup_separate_root_bone(stepped40):
    keep = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF)
    separate = flame.Cleanup.raw(root_motion=flame.RootMotion.SEPARATE)
    root = stepped40.read("sample", Layout.ROOT_BONE, Convention.GLTF, cleanup=separate)
    pelvis = stepped40.read("sample", Layout.ROOT_TRANSLATION, Convention.GLTF, cleanup=separate)
    assert root.shape == pelvis.shape == (CLEAN_FRAMES, 3)
    assert (root[:, 1] == 0).all()  # on the ground
    assert np.abs(root[:, HORIZONTAL]).max() > 1e-3  # and carrying the travel ...
    # ... exactly the travel the pelvis lost.
    np.testing.assert_allclose(pelvis[:, HORIZONTAL] + root[:, HORIZONTAL], keep[:, HORIZONTAL],
                               atol=1e-5)
    np.testing.assert_array_equal(pelvis[:, 1], keep[:, 1])
    # In Unreal's convention (Z up, centimetres) the bone is at height 0 as well.
    unreal = stepped40.read("sample", Layout.ROOT_BONE, Convention.UNREAL, cleanup=separate)
    assert (unreal[:, 2] == 0).all() and np.abs(unreal).max() > 0.1
    # The bone exists only with SEPARATE.
    expect_error(Status.INVALID_ARGUMENT, "root", stepped40.read, "sample", Layout.ROOT_BONE)
    expect_error(Status.INVALID_ARGUMENT, "root", stepped40.read, "sample", Layout.ROOT_BONE,
                 cleanup=flame.Cleanup())


# The motion two steps in is close to noise: its feet move too fast for the default contact
# detection (no contacts at all), so the feet tests widen it. That the widened values change the
# contacts is itself the check that the contact_* fields reach libflame.
WIDE_CONTACTS = dict(contact_height=1.0, contact_speed=20.0, contact_min_span=0.0)
# The contact columns (left ankle, left foot, right ankle, right foot) and their smpl24 joints.
LEGS = ((0, 1, 7, 10), (2, 3, 8, 11))


def test_cleanup_feet_and_ground(stepped40):
    default = stepped40.read("sample", Layout.FOOT_CONTACTS, cleanup=flame.Cleanup())
    contacts = stepped40.read("sample", Layout.FOOT_CONTACTS, cleanup=flame.Cleanup(**WIDE_CONTACTS))
    assert default.shape == contacts.shape == (CLEAN_FRAMES, 4)
    assert set(np.unique(contacts)) == {0.0, 1.0} and set(np.unique(default)) <= {0.0, 1.0}
    assert contacts.sum() > default.sum()
    # A raw read detects them with the default contact parameters, as the default cleanup does.
    np.testing.assert_array_equal(stepped40.read("sample", Layout.FOOT_CONTACTS), default)
    # ground: the lowest joint of a planted foot (ankle or toe, in a frame where that leg's
    # ankle or toe is in contact) stands at height 0 (y in glTF).
    grounded = stepped40.read("sample", Layout.GLOBAL_POSITIONS, Convention.GLTF,
                              cleanup=flame.Cleanup.raw(ground=True, **WIDE_CONTACTS))
    raw = stepped40.read("sample", Layout.GLOBAL_POSITIONS, Convention.GLTF)

    def floor(positions):
        heights = [positions[(contacts[:, a] + contacts[:, t]) > 0][:, [ja, jt], 1]
                   for a, t, ja, jt in LEGS]
        return min(h.min() for h in heights if h.size)

    assert abs(floor(grounded)) < 1e-5, floor(grounded)
    assert abs(floor(raw)) > 1e-2, floor(raw)  # the raw floor was elsewhere
    np.testing.assert_allclose(grounded[..., 1], raw[..., 1] - floor(raw), atol=1e-5)
    # feet lock moves the feet and nothing above the knees: the pelvis and the head are the
    # grounded read's, the feet are not.
    locked = stepped40.read("sample", Layout.GLOBAL_POSITIONS, Convention.GLTF,
                            cleanup=flame.Cleanup(**WIDE_CONTACTS))
    np.testing.assert_array_equal(locked[:, [0, 15]], grounded[:, [0, 15]])
    assert np.abs(locked[:, [10, 11]] - grounded[:, [10, 11]]).max() > 1e-3


def test_cleanup_bad_values(stepped40):
    read = stepped40.read
    pose = ("sample", Layout.ROOT_TRANSLATION, Convention.GLTF, 0)
    expect_error(Status.INVALID_ARGUMENT, "got NaN", read, *pose, flame.Cleanup(fps=float("nan")))
    expect_error(Status.INVALID_ARGUMENT, "got 1000000000", read, *pose, flame.Cleanup(fps=1e9))
    e = expect_error(Status.INVALID_ARGUMENT, "contact height", read, *pose,
                     flame.Cleanup(contact_height=-0.5))
    assert "got -0.5" in e.message, e.message
    expect_error(Status.INVALID_ARGUMENT, "feet mode 7", read, *pose, flame.Cleanup(feet=7))
    expect_error(Status.INVALID_ARGUMENT, "root motion 3", read, *pose, flame.Cleanup(root_motion=3))
    with pytest.raises(ValueError, match="unknown feet 'hover'"):
        read(*pose, flame.Cleanup(feet="hover"))
    with pytest.raises(TypeError, match="not a flame.Cleanup"):
        read(*pose, cleanup={"fps": 30})
    # The glTF export checks the same values.
    expect_error(Status.INVALID_ARGUMENT, "got NaN", stepped40.write_gltf,
                 cleanup=flame.Cleanup(fps=float("nan")))


def _glb_json(data: bytes) -> dict:
    import json
    import struct

    assert data[:4] == b"glTF"
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    return json.loads(data[20:20 + length])


def test_cleanup_gltf_export(stepped40):
    def names_and_keys(cleanup):
        doc = _glb_json(stepped40.write_gltf(cleanup=cleanup))
        times = doc["animations"][0]["samplers"][0]["input"]
        return [n.get("name") for n in doc["nodes"]], doc["accessors"][times]["count"]

    names, keys = names_and_keys(None)
    assert "root" not in names and keys == CLEAN_FRAMES
    names, keys = names_and_keys(flame.Cleanup(root_motion="separate", fps=30))
    assert "root" in names and "Pelvis" in names and keys == 59
    # The root bone is the pelvis's parent.
    doc = _glb_json(stepped40.write_gltf(cleanup=flame.Cleanup(root_motion="separate")))
    names = [n.get("name") for n in doc["nodes"]]
    root = doc["nodes"][names.index("root")]
    assert names.index("Pelvis") in root.get("children", [])
