"""Tests of ``store progress`` (denoisers/store/progress.py): what a config's trainings have reached in the store,
the logged step rate, the estimate of what is left, and totals that count a half-budget twin with its run."""
from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

from denoisers.store import ModelStore
from denoisers.store.progress import NOT_STARTED, PART_WAY, STORED, TrainingProgress, estimate, host_plan, \
    progress_table, runs, shape_of, training_progress
from denoisers.training.job import work_dir_for
from denoisers.training.loop import load_checkpoint
from denoisers.training.models import model_spec
from tests.test_store import store_config, train
from tests.test_training_job import synthetic_renders  # noqa: F401 (fixture)

REPO_ROOT = Path(__file__).resolve().parents[1]


def seeded_config(tmp_path: Path) -> dict:
    """The tiny store config trained with 2 seeds and half-budget twins: rae, rae_seed1, rae_half, rae_seed1_half."""
    cfg = store_config(tmp_path, steps=4)
    cfg["training"]["models"] = cfg["training"]["models"][:1]
    cfg["training"]["seeds"] = 2
    cfg["training"]["half_budget"] = True
    return cfg


def median_seconds_per_step(rates: list[float]) -> float:
    return float(1.0 / np.median(np.asarray(rates, dtype=np.float64)))


def test_progress_follows_a_training_from_nothing_to_part_way_to_stored(tmp_path: Path, synthetic_renders) -> None:
    cfg = seeded_config(tmp_path)
    store = ModelStore.of(cfg)
    rows = {row.model_id: row for row in training_progress(cfg, store)}
    assert set(rows) == {"rae", "rae_seed1", "rae_half", "rae_seed1_half"}
    assert all(row.state == NOT_STARTED and row.step == 0 and row.seconds_per_step is None for row in rows.values())
    assert rows["rae_half"].half_of == "rae" and rows["rae"].max_steps == 4 and rows["rae_half"].max_steps == 2

    train(cfg, tmp_path / "first", stop_at_step=2)
    work = work_dir_for(tmp_path / "first" / "models", cfg, model_spec(cfg, "rae"))
    store.publish_checkpoint(cfg, work)
    history = load_checkpoint(work / "checkpoint.pt")["history"]
    rows = {row.model_id: row for row in training_progress(cfg, store)}
    assert rows["rae"].state == PART_WAY and rows["rae"].step == 2
    assert rows["rae"].elapsed_s > 0 and rows["rae"].precision
    expected = median_seconds_per_step([row["steps_per_s"] for row in history if row.get("steps_per_s")])
    assert abs(rows["rae"].seconds_per_step - expected) <= 1e-9 * expected
    left = estimate(cfg, list(rows.values()), rows["rae"])
    assert left.remaining_steps == 2 and left.rate_from == "rae" and abs(left.remaining_s - 2 * expected) < 1e-9
    # Another seed of the same model has not trained: its estimate borrows the measured rate.
    other = estimate(cfg, list(rows.values()), rows["rae_seed1"])
    assert other.remaining_steps == 4 and other.rate_from == "rae" and abs(other.remaining_s - 4 * expected) < 1e-9
    assert rows["rae_seed1"].state == NOT_STARTED

    train(cfg, tmp_path / "first")                       # continues the run to its budget
    store.publish_model(cfg, tmp_path / "first" / "models" / "rae")
    rows = {row.model_id: row for row in training_progress(cfg, store)}
    assert rows["rae"].state == STORED and rows["rae"].step == 4
    with (store.model_entry(cfg, "rae").path / "curves.csv").open(newline="") as handle:
        logged = [float(row["steps_per_s"]) for row in csv.DictReader(handle) if row["steps_per_s"]]
    assert abs(rows["rae"].seconds_per_step - median_seconds_per_step(logged)) <= 1e-6 * rows["rae"].seconds_per_step
    assert estimate(cfg, list(rows.values()), rows["rae"]).remaining_steps == 0


def test_totals_count_a_half_budget_twin_with_its_full_run(tmp_path: Path) -> None:
    cfg = seeded_config(tmp_path)
    rows = [TrainingProgress("rae", STORED, 4, 4, 3600.0, "fp32", "cpu", seconds_per_step=2.0),
            TrainingProgress("rae_seed1", PART_WAY, 1, 4, 1800.0, "fp32", "cpu", seconds_per_step=3000.0),
            TrainingProgress("rae_half", STORED, 2, 2, 1700.0, "fp32", "cpu", half_of="rae", seconds_per_step=2.0),
            TrainingProgress("rae_seed1_half", NOT_STARTED, 0, 2, 0.0, half_of="rae_seed1")]
    assert [row.model_id for row in runs(rows)] == ["rae", "rae_seed1"]
    # The twin of the part-way seed takes that run's rate, not the other seed's.
    twin = estimate(cfg, rows, rows[3])
    assert twin.rate_from == "rae_seed1" and twin.remaining_s == 2 * 3000.0
    text = progress_table(cfg, rows)
    # 1.5 h of the two runs (the twin's 1700 s are inside rae's hour); 3 steps left of rae_seed1 at 3000 s/step.
    assert "over 2 runs" in text and "so far 1.50 h" in text and "left about 2.50 h" in text
    assert "2 stored, 1 part-way, 1 not started" in text
    markdown = progress_table(cfg, rows, markdown=True)
    assert markdown.splitlines()[0].startswith("| model | state |") and "| `rae_seed1_half` | not started |" in markdown


def test_the_cli_lists_every_training_of_the_isik_config() -> None:
    done = subprocess.run([sys.executable, "-m", "denoisers", "store", "progress", "--config",
                           str(REPO_ROOT / "config" / "isik2021.yaml")], cwd=REPO_ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    from denoisers.training.models import trained_model_specs
    from scenegen.config import load_config

    ids = [spec.id for spec in trained_model_specs(load_config(REPO_ROOT / "config" / "isik2021.yaml"))]
    assert [line.split()[0] for line in lines[1:1 + len(ids)]] == ids
    assert lines[1 + len(ids)].startswith(f"{len(ids)} trainings: ")


def test_a_model_with_no_run_borrows_the_rate_of_one_of_its_shape_only(tmp_path: Path) -> None:
    """An ablation that only flips a network switch (here RAE's demodulation) estimates at the rate of the model it
    ablates, labelled "same shape"; a model of another width has no measured rate and stays unknown."""
    cfg = store_config(tmp_path, steps=4)
    base = cfg["training"]["models"][0]
    cfg["training"]["models"] = [base,
                                 {**base, "id": "rae_nodemod", "net": {**base.get("net", {}), "demodulate": False}},
                                 {**base, "id": "rae_wide", "net": {**base.get("net", {}), "width": 0.5}}]
    specs = {m: model_spec(cfg, m) for m in ("rae", "rae_nodemod", "rae_wide")}
    assert shape_of(specs["rae"]) == shape_of(specs["rae_nodemod"]) != shape_of(specs["rae_wide"])
    rows = [TrainingProgress("rae", PART_WAY, 2, 4, 60.0, "fp32", "cpu", seconds_per_step=3.0),
            TrainingProgress("rae_nodemod", NOT_STARTED, 0, 4, 0.0),
            TrainingProgress("rae_wide", NOT_STARTED, 0, 4, 0.0)]
    ablated = estimate(cfg, rows, rows[1])
    assert (ablated.rate_from, ablated.same_shape, ablated.remaining_s) == ("rae", True, 12.0)
    assert estimate(cfg, rows, rows[2]).remaining_s is None
    own = estimate(cfg, rows, rows[0])
    assert (own.rate_from, own.same_shape, own.remaining_s) == ("rae", False, 6.0)
    text = progress_table(cfg, rows)
    assert "(rate of rae, same shape)" in text and "no measured rate (rae_wide)" in text


def test_the_totals_plan_per_arithmetic_and_set_apart_the_checkpoints_of_the_other(tmp_path: Path) -> None:
    """A host that trains in bf16 estimates at bf16 rates only, one in fp32 at fp32 rates; a part-way run whose
    checkpoint holds one arithmetic is left to a host of that kind (a run continues only in its own arithmetic)."""
    cfg = seeded_config(tmp_path)
    cfg["training"]["seeds"] = 3
    cfg["training"]["half_budget"] = False
    # rae: part-way in bf16 (1 s/step); rae_seed1 stored in fp32 (3 s/step); rae_seed2 not started.
    rows = [TrainingProgress("rae", PART_WAY, 1, 4, 1.0, "bf16", "cpu", seconds_per_step=1.0),
            TrainingProgress("rae_seed1", STORED, 4, 4, 12.0, "fp32", "cpu", seconds_per_step=3.0),
            TrainingProgress("rae_seed2", NOT_STARTED, 0, 4, 0.0)]
    bf16, fp32 = host_plan(cfg, rows, "bf16"), host_plan(cfg, rows, "fp32")
    # bf16: rae's 3 steps and rae_seed2's 4 at rae's 1 s/step; fp32: rae_seed2's 4 steps at rae_seed1's 3 s/step.
    assert (bf16.seconds, bf16.runs, bf16.unknown, bf16.elsewhere) == (7.0, 2, [], [])
    assert (fp32.seconds, fp32.runs, fp32.unknown, fp32.elsewhere) == (12.0, 1, [], ["rae"])
    assert estimate(cfg, rows, rows[2], "fp32").rate_from == "rae_seed1"
    assert estimate(cfg, rows, rows[2], "bf16").rate_from == "rae"
    # No row of an arithmetic measured a rate: the run is counted as unknown there, not at the other's rate.
    only_bf16 = [rows[0], rows[2]]
    fp32 = host_plan(cfg, only_bf16, "fp32")
    assert (fp32.seconds, fp32.unknown, fp32.elsewhere) == (0.0, ["rae_seed2"], ["rae"])
    text = progress_table(cfg, rows)
    assert "On a host that trains in bf16: about 0.00 h for the 2 runs" in text
    # The rates' hosts are named: the same arithmetic runs at other rates on another CPU.
    assert (bf16.measured_on, fp32.measured_on) == (("cpu",), ())
    assert "at bf16 rates measured on cpu (another CPU" in text
    assert "On a host that trains in fp32: about 0.00 h for the 1 runs" in text and "(rae)" in text
