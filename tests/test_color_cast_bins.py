"""benchmarks/color_cast.py --brightness-bins: output / reference luminance per bin of reference luminance,
against hand-built frames whose bins are known."""
from __future__ import annotations


import numpy as np

from tests.benchmark_modules import load_benchmark

color_cast = load_benchmark("color_cast")


def test_bins_split_at_the_reference_percentiles() -> None:
    # 2 frames of 10 x 10 grey pixels with luminance 1..200: p50 = 100.5, p90 = 180.1, p99 = 198.01.
    luminance = np.arange(1, 201, dtype=np.float64).reshape(2, 1, 10, 10)
    references = np.repeat(luminance, 3, axis=1)
    output = references.copy()
    output[references <= 100] *= 2.0          # the darker half doubled
    output[references > 199] *= 0.5           # the brightest pixel (200) halved; p99 bin = {199, 200}
    ratios = color_cast.brightness_bin_ratios(list(output), references)
    np.testing.assert_allclose(ratios, [2.0, 1.0, 1.0, (199 + 100) / (199 + 200)])


def test_darker_half_is_split_by_albedo() -> None:
    # 1 frame of 2 x 4 pixels: luminance 1..8; the darker half is 1..4, of which 1 and 2 have albedo 0.05.
    references = np.repeat(np.arange(1, 9, dtype=np.float64).reshape(1, 1, 2, 4), 3, axis=1)
    albedo = np.array([[[0.05, 0.05, 0.5, 0.5], [0.5, 0.5, 0.5, 0.5]]])
    output = references.copy()
    output[:, :, 0, 2:] *= 3.0                # pixels 3 and 4: a lit surface in shadow made 3x too bright
    ratios = color_cast.dark_half_ratios(list(output), references, albedo)
    np.testing.assert_allclose(ratios, [3.0, 1.0])


def test_psnr_line_is_the_mean_per_frame_psnr(capsys) -> None:
    """--psnr: the mean over frames of the evaluation's own PSNR (two frames with different errors); no PSNR
    without the references."""
    from denoisers.metrics import psnr

    references = np.ones((2, 3, 4, 4))
    outputs = [references[0] + 0.1, references[1] + 0.01]
    color_cast.report("train_024", "model", outputs, np.ones(3), None, references)
    line = capsys.readouterr().out
    expected = (psnr(outputs[0], references[0]) + psnr(outputs[1], references[1])) / 2
    assert f"PSNR {expected:.2f} dB" in line
    color_cast.report("train_024", "model", outputs, np.ones(3), None)
    assert "PSNR" not in capsys.readouterr().out
