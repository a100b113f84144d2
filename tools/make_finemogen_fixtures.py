#!/usr/bin/env python3
"""Generate the FineMoGen parity fixtures in tests/fixtures/ (seeded, deterministic).

Steps:
 1. A tiny random FineMoGen (sizes of docs/model-files-finemogen.md) with every weight nonzero,
    rounded to f16 (the fixture file is f16, to stay small); the gates of its four MoEs are then
    shaped (below) and rounded again. A tiny CLIP text tower (8 wide, 2 layers, 2 heads) and the
    real CLIP tokenizer (tests/fixtures/clip_tokenizer).
 2. The official mmcv layout (`model.*` with the key_motion / _num_global_experts buffers, the
    CLIP under `model.clip.*` in OpenAI names) is converted with `convert.py finemogen --dtype
    f16`; the same checkpoint without model.clip.* plus the tower as a Hugging Face folder (and
    as an OpenAI state-dict file) must convert to identical tensors; the converter's errors
    (unknown / missing tensor, wrong expert count, KIT size) are checked.
 3. The CONVERTED file is loaded back into tools/reference/finemogen.py; the routing is checked
    against a literal transcription of tutel's slot computation; one forward is cross-checked
    against a float64 run; every case is sampled in float32 and float64 and the routing
    decisions (experts, kept/dropped) of every MoE call must be identical; the margins of those
    decisions and the capacity drops are recorded; the expected values are written.

Gate shaping
(docs/official/finemogen.md#reproduction-hazards). For an MoE with input LayerNorm weight γ, the gate's projector
maps the token x = LN(h) + embedding[s, head] to v = W x + b. Its component in the 4-dim span
of the expert directions is rank one along u = (1/γ)/|1/γ|: since Σ_i z_i = 0 for a LayerNorm
output z, <u, γ⊙z> = 0, so that component is (1, α<u, β + embedding>) whatever the content: the
direction, hence which experts a token picks and in which order, follows the embedding alone
(up to the f16 rounding of W). The content only moves the orthogonal part of v, which scales all
cosines together (and so the top-1 scores a little). Each (position, head) gets a role through
the embedding: H (expert 0 first, high score; second expert 1, 2 or 3), M (expert 0 first,
middle score), L (expert 0 first, low score), X (expert 1 first, expert 0 second). The motion
MoE has per position 6 H heads, 1 L, 1 X; its capacity is exactly 6/8 of the tokens
(2·int(1.5·ceil(S/4)) with S = rows·T·8), so expert 0 keeps exactly the H tokens: the L first
choices and the X second choices (expert 0 full) are dropped, at a cut between score clusters.
In the last layer every H and L token's second choice is expert 3, which keeps the 6/8 with the
higher top-1 scores (H): the L tokens lose both choices (fully dropped).
The text MoE has per sequence 57 H positions, 1 M, 10 L, 9 X; with 2 or 6 sequences the cut
falls between M and L; with the 4 sequences of the staged case (A, B and their null copies) it
falls inside M, between prompt A's and prompt B's tokens, whose scores then differ only by the
content (checked to be far apart). The generator checks every margin on every MoE call.

Run from anywhere: python tools/make_finemogen_fixtures.py   (~1 min)
"""
import json
import math
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
sys.path.insert(0, TOOLS)

import make_finemogen_checkpoint as mk  # noqa: E402
from reference import finemogen as fm  # noqa: E402

TOKENIZER = os.path.join(FIX, "clip_tokenizer", "tokenizer.json")
# Steps (1-based) whose sample and x0 the fixture stores: the trajectory runs all 50.
STEPS_KEPT = [1, 10, 25, 40, 50]
PROMPTS = {"A": "a person walks forward and waves with the left hand",
           "B": "a person jumps", "C": "the person turns around"}
FRAMES = 40
STAGES = (("A", 24), ("B", 31))
PART_TEXTS = {"larm": "B", "root": "C"}
FORWARD_T = 640
GUIDANCE = 6.5
RESPACING = "15,15,8,6,6"
SEEDS = {"net": 40, "clip": 41, "gates": 42, "stats": 43, "forward": 44, "single": 45,
         "stages": 46, "parts": 47}
OWNED = ["finemogen_tiny.safetensors", "finemogen_expected.safetensors",
         "finemogen_expected.json"]
TEXT_PROJ_GAIN = 4.0
# Required routing margins (score units); f32 errors of the scores are ~1e-7.
MIN_ORDER_GAP = 1e-3
MIN_BOUNDARY_GAP = 1e-4

# Expert directions in the gate's expert plane: (angle, in-plane amplitude).
EXPERT_DIRS = [(0.0, 1.0), (-50.0, 1.0), (0.0, 0.8), (50.0, 1.0)]
# Role -> interval of plane angles (degrees), or of the logit gap between expert 0 and expert 3
# (M, L: angles solved per gate from its logit scale), see the module docstring.
ROLE_ANGLES = {"H1": (-18.0, -15.0), "H2": (-5.0, 5.0), "H3": (15.0, 18.0), "X": (-40.0, -35.0)}
ROLE_GAPS = {"M": (2.0, 2.0), "L": (0.3, 0.5)}
MOTION_ROLES = ["H1", "H1", "H2", "H2", "H3", "H3", "L", "X"]
# The last layer's motion MoE: every expert-0 token's second choice is expert 3, which then
# keeps only the H seconds: the L tokens lose both choices (output 0, wrapper output proj.bias).
MOTION_ROLES_FULL_DROP = ["H3"] * 6 + ["L", "X"]
TEXT_ROLES = ["H1"] * 19 + ["H2"] * 19 + ["H3"] * 19 + ["M"] + ["L"] * 10 + ["X"] * 9
# Size of the projector's part orthogonal to the expert span, relative to the span part.
RHO = {"motion": 0.15, "text": 0.4}


def log(msg):
    print(msg, file=sys.stderr)


def f16(t):
    return t.half().float()


# -- gate shaping ----------------------------------------------------------------------------------

def angle_for_gap(gap, scale):
    """Plane angle in (0, 25) degrees where scale·(cos θ - cos(θ - 50°)) = gap."""
    lo, hi = 0.0, 25.0
    for _ in range(60):
        mid = (lo + hi) / 2
        f = scale * (math.cos(math.radians(mid)) - math.cos(math.radians(mid - 50)))
        lo, hi = (mid, hi) if f > gap else (lo, mid)
    return lo


@torch.no_grad()
def shape_gate(moe, ln, roles, gen, rho, alpha=1.0):
    """Set moe.embedding and the gate projector / sim_matrix of one MoE (module docstring).
    roles[s][h]: role of position s, head h. rho: relative size of the projector's part
    orthogonal to the expert span."""
    gate = moe.model.gates[0]
    g, e = gate.sim_matrix.shape
    d = moe.embedding.shape[-1]
    scale = float(torch.clamp(gate.temperature, max=math.log(100.0)).exp())
    scale /= math.sqrt(1 + rho ** 2)  # the nominal shrink of the cosines by the orthogonal part
    q, _ = torch.linalg.qr(torch.randn(g, g, generator=gen, dtype=torch.float64))
    qm, qp = q[:, :e], q[:, e:]
    gamma, beta = ln.weight.double(), ln.bias.double()
    u = 1.0 / gamma
    u = u / u.norm()
    a = torch.zeros(e, dtype=torch.float64)
    a[1] = alpha
    b = torch.zeros(e, dtype=torch.float64)
    b[0] = 1.0
    # |x| is about sqrt(2 d) (LayerNorm output plus an N(0, 1) embedding).
    sd = rho / math.sqrt((g - e) * 2 * d)
    r_perp = sd * torch.randn(g - e, d, generator=gen, dtype=torch.float64)
    b_perp = sd * torch.randn(g - e, generator=gen, dtype=torch.float64)
    w = qm @ torch.outer(a, u) + qp @ r_perp
    gate.cosine_projector.weight.copy_(w.float())
    gate.cosine_projector.bias.copy_((qm @ b + qp @ b_perp).float())
    cols = []
    for k, (ang, amp) in enumerate(EXPERT_DIRS):
        rest = math.sqrt(max(1 - amp * amp, 0.0)) + 0.05
        c = torch.tensor([amp * math.cos(math.radians(ang)), amp * math.sin(math.radians(ang)),
                          rest * (1 if k % 2 else -1) * 0.8, rest * 0.6], dtype=torch.float64)
        cols.append(c / c.norm() * (0.5 + torch.rand(1, generator=gen, dtype=torch.float64)))
    gate.sim_matrix.copy_((qm @ torch.stack(cols, 1)).float())
    seq, heads = moe.embedding.shape[1:3]
    emb = torch.randn(seq, heads, d, generator=gen, dtype=torch.float64)
    for s in range(seq):
        for h in range(heads):
            role = roles[s][h]
            f = float(torch.rand(1, generator=gen))
            if role in ROLE_GAPS:
                lo, hi = ROLE_GAPS[role]
                ang = angle_for_gap(lo + (hi - lo) * f, scale)
            else:
                lo, hi = ROLE_ANGLES[role]
                ang = lo + (hi - lo) * f
            k = math.tan(math.radians(ang)) / alpha
            x = emb[s, h]
            emb[s, h] = x + (k - float(u @ (x + beta))) * u
    moe.embedding.copy_(emb[None].float())


def role_table(base, seq, heads, gen):
    """roles[s][h]: a random arrangement of `base` per position (motion: over the 8 heads) or
    over the positions (text, heads = 1)."""
    if heads > 1:
        return [[base[i] for i in torch.randperm(heads, generator=gen).tolist()]
                for _ in range(seq)]
    perm = torch.randperm(seq, generator=gen).tolist()
    return [[base[i]] for i in perm]


def top1_scores(moe, ln, xf):
    """Top-1 gate scores of the text MoE's tokens for the sequences xf [N, 77, M] -> [N, 77]."""
    with torch.no_grad():
        x = (ln(xf).unsqueeze(2) + moe.embedding[:, :xf.shape[1]]).reshape(-1, xf.shape[-1])
        return torch.softmax(moe.model.gates[0](x), 1).max(1).values.view(xf.shape[0], -1)


@torch.no_grad()
def place_middle(moe, ln, roles, xf_ab):
    """Move the text MoE's single M role to the position where the scores of prompts A and B
    differ most (the staged case cuts there), giving the displaced role a mid-range value."""
    gamma, beta = ln.weight.double(), ln.bias.double()
    u = 1.0 / gamma
    u = u / u.norm()
    emb = moe.embedding.data
    m_old = [s for s in range(len(roles)) if roles[s][0] == "M"][0]
    k_m = float(u @ (emb[0, m_old, 0].double() + beta))
    gaps = []
    for q in range(len(roles)):
        if roles[q][0] not in ("H1", "H2", "H3") and q != m_old:
            gaps.append(-1.0)
            continue
        saved = emb[0, q, 0].clone()
        x = saved.double()
        emb[0, q, 0] = (x + (k_m - float(u @ (x + beta))) * u).float()
        p = top1_scores(moe, ln, xf_ab)[:, q]
        gaps.append(float((p[0] - p[1]).abs()))
        emb[0, q, 0] = saved
    q = int(np.argmax(gaps))
    if q != m_old:
        role = roles[q][0]
        lo, hi = ROLE_ANGLES[role]
        k = math.tan(math.radians((lo + hi) / 2))
        x = emb[0, m_old, 0].double()
        emb[0, m_old, 0] = (x + (k - float(u @ (x + beta))) * u).float()
        x = emb[0, q, 0].double()
        emb[0, q, 0] = (x + (k_m - float(u @ (x + beta))) * u).float()
        roles[m_old], roles[q] = [role], ["M"]
    return q, gaps[q]


def build_models():
    """(net, clip) with f16-valued weights and shaped gates; the text MoEs' M positions."""
    torch.manual_seed(SEEDS["net"])
    net = fm.FineMoGenNet(mk.TINY)
    mk.randomize(net, torch.Generator().manual_seed(SEEDS["net"]))
    clip = mk.clip_model("tiny", SEEDS["clip"])
    with torch.no_grad():
        # A 4x stronger text path (keys and values of the text tokens), so that the fixtures
        # resolve the effect of the prompt and of the part texts well above f32 noise.
        for blk in net.temporal_decoder_blocks:
            blk.ca_block.text_moe.proj.weight.mul_(TEXT_PROJ_GAIN)
            blk.ca_block.text_moe.proj.bias.mul_(TEXT_PROJ_GAIN)
        for p in list(net.parameters()) + list(clip.parameters()):
            p.copy_(f16(p))
    net.eval()
    tok = tokenizer()
    ids = torch.tensor([fm.clip_ids(tok, PROMPTS[k]) for k in ("A", "B")])
    with torch.no_grad():
        xf_ab = net.encode_clip_features(fm.clip_features(clip, ids))
    gen = torch.Generator().manual_seed(SEEDS["gates"])
    middle = []
    last = len(net.temporal_decoder_blocks) - 1
    for i, blk in enumerate(net.temporal_decoder_blocks):
        sami = blk.ca_block
        mo = sami.motion_moe
        base = MOTION_ROLES_FULL_DROP if i == last else MOTION_ROLES
        shape_gate(mo, sami.norm, role_table(base, mo.embedding.shape[1], 8, gen), gen,
                   rho=RHO["motion"])
        tm = sami.text_moe
        roles = role_table(TEXT_ROLES, tm.embedding.shape[1], 1, gen)
        shape_gate(tm, sami.text_norm, roles, gen, rho=RHO["text"])
        middle.append(place_middle(tm, sami.text_norm, roles, xf_ab))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(f16(p))
            assert (p != 0).all()
    for p in clip.parameters():
        assert (p != 0).all()
    log(f"text MoE middle positions (A/B score gap before rounding): {middle}")
    return net, clip, [q for q, _ in middle]


def tokenizer():
    from tokenizers import Tokenizer
    return Tokenizer.from_file(TOKENIZER)


# -- checkpoint and converter --------------------------------------------------------------------

def run_convert(argv, expect_ok=True):
    r = subprocess.run([sys.executable, os.path.join(TOOLS, "convert.py"), "finemogen"] + argv,
                       capture_output=True, text=True)
    log((r.stdout + r.stderr).strip())
    assert (r.returncode == 0) == expect_ok, (argv, r.returncode)
    return r.stderr


def convert_and_check(tmp, net, clip):
    """Write the official layouts, convert, check the converter; returns the fixture path."""
    gen = torch.Generator().manual_seed(SEEDS["net"] + 100)
    with_clip = mk.official_state(net, clip, gen)
    mk.save_checkpoint(os.path.join(tmp, "latest.pth"), with_clip)
    no_clip = {k: v for k, v in with_clip.items() if not k.startswith("model.clip.")}
    mk.save_checkpoint(os.path.join(tmp, "noclip.pth"), no_clip)
    mk.write_hf_clip(os.path.join(tmp, "clip"), clip)
    openai = {k[len("model.clip."):]: v for k, v in with_clip.items()
              if k.startswith("model.clip.")}
    torch.save(openai, os.path.join(tmp, "ViT-tiny.pt"))
    rng = np.random.default_rng(SEEDS["stats"])
    np.save(os.path.join(tmp, "mean.npy"), rng.normal(0, 0.5, 263).astype(np.float32))
    np.save(os.path.join(tmp, "std.npy"), rng.uniform(0.05, 1.0, 263).astype(np.float32))
    stats = ["--mean", os.path.join(tmp, "mean.npy"), "--std", os.path.join(tmp, "std.npy")]
    tok = ["--tokenizer", TOKENIZER]
    out = os.path.join(FIX, "finemogen_tiny.safetensors")
    run_convert(["--ckpt", os.path.join(tmp, "latest.pth"), "--clip-heads", "2", "--dtype", "f16",
                 "--out", out] + tok + stats)
    canonical_header(out)
    # The CLIP from a Hugging Face folder or an OpenAI state-dict file: the same file.
    ref = load_file(out)
    for name, argv in (("hf", ["--clip", os.path.join(tmp, "clip")]),
                       ("openai", ["--clip", os.path.join(tmp, "ViT-tiny.pt"), "--clip-heads", "2"]
                        + tok)):
        other = os.path.join(tmp, f"{name}.safetensors")
        run_convert(["--ckpt", os.path.join(tmp, "noclip.pth"), "--dtype", "f16", "--out", other]
                    + argv + stats)
        got = load_file(other)
        assert sorted(got) == sorted(ref), (name, set(got) ^ set(ref))
        for k in ref:
            assert torch.equal(got[k], ref[k]), (name, k)
        assert read_meta(other) == read_meta(out), name
    # Strictness.
    bad = os.path.join(tmp, "bad.pth")
    x = os.path.join(tmp, "x.safetensors")
    common = ["--clip", os.path.join(tmp, "clip"), "--out", x] + stats
    cases = [
        ("unknown", dict(no_clip, **{"model.extra.weight": torch.ones(2)}),
         "unknown tensor 'model.extra.weight'"),
        ("missing", {k: v for k, v in no_clip.items()
                     if k != "model.temporal_decoder_blocks.1.ffn.linear2_list.7.bias"},
         "missing tensor 'model.temporal_decoder_blocks.1.ffn.linear2_list.7.bias'"),
        ("experts", dict(no_clip, **{
            "model.temporal_decoder_blocks.0.ca_block.text_moe.model._num_global_experts":
            torch.tensor(5)}), "_num_global_experts' = 5"),
        ("kit", dict(no_clip, **{"model.joint_embed.body_embed.weight": torch.ones(16, 251)}),
         "KIT-ML"),
        ("top", dict(no_clip, **{"loss.weight": torch.ones(1)}), "unknown tensor 'loss.weight'"),
    ]
    for name, state, want in cases:
        mk.save_checkpoint(bad, state)
        err = run_convert(["--ckpt", bad] + common, expect_ok=False)
        assert want in err, (name, err)
    err = run_convert(["--ckpt", os.path.join(tmp, "noclip.pth"), "--out", x] + stats,
                      expect_ok=False)
    assert "has no model.clip.*" in err, err
    return out


def canonical_header(path):
    """Rewrite a safetensors header with its metadata keys sorted (safetensors writes them in
    hash-map order), so the file is byte-for-byte reproducible; tensor data is untouched."""
    import struct
    with open(path, "rb") as f:
        blob = f.read()
    n = struct.unpack("<Q", blob[:8])[0]
    header = json.loads(blob[8:8 + n])
    meta = header.pop("__metadata__")
    ordered = {"__metadata__": dict(sorted(meta.items()))}
    ordered.update(header)
    text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)) + text + blob[8 + n:])


def read_meta(path):
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        return f.metadata()


# -- checks ----------------------------------------------------------------------------------------

def tutel_slots(scores, topk, capacity):
    """A literal transcription of tutel's extract_critical (batch-prioritised) slot computation
    with a stable argsort: one-hot masks, cumsum - 1 in importance order, unsorted by argsort of
    the argsort, second choices offset by the first-choice counts."""
    e = scores.shape[1]
    idx = torch.topk(scores, topk, dim=1).indices
    masks = [F.one_hot(idx[:, k], e) for k in range(topk)]
    importance = -1 * scores.max(dim=1)[0]
    order = importance.argsort(dim=0, stable=True)
    inverse = order.argsort(dim=0, stable=True)

    def location(m):
        sm = m[order]
        return ((torch.cumsum(sm, 0) - 1) * sm)[inverse]

    slots = [torch.sum(location(masks[0]) * masks[0], dim=1)]
    base = None
    for k in range(1, topk):
        base = masks[k - 1].sum(0, keepdim=True) if base is None else \
            base + masks[k - 1].sum(0, keepdim=True)
        slots.append(torch.sum((location(masks[k]) + base) * masks[k], dim=1))
    return idx, torch.stack(slots, 1)


def check_routing_transcription(net):
    gen = torch.Generator().manual_seed(7)
    for n in (154, 640, 991):
        scores = torch.softmax(3 * torch.randn(n, 4, generator=gen), 1)
        scores[5] = scores[3]  # exact ties between tokens: the lower index goes first
        scores[n - 1] = scores[0]
        cap = net.temporal_decoder_blocks[0].ca_block.motion_moe.model.capacity(n)
        ex, _, sl = fm.route(scores, 2, cap)
        ex2, sl2 = tutel_slots(scores, 2, cap)
        assert torch.equal(ex, ex2) and torch.equal(sl, sl2), n
    log("routing slots equal tutel's formulation (stable tie order) on 3 random batches")


def max_err(a, b):
    return float((a.double() - b.double()).abs().max())


# -- cases -----------------------------------------------------------------------------------------

class Encoder:
    def __init__(self, net, clip, tok):
        self.net, self.clip, self.tok, self.cache = net, clip, tok, {}

    def ids(self, text):
        return fm.clip_ids(self.tok, text)

    def clip_feat(self, text):
        dt = next(self.clip.parameters()).dtype
        with torch.no_grad():
            return fm.clip_features(self.clip, torch.tensor([self.ids(text)]))[0].to(dt)

    def __call__(self, text):
        if text not in self.cache:
            with torch.no_grad():
                self.cache[text] = self.net.encode_clip_features(self.clip_feat(text)[None])[0]
        return self.cache[text]


def stage_list(case):
    if case in ("forward", "single"):
        return [fm.Stage(PROMPTS["A"], FRAMES)]
    if case == "stages":
        return [fm.Stage(PROMPTS[k], n) for k, n in STAGES]
    return [fm.Stage(PROMPTS["A"], FRAMES, {p: PROMPTS[k] for p, k in PART_TEXTS.items()})]


def noise_for(case, stages):
    gen = torch.Generator().manual_seed(SEEDS[case])
    return torch.randn(len(stages), max(s.frames for s in stages), 263, generator=gen)


def run_case(net, enc, case, noise):
    """One case in the dtype of net; returns (outputs, MoE log)."""
    stages = stage_list(case)
    xf, index, texts = fm.condition(stages, enc)
    net.moe_log = []
    x = noise.to(xf.dtype)
    with torch.no_grad():
        if case == "forward":
            lengths = torch.tensor([s.frames for s in stages])
            text, null = net(x, FORWARD_T, lengths, xf, index, 1)
            out = {"text": text, "null": null}
        else:
            out = {"trace": fm.ddim_sample(net, x, stages, xf, index, GUIDANCE, RESPACING)}
    moe_log, net.moe_log = net.moe_log, None
    return out, moe_log, texts, index


def summarize(moe_log):
    """Drop counts and margins per (MoE, layer) over the calls of a case."""
    out = {}
    for r in moe_log:
        key = f"{r['tag'][0]}.layer{r['tag'][1]}"
        a = out.setdefault(key, {"calls": 0, "tokens": r["tokens"], "capacity": r["capacity"],
                                 "first_dropped": 0, "second_dropped": 0, "fully_dropped": 0,
                                 "per_call": set(), "min_order_gap_logits": math.inf,
                                 "min_boundary_gap_score": math.inf})
        assert a["tokens"] == r["tokens"] and a["capacity"] == r["capacity"]
        a["calls"] += 1
        a["first_dropped"] += r["dropped"][0]
        a["second_dropped"] += r["dropped"][1]
        a["fully_dropped"] += r["fully_dropped"]
        a["per_call"].add((r["dropped"][0], r["dropped"][1], r["fully_dropped"]))
        a["min_order_gap_logits"] = min(a["min_order_gap_logits"], r["order_gap"])
        a["min_boundary_gap_score"] = min(a["min_boundary_gap_score"], r["boundary_gap"])
    for a in out.values():
        a["per_call"] = [list(v) for v in sorted(a["per_call"])]
        if math.isinf(a["min_boundary_gap_score"]):
            a["min_boundary_gap_score"] = None
    return out


def same_routing(log32, log64, case):
    assert len(log32) == len(log64), case
    for i, (a, b) in enumerate(zip(log32, log64)):
        for x, y in zip(a["decisions"], b["decisions"]):
            assert torch.equal(x, y), (case, i, a["tag"])


def main():
    torch.set_num_threads(1)
    net0, clip0, middle = build_models()
    check_routing_transcription(net0)
    with tempfile.TemporaryDirectory() as tmp:
        path = convert_and_check(tmp, net0, clip0)
    size = os.path.getsize(path)
    log(f"{path}: {size / 1e6:.2f} MB")
    assert size < 4e6, size
    net, clip, tok, cfg, mean, std = fm.load_libflame(path)
    # The file holds exactly the weights built above.
    for (k, v), (k0, v0) in zip(sorted(net.state_dict().items()),
                                sorted(net0.state_dict().items())):
        assert k == k0 and (k.endswith(("key_motion", "_num_global_experts"))
                            or torch.equal(v, v0)), k
    net64, clip64 = fm.load_libflame(path)[0].double(), fm.load_libflame(path)[1].double()
    enc, enc64 = Encoder(net, clip, tok), Encoder(net64, clip64, tok)

    t, info_cases, tol = {}, {}, {}
    for key in ("A", "B", "C"):
        c32, c64 = enc.clip_feat(PROMPTS[key]), enc64.clip_feat(PROMPTS[key])
        t[f"clip.{key}"], t[f"xf.{key}"] = c32, enc(PROMPTS[key])
        tol[f"clip.{key}"] = max_err(c32, c64)
        tol[f"xf.{key}"] = max_err(enc(PROMPTS[key]), enc64(PROMPTS[key]))
    for case in ("forward", "single", "stages", "parts"):
        stages = stage_list(case)
        noise = noise_for(case, stages)
        out, lg, texts, index = run_case(net, enc, case, noise)
        out64, lg64, _, _ = run_case(net64, enc64, case, noise)
        same_routing(lg, lg64, case)
        summary = summarize(lg)
        for k, a in summary.items():
            assert a["min_order_gap_logits"] >= MIN_ORDER_GAP, (case, k, a)
            assert a["min_boundary_gap_score"] is None or \
                a["min_boundary_gap_score"] >= MIN_BOUNDARY_GAP, (case, k, a)
        assert any(a["first_dropped"] + a["second_dropped"] for k, a in summary.items()
                   if k.startswith("text")), case
        assert any(a["first_dropped"] + a["second_dropped"] for k, a in summary.items()
                   if k.startswith("motion")), case
        single = len(stages) == 1
        sq = (lambda v: v[0]) if single else (lambda v: v)
        if case == "forward":
            t["forward.x"] = sq(noise)
            t["forward.text"], t["forward.null"] = sq(out["text"]), sq(out["null"])
            tol["forward.text"] = max_err(out["text"], out64["text"])
            tol["forward.null"] = max_err(out["null"], out64["null"])
        else:
            tr, tr64 = out["trace"], out64["trace"]
            t[f"{case}.noise"] = sq(noise)
            # Stored at STEPS_KEPT only (the float64 cross-check below covers every step).
            kept = [tr[k - 1] for k in STEPS_KEPT]
            t[f"{case}.x"] = torch.stack([sq(s["x"]) for s in kept])
            if case != "parts":
                t[f"{case}.x0"] = torch.stack([sq(s["x0"]) for s in kept])
            tol[f"{case}.x"] = max(max_err(a["x"], b["x"]) for a, b in zip(tr, tr64))
            if case != "parts":
                tol[f"{case}.x0"] = max(max_err(a["x0"], b["x0"]) for a, b in zip(tr, tr64))
            if case == "stages":
                t["stages.motion"] = fm.compose(tr[-1]["x"], stages)
                tol["stages.motion"] = max_err(t["stages.motion"],
                                               fm.compose(tr64[-1]["x"], stages))
            info_cases[case] = {"steps_t": [s["t"] for s in tr],
                                "steps_w": [s["w"] for s in tr]}
        if case == "stages":
            # The text cut of this case falls inside the M position: which copies keep expert 0.
            cut = []
            for layer, q in enumerate(middle):
                r = [x for x in lg if x["tag"] == ("text", layer)][0]
                kept = r["decisions"][1][:, 0].view(len(texts) * 2, -1)[:, q]
                cut.append({"layer": layer, "position": q, "sequences": texts + texts,
                            "first_choice_kept": kept.tolist()})
            info_cases["stages"]["text_middle_cut"] = cut
        info_cases.setdefault(case, {}).update({
            "stages": [{"text": s.text, "frames": s.frames, "parts": s.parts} for s in stages],
            "sequences": texts, "text_index": index.tolist(), "moe": summary})
        log(f"{case}: " + ", ".join(f"{k} drops {a['first_dropped']}/{a['second_dropped']}/"
                                    f"{a['fully_dropped']} gaps {a['min_order_gap_logits']:.3f}/"
                                    f"{a['min_boundary_gap_score']}" for k, a in summary.items()))
    write(t, tol, info_cases, cfg, middle, enc)
    return 0


def write(t, tol, cases, cfg, middle, enc):
    t = {k: v.float().contiguous() for k, v in t.items()}
    for k, v in t.items():
        assert torch.isfinite(v).all(), k
        log(f"  {k:16s} {str(list(v.shape)):18s} max|x| {v.abs().max():.4g}  f64 err "
            f"{tol.get(k, float('nan')):.2e}")
    save_file(t, os.path.join(FIX, "finemogen_expected.safetensors"),
              metadata={"generator": "tools/make_finemogen_fixtures.py"})
    info = {
        "description": "FineMoGen tiny parity fixture; generated by "
                       "tools/make_finemogen_fixtures.py from tools/reference/finemogen.py on the "
                       "converted finemogen_tiny.safetensors (f16 weights, run in float32). "
                       "Frame-major; motion in normalised HumanML3D feature space.",
        "model": "finemogen_tiny.safetensors",
        "prompts": PROMPTS,
        "ids": {k: enc.ids(v) for k, v in PROMPTS.items()},
        "tokenizer": "clip_tokenizer/tokenizer.json; ids = [49406] + content[:75] + [49407], "
                     "zero-padded to 77",
        "forward": {"t": FORWARD_T, "frames": FRAMES, "prompt": "A",
                    "w": fm.guidance_weight(FORWARD_T, GUIDANCE),
                    "note": "forward.text / forward.null: the network's text and null rows on "
                            "forward.x (one stage, all frames valid) at original step t"},
        "single": {"frames": FRAMES, "prompt": "A"},
        "stages": {"La": STAGES[0][1], "Lb": STAGES[1][1], "prompts": ["A", "B"],
                   "Tmax": max(n for _, n in STAGES),
                   "note": "stages.motion = concat(x_final[0][:La], x_final[1][:Lb])"},
        "parts": {"frames": FRAMES, "prompt": "A",
                  "part_texts": {p: k for p, k in PART_TEXTS.items()}},
        "guidance": GUIDANCE, "respacing": RESPACING,
        "sampler": "DDIM eta 0 on x0: x0 = null + w*(text - null), w = 1 + guidance*t/1000 "
                   "(python double, used as float32); eps = (f32(sqrt(1/abar_t))*x - x0) / "
                   "f32(sqrt(1/abar_t - 1)); x_prev = x0*sqrt(f32(abar_prev)) + "
                   "sqrt(1 - f32(abar_prev))*eps (f32 sqrt), abar_prev = 1 at the last step "
                   "(so the final sample is x0); tables float64 (linear betas 1e-4..0.02, "
                   "respaced), cast to float32 per step",
        "trajectories": "*.x[i]: sample after step steps_kept[i] (1-based, first step first), "
                        "*.x0[i]: guided x0 of that step; steps_t: original steps the network "
                        "sees (all 50)",
        "steps_kept": STEPS_KEPT,
        "cases": cases,
        "text_moe_middle_positions": middle,
        "gate_shaping": "see the generator's docstring: routing follows the learned position/"
                        "part embedding; no decision depends on an exact tie (bit-identical "
                        "cond/null tokens always fall on the same side of every cut)",
        "routing": "tutel batch-prioritised, STABLE tie order (lower flattened token index "
                   "[rows, seq, heads], text rows first, wins); capacity = "
                   "topk*int(1.5*ceil(S/E)); moe.*.per_call lists the distinct "
                   "[first, second, fully] drop counts of one call; min_order_gap_logits: "
                   "smallest ln(score_k/score_k+1) for k < 2; min_boundary_gap_score: smallest "
                   "top-1 score difference across a capacity cut (null: no cut inside a list)",
        "tolerance_f64": {k: v for k, v in sorted(tol.items())},
        "tolerance_note": "max |float32 reference - float64 reference| per tensor (the float64 "
                          "run takes the same routing decisions at every call)",
        "seeds": SEEDS,
        "config": cfg,
    }
    info["tensors"] = {k: list(v.shape) for k, v in t.items()}
    with open(os.path.join(FIX, "finemogen_expected.json"), "w") as f:
        json.dump(info, f, indent=1)
        f.write("\n")
    total = sum(os.path.getsize(os.path.join(FIX, n)) for n in OWNED)
    log(f"finemogen fixtures total {total / 1e6:.2f} MB")


if __name__ == "__main__":
    sys.exit(main())
