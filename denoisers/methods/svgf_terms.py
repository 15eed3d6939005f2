"""Pieces of SVGF (Schied et al. 2017) used by :mod:`denoisers.methods.svgf`: the constants of its edge-stopping
terms, the history carried between frames, the geometric log-weights of the a-trous passes and the moment
variance and depth gradient helpers. No registration here."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from denoisers.filters import LOG2_E, MIN_LOG_WEIGHT, PairRegion, PairWorkspace

# Denominator floor of the luminance edge-stopping term (the paper only says "small"); with zero
# variance only neighbours of equal luminance pass, so a noise-free input comes out unchanged.
LUMINANCE_EPSILON = 1e-10
# Depth term floor, relative to the centre depth (metres): tolerates depth noise on fronto-parallel
# surfaces whose screen-space depth gradient is zero.
DEPTH_EPSILON_RELATIVE = 1e-3
# A reprojection succeeds when the consistent bilinear taps carry at least this much weight.
MIN_REPROJECTION_WEIGHT = 1e-2
# max(0, n_p . n_q) is floored here before its log (a zero would take exp/log slow paths); the
# resulting weight, 1e-30^sigma_n, is zero after the log-weight clamp anyway.
NORMAL_COSINE_FLOOR = 1e-30
# Below this fraction of short-history pixels the spatial variance estimate gathers just those pixels.
SPARSE_VARIANCE_FRACTION = 0.2
# History lengths are capped (only 1/n and n < 4 matter, and the cap keeps the state bounded).
MAX_HISTORY = 255.0


@dataclass
class History:
    """State carried from one frame to the next, all at the previous frame's pixels, packed into one
    (10, H, W) tensor so that the reprojection gathers every channel in one go."""

    state: torch.Tensor          # (10, H, W) [illumination, moments, length, depth, normal]
    index: int                   # frame index

    @property
    def illumination(self) -> torch.Tensor:
        """(3, H, W) demodulated colour after the first a-trous iteration."""
        return self.state[0:3]

    @property
    def moments(self) -> torch.Tensor:
        """(2, H, W) integrated first and second luminance moments."""
        return self.state[3:5]

    @property
    def length(self) -> torch.Tensor:
        """(1, H, W) history length in frames, 1 = this frame only."""
        return self.state[5:6]

    @property
    def depth(self) -> torch.Tensor:
        """(1, H, W) pixel-centre G-buffer depth (metres)."""
        return self.state[6:7]

    @property
    def normal(self) -> torch.Tensor:
        """(3, H, W) pixel-centre G-buffer normal (unit)."""
        return self.state[7:10]


class GeometryTerms:
    """Geometric base-2 log-weights of one frame, G(p, o) = log2(e) (sigma_n log max(0, n_p . n_q)
    - a_z(p, o) |z_p - z_q|) + log2 h, per tap pair, with a hand-over of terms between passes.

    ``log2_weights(region, log2_h)`` returns G of the taps +o and -o as (2, 1, h, w) over ``first``
    (taken from the hand-over when a previous pass kept it for this offset); ``keep`` hands it to the
    next pass that visits the same pixel offset (the next a-trous iteration, or the first one after the
    7x7 spatial variance estimate). The terms live in full-size buffers of the workspace, reused across
    frames (a dozen kept half-megabyte temporaries cost more in page faults than in arithmetic): a term
    that is not kept may be modified in place, and is valid until the next ``log2_weights`` call.
    n_p . n_q is floored at exp(MIN_LOG_WEIGHT / sigma_n) instead of 1e-30: below it the weight is
    clamped to exp(MIN_LOG_WEIGHT) either way (log h <= 0), and for sigma_n >= 87 the floor keeps the
    cosine in [0.5, 1], where log(c) = log1p(c - 1) is exact to rounding and faster than log.
    """

    def __init__(self, sigma_normal: float, sigma_depth: float, workspace: PairWorkspace, normal: torch.Tensor,
                 depth: torch.Tensor, gradient: torch.Tensor) -> None:
        self.workspace = workspace
        self.sigma_depth = sigma_depth
        self.normal_scale = sigma_normal * LOG2_E
        self.cosine_floor = cosine_floor(sigma_normal)
        for channel in range(3):
            workspace[f"normal{channel}"].copy_(normal[channel:channel + 1])
        workspace["depth"].copy_(depth)
        self.gradient = gradient
        # a_z(p, o) log2 e = 1 / (ln 2 (sigma_z |grad z . o| + eps(p))), |grad z . d| cached per direction d.
        self.depth_floor = (depth * DEPTH_EPSILON_RELATIVE + 1e-6).mul_(math.log(2.0))
        self.projections: dict[tuple[int, int], torch.Tensor] = {}
        # Pixel offset -> (index of its term buffer, log2 h included); the buffer of the last term made.
        self.handed_over: dict[tuple[int, int], tuple[int, float]] = {}
        self.current: int | None = None
        self.buffers = workspace.pool                     # (2, 1, H, W) each, grown on demand
        self.free = list(range(len(self.buffers)))

    def log2_weights(self, region: PairRegion, log2_h: float) -> torch.Tensor:
        """G of the taps +o and -o with kernel weight h, (2, 1, h, w) (see the class docstring)."""
        if self.current is not None:
            self.free.append(self.current)
        kept = self.handed_over.pop((region.dy, region.dx), None)
        if kept is not None:
            self.current, kept_log2_h = kept
            return region.at_first(self.buffers[self.current]).add_(log2_h - kept_log2_h)
        if not self.free:
            self.buffers.append(torch.empty(2, 1, self.workspace.height, self.workspace.width))
            self.free.append(len(self.buffers) - 1)
        self.current = self.free.pop()
        workspace = self.workspace
        cosine = workspace.first("normal0", region) * workspace.second("normal0", region)
        cosine.addcmul_(workspace.first("normal1", region), workspace.second("normal1", region))
        cosine.addcmul_(workspace.first("normal2", region), workspace.second("normal2", region))
        if self.cosine_floor >= 0.5:
            log_cosine = cosine.sub_(1.0).clamp_min_(self.cosine_floor - 1.0).log1p_()
        else:
            log_cosine = cosine.clamp_min_(self.cosine_floor).log_()
        symmetric = log_cosine.mul_(self.normal_scale).add_(log2_h)
        distance = torch.sub(workspace.first("depth", region), workspace.second("depth", region)).abs_()
        length = math.gcd(region.dy, region.dx)
        direction = (region.dy // length, region.dx // length)
        if direction not in self.projections:
            self.projections[direction] = (self.gradient[0:1] * direction[1]
                                           + self.gradient[1:2] * direction[0]).abs_()
        depth_scale = torch.add(self.depth_floor, self.projections[direction],
                                alpha=self.sigma_depth * length * math.log(2.0), out=workspace["depth_scale"])
        depth_scale.reciprocal_()
        return torch.addcmul(symmetric, workspace.pair("depth_scale", region), distance, value=-1.0,
                             out=region.at_first(self.buffers[self.current]))

    def keep(self, region: PairRegion, log2_h: float) -> None:
        """Hand the last term (made for ``region`` with ``log2_h``) to the next pass visiting its offset;
        the caller must not modify it afterwards."""
        self.handed_over[(region.dy, region.dx)] = (self.current, log2_h)
        self.current = None


def cosine_floor(sigma_normal: float) -> float:
    """Floor of n_p . n_q before its log: below exp(MIN_LOG_WEIGHT / sigma_n) the weight is clamped anyway
    (see :class:`GeometryTerms`)."""
    return max(NORMAL_COSINE_FLOOR, math.exp(MIN_LOG_WEIGHT / sigma_normal))


def moment_variance(moments: torch.Tensor, spp: int) -> torch.Tensor:
    """(2, H, W) luminance moments [m1, m2] of single samples -> (1, H, W) variance of the spp-sample mean."""
    return (moments[1:2] - moments[0:1].square()).clamp_min_(0) / spp


def depth_gradient(depth: torch.Tensor) -> torch.Tensor:
    """(1, H, W) -> (2, H, W) screen-space depth gradient [dz/dx, dz/dy] in metres per pixel.

    Of the forward and backward difference the smaller one is taken, so a pixel on the edge of an
    object gets the gradient of its own surface rather than the jump to the background.
    """
    def one_axis(dim: int) -> torch.Tensor:
        forward = torch.diff(depth, dim=dim, append=depth.narrow(dim, depth.shape[dim] - 1, 1))
        backward = torch.diff(depth, dim=dim, prepend=depth.narrow(dim, 0, 1))
        # At the image border one of the two is 0 by construction; use the other there.
        forward.narrow(dim, depth.shape[dim] - 1, 1).copy_(backward.narrow(dim, depth.shape[dim] - 1, 1))
        backward.narrow(dim, 0, 1).copy_(forward.narrow(dim, 0, 1))
        # torch.where(|forward| <= |backward|, forward, backward) with a float mask (where is slow on
        # the CPU); exact, as x * 1 + y * 0 = x for finite values.
        take_forward = torch.le(forward.abs(), backward.abs(), out=torch.empty_like(forward))
        return forward.mul_(take_forward).add_(backward.mul_(1 - take_forward))

    return torch.cat([one_axis(2), one_axis(1)])

