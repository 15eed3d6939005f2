"""The generated report: tables, figures, the claims table and results/REPORT.md (rule build_report).

Everything here is computed from the evaluation outputs (per-frame metric CSVs, timing.json, the
robustness scenario, the denoised EXRs and the references); nothing is typed in. Aggregation: a
metric is first averaged over the frames of a clip (NaN frames, e.g. temporal metrics during
warm-up, skipped), then over the test scenes, with a 95 % Student-t confidence interval over the
per-scene means (undefined with fewer than two scenes).

``report_outputs(cfg)`` lists the files the report writes and is called while the Snakefile is
parsed, so this module imports pandas and matplotlib only inside the functions that need them.
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from denoisers.evaluate import (
    ALL_METRICS,
    REFERENCE_METHODS,
    ROBUSTNESS_CSV,
    ROBUSTNESS_LAST_EXR,
    ROBUSTNESS_SUMMARY,
    TIMING_FILE,
    EvaluationError,
    MethodSpec,
    denoised_dir,
    method_specs,
    metrics_csv,
    read_frame_files,
    read_radiance_exr,
    robustness_dir,
    evaluated_scene_ids,
)
from scenegen.atomic import write_text_atomic
from scenegen.config import SCENE_SPLITS, scene_ids

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report_training import TrainedModels

CONFIDENCE = 0.95
#: Tables written as tables/{name}.csv and tables/{name}.md.
TABLES: tuple[str, ...] = ("summary", "per_scene", "psnr_by_spp", "chaitanya_fig8", "isik_video", "timing",
                           "equal_time", "noise_floor", "robustness", "claims", "runs", "split")
#: Tables also shown in the HTML report of ``snakemake --report``.
REPORT_TABLES: tuple[str, ...] = ("summary", "claims", "equal_time", "robustness", "timing", "noise_floor")
#: Timing columns aggregated like metrics (from timing.json).
TIMING_COLUMNS: tuple[str, ...] = ("ms_per_frame", "mpix_per_s", "peak_memory_mb")
#: Metrics whose larger value is better (the others are errors).
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "tpsnr": True, "rmse": False, "relmse": False, "smape": False,
                    "flip": False, "trmae": False, "ms_per_frame": False, "mpix_per_s": True,
                    "peak_memory_mb": False, "psnr_drop": False}
LABELS = {"psnr": "PSNR (dB)", "ssim": "SSIM", "rmse": "RMSE", "relmse": "rMSE", "smape": "SMAPE",
          "flip": "FLIP", "tpsnr": "tPSNR (dB)", "trmae": "TRMAE", "ms_per_frame": "ms/frame",
          "mpix_per_s": "Mpix/s", "peak_memory_mb": "peak MB", "psnr_drop": "PSNR drop under spikes (dB)"}
DECIMALS = {"psnr": 2, "tpsnr": 2, "ssim": 4, "flip": 4, "smape": 4, "trmae": 4, "rmse": 4, "relmse": 4,
            "ms_per_frame": 2, "mpix_per_s": 3, "peak_memory_mb": 1, "psnr_drop": 2}
REPRODUCED, NOT_REPRODUCED, NOT_RUN = "reproduced", "not reproduced", "not run"


# ---------------------------------------------------------------------------------------------------
# Output list (parse time, no heavy imports)
# ---------------------------------------------------------------------------------------------------

def report_outputs(cfg: dict, root: str = "results") -> dict[str, list[str]]:
    """Files the report writes, grouped: 'tables' (CSV), 'tables_md', 'quality' (chart PNG + SVG),
    'curves' (per-frame error per test scene), 'grids' (image grid per test scene + robustness), 'markdown',
    'training_tables' and 'training_figures' (trained models and ablations; empty without training)."""
    from denoisers.report_training import training_outputs

    scenes = evaluated_scene_ids(cfg)
    training = training_outputs(cfg, root)
    return {"training_tables": training["tables"], "training_figures": training["figures"],"tables": [f"{root}/tables/{t}.csv" for t in TABLES],
            "tables_md": [f"{root}/tables/{t}.md" for t in TABLES],
            "quality": [f"{root}/figures/quality_vs_speed.png", f"{root}/figures/quality_vs_speed.svg"],
            "curves": [f"{root}/figures/frame_curves_{scene}.png" for scene in scenes],
            "grids": [f"{root}/figures/grid_{scene}.png" for scene in scenes] + [f"{root}/figures/robustness_grid.png"],
            "markdown": [f"{root}/REPORT.md"]}


# ---------------------------------------------------------------------------------------------------
# Statistics and formatting
# ---------------------------------------------------------------------------------------------------

def mean_ci(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float, float, int]:
    """(mean, low, high, n) of the non-NaN values: Student-t interval mean +- t_{(1+c)/2, n-1} s / sqrt(n),
    s the sample standard deviation; low = high = NaN when n < 2."""
    from scipy import stats

    data = np.asarray([v for v in values if not np.isnan(v)], dtype=np.float64)
    n = len(data)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    mean = float(data.mean())
    if n < 2:
        return mean, math.nan, math.nan, n
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1) * data.std(ddof=1) / math.sqrt(n))
    return mean, mean - half, mean + half, n


def fmt(value: float, metric: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    decimals = DECIMALS.get(metric)
    if metric == "mpix_per_s":
        return f"{value:.3g}"
    return f"{value:.{decimals}f}" if decimals is not None else f"{value:.4g}"


def fmt_ci(mean: float, low: float, high: float, metric: str = "") -> str:
    """'mean ± half-width' (or just the mean when the interval is undefined)."""
    if math.isnan(low) or math.isnan(high):
        return fmt(mean, metric)
    half = (high - low) / 2.0
    if abs(half) <= 1e-9 * max(abs(mean), 1e-30):  # identical scenes: round-off only
        half = 0.0
    return f"{fmt(mean, metric)} ± {fmt(half, metric)}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table; cells are str()-ed and pipes escaped."""
    def cell(value: Any) -> str:
        return str(value).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def frame_to_markdown(table: pd.DataFrame) -> str:
    return markdown_table(list(table.columns), table.astype(object).where(table.notna(), "–").values.tolist())


# ---------------------------------------------------------------------------------------------------
# Collecting the evaluation outputs
# ---------------------------------------------------------------------------------------------------

@dataclass
class Results:
    """Everything the report is computed from."""

    cfg: dict
    specs: list[MethodSpec]
    scenes: list[str]                         # test scenes
    runs: list[dict]                          # every planned (method, spp): id, method, spp, status, reason
    frames: pd.DataFrame                    # per-frame metrics of runs that exist: method_id, spp, scene, frame, ...
    per_scene: pd.DataFrame                 # per (method_id, spp, scene): frame means + timing
    robustness: pd.DataFrame | None = None  # per (method_id, scene): spiked metrics and counts
    results_dir: Path = field(default_factory=lambda: Path("results"))
    models: TrainedModels | None = None      # trained models (denoisers.report_training)

    def ran(self, method_id: str, spp: int) -> bool:
        return any(r["id"] == method_id and r["spp"] == spp and r["status"] == "ran" for r in self.runs)

    def row_of(self, method: str) -> str | None:
        """The first row id whose registry method is ``method`` and that produced results."""
        for spec in self.specs:
            if spec.method == method and any(r["id"] == spec.id and r["status"] == "ran" for r in self.runs):
                return spec.id
        return None

    def rows_of(self, method: str) -> list[str]:
        """Every row id whose registry method is ``method`` and that produced results."""
        return [spec.id for spec in self.specs if spec.method == method
                and any(r["id"] == spec.id and r["status"] == "ran" for r in self.runs)]

    def spec(self, method_id: str) -> MethodSpec:
        return next(spec for spec in self.specs if spec.id == method_id)

    def scene_values(self, method_id: str, spp: int, column: str) -> pd.Series:
        """Per-scene means of one column, indexed by scene."""
        rows = self.per_scene[(self.per_scene.method_id == method_id) & (self.per_scene.spp == spp)]
        return rows.set_index("scene")[column]


def _plan_status(cfg: dict) -> dict[tuple[str, int], str]:
    """(method id, spp) -> '' if runnable, else the not-run reason (unregistered methods included)."""
    from denoisers.evaluate import plan_runs

    status = {}
    for spec in method_specs(cfg):
        single = {**cfg, "evaluation": {**cfg["evaluation"], "methods": [
            {"id": spec.id, "method": spec.method, "params": spec.params}]}}
        try:
            for run in plan_runs(single):
                status[(spec.id, run.spp)] = run.not_run
        except (KeyError, TypeError, ValueError) as error:
            for spp in cfg["evaluation"]["spp"]:
                status[(spec.id, spp)] = f"not run (method unavailable: {error})"
    return status


def collect(cfg: dict, results_dir: Path) -> Results:
    """Read every metrics CSV and timing.json of the configured runs on the test scenes."""
    import pandas as pd

    results_dir = Path(results_dir)
    specs, scenes = method_specs(cfg), evaluated_scene_ids(cfg)
    plan = None
    runs, frame_tables, timing_rows = [], [], []
    for spec in specs:
        for spp in cfg["evaluation"]["spp"]:
            missing = [s for s in scenes if not metrics_csv(results_dir, spec.id, s, spp).is_file()
                       or not (denoised_dir(results_dir, spec.id, s, spp) / TIMING_FILE).is_file()]
            if scenes and not missing:
                runs.append({"id": spec.id, "method": spec.method, "spp": spp, "status": "ran", "reason": ""})
                for scene in scenes:
                    table = pd.read_csv(metrics_csv(results_dir, spec.id, scene, spp))
                    table.insert(0, "scene", scene)
                    table.insert(0, "spp", spp)
                    table.insert(0, "method_id", spec.id)
                    frame_tables.append(table)
                    timing = json.loads((denoised_dir(results_dir, spec.id, scene, spp) / TIMING_FILE).read_text())
                    timing_rows.append({
                        "method_id": spec.id, "spp": spp, "scene": scene,
                        "ms_per_frame": timing["mean_seconds"] * 1e3, "mpix_per_s": timing["mpix_per_s"],
                        "peak_memory_mb": timing["peak_memory_mb"], "nonfinite_inputs": timing["nonfinite_inputs"],
                        "nonfinite_outputs": timing["nonfinite_outputs"],
                        "samples_factor": timing.get("samples_factor", 1),
                        "render_samples_per_s": timing.get("render_samples_per_s") or math.nan,
                        "pixels": timing["width"] * timing["height"]})
                continue
            plan = _plan_status(cfg) if plan is None else plan
            reason = plan.get((spec.id, spp), "")
            if not reason:
                reason = (f"not run (results missing for {', '.join(missing)})" if scenes
                          else "not run (no test scenes)")
            runs.append({"id": spec.id, "method": spec.method, "spp": spp, "status": "not run", "reason": reason})

    metric_columns = [*ALL_METRICS, "reference_psnr_halves"]
    if frame_tables:
        frames = pd.concat(frame_tables, ignore_index=True)
        per_scene = frames.groupby(["method_id", "spp", "scene"], sort=False)[metric_columns].mean().reset_index()
        per_scene = per_scene.merge(pd.DataFrame(timing_rows), on=["method_id", "spp", "scene"], how="left")
    else:
        frames = pd.DataFrame(columns=["method_id", "spp", "scene", "frame", *metric_columns, "camera_cut"])
        per_scene = pd.DataFrame(columns=["method_id", "spp", "scene", *metric_columns, *TIMING_COLUMNS])
    robustness = _collect_robustness(cfg, results_dir, specs, scenes) if cfg["evaluation"]["robustness"]["enabled"] \
        else None
    from denoisers.report_training import collect_models

    return Results(cfg, specs, scenes, runs, frames, per_scene, robustness, results_dir,
                   collect_models(cfg, results_dir))


def _collect_robustness(cfg: dict, results_dir: Path, specs: list[MethodSpec], scenes: list[str]) -> pd.DataFrame:
    import pandas as pd

    spp = cfg["evaluation"]["robustness"]["spp"]
    rows = []
    for spec in specs:
        for scene in scenes:
            folder = robustness_dir(results_dir, spec.id, scene, spp)
            if not (folder / ROBUSTNESS_CSV).is_file():
                continue
            table = pd.read_csv(folder / ROBUSTNESS_CSV)
            summary = json.loads((folder / ROBUSTNESS_SUMMARY).read_text())
            rows.append({"method_id": spec.id, "scene": scene, "spp": spp,
                         **{f"{m}_spiked": table[m].mean() for m in ALL_METRICS},
                         "nonfinite_inputs": summary["nonfinite_inputs"],
                         "nonfinite_outputs": summary["nonfinite_outputs"],
                         "spikes": summary["injected"]["spikes"], "nan_values": summary["injected"]["nan_values"],
                         "inf_values": summary["injected"]["inf_values"]})
    return pd.DataFrame(rows, columns=["method_id", "scene", "spp", *[f"{m}_spiked" for m in ALL_METRICS],
                                       "nonfinite_inputs", "nonfinite_outputs", "spikes", "nan_values",
                                       "inf_values"])


# ---------------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------------

def summary_table(res: Results) -> pd.DataFrame:
    """Long table: method x spp x metric -> mean, 95 % CI over test scenes, number of scenes."""
    import pandas as pd

    rows = []
    for run in res.runs:
        if run["status"] != "ran":
            continue
        for metric in (*ALL_METRICS, *TIMING_COLUMNS):
            mean, low, high, n = mean_ci(res.scene_values(run["id"], run["spp"], metric).to_numpy(np.float64))
            rows.append({"method_id": run["id"], "method": run["method"], "spp": run["spp"], "metric": metric,
                         "higher_is_better": HIGHER_IS_BETTER[metric], "mean": mean, "ci_low": low, "ci_high": high,
                         "n_scenes": n})
    return pd.DataFrame(rows, columns=["method_id", "method", "spp", "metric", "higher_is_better", "mean", "ci_low",
                                       "ci_high", "n_scenes"])


def _summary_lookup(summary: pd.DataFrame) -> dict[tuple[str, int, str], tuple[float, float, float, int]]:
    return {(r.method_id, r.spp, r.metric): (r.mean, r.ci_low, r.ci_high, r.n_scenes) for r in summary.itertuples()}


def summary_markdown(res: Results, summary: pd.DataFrame) -> str:
    """One Markdown table per spp: rows = methods, columns = metrics as 'mean ± 95 % CI half-width'."""
    lookup = _summary_lookup(summary)
    columns = (*ALL_METRICS, *TIMING_COLUMNS)
    arrows = {True: "↑", False: "↓"}
    parts = []
    for spp in res.cfg["evaluation"]["spp"]:
        rows = []
        for spec in res.specs:
            if not res.ran(spec.id, spp):
                continue
            rows.append([spec.id, *[fmt_ci(*lookup[(spec.id, spp, m)][:3], m) for m in columns]])
        n = max((lookup[k][3] for k in lookup if k[1] == spp), default=0)
        parts.append(f"### {spp} spp ({n} test scene{'s' if n != 1 else ''})\n\n")
        parts.append(markdown_table(["method", *[f"{LABELS[m]} {arrows[HIGHER_IS_BETTER[m]]}" for m in columns]],
                                    rows) if rows else "no method ran at this spp\n")
        parts.append("\n")
    return "".join(parts)


def pivot_table(res: Results, summary: pd.DataFrame, metrics: Sequence[str]) -> pd.DataFrame:
    """Rows = methods, columns = (metric, spp) 'mean ± CI' strings (the layout of Isik et al.'s tables)."""
    import pandas as pd

    lookup = _summary_lookup(summary)
    rows = []
    for spec in res.specs:
        row = {"method": spec.id}
        for metric in metrics:
            for spp in res.cfg["evaluation"]["spp"]:
                key = (spec.id, spp, metric)
                row[f"{LABELS[metric]} @ {spp} spp"] = fmt_ci(*lookup[key][:3], metric) if key in lookup else "not run"
        rows.append(row)
    return pd.DataFrame(rows)


#: Registry methods shown in the Chaitanya Fig. 8 table (the paper's EAW and RAE, plus SVGF and OIDN, and the input).
CHAITANYA_METHODS: tuple[str, ...] = ("noisy", "eaw", "svgf", "oidn", "rae")


def chaitanya_table(res: Results) -> pd.DataFrame:
    """Chaitanya et al. 2017 Fig. 8 layout at 1 spp (or the lowest evaluated spp): a row per method, RMSE and
    SSIM per test scene, then the mean over scenes with its 95 % CI."""
    import pandas as pd

    spp = _claim_spp(res, 1)
    rows = []
    for spec in res.specs:
        if spec.method not in CHAITANYA_METHODS:
            continue
        row: dict[str, Any] = {"method": spec.id, "spp": spp}
        ran = res.ran(spec.id, spp)
        for scene in res.scenes:
            for metric in ("rmse", "ssim"):
                row[f"{scene} {LABELS[metric]}"] = float(res.scene_values(spec.id, spp, metric)[scene]) if ran \
                    else math.nan
        for metric in ("rmse", "ssim"):
            mean, low, high, _ = mean_ci(res.scene_values(spec.id, spp, metric).to_numpy(float)) if ran \
                else (math.nan,) * 3 + (0,)
            row[f"{metric}_mean"], row[f"{metric}_ci_low"], row[f"{metric}_ci_high"] = mean, low, high
        rows.append(row)
    return pd.DataFrame(rows)


def timing_table(res: Results) -> pd.DataFrame:
    import pandas as pd

    rows = []
    for run in res.runs:
        if run["status"] != "ran":
            continue
        rows.append({"method_id": run["id"], "spp": run["spp"],
                     **{f"{c}_{part}": value for c in TIMING_COLUMNS
                        for part, value in zip(("mean", "ci_low", "ci_high"),
                                               mean_ci(res.scene_values(run["id"], run["spp"], c).to_numpy(float))[:3])},
                     "nonfinite_inputs": int(res.scene_values(run["id"], run["spp"], "nonfinite_inputs").sum()),
                     "nonfinite_outputs": int(res.scene_values(run["id"], run["spp"], "nonfinite_outputs").sum())})
    return pd.DataFrame(rows)


def equal_time_table(res: Results) -> pd.DataFrame:
    """For each denoiser and spp: the spp plain path tracing reaches in the same time (render time of
    spp samples + denoise time, with the renderer's measured samples/s), the plain path-tracing row
    whose total spp is nearest to it (in log ratio), and which of the two has the higher PSNR."""
    import pandas as pd

    baselines = []  # (row id, evaluated spp, total spp)
    for run in res.runs:
        if run["status"] == "ran" and res.spec(run["id"]).method in REFERENCE_METHODS:
            factor = int(res.scene_values(run["id"], run["spp"], "samples_factor").iloc[0])
            baselines.append((run["id"], run["spp"], run["spp"] * factor))
    rows = []
    for run in res.runs:
        if run["status"] != "ran" or res.spec(run["id"]).method in REFERENCE_METHODS:
            continue
        ms = res.scene_values(run["id"], run["spp"], "ms_per_frame")
        rate = res.scene_values(run["id"], run["spp"], "render_samples_per_s")
        pixels = res.scene_values(run["id"], run["spp"], "pixels")
        equal_spp = float(np.mean(run["spp"] + ms / 1e3 * rate / pixels))
        row = {"method_id": run["id"], "spp": run["spp"], "denoise_ms_per_frame": float(ms.mean()),
               "render_msamples_per_s": float(rate.mean() / 1e6), "equal_time_spp": equal_spp,
               "path_tracing_row": None, "path_tracing_spp": math.nan, "psnr_denoiser": math.nan,
               "psnr_path_tracing": math.nan, "psnr_diff_mean": math.nan, "psnr_diff_ci_low": math.nan,
               "psnr_diff_ci_high": math.nan, "better": "no path-tracing row"}
        if baselines and not math.isnan(equal_spp):
            best = min(baselines, key=lambda b: (abs(math.log(b[2] / equal_spp)), -b[2]))
            ours = res.scene_values(run["id"], run["spp"], "psnr")
            theirs = res.scene_values(best[0], best[1], "psnr")
            diff = (ours - theirs).dropna()
            mean, low, high, _ = mean_ci(diff.to_numpy(float))
            row.update({"path_tracing_row": f"{best[0]} @ {best[1]} spp", "path_tracing_spp": best[2],
                        "psnr_denoiser": float(ours.mean()), "psnr_path_tracing": float(theirs.mean()),
                        "psnr_diff_mean": mean, "psnr_diff_ci_low": low, "psnr_diff_ci_high": high,
                        "better": run["id"] if mean > 0 else "path tracing"})
            if best[2] < equal_spp / 1.5:
                row["better"] += f" (nearest rendered PT has {best[2]} spp < {equal_spp:.1f})"
        rows.append(row)
    return pd.DataFrame(rows)


def noise_floor_table(res: Results) -> pd.DataFrame:
    """Per test scene: PSNR between the two reference halves and the implied noise floor of the
    reference (+6.02 dB, docs/data-format.md), beside the best method PSNR at the highest spp."""
    import pandas as pd

    rows = []
    top_spp = max(res.cfg["evaluation"]["spp"])
    for scene in res.scenes:
        halves = res.frames.loc[res.frames.scene == scene, "reference_psnr_halves"]
        at_top = res.per_scene[(res.per_scene.scene == scene) & (res.per_scene.spp == top_spp)]
        at_top = at_top.dropna(subset=["psnr"])
        best = at_top.loc[at_top.psnr.idxmax()] if len(at_top) else None
        floor = float(halves.mean()) + 10 * math.log10(4.0) if len(halves) else math.nan
        rows.append({"scene": scene, "psnr_halves": float(halves.mean()) if len(halves) else math.nan,
                     "reference_noise_floor_psnr": floor, "best_method": best.method_id if best is not None else None,
                     "best_psnr": float(best.psnr) if best is not None else math.nan, "spp": top_spp,
                     "headroom_db": floor - float(best.psnr) if best is not None else math.nan})
    return pd.DataFrame(rows)


def robustness_table(res: Results) -> pd.DataFrame:
    """Per method at the robustness spp: PSNR on clean and on spiked input (mean ± CI over scenes), the
    drop, and the summed counts of injected and non-finite values."""
    import pandas as pd

    spp = res.cfg["evaluation"]["robustness"]["spp"]
    rows = []
    for spec in res.specs:
        spiked = res.robustness[res.robustness.method_id == spec.id].set_index("scene") if res.robustness is not None \
            else None
        if spiked is None or spiked.empty:
            rows.append({"method_id": spec.id, "spp": spp, "status": "not run"})
            continue
        clean = res.scene_values(spec.id, spp, "psnr") if res.ran(spec.id, spp) else None
        drop = (clean - spiked["psnr_spiked"]).dropna() if clean is not None else None
        row = {"method_id": spec.id, "spp": spp, "status": "ran"}
        for name, values in (("psnr_clean", clean), ("psnr_spiked", spiked["psnr_spiked"]), ("psnr_drop", drop)):
            mean, low, high, _ = mean_ci(values.to_numpy(float)) if values is not None else (math.nan,) * 4
            row.update({f"{name}_mean": mean, f"{name}_ci_low": low, f"{name}_ci_high": high})
        for count in ("spikes", "nan_values", "inf_values", "nonfinite_inputs", "nonfinite_outputs"):
            row[count] = int(spiked[count].sum())
        rows.append(row)
    return pd.DataFrame(rows)


def split_table(cfg: dict) -> pd.DataFrame:
    """The seeded train/test split: every scene id, its split and its derived seed."""
    import pandas as pd

    from scenegen.seeds import scene_seed

    rows = []
    for scene in scene_ids(cfg):
        split = next((s for s in SCENE_SPLITS if scene.startswith(f"{s}_")), "custom")
        rows.append({"scene": scene, "split": split, "evaluated": split == SCENE_SPLITS[1],
                     "scene_seed": scene_seed(cfg["seed"], scene) if split != "custom" else None})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------------
# Claims
# ---------------------------------------------------------------------------------------------------

@dataclass
class Comparison:
    """Method a versus method b on one metric, paired over the scenes where both exist."""

    metric: str
    a: str
    b: str
    spp: int
    mean_a: float
    mean_b: float
    diff: tuple[float, float, float, int]   # mean, low, high, n of (a - b) per scene

    @property
    def a_better(self) -> bool:
        """a beats b on the mean: higher for PSNR-like metrics, lower for errors."""
        mean = self.diff[0]
        return bool(mean > 0) if HIGHER_IS_BETTER.get(self.metric, True) else bool(mean < 0)

    def text(self) -> str:
        return (f"{LABELS.get(self.metric, self.metric)} @ {self.spp} spp: {self.a} {fmt(self.mean_a, self.metric)} "
                f"vs {self.b} {fmt(self.mean_b, self.metric)}")

    def ci_text(self) -> str:
        mean, low, high, n = self.diff
        if math.isnan(low):
            return f"{self.a}−{self.b} {fmt(mean, self.metric)} (n={n}, no CI)"
        return f"{self.a}−{self.b} {fmt(mean, self.metric)} [{fmt(low, self.metric)}, {fmt(high, self.metric)}] (n={n})"


def compare(a_values: pd.Series, b_values: pd.Series, metric: str, a: str, b: str, spp: int) -> Comparison:
    diff = (a_values - b_values).dropna()
    return Comparison(metric, a, b, spp, float(a_values.mean()), float(b_values.mean()), mean_ci(diff.to_numpy(float)))


@dataclass
class Claim:
    """One row of the claims table. ``needs`` are registry method names; ``decide`` computes the verdict
    from the results (None: no decision implemented yet, so the row stays 'not run')."""

    id: str
    paper: str
    statement: str
    needs: tuple[str, ...]
    decide: Callable[[Results], tuple[str, str, str, str]] | None = None


def _claim_spp(res: Results, preferred: int) -> int:
    """The paper's spp when it was evaluated, else the nearest evaluated one."""
    return min(res.cfg["evaluation"]["spp"], key=lambda s: (abs(s - preferred), s))


def _decide_c41(res: Results) -> tuple[str, str, str, str]:
    wrls, svgf = res.row_of("wrls"), res.row_of("svgf")
    spp = _claim_spp(res, 2)
    if not (res.ran(wrls, spp) and res.ran(svgf, spp)):
        return NOT_RUN, "", "", f"wrls or svgf did not run at {spp} spp"
    comparisons = [compare(res.scene_values(wrls, spp, m), res.scene_values(svgf, spp, m), m, wrls, svgf, spp)
                   for m in ("psnr", "trmae")]
    verdict = REPRODUCED if all(c.a_better for c in comparisons) else NOT_REPRODUCED
    return (verdict, "; ".join(c.text() for c in comparisons), "; ".join(c.ci_text() for c in comparisons),
            "needs higher PSNR and lower TRMAE; our test scenes are surfaces, not volumes (the paper's setting)")


def _decide_c42(res: Results) -> tuple[str, str, str, str]:
    wrls, rls = res.row_of("wrls"), res.row_of("rls")
    if res.robustness is None:
        return NOT_RUN, "", "", "robustness scenario disabled (evaluation.robustness.enabled)"
    table = res.robustness.set_index(["method_id", "scene"])
    have = set(res.robustness.method_id)
    if wrls not in have or rls not in have:
        return NOT_RUN, "", "", "no robustness results for wrls or rls"
    spp = res.cfg["evaluation"]["robustness"]["spp"]
    spiked = [table.loc[m]["psnr_spiked"] for m in (wrls, rls)]
    comparisons = [compare(spiked[0], spiked[1], "psnr", wrls, rls, spp)]
    if res.ran(wrls, spp) and res.ran(rls, spp):
        drops = [res.scene_values(m, spp, "psnr") - s for m, s in zip((wrls, rls), spiked)]
        drop = compare(drops[0], drops[1], "psnr_drop", wrls, rls, spp)
        comparisons.append(drop)
    verdict = REPRODUCED if all(c.a_better for c in comparisons) else NOT_REPRODUCED
    return (verdict, "; ".join(c.text() for c in comparisons), "; ".join(c.ci_text() for c in comparisons),
            "with spikes (up to 500x the frame mean) and NaN/Inf injected: needs higher PSNR and a smaller PSNR drop "
            "than RLS")


def _rae_rows(res: Results) -> tuple[str | None, str | None]:
    """(RAE row carrying its recurrent state, RAE row resetting it every frame), None where absent."""
    carried = [r for r in res.rows_of("rae") if not res.spec(r).params.get("reset_state_every_frame")]
    reset = [r for r in res.rows_of("rae") if res.spec(r).params.get("reset_state_every_frame")]
    return (carried[0] if carried else None), (reset[0] if reset else None)


def _verdict(comparisons: Sequence[Comparison]) -> str:
    return REPRODUCED if all(c.a_better for c in comparisons) else NOT_REPRODUCED


def _joined(comparisons: Sequence[Comparison]) -> tuple[str, str]:
    return "; ".join(c.text() for c in comparisons), "; ".join(c.ci_text() for c in comparisons)


def _rae_note(res: Results, row: str) -> str:
    """What the evaluated RAE is: its model, width and training budget (from the model's summary)."""
    model_id = res.spec(row).params.get("model")
    model = res.models.models.get(model_id) if res.models and model_id else None
    if model is None:
        return f"RAE row {row}"
    s = model.summary
    width = s.get("net", {}).get("config", {}).get("width")
    return (f"RAE {model_id}: width {width:g}, {s.get('parameters', 0):,} parameters, {s.get('steps')} steps "
            f"({s.get('elapsed_seconds', 0) / 60:.0f} min) on {len(s.get('train_scenes', []))} scenes")


def _decide_c11(res: Results) -> tuple[str, str, str, str]:
    rae, eaw = _rae_rows(res)[0], res.row_of("eaw")
    spp = _claim_spp(res, 1)
    if rae is None or not (res.ran(rae, spp) and res.ran(eaw, spp)):
        return NOT_RUN, "", "", f"rae (recurrent) or eaw did not run at {spp} spp"
    comparisons = [compare(res.scene_values(rae, spp, m), res.scene_values(eaw, spp, m), m, rae, eaw, spp)
                   for m in ("rmse", "ssim")]
    return (_verdict(comparisons), *_joined(comparisons),
            f"needs lower RMSE and higher SSIM on the test scenes; {_rae_note(res, rae)}")


def _ablation_pair(res: Results, ablation: str, a: str, b: str):
    variants = res.models.variants(ablation) if res.models else {}
    return variants.get(a), variants.get(b)


def _decide_c12(res: Results) -> tuple[str, str, str, str]:
    from denoisers.report_training import INPUT_VARIANT_LABELS, paired
    from denoisers.training.models import INPUT_ABLATION

    full, color = _ablation_pair(res, INPUT_ABLATION, "all", "color")
    if full is None or color is None:
        return NOT_RUN, "", "", f"training ablation {INPUT_ABLATION} with variants 'all' and 'color' not trained"
    variants = res.models.variants(INPUT_ABLATION)
    losses = {v: m.final_training_loss() for v, m in variants.items()}
    train_better = losses["all"] < losses["color"]
    val_diff = paired(color, full, "loss")
    val_better = val_diff[0] > 0
    ranking = " < ".join(f"{INPUT_VARIANT_LABELS.get(v, v)} {losses[v]:.4f}" for v in sorted(losses, key=losses.get))
    verdict = REPRODUCED if train_better and val_better else NOT_REPRODUCED
    mean, low, high, n = val_diff
    ci = (f"validation loss colour−all {mean:.4f} [{low:.4f}, {high:.4f}] (n={n} sequences)" if not math.isnan(low)
          else f"validation loss colour−all {mean:.4f} (n={n}, no CI)")
    rmse = {v: float(m.validation["rmse"].mean()) for v, m in (("all", full), ("color", color))}
    return (verdict, f"final training loss: {ranking}; validation RMSE of the remodulated output (one space for "
            f"all inputs): all {rmse['all']:.4f} vs colour only {rmse['color']:.4f}", ci,
            "needs a lower final training loss (mean of the last 20 % of logged steps) and a lower held-out "
            "validation loss for all inputs than for colour only; the colour-only loss is measured on "
            "non-demodulated colour, the others on demodulated colour (as in the paper's Fig. 3)")


def _decide_c13(res: Results) -> tuple[str, str, str, str]:
    from denoisers.report_training import paired
    from denoisers.training.models import LOSS_ABLATION

    combined, spatial = _ablation_pair(res, LOSS_ABLATION, "combined", "spatial")
    if combined is None or spatial is None:
        return NOT_RUN, "", "", f"training ablation {LOSS_ABLATION} with variants 'combined' and 'spatial' not trained"
    mean, low, high, n = paired(combined, spatial, "ssim")
    measured = (f"validation SSIM combined {combined.validation['ssim'].mean():.4f} vs spatial "
                f"{spatial.validation['ssim'].mean():.4f} (paper 0.9417 vs 0.9335)")
    ci = (f"combined−spatial {mean:.4f} [{low:.4f}, {high:.4f}] (n={n} sequences)" if not math.isnan(low)
          else f"combined−spatial {mean:.4f} (n={n}, no CI)")
    return (REPRODUCED if mean > 0 else NOT_REPRODUCED, measured, ci,
            f"same data, seed and budget ({combined.summary.get('steps')} steps); SSIM of each model's best "
            "validation-loss checkpoint on the held-out validation sequences")


def _decide_c14(res: Results) -> tuple[str, str, str, str]:
    rae, noisy = _rae_rows(res)[0], res.row_of("noisy")
    spp = _claim_spp(res, 4)
    if rae is None or not (res.ran(rae, spp) and res.ran(noisy, spp)):
        return NOT_RUN, "", "", f"rae or noisy did not run at {spp} spp"
    trained = res.models.models.get(res.spec(rae).params.get("model")) if res.models else None
    trained_spp = trained.spec.data.get("spp") if trained else None
    comparisons = [compare(res.scene_values(rae, spp, m), res.scene_values(noisy, spp, m), m, rae, noisy, spp)
                   for m in ("rmse", "ssim")]
    return (_verdict(comparisons), *_joined(comparisons),
            f"RAE trained at {trained_spp} spp, evaluated at {spp} spp; needs lower RMSE and higher SSIM than "
            "its input")


def _decide_c15(res: Results) -> tuple[str, str, str, str]:
    carried, reset = _rae_rows(res)
    spp = _claim_spp(res, 1)
    if carried is None or reset is None or not (res.ran(carried, spp) and res.ran(reset, spp)):
        return NOT_RUN, "", "", ("needs an rae row and an rae row with params.reset_state_every_frame: true, "
                                 f"both run at {spp} spp")
    comparisons = [compare(res.scene_values(carried, spp, "trmae"), res.scene_values(reset, spp, "trmae"), "trmae",
                           carried, reset, spp)]
    return (_verdict(comparisons), *_joined(comparisons),
            "same weights; the reset row starts every frame from a zero recurrent state")


def _decide_c43(res: Results) -> tuple[str, str, str, str]:
    wrls, noisy = res.row_of("wrls"), res.row_of("noisy")
    spps = [s for s in res.cfg["evaluation"]["spp"] if res.ran(wrls, s) and res.ran(noisy, s)]
    if not spps:
        return NOT_RUN, "", "", "wrls and noisy never ran at the same spp"
    comparisons = [compare(res.scene_values(wrls, s, "psnr"), res.scene_values(noisy, s, "psnr"), "psnr", wrls,
                           noisy, s) for s in spps]
    verdict = _verdict(comparisons)
    measured, ci = _joined(comparisons)
    rae = _rae_rows(res)[0]
    rae_spps = sorted(s for s in spps if rae is not None and res.ran(rae, s))
    if len(rae_spps) < 2:
        return (verdict, measured, ci, f"wRLS PSNR above the noisy input at every evaluated spp {spps}; the RAE "
                                       "half of the claim is not run (needs rae at two or more spp)")
    gains = {s: (res.scene_values(rae, s, "psnr") - res.scene_values(noisy, s, "psnr")) for s in rae_spps}
    low_spp, high_spp = rae_spps[0], rae_spps[-1]
    shrink = compare(gains[high_spp], gains[low_spp], "psnr", f"RAE gain @{high_spp}", f"RAE gain @{low_spp}",
                     high_spp)
    shrinks = shrink.diff[0] < 0
    verdict = REPRODUCED if verdict == REPRODUCED and shrinks else NOT_REPRODUCED
    gain_text = ", ".join(f"{s} spp {gains[s].mean():+.2f} dB" for s in rae_spps)
    return (verdict, f"{measured}; RAE PSNR gain over its input: {gain_text}", f"{ci}; {shrink.ci_text()}",
            f"needs wRLS above the noisy input at every spp {spps} and RAE's PSNR gain smaller at {high_spp} "
            f"than at {low_spp} spp")


def _decide_c44(res: Results) -> tuple[str, str, str, str]:
    from denoisers import registry

    wrls, rae = res.row_of("wrls"), _rae_rows(res)[0]
    spp = _claim_spp(res, 1)
    if rae is None or not (res.ran(wrls, spp) and res.ran(rae, spp)):
        return NOT_RUN, "", "", f"wrls or rae did not run at {spp} spp"
    untrained = not registry.get("wrls").info.trainable and registry.get("rae").info.trainable
    comparisons = [compare(res.scene_values(wrls, spp, "ms_per_frame"), res.scene_values(rae, spp, "ms_per_frame"),
                           "ms_per_frame", wrls, rae, spp)]
    verdict = REPRODUCED if untrained and comparisons[0].a_better else NOT_REPRODUCED
    return (verdict, *_joined(comparisons),
            f"wRLS trainable: {registry.get('wrls').info.trainable}, RAE trainable: "
            f"{registry.get('rae').info.trainable}; time per frame with {res.cfg['evaluation']['threads']} "
            f"thread(s), {_rae_note(res, rae)}")


CLAIMS: tuple[Claim, ...] = (
    Claim("C1.1", "Chaitanya 2017", "RAE has lower RMSE and higher SSIM than EAW at 1 spp", ("rae", "eaw"),
          _decide_c11),
    Claim("C1.2", "Chaitanya 2017", "albedo demodulation and auxiliary features lower the training loss",
          (), _decide_c12),
    Claim("C1.3", "Chaitanya 2017", "the combined loss gives higher validation SSIM than spatial L1 alone", (),
          _decide_c13),
    Claim("C1.4", "Chaitanya 2017", "RAE trained at 1 spp still improves on its input at 4 spp", ("rae", "noisy"),
          _decide_c14),
    Claim("C1.5", "Chaitanya 2017", "the recurrent network has lower TRMAE than the same network per frame", ("rae",),
          _decide_c15),
    Claim("C2.1", "Hasselgren 2020", "kernel prediction beats direct prediction (PSNR)", ("ntasd",)),
    Claim("C2.2", "Hasselgren 2020", "warped temporal recurrence improves PSNR and tPSNR over per-frame KPN",
          ("ntasd",)),
    Claim("C2.3", "Hasselgren 2020", "adaptive sampling at 4 spp on average beats uniform 4 spp", ("ntasd",)),
    Claim("C2.4", "Hasselgren 2020", "rMSE order: adaptive < uniform < DASR < direct prediction", ("ntasd",)),
    Claim("C2.5", "Hasselgren 2020", "at 4 spp NTASD beats RAE and SVGF in PSNR and is more stable than RAE",
          ("ntasd", "rae", "svgf")),
    Claim("C3.1", "Isik 2021", "ours-single beats ours-K1 and KPCN at 2-8 spp", ("afn", "kpcn")),
    Claim("C3.2", "Isik 2021", "affinity dimension d=1 is much worse than d>=2", ("afn",)),
    Claim("C3.3", "Isik 2021", "the temporal model has lower TRMAE than the single-frame model", ("afn",)),
    Claim("C3.4", "Isik 2021", "the learned temporal weight beats a fixed 0.8", ("afn",)),
    Claim("C3.5", "Isik 2021", "kernel size can change at test time; larger kernels help more at low spp", ("afn",)),
    Claim("C4.1", "Iglesias-Guitian 2022", "wRLS beats SVGF in PSNR and flickers less (TRMAE)", ("wrls", "svgf"),
          _decide_c41),
    Claim("C4.2", "Iglesias-Guitian 2022", "wRLS is more robust to spike noise than plain RLS", ("wrls", "rls"),
          _decide_c42),
    Claim("C4.3", "Iglesias-Guitian 2022", "wRLS improves on its input at every spp (RAE's gain shrinks)",
          ("wrls", "noisy"), _decide_c43),
    Claim("C4.4", "Iglesias-Guitian 2022", "wRLS needs no training and runs faster than RAE", ("wrls", "rae"),
          _decide_c44),
)


def claims_table(res: Results, claims: Sequence[Claim] = CLAIMS) -> pd.DataFrame:
    """Verdict per claim, computed from the results: 'not run' when a needed method has no results or
    no decision is implemented, else what ``decide`` finds."""
    import pandas as pd

    rows = []
    for claim in claims:
        missing = [name for name in claim.needs if res.row_of(name) is None]
        if missing:
            verdict, measured, ci, note = NOT_RUN, "", "", f"missing method(s): {', '.join(missing)}"
        elif claim.decide is None:
            verdict, measured, ci, note = NOT_RUN, "", "", "decision not implemented yet"
        else:
            verdict, measured, ci, note = claim.decide(res)
        rows.append({"claim": claim.id, "paper": claim.paper, "statement": claim.statement, "verdict": verdict,
                     "measured": measured, "ci_95": ci, "note": note})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _colours(specs: Sequence[MethodSpec]) -> dict[str, Any]:
    plt = _pyplot()
    cmap = plt.get_cmap("tab10")
    return {spec.id: cmap(i % 10) for i, spec in enumerate(specs)}


def plot_quality_vs_speed(res: Results, summary: pd.DataFrame, paths: Sequence[Path]) -> None:
    """PSNR against denoiser throughput (Mpix/s, log x), a point per method and spp with 95 % CI bars;
    the non-denoising rows (noisy input, plain path tracing) are horizontal reference lines."""
    plt = _pyplot()
    lookup = _summary_lookup(summary)
    colours = _colours(res.specs)
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    xs = []
    for spec in res.specs:
        spps = [s for s in res.cfg["evaluation"]["spp"] if res.ran(spec.id, s)]
        if not spps or spec.method in REFERENCE_METHODS:
            continue
        x = [lookup[(spec.id, s, "mpix_per_s")][0] for s in spps]
        y = [lookup[(spec.id, s, "psnr")] for s in spps]
        err = [[0 if math.isnan(v[1]) else v[0] - v[1] for v in y], [0 if math.isnan(v[2]) else v[2] - v[0] for v in y]]
        ax.errorbar(x, [v[0] for v in y], yerr=err, marker="o", color=colours[spec.id], label=spec.id, capsize=3)
        for xi, yi, s in zip(x, y, spps):
            ax.annotate(f"{spec.id} {s}spp", (xi, yi[0]), textcoords="offset points", xytext=(4, 4), fontsize=7)
        xs += x
    for spec in res.specs:
        if spec.method not in REFERENCE_METHODS:
            continue
        for s in res.cfg["evaluation"]["spp"]:
            if res.ran(spec.id, s):
                level = lookup[(spec.id, s, "psnr")][0]
                ax.axhline(level, color=colours[spec.id], linestyle="--", linewidth=0.8, alpha=0.7)
                # Noisy rows labelled on the right, path-tracing rows on the left: equal totals coincide.
                right = spec.method == "noisy"
                ax.annotate(f"{spec.id} {s}spp", (0.995 if right else 0.005, level),
                            xycoords=("axes fraction", "data"), ha="right" if right else "left", va="bottom",
                            fontsize=7, color=colours[spec.id])
    ax.set_xscale("log")
    if not xs:
        ax.set_xlim(0.1, 10)
    ax.set_xlabel("throughput (Mpix/s, denoising only, log scale)")
    ax.set_ylabel("PSNR (dB, tonemapped)")
    ax.set_title(f"Quality vs speed ({len(res.scenes)} test scene(s), mean ± 95 % CI)")
    ax.grid(True, which="both", alpha=0.3)
    if xs:
        ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    for path in paths:
        fig.savefig(path, dpi=150)
    plt.close(fig)


def plot_frame_curves(res: Results, scene: str, path: Path) -> None:
    """Per-frame relMSE (log), 1 - SSIM and tPSNR of every method, one row per spp, camera cuts dotted."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    spps = res.cfg["evaluation"]["spp"]
    colours = _colours(res.specs)
    panels = (("relmse", "rMSE (log)"), ("ssim", "1 − SSIM"), ("tpsnr", "tPSNR (dB)"))
    fig, axes = plt.subplots(len(spps), len(panels), figsize=(12, 2.6 * len(spps)), squeeze=False)
    data = res.frames[res.frames.scene == scene]
    for row, spp in enumerate(spps):
        for col, (metric, label) in enumerate(panels):
            ax = axes[row][col]
            for spec in res.specs:
                part = data[(data.method_id == spec.id) & (data.spp == spp)].sort_values("frame")
                if part.empty:
                    continue
                values = 1.0 - part[metric] if metric == "ssim" else part[metric]
                ax.plot(part["frame"], values, marker=".", color=colours[spec.id], label=spec.id)
                for t in part.loc[part.camera_cut.astype(bool), "frame"]:
                    ax.axvline(t, color="grey", linestyle=":", linewidth=0.8)
            if metric == "relmse" and ax.has_data():
                ax.set_yscale("log")
            ax.set_title(f"{label}, {spp} spp", fontsize=9)
            ax.set_xlabel("frame")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(True, alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 8), fontsize=8)
    fig.suptitle(f"{scene}: per-frame error (lower rMSE / 1−SSIM, higher tPSNR is better)", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _grid_frame(cfg: dict, frames: Sequence[int]) -> int:
    return list(frames)[int(cfg["evaluation"]["grid_frame"]) % len(frames)] if frames else 0


def _crop_window(error: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left (y, x) of the size x size window with the largest summed error (integral image)."""
    height, width = error.shape
    size = min(size, height, width)
    integral = np.pad(error.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = (integral[size:, size:] - integral[:-size, size:] - integral[size:, :-size] + integral[:-size, :-size])
    y, x = np.unravel_index(np.argmax(sums), sums.shape)
    return int(y), int(x)


def image_grid(columns: Sequence[tuple[str, np.ndarray]], reference: np.ndarray, path: Path, title: str) -> None:
    """Columns of (label, (3, H, W) radiance) plus the reference: full frame with the crop marked, the crop
    enlarged, and the error map |tonemap(x) - tonemap(ref)| (channel mean, common colour scale)."""
    from denoisers import metrics
    from denoisers.evaluate import preview_rgb8

    plt = _pyplot()
    from matplotlib.patches import Rectangle

    ref_tm = np.asarray(metrics.tonemap(reference))
    errors = [np.abs(np.asarray(metrics.tonemap(np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0))) - ref_tm)
              .mean(axis=0) for _, img in columns]
    size = max(8, min(reference.shape[1:]) // 4)
    y, x = _crop_window(errors[0] if errors else np.zeros(reference.shape[1:]), size)
    vmax = float(np.percentile(errors[0], 99)) if errors else 1.0
    vmax = vmax if vmax > 0 else 1.0
    panels = [*columns, ("reference", reference)]
    fig, axes = plt.subplots(3, len(panels), figsize=(1.9 * len(panels), 6.0), squeeze=False)
    for col, (label, img) in enumerate(panels):
        rgb = preview_rgb8(img)
        is_ref = col == len(panels) - 1
        psnr = "" if is_ref else f"\n{float(metrics.psnr(np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0), reference)):.2f} dB"
        axes[0][col].imshow(rgb, interpolation="nearest")
        axes[0][col].add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, edgecolor="cyan", linewidth=1))
        axes[0][col].set_title(f"{label}{psnr}", fontsize=8)
        axes[1][col].imshow(rgb[y:y + size, x:x + size], interpolation="nearest")
        if is_ref:
            axes[2][col].imshow(np.zeros_like(ref_tm[0]), cmap="inferno", vmin=0, vmax=vmax)
        else:
            axes[2][col].imshow(errors[col], cmap="inferno", vmin=0, vmax=vmax, interpolation="nearest")
        for row in range(3):
            axes[row][col].set_xticks([])
            axes[row][col].set_yticks([])
    axes[1][0].set_ylabel("crop", fontsize=8)
    axes[2][0].set_ylabel(f"|error| (0..{vmax:.2f})", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def placeholder(path: Path, text: str) -> None:
    """A small figure that only says why there is nothing to show."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(4, 1.5))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.set_axis_off()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _reference_frame(render_dir: Path, frame: int) -> np.ndarray:
    from scenegen.dataset import find_frames, load_reference_frame

    found = find_frames(Path(render_dir) / "reference")
    if frame not in found:
        raise EvaluationError(f"{render_dir}/reference: frame {frame} missing (needed for the image grid)")
    return load_reference_frame(found[frame], ["radiance"])[0]["radiance"]


def plot_grids(res: Results, figures: Path) -> list[Path]:
    """One image grid per test scene at the lowest evaluated spp, plus the robustness grid."""
    written = []
    spp = min(res.cfg["evaluation"]["spp"])
    for scene in res.scenes:
        columns, frame = [], None
        for spec in res.specs:
            if not res.ran(spec.id, spp):
                continue
            files = read_frame_files(denoised_dir(res.results_dir, spec.id, scene, spp))
            frame = _grid_frame(res.cfg, sorted(files)) if frame is None else frame
            columns.append((spec.id, read_radiance_exr(files[frame])))
        frame = frame if frame is not None else 0
        path = figures / f"grid_{scene}.png"
        reference = _reference_frame(res.results_dir / "renders" / scene, frame)
        image_grid(columns, reference, path, f"{scene}, frame {frame}, {spp} spp")
        written.append(path)
    robustness = res.cfg["evaluation"]["robustness"]
    path = figures / "robustness_grid.png"
    if not (robustness["enabled"] and res.scenes):
        placeholder(path, "robustness scenario disabled" if res.scenes else "no test scenes")
        written.append(path)
    else:
        scene, columns = res.scenes[0], []
        for spec in res.specs:
            exr = robustness_dir(res.results_dir, spec.id, scene, robustness["spp"]) / ROBUSTNESS_LAST_EXR
            if exr.is_file():
                columns.append((spec.id, read_radiance_exr(exr)))
        from scenegen.dataset import find_frames

        last = max(find_frames(res.results_dir / "renders" / scene / "reference"), default=0)
        image_grid(columns, _reference_frame(res.results_dir / "renders" / scene, last), path,
                   f"{scene}, frame {last}, {robustness['spp']} spp, spikes + NaN/Inf injected")
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------------------
# REPORT.md and the entry point
# ---------------------------------------------------------------------------------------------------

def _write_table(table: pd.DataFrame, tables: Path, name: str, markdown: str | None = None) -> None:
    write_text_atomic(tables / f"{name}.csv", table.to_csv(index=False))
    write_text_atomic(tables / f"{name}.md", markdown if markdown is not None else frame_to_markdown(table))


def _with_ci_columns(table: pd.DataFrame, merged: dict[str, tuple[str, str]], before: Sequence[str],
                     after: Sequence[str]) -> pd.DataFrame:
    """Display copy: each {prefix}_mean/_ci_low/_ci_high triple becomes one 'mean ± half-width' column."""
    shown = table[[c for c in before if c in table]].copy()
    for title, (prefix, metric) in merged.items():
        if f"{prefix}_mean" in table:
            shown[title] = [fmt_ci(m, lo, hi, metric) for m, lo, hi in
                            zip(table[f"{prefix}_mean"], table[f"{prefix}_ci_low"], table[f"{prefix}_ci_high"])]
    for column in after:
        if column in table:
            shown[column] = table[column]
    return shown


def _display(table: pd.DataFrame, metric_columns: dict[str, str]) -> pd.DataFrame:
    """A copy with numeric columns formatted for Markdown (column -> metric whose decimals apply)."""
    shown = table.copy()
    for column, metric in metric_columns.items():
        if column in shown:
            shown[column] = [fmt(float(v), metric) if v is not None else "–" for v in shown[column]]
    return shown


def _report_markdown(res: Results, outputs: dict[str, str], summary_md: str, claims: pd.DataFrame,
                     equal_time_md: str, robustness_md: str | None, noise_md: str, not_run: list[dict],
                     training_md: str = "") -> str:
    from denoisers import metrics

    cfg = res.cfg
    render = cfg["render"]
    lines = [
        "# Evaluation report",
        "",
        f"Generated by `snakemake report` from config: *{cfg.get('description', '')}*. Every number below is "
        "computed from the evaluation outputs; verdicts are derived from the tables, never typed in.",
        "",
        f"- Test scenes ({len(res.scenes)}): {', '.join(res.scenes) or 'none'}; training scenes are never "
        f"evaluated. Split and per-scene seeds (global seed {cfg['seed']}): [tables/split.csv](tables/split.csv).",
        f"- Renders: {render['width']}x{render['height']} px, {render['spp']} sample layers "
        f"(+{render['extra_radiance_spp']} radiance-only), references {render['reference_spp']} spp; "
        f"evaluated at {', '.join(map(str, cfg['evaluation']['spp']))} spp; "
        f"temporal metrics skip {cfg['evaluation']['warmup_frames']} warm-up frame(s) per shot.",
        "- Aggregation: metric averaged over a clip's frames, then over test scenes; ± is the half-width of "
        "the 95 % Student-t confidence interval over per-scene means (absent with one scene).",
        f"- Timing: in-process seconds per `denoise()` call with {cfg['evaluation']['threads']} torch thread(s), "
        "first frame (warm-up) and all I/O excluded; Mpix/s = pixels / mean seconds. Peak memory: RSS sampled "
        "with psutil every 5 ms during the denoise loop, minus the RSS before it.",
        "",
        "## Quality",
        "",
        summary_md,
        "Full tables: [summary (CSV)](tables/summary.csv), [summary (Markdown)](tables/summary.md), "
        "[per scene](tables/per_scene.csv), [PSNR by spp, Isik Table 2 layout](tables/psnr_by_spp.md), "
        "[PSNR and TRMAE, Isik Table 3 layout](tables/isik_video.md), "
        "[RMSE/SSIM per scene, Chaitanya Fig. 8 layout](tables/chaitanya_fig8.md), "
        "[timing and memory](tables/timing.md).",
        "",
        "![Quality versus speed](figures/quality_vs_speed.png)",
        "",
        "[Quality vs speed (SVG)](figures/quality_vs_speed.svg)",
        "",
        "## Claims",
        "",
        frame_to_markdown(claims[["claim", "paper", "statement", "verdict", "measured", "ci_95", "note"]]),
        "",
        "[claims (CSV)](tables/claims.csv)",
        "",
        "## Equal-time view",
        "",
        "Plain path tracing gets the samples it could render in the time of denoising (renderer speed "
        "measured during the reference renders: large batches, all feature buffers included); the nearest rendered row is compared.",
        "",
        equal_time_md,
        "",
    ]
    if robustness_md is not None:
        spec = cfg["evaluation"]["robustness"]
        lines += ["## Robustness (spikes and NaN/Inf)", "",
                  f"Per frame, {spec['spike_fraction']:.3%} of the radiance samples (at least one) get a spike of up to "
                  f"{spec['spike_max_factor']:g}x the frame mean, and {spec['nonfinite_fraction']:.3%} of the samples "
                  "of every input buffer (at least one) become NaN, +Inf or -Inf; seeded, identical for every method. "
                  "Metrics treat non-finite outputs as 0; their count is listed.", "",
                  robustness_md, "", "![Robustness grid](figures/robustness_grid.png)", ""]
    if training_md:
        lines += [training_md, ""]
    lines += ["## Reference noise floor", "", noise_md, ""]
    lines += ["## Per-scene figures", ""]
    for scene in res.scenes:
        lines += [f"- {scene}: [per-frame error curves](figures/frame_curves_{scene}.png), "
                  f"[image grid with crops and error maps](figures/grid_{scene}.png)"]
    lines += [""]
    if not_run:
        lines += ["## Not run", "", markdown_table(["method", "spp", "reason"],
                                                   [[r["id"], r["spp"], r["reason"]] for r in not_run]), ""]
    lines += ["## Metrics", ""]
    for name in ALL_METRICS:
        info = metrics.METRICS[name]
        lines.append(f"- **{LABELS[name]}** ({'higher' if info.higher_is_better else 'lower'} is better): "
                     f"{info.description}; `{info.formula}`")
    lines += ["", "## Files", ""]
    lines += [f"- [{Path(p).name}]({p})" for p in outputs.values()]
    return "\n".join(lines) + "\n"


def _write_training(res: Results, cfg: dict, tables: Path, figures: Path, paper_fig8: pd.DataFrame) -> str:
    """Training tables and figures (report_training); returns the REPORT.md section ('' without training)."""
    from denoisers import report_training as rt
    from denoisers.training.models import INPUT_ABLATION, LOSS_ABLATION

    expected = rt.training_outputs(cfg, root=str(tables.parent))
    if not expected["tables"]:
        return ""
    models = res.models
    training = rt.training_table(models)
    _write_table(training, tables, "training", frame_to_markdown(_display(training, {
        c: "" for c in ("train_minutes", "seconds_per_step", "final_train_loss", "val_loss", "val_ssim", "val_psnr",
                        "val_rmse") if c in training})))
    _write_table(paper_fig8, tables, "chaitanya_fig8_paper")
    rt.plot_training_curves(models, figures / "training_curves.png")
    lines = ["## Learned denoisers", "",
             "Trained on the training scenes (never on test scenes); validation on held-out training-distribution "
             "scenes. Sizes, budgets and validation metrics of each model's best (lowest validation loss) "
             "checkpoint:", "", frame_to_markdown(_display(training, {
                 c: "" for c in ("train_minutes", "seconds_per_step", "final_train_loss", "val_loss", "val_ssim",
                                 "val_psnr", "val_rmse") if c in training})),
             "![Training curves](figures/training_curves.png)", ""]
    if any(p.endswith(f"{INPUT_ABLATION}.csv") for p in expected["tables"]):
        table = rt.input_ablation_table(models)
        shown = _with_ci_columns(table.rename(columns={f"val_{m}": f"val_{m}_mean" for m in ("loss", "rmse", "ssim")})
                                 .rename(columns=lambda c: c.replace("_low", "_ci_low").replace("_high", "_ci_high")),
                                 {"val loss": ("val_loss", "rmse"), "val RMSE": ("val_rmse", "rmse"),
                                  "val SSIM": ("val_ssim", "ssim")},
                                 ["variant", "inputs", "model", "steps"], ["val_sequences"]) if len(table) else table
        if len(table):
            shown.insert(4, "final train loss", [fmt(v, "rmse") for v in table["final_train_loss"]])
        markdown = frame_to_markdown(shown) if len(table) else "no variant trained\n"
        _write_table(table, tables, INPUT_ABLATION, markdown)
        rt.plot_input_ablation(models, figures / f"{INPUT_ABLATION}_curves.png")
        lines += ["### Input ablation (Chaitanya et al. 2017, Fig. 3)", "",
                  "Same data, seed and budget for every input set; ± over validation sequences.", "", markdown,
                  f"![Input ablation](figures/{INPUT_ABLATION}_curves.png)", ""]
    if any(p.endswith(f"{LOSS_ABLATION}.csv") for p in expected["tables"]):
        table = rt.loss_ablation_table(models)
        shown = _with_ci_columns(table.rename(columns={"val_ssim": "val_ssim_mean", "val_ssim_low": "val_ssim_ci_low",
                                                       "val_ssim_high": "val_ssim_ci_high"}),
                                 {"val SSIM": ("val_ssim", "ssim")}, ["variant", "model", "loss_weights", "steps"],
                                 ["val_sequences", "paper_ssim"]) if len(table) else table
        markdown = frame_to_markdown(shown) if len(table) else "no variant trained\n"
        _write_table(table, tables, LOSS_ABLATION, markdown)
        rt.plot_loss_ablation(models, figures / f"{LOSS_ABLATION}_curves.png")
        lines += ["### Loss ablation (Chaitanya et al. 2017, §4.4)", "", markdown,
                  f"![Loss ablation](figures/{LOSS_ABLATION}_curves.png)", ""]
    if models.missing:
        lines += [f"Not trained (no complete model directory): {', '.join(models.missing)}", ""]
    return "\n".join(lines)


def build_report(cfg: dict, results_dir: Path, out_dir: Path | None = None) -> list[Path]:
    """Compute every table, figure and REPORT.md from the evaluation outputs under ``results_dir``;
    write them under ``out_dir`` (default ``results_dir``). Returns the written paths."""
    import pandas as pd

    results_dir = Path(results_dir)
    out_dir = Path(out_dir) if out_dir is not None else results_dir
    tables, figures = out_dir / "tables", out_dir / "figures"
    tables.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    res = collect(cfg, results_dir)

    summary = summary_table(res)
    summary_md = summary_markdown(res, summary)
    _write_table(summary, tables, "summary", summary_md)
    per_scene = res.per_scene.drop(columns=["pixels"], errors="ignore")
    _write_table(per_scene, tables, "per_scene", frame_to_markdown(_display(
        per_scene, {c: c for c in (*ALL_METRICS, *TIMING_COLUMNS)})))
    _write_table(pivot_table(res, summary, ["psnr"]), tables, "psnr_by_spp")
    _write_table(pivot_table(res, summary, ["psnr", "trmae"]), tables, "isik_video")
    chaitanya = chaitanya_table(res)
    scene_columns = [c for c in chaitanya.columns if c.endswith((" RMSE", " SSIM"))]
    chaitanya_md = frame_to_markdown(_with_ci_columns(
        _display(chaitanya, {c: "rmse" if c.endswith("RMSE") else "ssim" for c in scene_columns}),
        {}, ["method", "spp", *scene_columns], []).assign(**{
            "mean RMSE": [fmt_ci(m, lo, hi, "rmse") for m, lo, hi in
                          zip(chaitanya.get("rmse_mean", []), chaitanya.get("rmse_ci_low", []),
                              chaitanya.get("rmse_ci_high", []))],
            "mean SSIM": [fmt_ci(m, lo, hi, "ssim") for m, lo, hi in
                          zip(chaitanya.get("ssim_mean", []), chaitanya.get("ssim_ci_low", []),
                              chaitanya.get("ssim_ci_high", []))]}))
    from denoisers import report_training

    paper_fig8 = report_training.paper_fig8_table()
    chaitanya_md += ("\nPaper (Chaitanya et al. 2017, Fig. 8; 1 spp, 1-bounce GI, 1080p, 2000-4000 spp targets; "
                     "other scenes, for context only):\n\n" + frame_to_markdown(paper_fig8))
    _write_table(chaitanya, tables, "chaitanya_fig8", chaitanya_md)
    timing = timing_table(res)
    timing_md = frame_to_markdown(_display(timing, {c: c.rsplit("_", 1)[0].replace("_ci", "") for c in timing.columns
                                                    if c.endswith(("_mean", "_low", "_high"))}))
    _write_table(timing, tables, "timing", timing_md)
    equal_time = equal_time_table(res)
    equal_time_md = frame_to_markdown(_with_ci_columns(
        _display(equal_time, {"denoise_ms_per_frame": "ms_per_frame", "render_msamples_per_s": "",
                              "equal_time_spp": "", "psnr_denoiser": "psnr", "psnr_path_tracing": "psnr"}),
        {"PSNR difference": ("psnr_diff", "psnr")},
        ["method_id", "spp", "denoise_ms_per_frame", "render_msamples_per_s", "equal_time_spp", "path_tracing_row",
         "psnr_denoiser", "psnr_path_tracing"], ["better"])) if len(equal_time) else "no denoiser ran\n"
    _write_table(equal_time, tables, "equal_time", equal_time_md)
    noise = noise_floor_table(res)
    noise_md = frame_to_markdown(_display(noise, {c: "psnr" for c in ("psnr_halves", "reference_noise_floor_psnr",
                                                                       "best_psnr", "headroom_db")}))
    _write_table(noise, tables, "noise_floor", noise_md)
    robustness_md = None
    if res.robustness is not None:
        robustness = robustness_table(res)
        robustness_md = frame_to_markdown(_with_ci_columns(robustness, {
            "PSNR clean": ("psnr_clean", "psnr"), "PSNR spiked": ("psnr_spiked", "psnr"),
            "PSNR drop": ("psnr_drop", "psnr")}, ["method_id", "spp", "status"],
            ["spikes", "nan_values", "inf_values", "nonfinite_inputs", "nonfinite_outputs"]))
        _write_table(robustness, tables, "robustness", robustness_md)
    else:
        _write_table(pd.DataFrame({"status": ["disabled (evaluation.robustness.enabled: false)"]}), tables,
                     "robustness")
    claims = claims_table(res)
    _write_table(claims, tables, "claims")
    runs = pd.DataFrame(res.runs)
    _write_table(runs, tables, "runs")
    _write_table(split_table(cfg), tables, "split")

    training_md = _write_training(res, cfg, tables, figures, paper_fig8)

    plot_quality_vs_speed(res, summary, [figures / "quality_vs_speed.png", figures / "quality_vs_speed.svg"])
    for scene in res.scenes:
        plot_frame_curves(res, scene, figures / f"frame_curves_{scene}.png")
    plot_grids(res, figures)

    expected = report_outputs(cfg, root=str(out_dir))
    links = {p: str(Path(p).relative_to(out_dir))
             for group in ("tables", "quality", "curves", "grids", "training_tables", "training_figures")
             for p in expected[group] if p.endswith((".csv", ".png", ".svg"))}
    not_run = [r for r in res.runs if r["status"] != "ran"]
    text = _report_markdown(res, links, summary_md, claims, equal_time_md, robustness_md, noise_md, not_run,
                            training_md)
    write_text_atomic(out_dir / "REPORT.md", text)
    written = [Path(p) for group in expected.values() for p in group]
    absent = [p for p in written if not p.is_file()]
    if absent:
        raise EvaluationError(f"report did not write {', '.join(map(str, absent))}")
    return written
