"""Networks of neural temporal adaptive sampling and denoising (Hasselgren et al. 2020, Sec. 2.1, Fig. 3).

Both networks are U-Nets with 3 x 3 convolutions throughout (:class:`UNet`): ``levels`` = 5 resolutions,
two convolutions per level, 2 x 2 average pooling down, nearest-neighbour 2x up with concatenation of the
encoder features (skip connections), leaky ReLU (slope 0.1). Feature counts per level are
``width`` x (32, 48, 64, 80, 96): at width 1 the denoiser U-Net has about 0.85 M weights, the "~850k
weights" the paper states for its (and its DASR's) U-Nets; the paper's Fig. 3 feature counts are not in
its text, so these are ours. The default config trains width 0.5 (about 4x fewer multiply-adds) for two
CPU cores; the size is a config key (``net.width``) and a capacity sweep can choose it.

* Sample-map estimator (:class:`NTASDNet` ``sampler``): one linear output channel, the unnormalised
  s(p) of Eq. 2 (denoisers.adaptive.capped_density normalises it to the average budget within the stored layers).
* Denoiser, kernel prediction (``variant`` 'kpn' and 'temporal'): heads on the decoder's last three
  levels predict per-pixel 5 x 5 kernels (softmax-normalised) for the full, 1/2 and 1/4 resolution noisy
  image and a blend weight alpha (sigmoid) at 1/2 and 1/4 for the scale composition of Vogels et al.
  (denoisers.kernels.compose_multiscale); 'temporal' adds at full resolution a 5 x 5 kernel for the warped
  previous output and its blend weight alpha' (51 features at the finest level, 26 at the coarser ones,
  as in Fig. 3). 'direct': one linear 3-channel output, the denoised colour.

All images here are in the paper's training space ``x' = log(1 + clamp(x, 0, 65535))^(1/2.2)``
(:func:`encode`; Sec. 2.2): the network inputs, the kernels' operands (noisy image and warped history)
and the output; :func:`decode` inverts it. Shapes: (N, C, H, W); H and W are padded (replicate) to a
multiple of 2^(levels-1) inside and cropped back.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from denoisers import kernels

#: Sec. 2.2: inputs clamped to [0, 65535], then log(x + 1)^(1/2.2).
CLAMP_MAX = 65535.0
GAMMA = 2.2
BASE_FEATURES = (32, 48, 64, 80, 96)
VARIANTS = ("direct", "kpn", "temporal")
SAMPLINGS = ("uniform", "adaptive", "dasr")
NEGATIVE_SLOPE = 0.1
#: Guides fed to both networks: view-space normal (3), log(1 + depth) (1), albedo (3).
GUIDE_CHANNELS = 7
#: Per-pixel motion (2, pixels / MOTION_SCALE) and history validity (1), temporal variants only.
MOTION_CHANNELS = 3
MOTION_SCALE = 16.0


#: Below this log-radiance the power 1/2.2 is replaced by its secant through 0 (linear), so the encoding has a
#: finite derivative at black (an adaptive pixel with 0 samples); a radiance of 1e-4 is far below display.
LINEAR_BELOW = 1e-4


def encode(linear: torch.Tensor) -> torch.Tensor:
    """Linear HDR radiance -> the training space log(1 + clamp(x, 0, 65535))^(1/2.2); non-finite -> 0
    (linear below :data:`LINEAR_BELOW` in log space, where y^(1/2.2) has an infinite slope at 0)."""
    clean = torch.nan_to_num(linear, nan=0.0, posinf=CLAMP_MAX, neginf=0.0).clamp(0.0, CLAMP_MAX)
    y = torch.log1p(clean)
    power = y.clamp_min(LINEAR_BELOW).pow(1.0 / GAMMA)
    return torch.where(y >= LINEAR_BELOW, power, y * LINEAR_BELOW ** (1.0 / GAMMA - 1.0))


def decode(encoded: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`encode` (negative inputs -> 0)."""
    e = encoded.clamp_min(0.0)
    knee = LINEAR_BELOW ** (1.0 / GAMMA)
    y = torch.where(e >= knee, e.clamp_min(knee).pow(GAMMA), e / LINEAR_BELOW ** (1.0 / GAMMA - 1.0))
    return torch.expm1(y)


def grey(rgb: torch.Tensor) -> torch.Tensor:
    """CCIR 601 luma 0.2989 r + 0.587 g + 0.114 b of (..., 3, H, W) -> (..., 1, H, W) (Sec. 2.2: the sampler's
    colour inputs)."""
    weights = torch.tensor([0.2989, 0.587, 0.114], dtype=rgb.dtype, device=rgb.device).view(3, 1, 1)
    return (rgb * weights).sum(dim=-3, keepdim=True)


@dataclass(frozen=True)
class NTASDConfig:
    """variant: 'direct' | 'kpn' | 'temporal'; sampling: 'uniform' | 'adaptive' (sample-map network on the
    warped history and guides, temporal only) | 'dasr' (sample-map network on a 1-spp initial pass, per
    frame); width: feature multiplier; levels: U-Net resolutions (kernels at the finest three, so >= 3);
    kernel_size: odd; max_samples: stored radiance layers a pixel can get (S_avail)."""

    variant: str = "temporal"
    sampling: str = "adaptive"
    width: float = 0.5
    levels: int = 5
    kernel_size: int = kernels.DEFAULT_KERNEL_SIZE
    max_samples: int = 32

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"ntasd: net.variant = {self.variant!r} is unknown; allowed: {', '.join(VARIANTS)}")
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"ntasd: net.sampling = {self.sampling!r} is unknown; allowed: {', '.join(SAMPLINGS)}")
        if self.sampling == "adaptive" and self.variant != "temporal":
            raise ValueError("ntasd: net.sampling 'adaptive' reads the warped previous output, so it needs "
                             f"net.variant 'temporal', got {self.variant!r} (per-frame adaptive sampling is 'dasr')")
        if not 3 <= int(self.levels) <= len(BASE_FEATURES):
            raise ValueError(f"ntasd: net.levels must lie in 3..{len(BASE_FEATURES)}, got {self.levels}")
        if self.width <= 0 or self.kernel_size < 1 or self.kernel_size % 2 == 0 or self.max_samples < 1:
            raise ValueError(f"ntasd: need width > 0, odd kernel_size >= 1, max_samples >= 1; got {self}")

    @property
    def temporal(self) -> bool:
        return self.variant == "temporal"

    @property
    def adaptive(self) -> bool:
        return self.sampling != "uniform"

    @property
    def features(self) -> list[int]:
        return [max(4, int(round(f * self.width))) for f in BASE_FEATURES[:self.levels]]

    @property
    def denoiser_in_channels(self) -> int:
        """Noisy colour (3) + guides, + motion/validity and the warped history (3) when temporal, + the
        sample count relative to the budget (1) when adaptive."""
        return 3 + GUIDE_CHANNELS + (MOTION_CHANNELS + 3 if self.temporal else 0) + (1 if self.adaptive else 0)

    @property
    def sampler_in_channels(self) -> int:
        """'adaptive': grey warped history (1) + normal, depth (4) + grey albedo (1) + motion/validity (3);
        'dasr': the initial 1-spp colour (3) + guides (7); 0 for uniform sampling."""
        if self.sampling == "adaptive":
            return 1 + 4 + 1 + MOTION_CHANNELS
        return 3 + GUIDE_CHANNELS if self.sampling == "dasr" else 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "NTASDConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise KeyError(f"ntasd: unknown net keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**dict(data))


def _conv(in_channels: int, out_channels: int) -> nn.Conv2d:
    conv = nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1)
    nn.init.xavier_uniform_(conv.weight)   # Sec. 2.2: Xavier initialisation
    nn.init.zeros_(conv.bias)
    return conv


class UNet(nn.Module):
    """Encoder-decoder with skips; returns the decoder's features at every level, finest first:
    [(N, F_0, H, W), (N, F_1, H/2, W/2), ...] (the bottleneck is the coarsest entry)."""

    def __init__(self, in_channels: int, features: list[int]) -> None:
        super().__init__()
        self.features = list(features)
        self.encoder = nn.ModuleList()
        previous = in_channels
        for count in self.features:
            self.encoder.append(nn.ModuleList([_conv(previous, count), _conv(count, count)]))
            previous = count
        self.decoder = nn.ModuleList()
        for level in range(len(self.features) - 2, -1, -1):
            count = self.features[level]
            self.decoder.append(nn.ModuleList([_conv(previous + count, count), _conv(count, count)]))
            previous = count

    @property
    def multiple(self) -> int:
        return 2 ** (len(self.features) - 1)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        skips = []
        for level, (first, second) in enumerate(self.encoder):
            if level:
                x = F.avg_pool2d(x, 2)
            x = F.leaky_relu(second(F.leaky_relu(first(x), NEGATIVE_SLOPE)), NEGATIVE_SLOPE)
            skips.append(x)
        outputs = [x]
        for (first, second), skip in zip(self.decoder, reversed(skips[:-1])):
            x = torch.cat([F.interpolate(x, scale_factor=2, mode="nearest"), skip], dim=1)
            x = F.leaky_relu(second(F.leaky_relu(first(x), NEGATIVE_SLOPE)), NEGATIVE_SLOPE)
            outputs.append(x)
        return outputs[::-1]


def pad_to(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """(N, C, H, W) replicate-padded at the bottom and right to multiples of ``multiple``."""
    height, width = x.shape[-2:]
    pad_h, pad_w = (-height) % multiple, (-width) % multiple
    return F.pad(x, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else x


class NTASDNet(nn.Module):
    """The sample-map estimator (when ``config.adaptive``) and the denoiser of one NTASD variant.

    :meth:`sample_logits` (N, C_s, H, W) -> (N, H, W) s(p); :meth:`denoise` (N, C_d, H, W) network input,
    (N, 3, H, W) encoded noisy image, optional (N, 3, H, W) encoded warped history -> (N, 3, H, W) encoded
    output. denoisers.nets.ntasd_task assembles the inputs and runs the frame loop.
    """

    NET_NAME = "ntasd"
    Config = NTASDConfig

    def __init__(self, config: NTASDConfig | None = None) -> None:
        super().__init__()
        self.config = config or NTASDConfig()
        c = self.config
        features = c.features
        self.sampler = UNet(c.sampler_in_channels, features) if c.adaptive else None
        self.sampler_head = _conv(features[0], 1) if c.adaptive else None
        self.denoiser = UNet(c.denoiser_in_channels, features)
        taps = c.kernel_size ** 2
        if c.variant == "direct":
            self.heads = nn.ModuleList([_conv(features[0], 3)])
        else:
            finest = taps + (taps + 1 if c.temporal else 0)
            self.heads = nn.ModuleList([_conv(features[0], finest), _conv(features[1], taps + 1),
                                        _conv(features[2], taps + 1)])

    @property
    def multiple(self) -> int:
        return self.denoiser.multiple

    def sample_logits(self, x: torch.Tensor) -> torch.Tensor:
        if self.sampler is None:
            raise RuntimeError(f"ntasd: sampling {self.config.sampling!r} has no sample-map network")
        height, width = x.shape[-2:]
        features = self.sampler(pad_to(x, self.sampler.multiple))[0]
        return self.sampler_head(features)[:, 0, :height, :width]

    def denoise(self, x: torch.Tensor, noisy: torch.Tensor, history: torch.Tensor | None = None) -> torch.Tensor:
        height, width = x.shape[-2:]
        decoded = self.denoiser(pad_to(x, self.multiple))
        if self.config.variant == "direct":
            return self.heads[0](decoded[0])[:, :, :height, :width]
        taps = self.config.kernel_size ** 2
        noisy = pad_to(noisy, self.multiple)
        pyramid = [noisy, kernels.downsample(noisy), kernels.downsample(kernels.downsample(noisy))]
        # Kernel weights and blends in float32 under bf16 autocast: a bf16 sigmoid/softmax rounds to exactly
        # 1 at logits above ~6, and the saturated weight then has no gradient to come back.
        outputs = [head(level).float() for head, level in zip(self.heads, decoded)]
        spatial = [torch.softmax(out[:, :taps], dim=1) for out in outputs]
        filtered = [kernels.apply_kernels(image, weights) for image, weights in zip(pyramid, spatial)]
        alphas = [torch.sigmoid(out[:, taps:taps + 1]) for out in outputs[1:]]
        result = kernels.compose_multiscale(filtered, alphas)
        if self.config.temporal:
            if history is None:
                raise ValueError("ntasd: the temporal variant needs the warped history (at a shot's start the noisy uniform image)")
            finest = outputs[0]
            history_kernel = torch.softmax(finest[:, taps:2 * taps], dim=1)
            blend = torch.sigmoid(finest[:, 2 * taps:2 * taps + 1])
            result = kernels.temporal_blend(result, pad_to(history, self.multiple), history_kernel, blend)
        return result[:, :, :height, :width]
