"""PyTorch reference of FineMoGen's released HumanML3D text-to-motion model
(mingyuan-zhang/FineMoGen d5697b5aa6ad), written from the released code as docs/official/finemogen.md
describes it.

Module names follow the released code, so `FineMoGenNet.state_dict()` has the keys of an official
checkpoint without the `model.` prefix and without `model.clip.*`:
  text_pre_proj, textTransEncoder (nn.TransformerEncoder: post-LN, GELU, sequence-first, no
  padding mask), text_ln, time_embed.{0,2}, joint_embed.{part}_embed,
  temporal_decoder_blocks.{i}.ca_block (SAMI) / .ffn (SFFN), out.{part}_out.
The CLIP text tower is a transformers CLIPTextModelWithProjection run on all 77 positions
(last_hidden_state = ln_final, no projection, no padding mask).

The mixture of experts is tutel's cosine top-k routing written out (9.7): fp32 cosine gate with
exp(min(temperature, ln 100)), softmax scores, top-2, gates renormalised by their sum (clamped at
the float eps), capacity = topk * int(capacity_factor * ceil(S / E)), batch-prioritised slots
(tokens ordered by descending top-1 score with a STABLE sort: among equal scores the lower token
index goes first), a choice whose slot is >= capacity contributes 0. Every MoE call is recorded
in `net.moe_log` (when it is a list) with its drop counts and routing margins.

Also here: body-part texts (libflame's choice 3 of docs/model-files-finemogen.md), the staged
temporal composition (9.13), the respaced DDIM sampler with eta 0 on x0 and the in-network
guidance w(t) = 1 + scale * t / 1000 (9.11). Tensors are frame-major `[B, T, 263]`.
"""
import math

import torch
import torch.nn.functional as F
from torch import nn

from .diffusion import SpacedDiffusion, linear_betas, space_timesteps

PARTS = ("head", "stem", "larm", "rarm", "lleg", "rleg", "root", "body")
# SMPL joints of each part (docs/official/finemogen.md#body-part-split); body = all 22 in order.
PART_JOINTS = {"head": (12, 15), "stem": (3, 6, 9), "larm": (14, 17, 19, 21),
               "rarm": (13, 16, 18, 20), "lleg": (2, 5, 8, 11), "rleg": (1, 4, 7, 10),
               "root": (0,), "body": tuple(range(22))}
NUM_PARTS = 7  # body-part heads; head 7 is the whole body
MASK_VALUE = -1000000.0

RELEASED = dict(input_feats=263, dataset="human_ml3d", part_dim=64, num_layers=4,
                time_embed_dim=2048, max_seq_len=196, clip_width=512, text_latent_dim=256,
                text_layers=2, text_heads=4, text_ff_size=2048, max_text_len=77, ffn_dim=256,
                num_experts=16, topk=2, capacity_factor=1.5, gate_dim=256,
                text_expert_hidden=1024, motion_expert_hidden=256, layer_norm_eps=1e-5)


def t2m_joint_indices(j):
    """HumanML3D 263 feature indices of joint j (docs/official/finemogen.md#body-part-split)."""
    if j == 0:
        return [0, 1, 2, 3, 193, 194, 195, 259, 260, 261, 262]
    ric, rot, vel = 4 + 3 * (j - 1), 67 + 6 * (j - 1), 193 + 3 * j
    return [ric, ric + 1, ric + 2] + list(range(rot, rot + 6)) + [vel, vel + 1, vel + 2]


def part_indices(dataset="human_ml3d"):
    if dataset != "human_ml3d":
        raise ValueError(f"dataset {dataset!r}: only human_ml3d is supported")
    out = {}
    for p in PARTS:
        idx = []
        for j in PART_JOINTS[p]:
            idx.extend(t2m_joint_indices(j))
        out[p] = idx
    assert sorted(out["body"]) == list(range(263))
    assert sorted(sum((out[p] for p in PARTS[:NUM_PARTS]), [])) == list(range(263))
    return out


def timestep_embedding(t, dim, dtype=torch.float32, max_period=10000):
    """[cos(t f), sin(t f)], f_i = exp(-ln(max_period) i / half) (cos first, 9.3)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=dtype) / half)
    args = t[:, None].to(dtype) * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def ffn(dim, hidden, out=None):
    return nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, out or dim))


# -- pose encoder / decoder (9.4) ------------------------------------------------------------------

class PoseEncoder(nn.Module):
    def __init__(self, dataset, latent_dim):
        super().__init__()
        self.idx = part_indices(dataset)
        for p in PARTS:
            setattr(self, f"{p}_embed", nn.Linear(len(self.idx[p]), latent_dim))

    def forward(self, motion):
        return torch.cat([getattr(self, f"{p}_embed")(motion[:, :, self.idx[p]]) for p in PARTS],
                         dim=-1)


class PoseDecoder(nn.Module):
    def __init__(self, dataset, latent_dim, output_dim):
        super().__init__()
        self.idx = part_indices(dataset)
        self.latent_dim, self.output_dim = latent_dim, output_dim
        for p in PARTS:
            setattr(self, f"{p}_out", nn.Linear(latent_dim, len(self.idx[p])))

    def forward(self, h):
        b, t = h.shape[:2]
        d = self.latent_dim
        out = torch.zeros(b, t, self.output_dim, dtype=h.dtype)
        for i, p in enumerate(PARTS[:NUM_PARTS]):
            out[:, :, self.idx[p]] = getattr(self, f"{p}_out")(h[:, :, i * d:(i + 1) * d])
        # The body output is added in the natural feature order (not scattered).
        body = self.body_out(h[:, :, NUM_PARTS * d:])
        return (out + body) / 2.0


class StylizationBlock(nn.Module):
    def __init__(self, dim, time_embed_dim):
        super().__init__()
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(time_embed_dim, 2 * dim))
        self.norm = nn.LayerNorm(dim)
        self.out_layers = nn.Sequential(nn.SiLU(), nn.Dropout(0.0), nn.Linear(dim, dim))

    def forward(self, h, emb):
        scale, shift = torch.chunk(self.emb_layers(emb).unsqueeze(1), 2, dim=2)
        return self.out_layers(self.norm(h) * (1 + scale) + shift)


# -- mixture of experts (9.7) ----------------------------------------------------------------------

class CosineTopKGate(nn.Module):
    def __init__(self, model_dim, num_experts, proj_dim):
        super().__init__()
        self.temperature = nn.Parameter(torch.log(torch.full([1], 2.0)))
        self.cosine_projector = nn.Linear(model_dim, proj_dim)
        self.sim_matrix = nn.Parameter(0.01 * torch.randn(proj_dim, num_experts))

    def forward(self, x):
        logits = F.normalize(self.cosine_projector(x), dim=1) @ F.normalize(self.sim_matrix, dim=0)
        # tutel: clamp_max = torch.log(torch.tensor(100.)).item(), compared in the param dtype.
        clamp_max = float(torch.log(torch.tensor(100.0)))
        return logits * torch.clamp(self.temperature, max=clamp_max).exp()


class FusedExperts(nn.Module):
    """tutel's ffn experts: out = GELU(x W1[e]^T + b1[e]) W2[e] + b2[e]; W2 stored [hidden, out]."""

    def __init__(self, num_experts, model_dim, hidden, out_dim):
        super().__init__()
        self.batched_fc1_w = nn.Parameter(torch.randn(num_experts, hidden, model_dim))
        self.batched_fc2_w = nn.Parameter(torch.randn(num_experts, hidden, out_dim))
        self.batched_fc1_bias = nn.Parameter(torch.zeros(num_experts, hidden))
        self.batched_fc2_bias = nn.Parameter(torch.zeros(num_experts, out_dim))

    def expert(self, e, x):
        u = F.gelu(x @ self.batched_fc1_w[e].t() + self.batched_fc1_bias[e])
        return u @ self.batched_fc2_w[e] + self.batched_fc2_bias[e]


def route(scores, topk, capacity, priority=None):
    """tutel extract_critical with batch-prioritised routing (STABLE tie order).
    scores [N, E] -> (experts [N, k], gates [N, k] (renormalised), slots [N, k] int64).
    `priority(v)`, if given, replaces the stable descending sort of the top-1 scores: it must
    return the same order (an exporter's TopK, which breaks ties by the lower index)."""
    n, e = scores.shape
    top = torch.topk(scores, topk, dim=1)
    experts, raw = top.indices, top.values
    denom = raw[:, 0]
    for k in range(1, topk):
        denom = denom + raw[:, k]
    denom = torch.clamp(denom, min=torch.finfo(scores.dtype).eps)
    gates = raw / denom[:, None]
    # priority: descending top-1 score, ties in token order
    if priority is None:
        order = torch.sort(-raw[:, 0], stable=True).indices
    else:
        order = priority(raw[:, 0])
    slots = torch.zeros(n, topk, dtype=torch.long)
    base = torch.zeros(e, dtype=torch.long)
    for k in range(topk):
        ek = experts[order, k]
        onehot = F.one_hot(ek, e)
        rank = ((torch.cumsum(onehot, 0) - 1) * onehot).sum(1)
        slots[order, k] = rank + base[ek]
        base = base + onehot.sum(0)
    return experts, gates, slots


def routing_margins(scores, experts, slots, capacity):
    """Margins of the routing decisions of one call:
    order: min over tokens of ln(score[k-th]) - ln(score[k+1-th]) for k < topk, i.e. the logit
           gaps that decide which experts a token picks and in which order (also the top-2 vs
           3rd gap);
    boundary: min over the experts/choices whose capacity cut falls inside their list of the
           difference of the top-1 scores of the last kept and the first dropped token (the
           priority order decides it); inf when no cut falls inside a list."""
    s = torch.sort(scores, dim=1, descending=True).values
    topk = experts.shape[1]
    order_gap = float((torch.log(s[:, :topk]) - torch.log(s[:, 1:topk + 1])).min())
    top1 = s[:, 0]
    boundary = math.inf
    for k in range(topk):
        for e in range(scores.shape[1]):
            sel = experts[:, k] == e
            if not sel.any():
                continue
            sl, sc = slots[sel, k], top1[sel]
            kept, dropped = sl < capacity, sl >= capacity
            if kept.any() and dropped.any():
                boundary = min(boundary, float(sc[kept].min() - sc[dropped].max()))
    return order_gap, boundary


class TutelMoE(nn.Module):
    def __init__(self, model_dim, num_experts, hidden, out_dim, gate_dim, topk, capacity_factor):
        super().__init__()
        self.gates = nn.ModuleList([CosineTopKGate(model_dim, num_experts, gate_dim)])
        self.experts = FusedExperts(num_experts, model_dim, hidden, out_dim)
        self.register_buffer("_num_global_experts", torch.tensor(num_experts))
        self.num_experts, self.topk, self.capacity_factor = num_experts, topk, capacity_factor

    def capacity(self, n):
        e = self.num_experts
        return self.topk * int(self.capacity_factor * ((n + e - 1) // e))

    def forward(self, x, log=None, tag=None):
        """x [N, D] tokens -> [N, out]."""
        n = x.shape[0]
        scores = torch.softmax(self.gates[0](x), dim=1)
        cap = self.capacity(n)
        experts, gates, slots = route(scores, self.topk, cap)
        kept = slots < cap
        outs = [None] * self.topk
        for k in range(self.topk):
            outs[k] = torch.zeros(n, self.experts.batched_fc2_bias.shape[1], dtype=x.dtype)
        for e in range(self.num_experts):
            sel = (experts == e) & kept
            rows = sel.any(1).nonzero()[:, 0]
            if rows.numel() == 0:
                continue
            y = self.experts.expert(e, x[rows])
            for k in range(self.topk):
                m = sel[rows, k]
                outs[k][rows[m]] = y[m]
        y = torch.zeros_like(outs[0])
        for k in range(self.topk):
            y = y + torch.where(kept[:, k:k + 1], gates[:, k:k + 1] * outs[k],
                                torch.zeros_like(outs[k]))
        if log is not None:
            order_gap, boundary = routing_margins(scores, experts, slots, cap)
            log.append({"tag": tag, "tokens": n, "capacity": cap,
                        "dropped": [int((~kept[:, k]).sum()) for k in range(self.topk)],
                        "fully_dropped": int((~kept).all(1).sum()),
                        "order_gap": order_gap, "boundary_gap": boundary,
                        "decisions": (experts.clone(), kept.clone())})
        return y


class MOE(nn.Module):
    """FineMoGen's wrapper: x + embedding[:, :S], flatten, proj(GELU(moe(x)))."""

    def __init__(self, num_experts, topk, input_dim, ffn_dim, output_dim, num_heads, max_seq_len,
                 gate_dim, capacity_factor):
        super().__init__()
        self.proj = nn.Linear(input_dim, output_dim)
        self.model = TutelMoE(input_dim, num_experts, ffn_dim, input_dim, gate_dim, topk,
                              capacity_factor)
        self.embedding = nn.Parameter(torch.randn(1, max_seq_len, num_heads, input_dim))

    def forward(self, x, log=None, tag=None):
        b, t, h, d = x.shape
        x = x + self.embedding[:, :t]
        y = self.proj(F.gelu(self.model(x.reshape(-1, d), log, tag)))
        return y.reshape(b, t, h, -1)


# -- SAMI (9.6) and SFFN (9.8) ---------------------------------------------------------------------

class SAMI(nn.Module):
    def __init__(self, c, layer):
        super().__init__()
        l, tl, heads = c["part_dim"], c["text_latent_dim"], len(PARTS)
        self.layer = layer
        self.latent_dim, self.num_heads, self.max_seq_len = l, heads, c["max_seq_len"]
        self.norm = nn.LayerNorm(l)
        self.text_norm = nn.LayerNorm(tl)
        self.sigma = nn.Parameter(torch.Tensor([100]))
        self.text_moe = MOE(c["num_experts"], c["topk"], tl, c["text_expert_hidden"], 2 * l, 1,
                            c["max_text_len"], c["gate_dim"], c["capacity_factor"])
        self.motion_moe = MOE(c["num_experts"], c["topk"], l, c["motion_expert_hidden"], 3 * l,
                              heads, c["max_seq_len"], c["gate_dim"], c["capacity_factor"])
        self.key_motion = nn.Parameter(torch.randn(c["max_seq_len"], l))  # unused by forward
        self.body_weight = nn.Parameter(torch.randn(heads, heads))
        f = c["ffn_dim"]
        self.template_s, self.template_v = ffn(l, f), ffn(l, f)
        self.template_a, self.template_j = ffn(l, f), ffn(l, f)
        self.template_t = ffn(l, f, 1)
        self.t_sigma = nn.Parameter(torch.Tensor([1]))
        self.proj_out = StylizationBlock(l * heads, c["time_embed_dim"])

    def forward(self, x, xf, emb, src_mask, text_on, motion_length, num_intervals, text_index,
                log=None):
        """x [B, T, 8L]; xf [Nseq, 77, TL] the distinct text sequences (cond ones, then the null
        copies); text_index [B, 8]: the sequence each (row, head) reads; src_mask [B, T];
        text_on [B] (1 text row, 0 null row); motion_length [B] int64."""
        b, t, d = x.shape
        h, l = self.num_heads, self.latent_dim
        dt = x.dtype
        x = x.reshape(b, t, h, l)
        text_feat = self.text_moe(self.text_norm(xf).unsqueeze(2), log,
                                  ("text", self.layer))[:, :, 0]  # [Nseq, 77, 2L]
        text_feat = text_feat[text_index].permute(0, 2, 1, 3)  # [B, 77, H, 2L]
        motion_feat = self.motion_moe(self.norm(x), log, ("motion", self.layer))

        body_weight = torch.softmax(self.body_weight, dim=1)
        y_s = torch.einsum("hl,bnld->bnhd", body_weight, motion_feat[..., :l]).reshape(b, t, d)

        on = text_on.to(dt).view(b, 1, 1, 1)
        mask = src_mask.to(dt).view(b, t, 1, 1)
        key_text = text_feat[..., :l] + (1 - on) * MASK_VALUE
        key_motion = motion_feat[..., l:2 * l] + (1 - mask) * MASK_VALUE
        key = torch.softmax(torch.cat([key_text, key_motion], dim=1), dim=1)
        value_text = text_feat[..., l:] * on
        value_motion = motion_feat[..., 2 * l:] * mask
        value = torch.cat([value_text, value_motion], dim=1)
        template = torch.einsum("bnhd,bnhl->bhdl", key, value)  # [B, H, L(templates), L]

        tau = torch.sigmoid(self.template_t(template) / self.t_sigma)  # [B, H, L, 1]
        tau = tau * motion_length.view(b, 1, 1, 1).to(dt) / self.max_seq_len
        time = torch.arange(self.max_seq_len) / self.max_seq_len  # float32, as the release
        ni = num_intervals
        tk = time[:t].to(dt).view(1, 1, t, 1, 1).repeat(b // ni, ni, 1, 1, 1)
        tau = tau.reshape(b // ni, ni, h, l).clone()
        lengths = motion_length.view(b // ni, ni)
        for g in range(b // ni):
            start = 0
            for i in range(ni):
                if i > 0:  # the release adds start/196 as an int64 tensor divided by 196
                    off = torch.tensor(start, dtype=torch.int64).to(
                        torch.float64 if dt == torch.float64 else torch.float32) / self.max_seq_len
                    tk[g, i] += off
                    tau[g, i] += off
                start += int(lengths[g, i])
        # Every row sees the anchors and templates of all intervals of its group.
        tau = tau.permute(0, 2, 1, 3).unsqueeze(1).repeat(1, ni, 1, 1, 1).reshape(b, 1, h, ni * l)
        delta = (tk.view(b, t, 1, 1) - tau) * self.max_seq_len
        coef = torch.softmax(-(delta * delta) / self.sigma, dim=-1)  # [B, T, H, NI*L]
        template = template.reshape(b // ni, ni, h, l, l).permute(0, 2, 1, 3, 4).unsqueeze(1)
        template = template.repeat(1, ni, 1, 1, 1, 1).reshape(b, h, ni * l, l)
        s, v = self.template_s(template), self.template_v(template)
        a, j = self.template_a(template), self.template_j(template)
        tau = tau.reshape(b, h, ni * l, 1)
        a0 = s - v * tau + a * tau * tau - j * tau * tau * tau
        a1 = v - 2 * a * tau + 3 * j * tau * tau
        a2 = a - 3 * j * tau
        a3 = j
        c = [torch.einsum("bnhd,bhdl->bnhl", coef, ak).reshape(b, t, d) for ak in (a0, a1, a2, a3)]
        tt = tk.view(b, t, 1)
        y_t = c[0] + c[1] * tt + c[2] * tt * tt + c[3] * tt * tt * tt
        return x.reshape(b, t, d) + self.proj_out(y_s + y_t, emb)


class SFFN(nn.Module):
    def __init__(self, c):
        super().__init__()
        l, f = c["part_dim"], c["ffn_dim"]
        self.linear1_list = nn.ModuleList([nn.Linear(l, f) for _ in PARTS])
        self.linear2_list = nn.ModuleList([nn.Linear(f, l) for _ in PARTS])
        self.proj_out = StylizationBlock(l * len(PARTS), c["time_embed_dim"])

    def forward(self, x, emb):
        b, t, d = x.shape
        xs = x.reshape(b, t, len(PARTS), -1)
        y = torch.cat([self.linear2_list[i](F.gelu(self.linear1_list[i](xs[:, :, i])))
                       for i in range(len(PARTS))], dim=-1)
        return x + self.proj_out(y, emb)


class DecoderLayer(nn.Module):
    def __init__(self, c, layer):
        super().__init__()
        self.ca_block = SAMI(c, layer)
        self.ffn = SFFN(c)


class FineMoGenNet(nn.Module):
    def __init__(self, c):
        super().__init__()
        self.cfg = dict(c)
        tl = c["text_latent_dim"]
        self.latent_dim = c["part_dim"] * len(PARTS)
        self.text_pre_proj = nn.Linear(c["clip_width"], tl)
        layer = nn.TransformerEncoderLayer(tl, c["text_heads"], c["text_ff_size"], dropout=0.0,
                                           activation="gelu")
        self.textTransEncoder = nn.TransformerEncoder(layer, c["text_layers"],
                                                      enable_nested_tensor=False)
        self.text_ln = nn.LayerNorm(tl)
        self.time_embed = nn.Sequential(nn.Linear(self.latent_dim, c["time_embed_dim"]), nn.SiLU(),
                                        nn.Linear(c["time_embed_dim"], c["time_embed_dim"]))
        self.joint_embed = PoseEncoder(c["dataset"], c["part_dim"])
        self.temporal_decoder_blocks = nn.ModuleList(
            [DecoderLayer(c, i) for i in range(c["num_layers"])])
        self.out = PoseDecoder(c["dataset"], c["part_dim"], c["input_feats"])
        self.moe_log = None  # set to a list to record every MoE call

    def encode_clip_features(self, clip_feat):
        """CLIP ln_final features [N, 77, W] -> xf [N, 77, TL] (9.2)."""
        x = self.text_pre_proj(clip_feat).permute(1, 0, 2)  # sequence-first, as the release
        return self.text_ln(self.textTransEncoder(x)).permute(1, 0, 2)

    def forward(self, x, t, lengths, xf, text_index, num_intervals):
        """x [B, T, 263] (B = stages), t: original step (int, or an int64 tensor [1]), lengths [B]
        int64, xf [Nseq, 77, TL] (cond sequences then their null copies), text_index [2B, 8].
        Returns (text rows, null rows), each [B, T, 263]."""
        b, tn = x.shape[:2]
        dt = x.dtype
        # t a tensor too, so that an export takes the step as an input (same int64 values).
        ts = t.reshape(1).expand(b) if torch.is_tensor(t) else torch.full((b,), t)
        emb = self.time_embed(timestep_embedding(ts, self.latent_dim, dt))
        h = self.joint_embed(x)
        src_mask = (torch.arange(tn)[None, :] < lengths[:, None]).to(dt)
        h, emb, src_mask = h.repeat(2, 1, 1), emb.repeat(2, 1), src_mask.repeat(2, 1)
        motion_length = lengths.repeat(2)
        text_on = torch.cat([torch.ones(b), torch.zeros(b)]).to(dt)
        for blk in self.temporal_decoder_blocks:
            h = blk.ca_block(h, xf, emb, src_mask, text_on, motion_length, num_intervals,
                             text_index, self.moe_log)
            h = blk.ffn(h, emb)
        out = self.out(h)
        return out[:b], out[b:]


# -- CLIP and prompts ------------------------------------------------------------------------------

SOT, EOT, CONTEXT = 49406, 49407, 77


def clip_ids(tokenizer, text, context=CONTEXT):
    """clip.tokenize(text, truncate=True): [SOT] + ids + [EOT], zero-padded (pad id 0)."""
    content = tokenizer.encode(text, add_special_tokens=False).ids[: context - 2]
    ids = [SOT] + content + [EOT]
    return ids + [0] * (context - len(ids))


def clip_features(clip_model, ids):
    """ids [N, 77] -> ln_final [N, 77, W] at every position (causal mask only)."""
    return clip_model.text_model(input_ids=ids).last_hidden_state


class Stage:
    def __init__(self, text, frames, parts=None):
        self.text, self.frames, self.parts = text, int(frames), dict(parts or {})
        for p in self.parts:
            if p not in PARTS[:NUM_PARTS]:
                raise ValueError(f"unknown body part {p!r}")


def condition(stages, encode):
    """Distinct text sequences and the (row, head) -> sequence map (choice 3).
    encode(text) -> xf [77, TL]. Returns (xf [Nseq, 77, TL], text_index [2B, 8], texts)."""
    texts, rows = [], []
    for st in stages:
        own = [st.text]
        for p in PARTS[:NUM_PARTS]:
            pt = st.parts.get(p)
            if pt is not None and pt not in own:
                own.append(pt)
        base = len(texts)
        texts.extend(own)
        idx = []
        for p in PARTS:
            pt = st.parts.get(p, st.text) if p != "body" else st.text
            idx.append(base + own.index(pt))
        rows.append(idx)
    n = len(texts)
    index = torch.tensor(rows + [[i + n for i in r] for r in rows], dtype=torch.long)
    xf = torch.stack([encode(s) for s in texts])
    return torch.cat([xf, xf]), index, texts


# -- sampler (9.11) --------------------------------------------------------------------------------

def make_diffusion(respacing="15,15,8,6,6", num_timesteps=1000):
    return SpacedDiffusion(linear_betas(num_timesteps), space_timesteps(num_timesteps, respacing))


def guidance_weight(t, scale, num_timesteps=1000):
    return 1.0 + scale * t / num_timesteps


def ddim_sample(net, noise, stages, xf, text_index, scale=6.5, respacing="15,15,8,6,6"):
    """DDIM eta 0 with x0 prediction and in-network guidance. noise [B, Tmax, 263].
    Returns a list of per-step dicts (t, w, x = sample after the step, x0 = guided x-hat-0)."""
    diff = make_diffusion(respacing)
    dt = noise.dtype
    lengths = torch.tensor([s.frames for s in stages], dtype=torch.long)

    def tab(table, i):
        v = torch.tensor(float(table[i]), dtype=torch.float64)
        return v.to(dt)

    x = noise
    trace = []
    for i in reversed(range(diff.num_timesteps)):
        t = int(diff.timestep_map[i])
        w = guidance_weight(t, scale)
        text, null = net(x, t, lengths, xf, text_index, len(stages))
        x0 = null + (text - null) * w
        eps = (tab(diff.sqrt_recip_alphas_cumprod, i) * x - x0) \
            / tab(diff.sqrt_recipm1_alphas_cumprod, i)
        abp = tab(diff.alphas_cumprod_prev, i)
        x = x0 * torch.sqrt(abp) + torch.sqrt(1 - abp) * eps  # sigma = 0 (eta 0)
        trace.append({"t": t, "w": w, "x": x, "x0": x0})
    return trace


def compose(final, stages):
    """9.13: the stages' valid frames concatenated in order, [sum len, 263]."""
    return torch.cat([final[i, :s.frames] for i, s in enumerate(stages)], dim=0)


# -- loading ---------------------------------------------------------------------------------------

def load_official(state, cfg, strict=True):
    """Official `model.*` state dict (without model.clip.*) into a FineMoGenNet."""
    net = FineMoGenNet(cfg)
    sd = {k[len("model."):]: v for k, v in state.items()
          if k.startswith("model.") and not k.startswith("model.clip.")}
    net.load_state_dict(sd, strict=strict)
    return net.eval()


def load_libflame(path):
    """(net, clip model, tokenizer, config, mean, std) from a converted libflame file."""
    import json

    from safetensors import safe_open
    from tokenizers import Tokenizer
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    with safe_open(path, "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    cfg = json.loads(meta["flame.config"])
    if cfg["architecture"] != "finemogen":
        raise ValueError(f"{path}: architecture {cfg['architecture']!r}")
    net = FineMoGenNet(cfg["denoiser"])
    den = {k[len("denoiser."):]: v for k, v in tensors.items() if k.startswith("denoiser.")}
    missing, unexpected = net.load_state_dict(den, strict=False)
    assert not unexpected, unexpected
    assert all(k.endswith(("key_motion", "_num_global_experts")) for k in missing), missing
    te = cfg["text_encoder"]
    ccfg = CLIPTextConfig(vocab_size=te["vocab_size"], hidden_size=te["width"],
                          intermediate_size=te["intermediate_size"],
                          num_hidden_layers=te["layers"], num_attention_heads=te["heads"],
                          max_position_embeddings=te["context_length"],
                          projection_dim=te["projection_dim"], hidden_act="quick_gelu",
                          layer_norm_eps=te["layer_norm_eps"], attn_implementation="eager")
    clip = CLIPTextModelWithProjection(ccfg)
    clip_sd = {k[len("text."):]: v for k, v in tensors.items() if k.startswith("text.")}
    missing, unexpected = clip.load_state_dict(clip_sd, strict=False)
    assert not unexpected and all(k.endswith("position_ids") for k in missing), (missing,
                                                                                 unexpected)
    tok = Tokenizer.from_str(meta["flame.tokenizer"])
    return net.eval(), clip.eval(), tok, cfg, tensors["motion.mean"], tensors["motion.std"]
