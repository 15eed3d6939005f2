"""Shared building blocks of the classical filters: luminance, input sanitising, the edge-aware
a-trous step (B3-spline or box kernel) and motion-vector warping.

Image tensors are channels-first torch float32: (C, H, W) for one image, (N, C, H, W) for a batch.
Everything is vectorised over pixels; the only Python loops run over the (at most 49) kernel taps.

The a-trous step exploits that most edge-stopping terms are symmetric, d(p, q) = d(q, p): a term is
computed once per pair of opposite offsets (+o, -o), over the pixels where both ends lie in the image,
and used for both taps, which halves the dominant cost.

Speed notes (one CPU thread, where the filters are memory- and op-count-bound): weights are evaluated
as exp2 of base-2 log-weights (torch's exp is ~4x slower than exp2 here); masks are float 0 / 1 made by
comparisons with a float ``out`` (bool tensors, ``torch.where`` and ``masked_fill`` are 5-30x slower
than float ops); hot loops keep their full-image buffers in a :class:`PairWorkspace` across iterations
and frames, so that views are built once and no multi-megabyte temporaries are allocated per frame
(fresh ones cost page faults).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import torch
import torch.nn.functional as F

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
REC709_LUMINANCE: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)
#: 1D B3-spline taps (1, 4, 6, 4, 1) / 16 of the a-trous wavelet transform (Dammertz et al. 2010).
B3_SPLINE: tuple[float, ...] = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)
#: Magnitude limit of sanitised inputs: squares (second moments) of such values stay finite in float32.
SANITIZE_LIMIT = 1e8

#: Log-weights are clamped here: exp of very negative numbers takes a slow path on x86 (a 10x slower
#: filter), and exp(-60) ~ 1e-26 is as good as zero next to the centre tap's weight.
MIN_LOG_WEIGHT = -60.0
#: log2(e). Weights are evaluated as exp2(log2(e) x) = exp(x): torch's exp2 is ~4x faster than exp on
#: the CPU (and log1p ~1.5x faster than log), and the filters spend much of their time there.
LOG2_E = 1.0 / math.log(2.0)
#: :data:`MIN_LOG_WEIGHT` as a base-2 log-weight.
MIN_LOG2_WEIGHT = MIN_LOG_WEIGHT * LOG2_E

#: Callback of :func:`atrous_step`: (guides at p, guides at q) over one region -> (S, [U_k]) with
#: S (1, h, w) a symmetric log-weight (or None) and U_k (1, h, w) symmetric non-negative distances.
PairTerms = Callable[[dict[str, torch.Tensor], dict[str, torch.Tensor]],
                     tuple[torch.Tensor | None, Sequence[torch.Tensor]]]
#: Callback of :func:`atrous_step`: offset (dy, dx) in pixels -> per-centre scales a_k (1, H, W) of U_k;
#: must give the same result for (dy, dx) and (-dy, -dx).
CentreScales = Callable[[int, int], Sequence[torch.Tensor]]


def sanitize(x: torch.Tensor, limit: float = SANITIZE_LIMIT) -> torch.Tensor:
    """Copy of ``x`` with NaN and +-Inf replaced by 0 and finite values clamped to [-limit, limit].

    Every method sanitises its inputs so that its output stays finite; renderer outputs are finite
    already, this guards against corrupted or synthetic spike inputs.
    """
    x = torch.nan_to_num(x.float(), nan=0.0, posinf=0.0, neginf=0.0)
    return x.clamp_(-limit, limit)


def count_nonfinite(x: torch.Tensor) -> int:
    """Number of NaN/Inf entries of ``x``."""
    return int((~torch.isfinite(x)).sum())


def check_sizes(method: str, images: dict[str, torch.Tensor]) -> tuple[int, int]:
    """(H, W) shared by all ``images`` (..., C, H, W); ValueError naming the method and every size otherwise."""
    sizes = {name: tuple(image.shape[-2:]) for name, image in images.items()}
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{name} {h}x{w}" for name, (h, w) in sizes.items())
        raise ValueError(f"method {method!r}: input buffers differ in resolution ({listed})")
    return next(iter(sizes.values()))


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 709 luminance of linear RGB: (..., 3, H, W) -> (..., 1, H, W)."""
    r, g, b = rgb.unbind(dim=-3)
    return (REC709_LUMINANCE[0] * r + REC709_LUMINANCE[1] * g + REC709_LUMINANCE[2] * b).unsqueeze(-3)


def normalize_vectors(v: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Unit vectors along dim -3 of (..., 3, H, W); zero vectors (no surface) stay zero."""
    length = v.square().sum(dim=-3, keepdim=True).sqrt_()
    # The mask as float32: comparisons into bool tensors are several times slower on the CPU.
    nonzero = torch.gt(length, eps, out=torch.empty_like(length))
    return v / length.clamp_min_(eps) * nonzero


def b3_kernel_2d() -> torch.Tensor:
    """(5, 5) B3-spline a-trous kernel, the outer product of :data:`B3_SPLINE` (sums to 1)."""
    h = torch.tensor(B3_SPLINE, dtype=torch.float32)
    return torch.outer(h, h)


def gaussian_blur_3x3(x: torch.Tensor) -> torch.Tensor:
    """(C, H, W) -> (C, H, W) 3x3 binomial blur [1, 2, 1]^2 / 16, renormalised at the borders."""
    return _binomial_1d(_binomial_1d(x, -1), -2)


def _binomial_1d(x: torch.Tensor, dim: int) -> torch.Tensor:
    """[1, 2, 1] / 4 along ``dim``; a border pixel averages itself (2/3) and its one neighbour (1/3)."""
    n = x.shape[dim]
    if n < 2:
        return x.clone()
    out = x * 0.5
    out.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1), alpha=0.25)
    out.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1), alpha=0.25)
    for edge in (0, n - 1):
        out.narrow(dim, edge, 1).mul_(4.0 / 3.0)
    return out


def half_offsets(radius: int) -> list[tuple[int, int]]:
    """Tap offsets (i, j) of a (2 radius + 1)^2 grid with (i, j) > (0, 0) lexicographically.

    Together with their negatives and (0, 0) they cover the whole grid exactly once.
    """
    return [(i, j) for i in range(radius + 1) for j in range(-radius, radius + 1) if i > 0 or j > 0]


class PairRegion:
    """Index bookkeeping for one pair of opposite taps +o, -o = (dy, dx), (-dy, -dx).

    ``first`` is the set of pixels p with p and p + o both inside the image, ``second`` the same set
    shifted by +o. A symmetric term d(p, p + o) computed over ``first`` serves tap +o at the pixels of
    ``first`` and tap -o at the pixels of ``second``; taps that would leave the image are simply not
    accumulated, which renormalises the kernel at the borders without padding.
    """

    def __init__(self, height: int, width: int, dy: int, dx: int) -> None:
        self.dy, self.dx = dy, dx
        self.first = (slice(max(0, -dy), height - max(0, dy)), slice(max(0, -dx), width - max(0, dx)))
        self.second = (slice(max(0, dy), height - max(0, -dy)), slice(max(0, dx), width - max(0, -dx)))

    @property
    def empty(self) -> bool:
        return any(s.stop <= s.start for s in self.first)

    def at_first(self, image: torch.Tensor) -> torch.Tensor:
        """(..., C, h, w) view of an image over ``first``."""
        return image[..., self.first[0], self.first[1]]

    def at_second(self, image: torch.Tensor) -> torch.Tensor:
        """(..., C, h, w) view of an image over ``second``."""
        return image[..., self.second[0], self.second[1]]


def pair_regions(height: int, width: int, radius: int, step: int) -> Iterator[tuple[PairRegion, int, int]]:
    """(region, i, j) for every half offset (i, j) of a radius-``radius`` grid with spacing ``step``
    that still overlaps the image."""
    for i, j in half_offsets(radius):
        region = PairRegion(height, width, i * step, j * step)
        if not region.empty:
            yield region, i, j


class PairWorkspace:
    """Full-image buffers that an a-trous filter reuses across iterations and frames, with their views at
    the tap pairs of every offset created once (building a view costs about as much as a small op).

    A buffer is an image (C, H, W) or a doubled image (2, C, H, W): two copies that act as separate
    accumulators (or sources) of the taps +o and -o, so both taps of a pair are accumulated by one
    in-place op (within one image their target regions overlap, which an in-place op cannot write).
    Views of a pair are (2, C, h, w) with index 0 for tap +o (centres over ``first``) and 1 for -o:

    - ``pair(name)``, image: the image at ``first`` and at ``second`` (overlapping; read only);
    - ``straight(name)``, doubled: copy 0 at ``first``, copy 1 at ``second`` (the taps' centres);
    - ``crossed(name)``, doubled: copy 0 at ``second``, copy 1 at ``first`` (the taps' neighbours).
    """

    def __init__(self, height: int, width: int, images: dict[str, int], doubled: dict[str, int]) -> None:
        self.height, self.width = height, width
        self.buffers = {name: torch.zeros(channels, height, width) for name, channels in images.items()}
        self.buffers.update({name: torch.zeros(2, channels, height, width) for name, channels in doubled.items()})
        #: Further buffers of this size that the filter keeps with the workspace (no views cached).
        self.pool: list[torch.Tensor] = []
        self._views: dict[tuple[str, str, int, int], torch.Tensor] = {}
        self._cache: dict[tuple, object] = {}

    def __getitem__(self, name: str) -> torch.Tensor:
        return self.buffers[name]

    def regions(self, radius: int, step: int) -> list[tuple[PairRegion, int, int]]:
        """:func:`pair_regions` of this image size, cached."""
        key = ("regions", "", radius, step)
        if key not in self._cache:
            self._cache[key] = list(pair_regions(self.height, self.width, radius, step))
        return self._cache[key]

    def constant(self, value: float, shape: tuple[int, ...]) -> torch.Tensor:
        """A cached tensor of ``shape`` filled with ``value`` (for small operands, e.g. of addmm)."""
        key = ("constant", shape, value)
        if key not in self._cache:
            self._cache[key] = torch.full(shape, value)
        return self._cache[key]

    def first(self, name: str, region: PairRegion) -> torch.Tensor:
        """(C, h, w) view of image ``name`` over ``first``."""
        return self._view("first", name, region)

    def second(self, name: str, region: PairRegion) -> torch.Tensor:
        """(C, h, w) view of image ``name`` over ``second``."""
        return self._view("second", name, region)

    def pair(self, name: str, region: PairRegion) -> torch.Tensor:
        """(2, C, h, w): image ``name`` at ``first`` and at ``second`` (read only)."""
        return self._view("pair", name, region)

    def straight(self, name: str, region: PairRegion) -> torch.Tensor:
        """(2, C, h, w): doubled ``name``, copy 0 at ``first`` and copy 1 at ``second``."""
        return self._view("straight", name, region)

    def crossed(self, name: str, region: PairRegion) -> torch.Tensor:
        """(2, C, h, w): doubled ``name``, copy 0 at ``second`` and copy 1 at ``first``."""
        return self._view("crossed", name, region)

    def _view(self, kind: str, name: str, region: PairRegion) -> torch.Tensor:
        key = (kind, name, region.dy, region.dx)
        view = self._views.get(key)
        if view is None:
            view = self._views[key] = self._make_view(kind, self.buffers[name], region)
        return view

    def _make_view(self, kind: str, buffer: torch.Tensor, region: PairRegion) -> torch.Tensor:
        if kind == "first":
            return region.at_first(buffer)
        if kind == "second":
            return region.at_second(buffer)
        width, plane = self.width, self.height * self.width
        (first_rows, first_columns), (second_rows, second_columns) = region.first, region.second
        rows, columns = first_rows.stop - first_rows.start, first_columns.stop - first_columns.start
        start_first = first_rows.start * width + first_columns.start
        start_second = second_rows.start * width + second_columns.start
        shift = start_second - start_first       # = dy W + dx > 0 for a half offset
        channels = buffer.shape[-3]
        start_first += buffer.storage_offset()
        start_second += buffer.storage_offset()
        if kind == "pair":
            copy_stride, start = shift, start_first
        elif kind == "straight":
            copy_stride, start = channels * plane + shift, start_first
        else:
            copy_stride, start = channels * plane - shift, start_second
        if (kind == "pair") != (buffer.dim() == 3) or not buffer.is_contiguous() or shift <= 0:
            raise ValueError(f"PairWorkspace: no {kind} view of a buffer of shape {tuple(buffer.shape)}")
        return buffer.as_strided((2, channels, rows, columns), (copy_stride, plane, width, 1), start)


def revisited_next_step(i: int, j: int) -> bool:
    """Whether the next a-trous iteration (step doubled) visits the pixel offset of tap (i, j) again.

    Its tap (i / 2, j / 2) lands there, so terms that depend only on the offset (geometric edge-stopping
    distances) can be handed over instead of recomputed: 4 of the 12 pairs of a 5x5 kernel.
    """
    return i % 2 == 0 and j % 2 == 0


def atrous_step(values: torch.Tensor, step: int, guides: dict[str, torch.Tensor], pair_terms: PairTerms,
                centre_scales: CentreScales | None = None, variance: torch.Tensor | None = None,
                kernel_1d: Sequence[float] = B3_SPLINE) -> tuple[torch.Tensor, torch.Tensor | None]:
    """One edge-aware a-trous iteration: a (k x k) kernel with taps ``step`` pixels apart.

    out(p) = sum_q h(q - p) w(p, q) values(q) / sum_q h(q - p) w(p, q), over taps q inside the image
    (weights renormalised at the borders), with the edge-stopping weight
    w(p, q) = exp(max(S(p, q) - sum_k a_k(p, o) U_k(p, q), MIN_LOG_WEIGHT)), o = q - p, and w(p, p) = 1.

    values: (C, H, W); guides: name -> (C_g, H, W) images handed to ``pair_terms``;
    pair_terms: (guides at p, guides at q = p + o) over a region -> (S or None, [U_k]), symmetric terms
    (fresh tensors: S is modified in place);
    centre_scales: (dy, dx) -> [a_k (1, H, W)], even in o; kernel_1d: separable spatial kernel
    (B3 spline by default; length 2r + 1).
    variance: optional (C_v, H, W) filtered as var_out(p) = sum h^2 w^2 var(q) / (sum h w)^2 (the
    variance of the output when the inputs are independent).
    Returns (filtered values (C, H, W), filtered variance or None).
    """
    channels, height, width = values.shape
    radius = (len(kernel_1d) - 1) // 2
    kernel = [float(k) for k in kernel_1d]
    centre_h = kernel[radius] ** 2
    # A ones channel accumulates the weight sum alongside the values.
    with_ones = torch.cat([values, torch.ones_like(values[:1])])
    accumulated = with_ones * centre_h
    if variance is not None:
        variance_accumulated = variance * centre_h ** 2
    for region, i, j in pair_regions(height, width, radius, step):
        symmetric, distances = pair_terms({n: region.at_first(g) for n, g in guides.items()},
                                          {n: region.at_second(g) for n, g in guides.items()})
        log_h = math.log(kernel[radius + i] * kernel[radius + j])
        scales = centre_scales(region.dy, region.dx) if centre_scales is not None else ()
        if len(scales) != len(distances):
            raise ValueError(f"atrous_step: {len(distances)} distances but {len(scales)} centre scales")
        if not scales:  # fully symmetric weight: one exp for both taps
            if symmetric is None:
                shared_weight = torch.full_like(region.at_first(values[:1]), math.exp(log_h))
            else:
                shared_weight = symmetric.add_(log_h).clamp_min_(MIN_LOG_WEIGHT).mul_(LOG2_E).exp2_()
        elif symmetric is not None:
            symmetric.add_(log_h)
        # Tap +o: centres over `first`, neighbours over `second`; tap -o the other way round.
        for centre, neighbour in ((region.at_first, region.at_second), (region.at_second, region.at_first)):
            if scales:
                base = symmetric if symmetric is not None else torch.full_like(distances[0], log_h)
                exponent = torch.addcmul(base, centre(scales[0]), distances[0], value=-1.0)
                for a, u in zip(scales[1:], distances[1:]):
                    exponent.addcmul_(centre(a), u, value=-1.0)
                weight = exponent.clamp_min_(MIN_LOG_WEIGHT).mul_(LOG2_E).exp2_()
            else:
                weight = shared_weight
            centre(accumulated).addcmul_(neighbour(with_ones), weight)
            if variance is not None:
                centre(variance_accumulated).addcmul_(neighbour(variance), weight.square())
    weight_sum = accumulated[channels:]
    filtered = accumulated[:channels] / weight_sum
    filtered_variance = variance_accumulated / weight_sum.square() if variance is not None else None
    return filtered, filtered_variance


def warp_previous(prev: torch.Tensor, motion: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Bring previous-frame data to the current frame: sample ``prev`` at (x + motion_x, y + motion_y).

    prev: (C, H, W) or (N, C, H, W); motion: (2, H, W) backward motion in pixels (scenegen
    convention: the previous position of pixel centre (x + 0.5, y + 0.5) is centre + motion), shared by
    the batch, or (N, 2, H, W) per image for a batched ``prev``.
    Bilinear interpolation in pixel-index coordinates (``mode="nearest"``: the nearest pixel, as Isik et al.'s
    warp), lookups outside the image clamp to the border. Returns the same shape as ``prev``.
    """
    batched = prev.dim() == 4
    images = prev if batched else prev[None]
    height, width = images.shape[-2:]
    per_image = batched and motion.dim() == 4
    if motion.shape[-3:] != (2, height, width) or (per_image and motion.shape[0] != images.shape[0]) or (
            motion.dim() == 4 and not per_image):
        raise ValueError(f"warp_previous: motion must be (2, {height}, {width}) or, for a batch of {images.shape[0]}, "
                         f"({images.shape[0]}, 2, {height}, {width}); got {tuple(motion.shape)}")
    ys = torch.arange(height, dtype=torch.float32).view(height, 1)
    xs = torch.arange(width, dtype=torch.float32).view(1, width)
    motion = sanitize(motion)
    x = (xs + motion[..., 0, :, :]).clamp(0, width - 1)
    y = (ys + motion[..., 1, :, :]).clamp(0, height - 1)
    # grid_sample with align_corners=True maps -1 / +1 to the centres of the first / last pixel.
    grid = torch.stack([x * (2.0 / max(width - 1, 1)) - 1.0, y * (2.0 / max(height - 1, 1)) - 1.0], dim=-1)
    grid = grid.expand(images.shape[0], height, width, 2)
    warped = F.grid_sample(images.float(), grid, mode=mode, padding_mode="border", align_corners=True)
    return warped if batched else warped[0]


def bilinear_taps(motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The four bilinear taps of the backward lookup at (x + motion_x, y + motion_y).

    motion: (2, H, W) pixels. Returns (flat indices (4, H, W) int64 into an H*W image, clamped to the
    image; weights (4, H, W); inside (4, H, W) bool, whether the tap lies in the image). Taps are ordered
    (y0, x0), (y0, x1), (y1, x0), (y1, x1).
    """
    indices, weights, inside = bilinear_footprint(motion)
    return indices, weights, inside.bool()


def bilinear_footprint(motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`bilinear_taps` with ``inside`` as float32 0 / 1 (cheaper to make and to multiply with)."""
    _, height, width = motion.shape
    motion = sanitize(motion, limit=4.0 * (height + width))   # far outside is outside; keeps indices sane
    x = motion[0] + torch.arange(width, dtype=torch.float32)
    y = motion[1] + torch.arange(height, dtype=torch.float32).view(height, 1)
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    # Per axis: (2, H, W) for the taps at x0 and x0 + 1 (y0 and y0 + 1); the 4 taps are their outer product.
    x_taps, y_taps = torch.stack([x0, x0 + 1]), torch.stack([y0, y0 + 1])
    # Tap coordinates are integers, so clamp(c + 1, 0, 1) = [c >= 0] and clamp(n - c, 0, 1) = [c <= n - 1].
    x_inside = (x_taps + 1).clamp_(0, 1).mul_((width - x_taps).clamp_(0, 1))
    y_inside = (y_taps + 1).clamp_(0, 1).mul_((height - y_taps).clamp_(0, 1))
    # Flat indices are exact small integers, in float64 beyond float32's 2^24.
    index_dtype = torch.float32 if height * width < 2 ** 24 else torch.float64
    rows = y_taps.clamp_(0, height - 1).to(index_dtype).mul_(width)
    columns = x_taps.clamp_(0, width - 1).to(index_dtype)
    indices = (rows[:, None] + columns[None]).view(4, height, width).long()
    weights = (torch.stack([1 - fy, fy])[:, None] * torch.stack([1 - fx, fx])[None]).view(4, height, width)
    inside = (y_inside[:, None] * x_inside[None]).view(4, height, width)
    return indices, weights, inside


def gather_taps(image: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    """(C, H, W) image, (K, H, W) flat indices -> (K, C, H, W) values at those pixels."""
    channels = image.shape[0]
    taps, height, width = indices.shape
    gathered = torch.index_select(image.reshape(channels, -1), 1, indices.reshape(-1))
    return gathered.view(channels, taps, height, width).transpose(0, 1)
