"""The recurrent denoising autoencoder (RAE) of Chaitanya et al. 2017, its inputs and its training task.

Architecture (§4.1-4.2, Fig. 2, and the highlighted "AE" column of Fig. 4a), all convolutions 3 x 3 with
"same" padding, leaky ReLU (slope 0.1) after every convolution except the linear output layer (§5.3):

* encoder stage k = 0 .. L-1 (L = ``levels`` = 5) at resolution 1/2^k: convolution(s) to F_k features
  (two at stage 0: Fig. 4's "conv-32,32"), a recurrent block of F_k features, 2 x 2 max pooling.
  F_k = round(32 (4/3)^k) = 32, 43, 57, 76, 101 ("32 features in the first stage, multiplied by 4/3
  after every subsampling", §5.1).
* bottleneck at 1/2^L: one convolution to F_{L-1} (= 101, Fig. 4: the count does not grow here) and a
  recurrent block; L + 1 = 6 recurrent blocks in total.
* decoder stage at resolution 1/2^k, k = L-1 .. 0: 2 x 2 nearest-neighbour upsampling, concatenation
  with the encoder's recurrent-block output at that resolution (the skip connection), two
  convolutions to F_{k-1} features (76, 57, 43, 32), and at full resolution to 128 and 64 features
  (Fig. 4's "conv-128,64").
* output: one linear convolution to 3 channels.

That is 7 encoder + 10 decoder + 1 output convolutions and 3 in each of the 6 recurrent blocks, the 36
layers counted in §5.1. A recurrent block (§4.2) computes h_i = O_i = C(C(C(I_i) ^ h_{i-1})): a
convolution of the stage's input, concatenation with the previous hidden state, two more
convolutions; the result is both the block's output and the new hidden state (zeros at the start).

Inputs (§3.2): noisy radiance demodulated by the albedo (3), view-space shading normal x, y (2), depth
(1), roughness (1) = 7 channels. Colour is raised to the power 0.2 before it enters the network and
the training target likewise (§4.4, "raises both the input and target images into power 0.2 as a
preprocess"); the network's output is in that space, so the final image is
max(output, 0)^(1/0.2), re-modulated by the albedo. Building these inputs from a frame's buffers and the
training task live in :mod:`denoisers.nets.rae_task`.

Parameter count: the architecture above has 1,951,935 parameters at full size; §5.2 states 3.2 million.
No reading of Fig. 4 that keeps the 36 layers of §5.1 gives 3.2 million (Fig. 4's "AE large" column
with six pooling stages gives 3,429,947), so the figure's layer list is followed.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn


#: §5.2: "Our network has a total of 3.2 million trainable parameters".
PAPER_PARAMETER_COUNT = 3_200_000
#: Auxiliary features the network can take, in channel order, with their channel counts.
AUX_FEATURES: dict[str, int] = {"normal": 2, "depth": 1, "roughness": 1}
#: Where an RAE's albedo and auxiliary features come from (RAEConfig.features_from).
FEATURE_SOURCES: tuple[str, ...] = ("samples", "gbuffer")
#: How the first convolution's weights on the auxiliary features start (RAEConfig.feature_init).
FEATURE_INITS: tuple[str, ...] = ("he", "zero")
#: Encodings of the depth feature (RAEConfig.depth_encoding), metres -> network input.
DEPTH_ENCODINGS: dict[str, Any] = {"metres": lambda depth: depth,
                                   "log1p": lambda depth: torch.log1p(depth.clamp_min(0))}

State = list[torch.Tensor]


@dataclass(frozen=True)
class RAEConfig:
    """Architecture and input encoding of an RAE (defaults: the paper's network).

    width: multiplies every hidden feature count (1 = the paper's; < 1 for CPU budgets);
    levels: pooling stages (5 in the paper; 4 and 6 are Fig. 4's "AE small" and "AE large");
    demodulate: divide colour by max(albedo, albedo_floor) and multiply the output back (§3.2);
    features: auxiliary inputs, a subset of normal / depth / roughness (Fig. 3's ablation);
    exponent: the power applied to colour inputs and targets (0.2, §4.4);
    depth_encoding: how the depth feature enters: "metres" (view distance as rendered; 0-85 m in the open
    scenes) or "log1p" (log(1 + metres): 0-4.5, the range of the other inputs). §3.2 only says the depth is
    "linearized"; the scale is ours;
    features_from: where the albedo and the auxiliary features come from: "samples" (the mean of the frame's
    per-sample buffers, one jittered sample per pixel at 1 spp) or "gbuffer" (the pixel-centre G-buffer pass,
    noise-free: the paper's rasterised G-buffer, §3.1-3.2; method and task ``rae``; ``rae_samples`` reads the
    samples);
    feature_init: how the first convolution's weights on the auxiliary feature channels start: "he" (§5.3, like
    every other weight) or "zero" (ours: training starts from the function of the colour-only network and the
    features' weights grow only as far as they lower the loss; docs/findings.md "RAE: initialising the feature
    inputs").
    """

    width: float = 1.0
    levels: int = 5
    base_features: int = 32
    growth: float = 4.0 / 3.0
    final_features: tuple[int, int] = (128, 64)
    negative_slope: float = 0.1
    demodulate: bool = True
    features: tuple[str, ...] = ("normal", "depth", "roughness")
    exponent: float = 0.2
    albedo_floor: float = 0.01
    depth_encoding: str = "metres"
    features_from: str = "samples"
    feature_init: str = "he"

    def __post_init__(self) -> None:
        object.__setattr__(self, "features", tuple(self.features))
        object.__setattr__(self, "final_features", tuple(int(f) for f in self.final_features))
        unknown = [f for f in self.features if f not in AUX_FEATURES]
        if unknown or len(set(self.features)) != len(self.features):
            raise ValueError(f"rae: features must be distinct names among {list(AUX_FEATURES)}, got {list(self.features)}")
        if not self.width > 0 or self.levels < 1 or not 0 < self.exponent <= 1 or not self.albedo_floor > 0:
            raise ValueError(f"rae: need width > 0, levels >= 1, 0 < exponent <= 1, albedo_floor > 0; got {self}")
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise ValueError(f"rae: depth_encoding must be one of {list(DEPTH_ENCODINGS)}, got {self.depth_encoding!r}")
        if self.feature_init not in FEATURE_INITS:
            raise ValueError(f"rae: feature_init must be one of {list(FEATURE_INITS)}, got {self.feature_init!r}")
        if not self.features:
            # Nothing to initialise: a colour-only network is the same either way, and so is its fingerprint.
            object.__setattr__(self, "feature_init", "he")
        if self.features_from not in FEATURE_SOURCES:
            raise ValueError(f"rae: features_from must be one of {list(FEATURE_SOURCES)}, got {self.features_from!r}")
        if len(self.final_features) != 2:
            raise ValueError(f"rae: final_features needs two counts, got {self.final_features}")

    @property
    def in_channels(self) -> int:
        return 3 + sum(AUX_FEATURES[f] for f in self.features)

    def scaled(self, count: float) -> int:
        return max(1, int(round(count * self.width)))

    @property
    def encoder_features(self) -> list[int]:
        """F_k of encoder stages k = 0 .. levels-1."""
        return [self.scaled(self.base_features * self.growth**k) for k in range(self.levels)]

    @property
    def decoder_features(self) -> list[tuple[int, int]]:
        """(first, second) convolution outputs of decoder stages at resolutions 1/2^k, k = levels-1 .. 0."""
        enc = self.encoder_features
        stages = [(enc[k - 1], enc[k - 1]) for k in range(self.levels - 1, 0, -1)]
        return stages + [(self.scaled(self.final_features[0]), self.scaled(self.final_features[1]))]

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["features"] = list(self.features)
        data["final_features"] = list(self.final_features)
        # Defaults of keys added later are left out, so that checkpoints and model files written before the key
        # existed keep their fingerprint (a resumed training would otherwise refuse its own checkpoint).
        for key, default in (("depth_encoding", "metres"), ("features_from", "samples"), ("feature_init", "he")):
            if data[key] == default:
                del data[key]
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "RAEConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise TypeError(f"rae: unknown configuration keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**dict(data))


def _conv(in_channels: int, out_channels: int) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1)


def fused_conv_available() -> bool:
    """Whether this torch build has oneDNN's convolution with a fused pointwise post-op (the fast inference path)."""
    return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")


def conv_act(conv: nn.Conv2d, x: torch.Tensor, negative_slope: float | None, fast: bool = False) -> torch.Tensor:
    """leaky_relu(conv(x)) (plain conv(x) when ``negative_slope`` is None).

    ``fast`` (inference only, no autograd): float32 CPU tensors go through oneDNN's convolution with the
    leaky ReLU as a post-op, so the activation is applied while the output tile is still in cache instead
    of in a second pass over memory; otherwise the activation is applied in place.
    """
    if fast and x.device.type == "cpu" and x.dtype == torch.float32 and _FUSED_CONV:
        act = negative_slope is not None
        return torch.ops.mkldnn._convolution_pointwise(
            x, conv.weight, conv.bias, list(conv.padding), list(conv.stride), list(conv.dilation), conv.groups,
            "leaky_relu" if act else "none", [negative_slope] if act else [], "" if act else None)
    y = conv(x)
    if negative_slope is None:
        return y
    return F.leaky_relu_(y, negative_slope) if fast else F.leaky_relu(y, negative_slope)


_FUSED_CONV = fused_conv_available()


class RecurrentBlock(nn.Module):
    """h_i = C(C(C(x_i) ^ h_{i-1})) with leaky ReLU after each convolution (§4.2). (N, C, H, W) -> (N, C, H, W)."""

    def __init__(self, channels: int, negative_slope: float) -> None:
        super().__init__()
        self.channels = channels
        self.negative_slope = negative_slope
        self.input_conv = _conv(channels, channels)
        self.mix_conv = _conv(2 * channels, channels)
        self.output_conv = _conv(channels, channels)

    def forward(self, x: torch.Tensor, hidden: torch.Tensor | None, fast: bool = False) -> torch.Tensor:
        """``fast``: the inference path of :meth:`RecurrentAutoencoder.inference_step` (see :func:`conv_act`)."""
        slope = self.negative_slope
        if hidden is None and fast:
            hidden = torch.zeros_like(x, memory_format=torch.channels_last)  # x: (N, channels, H, W) too
        elif hidden is None:
            hidden = x.new_zeros(x.shape[0], self.channels, *x.shape[-2:])
        y = conv_act(self.input_conv, x, slope, fast)
        y = conv_act(self.mix_conv, torch.cat([y, hidden], dim=1), slope, fast)
        return conv_act(self.output_conv, y, slope, fast)


class RecurrentAutoencoder(nn.Module):
    """The RAE network on prepared inputs: (N, in_channels, H, W) -> (N, 3, H, W) in the 0.2-power space.

    ``step`` processes one frame with the recurrent state of the previous one; ``forward`` runs a
    sequence (N, T, C, H, W), carrying the state (back-propagation through time when training).
    Frames of any size work: they are padded (edge replication) to a multiple of 2^levels and the
    output is cropped back. The state is a list of ``levels + 1`` hidden tensors, or None (zeros).
    """

    NET_NAME = "rae"
    Config = RAEConfig

    def __init__(self, config: RAEConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or RAEConfig()
        enc = config.encoder_features
        self.encoder_convs = nn.ModuleList()
        self.encoder_blocks = nn.ModuleList()
        previous = config.in_channels
        for k, features in enumerate(enc):
            convs = [_conv(previous, features)] + ([_conv(features, features)] if k == 0 else [])
            self.encoder_convs.append(nn.ModuleList(convs))
            self.encoder_blocks.append(RecurrentBlock(features, config.negative_slope))
            previous = features
        self.bottleneck_conv = _conv(previous, enc[-1])
        self.bottleneck_block = RecurrentBlock(enc[-1], config.negative_slope)
        previous = enc[-1]
        self.decoder_convs = nn.ModuleList()
        for skip, (first, second) in zip(reversed(enc), config.decoder_features):
            self.decoder_convs.append(nn.ModuleList([_conv(previous + skip, first), _conv(first, second)]))
            previous = second
        self.output_conv = _conv(previous, 3)
        self._initialise()

    def _initialise(self) -> None:
        """He et al. 2015 initialisation (§5.3): normal, fan-in, gain of leaky ReLU 0.1; the linear
        output layer gets gain 1; biases 0. With ``feature_init`` "zero" the first convolution's weights on the
        auxiliary feature channels (input channels 3:) are then set to 0, so the initial network ignores them."""
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                if module is self.output_conv:
                    nn.init.kaiming_normal_(module.weight, nonlinearity="linear")
                else:
                    nn.init.kaiming_normal_(module.weight, a=self.config.negative_slope, nonlinearity="leaky_relu")
                nn.init.zeros_(module.bias)
        if self.config.feature_init == "zero":
            with torch.no_grad():
                self.encoder_convs[0][0].weight[:, 3:].zero_()

    @property
    def multiple(self) -> int:
        """Frame sizes are padded to a multiple of this."""
        return 2**self.config.levels

    def step(self, x: torch.Tensor, state: State | None = None) -> tuple[torch.Tensor, State]:
        """One frame: x (N, in_channels, H, W), state of the previous frame -> (output (N, 3, H, W), new state)."""
        return self._step(x, state, fast=False)

    def inference_step(self, x: torch.Tensor, state: State | None = None) -> tuple[torch.Tensor, State]:
        """:meth:`step` for inference: the same results up to float rounding, under ``torch.inference_mode``
        (no autograd; the outputs cannot be used in training).

        Activations are kept channels-last (NHWC), which oneDNN convolves directly with its brgemm kernels
        (with the default NCHW layout, ONEDNN_VERBOSE shows every convolution reordering its input to a
        blocked layout and its output back), and the leaky ReLU is fused into each convolution
        (:func:`conv_act`). Weights may be in either layout (channels-last saves a copy per call). The state
        it returns is channels-last too; either step accepts the other's state. ``benchmarks/rae_speed.py``
        measures the gain.
        """
        with torch.inference_mode():
            return self._step(x, state, fast=True)

    def _step(self, x: torch.Tensor, state: State | None, fast: bool) -> tuple[torch.Tensor, State]:
        if x.dim() != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(f"rae: expected input (N, {self.config.in_channels}, H, W), got {tuple(x.shape)}")
        height, width = x.shape[-2:]
        m = self.multiple
        pad_h, pad_w = (-height) % m, (-width) % m
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        if fast:
            x = x.contiguous(memory_format=torch.channels_last)
        n_blocks = self.config.levels + 1
        if state is not None and len(state) != n_blocks:
            raise ValueError(f"rae: state has {len(state)} tensors, expected {n_blocks}")
        hidden = list(state) if state is not None else [None] * n_blocks
        slope = self.config.negative_slope
        new_state: State = []
        skips = []
        for k, (convs, block) in enumerate(zip(self.encoder_convs, self.encoder_blocks)):
            for conv in convs:
                x = conv_act(conv, x, slope, fast)
            x = block(x, hidden[k], fast=fast)
            new_state.append(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottleneck_block(conv_act(self.bottleneck_conv, x, slope, fast), hidden[-1], fast=fast)
        new_state.append(x)
        for (first, second), skip in zip(self.decoder_convs, reversed(skips)):
            x = F.interpolate(x, scale_factor=2, mode="nearest")
            x = conv_act(first, torch.cat([x, skip], dim=1), slope, fast)
            x = conv_act(second, x, slope, fast)
        out = conv_act(self.output_conv, x, None, fast)[..., :height, :width]
        return (out.contiguous() if fast else out), new_state

    def forward(self, x: torch.Tensor, state: State | None = None,
                reset_every_frame: bool = False) -> tuple[torch.Tensor, State | None]:
        """A sequence x (N, T, in_channels, H, W) -> (outputs (N, T, 3, H, W), state after the last frame).

        ``reset_every_frame`` starts every frame from a zero state (the recurrent connections unused).
        """
        if x.dim() != 5:
            raise ValueError(f"rae: expected a sequence (N, T, C, H, W), got {tuple(x.shape)}")
        outputs = []
        for t in range(x.shape[1]):
            out, state = self.step(x[:, t], None if reset_every_frame else state)
            outputs.append(out)
        return torch.stack(outputs, dim=1), state


# ------------------------------------------------------------------------------------ descriptions
def layer_table(config: RAEConfig | None = None) -> list[str]:
    """One line per convolution: name, input -> output features, resolution divisor."""
    config = config or RAEConfig()
    lines = []
    previous = config.in_channels
    enc = config.encoder_features
    for k, features in enumerate(enc):
        for i in range(2 if k == 0 else 1):
            lines.append(f"encoder {k} conv {i}: {previous} -> {features} @1/{2**k}")
            previous = features
        lines.append(f"encoder {k} recurrent block: 3 convs, {features} features (+{features} hidden) @1/{2**k}")
    lines.append(f"bottleneck conv: {previous} -> {enc[-1]} @1/{2**config.levels}")
    lines.append(f"bottleneck recurrent block: 3 convs, {enc[-1]} features @1/{2**config.levels}")
    previous = enc[-1]
    for k, (skip, (first, second)) in zip(range(config.levels - 1, -1, -1), zip(reversed(enc), config.decoder_features)):
        lines.append(f"decoder {k} conv 0: {previous}+{skip} -> {first} @1/{2**k}")
        lines.append(f"decoder {k} conv 1: {first} -> {second} @1/{2**k}")
        previous = second
    lines.append(f"output conv: {previous} -> 3 (linear) @1/1")
    return lines


def parameter_count(config: RAEConfig | None = None) -> int:
    """Trainable parameters of an RAE with ``config`` (default: the paper's full-size network)."""
    model = RecurrentAutoencoder(config or RAEConfig())
    return sum(p.numel() for p in model.parameters())


def parameter_report(width: float = 1.0) -> str:
    """Full-size parameter count beside the paper's, plus the count at ``width`` if that differs."""
    full = parameter_count(RAEConfig())
    text = (f"RAE full size (Fig. 4 'AE': {RAEConfig().encoder_features} encoder features, 6 recurrent blocks, "
            f"36 conv layers): {full:,} trainable parameters; paper (§5.2): {PAPER_PARAMETER_COUNT:,}")
    if width != 1.0:
        text += f"\nRAE at width {width:g}: {parameter_count(RAEConfig(width=width)):,} trainable parameters"
    return text


def conv_flops(config: RAEConfig, height: int, width: int) -> int:
    """Floating-point operations (2 per multiply-add) of the convolutions for one frame of (height, width),
    counted at the padded size the network runs at (pooling, upsampling and activations excluded)."""
    model = RecurrentAutoencoder(config)
    m = model.multiple
    h, w = math.ceil(height / m) * m, math.ceil(width / m) * m
    total = 0
    for name, module in model.named_modules():
        if isinstance(module, nn.Conv2d):
            if name.startswith("encoder"):
                level = int(name.split(".")[1])
            elif name.startswith("bottleneck"):
                level = config.levels
            elif name.startswith("decoder"):
                level = config.levels - 1 - int(name.split(".")[1])
            else:
                level = 0
            pixels = (h >> level) * (w >> level)
            total += 2 * pixels * module.in_channels * module.out_channels * 9
    return total

