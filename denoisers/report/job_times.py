"""What a run's jobs cost: the Snakemake ``benchmark:`` files under ``<results>/benchmarks/`` summed per kind of
job and per stage (tables/job_times.csv / .md).

A benchmark file is ``benchmarks/<kind>/<wildcards>.tsv`` or ``benchmarks/<kind>.tsv``; its ``s`` is the job's
wall time in seconds and ``max_rss`` its peak resident memory in MB. The sums are job time, not the run's wall
time: jobs ran side by side (a render job uses every core, a training job one). Every benchmark file in the folder counts, so a results folder
that earlier runs also wrote into holds their jobs too; the report's own job is not counted (Snakemake writes its
file after it ends). A model installed from the store costs its install job here; what it cost to train is its
``train_minutes`` in the training table.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pandas as pd

#: Benchmark folder (``benchmarks/<kind>``) -> the stage of the workflow it belongs to. A kind missing here is
#: listed under "other" (tests/test_job_times.py checks every ``benchmark:`` of workflow/rules is mapped).
STAGE_OF_KIND: dict[str, str] = {
    "generate_scene": "scenes", "render_noisy": "rendering", "render_reference": "rendering",
    "train": "training", "verify": "training", "tune": "tuning",
    "denoise": "evaluation", "evaluate": "evaluation", "robustness": "evaluation",
    "time_methods": "evaluation", "time_training": "evaluation", "build_report": "evaluation",
    "denoise_volume": "evaluation", "evaluate_volume": "evaluation", "robustness_volume": "evaluation",
    "derive_masks": "stability", "denoise_scenario": "stability", "score_scenario": "stability",
    "build_atlas": "stability",
}
STAGES: tuple[str, ...] = ("scenes", "rendering", "training", "tuning", "evaluation", "stability", "other")
#: Stages that build the data and models the evaluation reads; the rest is the evaluation's job time.
PREPARATION_STAGES: tuple[str, ...] = ("scenes", "rendering", "training", "tuning")
COLUMNS: tuple[str, ...] = ("stage", "kind", "jobs", "job_seconds", "max_job_seconds", "max_rss_mb")


class BenchmarkFileError(ValueError):
    """A benchmark file that cannot be read as Snakemake writes them; the message names it."""


def _read_benchmark(path: Path) -> tuple[float, float]:
    """(wall seconds, peak RSS in MB) of one benchmark file (its first row: one repeat per job)."""
    lines = path.read_text().splitlines()
    if len(lines) < 2:
        raise BenchmarkFileError(f"{path}: no benchmark row under its header")
    header, values = lines[0].split("\t"), lines[1].split("\t")
    try:
        record = dict(zip(header, values, strict=True))
        seconds = float(record["s"])
        rss = float(record["max_rss"]) if record.get("max_rss") not in (None, "", "NA", "-") else math.nan
    except (KeyError, ValueError) as err:
        raise BenchmarkFileError(f"{path}: not a Snakemake benchmark row ({err})") from err
    if not math.isfinite(seconds) or seconds < 0:
        raise BenchmarkFileError(f"{path}: job seconds {seconds!r}")
    return seconds, rss


def job_times_table(results_dir: Path) -> pd.DataFrame:
    """One row per kind of job with benchmark files under ``results_dir/benchmarks`` (:data:`COLUMNS`), in
    :data:`STAGES` order, then by kind."""
    import pandas as pd

    root = Path(results_dir) / "benchmarks"
    totals: dict[str, list[float]] = {}
    if root.is_dir():
        for path in sorted(root.rglob("*.tsv")):
            relative = path.relative_to(root)
            kind = relative.parts[0] if len(relative.parts) > 1 else relative.stem
            totals.setdefault(kind, []).append(_read_benchmark(path))
    rows = []
    for kind, records in totals.items():
        seconds = [s for s, _ in records]
        rss = [r for _, r in records if math.isfinite(r)]
        rows.append({"stage": STAGE_OF_KIND.get(kind, "other"), "kind": kind, "jobs": len(records),
                     "job_seconds": sum(seconds), "max_job_seconds": max(seconds),
                     "max_rss_mb": max(rss) if rss else math.nan})
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    order = {stage: i for i, stage in enumerate(STAGES)}
    return table.sort_values(["stage", "kind"], key=lambda c: c.map(order) if c.name == "stage" else c,
                             ignore_index=True)


def stage_seconds(table: pd.DataFrame) -> dict[str, float]:
    """Job seconds per stage (only stages that ran jobs), in :data:`STAGES` order."""
    sums = table.groupby("stage")["job_seconds"].sum()
    return {stage: float(sums[stage]) for stage in STAGES if stage in sums}


def hours_text(seconds: float) -> str:
    """``seconds`` as minutes below an hour, else hours (one decimal)."""
    return f"{seconds / 60:.0f} min" if seconds < 3600 else f"{seconds / 3600:.1f} h"


def job_times_markdown(table: pd.DataFrame) -> str:
    """The table as Markdown with a line of per-stage totals under it."""
    from denoisers.report.stats import markdown_table

    if table.empty:
        return "No benchmark files in the results folder.\n"
    body = markdown_table(["stage", "kind", "jobs", "job time (s)", "longest job (s)", "peak RSS (MB)"],
                          [[r.stage, r.kind, int(r.jobs), f"{r.job_seconds:.0f}", f"{r.max_job_seconds:.0f}",
                            "–" if math.isnan(r.max_rss_mb) else f"{r.max_rss_mb:.0f}"]
                           for r in table.itertuples()])
    stages = stage_seconds(table)
    return (body.rstrip("\n") + "\n\nJob time per stage: " + ", ".join(f"{s} {hours_text(v)}" for s, v in stages.items())
            + f"; in all {hours_text(sum(stages.values()))} over {int(table['jobs'].sum())} jobs (sums of job wall "
              "times; jobs ran side by side).\n")
