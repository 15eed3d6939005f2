"""Training losses of the learned denoisers.

The RAE loss (Chaitanya et al. 2017, §4.4) on sequences of predicted and target images P, T of shape
(N, T, C, H, W) -- both already in the network's working space, i.e. colour raised to the power 0.2
("Our implementation raises both the input and target images into power 0.2 as a preprocess"):

    L = sum_t f_t (w_s L_s(t) + w_g L_g(t) + w_t L_t(t))

* spatial L1      L_s(t) = mean |P_t - T_t|
* gradient L1     L_g(t) = mean |LoG(P_t) - LoG(T_t)|, LoG = Laplacian of Gaussian, sigma 1.5 (the HFEN
                  filter of Ravishankar & Bresler 2011: 15 x 15 taps, zero sum)
* temporal L1     L_t(t) = mean |(P_t - P_{t-1}) - (T_t - T_{t-1})| (backward finite difference in time;
                  0 for the first frame, which has no predecessor)
* (w_s, w_g, w_t) = (0.8, 0.1, 0.1)
* f_t: "a Gaussian curve" over the frames, (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1) for 7 frames;
  those numbers are exp(-(t - (T - 1))^2 / (2 * 2^2)) to the printed precision, i.e. a Gaussian of
  sigma 2 frames centred on the last frame, which is how other sequence lengths are weighted here.

Means run over the batch, channels and pixels. The frame weights are applied as printed (not
normalised to sum 1), so the total for 7 frames is 3.004 times a per-frame average loss.
"""
from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache

import torch

#: (w_s, w_g, w_t) of §4.4.
RAE_LOSS_WEIGHTS: dict[str, float] = {"spatial": 0.8, "gradient": 0.1, "temporal": 0.1}
#: The per-frame weights printed in §4.4 for a 7-frame training sequence.
PAPER_FRAME_WEIGHTS_7: tuple[float, ...] = (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1.0)
#: Width (frames) of the Gaussian that reproduces the printed weights.
FRAME_WEIGHT_SIGMA = 2.0
#: HFEN's Laplacian-of-Gaussian parameters (sigma "recommended" in §4.4; 15 x 15 is HFEN's filter size).
LOG_SIGMA = 1.5
LOG_SIZE = 15


def frame_weights(n_frames: int, sigma: float = FRAME_WEIGHT_SIGMA) -> torch.Tensor:
    """(T,) weights exp(-(t - (T - 1))^2 / (2 sigma^2)): 1 on the last frame, decaying towards the first."""
    if n_frames < 1:
        raise ValueError(f"need at least one frame, got {n_frames}")
    t = torch.arange(n_frames, dtype=torch.float64)
    return torch.exp(-((t - (n_frames - 1)) ** 2) / (2.0 * sigma**2)).float()


@lru_cache(maxsize=8)
def _log_kernel64(sigma: float, size: int) -> torch.Tensor:
    radius = (size - 1) / 2.0
    offsets = torch.arange(size, dtype=torch.float64) - radius
    y, x = torch.meshgrid(offsets, offsets, indexing="ij")
    r2 = x**2 + y**2
    gauss = torch.exp(-r2 / (2 * sigma**2))
    gauss = gauss / gauss.sum()
    kernel = gauss * (r2 - 2 * sigma**2) / sigma**4
    # Zero sum (the discrete kernel is truncated): a constant image then has no response.
    return kernel - kernel.mean()


def _check_log_size(size: int) -> None:
    if size % 2 != 1 or size < 3:
        raise ValueError(f"LoG kernel size must be odd and >= 3, got {size}")


def log_kernel(sigma: float = LOG_SIGMA, size: int = LOG_SIZE) -> torch.Tensor:
    """(size, size) Laplacian-of-Gaussian kernel, Gaussian normalised to sum 1, then shifted to zero sum.

    Same construction as MATLAB's ``fspecial('log', size, sigma)``, which HFEN uses. Odd ``size`` only.
    """
    _check_log_size(size)
    return _log_kernel64(float(sigma), int(size)).float()


@lru_cache(maxsize=16)
def _log_operators(sigma: float, size: int, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, H, H) row and (R, W, W) column operators with LoG(X) = sum_r A_r X B_r^T, replicate borders folded in.

    The kernel is gauss * (x^2 + y^2 - 2 sigma^2) minus a constant: two separable terms plus a rank-1 shift,
    so its SVD has (at most) three non-zero singular values and the 2-D convolution is three pairs of 1-D
    ones. As matrices they run through the GEMM in both directions; a 15 x 15 single-channel convolution's
    backward pass took about half of the RAE's training step on this CPU.
    """
    kernel = _log_kernel64(sigma, size)
    u, s, vh = torch.linalg.svd(kernel)
    rank = int((s > s[0] * 1e-9).sum())
    radius = size // 2

    def operators(factors: torch.Tensor, n: int) -> torch.Tensor:
        # out[i] = sum_d factor[d] * x[clamp(i + d - radius)]: the 1-D correlation with replicated edges.
        rows = torch.arange(n).repeat_interleave(size)
        cols = (torch.arange(n)[:, None] + torch.arange(size)[None] - radius).clamp(0, n - 1).reshape(-1)
        out = torch.zeros(factors.shape[0], n, n, dtype=torch.float64)
        out.index_put_((torch.arange(factors.shape[0])[:, None], rows[None], cols[None]),
                       factors.repeat(1, n), accumulate=True)
        return out

    row_factors = (u[:, :rank] * s[:rank]).T          # (R, size): singular values folded into the rows
    col_factors = vh[:rank]                           # (R, size)
    return operators(row_factors, height).float(), operators(col_factors, width).float()


def laplacian_of_gaussian(x: torch.Tensor, sigma: float = LOG_SIGMA, size: int = LOG_SIZE) -> torch.Tensor:
    """LoG-filter every channel of (..., C, H, W) independently; borders replicate the edge pixels.

    Replicate padding keeps the response of a constant image exactly at the kernel's (zero) sum, so the
    gradient loss does not see a fake edge at the crop border. Equal (to float rounding) to ``F.conv2d`` of
    the replicate-padded image with :func:`log_kernel`, computed as the kernel's rank-3 separable form.
    """
    _check_log_size(size)
    rows, cols = _log_operators(float(sigma), int(size), x.shape[-2], x.shape[-1])
    rows, cols = rows.to(dtype=x.dtype, device=x.device), cols.to(dtype=x.dtype, device=x.device)
    filtered = rows @ (x.unsqueeze(-3) @ cols.transpose(-1, -2))     # (..., C, R, H, W)
    return filtered.sum(dim=-3)


def _per_frame_mean(x: torch.Tensor) -> torch.Tensor:
    """(N, T, ...) -> (T,) mean over everything but the frame axis."""
    return x.transpose(0, 1).reshape(x.shape[1], -1).mean(dim=1)


def _check_sequences(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 5:
        raise ValueError(f"loss needs pred and target of the same shape (N, T, C, H, W), got "
                         f"{tuple(pred.shape)} and {tuple(target.shape)}")


def spatial_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(T,) per-frame L_s = mean |P - T| of (N, T, C, H, W) sequences."""
    _check_sequences(pred, target)
    return _per_frame_mean((pred - target).abs())


def gradient_l1(pred: torch.Tensor, target: torch.Tensor, sigma: float = LOG_SIGMA,
                size: int = LOG_SIZE) -> torch.Tensor:
    """(T,) per-frame HFEN term L_g = mean |LoG(P) - LoG(T)| (LoG is linear: filtered once on P - T)."""
    _check_sequences(pred, target)
    return _per_frame_mean(laplacian_of_gaussian(pred - target, sigma, size).abs())


def temporal_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(T,) per-frame L_t = mean |dP/dt - dT/dt|, backward differences; frame 0 gets 0 (no predecessor)."""
    _check_sequences(pred, target)
    difference = pred - target
    per_frame = torch.zeros(pred.shape[1], dtype=pred.dtype, device=pred.device)
    if pred.shape[1] > 1:
        # d(P)/dt - d(T)/dt = d(P - T)/dt
        per_frame = torch.cat([per_frame[:1], _per_frame_mean((difference[:, 1:] - difference[:, :-1]).abs())])
    return per_frame


def rae_loss(pred: torch.Tensor, target: torch.Tensor, weights: Mapping[str, float] | None = None,
             per_frame: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The §4.4 training loss of (N, T, C, H, W) sequences in the 0.2-power space.

    weights: {'spatial', 'gradient', 'temporal'} (default 0.8 / 0.1 / 0.1; a zero weight skips the term);
    per_frame: (T,) frame weights (default :func:`frame_weights`). Returns (scalar loss, {term: scalar
    frame-weighted value of that term before its loss weight}).
    """
    _check_sequences(pred, target)
    weights = dict(RAE_LOSS_WEIGHTS if weights is None else weights)
    unknown = set(weights) - set(RAE_LOSS_WEIGHTS)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; known: {sorted(RAE_LOSS_WEIGHTS)}")
    f = frame_weights(pred.shape[1]) if per_frame is None else per_frame
    f = f.to(dtype=pred.dtype, device=pred.device)
    if f.shape != (pred.shape[1],):
        raise ValueError(f"per-frame weights must have shape ({pred.shape[1]},), got {tuple(f.shape)}")
    term_functions = {"spatial": spatial_l1, "gradient": gradient_l1, "temporal": temporal_l1}
    total = pred.new_zeros(())
    terms: dict[str, torch.Tensor] = {}
    for name, weight in weights.items():
        if weight == 0:
            continue
        value = (f * term_functions[name](pred, target)).sum()
        terms[name] = value.detach()
        total = total + weight * value
    return total, terms

