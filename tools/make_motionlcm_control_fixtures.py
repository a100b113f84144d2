#!/usr/bin/env python3
"""Generate the MotionLCM trajectory-control (ControlNet) parity fixtures in tests/fixtures/
(seeded, deterministic): motionlcm_v1_control_tiny.safetensors,
motionlcm_v2_control_tiny.safetensors, motionlcm_control_expected.safetensors.

Built on tools/make_motionlcm_fixtures.py (imported): the same tiny sentence-t5 folders, the same
tiny text-to-motion checkpoints (tiny_checkpoint: D 32, text/time 48, cond 16, 3-layer stacks,
4 heads, ff 64; v1 latent [1, 32], v2 [4, 8]), the same HumanML3D statistics and prompt 0, so the
text-to-motion part of each control file is that of motionlcm_{v1,v2}_tiny.safetensors.

Steps:
 1. Tiny control checkpoints in the official layout (Dai-Wenxun/MotionLCM configs/
    motionlcm_control*.yaml; tools/convert_motionlcm.py documents the names): the text-to-motion
    checkpoint plus `controlnet.*` (the copy of the denoiser built by
    tools/reference/motionlcm_control.py's ControlNet, whose names are the official ones:
    mld/models/architectures/mld_denoiser.py with is_controlnet=True; v2 also
    `controlnet.latent_post.*`, v1 a `controlnet.mem_pos.pe`, both to be dropped) and
    `traj_encoder.*` (mld/models/architectures/mld_traj_encoder.py: width 32, 3 layers, 4 heads,
    ff 64, 64 position rows, L global tokens, v2's latent_proj 32 -> 8). ControlNet embed width
    E 32 (v1: D). Every weight random and nonzero, including the modules the release
    zero-initialises (cond_proj, the last Linear of controlnet_cond_embedding, every
    controlnet_down_mid_blocks Linear).
 2. Tiny Mean_raw / Std_raw (66 values; std in [0.5, 1.5]), written [66] for v1 (as v1.0 ships
    them) and [22, 3] for v2 (as v2.0 does); `tools/convert.py motionlcm` (f32, --frames 24,
    --control-mean/--control-std) -> the two control files. Refusals exercised: a control
    checkpoint without --control-mean; a Std with a zero; a ControlNet down block of the wrong
    shape; a trajectory encoder whose token count differs from the latent's; ControlNet without
    trajectory encoder. `--skip-prefix controlnet. --skip-prefix traj_encoder.` gives exactly
    motionlcm_{v1,v2}_tiny.safetensors; an f16 conversion keeps control.* float32.
 3. tools/reference/motionlcm_control.py on the CONVERTED files (float32) ->
    motionlcm_control_expected.safetensors.

Expected tensors (r in v1, v2; L x C the latent, D 32, 3 blocks, 24 frames; NaN = free value):
  text.0 [48]                      prompt 0's sentence vector (= motionlcm_expected's text.0)
  {r}.joints [24, 22, 3]           targets: pelvis (0) on every frame, joints 10, 11, 15, 20, 21 on
                                   frames 0-4 (all three axes), the rest NaN
  {r}.hint [24, 66]                ((joints - mean_raw) / std_raw) x mask, flattened
  {r}.frame_mask [24]              1.0 / 0.0 (the release's rule: v1 row_sum, v2 mask)
  {r}.control_cond [L, C]          the trajectory encoder's output
  {r}.sparse.{joints, hint, frame_mask, control_cond}   pelvis on frames 0, 4, ..., 20, joints 20
                                   and 21 on frames 9-11, joint 15 on frame 2 AT Mean_raw (its
                                   normalised values are 0: v1's row_sum drops frame 2, v2 keeps
                                   it), the rest free; exercises the key padding
  {r}.empty_cond [L, C]            the encoder's output with no hinted value (hint 0, every
                                   frame masked: only the L global tokens are attended; finite)
  {r}.forward.z [1, L, C], {r}.forward.t [1] (699), {r}.forward.w [1] (6.5, the embedded value)
  {r}.residuals [3, L + 2, D]      the ControlNet's residuals after the down blocks, over the
                                   whole sequence (latent tokens, time, text), times the scale
  {r}.forward.eps [1, L, C]        the denoiser's eps with those residuals
  {r}.forward.eps_plain [1, L, C]  the same without control (the text-to-motion forward)
  {r}.s{n}.{noise [1, L, C], renoise [max(n-1, 1), L, C], guidance [1], timesteps [n],
            latent [1, L, C], denoised [n, L, C], features [24, 263]}   n in 1, 2: latent
                                   consistency sampling with control ({r}.control_cond), as in
                                   motionlcm_expected.safetensors
All conditioned on text.0 (metadata "prompts").

Run from anywhere: python tools/make_motionlcm_control_fixtures.py   (~20 s)
"""
import json
import os
import shutil
import sys
import tempfile

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TOOLS)

import make_motionlcm_fixtures as base  # noqa: E402
from make_latent_fixtures import log, randomize, run_convert  # noqa: E402
from reference import motionlcm  # noqa: E402
from reference import motionlcm_control as mc  # noqa: E402

FIX = base.FIX
FRAMES = base.FRAMES
WIDTH = base.WIDTH
LAYERS = base.DEN["layers"]
TRAJ = dict(layers=3, heads=4, ff_size=64, max_len=64)
EMBED_DIM = 32
SEEDS = {"v1": 51, "v2": 52, "stats": 53, "joints": 54, "inputs": 55, "extra": 56}
OUT = {"v1": "motionlcm_v1_control_tiny.safetensors",
       "v2": "motionlcm_v2_control_tiny.safetensors"}
EXPECTED = "motionlcm_control_expected.safetensors"
HINTED = {"pelvis": 0, "every_frame": [0], "early_joints": [10, 11, 15, 20, 21],
          "early_frames": [0, 1, 2, 3, 4]}


# -- 1. checkpoints ------------------------------------------------------------------------------

def control_checkpoint(r):
    """The tiny text-to-motion checkpoint of make_motionlcm_fixtures plus a random ControlNet
    and trajectory encoder in the official layout."""
    state = dict(base.tiny_checkpoint(r)["state_dict"])
    tokens, channels = base.LATENT[r]
    v2 = r == "v2"
    d = base.DEN
    torch.manual_seed(SEEDS[r])
    cn = mc.ControlNet(d["latent_dim"], tokens, channels, d["text_dim"], d["cond_dim"],
                       d["layers"], d["heads"], d["ff_size"], d["max_len"],
                       "none" if v2 else "relu", v2, EMBED_DIM if v2 else WIDTH,
                       "silu" if v2 else "none")
    traj = mc.TrajEncoder(WIDTH, tokens, channels, TRAJ["layers"], TRAJ["heads"],
                          TRAJ["ff_size"], TRAJ["max_len"], v2)
    gen = torch.Generator().manual_seed(SEEDS[r])
    randomize(cn, gen)
    randomize(traj, gen)
    state.update({"controlnet." + k: v.clone() for k, v in cn.state_dict().items()})
    state.update({"traj_encoder." + k: v.clone() for k, v in traj.state_dict().items()})
    for k in ("controlnet.controlnet_cond_embedding.2.weight",
              "controlnet.controlnet_down_mid_blocks.0.weight",
              "controlnet.time_embedding.cond_proj.weight"):
        if k in state:
            assert state[k].abs().min() > 0, k
    # Recognised and dropped by the converter.
    if v2:
        state["controlnet.latent_post.weight"] = torch.randn(channels, WIDTH, generator=gen)
        state["controlnet.latent_post.bias"] = torch.randn(channels, generator=gen)
    else:
        state["controlnet.mem_pos.pe"] = torch.randn(d["max_len"], 1, WIDTH, generator=gen)
    return {"state_dict": state}


# -- 2. convert ----------------------------------------------------------------------------------

def control_args(ckpt, folder, tmp, out, r, *more):
    return base.convert_args(ckpt, folder, tmp, out, "--control-mean",
                             os.path.join(tmp, f"mean_raw_{r}.npy"), "--control-std",
                             os.path.join(tmp, f"std_raw_{r}.npy"), *more)


def refuse(argv, needle):
    err = run_convert(argv, expect_ok=False)
    assert needle in err, (needle, err)


def make_files(tmp, mean_raw, std_raw):
    model, dense, tok = base.tiny_t5()
    folders = {"v1": os.path.join(tmp, "st5_safetensors"), "v2": os.path.join(tmp, "st5_bin")}
    base.write_folder(folders["v1"], model, dense, tok, binary=False)
    base.write_folder(folders["v2"], model, dense, tok, binary=True)
    np.save(os.path.join(tmp, "mean_raw_v1.npy"), mean_raw.reshape(66))
    np.save(os.path.join(tmp, "std_raw_v1.npy"), std_raw.reshape(66))
    np.save(os.path.join(tmp, "mean_raw_v2.npy"), mean_raw.reshape(22, 3))
    np.save(os.path.join(tmp, "std_raw_v2.npy"), std_raw.reshape(22, 3))
    ckpts = {}
    for r in ("v1", "v2"):
        ckpts[r] = control_checkpoint(r)
        path = os.path.join(tmp, f"control_{r}.ckpt")
        torch.save(ckpts[r], path)
        out = os.path.join(FIX, OUT[r])
        run_convert(control_args(path, folders[r], tmp, out, r))
        base.canonical_header(out)
        with safe_open(out, "pt") as f:
            cfg = json.loads(f.metadata()["flame.config"])
            names = set(f.keys())
            stats = f.get_tensor("control.mean_raw")
        want = {"joints": 22, "layers": TRAJ["layers"], "heads": 4, "ff_size": TRAJ["ff_size"],
                "max_len": TRAJ["max_len"], "embed_activation": "silu" if r == "v2" else "none",
                "embed_dim": EMBED_DIM if r == "v2" else WIDTH,
                "frame_mask": "mask" if r == "v2" else "row_sum", "scale": 1.0}
        assert cfg["control"] == want, cfg["control"]
        assert torch.equal(stats, torch.from_numpy(mean_raw)), r
        assert not any(n.startswith(("controlnet.latent_post", "controlnet.mem_pos",
                                     "controlnet.encoder.norm")) for n in names)
        keys = ("0", "2", "4") if r == "v2" else ("0", "1", "2")
        assert {n.split(".")[2] for n in names
                if n.startswith("controlnet.controlnet_cond_embedding.")} == set(keys)
        # The text-to-motion part alone is motionlcm_{r}_tiny.safetensors.
        skipped = os.path.join(tmp, f"skipped_{r}.safetensors")
        run_convert(base.convert_args(path, folders[r], tmp, skipped, "--skip-prefix",
                                      "controlnet.", "--skip-prefix", "traj_encoder."))
        base.same_tensors(skipped, os.path.join(FIX, base.OUT[r]))

    # f16: the statistics stay float32.
    f16 = os.path.join(tmp, "control_f16.safetensors")
    run_convert(control_args(os.path.join(tmp, "control_v2.ckpt"), folders["v2"], tmp, f16, "v2",
                             "--dtype", "f16"))  # the later --dtype wins
    with safe_open(f16, "pt") as f:
        assert f.get_tensor("control.std_raw").dtype == torch.float32
        assert f.get_tensor("traj_encoder.global_motion_token").dtype == torch.float16

    # Refusals.
    v1 = os.path.join(tmp, "control_v1.ckpt")
    fa = folders["v1"]
    refuse(base.convert_args(v1, fa, tmp, os.path.join(tmp, "r.st")),
           "converting trajectory control needs --control-mean")
    bad = std_raw.copy()
    bad[7, 1] = 0.0
    np.save(os.path.join(tmp, "std_raw_zero.npy"), bad)
    refuse(base.convert_args(v1, fa, tmp, os.path.join(tmp, "r.st"), "--control-mean",
                             os.path.join(tmp, "mean_raw_v1.npy"), "--control-std",
                             os.path.join(tmp, "std_raw_zero.npy")),
           "Std_raw must be > 0; joint 7 axis 1")
    gen = torch.Generator().manual_seed(SEEDS["extra"])
    state = dict(ckpts["v1"]["state_dict"])
    state["controlnet.controlnet_down_mid_blocks.1.weight"] = torch.randn(WIDTH, WIDTH + 1,
                                                                          generator=gen)
    torch.save({"state_dict": state}, os.path.join(tmp, "bad_down.ckpt"))
    refuse(control_args(os.path.join(tmp, "bad_down.ckpt"), fa, tmp, os.path.join(tmp, "r.st"),
                        "v1"),
           "tensor 'controlnet.controlnet_down_mid_blocks.1.weight' has shape (32, 33), "
           "expected (32, 32)")
    state = dict(ckpts["v2"]["state_dict"])
    state["traj_encoder.global_motion_token"] = torch.randn(5, WIDTH, generator=gen)
    torch.save({"state_dict": state}, os.path.join(tmp, "bad_tokens.ckpt"))
    refuse(control_args(os.path.join(tmp, "bad_tokens.ckpt"), folders["v2"], tmp,
                        os.path.join(tmp, "r.st"), "v2"), "the latent has 4 tokens")
    refuse(control_args(v1, fa, tmp, os.path.join(tmp, "r.st"), "v1", "--skip-prefix",
                        "traj_encoder."), "'controlnet.*' tensors without 'traj_encoder.*'")


# -- 3. expected values --------------------------------------------------------------------------

def targets(gen, mean_raw, std_raw, pattern):
    """[F, 22, 3] random targets (Mean_raw + Std_raw · N(0, 1)) where `pattern` [F, 22] is True,
    NaN elsewhere."""
    x = torch.from_numpy(mean_raw) + torch.from_numpy(std_raw) * torch.randn(
        (FRAMES, 22, 3), generator=gen)
    return torch.where(pattern[..., None], x, torch.tensor(float("nan")))


def release_expected(r, text, mean_np, std_np):
    den, cn, traj, dec, _, _, cfg, mean_raw, std_raw = mc.load_libflame(os.path.join(FIX, OUT[r]))
    assert torch.equal(mean_raw, torch.from_numpy(mean_np))
    tokens, channels = base.LATENT[r]
    gen = torch.Generator().manual_seed(SEEDS["joints"])  # the same targets for both releases
    t = {}

    # The main hint.
    pat = torch.zeros(FRAMES, 22, dtype=torch.bool)
    pat[:, 0] = True
    for j in HINTED["early_joints"]:
        pat[HINTED["early_frames"], j] = True
    joints = targets(gen, mean_np, std_np, pat)
    hint, valid, cond = mc.control_condition(traj, cfg, joints, mean_raw, std_raw)
    assert valid.all() and cond.shape == (tokens, channels)
    t[f"{r}.joints"], t[f"{r}.hint"] = joints, hint
    t[f"{r}.frame_mask"], t[f"{r}.control_cond"] = valid.float(), cond

    # The sparse hint: key padding and the two frame-mask rules.
    pat = torch.zeros(FRAMES, 22, dtype=torch.bool)
    pat[0::4, 0] = True
    pat[9:12, 20] = pat[9:12, 21] = True
    pat[2, 15] = True
    sj = targets(gen, mean_np, std_np, pat)
    sj[2, 15] = mean_raw[15]  # normalised to exactly 0
    sh, sv, sc = mc.control_condition(traj, cfg, sj, mean_raw, std_raw)
    want = pat.any(1).clone()
    if r == "v1":
        want[2] = False
    assert torch.equal(sv, want), (r, sv)
    # Masked frames are not attended: their hint values do not matter.
    junk = sh.clone()
    junk[~sv] = torch.randn(int((~sv).sum()), 66, generator=gen)
    with torch.no_grad():
        sc2 = traj(junk[None], sv[None])[0]
        sc_all = traj(sh[None], torch.ones_like(sv)[None])[0]
    assert torch.allclose(sc, sc2, atol=1e-6), r
    assert float((sc - sc_all).abs().max()) > 1e-3  # the mask is live
    t[f"{r}.sparse.joints"], t[f"{r}.sparse.hint"] = sj, sh
    t[f"{r}.sparse.frame_mask"], t[f"{r}.sparse.control_cond"] = sv.float(), sc

    # No hinted value at all: every frame masked, the L global tokens attend to themselves.
    ej = torch.full((FRAMES, 22, 3), float("nan"))
    eh, ev, ec = mc.control_condition(traj, cfg, ej, mean_raw, std_raw)
    assert not ev.any() and not eh.any()
    assert torch.isfinite(ec).all(), ec
    t[f"{r}.empty_cond"] = ec

    # One forward.
    g = torch.Generator().manual_seed(SEEDS["inputs"] + (0 if r == "v1" else 100))
    z = torch.randn((1, tokens, channels), generator=g)
    tt = torch.tensor([699.0])
    emb = motionlcm.guidance_embedding(torch.tensor([6.5]), cfg["denoiser"]["cond_dim"])
    scale = cfg["control"]["scale"]
    with torch.no_grad():
        eps, res = mc.controlled_eps(den, cn, z, tt, emb, text[None], cond[None], scale)
        plain = den(z, tt, emb, text[None])
        assert torch.equal(mc.denoise(den, z, tt, emb, text[None]), plain)
        zero = [torch.zeros_like(x) for x in res]
        assert torch.allclose(mc.denoise(den, z, tt, emb, text[None], zero), plain, atol=1e-6)
    diff = float((eps - plain).abs().max())
    assert diff > 1e-2, diff
    t[f"{r}.forward.z"], t[f"{r}.forward.t"], t[f"{r}.forward.w"] = z, tt, torch.tensor([6.5])
    t[f"{r}.residuals"] = torch.stack([x[:, 0] for x in res])
    t[f"{r}.forward.eps"], t[f"{r}.forward.eps_plain"] = eps, plain
    assert t[f"{r}.residuals"].shape == (LAYERS, tokens + 2, WIDTH)
    maxes = {"residual": float(t[f"{r}.residuals"].abs().max()), "eps": float(eps.abs().max()),
             "eps - plain": diff, "cond": float(cond.abs().max()),
             "empty cond": float(ec.abs().max())}

    for n in (1, 2):
        noise = torch.randn((1, tokens, channels), generator=g)
        renoise = torch.randn((max(n - 1, 1), tokens, channels), generator=g)
        gs = motionlcm.guidance_for(cfg, n)
        steps, samples, denoised = mc.sample(den, cn, cfg, noise, text[None], gs, n,
                                             renoise[: n - 1], cond)
        _, _, free = motionlcm.sample(den, cfg, noise, text[None], gs, n, renoise[: n - 1])
        assert float((free[-1] - denoised[-1]).abs().max()) > 1e-3  # control changes the result
        with torch.no_grad():
            feats = dec(denoised[-1], FRAMES)[0]
        t[f"{r}.s{n}.noise"], t[f"{r}.s{n}.renoise"] = noise, renoise
        t[f"{r}.s{n}.guidance"] = torch.tensor([gs])
        t[f"{r}.s{n}.timesteps"] = torch.tensor(steps, dtype=torch.float32)
        t[f"{r}.s{n}.latent"] = denoised[-1].clone()
        t[f"{r}.s{n}.denoised"] = denoised[:, 0]
        t[f"{r}.s{n}.features"] = feats
        maxes[f"s{n} latent"] = float(denoised[-1].abs().max())
        maxes[f"s{n} |latent - uncontrolled|"] = float((free[-1] - denoised[-1]).abs().max())
    log(f"{r}: max " + ", ".join(f"{k} {v:.3g}" for k, v in maxes.items()))
    return t


def main():
    torch.set_num_threads(1)
    gen = np.random.default_rng(base.SEEDS["stats"])  # make_motionlcm_fixtures' statistics
    mean = gen.normal(0, 0.5, 263).astype(np.float32)
    std = gen.uniform(0.05, 1.0, 263).astype(np.float32)
    gen = np.random.default_rng(SEEDS["stats"])
    mean_raw = gen.normal(0, 0.5, (22, 3)).astype(np.float32)
    std_raw = gen.uniform(0.5, 1.5, (22, 3)).astype(np.float32)
    tmp = tempfile.mkdtemp(prefix="motionlcm_control_fixtures_")
    try:
        np.save(os.path.join(tmp, "mean.npy"), mean)
        np.save(os.path.join(tmp, "std.npy"), std)
        make_files(tmp, mean_raw, std_raw)
    finally:
        shutil.rmtree(tmp)

    # Prompt 0's text vector from the converted file's T5, as make_motionlcm_fixtures computes it.
    _, _, _, _, text_model, tok, _, _, _ = mc.load_libflame(os.path.join(FIX, OUT["v1"]))
    _, text = motionlcm.encode_text(text_model, tok, base.PROMPTS[0])
    ref = load_file(os.path.join(FIX, base.EXPECTED))["text.0"]
    assert float((text - ref).abs().max()) < 1e-6
    expected = {"text.0": text}
    for r in ("v1", "v2"):
        expected.update(release_expected(r, text, mean_raw, std_raw))
    expected = {k: v.float().contiguous() for k, v in sorted(expected.items())}
    for k, v in expected.items():
        if k.endswith("joints"):
            assert torch.isnan(v).any() and torch.isfinite(v[~torch.isnan(v)]).all(), k
        else:
            assert torch.isfinite(v).all(), k
        log(f"  {k:26s} {str(list(v.shape)):14s} max|x| {v.nan_to_num().abs().max():.4g}")
    save_file(expected, os.path.join(FIX, EXPECTED),
              metadata={"prompts": json.dumps(base.PROMPTS[:1]), "frames": str(FRAMES),
                        "hinted": json.dumps(HINTED),
                        "generator": "tools/make_motionlcm_control_fixtures.py"})
    base.canonical_header(os.path.join(FIX, EXPECTED))
    total = sum(os.path.getsize(os.path.join(FIX, n)) for n in list(OUT.values()) + [EXPECTED])
    log(f"motionlcm control fixtures total {total / 1e6:.2f} MB")
    assert total < 2e6, "motionlcm control fixtures must stay small"
    return 0


if __name__ == "__main__":
    sys.exit(main())
