"""benchmarks/crop_consistency.py: windows tile the frame, and the gap (whole-frame run minus window run) is
exactly 0 for a pointwise method and negative for one that reads the whole frame's statistics."""
from __future__ import annotations

import torch

from denoisers import registry
from tests.benchmark_modules import load_benchmark

crop_consistency = load_benchmark("crop_consistency")


def _frame(height: int = 40, width: int = 56, seed: int = 0) -> registry.Frame:
    generator = torch.Generator().manual_seed(seed)
    radiance = torch.rand(4, 3, height, width, generator=generator) * 2.0
    return registry.Frame(samples={"radiance": radiance},
                          pixel={"valid": torch.ones(1, height, width)})


class _GlobalMean(registry.Denoiser):
    """Output: the image mean everywhere -- depends on how much of the image it sees."""

    def denoise(self, frame: registry.Frame) -> torch.Tensor:
        mean = frame.samples["radiance"].mean(dim=(0, 2, 3))
        return mean[:, None, None].expand(3, frame.height, frame.width).clone()


def test_windows_cover_the_frame_flush_with_its_edges() -> None:
    corners = crop_consistency.windows(40, 56, 16)
    assert corners == [(y, x) for y in (0, 16, 24) for x in (0, 16, 32, 40)]
    covered = torch.zeros(40, 56, dtype=torch.bool)
    for y, x in corners:
        covered[y:y + 16, x:x + 16] = True
    assert covered.all()
    assert crop_consistency.windows(16, 16, 16) == [(0, 0)]


def test_crop_frame_cuts_every_buffer() -> None:
    frame = _frame()
    window = crop_consistency.crop_frame(frame, 8, 12, 16)
    assert window.samples["radiance"].shape == (4, 3, 16, 16)
    assert window.pixel["valid"].shape == (1, 16, 16)
    assert torch.equal(window.samples["radiance"], frame.samples["radiance"][..., 8:24, 12:28])


def test_pointwise_method_has_no_gap() -> None:
    frame = _frame()
    reference = frame.samples["radiance"].mean(dim=0).numpy() * 0.9
    scores = crop_consistency.frame_gaps(registry.build("noisy"), frame, reference, 16)
    assert len(scores) == 12
    assert all(whole == alone for whole, alone in scores)


def test_frame_dependent_method_shows_a_gap() -> None:
    # Left half dark, right half bright: the whole-frame mean suits neither half, each window's own mean does.
    frame = _frame()
    frame.samples["radiance"][..., :28] *= 0.05
    reference = frame.samples["radiance"].mean(dim=0).numpy()
    scores = crop_consistency.frame_gaps(_GlobalMean(), frame, reference, 16)
    assert sum(whole - alone for whole, alone in scores) / len(scores) < -1.0
