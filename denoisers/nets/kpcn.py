"""Networks of the kernel-predicting convolutional network (KPCN, Bako et al. 2017), the single-frame
baseline Isik et al. 2021 compare with (their Sec. 5.1: "We followed Bako et al. [2017] for our
implementation of KPCN ... we adopted 17 x 17 kernels for SBMC and KPCN rather than their original 21 x 21").

No text of Bako et al. is available in this project; this follows what is well known about KPCN:

* Two networks of the same architecture, one for the diffuse and one for the specular component of the
  radiance (``radiance = diffuse + specular``, docs/data-format.md). Diffuse is demodulated, divided by
  (albedo + 0.00316), before filtering and multiplied back after; specular is log-transformed, log(1 + x),
  before filtering and exp(x) - 1 after. Output = diffuse' x (albedo + 0.00316) + specular'.
* Each network is a plain CNN of ``layers`` convolutions (Bako: 9 layers of 100 5 x 5 kernels), ReLU after
  every one but the last, zero ("same") padding (ours: Bako trains on valid convolutions of padded
  patches), Xavier-uniform weights and zero biases. The last layer predicts k*k kernel logits per pixel
  (k = ``kernel_size``: 17, Isik's size; Bako 21); the kernel weights are their softmax over the k*k taps
  (denoisers.nets.kpcn_task applies them to the transformed noisy colour).
* Input per branch (:data:`INPUTS`; per-pixel statistics over the frame's samples, built by
  denoisers.nets.kpcn_task.branch_inputs): the branch's transformed colour (3), its variance (1), the colour's
  x / y gradients (6), the gradients of the auxiliary features normal (6), depth (2) and albedo (6), and the
  features' variances (1 each): 27 channels. Bako et al. feed gradients of colour and features, and
  variances, not the features themselves; 27 input channels is also what reproduces Isik et al.'s count
  (Sec. 5.4: "KPCN: 5.08M") exactly: 9 layers of 100 5 x 5 kernels with 17 x 17 kernels have 5 082 178
  parameters at 27 inputs (5 117 178 at 34). ``raw_features`` (ours, off by default) adds the features
  themselves (normal 3, depth 1, albedo 3): 34 channels.

Size (configurable for the two CPU cores here): ``layers`` (9), ``features`` (None = 100 x ``width``; width
0.25 by default -> 25; width 1 = Bako's 100), ``conv_size`` (5), ``kernel_size`` (17). Parameters (both
networks): 614 728 at the defaults, 5 082 178 at width 1 (Isik's 5.08M).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import nn

#: Per-branch network input, in channel order: name -> channels (module docstring). "colour" is the branch's
#: transformed colour (demodulated diffuse, log specular); variances are one channel each (the mean over the
#: buffer's channels of the variance of the per-pixel mean); gradients: x of every channel, then y.
INPUTS: tuple[tuple[str, int], ...] = (
    ("colour", 3), ("colour_variance", 1), ("colour_gradient", 6),
    ("normal_gradient", 6), ("depth_gradient", 2), ("albedo_gradient", 6),
    ("normal_variance", 1), ("depth_variance", 1), ("albedo_variance", 1))
#: Added by ``raw_features`` (ours): the per-pixel mean features themselves.
RAW_FEATURES: tuple[tuple[str, int], ...] = (("normal", 3), ("depth", 1), ("albedo", 3))
#: Convolution features of Bako et al. (width 1).
BASE_FEATURES = 100
BRANCHES = ("diffuse", "specular")


@dataclass(frozen=True)
class KPCNConfig:
    """layers: convolutions per network (>= 2); width: features = round(100 x width) unless ``features`` is
    given; conv_size: odd convolution size; kernel_size: odd taps per side of the predicted kernels;
    raw_features: add the per-pixel feature means to the input (ours; Bako et al. feed their gradients)."""

    layers: int = 9
    width: float = 0.25
    features: int | None = None
    conv_size: int = 5
    kernel_size: int = 17
    raw_features: bool = False

    def __post_init__(self) -> None:
        if self.layers < 2:
            raise ValueError(f"kpcn: net.layers must be >= 2, got {self.layers}")
        if self.width <= 0 or (self.features is not None and self.features < 1):
            raise ValueError(f"kpcn: need net.width > 0 and net.features >= 1 (or null), got width {self.width}, "
                             f"features {self.features}")
        for name in ("conv_size", "kernel_size"):
            size = getattr(self, name)
            if size < 1 or size % 2 == 0:
                raise ValueError(f"kpcn: net.{name} must be odd and >= 1, got {size}")

    @property
    def channels(self) -> int:
        """Convolution features of the hidden layers."""
        return int(self.features) if self.features is not None else max(1, int(round(BASE_FEATURES * self.width)))

    @property
    def inputs(self) -> tuple[tuple[str, int], ...]:
        return INPUTS + (RAW_FEATURES if self.raw_features else ())

    @property
    def in_channels(self) -> int:
        return sum(c for _, c in self.inputs)

    @property
    def out_channels(self) -> int:
        return self.kernel_size ** 2

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "KPCNConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise KeyError(f"kpcn: unknown net keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**dict(data))


class KPCNBranch(nn.Module):
    """One branch's plain CNN: (N, C_in, H, W) -> (N, k*k, H, W) kernel logits."""

    def __init__(self, config: KPCNConfig) -> None:
        super().__init__()
        c = config
        sizes = [c.in_channels] + [c.channels] * (c.layers - 1) + [c.out_channels]
        self.convs = nn.ModuleList(nn.Conv2d(a, b, c.conv_size, padding=c.conv_size // 2)
                                   for a, b in zip(sizes[:-1], sizes[1:]))
        for conv in self.convs:
            nn.init.xavier_uniform_(conv.weight)
            nn.init.zeros_(conv.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv in self.convs[:-1]:
            x = torch.relu(conv(x))
        return self.convs[-1](x)


class KPCNNet(nn.Module):
    """The diffuse and the specular network: ``forward(x_diffuse, x_specular)`` (N, C_in, H, W) each ->
    (diffuse logits, specular logits), (N, k*k, H, W) each."""

    NET_NAME = "kpcn"
    Config = KPCNConfig

    def __init__(self, config: KPCNConfig | None = None) -> None:
        super().__init__()
        self.config = config or KPCNConfig()
        self.diffuse = KPCNBranch(self.config)
        self.specular = KPCNBranch(self.config)

    def forward(self, x_diffuse: torch.Tensor, x_specular: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        channels = self.config.in_channels
        if x_diffuse.shape[1] != channels or x_specular.shape[1] != channels:
            raise ValueError(f"kpcn: inputs must have {channels} channels, got {x_diffuse.shape[1]} and "
                             f"{x_specular.shape[1]}")
        return self.diffuse(x_diffuse), self.specular(x_specular)
