"""MotionLCM through the Python binding: the latent consistency sampler and trajectory control
(`Session.set_control`) on the tiny v2 control fixture, bit for bit against the `flame` CLI
(which tests/motionlcm_control.rs checks against the PyTorch reference), and the refusals."""
import subprocess

import numpy as np
import pytest

import flame
from flame import FlameError, Status
from test_flame import ROOT, cli_path, expect_error

CONTROL = str(ROOT / "tests/fixtures/motionlcm_v2_control_tiny.safetensors")
PLAIN = str(ROOT / "tests/fixtures/motionlcm_v2_tiny.safetensors")
PROMPT = "a person walks forward"
FRAMES = 24


def pelvis_path():
    """A pelvis path in HumanML3D's frame (Y up, metres) on every frame; the rest free."""
    h = np.full((FRAMES, 22, 3), np.nan, dtype=np.float32)
    f = np.arange(FRAMES, dtype=np.float32)
    h[:, 0] = np.stack([0.05 * f, np.full(FRAMES, 0.9, np.float32), 0.02 * f], axis=1)
    return h


def test_control_follows_a_path_as_the_cli_does(tmp_path):
    hint = pelvis_path()
    with flame.Model.load(CONTROL) as m:
        assert m.info.architecture == "motionlcm" and m.info.control
        assert m.info.default_sampler == flame.Sampler.LCM
        with m.session(frames=FRAMES, steps=2, sampler="lcm", seed=5, threads=1) as s:
            s.set_prompt(PROMPT)
            s.set_control(hint)
            controlled = s.run().copy()
        with m.session(frames=FRAMES, steps=2, sampler="lcm", seed=5, threads=1) as s:
            s.set_prompt(PROMPT)
            s.set_control(hint)
            s.clear_control()
            plain = s.run().copy()
    assert np.isfinite(controlled).all()
    assert not np.array_equal(controlled, plain), "the control changes the motion"
    np.save(tmp_path / "hint.npy", hint)
    out = tmp_path / "cli.npy"
    subprocess.run([cli_path(), "generate", "--model", CONTROL, "--prompt", PROMPT,
                    "--frames", str(FRAMES), "--steps", "2", "--sampler", "lcm", "--seed", "5",
                    "--threads", "1", "--convention", "native",
                    "--control", str(tmp_path / "hint.npy"), "--out", str(out)],
                   check=True, capture_output=True)
    assert np.load(out).tobytes() == controlled.tobytes()


def test_latent_tuning_as_the_cli_does(tmp_path):
    hint = pelvis_path()
    with flame.Model.load(CONTROL) as m:
        with m.session(frames=FRAMES, steps=1, seed=5, threads=1) as s:
            s.set_prompt(PROMPT)
            s.set_control(hint)
            r = s.tune_latent(20)
            tuned = s.run().copy()
        assert r.iterations == 20
        assert r.control_error[1] < r.control_error[0], r
        assert r.hint_loss[1] < r.hint_loss[0], r
        with m.session(frames=FRAMES, steps=1, seed=5) as s:
            s.set_prompt(PROMPT)
            expect_error(Status.WRONG_STATE, "set one first", s.tune_latent, 5)
        with m.session(frames=FRAMES, steps=2, seed=5) as s:
            s.set_prompt(PROMPT)
            s.set_control(hint)
            expect_error(Status.INVALID_ARGUMENT, "1-step sampler", s.tune_latent, 5)
        with pytest.raises(ValueError):
            s.tune_latent(-1)
    np.save(tmp_path / "hint.npy", hint)
    out = tmp_path / "cli.npy"
    subprocess.run([cli_path(), "generate", "--model", CONTROL, "--prompt", PROMPT,
                    "--frames", str(FRAMES), "--steps", "1", "--seed", "5", "--threads", "1",
                    "--convention", "native", "--control", str(tmp_path / "hint.npy"),
                    "--optimize", "20", "--out", str(out)],
                   check=True, capture_output=True)
    assert np.load(out).tobytes() == tuned.tobytes()


def test_control_refusals():
    with flame.Model.load(PLAIN) as m:
        assert not m.info.control
        with m.session(frames=FRAMES) as s:
            expect_error(Status.INVALID_ARGUMENT, "no ControlNet", s.set_control, pelvis_path())
    with flame.Model.load(CONTROL) as m, m.session(frames=FRAMES) as s:
        expect_error(Status.INVALID_ARGUMENT, "constrain", s.set_control,
                     np.full((FRAMES, 22, 3), np.nan, dtype=np.float32))
        with pytest.raises(ValueError):
            s.set_control(np.zeros((FRAMES, 21, 3), dtype=np.float32))
        expect_error(Status.INVALID_ARGUMENT, "the session has 24", s.set_control,
                     np.zeros((FRAMES + 1, 22, 3), dtype=np.float32))
        # A step count v2's table lacks.
        with pytest.raises(FlameError) as e:
            m.session(frames=FRAMES, steps=3)
        assert "1, 2, 4" in e.value.message


def test_editing_tasks_go_through_the_control_net_as_the_cli_does(tmp_path):
    ref = tmp_path / "ref.npy"
    subprocess.run([cli_path(), "generate", "--model", CONTROL, "--prompt", PROMPT,
                    "--frames", str(FRAMES), "--steps", "2", "--seed", "1", "--threads", "1",
                    "--out", str(ref)], check=True, capture_output=True)
    reference = np.load(ref)
    with flame.Model.load(CONTROL) as m, \
            m.session(frames=FRAMES, steps=2, seed=3, threads=1) as s:
        s.set_prompt("then jumps")
        s.set_task_targets(reference, "predict")
        edited = s.run().copy()
    out = tmp_path / "edited.npy"
    subprocess.run([cli_path(), "edit", "--model", CONTROL, "--reference", str(ref), "--task",
                    "predict", "--prompt", "then jumps", "--frames", str(FRAMES), "--steps", "2",
                    "--seed", "3", "--threads", "1", "--out", str(out)],
                   check=True, capture_output=True)
    assert np.load(out).tobytes() == edited.tobytes()
    with flame.Model.load(PLAIN) as m, m.session(frames=FRAMES, steps=2) as s:
        expect_error(Status.INVALID_ARGUMENT, "gradient", s.set_task_targets, reference,
                     "predict")


def test_a_prompt_encoded_once_serves_other_sessions():
    with flame.Model.load(PLAIN) as m:
        with m.session(frames=FRAMES, steps=2, seed=4, threads=1) as a, \
                m.session(frames=FRAMES, steps=2, seed=4, threads=1) as b:
            a.set_prompt(PROMPT)
            first = a.run().copy()
            b.set_prompt_from(a)
            assert b.prompt_info().tokens == a.prompt_info().tokens
            assert b.run().tobytes() == first.tobytes()
        with m.session(frames=FRAMES) as empty, m.session(frames=FRAMES) as c:
            expect_error(Status.WRONG_STATE, "no prompt", c.set_prompt_from, empty)
            with pytest.raises(TypeError):
                c.set_prompt_from("a person walks")
            with flame.Model.load(PLAIN) as other, other.session(frames=FRAMES) as d:
                empty.set_prompt(PROMPT)
                expect_error(Status.INVALID_ARGUMENT, "another model", d.set_prompt_from, empty)
