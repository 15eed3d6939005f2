"""Adaptive sampling from stored sample layers (issue 12; Hasselgren et al. 2020, Kuznetsov et al. 2018).

The renderer stores independent 1-spp layers per frame (``render.spp`` layers with every buffer, then
``render.extra_radiance_spp`` radiance-only layers). A pixel given ``k`` samples gets the mean of its
first ``k`` layers, which is exactly what rendering ``k`` samples there would give. This module holds:

* :func:`density` -- Eq. 2 of Hasselgren et al. before rounding, ``M n softmax(s)``: differentiable (real-valued
  samples per pixel, mean exactly ``n``); :func:`capped_density` the same with the renderer's cap of the stored
  layers per pixel, what the NTASD and DASR samplers train and run with.
* :func:`normalize_sample_map` -- Eq. 2 to an integer (H, W) sample map whose mean never exceeds the
  budget ``n`` (rounding included), at least ``minimum`` and at most the available layers per pixel.
* :func:`gather_mean` / :func:`masked_samples` -- the per-pixel mean of the first ``k`` layers (and the
  per-sample tensor with the layers beyond ``k`` zeroed), vectorised over pixels.
* :func:`budget_total`, :func:`budget_problems`, :func:`realised_spp` -- the sample accounting the
  evaluation applies to every adaptive row (denoisers.jobs.denoise, denoisers.jobs.scoring).
* :func:`render_adaptive` -- the "renderer" of training: real densities -> integer maps -> gathered means,
  with the renderer gradient below for the backward pass.

Renderer gradient (Kuznetsov et al. 2018, used by Hasselgren et al. 2020 Sec. 2.1). Rendering is not
differentiable in the sample count, so the backward pass uses the forward difference of the stored
layers: the mean of the first k layers, I_k = (1/k) sum_{i<=k} x_i, changes by one more sample by
``dI/dk ~ I_{k+1} - I_k = (x_{k+1} - I_k) / (k + 1)`` (with the realised next layer x_{k+1}, so it is the
renderer's own finite difference; at k = S_avail the backward difference I_S - I_{S-1}; at k = 0,
I_0 = 0, it is x_1). The density gradient is then sum_c dL/dI_c * dI_c/dk per pixel; the rounding to
integers is skipped (straight through). In expectation over x_{k+1} this is ``dL/dI . (mu - I_k)/(k + 1)``,
the derivative of the expected loss of the linearly interpolated renderer
I(k + h) = I_k + h (x_{k+1} - I_k)/(k + 1), i.e. the first-order term of adding one sample. For a squared
error the integer step's finite difference E[L(k + 1)] - E[L(k)] adds a positive second-order term, and the
estimate is exactly twice that finite difference (-2 sigma^2 / (k (k + 1)) against -sigma^2 / (k (k + 1))
per pixel): same sign and the same ordering of pixels by the error one more sample removes.
tests/test_ntasd.py checks this against directly computed finite differences of the expected error.
When the network sees the means through an encoding T (NTASD's log-gamma), the difference is taken after it,
T(I_{k+1}) - T(I_k): the chain rule through T'(I_k) instead multiplies a firefly's linear jump by T's slope at
a dark mean (up to 151 for NTASD's encoding at 0): replaying the 2026-12-01 run's adaptive training, the
sampler's gradient norm reached 20,000 times its median within 300 steps, and that run's model diverged at
step 750 and never recovered.

Rounding (``normalize_sample_map``): the budget is ``T = floor(n M + 1e-9)`` integer samples for M pixels
(:func:`budget_total`). Eq. 2 gives real counts ``x_p = minimum + (T - minimum M) w_p / sum w``; counts
above the available layers are clipped and their excess is given to the other pixels in proportion to
their importance (water filling). Each pixel then gets ``floor(x_p)`` and the ``R = T - sum floor(x_p)``
remaining samples go to
  - ``"largest_remainder"`` (default, deterministic): the R pixels with the largest fractional parts
    (ties to the lower raster index);
  - ``"stochastic"`` (seeded): systematic sampling of the fractional parts along a seeded random
    permutation of the pixels, so pixel p gets an extra sample with probability frac(x_p) (unbiased)
    and exactly R extra samples are given.
Both never exceed T; the same inputs and seed give the same map. The paper's ``round()`` can exceed the
budget by up to M/2 samples, hence these schemes. The paper's minimum is 0 (Eq. 2 rounds, Hasselgren
et al. have no initial pass); DASR (Kuznetsov et al.) first renders 1 spp everywhere, i.e. ``minimum=1``,
and those samples count toward the budget.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

#: Tolerance of the float budget product n M before flooring (n given as a decimal, e.g. 1.1 x 10 px).
BUDGET_EPSILON = 1e-9
ROUNDING_SCHEMES = ("largest_remainder", "stochastic")
#: Per-frame sample maps of an adaptive row beside its denoised frames (denoisers.jobs.denoise):
#: arrays ``frames`` (T,) int64 and ``sample_maps`` (T, H, W) uint8.
SAMPLE_MAPS_FILE = "sample_maps.npz"


class BudgetError(ValueError):
    """A sample map is invalid or spends more samples than its budget; the message names where."""


def budget_total(budget: float, pixels: int) -> int:
    """Integer samples a frame of ``pixels`` pixels may spend at an average of ``budget`` spp:
    floor(budget x pixels) (+1e-9 against float error). A map's mean is within budget iff its sum is <= this."""
    if not math.isfinite(budget) or budget < 0:
        raise BudgetError(f"average sample budget must be finite and >= 0, got {budget}")
    return int(math.floor(budget * pixels + BUDGET_EPSILON))


def density(logits: torch.Tensor, budget: float) -> torch.Tensor:
    """Eq. 2 of Hasselgren et al. without the rounding: ``M n exp(s_p) / sum_i exp(s_i)``.

    logits: (..., H, W) unnormalised network output s (any real); budget n: average spp. Returns the
    same shape, real samples per pixel with per-image mean n. Implemented as a softmax over the unrolled
    image (the paper found this more stable for the gradient); differentiable.
    """
    height, width = logits.shape[-2:]
    flat = logits.reshape(*logits.shape[:-2], height * width)
    return (torch.softmax(flat, dim=-1) * (height * width * float(budget))).reshape(logits.shape)


def capped_density(logits: torch.Tensor, budget: float, max_count: int, *, minimum: int = 0) -> torch.Tensor:
    """Eq. 2 with the cap the renderer has: ``minimum`` samples everywhere, then the rest of the budget
    ``T = budget_total(budget, M)`` as ``softmax(s)`` over the pixels, where a pixel cannot get more than
    ``max_count`` samples (the stored layers) and the excess goes to the others in proportion to ``exp(s)``
    (the water filling of :func:`normalize_sample_map`).

    logits: (N, H, W). Returns (N, H, W) real samples per pixel summing to T (at most ``M max_count``). Capped
    pixels are constants (``max_count``, zero gradient); the others are ``minimum + R softmax(s | uncapped)``
    with R the samples left for them, so the gradient reaches every pixel that can still change. Without the
    cap (plain :func:`density`) a pixel whose logit outgrows the rest takes all of the real-valued density while
    rendering gives it only ``max_count`` samples: the other pixels' densities, and so their gradients, vanish,
    and the map stays flat (what the whole-DAG run of 2026-12-01 showed: logits of +-1000s, one pixel at 32).
    """
    height, width = logits.shape[-2:]
    pixels = height * width
    total = budget_total(budget, pixels)
    if minimum * pixels > total:
        raise BudgetError(f"budget {budget} spp is below the minimum of {minimum} sample(s) per pixel")
    flat = logits.reshape(-1, pixels)
    capacity = float(max_count - minimum)
    out = []
    for row in flat:
        weights = torch.softmax(row.detach().to(torch.float64), dim=0)
        allocation = _water_fill(weights, total - minimum * pixels, torch.full_like(weights, capacity))
        capped = allocation >= capacity - 1e-9
        remaining = float(total - minimum * pixels) - capacity * float(capped.sum())
        free = torch.softmax(torch.where(capped, torch.full_like(row, -math.inf), row), dim=0)
        if bool(capped.all()):
            free = torch.zeros_like(row)
        out.append(minimum + torch.where(capped, torch.full_like(row, capacity), remaining * free))
    return torch.stack(out).reshape(logits.shape)


def _water_fill(weights: torch.Tensor, extra: float, capacity: torch.Tensor) -> torch.Tensor:
    """Real allocation a_p in [0, capacity_p] with sum a = min(extra, sum capacity), proportional to
    ``weights`` where not capped; the excess of capped pixels goes to the others; uniform over the
    pixels left when no positive weight remains. All (M,) float64."""
    allocation = torch.zeros_like(weights)
    remaining = min(float(extra), float(capacity.sum()))
    free = capacity > 0
    while remaining > 1e-9 and bool(free.any()):
        w = torch.where(free, weights, torch.zeros_like(weights))
        if float(w.sum()) <= 0:                      # only zero-importance pixels left: spread uniformly
            w = free.to(weights.dtype)
        share = remaining * w / w.sum()
        room = capacity - allocation
        capped = free & (share >= room)
        if not bool(capped.any()):
            allocation += share
            break
        remaining -= float(room[capped].sum())
        allocation[capped] = capacity[capped]
        free &= ~capped
    return allocation


def normalize_sample_map(importance: torch.Tensor, budget: float, max_count: int, *, minimum: int = 0,
                         rounding: str = "largest_remainder", seed: int = 0) -> torch.Tensor:
    """Eq. 2: a non-negative (H, W) importance map -> an integer (H, W) int64 sample map.

    importance: w_p >= 0 (e.g. ``exp(s)`` of a network, or a variance estimate); all zeros means uniform.
    budget: average spp n (float). max_count: available layers per pixel (S_avail). minimum: samples every
    pixel gets first (0 as in the paper; 1 for DASR's initial pass), counted in the budget. Guarantees
    ``minimum <= k <= max_count`` and ``k.sum() <= budget_total(budget, H W)``; it equals that total unless
    every pixel is at ``max_count``. Rounding: see the module docstring. BudgetError on invalid input.
    """
    if importance.dim() != 2:
        raise BudgetError(f"importance must be (H, W), got shape {tuple(importance.shape)}")
    if rounding not in ROUNDING_SCHEMES:
        raise BudgetError(f"rounding must be one of {ROUNDING_SCHEMES}, got {rounding!r}")
    weights = importance.detach().to(torch.float64).flatten()
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise BudgetError("importance must be finite and >= 0 everywhere")
    pixels = weights.numel()
    total = budget_total(budget, pixels)
    if not 0 <= minimum <= max_count:
        raise BudgetError(f"minimum {minimum} must be in 0..max_count = {max_count}")
    if minimum * pixels > total:
        raise BudgetError(f"budget {budget} spp ({total} samples for {pixels} pixels) is below the minimum "
                          f"of {minimum} sample(s) per pixel")
    capacity = torch.full_like(weights, float(max_count - minimum))
    real = minimum + _water_fill(weights, total - minimum * pixels, capacity)
    counts = torch.floor(real + 1e-9).clamp_(minimum, max_count)
    excess = int(counts.sum().item()) - min(total, pixels * max_count)
    if excess > 0:                     # the 1e-9 snap rounded up too often: take back the smallest overshoots
        overshoot = torch.where(counts > minimum, real - counts, torch.full_like(real, math.inf))
        counts[torch.sort(overshoot, stable=True).indices[:excess]] -= 1
    fraction = (real - counts).clamp_(0.0, 1.0)
    fraction[counts >= max_count] = -1.0                       # never above the available layers
    target = min(total, pixels * max_count)
    remainder = int(target - counts.sum().item())
    if remainder > 0:
        if rounding == "largest_remainder":
            order = torch.sort(fraction, descending=True, stable=True).indices
            chosen = order[:remainder]
        else:
            chosen = _systematic(fraction.clamp(min=0.0), remainder, seed)
        chosen = chosen[fraction[chosen] >= 0]
        counts[chosen] += 1
    return counts.to(torch.int64).reshape(importance.shape)


def _systematic(fraction: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """Indices of ``count`` pixels chosen by systematic sampling of ``fraction`` (M,) along a seeded random
    permutation: pixel p is chosen with probability fraction_p when the fractions sum to ``count``."""
    generator = torch.Generator().manual_seed(int(seed))
    permutation = torch.randperm(fraction.numel(), generator=generator)
    offset = float(torch.rand((), generator=generator, dtype=torch.float64))
    permuted = fraction[permutation]
    cumulative = torch.cumsum(permuted, 0)
    hits = torch.floor(cumulative + offset) - torch.floor(cumulative - permuted + offset)
    chosen = permutation[hits > 0]
    if chosen.numel() > count:                                 # float error: drop the smallest fractions
        chosen = chosen[torch.sort(fraction[chosen], descending=True, stable=True).indices[:count]]
    elif chosen.numel() < count:                               # float error: add the largest unchosen ones
        rest = torch.ones_like(fraction, dtype=torch.bool)
        rest[chosen] = False
        candidates = torch.nonzero(rest & (fraction > 0)).flatten()
        extra = candidates[torch.sort(fraction[candidates], descending=True, stable=True).indices]
        chosen = torch.cat([chosen, extra[:count - chosen.numel()]])
    return chosen


def _check_counts(layers: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    if layers.dim() != 4:
        raise BudgetError(f"layers must be (S, C, H, W), got shape {tuple(layers.shape)}")
    if counts.shape != layers.shape[-2:] or counts.dtype.is_floating_point or counts.dtype == torch.bool:
        raise BudgetError(f"counts must be an integer (H, W) = {tuple(layers.shape[-2:])} map, got "
                          f"{counts.dtype} {tuple(counts.shape)}")
    if counts.numel() and (int(counts.min()) < 0 or int(counts.max()) > layers.shape[0]):
        raise BudgetError(f"counts must be in 0..{layers.shape[0]} (available layers), got "
                          f"{int(counts.min())}..{int(counts.max())}")
    return torch.arange(layers.shape[0], device=layers.device).view(-1, 1, 1) < counts.to(layers.device)


def masked_samples(layers: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(S, C, H, W) layers, integer (H, W) counts k -> (layers with every layer s >= k_p zeroed at pixel p,
    (S, 1, H, W) bool mask of the kept layers). Values beyond k (even NaN) never leak into the result."""
    mask = _check_counts(layers, counts).unsqueeze(1)
    return torch.where(mask, layers, torch.zeros((), dtype=layers.dtype)), mask


def gather_mean(layers: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """(C, H, W) per-pixel mean of the first k_p of the (S, C, H, W) layers; 0 where k_p = 0.

    counts: integer (H, W), 0 <= k <= S. Values are summed in layer order, as a direct mean would.
    """
    kept, _ = masked_samples(layers, counts)
    divisor = counts.to(device=layers.device, dtype=layers.dtype).clamp(min=1)
    return kept.sum(dim=0) / divisor


def realised_spp(sample_map: torch.Tensor) -> float:
    """Mean samples per pixel actually used by an (H, W) sample map."""
    return float(sample_map.to(torch.float64).mean())


def budget_problems(sample_maps: Sequence, budget: float, frames: Sequence[int], where: str = "") -> list[str]:
    """One message per frame whose (H, W) sample map spends more than ``budget`` spp on average (its sum
    above :func:`budget_total`), naming ``where`` (e.g. the row and scene) and the frame index."""
    problems = []
    prefix = f"{where}: " if where else ""
    for frame, sample_map in zip(frames, sample_maps):
        counts = torch.as_tensor(sample_map)
        used, allowed = int(counts.to(torch.int64).sum()), budget_total(budget, counts.numel())
        if used > allowed:
            problems.append(f"{prefix}frame {int(frame)} uses {used} samples for {counts.numel()} pixels "
                            f"(mean {used / counts.numel():.6g} spp), above the budget of {budget:g} spp "
                            f"({allowed} samples)")
    return problems


class _RenderAdaptive(torch.autograd.Function):
    """Forward: (N, H, W) integer counts -> (N, C, H, W) ``transform`` of the means of the first k layers.
    Backward: the renderer gradient of the module docstring, taken after ``transform``, to the (N, H, W) real
    density (counts are not differentiated)."""

    @staticmethod
    def forward(ctx, density: torch.Tensor, layers: torch.Tensor, counts: torch.Tensor,
                transform: Callable[[torch.Tensor], torch.Tensor] | None) -> torch.Tensor:
        means = torch.stack([gather_mean(layer, count) for layer, count in zip(layers, counts)])
        ctx.save_for_backward(layers, counts, means)
        ctx.transform = transform
        return means if transform is None else transform(means)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        layers, counts, means = ctx.saved_tensors
        derivative = renderer_derivative(layers, counts, means, transform=ctx.transform)
        return derivative.mul(grad).sum(dim=1), None, None, None


def renderer_derivative(layers: torch.Tensor, counts: torch.Tensor, means: torch.Tensor,
                        transform: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """(N, C, H, W) dI/dk of the module docstring: layers (N, S, C, H, W), integer counts k (N, H, W),
    means I_k (N, C, H, W). With ``transform`` (elementwise, e.g. the network's input encoding) the difference
    is taken after it, T(I_{k+1}) - T(I_k): the change of what the network sees, bounded by T's range, instead
    of T'(I_k) (I_{k+1} - I_k), which a firefly after dark samples makes enormous where T is steep."""
    available = layers.shape[1]
    k = counts.to(torch.int64)
    at_end = k >= available
    index = torch.where(at_end, torch.full_like(k, available - 1), k)           # layer x_{k+1} (0-based k)
    gather_index = index[:, None, None].expand(-1, 1, layers.shape[2], -1, -1)
    next_layer = torch.gather(layers, 1, gather_index)[:, 0]                     # (N, C, H, W)
    kf = k.to(layers.dtype)[:, None]
    after = means + (next_layer - means) / (kf + 1.0)                            # I_{k+1}
    # k = S: the backward difference I_S - I_{S-1}, with I_{S-1} = (S I_S - x_S) / (S - 1) (I_0 = 0)
    if available > 1:
        before = (available * means - next_layer) / (available - 1)
    else:
        before = torch.zeros_like(means)
    low = torch.where(at_end[:, None], before, means)
    high = torch.where(at_end[:, None], means, after)
    if transform is None:
        return high - low
    return transform(high) - transform(low)


def render_adaptive(density: torch.Tensor, layers: torch.Tensor, budget: float, *, minimum: int = 0,
                    rounding: str = "largest_remainder", seed: int = 0,
                    transform: Callable[[torch.Tensor], torch.Tensor] | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Training's renderer: density (N, H, W) real samples per pixel (e.g. :func:`density`), layers
    (N, S, C, H, W) stored 1-spp samples -> (means (N, C, H, W), counts (N, H, W) int64), the means passed
    through ``transform`` when given. Counts per image by :func:`normalize_sample_map` (never above the
    budget); gradient to ``density`` as documented above (after ``transform``, :func:`renderer_derivative`)."""
    # Eq. 2's weights are the samples above the minimum (DASR's initial pass), so a density built as
    # minimum + (n - minimum) M softmax(s) is reproduced up to rounding.
    counts = torch.stack([normalize_sample_map((d.detach() - minimum).clamp_min(0), budget, layers.shape[1],
                                               minimum=minimum,
                                               rounding=rounding, seed=seed + i) for i, d in enumerate(density)])
    return _RenderAdaptive.apply(density, layers, counts, transform), counts
