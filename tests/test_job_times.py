"""What a run cost: the job-times table from Snakemake benchmark files (denoisers/report/job_times.py), the
training table's shared twin runs, and the published README block's cost lines built from both."""
from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from denoisers.report.job_times import (STAGE_OF_KIND, BenchmarkFileError, job_times_markdown, job_times_table,
                                        stage_seconds)
from denoisers.report.published import publish_run, readme_block
from denoisers.report.training_tables import shares_run
from scenegen.config import load_config

REPO_ROOT = Path(__file__).resolve().parents[1]
HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def write_benchmark(path: Path, seconds: float, rss: str = "300.5") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER + f"{seconds:.2f}\t0:00:00\t{rss}\t900\t200\t250\t0\t1\t90\t{seconds * 0.9:.2f}\n")


def test_every_benchmark_folder_of_the_workflow_has_a_stage() -> None:
    kinds = set()
    for rules in sorted((REPO_ROOT / "workflow" / "rules").glob("*.smk")):
        kinds |= set(re.findall(r'benchmarks/([A-Za-z_]+)(?:/|\.tsv)', rules.read_text()))
    assert kinds and kinds <= set(STAGE_OF_KIND), sorted(kinds - set(STAGE_OF_KIND))
    assert {"denoise", "evaluate", "train", "render_noisy", "build_report"} <= kinds


def test_job_times_sum_each_kind_and_stage(tmp_path: Path) -> None:
    bench = tmp_path / "benchmarks"
    write_benchmark(bench / "render_noisy" / "test_000" / "chunk_0.tsv", 12.0, rss="400")
    write_benchmark(bench / "render_noisy" / "test_001" / "chunk_0.tsv", 8.5, rss="-")
    write_benchmark(bench / "denoise" / "oidn.tsv", 30.0)
    write_benchmark(bench / "evaluate" / "oidn.tsv", 4.0, rss="1200")
    write_benchmark(bench / "time_methods.tsv", 100.0)
    write_benchmark(bench / "something_new" / "x.tsv", 1.0)
    table = job_times_table(tmp_path)
    rows = {r.kind: r for r in table.itertuples()}
    assert rows["render_noisy"].jobs == 2 and rows["render_noisy"].job_seconds == pytest.approx(20.5)
    assert rows["render_noisy"].max_job_seconds == pytest.approx(12.0) and rows["render_noisy"].max_rss_mb == 400
    assert rows["time_methods"].stage == "evaluation" and rows["something_new"].stage == "other"
    assert list(table["stage"]) == ["rendering", "evaluation", "evaluation", "evaluation", "other"]
    assert stage_seconds(table) == pytest.approx({"rendering": 20.5, "evaluation": 134.0, "other": 1.0})
    markdown = job_times_markdown(table)
    assert "| rendering | render_noisy | 2 | 20 | 12 | 400 |" in markdown
    assert "in all 3 min over 6 jobs" in markdown
    assert job_times_table(tmp_path / "nothing").empty
    (bench / "evaluate" / "bad.tsv").write_text(HEADER)
    with pytest.raises(BenchmarkFileError, match="bad.tsv: no benchmark row"):
        job_times_table(tmp_path)
    (bench / "evaluate" / "bad.tsv").write_text("wall\nfast\n")
    with pytest.raises(BenchmarkFileError, match="bad.tsv: not a Snakemake benchmark row"):
        job_times_table(tmp_path)


def test_a_twin_shares_its_full_models_run_only_when_its_curve_is_the_head_of_that_run() -> None:
    full = pd.DataFrame({"step": [20, 40, 60, 80], "train_loss": [1.0, 0.8, 0.7, 0.65], "elapsed_s": [1, 2, 3, 4]})
    assert shares_run(full.iloc[:2], full)
    assert not shares_run(full.iloc[:2].assign(train_loss=[1.0, 0.81]), full)       # trained on its own
    assert not shares_run(full, full.iloc[:2]) and not shares_run(full.iloc[:0], full)
    assert not shares_run(full.drop(columns="train_loss").iloc[:2], full)


def test_the_published_block_states_training_and_evaluation_cost(tmp_path: Path) -> None:
    from tests.test_published_run import fake_results

    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    repo = tmp_path / "repo"
    (repo / "config").mkdir(parents=True)
    (repo / "config" / "smoke.yaml").write_text((REPO_ROOT / "config" / "smoke.yaml").read_text())
    results = fake_results(tmp_path / "results")
    readme_without = readme_block(repo, "runs/smoke", "config/smoke.yaml")
    pd.DataFrame([
        {"model": "afn", "status": "trained", "steps": 4000, "train_minutes": 120.0, "seconds_per_step": 1.5,
         "precision": "bf16", "cpu": "AMD EPYC", "run_of": None},
        {"model": "afn_half", "status": "trained", "steps": 2000, "train_minutes": 59.0, "seconds_per_step": 1.5,
         "precision": "bf16", "cpu": "AMD EPYC", "run_of": "afn"},
        {"model": "kpcn", "status": "trained", "steps": 4000, "train_minutes": 30.0, "seconds_per_step": 0.4,
         "precision": "fp32", "cpu": "Intel", "run_of": None},
        {"model": "afn_heur", "status": "not trained", "steps": None, "train_minutes": None,
         "seconds_per_step": None, "precision": None, "cpu": None, "run_of": None},
    ]).to_csv(results / "tables" / "training.csv", index=False)
    for kind, seconds in (("generate_scene", 600.0), ("denoise", 2400.0), ("evaluate", 1200.0),
                          ("derive_masks", 300.0)):
        write_benchmark(results / "benchmarks" / kind / "a.tsv", seconds)
    job_times_table(results).to_csv(results / "tables" / "job_times.csv", index=False)
    publish_run(cfg, "config/smoke.yaml", results, repo / "runs" / "smoke")
    body = readme_block(repo, "runs/smoke", "config/smoke.yaml")
    # afn 2 h + kpcn 0.5 h; the twin is part of afn's run and the untrained row is no run at all.
    assert "Training: 3 models in 2 runs, 2.5 h of training wall time" in body
    assert "| afn_half | 2000 | 59 min (in afn's run) | 1.500 | bf16 | AMD EPYC |" in body
    assert "| kpcn | 4000 | 30 min | 0.400 | fp32 | Intel |" in body and "afn_heur" not in body
    assert "Evaluation: 1.1 h of job time (evaluation 1.0 h, stability 5 min)" in body
    assert "the whole run's jobs: scenes 10 min, evaluation 1.0 h, stability 5 min" in body
    assert "Training:" not in readme_without and "Evaluation:" not in readme_without
