"""benchmarks/remodulation_ceiling.py: the oracle that re-modulates the exact illumination by a per-pixel albedo,
against a hand-built pixel footprint."""
from __future__ import annotations

import numpy as np
import pytest

from denoisers.metrics import psnr
from tests.benchmark_modules import load_benchmark

ceiling = load_benchmark("remodulation_ceiling")


def test_a_pixel_straddling_a_texture_edge_keeps_the_centre_albedo_error() -> None:
    # One pixel, half albedo 0.2 and half 0.8 under illumination 1: reference 0.5, footprint albedo 0.5. The
    # centre lies on the 0.8 half: re-modulating the exact illumination by 0.8 gives 0.8, not 0.5.
    reference = np.full((1, 3, 1, 1), 0.5)
    footprint = np.full((1, 3, 1, 1), 0.5)
    centre = np.full((1, 3, 1, 1), 0.8)
    out = ceiling.oracle(reference, footprint, centre, floor=0.01)
    np.testing.assert_allclose(out, 0.8)
    assert ceiling.mismatch_fraction(footprint, centre, floor=0.01) == 1.0


def test_a_uniform_albedo_costs_nothing_and_the_floor_bounds_the_divisor() -> None:
    rng = np.random.default_rng(0)
    reference = rng.uniform(0.0, 4.0, size=(2, 3, 8, 8))
    albedo = rng.uniform(0.05, 0.9, size=(2, 3, 8, 8))
    out = ceiling.oracle(reference, albedo, albedo, floor=0.01)
    np.testing.assert_allclose(out, reference)
    assert psnr(out[0], reference[0]) > 200.0          # rounding only
    assert ceiling.mismatch_fraction(albedo, albedo, floor=0.01) == 0.0
    # Black footprint (sky, dark material) and a lit centre: both albedos are floored before the ratio.
    out = ceiling.oracle(np.ones((1, 3, 1, 1)), np.zeros((1, 3, 1, 1)), np.full((1, 3, 1, 1), 0.5), floor=0.01)
    np.testing.assert_allclose(out, 50.0)


@pytest.mark.parametrize("mismatch, aliased", [(0.05, 0.0), (0.15, 1.0)])
def test_mismatch_fraction_counts_relative_differences_above_ten_percent(mismatch: float, aliased: float) -> None:
    footprint = np.full((1, 3, 2, 2), 0.4)
    assert ceiling.mismatch_fraction(footprint, footprint * (1.0 + mismatch), floor=0.01) == aliased
