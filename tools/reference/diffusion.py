"""Reference of FLAME's diffusion sampling (guided-diffusion semantics), from kakaobrain/flame
`src/models/components/gaussian_diffusion.py`, `respace.py` and `src/utils/sample_util.py`
(docs/official/flame.md#noise-schedule to docs/official/flame.md#classifier-free-guidance).

dtype behaviour mirrors the official code: every table is float64 numpy, a step gathers its
coefficients as float64 and casts them to float32 (`.float()`), and all per-step math on x runs in
float32 torch.

Contents: beta schedules, `space_timesteps`, `GaussianDiffusion` (p_mean_variance with learned-range
variance + clip_denoised, p_sample, ddim_sample), `SpacedDiffusion` (the network sees
timestep_map[t]), and `ClassifierFreeGuidance` (batch [cond; ""], first half of x duplicated,
eps guided, variance channels left per row).
"""
import math

import numpy as np
import torch


# -- schedules (docs/official/flame.md#noise-schedule) ----------------------------------------------

def cosine_alpha_bar(s):
    return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2


def cosine_betas(num_timesteps, max_beta=0.999):
    betas = []
    for i in range(num_timesteps):
        t1, t2 = i / num_timesteps, (i + 1) / num_timesteps
        betas.append(min(1 - cosine_alpha_bar(t2) / cosine_alpha_bar(t1), max_beta))
    return np.array(betas, dtype=np.float64)


def linear_betas(num_timesteps):
    scale = 1000 / num_timesteps
    return np.linspace(scale * 0.0001, scale * 0.02, num_timesteps, dtype=np.float64)


def named_betas(schedule, num_timesteps):
    if schedule in ("cosine", "squaredcos_cap_v2"):
        return cosine_betas(num_timesteps)
    if schedule == "linear":
        return linear_betas(num_timesteps)
    raise ValueError(f"unknown beta schedule {schedule!r}")


# -- respacing (docs/official/flame.md#respacing) ---------------------------------------------------

def space_timesteps(num_timesteps, section_counts):
    """Set of original step indices to keep (section rule, or "ddimN")."""
    if isinstance(section_counts, str):
        if section_counts.startswith("ddim"):
            wanted = int(section_counts[len("ddim"):])
            for stride in range(1, num_timesteps):
                if len(range(0, num_timesteps, stride)) == wanted:
                    return set(range(0, num_timesteps, stride))
            raise ValueError(f"cannot take exactly {wanted} steps with an integer stride")
        section_counts = [int(x) for x in section_counts.split(",")]
    size_per = num_timesteps // len(section_counts)
    extra = num_timesteps % len(section_counts)
    start = 0
    kept = []
    for i, count in enumerate(section_counts):
        size = size_per + (1 if i < extra else 0)
        if size < count:
            raise ValueError(f"cannot divide section of {size} steps into {count}")
        stride = 1 if count <= 1 else (size - 1) / (count - 1)
        cur = 0.0
        for _ in range(count):
            kept.append(start + round(cur))  # Python round: half to even
            cur += stride
        start += size
    return set(kept)


def _gather(table, t, shape):
    """float64 table[t] -> float32, broadcast to `shape` (guided-diffusion `_extract_into_tensor`)."""
    res = torch.from_numpy(table)[t].float()
    while res.dim() < len(shape):
        res = res[..., None]
    return res.expand(shape)


class GaussianDiffusion:
    """Epsilon prediction, learned-range variance (docs/official/flame.md#ddpm-step)."""

    def __init__(self, betas):
        betas = np.asarray(betas, dtype=np.float64)
        self.betas = betas
        self.num_timesteps = len(betas)
        alphas = 1.0 - betas
        self.alphas_cumprod = np.cumprod(alphas, axis=0)
        self.alphas_cumprod_prev = np.append(1.0, self.alphas_cumprod[:-1])
        self.alphas_cumprod_next = np.append(self.alphas_cumprod[1:], 0.0)
        self.sqrt_recip_alphas_cumprod = np.sqrt(1.0 / self.alphas_cumprod)
        self.sqrt_recipm1_alphas_cumprod = np.sqrt(1.0 / self.alphas_cumprod - 1)
        self.posterior_variance = (betas * (1.0 - self.alphas_cumprod_prev)
                                   / (1.0 - self.alphas_cumprod))
        self.posterior_log_variance_clipped = np.log(
            np.append(self.posterior_variance[1], self.posterior_variance[1:]))
        self.log_betas = np.log(betas)
        self.posterior_mean_coef1 = (betas * np.sqrt(self.alphas_cumprod_prev)
                                     / (1.0 - self.alphas_cumprod))
        self.posterior_mean_coef2 = ((1.0 - self.alphas_cumprod_prev) * np.sqrt(alphas)
                                     / (1.0 - self.alphas_cumprod))

    def model_timesteps(self, t):
        """Timesteps the network sees for loop index t (identity without respacing)."""
        return t

    def predict_xstart_from_eps(self, x_t, t, eps):
        return (_gather(self.sqrt_recip_alphas_cumprod, t, x_t.shape) * x_t
                - _gather(self.sqrt_recipm1_alphas_cumprod, t, x_t.shape) * eps)

    def predict_eps_from_xstart(self, x_t, t, pred_xstart):
        return ((_gather(self.sqrt_recip_alphas_cumprod, t, x_t.shape) * x_t - pred_xstart)
                / _gather(self.sqrt_recipm1_alphas_cumprod, t, x_t.shape))

    def q_posterior_mean(self, x_start, x_t, t):
        return (_gather(self.posterior_mean_coef1, t, x_t.shape) * x_start
                + _gather(self.posterior_mean_coef2, t, x_t.shape) * x_t)

    def p_mean_variance(self, model, x, t, clip_denoised=True):
        """model(x, timesteps) -> `[B, 2C, ...]` (eps ; v). Returns dict of mean, log_variance,
        pred_xstart (clamped when clip_denoised), eps (network eps)."""
        channels = x.shape[1]
        out = model(x, self.model_timesteps(t))
        assert out.shape[1] == 2 * channels, out.shape
        eps, var_values = torch.split(out, channels, dim=1)
        min_log = _gather(self.posterior_log_variance_clipped, t, x.shape)
        max_log = _gather(self.log_betas, t, x.shape)
        frac = (var_values + 1) / 2  # v is not clamped
        log_variance = frac * max_log + (1 - frac) * min_log
        pred_xstart = self.predict_xstart_from_eps(x, t, eps)
        if clip_denoised:
            pred_xstart = pred_xstart.clamp(-1, 1)
        mean = self.q_posterior_mean(pred_xstart, x, t)
        return {"mean": mean, "log_variance": log_variance, "pred_xstart": pred_xstart,
                "eps": eps}

    def p_sample(self, model, x, t, noise, clip_denoised=True):
        out = self.p_mean_variance(model, x, t, clip_denoised)
        nonzero = (t != 0).float().view(-1, *([1] * (x.dim() - 1)))
        sample = out["mean"] + nonzero * torch.exp(0.5 * out["log_variance"]) * noise
        return {"sample": sample, "pred_xstart": out["pred_xstart"]}

    def ddim_sample(self, model, x, t, noise=None, eta=0.0, clip_denoised=True):
        """DDIM (docs/official/flame.md#ddim); eps re-derived from the (clamped) x0."""
        out = self.p_mean_variance(model, x, t, clip_denoised)
        eps = self.predict_eps_from_xstart(x, t, out["pred_xstart"])
        alpha_bar = _gather(self.alphas_cumprod, t, x.shape)
        alpha_bar_prev = _gather(self.alphas_cumprod_prev, t, x.shape)
        sigma = (eta * torch.sqrt((1 - alpha_bar_prev) / (1 - alpha_bar))
                 * torch.sqrt(1 - alpha_bar / alpha_bar_prev))
        mean = (out["pred_xstart"] * torch.sqrt(alpha_bar_prev)
                + torch.sqrt(1 - alpha_bar_prev - sigma ** 2) * eps)
        sample = mean
        if noise is not None:
            nonzero = (t != 0).float().view(-1, *([1] * (x.dim() - 1)))
            sample = mean + nonzero * sigma * noise
        return {"sample": sample, "pred_xstart": out["pred_xstart"]}

    def sample_loop(self, model, x_T, method="ddpm", eta=0.0, noise_fn=None, clip_denoised=True):
        """Run t = T-1 .. 0. noise_fn(k, shape) supplies the z of loop step k (DDPM always draws one,
        also at t = 0 where it is multiplied by 0; DDIM only when eta > 0).
        Returns (final, list of per-step dicts with x, pred_xstart, noise)."""
        x = x_T
        trace = []
        for k, i in enumerate(reversed(range(self.num_timesteps))):
            t = torch.full((x.shape[0],), i, dtype=torch.long)
            if method == "ddpm":
                z = noise_fn(k, x.shape)
                out = self.p_sample(model, x, t, z, clip_denoised)
            elif method == "ddim":
                z = noise_fn(k, x.shape) if eta > 0 else None
                out = self.ddim_sample(model, x, t, z, eta, clip_denoised)
            else:
                raise ValueError(method)
            x = out["sample"]
            trace.append({"t": i, "x": x, "pred_xstart": out["pred_xstart"], "noise": z})
        return x, trace


class SpacedDiffusion(GaussianDiffusion):
    """Betas rebuilt from the kept steps; the network sees timestep_map[t] (docs/official/flame.md#respacing)."""

    def __init__(self, base_betas, use_timesteps):
        base = GaussianDiffusion(base_betas)
        use_timesteps = set(use_timesteps)
        new_betas = []
        self.timestep_map = []
        last = 1.0
        for i, alpha_cumprod in enumerate(base.alphas_cumprod):
            if i in use_timesteps:
                new_betas.append(1 - alpha_cumprod / last)
                last = alpha_cumprod
                self.timestep_map.append(i)
        super().__init__(np.array(new_betas, dtype=np.float64))

    def model_timesteps(self, t):
        return torch.tensor(self.timestep_map, dtype=t.dtype)[t]


class ClassifierFreeGuidance:
    """FLAME's guidance (`src/utils/sample_util.py`; docs/official/flame.md#classifier-free-guidance)
    as a model(x, timesteps) callable over a 2N batch [cond rows; "" rows].

    The first half of x is duplicated, one forward runs on the 2N batch, eps = eps_u + s(eps_c - eps_u)
    goes to both halves, and the variance channels are left per row (so the kept first half uses the
    conditional variance).
    """

    def __init__(self, net, texts, frames, guidance, text_features=None):
        self.net = net
        n = len(texts)
        self.texts = list(texts) + [""] * n
        self.guidance = guidance
        self.motion_length = torch.full((2 * n,), frames, dtype=torch.long)
        self.mask = torch.ones(2 * n, frames, dtype=torch.bool)
        # The LM output does not depend on x or t; cache it like a pure function would allow.
        self.text_features = text_features
        if self.text_features is None:
            with torch.no_grad():
                self.text_features = net.encode_text(self.texts)

    def __call__(self, x, timesteps):
        n = x.shape[0] // 2
        half = x[:n]
        combined = torch.cat([half, half], dim=0)
        out = self.net(combined, timesteps, self.motion_length, mask=self.mask,
                       text_features=self.text_features)
        channels = x.shape[1]
        eps, rest = out[:, :channels], out[:, channels:]
        cond_eps, uncond_eps = eps[:n], eps[n:]
        half_eps = uncond_eps + self.guidance * (cond_eps - uncond_eps)
        eps = torch.cat([half_eps, half_eps], dim=0)
        return torch.cat([eps, rest], dim=1)
