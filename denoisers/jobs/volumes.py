"""The volumetric clips' evaluation (Iglesias-Guitian et al. 2022; issue 14 §3): which rows run on which clips,
and where their outputs go.

* rule denoise_volume: ``python -m denoisers denoise`` (denoisers.jobs.denoise.denoise_clip, unchanged) on a
  vol_test_* clip -> <out>/volumes/denoised/{method}/{scene}/spp{spp}/ (frames, timing.json, like denoise_clip);
* rule evaluate_volume: ``python -m denoisers evaluate`` (per-frame metrics against the volpath reference)
  -> <out>/volumes/metrics/{method}/{scene}/spp{spp}.csv + .json;
* rule robustness_volume: ``python -m denoisers robustness`` (the spike/NaN scenario of evaluation.robustness)
  for the rows with ``robustness: true`` -> <out>/volumes/robustness/{method}/{scene}/spp{spp}/.

The rows are ``volumes.rows`` (denoisers.evaluate.volume_method_specs), each at ``volumes.denoise_spp``
(narrowed by its own ``spp``). A run is not run, with the reason, when its method reads a buffer the
volumetric clips do not have (they hold scenegen.channels.VOLUME_BUFFERS: no normals, no diffuse/specular
split) or more sample layers than they hold (``volumes.spp``). Only the vol_test_* clips are evaluated; the
vol_train_* clips are for training.
"""
from __future__ import annotations

from pathlib import Path

from denoisers.evaluate import Run, volume_method_specs
from denoisers.training.models import resolve_method_params
from scenegen.catalog import VOLUME_CUSTOM_PREFIX, VOLUME_PREFIX, volume_scene_ids

VOLUME_TEST_PREFIX = f"{VOLUME_PREFIX}test_"


def volume_test_scene_ids(cfg: dict) -> list[str]:
    """The evaluated volumetric clips: every vol_test_* id of the config, then the bring-your-own vol_custom_*."""
    return [scene for scene in volume_scene_ids(cfg) if scene.startswith((VOLUME_TEST_PREFIX, VOLUME_CUSTOM_PREFIX))]


def volume_layers(cfg: dict) -> int:
    """Sample layers of every buffer of a volumetric clip (volumes.spp, null = render.spp)."""
    volumes = cfg["volumes"]
    return int(volumes["spp"] if volumes.get("spp") is not None else cfg["render"]["spp"])


def volume_problems(cfg: dict) -> list[str]:
    """Constraints of ``volumes.rows`` the JSON schema cannot express: unique ids (also against the evaluation rows
    and the ablation variants' rows), spp within ``volumes.denoise_spp``. Unknown methods are reported when the
    runs are planned (registry.build names the registered ones); checking here would import every method."""
    from denoisers.evaluate import method_specs

    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return []
    problems = []
    rows = volumes.get("rows", [])
    ids = [entry["id"] for entry in rows]
    for row_id in sorted({i for i in ids if ids.count(i) > 1}):
        problems.append(f"config key 'volumes.rows' has the id {row_id!r} more than once; allowed: unique ids")
    for row_id in sorted(set(ids) & {spec.id for spec in method_specs(cfg)}):
        problems.append(f"config key 'volumes.rows' has the id {row_id!r}, which an evaluation row (evaluation.methods "
                        "or an ablation variant) already has; allowed: ids of their own (e.g. vol_<method>)")
    from denoisers.training.models import method_model, model_specs

    models = [spec.id for spec in model_specs(cfg)]
    denoise_spp = list(volumes.get("denoise_spp", []))
    for index, entry in enumerate(rows):
        model = method_model(entry.get("params") or {})
        if model is not None and model not in models:
            problems.append(f"config key 'volumes.rows' row {entry['id']!r} uses model {model!r}, which training does "
                            f"not define; allowed: {', '.join(models) or 'none (training.models is empty)'}")
        outside = [spp for spp in entry.get("spp") or [] if spp not in denoise_spp]
        if outside:
            problems.append(f"config key 'volumes.rows[{index}].spp' (row {entry['id']!r}) = {entry['spp']!r} has "
                            f"values {outside} that are not in 'volumes.denoise_spp' = {denoise_spp!r}")
    return problems


def volume_runs(cfg: dict) -> list[Run]:
    """Every (volume row, spp), runnable or not (Run.not_run names the missing buffer or layers)."""
    from denoisers import registry
    from scenegen.channels import PIXEL_BUFFERS, VOLUME_BUFFERS, VOLUME_ZERO_PIXEL_BUFFERS

    layers = volume_layers(cfg)
    runs = []
    for spec in volume_method_specs(cfg):
        method = registry.build(spec.method, resolve_method_params(cfg, spec.params), row=spec.id)
        missing = [b for b in method.info.inputs if b not in VOLUME_BUFFERS]
        missing += [b for b in method.info.pixel_inputs if b not in PIXEL_BUFFERS]
        zeros = [b for b in method.info.pixel_inputs if b in VOLUME_ZERO_PIXEL_BUFFERS]
        for spp in spec.spp:
            needed = spp * method.samples_factor
            if missing:
                reason = (f"not run (reads buffer {missing[0]!r}, which volumetric clips do not have; they hold "
                          f"{', '.join(VOLUME_BUFFERS)})")
            elif zeros:
                reason = f"not run (reads {zeros[0]!r}, which volumetric clips store as zeros: no surfaces)"
            elif needed > layers:
                reason = f"not run (needs {needed} sample layers, the clips have {layers}; raise volumes.spp)"
            else:
                reason = ""
            runs.append(Run(spec, spp, method.samples_factor, reason))
    return runs


def volume_robustness_runs(cfg: dict) -> list[Run]:
    """The runs of the spike/NaN scenario on the evaluated clips: every runnable volume row with ``robustness: true``
    at ``evaluation.robustness.spp`` (when that scenario is enabled and the row denoises at that spp)."""
    robustness = cfg["evaluation"]["robustness"]
    if not robustness["enabled"]:
        return []
    wanted = {entry["id"] for entry in (cfg.get("volumes") or {}).get("rows", []) if entry.get("robustness")}
    return [run for run in volume_runs(cfg)
            if run.runnable and run.spec.id in wanted and run.spp == int(robustness["spp"])]


def volume_denoised_dir(results: Path | str, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "volumes" / "denoised" / method_id / scene / f"spp{spp}"


def volume_metrics_csv(results: Path | str, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "volumes" / "metrics" / method_id / scene / f"spp{spp}.csv"


def volume_robustness_dir(results: Path | str, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "volumes" / "robustness" / method_id / scene / f"spp{spp}"
