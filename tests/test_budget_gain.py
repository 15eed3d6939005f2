"""The doubling-gain estimator (denoisers.report.budget) on synthetic power-law validation curves, whose gain
from doubling the budget is known in closed form: b T^-c (1 - 2^-c)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from denoisers.report.budget import doubling_gain, fit_power_law


@pytest.mark.parametrize("p_inf, b, c", [(32.0, 40.0, 0.5), (28.0, 5.0, 0.3), (35.0, 300.0, 1.0)])
def test_the_gain_of_an_exact_power_law_is_recovered(p_inf: float, b: float, c: float) -> None:
    steps = np.arange(100, 4001, 100, dtype=np.float64)
    psnr = p_inf - b * steps ** -c
    expected = b * 4000.0 ** -c * (1 - 2 ** -c)
    assert doubling_gain(steps, psnr) == pytest.approx(expected, rel=1e-3)
    assert fit_power_law(steps, psnr) == pytest.approx((p_inf, b, c), rel=1e-3)


def test_noise_is_averaged_out() -> None:
    """Validation noise of 0.05 dB on a curve that would still gain 0.196 dB: the median of 20 noisy fits is
    within 0.1 dB of it (seeded)."""
    rng = np.random.default_rng(3)
    steps = np.arange(200, 8001, 200, dtype=np.float64)
    clean = 31.0 - 60.0 * steps ** -0.5
    expected = 60.0 * 8000.0 ** -0.5 * (1 - 2 ** -0.5)
    estimates = [doubling_gain(steps, clean + rng.normal(0.0, 0.05, len(steps))) for _ in range(20)]
    assert expected == pytest.approx(0.196, abs=1e-3)
    assert abs(np.median(estimates) - expected) < 0.1


def test_a_flat_curve_gains_nothing_and_too_few_points_give_nan() -> None:
    steps = np.arange(100, 2001, 100, dtype=np.float64)
    assert doubling_gain(steps, np.full(len(steps), 30.0)) == pytest.approx(0.0, abs=1e-3)
    assert math.isnan(doubling_gain([100, 200, 300], [20.0, 21.0, 21.5]))
    assert math.isnan(doubling_gain(steps, np.full(len(steps), np.nan)))
