"""flame.Stream (flame_stream_*): a timeline of prompts on the FLAME and MDM fixtures,
determinism under pump patterns, the lookahead, reads of frames not generated or dropped, and
bad input."""
from pathlib import Path

import numpy as np
import pytest

import flame
from flame import FlameError, Layout, Convention, Status

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


def model(name):
    return flame.Model.load(str(FIXTURES / f"{name}.safetensors"))


def stream(m, **kw):
    args = dict(chunk=40, overlap=10, lookahead=100000, window=100000, steps=2, sampler="ddim",
                seed=4)
    args.update(kw)
    return flame.Stream(m, **args)


@pytest.mark.parametrize("name,dim", [("flame_tiny", 147), ("mdm_tiny", 263)])
def test_a_timeline_is_generated_the_same_whatever_the_pump_pattern(name, dim):
    m = model(name)
    a, b = stream(m, threads=1), stream(m, threads=2)
    for s in (a, b):
        s.push("a person walks forward.", 30)
        s.push("a person waves.", 20)
    calls = 0
    while a.pump(1).steps:
        calls += 1
    # 30 = one chunk, 20 = 20 new frames after 10 kept: two chunks of 2 steps.
    assert calls == 4
    st = b.pump()
    # Every segment generated and the lookahead (100000) not reached: starving, push more.
    assert (st.steps, st.ready, st.first_frame, st.starving) == (4, 50, 0, True)
    fa, fb = a.read(0, 50, Layout.FEATURES), b.read(0, 50, Layout.FEATURES)
    assert fa.shape == (50, dim)
    assert fa.tobytes() == fb.tobytes()
    q = a.read(10, 5, Layout.LOCAL_QUAT_XYZW, Convention.UNITY)
    assert q.shape == (5, m.info.joint_count, 4)
    assert a.status().ready == 50


def test_frames_not_ready_dropped_and_bad_input_are_errors():
    m = model("flame_tiny")
    s = stream(m, window=10)
    with pytest.raises(FlameError) as e:
        s.push("a person walks.", 0)
    assert e.value.status == Status.INVALID_ARGUMENT
    s.push("a person walks.", 60)
    s.pump(1)
    with pytest.raises(FlameError) as e:
        s.read(0, 5, Layout.ROOT_TRANSLATION)
    assert e.value.status == Status.WRONG_STATE and "not generated yet" in str(e.value)
    s.pump()
    assert s.status().ready == 60
    s.set_playhead(45)
    assert s.status().first_frame == 35
    with pytest.raises(FlameError) as e:
        s.read(30, 5, Layout.ROOT_TRANSLATION)
    assert e.value.status == Status.INVALID_ARGUMENT and "dropped" in str(e.value)
    st = s.pump()
    assert st.starving
    with pytest.raises(FlameError) as e:
        stream(model("mld_tiny"))
    assert "latent" in str(e.value)
    with pytest.raises(FlameError):
        stream(m, chunk=40, overlap=40)
    s.close()
    with pytest.raises(ValueError):
        s.pump()
