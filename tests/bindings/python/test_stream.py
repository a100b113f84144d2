"""flame.Stream (flame_stream_*): a timeline of prompts on the FLAME and MDM fixtures,
determinism under pump patterns, the lookahead, reads of frames not generated or dropped, and
bad input; cancel (from another thread during pumps, and between pumps), segments with part
texts (push_stage / interrupt_stage: FineMoGen reads them, FLAME refuses them), a MoLA stream,
quaternions read one frame at a time, cleaned reads and a timeline closed into a loop
(end_timeline_looped)."""
import threading
import time
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
    assert e.value.status == Status.INVALID_ARGUMENT and "gradient" in str(e.value)
    with pytest.raises(FlameError):
        stream(m, chunk=40, overlap=40)
    s.close()
    with pytest.raises(ValueError):
        s.pump()


# --- cancel ----------------------------------------------------------------------------------

# The settings of tests/c/test_stream.c: chunks of 40 frames keeping 10, 3 DDIM steps, seed 5;
# 50 + 25 + 40 = 115 frames in five chunks of 3 steps.
TIMELINE = (("a person walks forward.", 50), ("a person waves.", 25), ("a person sits down.", 40))
TIMELINE_FRAMES = 115


def small(m, **kw):
    args = dict(chunk=40, overlap=10, lookahead=1000, window=10000, steps=3, sampler="ddim",
                seed=5, threads=1)
    args.update(kw)
    return flame.Stream(m, **args)


def timeline(s, segments=TIMELINE):
    for text, frames in segments:
        s.push(text, frames)
    return s


def pump_on(s, per_call=0xFFFFFFFF):
    """Pumps until a call runs no step; returns how many pumps raised CANCELLED."""
    cancelled = 0
    for _ in range(100000):
        try:
            if s.pump(per_call).steps == 0:
                return cancelled
        except FlameError as e:
            assert e.status == Status.CANCELLED, e
            cancelled += 1
    raise AssertionError("the stream never finished")


def features(s, frames):
    return s.read(0, frames, Layout.FEATURES)


def _full(m, **kw):
    """A stream of TIMELINE pumped to its end, never cancelled."""
    s = timeline(small(m, **kw))
    assert pump_on(s) == 0
    return s


@pytest.mark.parametrize("name", ["flame_tiny", "mdm_tiny"])
def test_cancel_between_pumps_cancels_the_next_one(name):
    m = model(name)
    want = features(_full(m), TIMELINE_FRAMES)
    s = timeline(small(m))
    assert s.pump(4).ready == 40  # the first chunk (3 steps) and one step of the second
    s.cancel()
    with pytest.raises(FlameError) as e:
        s.pump()
    assert e.value.status == Status.CANCELLED and e.value.status_name == "FLAME_STATUS_CANCELLED"
    assert s.status().ready == 40  # nothing kept from the cancelled pump
    # The cancel was spent on that pump: the next one goes on, to the frames of a stream never
    # cancelled.
    st = s.pump()
    assert st.ready == TIMELINE_FRAMES and st.steps == 11
    assert features(s, TIMELINE_FRAMES).tobytes() == want.tobytes()
    s.close()
    s.cancel()  # a no-op on a closed stream


@pytest.mark.parametrize("name", ["flame_tiny", "mdm_tiny"])
def test_cancel_from_another_thread_during_pumps_then_pumping_on_is_bit_identical(name):
    """Cancels raised by another thread while this one pumps one step per call (as
    tests/c/test_stream.c does): each lands inside a pump or cancels the next one, and pumping
    on gives the bits of a stream never cancelled."""
    m = model(name)
    want = features(_full(m), TIMELINE_FRAMES)
    s = timeline(small(m))
    stop = threading.Event()

    def canceller():
        for _ in range(30):
            if stop.is_set():
                return
            time.sleep(0.0002)
            s.cancel()

    t = threading.Thread(target=canceller)
    t.start()
    try:
        cancelled = pump_on(s, 1)
    finally:
        stop.set()
        t.join()
    # A cancel raised after the last pump would cancel the next one: drain it.
    while True:
        try:
            s.pump(1)
            break
        except FlameError as e:
            assert e.status == Status.CANCELLED
            cancelled += 1
    assert cancelled >= 1
    assert s.status().ready == TIMELINE_FRAMES
    assert features(s, TIMELINE_FRAMES).tobytes() == want.tobytes()


def test_cancel_stops_a_long_pump_on_another_thread():
    """One pump of a long timeline (about a hundred steps) on a worker thread, cancelled once
    from this one: that pump raises CANCELLED part way, and pumping on gives the frames of a
    stream never cancelled."""
    m = model("flame_tiny")
    long = (("a person walks forward.", 600), ("a person waves.", 400))
    want = timeline(small(m, lookahead=100000), long)
    assert pump_on(want) == 0
    s = timeline(small(m, lookahead=100000), long)
    started, result = threading.Event(), {}

    def worker():
        started.set()
        try:
            result["status"] = s.pump()
        except FlameError as e:
            result["error"] = e

    t = threading.Thread(target=worker)
    t.start()
    assert started.wait(30)
    time.sleep(0.005)
    begun = time.monotonic()
    s.cancel()
    t.join(30)
    assert not t.is_alive()
    assert "error" in result and result["error"].status == Status.CANCELLED, result
    assert time.monotonic() - begun < 5
    assert s.status().ready < 1000  # it stopped part way
    assert pump_on(s) == 0  # the cancel was spent
    assert s.status().ready == 1000
    assert features(s, 1000).tobytes() == features(want, 1000).tobytes()


# --- segments with part texts ----------------------------------------------------------------


def test_stage_segments_on_finemogen():
    """FineMoGen reads part texts: a segment whose every part text is the segment's own text is
    the plain push, bit for bit; another right-arm text changes the second segment's frames
    only (the first segment's 20 frames are generated before it)."""
    m = model("finemogen_tiny")
    walk, wave = "a person walks forward.", "a person waves."
    parts = ("head", "stem", "left_arm", "right_arm", "left_leg", "right_leg", "pelvis")

    def run(push):
        s = small(m, chunk=30, overlap=8)
        s.push(walk, 20)
        push(s)
        assert pump_on(s) == 0
        assert s.status().ready == 50
        return features(s, 50)

    plain = run(lambda s: s.push(wave, 30))
    every = run(lambda s: s.push_stage(flame.Stage(wave, 30, **{p: wave for p in parts})))
    bare = run(lambda s: s.push_stage(flame.Stage(wave, 30)))
    arm = run(lambda s: s.push_stage(flame.Stage(wave, 30, right_arm="the right arm swings up and down.")))
    assert plain.shape == (50, m.info.feature_dim)
    assert every.tobytes() == plain.tobytes()
    assert bare.tobytes() == plain.tobytes()
    assert arm[:20].tobytes() == plain[:20].tobytes()
    assert not np.array_equal(arm[20:], plain[20:])

    # interrupt_stage: the same as interrupt for the same texts; another text changes the
    # frames after the interrupt only.
    def interrupted(interrupt):
        s = small(m, chunk=30, overlap=8)
        s.push(walk, 100)
        assert s.pump(3).ready == 30  # the first chunk
        interrupt(s)
        assert pump_on(s) == 0
        assert s.status().ready == 60
        return features(s, 60)

    plain = interrupted(lambda s: s.interrupt(wave, 30))
    every = interrupted(lambda s: s.interrupt_stage(flame.Stage(wave, 30, **{p: wave for p in parts})))
    arm = interrupted(lambda s: s.interrupt_stage(flame.Stage(wave, 30, left_arm="the left arm rises.")))
    assert every.tobytes() == plain.tobytes()
    assert arm[:30].tobytes() == plain[:30].tobytes()
    assert not np.array_equal(arm[30:], plain[30:])


def test_part_texts_refused_by_flame_when_the_segment_starts():
    m = model("flame_tiny")
    plain = timeline(small(m), (("a person walks.", 30),))
    assert pump_on(plain) == 0
    # Empty part texts follow the whole-body text: a plain segment, bit for bit.
    s = small(m)
    s.push_stage(flame.Stage("a person walks.", 30, head="", left_arm=""))
    assert pump_on(s) == 0
    assert features(s, 30).tobytes() == features(plain, 30).tobytes()
    # A part text is accepted by the push and refused by the pump that starts the segment.
    s.push_stage(flame.Stage("a person waves.", 30, left_arm="the left arm waves."))
    with pytest.raises(FlameError) as e:
        s.pump()
    assert e.value.status == Status.INVALID_ARGUMENT and "part" in e.value.message
    s = small(m)
    s.interrupt_stage(flame.Stage("a person waves.", 30, pelvis="the pelvis turns."))
    with pytest.raises(FlameError) as e:
        s.pump()
    assert e.value.status == Status.INVALID_ARGUMENT and "part" in e.value.message


def test_stage_segment_input_errors():
    s = small(model("flame_tiny"))
    for push in (s.push_stage, s.interrupt_stage):
        with pytest.raises(TypeError):
            push(("a person walks.", 30))
        with pytest.raises(ValueError, match="stage.frames"):
            push(flame.Stage("a person walks.", -1))
        with pytest.raises(ValueError, match="stage.left_arm contains a NUL"):
            push(flame.Stage("a person walks.", 30, left_arm="a\0b"))
        with pytest.raises(TypeError, match="stage.head"):
            push(flame.Stage("a person walks.", 30, head=3))
        with pytest.raises(FlameError) as e:
            push(flame.Stage("a person walks.", 0))
        assert e.value.status == Status.INVALID_ARGUMENT and "frame" in e.value.message
        with pytest.raises(FlameError) as e:
            push(flame.Stage(None, 30))
        assert e.value.status == Status.INVALID_ARGUMENT and "stage.text" in e.value.message
    # Nothing was queued by the refused calls.
    st = s.pump()
    assert (st.steps, st.ready, st.starving) == (0, 0, True)
    s.close()
    with pytest.raises(ValueError):
        s.push_stage(flame.Stage("a person walks.", 30))


# --- a latent model and quaternion reads -----------------------------------------------------


def test_a_mola_stream_runs_and_is_deterministic():
    """MoLA (a latent model) continues each chunk through position targets: the same timeline
    gives the same frames one step per call on one thread as all at once on two."""
    m = model("mola_tiny")
    assert m.latent
    got = []
    for threads, per_call in ((1, 1), (2, 0xFFFFFFFF)):
        s = timeline(small(m, chunk=32, overlap=8, threads=threads))
        assert pump_on(s, per_call) == 0
        assert s.status().ready == TIMELINE_FRAMES
        pos = s.read(0, TIMELINE_FRAMES, Layout.GLOBAL_POSITIONS)
        assert pos.shape == (TIMELINE_FRAMES, m.info.joint_count, 3)
        got.append((pos, features(s, TIMELINE_FRAMES)))
    assert got[0][0].tobytes() == got[1][0].tobytes()
    assert got[0][1].tobytes() == got[1][1].tobytes()
    assert np.isfinite(got[0][0]).all()


@pytest.mark.parametrize("name", ["flame_tiny", "mdm_tiny"])
def test_quaternions_read_one_frame_at_a_time_are_the_whole_read(name):
    s = timeline(small(model(name)))
    assert pump_on(s) == 0
    for layout in (Layout.LOCAL_QUAT_XYZW, Layout.GLOBAL_QUAT_WXYZ):
        whole = s.read(0, TIMELINE_FRAMES, layout, Convention.UNITY)
        ticks = np.concatenate([s.read(f, 1, layout, Convention.UNITY)
                                for f in range(TIMELINE_FRAMES)])
        assert ticks.tobytes() == whole.tobytes()


# --- cleaned reads ---------------------------------------------------------------------------

def test_cleaned_frames_read_one_at_a_time_equal_one_read_at_the_end():
    # flame_stream_read_cleaned: frames once settled never change, so reading them as they
    # settle gives the bytes one read at the end gives; at 30 fps the 115 frames at 20 fps are
    # 172 (the last frame's time kept).
    m = model("flame_tiny")
    cleanup = flame.Cleanup(fps=30.0, root_motion=flame.RootMotion.SEPARATE)
    a, b = timeline(small(m)), timeline(small(m))
    for s in (a, b):
        s.end_timeline()
    with pytest.raises(FlameError) as e:
        a.push("a person waves.", 10)
    assert e.value.status == Status.WRONG_STATE
    got = []
    while True:
        stepped = a.pump(1).steps
        k = len(got)
        try:
            got.append(a.read(k, 1, Layout.GLOBAL_POSITIONS, Convention.GLTF, cleanup)[0])
            continue
        except FlameError as err:
            assert err.status == Status.WRONG_STATE
        if stepped == 0:
            break
    pump_on(b)
    whole = b.read(0, 172, Layout.GLOBAL_POSITIONS, Convention.GLTF, cleanup)
    assert len(got) == 172
    assert np.stack(got).tobytes() == whole.tobytes()
    bone = b.read(0, 172, Layout.ROOT_BONE, Convention.GLTF, cleanup)
    assert np.all(bone[:, 1] == 0.0)
    with pytest.raises(FlameError) as e:
        b.read(0, 172, Layout.GLOBAL_POSITIONS, Convention.GLTF, flame.Cleanup(fps=60.0))
    assert e.value.status == Status.WRONG_STATE
    with pytest.raises(FlameError) as e:
        small(m).read(0, 1, Layout.GLOBAL_POSITIONS, 0, flame.Cleanup(wrap=True))
    assert e.value.status == Status.INVALID_ARGUMENT


# --- a timeline closed into a loop -----------------------------------------------------------

# tests/c/test_stream.c's loop (the settings of tests/cycle.rs): chunks of 60 frames keeping 20,
# 3 steps, seed 9; "a person walks" 70 + "a person jumps" 30 = 100 frames, a 20-frame bridge.
LOOP = (("a person walks", 70), ("a person jumps", 30))


def loop_stream(m, **kw):
    args = dict(chunk=60, overlap=20, lookahead=1000, window=1000, steps=3, seed=9, threads=1)
    args.update(kw)
    return flame.Stream(m, **args)


def test_a_timeline_closed_into_a_loop_appends_a_bridge():
    m = model("flame_tiny")
    plain, looped = timeline(loop_stream(m), LOOP), timeline(loop_stream(m), LOOP)
    plain.end_timeline()
    looped.end_timeline_looped(20)
    assert pump_on(plain, 1) == 0 and pump_on(looped, 1) == 0
    assert plain.status().ready == 100
    st = looped.status()
    assert (st.ready, st.first_frame, st.starving) == (120, 0, True)
    with pytest.raises(FlameError) as e:
        looped.read(120, 1, Layout.FEATURES)
    assert e.value.status == Status.WRONG_STATE and "not generated yet" in e.value.message
    # The bridge only appends: the first 100 frames are the plain stream's, bit for bit.
    x = features(looped, 120)
    assert x.shape == (120, m.info.feature_dim) and np.isfinite(x).all()
    assert x[:100].tobytes() == features(plain, 100).tobytes()
    # Cleaned reads (the default cleanup: feet locked) settle all 120 frames.
    cleanup = flame.Cleanup()
    assert cleanup.feet == flame.Feet.LOCK
    pos = looped.read(0, 120, Layout.GLOBAL_POSITIONS, Convention.GLTF, cleanup)
    assert pos.shape == (120, m.info.joint_count, 3) and np.isfinite(pos).all()
    # Closed: a second close and a push are WRONG_STATE.
    for call in (lambda: looped.end_timeline_looped(20), lambda: looped.push("a person waves", 10)):
        with pytest.raises(FlameError) as e:
            call()
        assert e.value.status == Status.WRONG_STATE and "closed" in e.value.message


def test_a_looped_close_is_refused_when_it_cannot_loop():
    m = model("flame_tiny")
    s = loop_stream(m)
    with pytest.raises(FlameError) as e:
        s.end_timeline_looped(20)
    assert e.value.status == Status.WRONG_STATE and "push a segment" in e.value.message
    s.push("a person walks", 40)
    with pytest.raises(FlameError) as e:
        s.end_timeline_looped(12)
    assert e.value.status == Status.INVALID_ARGUMENT
    assert "bridge of 12 frames" in e.value.message, e.value.message
    with pytest.raises(ValueError, match="bridge_frames"):
        s.end_timeline_looped(-1)
    s.push("a person jumps", 20)  # the refused closes left the stream open
    s.end_timeline_looped(20)
    s.close()
    with pytest.raises(ValueError):
        s.end_timeline_looped(20)
    latent = timeline(loop_stream(model("mola_tiny"), chunk=32, overlap=8), LOOP[:1])
    with pytest.raises(FlameError) as e:
        latent.end_timeline_looped(20)
    assert e.value.status == Status.INVALID_ARGUMENT and "samples a latent" in e.value.message
