"""One NTASD frame step (sampling, rendering from stored layers, denoising) and its training task.

:func:`frame_step` is shared by training and the evaluation method (denoisers.methods.ntasd), so both
assemble the networks' inputs the same way. Per frame, tensors (N, C, H, W) unless stated:

* ``layers`` (N, S, 3, H, W) stored 1-spp radiance layers (linear); ``albedo`` mean albedo (N, 3, H, W);
  ``normal`` world-space first-hit normal, rotated to view space with ``world_to_view`` (N, 3, 3);
  ``depth`` (N, 1, H, W) metres, fed as log(1 + depth); ``motion`` (N, 2, H, W) backward motion in pixels;
  ``valid`` (N, 1, H, W) in {0, 1}.
* The previous output (encoded, :func:`denoisers.nets.ntasd.encode`) is warped with the motion vectors
  (Eq. 1; denoisers.kernels.warp_previous). At a shot's first frame there is no history: the frame is sampled
  uniformly at the budget (an adaptive sampler has nothing to read yet), and that noisy uniform image is both
  the frame's input and its history (Sec. 2.2, "Training": "we initialize the recurrent term to the noisy
  uniformly sampled image at our target sample count"), so the frame keeps the budget; the validity channel the
  networks see is 0 (the renderer's ``valid`` says where reprojection succeeded; the
  paper's networks see only the warp, so this channel is our addition).
* Sampling: 'uniform' -- every pixel the budget (Eq. 2 with equal weights for a fractional budget);
  'adaptive' -- Eq. 2 on the sample-map network's output from the grey warped history, guides, grey albedo
  and motion; 'dasr' -- one initial sample everywhere (counted in the budget), the rest by Eq. 2 on the
  network's output from that 1-spp image and the guides. Counts never exceed the budget
  (denoisers.adaptive.normalize_sample_map); the renderer gradient is denoisers.adaptive.render_adaptive's.
  Adaptive denoisers also see the per-pixel count divided by the budget (a pixel with 0 samples is
  otherwise black; our addition, the paper does not list the inputs beyond the guides).

Loss (Sec. 2.1, Eq. 4): on the last frame of each training sequence only, L1(x_T, y_T) + L1(x_T - x_{T-1},
y_T - y_{T-1}) in the encoded space (the paper's log-space training), equally weighted; back-propagated
through time over the whole sequence for the temporal variants. Per-frame variants only need the last two
frames for this loss, so only those are run (the result is identical).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from denoisers import kernels
from denoisers.adaptive import capped_density, gather_mean, normalize_sample_map, render_adaptive
from denoisers.nets.ntasd import MOTION_SCALE, NTASDConfig, NTASDNet, decode, encode, grey

#: Per-pixel buffers a training batch carries for NTASD (besides the radiance layers and mean albedo).
PIXEL_BUFFERS: tuple[str, ...] = ("motion", "valid", "gbuffer.normal", "gbuffer.depth")
MEAN_BUFFERS: tuple[str, ...] = ("albedo",)
#: Average spp the networks train at (the paper's comparisons are at 4 spp).
DEFAULT_TRAIN_BUDGET = 4.0


@dataclass
class FrameInputs:
    """One frame of a batch (shapes in the module docstring)."""

    layers: torch.Tensor
    albedo: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    motion: torch.Tensor
    valid: torch.Tensor
    world_to_view: torch.Tensor


@dataclass
class StepResult:
    """output: encoded (N, 3, H, W); counts: (N, H, W) int64 samples used; logits: sampler output or None."""

    output: torch.Tensor
    counts: torch.Tensor
    logits: torch.Tensor | None = None


def guides(frame: FrameInputs) -> torch.Tensor:
    """(N, 7, H, W): view-space normal, log(1 + depth), albedo clamped to [0, 1]."""
    normal = torch.einsum("nij,njhw->nihw", torch.nan_to_num(frame.world_to_view), torch.nan_to_num(frame.normal))
    depth = torch.log1p(torch.nan_to_num(frame.depth, posinf=0.0).clamp_min(0.0))
    return torch.cat([normal, depth, torch.nan_to_num(frame.albedo).clamp(0.0, 1.0)], dim=1)


def uniform_counts(budget: float, layers: torch.Tensor) -> torch.Tensor:
    """(N, H, W) int64: every pixel floor(budget), the remainder by Eq. 2 with equal weights."""
    n, available, _, height, width = layers.shape
    if float(budget).is_integer() and budget <= available:
        return torch.full((n, height, width), int(budget), dtype=torch.int64)
    ones = torch.ones(height, width)
    return torch.stack([normalize_sample_map(ones, budget, available) for _ in range(n)])


def uniform_image(layers: torch.Tensor, budget: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The noisy uniformly sampled image at ``budget`` from (N, S, 3, H, W) layers: encoded (N, 3, H, W) and its
    (N, H, W) int64 sample counts (:func:`uniform_counts`)."""
    layers = torch.nan_to_num(layers[:, :max(1, min(layers.shape[1], math.ceil(budget)))], nan=0.0, posinf=0.0,
                              neginf=0.0).clamp_min(0.0)
    counts = uniform_counts(budget, layers)
    return encode(torch.stack([gather_mean(layer, count) for layer, count in zip(layers, counts)])), counts


def frame_step(model: NTASDNet, frame: FrameInputs, history: torch.Tensor | None, budget: float) -> StepResult:
    """One frame of NTASD: sample map, gathered noisy mean, denoised output (module docstring)."""
    config = model.config
    guide = guides(frame)
    warped = None
    motion_features = None
    initial_counts = None
    if config.temporal:
        if history is None:
            warped, initial_counts = uniform_image(frame.layers, budget)
            validity = torch.zeros_like(frame.valid)
        else:
            warped = kernels.warp_previous(history, torch.nan_to_num(frame.motion))
            validity = frame.valid
        motion_features = torch.cat([torch.nan_to_num(frame.motion) / MOTION_SCALE, validity], dim=1)
    logits = None
    if initial_counts is not None:               # a shot's first frame: sampled uniformly, its own history
        noisy, counts = warped, initial_counts
    elif config.sampling == "uniform":           # reads the first ceil(budget) layers only
        noisy, counts = uniform_image(frame.layers, budget)
    else:
        layers = torch.nan_to_num(frame.layers, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
        # The adaptive renderers return the encoded means: their gradient is the renderer's finite difference in
        # the encoded space the networks see (denoisers.adaptive.renderer_derivative).
        if config.sampling == "adaptive":
            x = torch.cat([grey(warped), guide[:, :4], grey(guide[:, 4:7]), motion_features], dim=1)
            logits = model.sample_logits(x)
            noisy, counts = render_adaptive(capped_density(logits, budget, layers.shape[1]), layers, budget,
                                            transform=encode)
        else:                                                    # dasr: a 1-spp initial pass, then Eq. 2
            if budget < 1:
                raise ValueError(f"dasr: the budget {budget} spp is below its initial pass of 1 sample per pixel")
            x = torch.cat([encode(layers[:, 0]), guide], dim=1)
            logits = model.sample_logits(x)
            noisy, counts = render_adaptive(capped_density(logits, budget, layers.shape[1], minimum=1), layers,
                                            budget, minimum=1, transform=encode)
    parts = [noisy, guide]
    if config.temporal:
        parts += [motion_features, warped]
    if config.adaptive:
        parts.append(counts.to(noisy.dtype)[:, None] / float(budget))
    output = model.denoise(torch.cat(parts, dim=1), noisy, warped)
    return StepResult(output, counts, logits)


def batch_frame(batch: Mapping[str, torch.Tensor], t: int) -> FrameInputs:
    """Frame ``t`` of a training batch (denoisers.training.data layout)."""
    return FrameInputs(layers=batch["radiance"][:, t], albedo=batch["mean.albedo"][:, t],
                       normal=batch["gbuffer.normal"][:, t], depth=batch["gbuffer.depth"][:, t],
                       motion=batch["motion"][:, t], valid=batch["valid"][:, t],
                       world_to_view=batch["world_to_view"][:, t])


def l1_spatial_temporal(outputs: list[torch.Tensor], targets: list[torch.Tensor]) -> tuple[torch.Tensor, dict]:
    """Eq. 4 on the last frame: L1(x_T, y_T) + L1(x_T - x_{T-1}, y_T - y_{T-1}) (one frame: spatial only)."""
    spatial = F.l1_loss(outputs[-1], targets[-1])
    if len(outputs) < 2:
        return spatial, {"spatial": float(spatial.detach())}
    temporal = F.l1_loss(outputs[-1] - outputs[-2], targets[-1] - targets[-2])
    return spatial + temporal, {"spatial": float(spatial.detach()), "temporal": float(temporal.detach())}


@dataclass
class NTASDTask:
    """How the trainer (denoisers.training.loop) trains one NTASD variant on sequences."""

    config: NTASDConfig = field(default_factory=NTASDConfig)
    budget: float = DEFAULT_TRAIN_BUDGET
    name: str = "ntasd"

    def build_model(self) -> NTASDNet:
        return NTASDNet(self.config)

    def net_spec(self) -> dict[str, Any]:
        return {"name": NTASDNet.NET_NAME, "config": self.config.to_dict()}

    def describe(self) -> dict[str, Any]:
        described = {"task": self.name, "net": self.net_spec(), "budget": self.budget,
                     "loss": "L1 + temporal L1 on the last frame (Hasselgren et al. Eq. 4), encoded space"}
        if self.config.sampling != "uniform":   # checkpoints of the earlier sampler training do not resume
            described["sample_density"] = "capped (adaptive.capped_density)"
            described["renderer_gradient"] = "finite difference after the encoding (adaptive.renderer_derivative)"
        return described

    def run(self, model: nn.Module, batch: Mapping[str, torch.Tensor], first: int = 0) -> list[StepResult]:
        """Frame steps t = first .. T-1, the history carried (temporal variants) from ``first``. ``model`` may be
        the trainer's bf16 wrapper (denoisers.training.precision.AutocastForward): the steps then run under its
        autocast and their outputs are cast back to float32 (the loss stays float32)."""
        from denoisers.training.precision import AutocastForward

        net, dtype = (model.model, model.dtype) if isinstance(model, AutocastForward) else (model, None)
        steps, history = [], None
        for t in range(first, batch["radiance"].shape[1]):
            with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
                step = frame_step(net, batch_frame(batch, t), history, self.budget)
            step.output = step.output.float()
            history = step.output
            steps.append(step)
        return steps

    def loss(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        length = batch["radiance"].shape[1]
        first = 0 if self.config.temporal else max(0, length - 2)
        outputs = [step.output for step in self.run(model, batch, first)]
        targets = [encode(batch["reference.radiance"][:, t]) for t in range(first, length)]
        return l1_spatial_temporal(outputs, targets)

    def predict(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N, T, 3, H, W) linear HDR radiance over the whole sequence (history carried)."""
        return torch.stack([decode(step.output) for step in self.run(model, batch)], dim=1)
