"""Edge-avoiding a-trous wavelet filter (Dammertz, Sewtz, Hanika, Lensch 2010), the EAW baseline of
Chaitanya et al. 2017 (Sec. 5.4, Figs. 7-8)."""
from __future__ import annotations

import math
from types import ModuleType

import torch
import torch.nn.functional as F

from denoisers import native
from denoisers.filters import (B3_SPLINE, LOG2_E, MIN_LOG2_WEIGHT, PairRegion, PairWorkspace, check_sizes,
                               luminance, revisited_next_step, sanitize)
from denoisers.registry import Denoiser, Frame, register


@register("eaw", inputs=("radiance", "normal", "position", "flags"),
          description="edge-avoiding a-trous wavelet filter (Dammertz et al. 2010)")
class EdgeAvoidingATrous(Denoiser):
    """Edge-avoiding a-trous wavelet filter on the box-filtered radiance, single frame.

    ``iterations`` passes of the 5x5 B3-spline kernel with taps 2^i pixels apart (i = 0, 1, ...), each
    weighted by w(p, q) = w_rt * w_n * w_x, w_k = exp(-|I_k(p) - I_k(q)|^2 / sigma_k^2), where I_rt is the
    current iterate c_i, I_n the normal and I_x the world position buffer (Dammertz et al. 2010);
    the output is the last iterate (the wavelet detail coefficients are dropped).

    Parameters (the paper gives the form of each term; its values are set per scene). The defaults
    below are starting values; the shipped configs choose sigma_color, sigma_normal and sigma_position
    by the grid search of ``denoisers.jobs.tuning`` on the training scenes (rule tune_method, rows with
    ``params: {tuned: true}``), which prints and records the chosen values:

    - ``sigma_color`` (8.0): sigma_rt of the colour term in the first pass, in units of the frame's mean
      surface luminance (our choice: the scenes' exposure spans two orders of magnitude, so an absolute
      sigma would filter dark and bright scenes completely differently). The mean is taken over pixels
      whose samples mostly end on a surface rather than on an emitter or the environment (the
      ``flags`` buffer's emissive channel), so a bright sky or light panel filling much of the frame
      does not inflate the sigma. Large, because 1-4 spp inputs are dominated by fireflies that a small
      sigma would keep.
    - ``color_sigma_decay`` (0.5): sigma_rt at pass i is sigma_rt * decay^i -- the paper's 2^-i, so
      later, wider passes do not blur the features that earlier passes kept.
    - ``sigma_normal`` (0.5): sigma_n on the difference of (sample-mean) world-space normals; a 90
      degree crease (|dn|^2 = 2) gets weight exp(-8), facets of a tessellated sphere pass.
    - ``sigma_position`` (0.25): sigma_x in metres on world-position differences (0.1 and 0.5 gave
      1-2.5 dB lower mean PSNR on 48x48 scenes). Being in metres, the best value depends on the
      resolution (pixel footprint) and scene scale, hence the tuning per config.
    - ``iterations`` (5): 5 passes with doubling step (issue text), a 125x125 pixel footprint.

    Inputs: mean over the frame's samples of radiance, normal and position (first non-specular vertex);
    the emissive flag only for the colour scale. No albedo: texture edges are kept only by the colour term.
    """

    def __init__(self, sigma_color: float = 8.0, sigma_normal: float = 0.5, sigma_position: float = 0.25,
                 iterations: int = 5, color_sigma_decay: float = 0.5) -> None:
        super().__init__()
        for name, value in (("sigma_color", sigma_color), ("sigma_normal", sigma_normal),
                            ("sigma_position", sigma_position), ("color_sigma_decay", color_sigma_decay)):
            if not float(value) > 0:
                raise ValueError(f"eaw: {name} must be > 0, got {value}")
        if int(iterations) < 1:
            raise ValueError(f"eaw: iterations must be >= 1, got {iterations}")
        self.sigma_color = float(sigma_color)
        self.sigma_normal = float(sigma_normal)
        self.sigma_position = float(sigma_position)
        self.iterations = int(iterations)
        self.color_sigma_decay = float(color_sigma_decay)
        self._workspace: PairWorkspace | None = None   # a-trous buffers, kept from frame to frame
        #: Implementation of the a-trous passes in the last ``denoise`` call: "native" or "torch".
        self.backend = "torch"

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        color = sanitize(frame.mean("radiance"))
        geometry = torch.cat([sanitize(frame.mean("normal")) / self.sigma_normal,
                              sanitize(frame.mean("position")) / self.sigma_position])
        height, width = color.shape[-2:]
        if _native_kernels(color, geometry) is not None:
            self.backend = "native"
        else:
            self.backend = "torch"
            self._workspace = eaw_workspace(height, width, color.shape[0], geometry.shape[0], self._workspace)
        scale = surface_luminance_scale(color, sanitize(frame.mean("flags"))[EMISSIVE_FLAG])
        return filter_eaw(color, geometry, self.sigma_color * scale,
                          self.iterations, self.color_sigma_decay, self._workspace)


def mean_luminance_scale(color: torch.Tensor) -> float:
    """Mean absolute luminance of a (3, H, W) image, floored so that black frames give a usable scale."""
    return max(float(luminance(color).abs().mean()), 1e-6)


EMISSIVE_FLAG = 0
"""Channel of the ``flags`` buffer that is 1 where a sample's first non-specular vertex is an emitter
or the path escaped to the environment (scenegen.integrator)."""
MIN_SURFACE_FRACTION = 0.01
"""Below this fraction of surface pixels the scale falls back to the whole frame."""


def surface_luminance_scale(color: torch.Tensor, emissive: torch.Tensor) -> float:
    """Mean absolute luminance of a (3, H, W) image over its surface pixels: those whose samples end on an
    emitter or the environment in at most half the cases (``emissive``: (H, W) fraction of such samples).
    The whole frame when fewer than 1 % of the pixels are surface pixels; floored like
    :func:`mean_luminance_scale`."""
    surface = emissive <= 0.5
    if float(surface.float().mean()) < MIN_SURFACE_FRACTION:
        return mean_luminance_scale(color)
    return max(float(luminance(color).abs().reshape(emissive.shape)[surface].mean()), 1e-6)


def filter_eaw(color: torch.Tensor, scaled_geometry: torch.Tensor, sigma_color: float, iterations: int,
               color_sigma_decay: float = 0.5, workspace: PairWorkspace | None = None) -> torch.Tensor:
    """Run the EAW iterations on ``color`` (C, H, W).

    scaled_geometry: (G, H, W) static edge-stopping features already divided by their sigmas (the
    normal and position terms); sigma_color: sigma_rt of the first iteration in radiance units;
    workspace: buffers of :func:`eaw_workspace` to reuse (made here when None or of another size).

    Each iteration is :func:`denoisers.filters.atrous_step` with the symmetric weight
    w(p, q) = exp(-|f_p - f_q|^2) of the concatenated scaled features f = [c_i / sigma_i, geometry],
    written out because it is the hot loop: the weight is a base-2 exponential, one per pair of opposite
    taps, the geometric distance of an offset is computed once for the two iterations that visit it
    (:func:`denoisers.filters.revisited_next_step`), and both taps of a pair are accumulated by one op
    on the views of a :class:`denoisers.filters.PairWorkspace`.

    With the native kernels (:mod:`denoisers.native`, unless ``MCDN_NATIVE=0``), float32 inputs, C = 3
    and G <= 8, the same iterations run as one fused C++ loop per pass instead (``workspace`` unused).
    """
    channels, height, width = color.shape
    # Features scaled by sqrt(log2 e): -|f_p - f_q|^2 is then directly a base-2 log-weight.
    root_log2_e = math.sqrt(LOG2_E)
    kernels = _native_kernels(color, scaled_geometry)
    if kernels is not None:
        scales = [root_log2_e / (sigma_color * color_sigma_decay ** i) for i in range(iterations)]
        return kernels.eaw_atrous(color.contiguous(), scaled_geometry.contiguous(), scales, root_log2_e,
                                  MIN_LOG2_WEIGHT)
    workspace = eaw_workspace(height, width, channels, scaled_geometry.shape[0], workspace)
    radius = (len(B3_SPLINE) - 1) // 2
    centre_h = B3_SPLINE[radius] ** 2
    torch.mul(scaled_geometry, root_log2_e, out=workspace["geometry"])
    values, accumulated = workspace["values"], workspace["accumulated"]   # (2, C + 1, H, W) each
    values[:, :channels] = color
    # Pixel offset -> (log2 h - |g_p - g_q|^2 over the pair region, the log2 h it includes).
    geometry_terms: dict[tuple[int, int], tuple[torch.Tensor, float]] = {}
    for i in range(iterations):
        torch.mul(values[0, :channels], root_log2_e / (sigma_color * color_sigma_decay ** i),
                  out=workspace["features"])
        torch.mul(values[0], centre_h, out=accumulated[0])
        accumulated[1].zero_()
        next_terms: dict[tuple[int, int], tuple[torch.Tensor, float]] = {}
        for region, ti, tj in workspace.regions(radius, 2 ** i):
            log2_h = math.log2(B3_SPLINE[radius + ti] * B3_SPLINE[radius + tj])
            offset = (region.dy, region.dx)
            if offset in geometry_terms:
                base, base_log2_h = geometry_terms.pop(offset)
                base.add_(log2_h - base_log2_h)
            else:
                base = _log2_weight(workspace.constant(log2_h, (1, 1)), workspace, "geometry", region)
            if i + 1 < iterations and revisited_next_step(ti, tj):
                next_terms[offset] = (base, log2_h)
            weight = _log2_weight(base.view(1, -1), workspace, "features", region)
            weight.clamp_min_(MIN_LOG2_WEIGHT).exp2_()          # shared by the taps +o and -o
            workspace.straight("accumulated", region).addcmul_(workspace.crossed("values", region), weight)
        geometry_terms = next_terms
        total = accumulated[0].add_(accumulated[1])
        if i + 1 < iterations:    # the next pass's input, straight into both copies
            torch.div(total[:channels], total[channels:], out=values[0, :channels])
            values[1, :channels] = values[0, :channels]
        else:
            color = total[:channels] / total[channels:]
    return color


def _native_kernels(color: torch.Tensor, geometry: torch.Tensor) -> ModuleType | None:
    """The native extension if it is enabled, built and supports these (C, H, W) colour and (G, H, W)
    geometry images (float32, C = 3, G <= 8, on the CPU), else None."""
    kernels = native.load() if color.device.type == "cpu" else None   # C++ on host memory; elsewhere torch
    if (kernels is None or color.dtype != torch.float32 or geometry.dtype != torch.float32
            or color.shape[0] != 3 or geometry.shape[0] > kernels.max_eaw_geometry):
        return None
    return kernels


def _log2_weight(base: torch.Tensor, workspace: PairWorkspace, name: str, region: PairRegion) -> torch.Tensor:
    """base - |f_p - f_q|^2 over the pair region, (1, h, w), for the features ``name`` of the workspace.

    base: (1, h w) or (1, 1). The channel sum is a (1, C) x (C, h w) product, cheaper than a reduction.
    """
    squares = F.mse_loss(workspace.first(name, region), workspace.second(name, region), reduction="none")
    channels, rows, columns = squares.shape
    minus_ones = workspace.constant(-1.0, (1, channels))
    return torch.addmm(base, minus_ones, squares.view(channels, rows * columns)).view(1, rows, columns)


def eaw_workspace(height: int, width: int, channels: int, geometry_channels: int,
                  reuse: PairWorkspace | None = None) -> PairWorkspace:
    """Buffers of :func:`filter_eaw` for C colour and G geometry channels; ``reuse`` if it fits."""
    if reuse is not None and (reuse.height, reuse.width) == (height, width) \
            and reuse["geometry"].shape[0] == geometry_channels and reuse["features"].shape[0] == channels:
        return reuse
    workspace = PairWorkspace(height, width, images={"geometry": geometry_channels, "features": channels},
                              doubled={"values": channels + 1, "accumulated": channels + 1})
    workspace["values"][:, channels] = 1.0   # the ones channel accumulates the weight sum
    return workspace
