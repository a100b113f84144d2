"""Session.write_amass (flame_session_write_amass) through the Python bindings, the files read
back with NumPy's own np.load: both AMASS layouts' keys, dtypes and shapes (nghorbani/amass
SMPL-H `*_poses.npz`, SMPL-X `*_stageii.npz`), `trans` + the neutral SMPL rest pelvis equal to
the root translation Session.read gives, turned into AMASS's Z-up world (smpl24_6d: its native
frame already; humanml263: (x, y, z) -> (x, -z, y)), the cleanup's frame rate, `path`, and the
refusals. On a smpl24_6d fixture (FLAME) and a humanml263 one (MDM).
"""

import io
from pathlib import Path

import numpy as np
import pytest

import flame
from flame import AmassLayout, Cleanup, Convention, FlameError, Layout, Status

FIXTURES = Path(__file__).resolve().parents[3] / "tests/fixtures"
MODELS = [("flame_tiny.safetensors", "smpl24_6d"), ("mdm_tiny.safetensors", "humanml263")]
PROMPT = "a person walks forward and waves."
SEED = 5
FRAMES = 16
REST_PELVIS = np.array([-0.00179506, -0.22333345, 0.02821913])
SMPLH_KEYS = {"poses", "trans", "betas", "gender", "mocap_framerate", "dmpls"}
SMPLX_KEYS = {"root_orient", "pose_body", "pose_hand", "pose_jaw", "pose_eye", "trans", "betas",
              "num_betas", "gender", "surface_model_type", "mocap_frame_rate",
              "mocap_time_length", "poses"}


def expect_error(status, fragment, fn, *args, **kwargs):
    with pytest.raises(FlameError) as e:
        fn(*args, **kwargs)
    assert e.value.status == status, str(e.value)
    assert fragment in e.value.message, e.value.message


@pytest.fixture(scope="module", params=MODELS, ids=[m[1] for m in MODELS])
def stepped(request):
    """(session, motion format): two steps of four (the tiny models' final motions saturate)."""
    name, fmt = request.param
    with flame.Model.load(FIXTURES / name) as model, \
            model.session(frames=FRAMES, steps=4, sampler="ddim", seed=SEED, threads=1) as s:
        s.set_prompt(PROMPT)
        s.step()
        s.step()
        yield s, fmt


def load(data: bytes):
    return np.load(io.BytesIO(data))


def test_both_layouts_hold_amass_keys(stepped):
    s, fmt = stepped
    h = load(s.write_amass())
    assert set(h.files) == SMPLH_KEYS
    assert h["poses"].dtype == np.float64 and h["poses"].shape == (FRAMES, 156)
    assert h["trans"].shape == (FRAMES, 3) and h["dmpls"].shape == (FRAMES, 8)
    assert h["betas"].shape == (16,) and not h["betas"].any()
    assert str(h["gender"]) == "neutral" and float(h["mocap_framerate"]) == 20.0
    x = load(s.write_amass(layout="smplx"))
    assert set(x.files) == SMPLX_KEYS
    assert x["pose_body"].shape == (FRAMES, 63) and x["poses"].shape == (FRAMES, 165)
    assert int(x["num_betas"]) == 16 and str(x["surface_model_type"]) == "smplx"
    assert x["mocap_frame_rate"].item() == 20.0
    assert x["mocap_time_length"].item() == pytest.approx(FRAMES / 20.0)
    assert np.array_equal(x["poses"][:, :66], h["poses"][:, :66])
    assert np.array_equal(x["root_orient"], h["poses"][:, :3])
    assert np.array_equal(load(s.write_amass(layout=AmassLayout.SMPLX))["trans"], x["trans"])


def test_trans_is_the_pelvis_less_the_rest_pelvis(stepped):
    s, fmt = stepped
    trans = load(s.write_amass())["trans"]
    root = s.read(layout=Layout.ROOT_TRANSLATION, convention=Convention.NATIVE).astype(np.float64)
    if fmt == "humanml263":
        root = np.stack([root[:, 0], -root[:, 2], root[:, 1]], axis=1)
    assert np.abs(trans + REST_PELVIS - root).max() < 1e-5


def test_cleanup_rate_and_path(stepped, tmp_path):
    s, _ = stepped
    path = tmp_path / "walk_stageii.npz"
    data = s.write_amass(path, layout="smplx", cleanup=Cleanup(fps=30))
    assert path.read_bytes() == data
    x = np.load(path)
    frames = len(s.read(layout=Layout.ROOT_TRANSLATION, cleanup=Cleanup(fps=30)))
    assert x["mocap_frame_rate"].item() == 30.0 and x["trans"].shape == (frames, 3)
    assert frames == 23  # 15 intervals of 1/20 s at 30 fps: 0..22


def test_refusals(stepped):
    s, _ = stepped
    with pytest.raises(ValueError, match="unknown AMASS layout"):
        s.write_amass(layout="smpl")
    expect_error(Status.INVALID_ARGUMENT, "AMASS layout 7", s.write_amass, layout=7)
    expect_error(Status.INVALID_ARGUMENT, "frame rate", s.write_amass, cleanup=Cleanup(fps=-1))


def test_nothing_to_write_before_the_first_step():
    with flame.Model.load(FIXTURES / MODELS[0][0]) as model, \
            model.session(frames=FRAMES, steps=4, seed=SEED, threads=1) as s:
        s.set_prompt(PROMPT)
        with pytest.raises(FlameError) as e:
            s.write_amass()
        assert e.value.status == Status.WRONG_STATE
