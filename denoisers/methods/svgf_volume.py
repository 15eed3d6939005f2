"""SVGF on volumetric clips (Iglesias-Guitian et al. 2022, Sec. 7.1: "we exchanged its reprojection scheme with
ours"): the same filter as ``svgf`` without normals, which a medium does not have."""
from __future__ import annotations

import torch

from denoisers.methods.svgf import SVGF
from denoisers.registry import Frame, register


@register("svgf_volume", inputs=("radiance", "albedo", "depth"), pixel_inputs=("motion", "valid", "gbuffer.depth"),
          temporal=True, description="SVGF without normals, on the volumetric clips' first-collision features")
class SVGFVolume(SVGF):
    """SVGF (Schied et al. 2017, as ``svgf``) for volumetric clips: every normal is +z, so the normal terms of
    the edge-stopping weights and of the reprojection test are 1 / always pass, and only depth and luminance
    stop edges. The features are the clips' (docs/data-format.md, "Volumetric clips"): albedo is the
    single-scattering albedo at the first real collision, depth its distance, and reprojection uses the
    renderer's motion vectors and validity from the closest collision (the paper's scheme) plus SVGF's own
    depth test on ``gbuffer.depth``. Parameters as ``svgf``."""

    def _normals(self, frame: Frame, gbuffer_depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        up = torch.zeros((3, *gbuffer_depth.shape[-2:]), dtype=gbuffer_depth.dtype)
        up[2] = 1.0
        return up, up.clone()
