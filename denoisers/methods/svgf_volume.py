"""SVGF on volumetric clips (Iglesias-Guitian et al. 2022, Sec. 7.1: "we exchanged its reprojection scheme with
ours"): the same filter as ``svgf`` without normals, which a medium does not have."""
from __future__ import annotations

import torch

from denoisers.methods.svgf import SVGF
from denoisers.registry import Frame, register


@register("svgf_volume", inputs=("radiance",), pixel_inputs=("motion", "valid", "gbuffer.depth"),
          temporal=True, description="SVGF on the volumetric clips' first-collision reprojection, without normals "
                                     "or albedo demodulation")
class SVGFVolume(SVGF):
    """SVGF (Schied et al. 2017, as ``svgf``) for volumetric clips, with the clips' reprojection (the paper's
    Sec. 6 scheme: the renderer's motion vectors and validity from the closest first collision, plus SVGF's own
    depth test on ``gbuffer.depth``). A medium has no surface G-buffer, so:

    - every normal is +z: the normal terms of the edge-stopping weights and of the reprojection test are 1 /
      always pass;
    - the edge-stopping depth is that of the reprojection point (``gbuffer.depth``), not the mean over the
      frame's samples, which in a medium mixes scatter events at random depths with the surfaces behind;
    - no albedo demodulation: a pixel's mean albedo mixes the single-scattering albedo of medium events with
      surfaces behind and escaped samples (albedo 0), and dividing by it spreads background radiance.

    The last two were chosen on the volumetric *training* clips (vol_train_*, default config, 2 spp: mean
    PSNR 27.8 dB with the surface choices, 31.5 without demodulation, 32.3 with both), never on the test clips.
    Parameters as ``svgf`` (``albedo_epsilon`` has no effect)."""

    def _albedo(self, frame: Frame) -> torch.Tensor:
        return torch.ones((3, frame.height, frame.width))

    def _edge_depth(self, frame: Frame, gbuffer_depth: torch.Tensor) -> torch.Tensor:
        return gbuffer_depth.abs()

    def _normals(self, frame: Frame, gbuffer_depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        up = torch.zeros((3, *gbuffer_depth.shape[-2:]), dtype=gbuffer_depth.dtype)
        up[2] = 1.0
        return up, up.clone()
