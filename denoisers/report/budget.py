"""What a larger training budget would buy, estimated from a model's own validation curve.

A learned model's validation PSNR over training steps t is fitted with a saturating power law

    psnr(t) = p_inf - b * t^(-c),     b > 0, 0 < c <= MAX_EXPONENT,

the form learning curves of networks follow over the range of budgets this harness trains (the loss falling
as a power of the steps towards a floor). Its prediction for doubling the budget T is

    gain(T) = psnr(2T) - psnr(T) = b * T^(-c) * (1 - 2^(-c))   (dB),

a measurement shown beside the claims, not a threshold. The fit uses the validations after the first
``WARMUP_FRACTION`` of the steps (the early transient is not a power law) and needs at least ``MIN_POINTS`` of
them; otherwise, or if the least-squares fit fails, the estimate is NaN.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

WARMUP_FRACTION = 0.1
MIN_POINTS = 5
MAX_EXPONENT = 3.0


def power_law(t: np.ndarray, p_inf: float, b: float, c: float) -> np.ndarray:
    """p_inf - b t^-c for steps t (> 0)."""
    return p_inf - b * np.power(t, -c)


def fit_power_law(steps: Sequence[float], psnr: Sequence[float]) -> tuple[float, float, float] | None:
    """Least-squares (p_inf, b, c) of :func:`power_law` to validations after the warm-up, or None (too few
    points, non-finite values, or no convergence)."""
    from scipy.optimize import curve_fit

    t = np.asarray(steps, np.float64)
    y = np.asarray(psnr, np.float64)
    keep = np.isfinite(t) & np.isfinite(y) & (t > 0)
    t, y = t[keep], y[keep]
    if not len(t):
        return None
    later = t > WARMUP_FRACTION * t.max()
    t, y = t[later], y[later]
    if len(t) < MIN_POINTS:
        return None
    span = max(float(y.max() - y.min()), 1e-3)
    start = (float(y.max()) + span, span * float(t.min()) ** 0.5, 0.5)
    try:
        params, _ = curve_fit(power_law, t, y, p0=start, bounds=([-np.inf, 0.0, 1e-3], [np.inf, np.inf, MAX_EXPONENT]),
                              maxfev=20_000)
    except (RuntimeError, ValueError):
        return None
    return float(params[0]), float(params[1]), float(params[2])


def doubling_gain(steps: Sequence[float], psnr: Sequence[float], budget: float | None = None) -> float:
    """Predicted validation-PSNR gain (dB) of training to 2 x ``budget`` steps instead of ``budget`` (default: the
    last step of the curve), from :func:`fit_power_law`; NaN when it cannot be fitted."""
    params = fit_power_law(steps, psnr)
    if params is None:
        return math.nan
    _, b, c = params
    total = float(budget if budget is not None else np.nanmax(np.asarray(steps, np.float64)))
    return float(b * total ** (-c) * (1.0 - 2.0 ** (-c)))
