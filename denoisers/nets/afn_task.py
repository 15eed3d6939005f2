"""One AFN frame step (Isik et al. 2021, Sec. 3, Eq. 1-8) and its training task (Sec. 4.2-4.3).

:func:`frame_step` is shared by training and the evaluation method (denoisers.methods.afn). Per frame
(tensors (N, C, H, W) unless stated):

1. e_t = mean over samples of FC(r_s) (Eq. 1), r_s the 18 features of :func:`sample_features`.
2. The history (the previous frame's accumulated embedding, accumulated radiance, last-kernel features and
   output) is warped to frame t with nearest-neighbour lookups along the renderer's motion vectors (the
   paper's W_t); at a shot's first frame there is none.
3. U-Net on (e_t, W ebar_{t-1}, validity) -> per-pixel kernel parameters and lambda (Eq. 2);
   ebar_t = (1 - lambda) e_t + lambda W ebar_{t-1} (Eq. 3), Lbar_t likewise for the noisy radiance (Eq. 5).
4. K dilated affinity kernels applied in sequence to Lbar_t (Eq. 4, 6); the last one normalised jointly with
   the temporal kernel on the warped previous output (Eq. 7-8; omega = 0 at a shot's first frame).

Variants (denoisers.nets.afn.AFNConfig) switch parts off: single-frame (no history at all), no temporal
kernel, no radiance accumulation, fixed lambda, the warped previous output instead of the accumulated
embedding as the U-Net's history input.

Loss (Eq. 9-13): SMAPE(O, O*) + 0.25 SMAPE(d_t O, d_t O*) + 1e-5 (sum_k E a_k^2 + E b^2) over every frame
of a training sequence, on linear radiance; SMAPE per element with eps = denoisers.metrics.SMAPE_EPS (Eq. 11
states no value), as the evaluation's metric. Samples per pixel: training batch i uses the first
``spp_choices[i % len]`` of its drawn layers (the paper's round-robin over S in {1, 2, 4} per epoch, per
batch here); validation (model in eval mode) uses every carried layer (``data.spp``: the paper validates at
4 spp, 8 for the single-frame model).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from denoisers import affinity
from denoisers.filters import warp_previous
from denoisers.metrics import SMAPE_EPS
from denoisers.nets.afn import AFNConfig, AFNNet, KernelParameters
from denoisers.training.spp_schedule import samples_for_batch

#: Per-sample buffers an AFN batch / frame carries (the features of Sec. 3.1 and the radiance).
SAMPLE_BUFFERS: tuple[str, ...] = ("radiance", "diffuse", "specular", "normal", "depth", "roughness", "albedo",
                                   "flags")
PIXEL_BUFFERS: tuple[str, ...] = ("motion", "valid")
LOSS_DEFAULTS: dict[str, Any] = {"temporal": 0.25, "regularizer": 1e-5, "spp_choices": [1, 2, 4]}


def sample_features(samples: Mapping[str, torch.Tensor], world_to_view: torch.Tensor) -> torch.Tensor:
    """(N, S, 18, H, W) network input of per-sample buffers (N, S, C, H, W): log(1 + diffuse), log(1 + specular)
    (negatives clamped), the normal rotated to view space with ``world_to_view`` (N, 3, 3), log(1 + depth)
    (ours: the paper gives depth unscaled), roughness, albedo, the 4 flags. Non-finite values -> 0."""
    def clean(x: torch.Tensor) -> torch.Tensor:
        return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)

    normal = torch.einsum("nij,nsjhw->nsihw", clean(world_to_view), clean(samples["normal"]))
    parts = [torch.log1p(clean(samples["diffuse"]).clamp_min(0.0)), torch.log1p(clean(samples["specular"]).clamp_min(0.0)),
             normal, torch.log1p(clean(samples["depth"]).clamp_min(0.0)), clean(samples["roughness"]),
             clean(samples["albedo"]), clean(samples["flags"])]
    return torch.cat(parts, dim=2)


@dataclass
class History:
    """What one frame passes to the next: accumulated embedding (N, E, H, W), accumulated radiance and output
    (N, 3, H, W), last-kernel affinity features (N, d, H, W) (None where a variant does not use it)."""

    embedding: torch.Tensor | None
    radiance: torch.Tensor | None
    features: torch.Tensor | None
    output: torch.Tensor


@dataclass
class StepResult:
    """output (N, 3, H, W) linear radiance; params: the frame's kernel parameters; history for the next frame."""

    output: torch.Tensor
    params: KernelParameters
    history: History
    blend: torch.Tensor | None = None


def _warp(x: torch.Tensor | None, motion: torch.Tensor) -> torch.Tensor | None:
    return None if x is None else warp_previous(x, motion, mode="nearest")


def frame_step(model: AFNNet, features: torch.Tensor, radiance: torch.Tensor, motion: torch.Tensor | None,
               valid: torch.Tensor | None, history: History | None, kernel_size: int | None = None,
               temporal_kernel_size: int | None = None, backend: str = "auto") -> StepResult:
    """One frame (module docstring). features (N, S, 18, H, W); radiance (N, 3, H, W) the per-pixel noisy mean;
    motion (N, 2, H, W) backward motion in pixels and valid (N, 1, H, W) (temporal models); ``history`` None at
    a shot's first frame. kernel_size / temporal_kernel_size override the trained sizes (Sec. 3.6)."""
    c = model.config
    size = kernel_size or c.kernel_size
    temporal_size = temporal_kernel_size or c.temporal_kernel_size
    embedding = model.embed(features).float()
    radiance = torch.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    warped = None
    if c.temporal:
        if history is not None:
            motion = torch.nan_to_num(motion)
            warped = History(_warp(history.embedding, motion), _warp(history.radiance, motion),
                             _warp(history.features, motion), _warp(history.output, motion))
            validity = valid.float()
        else:
            validity = torch.zeros_like(radiance[:, :1])
        # Sec. 4.1: motion vectors that fail the reprojection test are discarded, so a pixel with valid = 0 has
        # no history: the U-Net sees none there, Eq. 3 / 5 keep the current value and the temporal kernel is off.
        if c.history_input == "embedding":
            previous = warped.embedding * validity if warped is not None else torch.zeros_like(embedding)
        else:
            previous = torch.log1p(warped.output) * validity if warped is not None else torch.zeros_like(radiance)
        x = torch.cat([embedding, previous, validity], dim=1)
    else:
        x = embedding
    params = model.parameters_from(x)
    blend = None
    if c.temporal:
        blend = params.blend if c.fixed_lambda is None else torch.full_like(params.blend, float(c.fixed_lambda))
        if warped is None:
            blend = torch.zeros_like(blend)           # ebar_0 = e_0, Lbar_0 = L_0
        else:
            blend = blend * validity                  # no history where the reprojection failed (Sec. 4.1)
    accumulated_embedding = None
    if c.temporal:                                    # Eq. 3 (ours-wpred feeds the prediction instead)
        carried = warped.embedding if warped is not None and c.history_input == "embedding" else None
        accumulated_embedding = affinity.accumulate(embedding, carried, blend)
    image = radiance
    if c.temporal and c.accumulate_radiance:
        image = affinity.accumulate(radiance, warped.radiance if warped is not None else None, blend)
    accumulated_radiance = image
    for k in range(c.kernels):
        dilation = c.dilation(k)
        last = k == c.kernels - 1
        if c.kernel_kind == "gather":
            num, den = affinity.gather_sums(image, params.logits[k], size, dilation)
            image = num / (affinity.EPS + den)
        elif last and c.temporal and c.temporal_kernel and warped is not None:
            image = affinity.joint_filter(image, params.features[k], params.bandwidth[k], params.center[k], size,
                                          dilation, warped.output, warped.features, params.temporal_bandwidth,
                                          temporal_size, backend=backend, history_valid=validity)
        else:
            image = affinity.spatial_filter(image, params.features[k], params.bandwidth[k], params.center[k], size,
                                            dilation, backend=backend)
    last_features = params.features[-1] if c.kernel_kind == "affinity" and c.temporal_kernel else None
    new_history = History(accumulated_embedding, accumulated_radiance if c.accumulate_radiance else None,
                          last_features, image)
    return StepResult(image, params, new_history, blend)


def smape(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Eq. 11, per element: mean |a - b| / (|a| + |b| + eps)."""
    return ((a - b).abs() / (a.abs() + b.abs() + SMAPE_EPS)).mean()


def afn_loss(outputs: Sequence[torch.Tensor], targets: Sequence[torch.Tensor], params: Sequence[KernelParameters],
             temporal_weight: float, regularizer: float) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 9: SMAPE over all frames + temporal_weight x SMAPE of frame differences + regularizer x L_reg (Eq. 13).
    outputs / targets: per frame (N, 3, H, W) linear radiance."""
    out, ref = torch.stack(list(outputs), 1), torch.stack(list(targets), 1)
    reconstruction = smape(out, ref)
    total = reconstruction
    terms = {"reconstruction": float(reconstruction.detach())}
    if out.shape[1] > 1 and temporal_weight > 0:
        temporal = smape(out[:, 1:] - out[:, :-1], ref[:, 1:] - ref[:, :-1])
        total = total + temporal_weight * temporal
        terms["temporal"] = float(temporal.detach())
    squares = [a.square().mean() for p in params for a in p.bandwidth]
    squares += [p.temporal_bandwidth.square().mean() for p in params if p.temporal_bandwidth is not None]
    if squares and regularizer > 0:
        reg = torch.stack(squares).sum() / len(params)
        total = total + regularizer * reg
        terms["regularizer"] = float(reg.detach())
    return total, terms


@dataclass
class AFNTask:
    """How the trainer (denoisers.training.loop) trains one AFN variant on sequences (module docstring)."""

    config: AFNConfig = field(default_factory=AFNConfig)
    temporal_weight: float = LOSS_DEFAULTS["temporal"]
    regularizer: float = LOSS_DEFAULTS["regularizer"]
    spp_choices: tuple[int, ...] = tuple(LOSS_DEFAULTS["spp_choices"])
    name: str = "afn"

    def build_model(self) -> AFNNet:
        return AFNNet(self.config)

    def net_spec(self) -> dict[str, Any]:
        return {"name": AFNNet.NET_NAME, "config": self.config.to_dict()}

    def describe(self) -> dict[str, Any]:
        return {"task": self.name, "net": self.net_spec(), "temporal_weight": self.temporal_weight,
                "regularizer": self.regularizer, "spp_choices": list(self.spp_choices),
                "loss": "SMAPE + temporal SMAPE + bandwidth L2 (Isik et al. Eq. 9), linear radiance"}

    def samples_used(self, model: nn.Module, batch: Any) -> int:
        return samples_for_batch(model, batch, self.spp_choices)

    def run(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> list[StepResult]:
        from denoisers.training.precision import AutocastForward

        net, dtype = (model.model, model.dtype) if isinstance(model, AutocastForward) else (model, None)
        spp = self.samples_used(model, batch)
        steps, history = [], None
        for t in range(batch["radiance"].shape[1]):
            samples = {b: batch[b][:, t, :spp] for b in SAMPLE_BUFFERS}
            features = sample_features(samples, batch["world_to_view"][:, t])
            temporal = net.config.temporal
            with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
                step = frame_step(net, features, samples["radiance"].mean(1),
                                  batch["motion"][:, t] if temporal else None,
                                  batch["valid"][:, t] if temporal else None, history)
            history = step.history if temporal else None
            steps.append(step)
        return steps

    def loss(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        steps = self.run(model, batch)
        targets = [batch["reference.radiance"][:, t] for t in range(len(steps))]
        return afn_loss([s.output for s in steps], targets, [s.params for s in steps], self.temporal_weight,
                        self.regularizer)

    def predict(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N, T, 3, H, W) linear HDR radiance over the whole sequence (history carried)."""
        return torch.stack([step.output for step in self.run(model, batch)], dim=1)
