"""Image and temporal error metrics for linear HDR radiance, with the formulas and their sources.

Inputs are numpy arrays or torch tensors of linear HDR radiance, either one frame (C, H, W) or a
sequence (T, C, H, W), with C = 3 colour channels (any C for all metrics except FLIP). Everything is
computed in float64 numpy; results are Python floats (frame metrics) or numpy arrays (per-frame
temporal metrics).

Spaces and constants (each decision is repeated in the function's docstring):

* ``tau`` (Isik et al. 2021, Eq. 15): tau(x) = (x / (1 + x))^(1/2.4) for x >= 0; negative values are
  clamped to 0 first, since Eq. 15 is defined on R+ only. PSNR, SSIM, RMSE, tPSNR and FLIP use tau
  images, whose range is [0, 1].
* relMSE, SMAPE and TRMAE are computed on linear HDR radiance, as their papers define them.
* Per-channel averaging everywhere: Isik's "1/3 E_xyt ||.||" with "the factor 3 accounts for colour
  channels" is read as the mean over pixels, frames and channels of per-channel ratios (Eq. 11, 16).
  The literal reading with vector L1 norms in both numerator and denominator would make the 1/3
  scale every ratio down instead of averaging channels, so it cannot be what the text says it is.

Invalid input never yields a NaN score: mismatched shapes raise ``ValueError`` naming both shapes,
and NaN/Inf values raise :class:`NonFiniteError` (a ``ValueError``) naming the metric and counting
the bad values, so the evaluation can count and report them.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

# torch is not imported here: the scoring jobs never hold a tensor, and its import costs about 1.7 s per job.
ArrayLike = Any   # np.ndarray | torch.Tensor


def _is_tensor(x: Any) -> bool:
    """True for a torch tensor; without importing torch (a tensor exists only if torch was imported)."""
    module = sys.modules.get("torch")
    return module is not None and isinstance(x, module.Tensor)

TAU_GAMMA = 2.4            # Isik 2021 Eq. 15
RELMSE_EPS = 0.01          # relMSE denominator guard (Hasselgren 2020 gives none; 0.01 is the usual value)
SMAPE_EPS = 0.01           # Isik 2021 Eq. 11 states no value; we reuse the eps of Eq. 16
TRMAE_EPS = 0.01           # Isik 2021 Eq. 16
SSIM_SIGMA = 1.5           # Wang et al. 2004 gaussian window
SSIM_RADIUS = 5            # 11-tap window: int(3.5 * sigma + 0.5), as scipy/skimage truncate it
SSIM_K1, SSIM_K2 = 0.01, 0.03
DATA_RANGE = 1.0           # peak value of tau images


@dataclass(frozen=True)
class MetricInfo:
    """What a metric measures: its name, its direction, a one-line description and its formula."""

    name: str
    higher_is_better: bool
    description: str
    formula: str
    temporal: bool = False  # True: per-frame values from temporal differences (temporal_metrics)


class NonFiniteError(ValueError):
    """A metric received NaN/Inf values; ``count`` of them in ``which`` ('pred' or 'ref')."""

    def __init__(self, metric: str, which: str, n_nan: int, n_inf: int, size: int) -> None:
        self.metric, self.which, self.n_nan, self.n_inf, self.size = metric, which, n_nan, n_inf, size
        self.count = n_nan + n_inf
        super().__init__(f"{metric}: {which} has {self.count} non-finite values "
                         f"({n_nan} NaN, {n_inf} Inf) out of {size}")


def count_nonfinite(x: ArrayLike) -> int:
    """Number of NaN/Inf values in an array or tensor."""
    return int(np.count_nonzero(~np.isfinite(_as_numpy(x))))


# --------------------------------------------------------------------------------------------- input
def _as_numpy(x: ArrayLike) -> np.ndarray:
    if _is_tensor(x):
        return x.detach().to("cpu", sys.modules["torch"].float64).numpy()
    return np.asarray(x, dtype=np.float64)


def _prepare(metric: str, pred: ArrayLike, ref: ArrayLike, *, sequence: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert a (pred, ref) pair to float64 (N, C, H, W) arrays.

    sequence=False accepts (C, H, W) or (T, C, H, W); sequence=True requires (T, C, H, W).
    """
    p, r = _as_numpy(pred), _as_numpy(ref)
    if p.shape != r.shape:
        raise ValueError(f"{metric}: pred shape {tuple(p.shape)} does not match ref shape {tuple(r.shape)}")
    allowed = (4,) if sequence else (3, 4)
    if p.ndim not in allowed:
        expected = "(T, C, H, W)" if sequence else "(C, H, W) or (T, C, H, W)"
        raise ValueError(f"{metric}: expected {expected}, got shape {tuple(p.shape)}")
    if p.size == 0:
        raise ValueError(f"{metric}: empty input of shape {tuple(p.shape)}")
    for which, a in (("pred", p), ("ref", r)):
        bad = ~np.isfinite(a)
        if bad.any():
            n_nan = int(np.count_nonzero(np.isnan(a)))
            raise NonFiniteError(metric, which, n_nan, int(np.count_nonzero(bad)) - n_nan, a.size)
    if p.ndim == 3:
        p, r = p[None], r[None]
    return p, r


# ------------------------------------------------------------------------------------------- tonemap
def tonemap(x: ArrayLike) -> ArrayLike:
    """tau(x) = (max(x, 0) / (1 + max(x, 0)))^(1/2.4)  (Isik 2021 Eq. 15, Reinhard + gamma).

    Pointwise on any shape; linear HDR radiance in, display values in [0, 1] out. Returns the same
    kind as the input (torch tensor or numpy array, same dtype for floats). +Inf maps to 1 (the limit);
    NaN stays NaN.
    """
    if _is_tensor(x):
        import torch

        x = x if x.is_floating_point() else x.to(torch.float32)
        clamped = x.clamp_min(0.0)
        ratio = torch.where(torch.isposinf(clamped), torch.ones_like(clamped), clamped / (1.0 + clamped))
        return ratio.pow(1.0 / TAU_GAMMA)
    a = np.asarray(x)
    a = a if np.issubdtype(a.dtype, np.floating) else a.astype(np.float64)
    clamped = np.maximum(a, 0.0)
    with np.errstate(invalid="ignore"):
        ratio = np.where(np.isposinf(clamped), 1.0, clamped / (1.0 + clamped))
    return np.power(ratio, 1.0 / TAU_GAMMA).astype(a.dtype, copy=False)


def _mse_to_psnr(mse: np.ndarray | float) -> np.ndarray:
    """-10 log10(mse / peak^2) with peak 1; +inf for mse == 0."""
    with np.errstate(divide="ignore"):
        return -10.0 * np.log10(np.asarray(mse, dtype=np.float64) / DATA_RANGE**2)


# ------------------------------------------------------------------------------------ frame metrics
def _psnr(p: np.ndarray, r: np.ndarray) -> float:
    return float(_mse_to_psnr(np.mean((tonemap(p) - tonemap(r)) ** 2)))


def psnr(pred: ArrayLike, ref: ArrayLike) -> float:
    """PSNR in dB on tau-tonemapped radiance (Isik 2021 Eq. 14), peak 1.

    PSNR = -10 log10( (1/3) E_xyt ||tau(pred) - tau(ref)||_2^2 ): the MSE is averaged over pixels,
    channels and (for a (T, C, H, W) sequence) frames before the log. +inf for identical images.
    """
    return _psnr(*_prepare("psnr", pred, ref))


def _rmse(p: np.ndarray, r: np.ndarray) -> float:
    return float(np.sqrt(np.mean((tonemap(p) - tonemap(r)) ** 2)))


def rmse(pred: ArrayLike, ref: ArrayLike) -> float:
    """Root-mean-square error on tau-tonemapped radiance: sqrt(E_xytc (tau(pred) - tau(ref))^2).

    Chaitanya 2017 (Sec. 5.4, Fig. 8) does not state the space; its values (0.014-0.09) are those of
    display-range [0, 1] images. We use tau images, the same space as PSNR and SSIM, so that HDR
    outliers (emitters, fireflies up to hundreds of times the mean) cannot dominate the score.
    For one frame rmse = 10^(-psnr/20); the two differ once averaged across frames or scenes.
    """
    return _rmse(*_prepare("rmse", pred, ref))


def _relmse(p: np.ndarray, r: np.ndarray) -> float:
    return float(np.mean((p - r) ** 2 / (r**2 + RELMSE_EPS)))


def relmse(pred: ArrayLike, ref: ArrayLike) -> float:
    """Relative MSE on linear HDR radiance: E_xytc (pred - ref)^2 / (ref^2 + eps), eps = 0.01.

    Hasselgren 2020 (Sec. 3, Table 1) reports rMSE "measured on high dynamic range data" without a
    formula; we use the per-channel form (each colour channel relative to its own reference value,
    then averaged) with the customary eps = 0.01.
    """
    return _relmse(*_prepare("relmse", pred, ref))


def _smape(p: np.ndarray, r: np.ndarray) -> float:
    return float(np.mean(np.abs(p - r) / (np.abs(p) + np.abs(r) + SMAPE_EPS)))


def smape(pred: ArrayLike, ref: ArrayLike) -> float:
    """Symmetric mean absolute percentage error on linear HDR radiance (Isik 2021 Eq. 11).

    SMAPE = (1/3) E_xyt sum_c |pred_c - ref_c| / (|pred_c| + |ref_c| + eps), eps = 0.01 (Eq. 11 states
    no value; we use that of Eq. 16). Range [0, 1).
    """
    return _smape(*_prepare("smape", pred, ref))


def _gaussian_window() -> np.ndarray:
    offsets = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    weights = np.exp(-0.5 * (offsets / SSIM_SIGMA) ** 2)
    return weights / weights.sum()


def _filter_valid(x: np.ndarray) -> np.ndarray:
    """Separable gaussian filter over the last two axes, 'valid' part only: (..., H, W) -> (..., H-10, W-10)."""
    window = _gaussian_window()
    taps = window.size
    x = np.lib.stride_tricks.sliding_window_view(x, taps, axis=-1) @ window
    x = np.lib.stride_tricks.sliding_window_view(x, taps, axis=-2) @ window
    return x


def _ssim(p: np.ndarray, r: np.ndarray) -> float:
    taps = 2 * SSIM_RADIUS + 1
    if p.shape[-1] < taps or p.shape[-2] < taps:
        raise ValueError(f"ssim: images must be at least {taps}x{taps}, got shape {tuple(p.shape)}")
    x, y = tonemap(p), tonemap(r)
    # One filtering pass over the five local moments, stacked on a leading axis.
    mu_x, mu_y, e_xx, e_yy, e_xy = _filter_valid(np.stack([x, y, x * x, y * y, x * y]))
    var_x, var_y, cov_xy = e_xx - mu_x**2, e_yy - mu_y**2, e_xy - mu_x * mu_y
    c1, c2 = (SSIM_K1 * DATA_RANGE) ** 2, (SSIM_K2 * DATA_RANGE) ** 2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


def ssim(pred: ArrayLike, ref: ArrayLike) -> float:
    """Structural similarity (Wang et al. 2004) on tau-tonemapped radiance, data range 1.

    Gaussian window sigma 1.5 truncated to 11x11, K1 = 0.01, K2 = 0.03, population (biased) local
    variances; SSIM map = (2 mu_x mu_y + C1)(2 cov_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2))
    with C = (K * 1)^2, averaged over the pixels whose window lies inside the image (5-pixel border
    dropped), over channels and over frames. Equals skimage's structural_similarity(gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=0). Needs H, W >= 11.
    """
    return _ssim(*_prepare("ssim", pred, ref))


def _flip(p: np.ndarray, r: np.ndarray) -> float:
    import flip_evaluator

    if p.shape[1] != 3:
        raise ValueError(f"flip: needs 3 colour channels, got shape {tuple(p.shape)}")
    # flip_evaluator wants (H, W, 3) float32, C-contiguous, in [0, 1] for LDR.
    tp = np.ascontiguousarray(np.clip(tonemap(p), 0.0, 1.0).transpose(0, 2, 3, 1), dtype=np.float32)
    tr = np.ascontiguousarray(np.clip(tonemap(r), 0.0, 1.0).transpose(0, 2, 3, 1), dtype=np.float32)
    scores = [flip_evaluator.evaluate(tr[i], tp[i], "LDR", inputsRGB=True, applyMagma=False,
                                      computeMeanError=True)[1] for i in range(tp.shape[0])]
    return float(np.mean(scores))


def flip(pred: ArrayLike, ref: ArrayLike) -> float:
    """Mean LDR-FLIP error (Andersson et al. 2020) of tau-tonemapped images, via flip_evaluator.

    LDR-FLIP on tau(x) (treated as sRGB-encoded: tau's 1/2.4 gamma is close to the sRGB curve), default
    viewing conditions (67 pixels per degree). HDR-FLIP would tonemap again over many exposures and
    is much slower; using tau keeps FLIP in the same space as PSNR/SSIM. 0 = identical, 1 = worst.
    A (T, C, H, W) sequence gives the mean of the per-frame means.
    """
    return _flip(*_prepare("flip", pred, ref))


FRAME_METRICS: tuple[str, ...] = ("psnr", "ssim", "rmse", "relmse", "smape", "flip")
_FRAME_IMPLS = {"psnr": _psnr, "ssim": _ssim, "rmse": _rmse, "relmse": _relmse, "smape": _smape, "flip": _flip}


def frame_metrics(pred: ArrayLike, ref: ArrayLike) -> dict[str, float]:
    """All frame metrics of one (C, H, W) frame (or a (T, C, H, W) sequence, each metric pooled as
    documented on it): {'psnr', 'ssim', 'rmse', 'relmse', 'smape', 'flip'} -> float."""
    p, r = _prepare("frame_metrics", pred, ref)
    return {name: _FRAME_IMPLS[name](p, r) for name in FRAME_METRICS}


# --------------------------------------------------------------------------------- temporal metrics
def _skipped_frames(n_frames: int, warmup: int) -> np.ndarray:
    """(T,) bool: frames without a predecessor (frame 0) or inside the warm-up."""
    if int(warmup) != warmup or warmup < 0:
        raise ValueError(f"temporal metrics: warmup must be a non-negative integer, got {warmup!r}")
    index = np.arange(n_frames)
    return (index < 1) | (index < warmup)


def tpsnr(pred_seq: ArrayLike, ref_seq: ArrayLike, warmup: int = 0) -> np.ndarray:
    """Per-frame temporal PSNR (Hasselgren 2020 Sec. 3): PSNR of temporal finite differences.

    With d_t(x) = tau(x_t) - tau(x_{t-1}) (differences of tonemapped frames, Hasselgren applies both
    metrics "on the tonemapped output"): tPSNR_t = -10 log10 E_xyc (d_t(pred) - d_t(ref))^2, peak 1 as
    for PSNR. Input (T, C, H, W); returns (T,) float64 with NaN for frame 0 and frames < warmup,
    +inf where the prediction changes exactly as the reference does.
    """
    return _tpsnr(*_prepare("tpsnr", pred_seq, ref_seq, sequence=True), warmup)


def _tpsnr(p: np.ndarray, r: np.ndarray, warmup: int) -> np.ndarray:
    skipped = _skipped_frames(p.shape[0], warmup)
    out = np.full(p.shape[0], np.nan)
    if p.shape[0] > 1:
        tp, tr = tonemap(p), tonemap(r)
        mse = np.mean(((tp[1:] - tp[:-1]) - (tr[1:] - tr[:-1])) ** 2, axis=(1, 2, 3))
        out[1:] = _mse_to_psnr(mse)
    out[skipped] = np.nan
    return out


def trmae(pred_seq: ArrayLike, ref_seq: ArrayLike, warmup: int = 0) -> np.ndarray:
    """Per-frame temporal relative mean absolute error (Isik 2021 Eq. 16) on linear HDR radiance.

    TRMAE_t = (1/3) E_xy sum_c |dp_c - dr_c| / (|dr_c| + eps), eps = 0.01, with dp = pred_t - pred_{t-1}
    and dr = ref_t - ref_{t-1}. Input (T, C, H, W); returns (T,) float64, NaN for frame 0 and frames
    < warmup, 0 where the prediction changes exactly as the reference does.
    """
    return _trmae(*_prepare("trmae", pred_seq, ref_seq, sequence=True), warmup)


def _trmae(p: np.ndarray, r: np.ndarray, warmup: int) -> np.ndarray:
    skipped = _skipped_frames(p.shape[0], warmup)
    out = np.full(p.shape[0], np.nan)
    if p.shape[0] > 1:
        dp, dr = p[1:] - p[:-1], r[1:] - r[:-1]
        out[1:] = np.mean(np.abs(dp - dr) / (np.abs(dr) + TRMAE_EPS), axis=(1, 2, 3))
    out[skipped] = np.nan
    return out


TEMPORAL_METRICS: tuple[str, ...] = ("tpsnr", "trmae")


def temporal_metrics(pred_seq: ArrayLike, ref_seq: ArrayLike, warmup: int = 0) -> dict[str, np.ndarray]:
    """Per-frame temporal metrics of a (T, C, H, W) sequence: {'tpsnr', 'trmae'} -> (T,) float64.

    Frame t compares the change from frame t-1 to t; frame 0 and frames t < warmup are NaN.
    """
    p, r = _prepare("temporal_metrics", pred_seq, ref_seq, sequence=True)
    return {"tpsnr": _tpsnr(p, r, warmup), "trmae": _trmae(p, r, warmup)}


METRICS: dict[str, MetricInfo] = {info.name: info for info in (
    MetricInfo("psnr", True, "PSNR (dB) of tau-tonemapped radiance, peak 1 (Isik 2021 Eq. 14-15)",
               "-10 log10( E_xytc (tau(p) - tau(r))^2 ),  tau(x) = (x / (1 + x))^(1/2.4)"),
    MetricInfo("ssim", True, "SSIM of tau-tonemapped radiance, gaussian 11x11 sigma 1.5, channel mean",
               "mean SSIM map (2 mu_p mu_r + C1)(2 cov + C2) / ((mu_p^2 + mu_r^2 + C1)(var_p + var_r + C2))"),
    MetricInfo("rmse", False, "RMSE of tau-tonemapped radiance (Chaitanya 2017 Fig. 8 unit)",
               "sqrt( E_xytc (tau(p) - tau(r))^2 )"),
    MetricInfo("relmse", False, "relative MSE of linear HDR radiance, eps 0.01 (Hasselgren 2020 Table 1)",
               "E_xytc (p - r)^2 / (r^2 + 0.01)"),
    MetricInfo("smape", False, "symmetric MAPE of linear HDR radiance, eps 0.01 (Isik 2021 Eq. 11)",
               "E_xytc |p - r| / (|p| + |r| + 0.01)"),
    MetricInfo("flip", False, "mean LDR-FLIP error of tau-tonemapped images (flip_evaluator)",
               "mean_xy FLIP_LDR(tau(r), tau(p))"),
    MetricInfo("tpsnr", True, "per-frame PSNR of temporal differences of tau images (Hasselgren 2020 Sec. 3)",
               "-10 log10( E_xyc (d tau(p)_t - d tau(r)_t)^2 ),  d x_t = x_t - x_{t-1}", temporal=True),
    MetricInfo("trmae", False, "per-frame temporal relative MAE of linear radiance (Isik 2021 Eq. 16)",
               "E_xyc |d p_t - d r_t| / (|d r_t| + 0.01),  d x_t = x_t - x_{t-1}", temporal=True),
)}
