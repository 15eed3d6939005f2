"""denoisers/crop_check.py: windows tile the frame, and the gap (whole-frame run minus window run) is exactly 0
for a pointwise method and negative for one that reads the whole frame's statistics."""
from __future__ import annotations

import math

import pytest
import torch

from denoisers import crop_check, registry


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
    corners = crop_check.windows(40, 56, 16)
    assert corners == [(y, x) for y in (0, 16, 24) for x in (0, 16, 32, 40)]
    covered = torch.zeros(40, 56, dtype=torch.bool)
    for y, x in corners:
        covered[y:y + 16, x:x + 16] = True
    assert covered.all()
    assert crop_check.windows(16, 16, 16) == [(0, 0)]


def test_crop_frame_cuts_every_buffer() -> None:
    frame = _frame()
    window = crop_check.crop_frame(frame, 8, 12, 16)
    assert window.samples["radiance"].shape == (4, 3, 16, 16)
    assert window.pixel["valid"].shape == (1, 16, 16)
    assert torch.equal(window.samples["radiance"], frame.samples["radiance"][..., 8:24, 12:28])


def test_pointwise_method_has_no_gap() -> None:
    frame = _frame()
    reference = frame.samples["radiance"].mean(dim=0).numpy() * 0.9
    scores = crop_check.frame_gaps(registry.build("noisy"), frame, reference, 16)
    assert len(scores) == 12
    assert all(whole == alone for whole, alone in scores)


def test_frame_dependent_method_shows_a_gap() -> None:
    # Left half dark, right half bright: the whole-frame mean suits neither half, each window's own mean does.
    frame = _frame()
    frame.samples["radiance"][..., :28] *= 0.05
    reference = frame.samples["radiance"].mean(dim=0).numpy()
    scores = crop_check.frame_gaps(_GlobalMean(), frame, reference, 16)
    assert sum(whole - alone for whole, alone in scores) / len(scores) < -1.0


def test_check_method_scores_every_scene_of_loaded_clips() -> None:
    from tests.test_training import synthetic_clip

    clips = [synthetic_clip(frames=6, layers=4, seed=s, scene=f"val_{s}") for s in (1, 2)]
    result = crop_check.check_method(registry.build("noisy"), clips, spp=2, crop=8, frames=3)
    assert set(result["scenes"]) == {"val_1", "val_2"}
    assert result["gap_db"] == 0.0 and result["crop"] == 8 and result["spp"] == 2
    scene = result["scenes"]["val_1"]
    assert scene["whole_psnr"] == scene["window_psnr"] and math.isfinite(scene["whole_psnr"])


def test_check_method_refuses_a_crop_as_large_as_the_frame() -> None:
    from tests.test_training import synthetic_clip

    with pytest.raises(ValueError, match="not larger than the crop 16"):
        crop_check.check_method(registry.build("noisy"), [synthetic_clip(scene="val")], spp=2, crop=16)
