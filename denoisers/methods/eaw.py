"""Edge-avoiding a-trous wavelet filter (Dammertz, Sewtz, Hanika, Lensch 2010), the EAW baseline of
Chaitanya et al. 2017 (Sec. 5.4, Figs. 7-8)."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from denoisers.filters import atrous_step, check_sizes, luminance, sanitize
from denoisers.registry import Denoiser, Frame, register


@register("eaw", inputs=("radiance", "normal", "position"),
          description="edge-avoiding a-trous wavelet filter (Dammertz et al. 2010)")
class EdgeAvoidingATrous(Denoiser):
    """Edge-avoiding a-trous wavelet filter on the box-filtered radiance, single frame.

    ``iterations`` passes of the 5x5 B3-spline kernel with taps 2^i pixels apart (i = 0, 1, ...), each
    weighted by w(p, q) = w_rt * w_n * w_x, w_k = exp(-|I_k(p) - I_k(q)|^2 / sigma_k^2), where I_rt is the
    current iterate c_i, I_n the normal and I_x the world position buffer (Dammertz et al. 2010);
    the output is the last iterate (the wavelet detail coefficients are dropped).

    Parameters (the paper gives the form of each term; its values are set per scene, so ours were
    picked by a coarse grid search on the two smoke-test scenes, 48x48, 1 and 4 spp, mean PSNR):

    - ``sigma_color`` (8.0): sigma_rt of the colour term in the first pass, in units of the frame's mean
      luminance (our choice: the scenes' exposure spans two orders of magnitude, so an absolute sigma
      would filter dark and bright scenes completely differently). Large, because 1-4 spp inputs are
      dominated by fireflies that a small sigma would keep.
    - ``color_sigma_decay`` (0.5): sigma_rt at pass i is sigma_rt * decay^i -- the paper's 2^-i, so
      later, wider passes do not blur the features that earlier passes kept.
    - ``sigma_normal`` (0.5): sigma_n on the difference of (sample-mean) world-space normals; a 90
      degree crease (|dn|^2 = 2) gets weight exp(-8), facets of a tessellated sphere pass.
    - ``sigma_position`` (0.25): sigma_x in metres on world-position differences (0.1 and 0.5 gave
      1-2.5 dB lower mean PSNR on the smoke scenes). Being in metres, the best value depends on the
      resolution (pixel footprint) and scene scale; it was picked at 48x48.
    - ``iterations`` (5): 5 passes with doubling step (issue text), a 125x125 pixel footprint.

    Inputs: mean over the frame's samples of radiance, normal and position (first non-specular vertex).
    No albedo: texture edges are kept only by the colour term.
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

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        color = sanitize(frame.mean("radiance"))
        geometry = torch.cat([sanitize(frame.mean("normal")) / self.sigma_normal,
                              sanitize(frame.mean("position")) / self.sigma_position])
        return filter_eaw(color, geometry, self.sigma_color * mean_luminance_scale(color),
                          self.iterations, self.color_sigma_decay)


def mean_luminance_scale(color: torch.Tensor) -> float:
    """Mean absolute luminance of a (3, H, W) image, floored so that black frames give a usable scale."""
    return max(float(luminance(color).abs().mean()), 1e-6)


def filter_eaw(color: torch.Tensor, scaled_geometry: torch.Tensor, sigma_color: float, iterations: int,
               color_sigma_decay: float = 0.5) -> torch.Tensor:
    """Run the EAW iterations on ``color`` (3, H, W).

    scaled_geometry: (G, H, W) static edge-stopping features already divided by their sigmas (the
    normal and position terms); sigma_color: sigma_rt of the first iteration in radiance units.
    """

    def pair_terms(at_p: dict[str, torch.Tensor], at_q: dict[str, torch.Tensor]):
        # exp(-|f_p - f_q|^2) over the concatenated scaled features = w_rt * w_n * w_x.
        return F.mse_loss(at_p["f"], at_q["f"], reduction="none").sum(dim=0, keepdim=True).neg_(), ()

    for i in range(iterations):
        sigma = sigma_color * color_sigma_decay ** i
        features = torch.cat([color / sigma, scaled_geometry])
        color, _ = atrous_step(color, 2 ** i, {"f": features}, pair_terms)
    return color
