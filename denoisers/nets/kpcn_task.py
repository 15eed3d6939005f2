"""One KPCN frame (Bako et al. 2017; the networks: denoisers.nets.kpcn) and its training task.

:func:`frame_step` is shared by training and the evaluation method (denoisers.methods.kpcn). Every frame is
processed on its own (single-frame method; a training sequence is T independent frames). Per frame, tensors
(N, C, H, W) unless stated, samples (N, S, C, H, W):

1. Transforms (:func:`demodulate`, :func:`log_transform`): diffuse / (albedo + 0.00316), with albedo the
   per-pixel mean over the frame's samples; log(1 + specular). Negative and non-finite radiance -> 0.
2. Per branch the network input of denoisers.nets.kpcn.INPUTS (:func:`branch_inputs`): the transformed
   per-pixel mean colour -- the demodulated mean diffuse, log(1 + mean specular) --, the variance of the
   per-pixel mean of the transformed samples, sum_s (x_s - mean)^2 / (S (S - 1)) averaged over channels (0 when
   S = 1), and forward-difference x / y gradients (0 in the last column / row) of the colour and of the
   features: the normal rotated to view space with the frame's camera (ours, as the other learned methods
   here: consistent with the rotation augmentation; Bako et al. use the renderer's normals), log(1 + depth)
   (ours: the scale of depth is scene-dependent) and the albedo; the features' variances likewise.
3. Each network predicts k*k logits per pixel; the kernel = their softmax; it is applied
   (denoisers.kernels.apply_kernels: native for inference, differentiable torch for training) to the
   transformed noisy colour. Near the image border, taps outside the image (zero padding) are dropped and the
   kernel renormalised over the taps inside, sum_t w_t I_t / sum_t w_t [t inside] -- ours: Bako et al. filter
   padded patches; at an interior pixel this is exactly the softmax kernel.
4. Output = diffuse' x (albedo + 0.00316) + exp(specular') - 1 (:func:`compose`).

Loss: Bako et al. train each branch with L1 on its own transformed output; here the sum of the two:
mean |diffuse' - reference diffuse / (albedo + 0.00316)| + mean |specular' - log(1 + reference specular)|,
albedo the noisy per-pixel mean the output is remodulated with, over every frame of the batch. The reference
diffuse / specular exist only for references rendered with ``render.reference_integrator: features``
(denoisers.training.job carries them when every training and validation clip has them). Fallback when a batch
lacks them (the default config renders references with Mitsuba's ``path``, radiance only): L1 on the whole
output in log space, mean |log(1 + output) - log(1 + reference radiance)| -- ours, the specular branch's space
applied to the sum. The loss's terms say which one ran ("diffuse" and "specular", or "log_radiance").
Training uses the first ``loss.spp_choices[i % n]`` of the batch's layers in batch i (as AFN, Isik et al.
§4.3; unset: every carried layer, ``data.spp``); validation every carried layer.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from denoisers.kernels import apply_kernels
from denoisers.nets.kpcn import KPCNConfig, KPCNNet
from denoisers.training.spp_schedule import samples_for_batch

#: Per-sample buffers a KPCN batch / frame carries (radiance: by the data pipeline's conventions, e.g.
#: importance crops; the output is composed from diffuse and specular, radiance = diffuse + specular).
SAMPLE_BUFFERS: tuple[str, ...] = ("radiance", "diffuse", "specular", "albedo", "normal", "depth")
#: Reference buffers of the per-branch loss (only in references of render.reference_integrator: features).
SPLIT_REFERENCE: tuple[str, ...] = ("diffuse", "specular")
#: Added to the albedo before demodulation (Bako et al.).
ALBEDO_EPS = 0.00316
#: Floor of the in-image kernel weight a border pixel is renormalised by.
COVERAGE_FLOOR = 1e-10


def _clean(x: torch.Tensor) -> torch.Tensor:
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def demodulate(diffuse: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """diffuse / (albedo + 0.00316); albedo broadcastable to diffuse."""
    return diffuse / (albedo + ALBEDO_EPS)


def remodulate(demodulated: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`demodulate`: demodulated x (albedo + 0.00316)."""
    return demodulated * (albedo + ALBEDO_EPS)


def log_transform(specular: torch.Tensor) -> torch.Tensor:
    """log(1 + x)."""
    return torch.log1p(specular)


def exp_transform(transformed: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`log_transform`: exp(x) - 1."""
    return torch.expm1(transformed)


def compose(diffuse: torch.Tensor, specular: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Linear radiance from the filtered branches: diffuse' x (albedo + eps) + exp(specular') - 1."""
    return remodulate(diffuse, albedo) + exp_transform(specular)


def mean_and_variance(samples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, S, C, H, W) -> per-pixel mean (N, C, H, W) and the variance of that mean, sum_s (x_s - mean)^2 /
    (S (S - 1)) averaged over the C channels, (N, 1, H, W); 0 when S = 1."""
    count = samples.shape[1]
    mean = samples.mean(dim=1)
    if count < 2:
        return mean, torch.zeros_like(mean[:, :1])
    variance = (samples - mean.unsqueeze(1)).square().sum(dim=1) / (count * (count - 1))
    return mean, variance.mean(dim=1, keepdim=True)


def gradients(image: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) -> (N, 2C, H, W): forward differences along x for every channel, then along y; 0 in the
    last column (x) / row (y)."""
    dx = F.pad(image[..., :, 1:] - image[..., :, :-1], (0, 1, 0, 0))
    dy = F.pad(image[..., 1:, :] - image[..., :-1, :], (0, 0, 0, 1))
    return torch.cat([dx, dy], dim=1)


@dataclass
class BranchInputs:
    """One frame's transformed noisy colours (N, 3, H, W) -- diffuse demodulated, specular log --, the per-pixel
    mean albedo (N, 3, H, W) they are remodulated with, and the two networks' inputs (N, C_in, H, W)."""

    diffuse: torch.Tensor
    specular: torch.Tensor
    albedo: torch.Tensor
    x_diffuse: torch.Tensor
    x_specular: torch.Tensor


def branch_inputs(samples: Mapping[str, torch.Tensor], world_to_view: torch.Tensor,
                  raw_features: bool = False) -> BranchInputs:
    """Steps 1-2 of the module docstring: per-sample buffers (N, S, C, H, W) of :data:`SAMPLE_BUFFERS` (radiance
    unused) and the frame's world-to-view rotation (N, 3, 3) -> :class:`BranchInputs`, channels in the order of
    denoisers.nets.kpcn.INPUTS (+ RAW_FEATURES with ``raw_features``)."""
    albedo_samples = _clean(samples["albedo"]).clamp_min(0.0)
    albedo, albedo_variance = mean_and_variance(albedo_samples)
    diffuse_samples = demodulate(_clean(samples["diffuse"]).clamp_min(0.0), albedo.unsqueeze(1))
    diffuse, diffuse_variance = mean_and_variance(diffuse_samples)
    specular_linear = _clean(samples["specular"]).clamp_min(0.0)
    specular = log_transform(specular_linear.mean(dim=1))
    _, specular_variance = mean_and_variance(log_transform(specular_linear))
    normal, normal_variance = mean_and_variance(
        torch.einsum("nij,nsjhw->nsihw", _clean(world_to_view).to(albedo.dtype), _clean(samples["normal"])))
    depth, depth_variance = mean_and_variance(log_transform(_clean(samples["depth"]).clamp_min(0.0)))
    features = [gradients(normal), gradients(depth), gradients(albedo), normal_variance, depth_variance,
                albedo_variance]
    if raw_features:
        features += [normal, depth, albedo]

    def stack(colour: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
        return torch.cat([colour, variance, gradients(colour), *features], dim=1)

    return BranchInputs(diffuse, specular, albedo, stack(diffuse, diffuse_variance), stack(specular, specular_variance))


def kernel_weights(logits: torch.Tensor) -> torch.Tensor:
    """(N, k*k, H, W) logits -> the per-pixel kernels: softmax over the k*k taps."""
    return torch.softmax(logits, dim=1)


def filter_image(image: torch.Tensor, logits: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Step 3: the softmax kernels of ``logits`` (N, k*k, H, W) applied to ``image`` (N, C, H, W), renormalised
    over the taps inside the image (at least COVERAGE_FLOOR)."""
    weights = kernel_weights(logits.float())
    image = image.float()
    out = apply_kernels(torch.cat([image, torch.ones_like(image[:, :1])], dim=1), weights, backend=backend)
    return out[:, :-1] / out[:, -1:].clamp_min(COVERAGE_FLOOR)


@dataclass
class StepResult:
    """output (N, 3, H, W) linear radiance; diffuse / specular: the filtered branches in their transformed
    spaces (demodulated, log); inputs: the frame's :class:`BranchInputs`."""

    output: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    inputs: BranchInputs


def _net(model: nn.Module) -> KPCNNet:
    from denoisers.training.precision import AutocastForward

    return model.model if isinstance(model, AutocastForward) else model


def frame_step(model: nn.Module, samples: Mapping[str, torch.Tensor], world_to_view: torch.Tensor,
               backend: str = "auto") -> StepResult:
    """One frame (module docstring): per-sample buffers (N, S, C, H, W), world-to-view (N, 3, 3). ``model``: a
    KPCNNet or the trainer's bf16 wrapper (the networks then run under autocast, the filtering in float32)."""
    inputs = branch_inputs(samples, world_to_view, _net(model).config.raw_features)
    logits_diffuse, logits_specular = model(inputs.x_diffuse, inputs.x_specular)
    diffuse = filter_image(inputs.diffuse, logits_diffuse, backend)
    specular = filter_image(inputs.specular, logits_specular, backend)
    return StepResult(compose(diffuse, specular, inputs.albedo), diffuse, specular, inputs)


def has_split_reference(batch: Mapping[str, torch.Tensor]) -> bool:
    """Whether ``batch`` carries the reference diffuse and specular of the per-branch loss."""
    return all(f"reference.{b}" in batch for b in SPLIT_REFERENCE)


def kpcn_loss(steps: Sequence[StepResult], batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of the module docstring over the frames ``steps`` (frame t = steps[t]) of ``batch``."""
    if has_split_reference(batch):
        diffuse = torch.stack([s.diffuse for s in steps], 1)
        specular = torch.stack([s.specular for s in steps], 1)
        albedo = torch.stack([s.inputs.albedo for s in steps], 1)
        target_diffuse = demodulate(_clean(batch["reference.diffuse"]).clamp_min(0.0), albedo)
        target_specular = log_transform(_clean(batch["reference.specular"]).clamp_min(0.0))
        l_diffuse = (diffuse - target_diffuse).abs().mean()
        l_specular = (specular - target_specular).abs().mean()
        return l_diffuse + l_specular, {"diffuse": float(l_diffuse.detach()), "specular": float(l_specular.detach())}
    output = torch.stack([s.output for s in steps], 1)
    target = _clean(batch["reference.radiance"]).clamp_min(0.0)
    loss = (log_transform(output.clamp_min(0.0)) - log_transform(target)).abs().mean()
    return loss, {"log_radiance": float(loss.detach())}


@dataclass
class KPCNTask:
    """How the trainer (denoisers.training.loop) trains KPCN on sequences (module docstring): every frame alone."""

    config: KPCNConfig = field(default_factory=KPCNConfig)
    spp_choices: tuple[int, ...] | None = None
    name: str = "kpcn"

    def build_model(self) -> KPCNNet:
        return KPCNNet(self.config)

    def net_spec(self) -> dict[str, Any]:
        return {"name": KPCNNet.NET_NAME, "config": self.config.to_dict()}

    def describe(self) -> dict[str, Any]:
        return {"task": self.name, "net": self.net_spec(), **({"spp_choices": list(self.spp_choices)}
                                                              if self.spp_choices else {}),
                "loss": "L1 per branch (demodulated diffuse + log specular, Bako et al.) when the batch carries "
                        "reference diffuse/specular, else L1 on log(1 + radiance)"}

    def run(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> list[StepResult]:
        """Every frame on its own, at the batch's spp (denoisers.training.spp_schedule: ``spp_choices`` round robin
        in training, every carried layer in validation)."""
        spp = samples_for_batch(model, batch, self.spp_choices)
        return [frame_step(model, {b: batch[b][:, t, :spp] for b in SAMPLE_BUFFERS}, batch["world_to_view"][:, t])
                for t in range(batch["radiance"].shape[1])]

    def loss(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        return kpcn_loss(self.run(model, batch), batch)

    def predict(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N, T, 3, H, W) linear HDR radiance, every frame denoised on its own."""
        return torch.stack([step.output for step in self.run(model, batch)], dim=1)
