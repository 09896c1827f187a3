"""Building blocks of the world model and the actor-critic (pure PyTorch, no ROS).

Shapes: images are channels-first floats in [-0.5, 0.5], (N, 3, 64, 64); every module accepts
extra leading dims and flattens them itself ((B, T, 3, 64, 64) -> (B, T, E)).

The action distributions are small hand-written classes instead of torch.distributions: the
imagination loop calls them 15 times per update on 1000+ states, and torch.distributions'
argument validation and broadcasting cost more than the maths.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["activation", "init_weights", "MLP", "ChannelNorm", "ConvEncoder", "ConvDecoder", "GRUCell",
           "TruncNormal", "TanhNormal", "ActionHead", "flatten_leading"]


def activation(name: str) -> nn.Module:
    acts = {"elu": nn.ELU, "silu": nn.SiLU, "relu": nn.ReLU, "tanh": nn.Tanh, "gelu": nn.GELU}
    if name not in acts:
        raise ValueError(f"unknown activation {name!r}; valid: {sorted(acts)}")
    return acts[name]()


def init_weights(module: nn.Module, scheme: str = "glorot") -> nn.Module:
    """Re-initialise every Linear / Conv / ConvTranspose in `module`: 'glorot' = uniform
    fan-average weights and zero biases (Keras' default, i.e. DreamerV2's and DreamerPro's;
    fan-average is the same for a conv and its transpose), 'torch' = leave PyTorch's
    defaults. Norm layers and free parameters (prototypes) keep their own."""
    if scheme == "torch":
        return module
    if scheme != "glorot":
        raise ValueError(f"unknown weight init {scheme!r}; valid: glorot, torch")
    for m in module.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
    return module


def flatten_leading(x: torch.Tensor, keep: int) -> tuple[torch.Tensor, tuple[int, ...]]:
    """(*lead, *last `keep` dims) -> (N, *last), plus the lead shape to restore it."""
    lead = x.shape[: x.dim() - keep]
    return x.reshape(-1, *x.shape[x.dim() - keep:]), tuple(lead)


class MLP(nn.Sequential):
    """`layers` x (Linear -> [LayerNorm] -> act), then a linear output of size `out` (or none).

    DreamerV2 heads: 4 x 400 ELU, no norm. DreamerV3: 2 x 512 SiLU + LayerNorm.
    """

    def __init__(self, inp: int, out: int | None, layers: int, units: int, act: str = "elu",
                 norm: str = "none"):
        mods: list[nn.Module] = []
        for i in range(layers):
            mods.append(nn.Linear(inp if i == 0 else units, units, bias=norm == "none"))
            if norm == "layer":
                mods.append(nn.LayerNorm(units))
            mods.append(activation(act))
        last = units if layers else inp
        if out is not None:
            mods.append(nn.Linear(last, out))
        super().__init__(*mods)
        self.out_dim = out if out is not None else last


class ChannelNorm(nn.Module):
    """LayerNorm over the channels of (N, C, H, W) (DreamerV3's image-channel LayerNorm)."""

    def __init__(self, channels: int):
        super().__init__()
        self.norm = nn.LayerNorm(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def _conv_layers(specs, act: str, norm: str, transpose: bool, last_plain: bool) -> nn.Sequential:
    """specs: list of (cin, cout, kernel, stride, padding)."""
    mods: list[nn.Module] = []
    conv_cls = nn.ConvTranspose2d if transpose else nn.Conv2d
    for i, (cin, cout, k, s, p) in enumerate(specs):
        plain = last_plain and i == len(specs) - 1
        mods.append(conv_cls(cin, cout, k, s, p, bias=plain or norm == "none"))
        if not plain:
            if norm == "layer":
                mods.append(ChannelNorm(cout))
            mods.append(activation(act))
    return nn.Sequential(*mods)


class ConvEncoder(nn.Module):
    """64x64 RGB -> embedding. o_t in [-0.5, 0.5], (..., 3, 64, 64) -> (..., out_dim).

    'dreamerv2': 4 convs, kernel 4, stride 2, no padding: 64 -> 31 -> 14 -> 6 -> 2, channels
                 depth x (1, 2, 4, 8), embedding 32 * depth (1536 for DreamerPro's depth 48).
    'dreamerv3': kernel 4, stride 2, padding 1 down to 4x4 (minres 4): 64 -> 32 -> 16 -> 8 -> 4,
                 embedding 128 * depth (4096 for dreamerv3-torch's depth 32).
    """

    def __init__(self, depth: int = 48, cnn: str = "dreamerv2", act: str = "elu",
                 norm: str = "none"):
        super().__init__()
        d = depth
        chans = [3, d, 2 * d, 4 * d, 8 * d]
        pad, side = (0, 2) if cnn == "dreamerv2" else (1, 4)
        self.convs = _conv_layers([(chans[i], chans[i + 1], 4, 2, pad) for i in range(4)],
                                  act, norm, transpose=False, last_plain=False)
        self.convs.to(memory_format=torch.channels_last)  # NHWC weights for oneDNN / cuDNN
        self.out_dim = 8 * d * side * side

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x, lead = flatten_leading(image, 3)
        # channels_last lets oneDNN (CPU) / cuDNN pick their fast NHWC kernels.
        x = self.convs(x.contiguous(memory_format=torch.channels_last))
        return x.reshape(*lead, -1)


class ConvDecoder(nn.Module):
    """x_t -> mean image (..., 3, 64, 64); p(o_t | x_t) = N(mean, 1) per pixel (paper eq. 7).

    'dreamerv2': Linear -> (32 d, 1, 1) -> transposed convs kernels 5, 5, 6, 6, stride 2:
                 1 -> 5 -> 13 -> 30 -> 64 (DreamerV1/V2 decoder). A transposed conv of a 1x1
                 input is a matrix product, so the first one is computed as a Linear to
                 (4 d, 5, 5) (same function and parameter count, without oneDNN's slow path).
    'dreamerv3': Linear -> (8 d, 4, 4) -> transposed convs kernel 4, stride 2, padding 1.
    """

    def __init__(self, feat_dim: int, depth: int = 48, cnn: str = "dreamerv2", act: str = "elu",
                 norm: str = "none"):
        super().__init__()
        d = depth
        if cnn == "dreamerv2":
            # Dense(32 d) -> ConvT(32 d -> 4 d, k5) on 1x1 == Dense(32 d) -> Dense(4 d * 5 * 5)
            self.linear = nn.Sequential(
                nn.Linear(feat_dim, 32 * d),
                nn.Linear(32 * d, 4 * d * 25, bias=norm == "none"),
                nn.Unflatten(-1, (4 * d, 5, 5)),
                *([ChannelNorm(4 * d)] if norm == "layer" else []), activation(act))
            specs = [(4 * d, 2 * d, 5, 2, 0), (2 * d, d, 6, 2, 0), (d, 3, 6, 2, 0)]
        else:
            self.linear = nn.Sequential(nn.Linear(feat_dim, 8 * d * 16),
                                        nn.Unflatten(-1, (8 * d, 4, 4)))
            specs = [(8 * d, 4 * d, 4, 2, 1), (4 * d, 2 * d, 4, 2, 1), (2 * d, d, 4, 2, 1),
                     (d, 3, 4, 2, 1)]
        self.deconvs = _conv_layers(specs, act, norm, transpose=True, last_plain=True)
        self.deconvs.to(memory_format=torch.channels_last)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        x, lead = flatten_leading(feat, 1)
        x = self.linear(x)
        x = self.deconvs(x.contiguous(memory_format=torch.channels_last))
        return x.reshape(*lead, 3, 64, 64)


class GRUCell(nn.Module):
    """DreamerV2's GRU: one Linear on [x, h], LayerNorm on the gates, update bias -1.

    h' = u * tanh(r * c) + (1 - u) * h with (r, c, u) = LN(W [x, h]), u = sigmoid(u - 1).
    """

    def __init__(self, inp: int, size: int, norm: bool = True, update_bias: float = -1.0):
        super().__init__()
        self.size, self.update_bias = size, update_bias
        self.linear = nn.Linear(inp + size, 3 * size, bias=not norm)
        self.norm = nn.LayerNorm(3 * size) if norm else None

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        parts = self.linear(torch.cat([x, h.to(x.dtype)], -1))
        if self.norm is not None:
            parts = self.norm(parts)
        reset, cand, update = parts.float().chunk(3, -1)  # gate maths in float32
        reset = torch.sigmoid(reset)
        cand = torch.tanh(reset * cand)
        update = torch.sigmoid(update + self.update_bias)
        return update * cand + (1 - update) * h.float()


# ------------------------------------------------------------------------------------------------
# Action distributions in [-1, 1]
# ------------------------------------------------------------------------------------------------
_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def _ndtr(x: torch.Tensor) -> torch.Tensor:
    return 0.5 * (1 + torch.erf(x / _SQRT2))


class TruncNormal:
    """Normal(mean, std) truncated to [-1, 1], reparameterised (DreamerV2 'trunc_normal').

    mean = tanh(out), std = 2 sigmoid((out_std + init) / 2) + min_std (DreamerV2 DistLayer).
    Sampling by inverse CDF, x = mean + std * Phi^-1(Phi(alpha) + U (Phi(beta) - Phi(alpha))),
    differentiable in mean and std; samples are clipped into (-1, 1) with a straight-through
    gradient as in DreamerV2's TruncNormalDist.  All arguments (..., A); sums over A.
    """

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, clip: float = 1e-6):
        self.mean, self.std, self._clip = mean, std, clip
        self.alpha = (-1 - mean) / std
        self.beta = (1 - mean) / std
        self._cdf_a, self._cdf_b = _ndtr(self.alpha), _ndtr(self.beta)
        # mean in (-1, 1) so alpha < 0 < beta: Z >= 0.5 * (1 - erfc stuff) is well above 0.
        self.Z = (self._cdf_b - self._cdf_a).clamp_min(1e-6)

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        u = torch.rand(self.mean.shape, generator=generator, device=self.mean.device,
                       dtype=self.mean.dtype)
        p = (self._cdf_a + u * self.Z).clamp(1e-6, 1 - 1e-6)
        x = self.mean + self.std * _SQRT2 * torch.erfinv(2 * p - 1)
        clipped = x.clamp(-1 + self._clip, 1 - self._clip)
        return x + (clipped - x).detach()

    def mode(self, generator: torch.Generator | None = None) -> torch.Tensor:
        # DreamerV2's TruncNormalDist mode: the (clipped) mean, which lies inside (-1, 1).
        return self.mean

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.mean) / self.std
        return (-0.5 * z * z - _LOG_SQRT_2PI - self.std.log() - self.Z.log()).sum(-1)

    def entropy(self) -> torch.Tensor:
        # H = log(sqrt(2 pi e) std Z) + (alpha phi(alpha) - beta phi(beta)) / (2 Z)
        phi = lambda t: torch.exp(-0.5 * t * t) / math.sqrt(2 * math.pi)  # noqa: E731
        h = (_LOG_SQRT_2PI + 0.5 + self.std.log() + self.Z.log()
             + (self.alpha * phi(self.alpha) - self.beta * phi(self.beta)) / (2 * self.Z))
        return h.sum(-1)


#: Draws the tanh_normal mode is picked from (DreamerV1/DreamerPro SampleDist(samples=100)).
MODE_SAMPLES = 100


class TanhNormal:
    """tanh(Normal(mean, std)) (DreamerV1 'tanh_normal'): mean = 5 tanh(out / 5),
    std = softplus(out_std + init) + min_std.  Entropy is the one-sample estimate
    -log p(sample) (DreamerV1 estimates it from 100 samples); the mode is the most likely of
    100 samples, as in DreamerV1 and DreamerPro."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor):
        self.mean, self.std = mean, std
        self._last_pre: torch.Tensor | None = None

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        eps = torch.randn(self.mean.shape, generator=generator, device=self.mean.device,
                          dtype=self.mean.dtype)
        self._last_pre = self.mean + self.std * eps
        return torch.tanh(self._last_pre)

    def mode(self, generator: torch.Generator | None = None, samples: int = MODE_SAMPLES
             ) -> torch.Tensor:
        """The most likely of `samples` draws, by their joint density over the actions
        (DreamerV1/DreamerPro SampleDist.mode). Not tanh(mean): where std is large the density
        of tanh(Normal) piles up near +-1 (mean 0.5, std 1.5: tanh(mean) 0.46, this ~0.999),
        which is where a swing-up's torque is."""
        eps = torch.randn((samples, *self.mean.shape), generator=generator,
                          device=self.mean.device, dtype=self.mean.dtype)
        pre = self.mean + self.std * eps                        # (S, ..., A)
        best = self._log_prob_pre(pre).argmax(0)                # (...)
        pick = torch.gather(pre, 0, best[None, ..., None].expand(1, *pre.shape[1:]))[0]
        return torch.tanh(pick)

    def sample_log_prob(self, generator: torch.Generator | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised sample and its log-density (summed over actions), computed from
        the pre-tanh value, so it stays exact where tanh saturates (SAC's squashed Gaussian)."""
        action = self.sample(generator)
        return action, self._log_prob_pre(self._last_pre)

    def _log_prob_pre(self, pre: torch.Tensor) -> torch.Tensor:
        z = (pre - self.mean) / self.std
        logp = -0.5 * z * z - _LOG_SQRT_2PI - self.std.log()
        # log |d tanh / d pre| = 2 (log 2 - pre - softplus(-2 pre)), numerically stable
        logdet = 2 * (math.log(2) - pre - F.softplus(-2 * pre))
        return (logp - logdet).sum(-1)

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        x = x.clamp(-1 + 1e-6, 1 - 1e-6)
        return self._log_prob_pre(torch.atanh(x))

    def entropy(self) -> torch.Tensor:
        pre = self._last_pre
        if pre is None:
            pre = self.mean + self.std * torch.randn_like(self.mean)
        return -self._log_prob_pre(pre)


class ActionHead(nn.Module):
    """MLP trunk -> (mean, std) -> TruncNormal / TanhNormal over A actions in [-1, 1]."""

    def __init__(self, inp: int, action_dim: int, layers: int, units: int, act: str, norm: str, *,
                 dist: str = "trunc_normal", min_std: float = 0.1, init_std: float = 0.0):
        super().__init__()
        self.trunk = MLP(inp, None, layers, units, act, norm)
        self.out = nn.Linear(self.trunk.out_dim, 2 * action_dim)
        self.dist_name, self.min_std, self.init_std = dist, min_std, init_std

    def forward(self, x: torch.Tensor):
        mean, std = self.out(self.trunk(x)).float().chunk(2, -1)
        if self.dist_name == "trunc_normal":
            return TruncNormal(torch.tanh(mean),
                               2 * torch.sigmoid((std + self.init_std) / 2) + self.min_std)
        return TanhNormal(5 * torch.tanh(mean / 5),
                          F.softplus(std + self.init_std) + self.min_std)
