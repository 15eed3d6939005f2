"""benchmarks/train_data_choice.py, arm key gbuffer_albedo_spp: the clips' G-buffer albedo is swapped for a rendered
footprint mean (the renderer is replaced by a stub here; remodulation_ceiling's own tests cover the oracle)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.dataset import Clip
from tests.benchmark_modules import load_benchmark

choice = load_benchmark("train_data_choice")


def _clip(scene: str, frames: int = 2) -> Clip:
    zeros = np.zeros((frames, 1, 4, 4), np.float32)
    return Clip(scene=scene, frames=list(range(frames)), samples={}, motion=np.zeros((frames, 2, 4, 4), np.float32),
                valid=zeros.astype(bool), gbuffer={"albedo": np.full((frames, 3, 4, 4), 0.8, np.float32),
                                                   "depth": zeros}, reference=None, meta=[{}] * frames)


def test_albedo_is_replaced_once_per_scene_and_other_buffers_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def stub(cfg: dict, scene_dir: Path, frames: list[int], spp: int, mode: str) -> np.ndarray:
        calls.append((scene_dir.name, spp, mode))
        return np.full((len(frames), 3, 4, 4), 0.5, np.float32)

    monkeypatch.setattr(choice, "rendered_footprint_albedo", stub)
    clips = [_clip("train_000"), _clip("train_001")]
    cache: dict = {}
    out = choice.with_footprint_albedo(clips, {}, Path("scenes"), 16, cache)
    again = choice.with_footprint_albedo(clips, {}, Path("scenes"), 16, cache)
    assert calls == [("train_000", 16, "gbuffer"), ("train_001", 16, "gbuffer")]     # the second call hit the cache
    for new, old in zip(out + again, clips + clips):
        np.testing.assert_array_equal(new.gbuffer["albedo"], 0.5)
        assert new.gbuffer["depth"] is old.gbuffer["depth"]
        np.testing.assert_array_equal(old.gbuffer["albedo"], np.float32(0.8))                     # the loaded clip is untouched
    assert choice.with_footprint_albedo(clips, {}, Path("scenes"), 1, cache) is clips


def test_a_rendered_albedo_of_another_size_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(choice, "rendered_footprint_albedo",
                        lambda cfg, scene_dir, frames, spp, mode: np.zeros((len(frames), 3, 8, 8), np.float32))
    with pytest.raises(ValueError, match="train_000: rendered albedo"):
        choice.with_footprint_albedo([_clip("train_000")], {}, Path("scenes"), 4, {})


def test_split_arm_takes_gbuffer_albedo_spp_as_a_clip_key() -> None:
    keys, rest = choice.split_arm("gbuffer_albedo_spp=16,crops=uniform")
    assert keys == {"gbuffer_albedo_spp": "16"} and rest == "crops=uniform"
