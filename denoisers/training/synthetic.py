"""Synthetic training batches of a model's size (the training-speed job, denoisers/training/speed.py, and the
benchmarks): speed does not depend on the content, so a procedural clip stands in for rendered data."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from scenegen.channels import SAMPLE_BUFFERS

if TYPE_CHECKING:
    from denoisers.training.spec import ModelSpec


class FixedBatch:
    """The same batch every step (speed does not depend on the content)."""

    def __init__(self, batch: dict[str, torch.Tensor]) -> None:
        self._batch = batch

    def batch(self, index: int, batch_size: int) -> dict[str, torch.Tensor]:
        return self._batch

    def describe(self) -> dict[str, Any]:
        return {"fixed synthetic batch": {k: list(v.shape) for k, v in self._batch.items()}}


def synthetic_batch(spec: ModelSpec, buffers: tuple[str, ...], seed: int = 0, *, pixel_buffers: tuple[str, ...] = (),
                    mean_buffers: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
    """(N, T, S, C, crop, crop) per-sample ``buffers`` of a procedural clip (boxes and a bump, panning half a
    pixel per frame, heavy-tailed noise on radiance), (N, T, 3, crop, crop) clean reference radiance and
    identity world-to-view rotations (N, T, 3, 3); N = batch_size, T = length, S = spp. ``pixel_buffers``
    (motion: the pan, +0.5 px in x; valid; gbuffer.normal / depth / albedo / roughness) and ``mean_buffers``
    (``mean.{buffer}``, (N, T, C, crop, crop)) as denoisers.training.data batches carry them."""
    n, t, crop, spp = spec.optimizer["batch_size"], spec.data["length"], spec.data["crop"], spec.data["spp"]
    generator = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.arange(crop, dtype=torch.float32), torch.arange(crop, dtype=torch.float32),
                          indexing="ij")
    shift = 0.5 * torch.arange(t).view(1, t, 1, 1) + 7.0 * torch.arange(n).view(n, 1, 1, 1)
    u, v = (x + shift) / crop, (y / crop).expand(n, t, crop, crop)                      # (N, T, H, W)
    boxes = (torch.floor(u * 6) + torch.floor(v * 6)) % 2
    bump = torch.clamp(1.0 - ((u - 0.6) ** 2 + (v - 0.5) ** 2) / 0.06, 0.0, 1.0)
    gy, gx = torch.gradient(torch.sqrt(bump) * 4.0, dim=(2, 3))
    normal = torch.stack([-gx, -gy, torch.ones_like(gx)], dim=2)
    normal = normal / normal.norm(dim=2, keepdim=True)                                  # (N, T, 3, H, W)
    albedo = torch.stack([0.3 + 0.5 * boxes, 0.4 + 0.2 * bump, 0.6 - 0.3 * boxes], dim=2)
    depth = (3.0 - torch.sqrt(bump)).unsqueeze(2)
    clean = albedo * torch.clamp(normal[:, :, 2:3] * 0.8 + 0.2, min=0.0) * 2.0
    noise = -torch.log1p(-torch.rand(n, t, spp, 1, crop, crop, generator=generator))     # Exp(1) per sample
    per_pixel = {"albedo": albedo, "normal": normal, "depth": depth, "roughness": torch.ones_like(depth),
                 "position": torch.stack([u * 4.0, v * 4.0, -depth[:, :, 0]], dim=2)}
    samples: dict[str, torch.Tensor] = {}
    for name in buffers:
        channels = len(SAMPLE_BUFFERS[name])
        if name in ("radiance", "diffuse"):
            samples[name] = clean.unsqueeze(2) * noise
        elif name in per_pixel:
            samples[name] = per_pixel[name].unsqueeze(2).expand(n, t, spp, channels, crop, crop).contiguous()
        else:                                     # specular 0, roughness 1, flags 0
            samples[name] = torch.full((n, t, spp, channels, crop, crop), float(name == "roughness"))
    for name in mean_buffers:
        samples[f"mean.{name}"] = per_pixel[name].contiguous() if name in per_pixel else \
            torch.full((n, t, len(SAMPLE_BUFFERS[name]), crop, crop), float(name == "roughness"))
    for name in pixel_buffers:
        if name == "motion":
            samples[name] = torch.stack([torch.full((n, t, crop, crop), 0.5), torch.zeros(n, t, crop, crop)], dim=2)
        elif name == "valid":
            samples[name] = torch.ones(n, t, 1, crop, crop)
        else:
            samples[name] = per_pixel[name.split(".", 1)[1]].contiguous()
    samples["reference.radiance"] = clean.contiguous()
    samples["world_to_view"] = torch.eye(3).expand(n, t, 3, 3).clone()
    return samples
