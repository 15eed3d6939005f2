"""denoisers/jobs/rows.py: one job per evaluation row writes exactly what the per-clip functions write for each of
the row's clips (every evaluated scene at each runnable spp), and nothing that looks complete when a clip fails."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from denoisers.evaluate import EvaluationError, read_radiance_exr
from denoisers.jobs import denoise, robustness, rows, scoring
from tests.test_evaluate import BASIC_METHODS, smoke_config, write_synthetic_scene

SCENES = ("test_000", "test_001")
#: timing.json keys that are measurements of the run, not results (they differ between two runs).
MEASURED = {"seconds_per_frame", "mean_seconds", "median_seconds", "mpix_per_s", "peak_memory_mb", "peak_rss_mb",
            "maxrss_delta_mb"}


@pytest.fixture(scope="module")
def two_scenes(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """A config with two evaluated scenes (4 sample layers each) and their renders below <root>/renders."""
    cfg = smoke_config(methods=BASIC_METHODS)
    cfg["scenes"]["n_test"], cfg["extra_scenes"], cfg["render"]["extra_radiance_spp"] = 2, [], 0
    root = tmp_path_factory.mktemp("rows")
    for seed, scene in enumerate(SCENES):
        write_synthetic_scene(root / "renders" / scene, scene=scene, seed=seed)
    return cfg, root


def test_row_clips_are_every_evaluated_scene_at_each_runnable_spp(two_scenes: tuple[dict, Path]) -> None:
    cfg, _ = two_scenes
    # 4 rendered layers: noisy at 1, 2, 4 spp; path_x2 averages 2 x spp layers, so 4 spp (8 layers) is left out.
    assert rows.row_clips(cfg, "noisy") == [(scene, spp) for spp in (1, 2, 4) for scene in SCENES]
    assert rows.row_clips(cfg, "path_x2") == [(scene, spp) for spp in (1, 2) for scene in SCENES]
    spp = cfg["evaluation"]["robustness"]["spp"]
    assert rows.row_clips(cfg, "noisy", "robustness") == [(scene, spp) for scene in SCENES]
    with pytest.raises(KeyError, match="nope"):
        rows.row_clips(cfg, "nope")


def test_a_row_job_writes_what_the_clip_jobs_write(two_scenes: tuple[dict, Path], tmp_path: Path) -> None:
    cfg, root = two_scenes
    renders = root / "renders"
    row_dir = tmp_path / "denoised" / "path_x2"
    records = rows.denoise_row(cfg, "path_x2", renders, row_dir)
    clips = rows.row_clips(cfg, "path_x2")
    assert sorted(p.relative_to(row_dir).as_posix() for p in row_dir.glob("*/spp*")) == \
        sorted(f"{scene}/spp{spp}" for scene, spp in clips)
    assert [(r["scene"], r["spp"]) for r in records] == clips
    assert not list(tmp_path.rglob(".*tmp*")), "staging directory left behind"
    metrics_dir = tmp_path / "metrics" / "path_x2"
    assert rows.evaluate_row(cfg, row_dir, renders, metrics_dir) == len(clips)
    for scene, spp in clips:
        alone = tmp_path / "alone" / scene / f"spp{spp}"
        record = denoise.denoise_clip(cfg, "path_x2", scene, spp, renders / scene, alone)
        clip = row_dir / scene / f"spp{spp}"
        assert sorted(p.name for p in clip.iterdir()) == sorted(p.name for p in alone.iterdir())
        for exr in sorted(alone.glob("*.exr")):
            np.testing.assert_array_equal(read_radiance_exr(clip / exr.name), read_radiance_exr(exr))
        in_row = json.loads((clip / "timing.json").read_text())
        assert {k: v for k, v in in_row.items() if k not in MEASURED} == \
            {k: v for k, v in record.items() if k not in MEASURED}
        table = scoring.evaluate_clip(cfg, alone, renders / scene, tmp_path / "alone" / f"{scene}_{spp}.csv")
        pd.testing.assert_frame_equal(pd.read_csv(metrics_dir / scene / f"spp{spp}.csv"),
                                      pd.read_csv(tmp_path / "alone" / f"{scene}_{spp}.csv"))
        assert len(table) == len(in_row["frames"])
        assert json.loads((metrics_dir / scene / f"spp{spp}.json").read_text())["scene"] == scene


def test_a_row_robustness_job_writes_what_the_clip_jobs_write(two_scenes: tuple[dict, Path], tmp_path: Path) -> None:
    cfg, root = two_scenes
    renders = root / "renders"
    summaries = rows.robustness_row(cfg, "noisy", renders, tmp_path / "robustness" / "noisy")
    spp = cfg["evaluation"]["robustness"]["spp"]
    assert [(s["scene"], s["spp"]) for s in summaries] == [(scene, spp) for scene in SCENES]
    for scene in SCENES:
        robustness.robustness_clip(cfg, "noisy", scene, spp, renders / scene, tmp_path / "alone" / scene)
        in_row = tmp_path / "robustness" / "noisy" / scene / f"spp{spp}"
        assert sorted(p.name for p in in_row.iterdir()) == sorted(p.name for p in (tmp_path / "alone" / scene).iterdir())
        assert json.loads((in_row / robustness.ROBUSTNESS_SUMMARY).read_text()) == \
            json.loads((tmp_path / "alone" / scene / robustness.ROBUSTNESS_SUMMARY).read_text())
        # Compared as numbers: the text of a float column depends on the writing process's pandas state.
        pd.testing.assert_frame_equal(pd.read_csv(in_row / robustness.ROBUSTNESS_CSV),
                                      pd.read_csv(tmp_path / "alone" / scene / robustness.ROBUSTNESS_CSV),
                                      check_exact=False, rtol=1e-9)


def test_a_failing_clip_leaves_no_row_folder(two_scenes: tuple[dict, Path], tmp_path: Path) -> None:
    """A corrupt frame of the last scene: the row job fails with the clip's own error (raised again in the job from
    the clip's process, so the command line reports it in one line and refuses a retry), and leaves no row folder."""
    import shutil

    from scenegen.dataset import DatasetError
    from scenegen.exr import EXRError

    cfg, root = two_scenes
    renders = tmp_path / "renders"
    shutil.copytree(root / "renders", renders)
    frame = renders / SCENES[-1] / "noisy" / "chunk_000" / "frame_0001.exr"
    frame.write_bytes(frame.read_bytes()[:200])
    with pytest.raises((DatasetError, EXRError), match="frame_0001.exr") as raised:
        rows.denoise_row(cfg, "noisy", renders, tmp_path / "denoised" / "noisy")
    assert any("in the clip's process" in note for note in raised.value.__notes__)
    assert not list((tmp_path / "denoised").iterdir())
    with pytest.raises(EvaluationError, match="no denoised clips"):
        (tmp_path / "empty").mkdir()
        rows.evaluate_row(cfg, tmp_path / "empty", renders, tmp_path / "metrics")
    assert not (tmp_path / "metrics").exists()


def test_a_clip_runs_in_a_fresh_process_with_its_result_or_error() -> None:
    """in_fresh_process returns the function's result from another process, and raises its exception again as
    its own class; a process that dies without a result is an EvaluationError naming its exit code."""
    import os

    assert rows.in_fresh_process(os.getpid) != os.getpid()
    with pytest.raises(ZeroDivisionError) as raised:
        rows.in_fresh_process(divmod, 1, 0)
    assert "ZeroDivisionError" in raised.value.__notes__[0]
    with pytest.raises(EvaluationError, match="exit code 7"):
        rows.in_fresh_process(os._exit, 7)
