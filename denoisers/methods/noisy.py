"""Reference rows: the noisy input itself, and plain path tracing with k times the samples."""
from __future__ import annotations

import torch

from denoisers.filters import sanitize
from denoisers.registry import Denoiser, Frame, register


@register("noisy", inputs=("radiance",), description="the box-filtered noisy input (no denoising)")
class NoisyInput(Denoiser):
    """Mean of the frame's samples (non-finite samples count as 0): what every denoiser starts from."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        return sanitize(frame.samples["radiance"]).mean(dim=0)


@register("path_tracing", inputs=("radiance",),
          description="plain path tracing at `factor` times the evaluated spp (equal-time view)")
class PathTracing(Denoiser):
    """Mean of ``factor`` x spp samples. The evaluation hands this method ``factor`` times the
    evaluated spp (``samples_factor``); it fails with MissingInputError when fewer were rendered."""

    def __init__(self, factor: int = 4) -> None:
        super().__init__()
        if int(factor) < 1:
            raise ValueError(f"path_tracing: factor must be >= 1, got {factor}")
        self.samples_factor = int(factor)

    def denoise(self, frame: Frame) -> torch.Tensor:
        return sanitize(frame.samples["radiance"]).mean(dim=0)
