"""Adaptive-sampling baselines (issue 12): they exercise the adaptive interface end to end, no denoising.

Both receive every stored layer of a frame and its average budget (registry.Frame.budget), choose an
integer sample map with denoisers.adaptive.normalize_sample_map (Eq. 2 of Hasselgren et al. 2020, never
above the budget) and return the per-pixel mean of the first k layers with that map. They read radiance
only; an adaptive method that wants auxiliary buffers gets them for the first render.spp layers only
(the radiance-only extra layers have none).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from denoisers.adaptive import gather_mean, normalize_sample_map
from denoisers.filters import luminance, sanitize
from denoisers.registry import AdaptiveOutput, Denoiser, Frame, register


def _budget(frame: Frame, name: str) -> float:
    if frame.budget is None:
        raise ValueError(f"adaptive method {name!r}, frame {frame.index}: the frame carries no budget")
    return float(frame.budget)


@register("uniform_adaptive", inputs=("radiance",), adaptive=True,
          description="adaptive interface check: every pixel gets the budget (uniform sampling), no denoising")
class UniformAdaptive(Denoiser):
    """Uniform sample map at the budget: for an integer budget n every pixel gets n samples, so the output
    equals the non-adaptive ``noisy`` row at n spp; a fractional budget gives floor(n) everywhere and the
    remainder to the first pixels in raster order (largest-remainder rounding of equal fractions)."""

    def denoise(self, frame: Frame) -> AdaptiveOutput:
        layers = sanitize(frame.samples["radiance"])
        importance = torch.ones(frame.height, frame.width)
        counts = normalize_sample_map(importance, _budget(frame, self.info.name), layers.shape[0])
        return AdaptiveOutput(gather_mean(layers, counts), counts)


@register("variance_adaptive", inputs=("radiance",), adaptive=True,
          description="relative-variance adaptive sampling from a pilot pass (Eq. 2), mean of the gathered "
                      "layers, no denoising")
class VarianceAdaptive(Denoiser):
    """Every pixel first gets ``pilot`` samples (DASR-style initial pass, counted in the budget); the rest of
    the budget follows the importance = relative variance of the pilot samples' luminance,
    var / (mean^2 + epsilon), smoothed by a 3x3 box so single outliers do not grab all samples; stochastic
    rounding seeded by ``seed`` and the frame index.

    The pilot is min(pilot, floor(budget)); below 2 pilot samples there is no variance estimate and the map
    is uniform. Parameters: pilot (2), epsilon (1e-2, in squared radiance units), rounding
    ("stochastic" | "largest_remainder"), seed (0).
    """

    def __init__(self, pilot: int = 2, epsilon: float = 1e-2, rounding: str = "stochastic", seed: int = 0) -> None:
        super().__init__()
        if int(pilot) < 1 or float(epsilon) <= 0:
            raise ValueError(f"variance_adaptive: pilot must be >= 1 and epsilon > 0, got {pilot}, {epsilon}")
        self.pilot, self.epsilon, self.rounding, self.seed = int(pilot), float(epsilon), rounding, int(seed)

    def importance(self, layers: torch.Tensor, pilot: int) -> torch.Tensor:
        """(H, W) relative variance of the luminance of the first ``pilot`` of the (S, 3, H, W) layers."""
        pilot_luminance = luminance(layers[:pilot])[:, 0]                 # (pilot, H, W)
        variance = pilot_luminance.var(dim=0, unbiased=True)
        relative = variance / (pilot_luminance.mean(dim=0).square() + self.epsilon)
        return F.avg_pool2d(relative[None, None], 3, stride=1, padding=1, count_include_pad=False)[0, 0]

    def denoise(self, frame: Frame) -> AdaptiveOutput:
        layers = sanitize(frame.samples["radiance"])
        budget = _budget(frame, self.info.name)
        pilot = min(self.pilot, int(budget), layers.shape[0])
        importance = self.importance(layers, pilot) if pilot >= 2 else torch.ones(frame.height, frame.width)
        counts = normalize_sample_map(importance, budget, layers.shape[0], minimum=pilot, rounding=self.rounding,
                                      seed=self.seed * 1_000_003 + frame.index)
        return AdaptiveOutput(gather_mean(layers, counts), counts)
