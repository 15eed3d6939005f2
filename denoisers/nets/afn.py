"""Networks of the affinity-of-neural-features denoiser (Isik et al. 2021, Sec. 3.2-3.3, Fig. 2).

* Sample embedding (Eq. 1): a pointwise network of 3 fully connected layers with ``embed_features`` (32)
  channels and leaky ReLU, applied to every sample's 18 render-buffer features (:data:`SAMPLE_FEATURES`),
  averaged over the pixel's samples.
* U-Net (Eq. 2): 5 scales, two 3 x 3 convolutions per scale, 2 x 2 max pooling down, bilinear 2x up,
  concatenated skips; the paper's feature counts c64c64 -> c64c64 -> c64c64 -> c80c80 -> c96c96 (bottleneck)
  -> c80c80 -> c64c64 -> c64c64 -> c32 + output convolution, multiplied by ``width`` (1 = the paper; the
  default 0.5 for two CPU cores). Leaky ReLU (slope 0.01, torch's default: the paper names no slope) after
  every convolution but the last. At width 1, K = 3, d = 8 the output convolution has 32 channels, the
  paper's final "c32".
* Output per pixel: for each of the K kernels the affinity features f^k (d), the bandwidth a^k = raw^2 and
  the centre weight c^k = sigmoid(raw); then the temporal bandwidth b = raw^2 and the accumulation weight
  lambda = sigmoid(raw) (temporal models only). Gather-kernel models (Table 5) instead predict k*k logits per
  kernel (:func:`denoisers.affinity.gather_sums`).

The network's input is the current frame's embedding and (temporal models) the warped accumulated embedding
of the previous frame plus the renderer's reprojection validity (0 at a shot's first frame; our addition:
the paper's U-Net sees the warp only), or for ``history_input = 'prediction'`` (ours-wpred) the warped
previous output, log(1 + x), instead of the accumulated embedding. The frame loop and the filtering are
denoisers.nets.afn_task. Shapes (N, C, H, W); H and W are padded (replicate) to a multiple of 16 inside.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from denoisers.nets.ntasd import pad_to

#: Per-sample input features (Sec. 3.1): name -> channels; radiance parts as log(1 + x).
SAMPLE_FEATURES: tuple[tuple[str, int], ...] = (
    ("diffuse", 3), ("specular", 3), ("normal", 3), ("depth", 1), ("roughness", 1), ("albedo", 3), ("flags", 4))
SAMPLE_CHANNELS = sum(c for _, c in SAMPLE_FEATURES)
#: U-Net features of the paper (Sec. 3.3): encoder levels, bottleneck, and the last decoder convolution.
BASE_FEATURES = (64, 64, 64, 80, 96)
BASE_LAST = 32
KERNEL_KINDS = ("affinity", "gather")
HISTORY_INPUTS = ("embedding", "prediction")
#: Pixels per block of the per-sample embedding (:meth:`AFNNet.embed`): 4096 x S x 32 floats stay in cache.
EMBED_CHUNK = 4096


@dataclass(frozen=True)
class AFNConfig:
    """temporal: accumulation (Eq. 3, 5) and the temporal kernel (Eq. 7-8); False = ours-single.
    kernels: K; kernel_size: spatial taps per side (13; can change at test time); dilate: dilation 2^(k-1)
    for kernel k (False: all undilated, with K = 1 = ours-K1); affinity_dim: d; kernel_kind: 'affinity' or
    'gather' (Table 5, single-frame only); temporal_kernel_size: taps per side of Eq. 7 (13);
    temporal_kernel: False = ours-ntk; accumulate_radiance: False = ours-nar; fixed_lambda: a constant
    accumulation weight instead of the learned one (0.8 = ours-heur); history_input: 'embedding' or
    'prediction' (ours-wpred); width: U-Net feature multiplier; embed_features: sample-embedding channels."""

    temporal: bool = True
    kernels: int = 3
    kernel_size: int = 13
    dilate: bool = True
    affinity_dim: int = 8
    kernel_kind: str = "affinity"
    temporal_kernel_size: int = 13
    temporal_kernel: bool = True
    accumulate_radiance: bool = True
    fixed_lambda: float | None = None
    history_input: str = "embedding"
    width: float = 0.5
    embed_features: int = 32

    def __post_init__(self) -> None:
        if self.kernel_kind not in KERNEL_KINDS:
            raise ValueError(f"afn: net.kernel_kind = {self.kernel_kind!r} is unknown; allowed: {KERNEL_KINDS}")
        if self.history_input not in HISTORY_INPUTS:
            raise ValueError(f"afn: net.history_input = {self.history_input!r} is unknown; allowed: {HISTORY_INPUTS}")
        if self.kernel_kind == "gather" and self.temporal:
            raise ValueError("afn: gather kernels (Table 5) are single-frame: set net.temporal false")
        for name in ("kernel_size", "temporal_kernel_size"):
            size = getattr(self, name)
            if size < 1 or size % 2 == 0:
                raise ValueError(f"afn: net.{name} must be odd and >= 1, got {size}")
        if self.kernels < 1 or self.affinity_dim < 1 or self.width <= 0 or self.embed_features < 1:
            raise ValueError(f"afn: need kernels >= 1, affinity_dim >= 1, width > 0, embed_features >= 1; got {self}")
        if self.fixed_lambda is not None and not 0 <= self.fixed_lambda <= 1:
            raise ValueError(f"afn: net.fixed_lambda must lie in [0, 1], got {self.fixed_lambda}")

    def dilation(self, k: int) -> int:
        """Dilation of kernel k = 0..K-1: 2^k when dilated (the paper's 2^(k-1) for k = 1..K), else 1."""
        return 2 ** k if self.dilate else 1

    @property
    def kernel_channels(self) -> int:
        """Output channels per spatial kernel: f, a, c (affinity) or k*k logits (gather)."""
        return self.affinity_dim + 2 if self.kernel_kind == "affinity" else self.kernel_size ** 2

    @property
    def out_channels(self) -> int:
        return self.kernels * self.kernel_channels + (2 if self.temporal else 0)

    @property
    def in_channels(self) -> int:
        """Current embedding, + (temporal) the warped history (embedding or 3 colour channels) and validity."""
        if not self.temporal:
            return self.embed_features
        return self.embed_features + (self.embed_features if self.history_input == "embedding" else 3) + 1

    @property
    def features(self) -> list[int]:
        return [max(4, int(round(f * self.width))) for f in BASE_FEATURES]

    @property
    def last_features(self) -> int:
        return max(4, int(round(BASE_LAST * self.width)))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "AFNConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise KeyError(f"afn: unknown net keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**dict(data))


@dataclass
class KernelParameters:
    """One frame's per-pixel parameters: lists over the K kernels of f (N, d, H, W), a, c (N, 1, H, W) (affinity)
    or logits (N, k*k, H, W) (gather); b and lambda (N, 1, H, W) for temporal models."""

    features: list[torch.Tensor]
    bandwidth: list[torch.Tensor]
    center: list[torch.Tensor]
    logits: list[torch.Tensor]
    temporal_bandwidth: torch.Tensor | None
    blend: torch.Tensor | None


def _conv(in_channels: int, out_channels: int, size: int = 3) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size=size, padding=size // 2)


class AFNUNet(nn.Module):
    """The paper's 5-scale U-Net (module docstring): (N, C_in, H, W) -> (N, C_out, H, W), H, W multiples of 16."""

    def __init__(self, in_channels: int, out_channels: int, features: list[int], last: int) -> None:
        super().__init__()
        self.encoder = nn.ModuleList()
        previous = in_channels
        for count in features:
            self.encoder.append(nn.ModuleList([_conv(previous, count), _conv(count, count)]))
            previous = count
        self.decoder = nn.ModuleList()
        for level in range(len(features) - 2, 0, -1):
            self.decoder.append(nn.ModuleList([_conv(previous + features[level], features[level]),
                                               _conv(features[level], features[level])]))
            previous = features[level]
        self.last = nn.ModuleList([_conv(previous + features[0], last), _conv(last, out_channels)])
        self.multiple = 2 ** (len(features) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for level, (first, second) in enumerate(self.encoder):
            if level:
                x = F.max_pool2d(x, 2)
            x = F.leaky_relu(second(F.leaky_relu(first(x))))
            skips.append(x)
        for (first, second), skip in zip(self.decoder, reversed(skips[1:-1])):
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
            x = F.leaky_relu(second(F.leaky_relu(first(torch.cat([x, skip], dim=1)))))
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        first, output = self.last
        return output(F.leaky_relu(first(torch.cat([x, skips[0]], dim=1))))


class AFNNet(nn.Module):
    """Sample embedding + U-Net of one AFN variant.

    :meth:`embed` (N, S, 18, H, W) sample features -> (N, E, H, W) per-pixel embedding (Eq. 1);
    :meth:`parameters_from` (N, C_in, H, W) U-Net input -> :class:`KernelParameters` (Eq. 2).
    """

    NET_NAME = "afn"
    Config = AFNConfig

    def __init__(self, config: AFNConfig | None = None) -> None:
        super().__init__()
        self.config = c = config or AFNConfig()
        self.embedding = nn.Sequential(nn.Conv2d(SAMPLE_CHANNELS, c.embed_features, 1), nn.LeakyReLU(),
                                       nn.Conv2d(c.embed_features, c.embed_features, 1), nn.LeakyReLU(),
                                       nn.Conv2d(c.embed_features, c.embed_features, 1), nn.LeakyReLU())
        self.unet = AFNUNet(c.in_channels, c.out_channels, c.features, c.last_features)

    def embed(self, samples: torch.Tensor) -> torch.Tensor:
        n, s, channels, height, width = samples.shape
        if channels != SAMPLE_CHANNELS:
            raise ValueError(f"afn: samples must have {SAMPLE_CHANNELS} feature channels, got {channels}")
        if torch.is_grad_enabled():      # training: 1 x 1 convolutions over N * S images (the faster backward)
            embedded = self.embedding(samples.reshape(n * s, channels, height, width))
            return embedded.view(n, s, -1, height, width).mean(dim=1)
        # Inference: the same layers as matrix products over pixel-major rows, EMBED_CHUNK pixels (times S
        # samples) at a time so that the intermediates stay in cache, bias fused into the product, activations
        # in place, a channels-last result for the U-Net. The convolutions took half of a frame (torch's slow
        # 1 x 1 path); unchunked matrix products twice the time of these at 256^2.
        rows = samples.permute(0, 3, 4, 1, 2).reshape(n * height * width, s, channels)
        means = []
        for start in range(0, rows.shape[0], EMBED_CHUNK):
            x = rows[start:start + EMBED_CHUNK]
            for layer in self.embedding:
                if isinstance(layer, nn.Conv2d):
                    x = F.linear(x, layer.weight.flatten(1), layer.bias)
                else:
                    x = F.leaky_relu(x, layer.negative_slope, inplace=True)
            means.append(x.mean(dim=1))
        return torch.cat(means).view(n, height, width, -1).permute(0, 3, 1, 2)

    def parameters_from(self, x: torch.Tensor) -> KernelParameters:
        c = self.config
        height, width = x.shape[-2:]
        # One float32, contiguous (NCHW) copy of the channels-last output: the kernels read per-channel planes,
        # and slicing them out of channels-last memory cost one strided copy per kernel call.
        out = self.unet(pad_to(x, self.unet.multiple))[:, :, :height, :width].to(
            torch.float32, memory_format=torch.contiguous_format)
        features, bandwidth, center, logits = [], [], [], []
        for k in range(c.kernels):
            block = out[:, k * c.kernel_channels:(k + 1) * c.kernel_channels]
            if c.kernel_kind == "gather":
                logits.append(block)
                continue
            d = c.affinity_dim
            features.append(block[:, :d])
            bandwidth.append(block[:, d:d + 1].square())
            center.append(torch.sigmoid(block[:, d + 1:d + 2]))
        temporal_bandwidth = blend = None
        if c.temporal:
            rest = out[:, c.kernels * c.kernel_channels:]
            temporal_bandwidth = rest[:, :1].square()
            blend = torch.sigmoid(rest[:, 1:2])
        return KernelParameters(features, bandwidth, center, logits, temporal_bandwidth, blend)
