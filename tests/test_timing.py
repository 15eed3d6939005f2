"""The timing job (denoisers/jobs/timing.py): passes, medians and spread, rows timed on the same frames."""
from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from denoisers import registry
from denoisers.registry import Denoiser, Frame
from denoisers.jobs.timing import (TimingJob, pass_seconds, prepare_run, speed_ratios, summarise_passes, time_interleaved,
                              time_run, timed_runs, timing_scene)
from tests.test_evaluate import smoke_config, write_synthetic_scene


class Sleeper(Denoiser):
    """Test only: the sample mean after sleeping ``ms`` milliseconds (a known cost per frame)."""

    def __init__(self, ms: float = 1.0) -> None:
        super().__init__()
        self.ms = float(ms)

    def denoise(self, frame: Frame) -> torch.Tensor:
        CALLS.append(self.ms)
        time.sleep(self.ms / 1e3)
        return frame.samples["radiance"].mean(0)


CALLS: list[float] = []     # the ms of every denoise() call, in order


class Products(Denoiser):
    """Test only: ``count`` float32 (n x n) @ (n x n) products per frame (2 n^3 FLOPs each), then the mean."""

    def __init__(self, n: int = 64, count: int = 3) -> None:
        super().__init__()
        self.n, self.count = int(n), int(count)

    def denoise(self, frame: Frame) -> torch.Tensor:
        a = torch.ones(self.n, self.n)
        for _ in range(self.count):
            a = torch.mm(a, a) / self.n
        return frame.samples["radiance"].mean(0) * a[0, 0]


@pytest.fixture
def sleeper() -> Iterator[str]:
    registry.register("test_sleeper", inputs=("radiance",), description="test only: sleeps")(Sleeper)
    yield "test_sleeper"
    registry._REGISTRY.pop("test_sleeper", None)


def test_a_pass_is_the_median_frame_without_the_first() -> None:
    assert pass_seconds([9.0, 1.0, 3.0, 2.0]) == 2.0
    assert pass_seconds([5.0]) == 5.0
    summary = summarise_passes([0.002, 0.004, 0.003], pixels=1_000_000)
    assert summary["ms_per_frame"] == pytest.approx(3.0) and summary["repeats"] == 3
    assert summary["ms_per_frame_min"] == pytest.approx(2.0) and summary["ms_per_frame_max"] == pytest.approx(4.0)
    assert summary["spread"] == pytest.approx(2.0 / 3.0) and summary["mpix_per_s"] == pytest.approx(1000 / 3.0)


def test_rows_are_timed_over_repeated_passes_on_the_same_frames(tmp_path: Path, sleeper: str) -> None:
    write_synthetic_scene(tmp_path / "test_000")
    cfg = smoke_config(methods=[{"id": "slow", "method": sleeper, "params": {"ms": 20.0}},
                                {"id": "fast", "method": sleeper, "params": {"ms": 5.0}}])
    CALLS.clear()
    slow = time_run(cfg, "slow", 1, tmp_path / "test_000", frames=3, repeats=3, threads=1, results=tmp_path)
    fast = time_run(cfg, "fast", 1, tmp_path / "test_000", frames=3, repeats=3, threads=1, results=tmp_path)
    assert slow["frames"] == fast["frames"] == [0, 1, 2] and slow["repeats"] == 3 == len(slow["pass_ms_per_frame"])
    # A warm-up pass and 3 timed passes over the same 3 frames, one row after the other.
    assert CALLS == [20.0] * 12 + [5.0] * 12
    # Sleeping sets a floor on every pass; the scheduler can only add time (no upper bound is asserted:
    # a starved machine once stretched the 5 ms sleeper to 78 ms).
    assert min(slow["pass_ms_per_frame"]) >= 20.0 and min(fast["pass_ms_per_frame"]) >= 5.0
    for record in (slow, fast):
        passes = record["pass_ms_per_frame"]
        assert record["ms_per_frame"] == pytest.approx(float(np.median(passes)))
        assert (record["ms_per_frame_min"], record["ms_per_frame_max"]) == (min(passes), max(passes))


def test_rounds_interleave_the_rows_and_ratios_pair_rounds(tmp_path: Path, sleeper: str) -> None:
    """After one warm-up pass of each row, every round runs one pass of every row in turn (so a slow spell
    of the machine falls on all rows of a round); speed_ratios pairs pass k of one row with pass k of the other."""
    write_synthetic_scene(tmp_path / "test_000")
    cfg = smoke_config(methods=[{"id": "slow", "method": sleeper, "params": {"ms": 8.0}},
                                {"id": "fast", "method": sleeper, "params": {"ms": 2.0}}])
    runs = [prepare_run(cfg, row, 1, tmp_path / "test_000", frames=2, results=tmp_path) for row in ("slow", "fast")]
    CALLS.clear()
    time_interleaved(runs, repeats=3, threads=1)
    # 4 passes per row (warm-up + 3 rounds) of 2 frames each, alternating row by row.
    assert CALLS == ([8.0, 8.0, 2.0, 2.0] * 4)
    job = TimingJob({"rows": [run.record(1) for run in runs]})
    ratios = speed_ratios(job, ("fast", 1), ("slow", 1))
    assert len(ratios) == 3 and (ratios < 1.0).all()
    assert ratios == pytest.approx(np.asarray(job.row("fast", 1)["pass_ms_per_frame"])
                                   / np.asarray(job.row("slow", 1)["pass_ms_per_frame"]))
    with pytest.raises(KeyError, match="nope @ 1 spp"):
        speed_ratios(job, ("nope", 1), ("slow", 1))


def test_flops_and_fraction_of_sgemm_per_round(tmp_path: Path, sleeper: str) -> None:
    """A row of known matrix products gets its analytic FLOPs per frame and per-round fractions of the round's
    sgemm rate; a row without torch products gets none."""
    registry.register("test_products", inputs=("radiance",), description="test only: products")(Products)
    try:
        write_synthetic_scene(tmp_path / "test_000")
        cfg = smoke_config(methods=[{"id": "mm", "method": "test_products", "params": {"n": 96, "count": 3}},
                                    {"id": "sleep", "method": sleeper, "params": {"ms": 1.0}}])
        runs = [prepare_run(cfg, row, 1, tmp_path / "test_000", frames=2, results=tmp_path) for row in ("mm", "sleep")]
        assert [run.count_flops(1) for run in runs] == [3 * 2 * 96**3, 0]
        rates = iter([50.0, 100.0])
        sgemm = time_interleaved(runs, repeats=2, threads=1, sgemm=lambda threads: next(rates, 80.0))
        assert sgemm == [100.0, 80.0]           # the warm-up call took the first value
        products, sleeping = (run.record(1, sgemm) for run in runs)
        per_round = [3 * 2 * 96**3 / 1e9 / s / g for s, g in zip(runs[0].passes, sgemm)]
        assert products["gflop_per_frame"] == pytest.approx(3 * 2 * 96**3 / 1e9)
        assert products["fraction_of_sgemm"] == pytest.approx(float(np.median(per_round)))
        assert products["fraction_of_sgemm_min"] == pytest.approx(min(per_round))
        assert sleeping["gflop_per_frame"] == 0 and sleeping["fraction_of_sgemm"] is None
        assert sleeping["gflops_per_s"] is None
    finally:
        registry._REGISTRY.pop("test_products", None)


def test_the_raes_fused_inference_convolutions_are_counted() -> None:
    """The RAE's inference path calls oneDNN's fused convolution, which torch's flop counter does not know: the
    timing job's counter gives it the FLOPs torch counts for the same network's plain (aten) step."""
    from torch.utils.flop_counter import FlopCounterMode

    from denoisers.nets import for_inference
    from denoisers.nets.rae import RAEConfig, RecurrentAutoencoder
    from denoisers.jobs.timing import flop_counter

    config = RAEConfig(features=("normal", "depth", "roughness"), width=0.25)
    model = RecurrentAutoencoder(config).eval()
    x = torch.rand(1, config.in_channels, 32, 48)
    with torch.no_grad(), FlopCounterMode(display=False) as plain:
        model.step(x, None)
    fast = flop_counter()
    with fast:
        for_inference(model).inference_step(x, None)
    assert plain.get_total_flops() > 0
    assert fast.get_total_flops() == plain.get_total_flops()


def test_the_timing_job_times_the_configured_rows_on_the_first_evaluated_scene() -> None:
    cfg = smoke_config(methods=[{"id": "noisy", "method": "noisy"}, {"id": "eaw", "method": "eaw"}], spp=[1, 2])
    assert timing_scene(cfg) == "test_000"
    # The configured rows, then the smoke config's capacity variants at ablation_spp (their sizes differ).
    assert timed_runs(cfg) == [("noisy", 1), ("noisy", 2), ("eaw", 1), ("eaw", 2), ("rae_capacity_width0125", 1),
                               ("rae_capacity_levels4", 1)]
    cfg["evaluation"]["timing"] = {"enabled": False}
    assert timed_runs(cfg) == []


def test_a_timing_scene_that_is_not_evaluated_is_a_config_error() -> None:
    from denoisers.evaluate import evaluation_problems

    cfg = smoke_config(methods=[{"id": "noisy", "method": "noisy"}])
    cfg["evaluation"]["timing"] = {"scene": "train_000"}
    problems = evaluation_problems(cfg)
    assert any("evaluation.timing.scene" in p and "'train_000'" in p and "test_000" in p for p in problems), problems
