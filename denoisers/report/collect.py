"""Collecting what the report is computed from: per-frame metric CSVs, timing.json, the robustness
scenario (rules evaluate_row, denoise_row, robustness_row), the timing job (time_methods: every speed
number of the report), the training-speed job (time_training), the trained models (train_denoiser, read by
denoisers.report.trained) and the manifests of the external scenes (generate_scene: what was rendered and what
was substituted).

Nothing here computes a verdict; :class:`Results` only answers lookups (which rows ran, per-scene
values of a column, rows whose outputs were flagged as non-finite or absurd).

Every output read is checked against the settings digest this config expects for it
(denoisers.experiment.Lineage): outputs computed from other settings (another seed, other render or
method settings) are not combined; :func:`collect` raises SettingsMismatchError naming each of them.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.evaluate import (
    ALL_METRICS,
    ROBUSTNESS_CSV,
    ROBUSTNESS_SUMMARY,
    TIMING_FILE,
    MethodSpec,
    denoised_dir,
    evaluated_scene_ids,
    method_spec,
    method_specs,
    metrics_csv,
    metrics_sidecar,
    robustness_dir,
)
from denoisers.experiment import DIGEST_KEY, DigestLedger, Lineage
from denoisers.report.seeds import SeedAveraged, seed_mean
from denoisers.report.stats import pooled_psnr
from denoisers.report.trained import MIN_TRAINING_STEPS, TrainedModel, TrainedModels, collect_models
from denoisers.report.volumes import VolumeResults, collect_volumes
from denoisers.jobs.timing import TIMING_JOB_FILE, TimingJob, read_timing_job, timed_runs, timing_scene, timing_settings
from denoisers.training.speed import TRAINING_SPEED_FILE, read_training_speed, speed_models
from denoisers.jobs.tuning import TUNED_KEY, tuning_file
from scenegen.catalog import CUSTOM_PREFIX
from scenegen.config import output_root

if TYPE_CHECKING:
    import pandas as pd

#: Cost columns aggregated over scenes like metrics (from each denoise job's timing.json).
TIMING_COLUMNS: tuple[str, ...] = ("peak_memory_mb",)
#: Speed columns: from the timing job only (median and range over its rounds), never from the denoise jobs,
#: whose times depend on what else ran beside them (kept in per_scene.csv as clip_ms_per_frame).
SPEED_COLUMNS: tuple[str, ...] = ("ms_per_frame", "mpix_per_s")
#: Per-scene columns derived from the per-frame metrics (Isik et al. 2021 Eq. 14: MSE pooled over frames).
DERIVED_METRICS: tuple[str, ...] = ("video_psnr",)


# ------------------------------------------------------------------------------------------ results
@dataclass
class Results(SeedAveraged):
    """Everything the report is computed from."""

    cfg: dict
    specs: list[MethodSpec]                   # every evaluation row (configured rows, then ablation rows)
    scenes: list[str]                         # evaluated scenes: the units of every comparison
    runs: list[dict]                          # every planned (row, spp): id, method, spp, status, reason
    frames: pd.DataFrame                      # per-frame metrics of runs that exist: method_id, spp, scene, frame, ...
    per_scene: pd.DataFrame                   # per (method_id, spp, scene): frame means, video PSNR, timing, counts
    robustness: pd.DataFrame | None = None    # per (method_id, scene): spiked metrics and counts
    results_dir: Path | None = None           # the experiment folder read (None: the config's output_dir)
    models: TrainedModels | None = None
    external: dict[str, dict | None] = field(default_factory=dict)   # custom_* scene -> manifest (None: missing)
    digests: DigestLedger | None = None       # settings digests of the outputs read
    timing: TimingJob | None = None           # the timing job's record (None: disabled or not run)
    training_speed: dict | None = None        # the training-speed job's record (None: disabled or not run)
    volumes: VolumeResults | None = None      # the volume rows on the vol_test_* clips (None: no such clips)

    def __post_init__(self) -> None:
        if self.results_dir is None:
            self.results_dir = output_root(self.cfg)

    @property
    def external_scenes(self) -> list[str]:
        """The evaluated external (bring-your-own XML) scenes, in evaluation order."""
        return [scene for scene in self.scenes if scene.startswith(CUSTOM_PREFIX)]

    @property
    def main_specs(self) -> list[MethodSpec]:
        """Configured rows (the ones in the cross-paper tables, chart and grids); ablation rows excluded."""
        return [spec for spec in self.specs if spec.role == "method"]

    def ran(self, method_id: str | None, spp: int) -> bool:
        return method_id is not None and any(
            r["id"] == method_id and r["spp"] == spp and r["status"] == "ran" for r in self.runs)

    def rows_of(self, method: str, role: str = "method", **params: Any) -> list[str]:
        """Row ids of ``role`` whose registry method is ``method`` (and whose params include ``params``) that
        produced results at some spp; the params value None matches a missing or false key, any other value
        the row's value or, where the row leaves the key out, the method's constructor default (so
        ``budget_factor=1`` matches a row with ``budget_factor: 1`` and one without the key)."""
        from denoisers import registry

        defaults = registry.parameters(method) if method in registry.available() else {}

        def matches(spec: MethodSpec) -> bool:
            return spec.role == role and spec.method == method and all(
                (not spec.params.get(key)) if value is None else spec.params.get(key, defaults.get(key)) == value
                for key, value in params.items())

        return [spec.id for spec in self.specs if matches(spec)
                and any(r["id"] == spec.id and r["status"] == "ran" for r in self.runs)]

    def row_of(self, method: str, role: str = "method", **params: Any) -> str | None:
        rows = self.rows_of(method, role, **params)
        return rows[0] if rows else None

    def spec(self, method_id: str) -> MethodSpec:
        return next(spec for spec in self.specs if spec.id == method_id)

    def claim_values(self, method_id: str, spp: int, column: str) -> pd.Series:
        """:meth:`claim_values_per_seed` averaged over the row's seeds per scene (on the scenes every seed has)."""
        return seed_mean(self.claim_values_per_seed(method_id, spp, column))

    def claim_values_per_seed(self, method_id: str, spp: int, column: str) -> list[pd.Series]:
        """The per-scene values the claims decide on of each seed of the row (:meth:`seed_rows`), seed order."""
        return [self._own_claim_values(row, spp, column) for row in self.seed_rows(method_id, spp)]

    def _own_claim_values(self, method_id: str, spp: int, column: str) -> pd.Series:
        """Per-scene values the claims decide on, indexed by scene: a frame metric averaged over each clip's
        steady frames only (:func:`steady_frames`: the first evaluation.warmup_frames frames of the clip and of
        every shot after a camera cut left out, for every method alike, since they bias against temporal
        methods); video_psnr pooled over the same frames. Other columns, and results without per-frame tables
        (hand-built ones), are scene_values."""
        if self.frames.empty or column not in self.frames.columns and column != "video_psnr":
            return self.own_scene_values(method_id, spp, column)
        rows = self.frames[(self.frames.method_id == method_id) & (self.frames.spp == spp)]
        if rows.empty:
            return self.own_scene_values(method_id, spp, column)
        warmup = int(self.cfg["evaluation"].get("warmup_frames", 0))
        steady = rows[steady_frames(rows, warmup)]
        grouped = steady.groupby("scene", sort=False)
        values = grouped["psnr"].agg(pooled_psnr) if column == "video_psnr" else grouped[column].mean()
        return values.reindex(rows["scene"].unique())

    def flag(self, method_id: str, spp: int) -> str:
        """'' or why this row's outputs are suspect: non-finite values or values far outside the input range."""
        rows = self.per_scene[(self.per_scene.method_id == method_id) & (self.per_scene.spp == spp)]
        parts = []
        nonfinite = rows["nonfinite_outputs"].sum() if "nonfinite_outputs" in rows else 0
        absurd = rows["out_of_range_outputs"].sum() if "out_of_range_outputs" in rows else 0
        if nonfinite > 0:
            parts.append(f"{int(nonfinite):,} non-finite output values")
        if absurd > 0:
            factor = rows["out_of_range_factor"].max()
            parts.append(f"{int(absurd):,} output values beyond {factor:g}x the largest input sample")
        for row in self.seed_rows(method_id, spp):     # every seed's model
            model = self.model_of(row)
            steps = model.summary.get("steps") if model else None
            if steps is not None and steps < MIN_TRAINING_STEPS:
                parts.append(f"model {model.spec.id} trained only {steps} steps")
            elif model is not None and model.undertrained(self.cfg):
                parts.append(model.undertrained(self.cfg))
        return f"{method_id} @ {spp} spp: " + ", ".join(parts) if parts else ""

    def speed(self, method_id: str | None, spp: int) -> dict[str, Any] | None:
        """The timing job's record of (row, spp): ms_per_frame (median over rounds), its min/max, Mpix/s."""
        return self.timing.row(method_id, spp) if self.timing is not None and method_id is not None else None

    def model_of(self, method_id: str) -> TrainedModel | None:
        if not any(spec.id == method_id for spec in self.specs):
            return None
        model_id = self.spec(method_id).params.get("model")
        return self.models.models.get(model_id) if self.models and model_id else None


def _plan_status(cfg: dict) -> dict[tuple[str, int], str]:
    """(row id, spp) -> '' if runnable, else the not-run reason (unregistered methods included)."""
    from denoisers.evaluate import plan_runs

    status = {}
    for spec in method_specs(cfg):
        try:
            for run in plan_runs(cfg, rows=[spec]):
                status[(spec.id, run.spp)] = run.not_run
        except (KeyError, TypeError, ValueError) as error:
            for spp in spec.spp:
                status[(spec.id, spp)] = f"not run (method unavailable: {error})"
    return status


def _timing_row(spec: MethodSpec, scene: str, spp: int, timing: dict) -> dict[str, Any]:
    return {"method_id": spec.id, "spp": spp, "scene": scene,
            "clip_ms_per_frame": timing["mean_seconds"] * 1e3,
            "peak_memory_mb": timing["peak_memory_mb"], "nonfinite_inputs": timing["nonfinite_inputs"],
            "nonfinite_outputs": timing["nonfinite_outputs"],
            # Older timing files carry no range check: unknown, not zero.
            "out_of_range_outputs": timing.get("out_of_range_outputs", math.nan),
            "out_of_range_factor": timing.get("out_of_range_factor", math.nan),
            "samples_factor": timing.get("samples_factor", 1),
            "pixels": timing["width"] * timing["height"]}


def collect(cfg: dict, results_dir: Path | None = None) -> Results:
    """Read every metrics CSV and timing.json of the configured runs on the evaluated scenes, the robustness
    outputs and the trained models below ``results_dir`` (default: the config's output_dir). Raises
    SettingsMismatchError, naming the files, if any of them records a settings digest other than this
    config's (outputs of another seed or other settings are never combined)."""
    import pandas as pd

    results_dir = output_root(cfg) if results_dir is None else Path(results_dir)
    ledger, lineage = DigestLedger(), Lineage(cfg)
    specs, scenes = method_specs(cfg), evaluated_scene_ids(cfg)
    plan = None
    runs, frame_tables, timing_rows = [], [], []
    for spec in specs:
        for spp in spec.spp:
            missing = [s for s in scenes if not metrics_csv(results_dir, spec.id, s, spp).is_file()
                       or not (denoised_dir(results_dir, spec.id, s, spp) / TIMING_FILE).is_file()]
            if scenes and not missing:
                runs.append({"id": spec.id, "method": spec.method, "role": spec.role, "spp": spp, "status": "ran",
                             "reason": ""})
                for scene in scenes:
                    csv = metrics_csv(results_dir, spec.id, scene, spp)
                    table = pd.read_csv(csv)
                    sidecar = metrics_sidecar(csv)
                    recorded = json.loads(sidecar.read_text()).get(DIGEST_KEY) if sidecar.is_file() else None
                    ledger.add(sidecar if sidecar.is_file() else csv, recorded, lineage.metrics(spec, scene, spp))
                    table.insert(0, "scene", scene)
                    table.insert(0, "spp", spp)
                    table.insert(0, "method_id", spec.id)
                    frame_tables.append(table)
                    timing_path = denoised_dir(results_dir, spec.id, scene, spp) / TIMING_FILE
                    timing = json.loads(timing_path.read_text())
                    ledger.add(timing_path, timing.get(DIGEST_KEY), lineage.denoised(spec, scene, spp))
                    timing_rows.append(_timing_row(spec, scene, spp, timing))
                continue
            plan = _plan_status(cfg) if plan is None else plan
            reason = plan.get((spec.id, spp), "")
            if not reason:
                reason = (f"not run (results missing for {', '.join(missing)})" if scenes
                          else "not run (no evaluated scenes)")
            runs.append({"id": spec.id, "method": spec.method, "role": spec.role, "spp": spp, "status": "not run",
                         "reason": reason})

    metric_columns = [*ALL_METRICS, "reference_psnr_halves"]
    if frame_tables:
        frames = pd.concat(frame_tables, ignore_index=True)
        grouped = frames.groupby(["method_id", "spp", "scene"], sort=False)
        per_scene = grouped[metric_columns].mean().reset_index()
        per_scene["video_psnr"] = grouped["psnr"].agg(pooled_psnr).to_numpy()
        per_scene = per_scene.merge(pd.DataFrame(timing_rows), on=["method_id", "spp", "scene"], how="left")
    else:
        frames = pd.DataFrame(columns=["method_id", "spp", "scene", "frame", *metric_columns, "camera_cut"])
        per_scene = pd.DataFrame(columns=["method_id", "spp", "scene", *metric_columns, *DERIVED_METRICS,
                                          *TIMING_COLUMNS, "nonfinite_outputs", "out_of_range_outputs"])
    robustness = _collect_robustness(cfg, results_dir, specs, scenes, ledger) \
        if cfg["evaluation"]["robustness"]["enabled"] else None
    models = collect_models(cfg, results_dir, ledger)
    for method in sorted({spec.method for spec in specs if spec.params.get(TUNED_KEY)}):
        path = tuning_file(results_dir, method)
        if path.is_file():
            ledger.add(path, json.loads(path.read_text()).get(DIGEST_KEY), lineage.tuning(method))
    timing = None
    timing_path = results_dir / TIMING_JOB_FILE
    if timing_settings(cfg)["enabled"] and timing_path.is_file():
        timing = read_timing_job(timing_path)
        timed = [(method_spec(cfg, row), spp) for row, spp in timed_runs(cfg)]
        ledger.add(timing_path, timing.record.get(DIGEST_KEY), lineage.timing(timing_scene(cfg), timed))
    training_speed = None
    speed_path = results_dir / TRAINING_SPEED_FILE
    if speed_models(cfg) and speed_path.is_file():
        training_speed = read_training_speed(speed_path)
        ledger.add(speed_path, training_speed.get(DIGEST_KEY), lineage.training_speed())
    volumes = collect_volumes(cfg, results_dir, ledger)
    ledger.raise_if_mixed(cfg, results_dir)
    return Results(cfg, specs, scenes, runs, frames, per_scene, robustness, results_dir, models,
                   external_manifests(results_dir, scenes), ledger, timing, training_speed, volumes)


def steady_frames(frames: pd.DataFrame, warmup: int) -> pd.Series:
    """Boolean mask of the rows of a per-frame table (method_id, spp, scene, frame, camera_cut) that are at
    least ``warmup`` frames after the start of their shot: the clip's first frame, or a frame with
    camera_cut true."""
    import pandas as pd

    if warmup <= 0:
        return pd.Series(True, index=frames.index)
    keys = ["method_id", "spp", "scene"]
    ordered = frames.sort_values([*keys, "frame"])
    cut = ordered["camera_cut"].fillna(False).astype(bool) if "camera_cut" in ordered else False
    first = ordered.groupby(keys, sort=False)["frame"].transform("min")
    shot_start = ordered["frame"].where(cut | (ordered["frame"] == first))
    shot_start = shot_start.groupby([ordered[key] for key in keys], sort=False).ffill()
    since = ordered["frame"] - shot_start
    return (since >= warmup).reindex(frames.index)


def external_manifests(results_dir: Path, scenes: list[str]) -> dict[str, dict | None]:
    """<results_dir>/scenes/{scene}/manifest.json of every external scene in ``scenes`` (None if absent)."""
    found = {}
    for scene in (s for s in scenes if s.startswith(CUSTOM_PREFIX)):
        path = Path(results_dir) / "scenes" / scene / "manifest.json"
        found[scene] = json.loads(path.read_text()) if path.is_file() else None
    return found


def _collect_robustness(cfg: dict, results_dir: Path, specs: list[MethodSpec], scenes: list[str],
                        ledger: DigestLedger) -> pd.DataFrame:
    import pandas as pd

    spp, lineage = cfg["evaluation"]["robustness"]["spp"], Lineage(cfg)
    rows = []
    for spec in specs:
        for scene in scenes:
            folder = robustness_dir(results_dir, spec.id, scene, spp)
            if not (folder / ROBUSTNESS_CSV).is_file():
                continue
            table = pd.read_csv(folder / ROBUSTNESS_CSV)
            summary = json.loads((folder / ROBUSTNESS_SUMMARY).read_text())
            ledger.add(folder / ROBUSTNESS_SUMMARY, summary.get(DIGEST_KEY), lineage.robustness(spec, scene, spp))
            rows.append({"method_id": spec.id, "scene": scene, "spp": spp,
                         **{f"{m}_spiked": table[m].mean() for m in ALL_METRICS},
                         "nonfinite_inputs": summary["nonfinite_inputs"],
                         "nonfinite_outputs": summary["nonfinite_outputs"],
                         "out_of_range_outputs": summary.get("out_of_range_outputs", math.nan),
                         "spikes": summary["injected"]["spikes"], "nan_values": summary["injected"]["nan_values"],
                         "inf_values": summary["injected"]["inf_values"]})
    return pd.DataFrame(rows, columns=["method_id", "scene", "spp", *[f"{m}_spiked" for m in ALL_METRICS],
                                       "nonfinite_inputs", "nonfinite_outputs", "out_of_range_outputs", "spikes",
                                       "nan_values", "inf_values"])
