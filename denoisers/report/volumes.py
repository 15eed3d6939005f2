"""Collecting the volumetric clips' evaluation (rules denoise_volume, evaluate_volume; denoisers.jobs.volumes): the
per-frame metrics of every volume row on every vol_test_* clip, checked against this config's settings digests
like every other output the report reads (denoisers.experiment.Lineage)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from denoisers.evaluate import (ALL_METRICS, ROBUSTNESS_CSV, ROBUSTNESS_SUMMARY, TIMING_FILE, MethodSpec, metrics_sidecar,
                                volume_method_specs)
from denoisers.experiment import DIGEST_KEY, DigestLedger, Lineage
from denoisers.report.seeds import SeedAveraged
from denoisers.report.stats import pooled_psnr
from denoisers.jobs.volumes import (volume_denoised_dir, volume_metrics_csv, volume_robustness_dir, volume_robustness_runs,
                                   volume_runs, volume_test_scene_ids)
from scenegen.catalog import volume_clip_spec

if TYPE_CHECKING:
    import pandas as pd


@dataclass
class VolumeResults(SeedAveraged):
    """The volume rows' results. ``runs``: every (row, spp) with status 'ran' or 'not run' and the reason;
    ``frames``: per-frame metrics (method_id, spp, scene, scenario, frame, ...); ``per_scene``: their means per
    (method_id, spp, scene) with the clip's scenario and its video PSNR."""

    specs: list[MethodSpec]
    scenes: list[str]                  # the evaluated clips (vol_test_*): the units of the volume claims
    scenarios: dict[str, str]          # clip -> scenario kind (camera, light, transfer_function)
    runs: list[dict]
    frames: pd.DataFrame
    per_scene: pd.DataFrame
    robustness: pd.DataFrame | None = None   # spike scenario: method_id, scene, spp, {metric}_spiked (None: none ran)

    def ran(self, method_id: str | None, spp: int) -> bool:
        return method_id is not None and any(
            r["id"] == method_id and r["spp"] == spp and r["status"] == "ran" for r in self.runs)

    def row_of(self, method: str, **params: object) -> str | None:
        """The first volume row of registry method ``method`` (whose params include ``params``) that ran."""
        for spec in self.specs:
            if spec.method == method and all(spec.params.get(k) == v for k, v in params.items()) and any(
                    r["id"] == spec.id and r["status"] == "ran" for r in self.runs):
                return spec.id
        return None

    def reason(self, method_id: str, spp: int) -> str:
        return next((r["reason"] for r in self.runs if r["id"] == method_id and r["spp"] == spp), "not configured")



def collect_volumes(cfg: dict, results_dir: Path, ledger: DigestLedger) -> VolumeResults | None:
    """Read every volume row's metrics on every vol_test_* clip below ``results_dir`` (None when the config has
    no evaluated volumetric clips). A (row, spp) counts as ran only when every clip has its metrics and
    timing.json; the outputs' recorded digests go into ``ledger``."""
    import pandas as pd

    scenes = volume_test_scene_ids(cfg)
    if not scenes:
        return None
    lineage = Lineage(cfg)
    scenarios = {scene: volume_clip_spec(cfg, scene)[1] for scene in scenes}
    runs, tables = [], []
    planned = volume_runs(cfg)
    for run in planned:
        spec, spp = run.spec, run.spp
        entry = {"id": spec.id, "method": spec.method, "spp": spp}
        if not run.runnable:
            runs.append({**entry, "status": "not run", "reason": run.not_run})
            continue
        missing = [s for s in scenes if not volume_metrics_csv(results_dir, spec.id, s, spp).is_file()
                   or not (volume_denoised_dir(results_dir, spec.id, s, spp) / TIMING_FILE).is_file()]
        if missing:
            runs.append({**entry, "status": "not run", "reason": f"not run (results missing for {', '.join(missing)})"})
            continue
        runs.append({**entry, "status": "ran", "reason": ""})
        for scene in scenes:
            csv = volume_metrics_csv(results_dir, spec.id, scene, spp)
            sidecar = metrics_sidecar(csv)
            recorded = json.loads(sidecar.read_text()).get(DIGEST_KEY) if sidecar.is_file() else None
            ledger.add(sidecar if sidecar.is_file() else csv, recorded, lineage.metrics(spec, scene, spp))
            timing_path = volume_denoised_dir(results_dir, spec.id, scene, spp) / TIMING_FILE
            ledger.add(timing_path, json.loads(timing_path.read_text()).get(DIGEST_KEY),
                       lineage.denoised(spec, scene, spp))
            table = pd.read_csv(csv)
            table.insert(0, "scenario", scenarios[scene])
            table.insert(0, "scene", scene)
            table.insert(0, "spp", spp)
            table.insert(0, "method_id", spec.id)
            tables.append(table)
    columns = [*ALL_METRICS, "reference_psnr_halves"]
    if tables:
        frames = pd.concat(tables, ignore_index=True)
        grouped = frames.groupby(["method_id", "spp", "scene", "scenario"], sort=False)
        per_scene = grouped[columns].mean().reset_index()
        per_scene["video_psnr"] = grouped["psnr"].agg(pooled_psnr).to_numpy()
    else:
        frames = pd.DataFrame(columns=["method_id", "spp", "scene", "scenario", "frame", *columns])
        per_scene = pd.DataFrame(columns=["method_id", "spp", "scene", "scenario", *columns, "video_psnr"])
    return VolumeResults(volume_method_specs(cfg), scenes, scenarios, runs, frames, per_scene,
                         _collect_robustness(cfg, results_dir, scenes, ledger, lineage))


def _collect_robustness(cfg: dict, results_dir: Path, scenes: list[str], ledger: DigestLedger,
                        lineage: Lineage) -> pd.DataFrame | None:
    """Frame means of the spike scenario's metrics per (row, clip) for every volume robustness run whose every clip
    has its outputs (None when no row has them)."""
    import pandas as pd

    rows = []
    for run in volume_robustness_runs(cfg):
        folders = {scene: volume_robustness_dir(results_dir, run.spec.id, scene, run.spp) for scene in scenes}
        if not all((folder / ROBUSTNESS_CSV).is_file() and (folder / ROBUSTNESS_SUMMARY).is_file()
                   for folder in folders.values()):
            continue
        for scene, folder in folders.items():
            summary = json.loads((folder / ROBUSTNESS_SUMMARY).read_text())
            ledger.add(folder / ROBUSTNESS_SUMMARY, summary.get(DIGEST_KEY), lineage.robustness(run.spec, scene, run.spp))
            table = pd.read_csv(folder / ROBUSTNESS_CSV)
            rows.append({"method_id": run.spec.id, "scene": scene, "spp": run.spp,
                         **{f"{metric}_spiked": table[metric].mean() for metric in ALL_METRICS}})
    return pd.DataFrame(rows) if rows else None
