"""The stability suite's evaluation (issue 15 §2): which rows run on the scenario clips, where their outputs
go, and the job behind rule score_scenario.

* rule denoise_scenario: ``python -m denoisers denoise`` (denoisers.jobs.denoise.denoise_clip, unchanged) on a
  stab_* clip -> <out>/stability/denoised/{method}/{scene}/spp{spp}/
* rule score_scenario: :func:`score_scenario` -> <out>/stability/scores/{method}/{scene}/spp{spp}.csv (per-frame
  failure metrics, denoisers.stability_metrics) + .json (clip summary and settings digest)

Every configured evaluation row (``evaluation.methods``; not the ablation variants) runs on every scenario at
every ``stability.denoise_spp`` that its sample layers allow (a scenario clip has ``stability.spp`` layers).
Config level only at import time (no torch): the Snakefile calls the planning helpers while it is parsed.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from denoisers.evaluate import METHOD_ROLE, MethodSpec, Run, method_specs
from scenegen.catalog import scene_render_config, stability_scene_ids
from scenegen.config import config_digest, short_digest

#: Defaults of the evaluation keys of the ``stability`` section (the schema's).
DEFAULT_DENOISE_SPP: tuple[int, ...] = (2,)
SCORES_JSON_KEYS = ("method_id", "scene", "scenario", "spp", "focus")


def stability_settings(cfg: dict) -> dict[str, Any]:
    """``stability.denoise_spp`` (list) and ``stability.margin`` with their defaults."""
    section = cfg.get("stability") or {}
    return {"denoise_spp": [int(s) for s in section.get("denoise_spp", DEFAULT_DENOISE_SPP)],
            "margin": float(section.get("margin", 0.1))}


def stability_rows(cfg: dict) -> list[MethodSpec]:
    """The rows run on the scenarios: the configured rows of ``evaluation.methods`` (all of them, or those named
    by ``stability.rows``), in table order; ValueError naming an id that is not a row."""
    rows = [spec for spec in method_specs(cfg) if spec.role == METHOD_ROLE]
    chosen = (cfg.get("stability") or {}).get("rows")
    if chosen is None:
        return rows
    unknown = sorted(set(chosen) - {spec.id for spec in rows})
    if unknown:
        raise ValueError(f"config key 'stability.rows' names {unknown}, which are not rows of evaluation.methods; "
                         f"allowed: {[spec.id for spec in rows]}")
    return [spec for spec in rows if spec.id in chosen]


def stability_runs(cfg: dict) -> list[Run]:
    """Every (row, spp) of the suite, runnable or not: a run needing more sample layers than a scenario clip has
    (``stability.spp`` + render.extra_radiance_spp) is marked not runnable. Builds each row's method (torch)."""
    from denoisers.evaluate import _plan

    scenes = stability_scene_ids(cfg)
    if not scenes:
        return []
    clip_cfg = {**cfg, "render": scene_render_config(cfg, scenes[0])}
    spps = stability_settings(cfg)["denoise_spp"]
    return _plan(clip_cfg, stability_rows(cfg), lambda spec: spps)


def atlas_digest(cfg: dict) -> str:
    """Rule build_atlas's settings: the stability section and the configured rows."""
    return config_digest({"stability": cfg.get("stability"), "methods": cfg["evaluation"]["methods"]})


def scenario_denoised_dir(results: Path | str, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "stability" / "denoised" / method_id / scene / f"spp{spp}"


def scores_csv(results: Path | str, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "stability" / "scores" / method_id / scene / f"spp{spp}.csv"


def score_digest(cfg: dict) -> str:
    """Rule score_scenario's own settings: the margin and the warm-up frames of the temporal metrics."""
    return config_digest({"margin": stability_settings(cfg)["margin"],
                          "warmup_frames": cfg["evaluation"]["warmup_frames"]})


def scores_lineage(cfg: dict, spec: MethodSpec, scene: str, spp: int) -> str:
    """Recorded digest of a scores file: the denoised clip's lineage, the reference and masks settings, the
    scoring settings, and the control clip's denoised lineage and reference settings (when it has one)."""
    from denoisers.experiment import Lineage
    from scenegen.digests import masks_digest, render_digest
    from scenegen.scenarios import scenario_control

    control = scenario_control(cfg, scene)
    parts = {"denoised": Lineage(cfg).denoised(spec, scene, spp), "reference": render_digest(cfg, scene, "reference"),
             "masks": masks_digest(cfg, scene), "score": score_digest(cfg)}
    if control is not None:
        parts["control"] = {"denoised": Lineage(cfg).denoised(spec, control, spp),
                            "reference": render_digest(cfg, control, "reference")}
    return short_digest(config_digest(parts))


def load_masks(masks_dir: Path, frames: list[int]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """({kind: (T, H, W) bool}, events.json) of a scenario (rule derive_masks' output directory)."""
    from scenegen.exr import read_exr
    from scenegen.scenarios import MASK_KINDS

    masks_dir = Path(masks_dir)
    events_path = masks_dir / "events.json"
    if not events_path.is_file():
        raise FileNotFoundError(f"{events_path}: no events.json (rule derive_masks)")
    planes = []
    for t in frames:
        path = masks_dir / "masks" / f"frame_{t:04d}.exr"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: mask frame {t} is missing (rule derive_masks)")
        planes.append(read_exr(path, [f"mask.{kind}" for kind in MASK_KINDS])[0])
    masks = {kind: np.stack([plane[f"mask.{kind}"] > 0.5 for plane in planes]) for kind in MASK_KINDS}
    return masks, json.loads(events_path.read_text())


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (np.integer, np.floating)):
        return _jsonable(value.item())
    return value


def _load_denoised_clip(cfg: dict, denoised: Path, render_dir: Path,
                        expected: tuple[str, str, int] | None = None) -> tuple:
    """(row spec, scene, spp, frames, pred (T, 3, H, W), reference (T, 3, H, W), reference frame records, the
    denoise job's timing record) of a denoised stability clip; refuses a clip whose recorded digest is not this
    config's, or (``expected`` = (row, scene, spp)) that is not the one asked for."""
    from denoisers.evaluate import EvaluationError, TIMING_FILE, method_spec, read_frame_files, read_radiance_exr
    from denoisers.experiment import DIGEST_KEY, Lineage, check_recorded
    from denoisers.jobs.scoring import load_references

    timing_path = Path(denoised) / TIMING_FILE
    if not timing_path.is_file():
        raise EvaluationError(f"{timing_path}: missing (rule denoise_scenario writes it)")
    timing = json.loads(timing_path.read_text())
    spec, scene, spp = method_spec(cfg, timing["method_id"]), timing["scene"], int(timing["spp"])
    if expected is not None and (spec.id, scene, spp) != expected:
        raise EvaluationError(f"{denoised}: holds row {spec.id}, scene {scene}, spp {spp}; expected row "
                              f"{expected[0]}, scene {expected[1]}, spp {expected[2]}")
    check_recorded(timing_path, timing.get(DIGEST_KEY), Lineage(cfg).denoised(spec, scene, spp))
    frames, _, reference, ref_meta = load_references(Path(render_dir))
    found = read_frame_files(Path(denoised))
    if sorted(found) != frames:
        raise EvaluationError(f"{denoised}: denoised frames {sorted(found)} differ from the reference frames {frames}")
    pred = np.nan_to_num(np.stack([read_radiance_exr(found[t]) for t in frames]), nan=0.0, posinf=0.0, neginf=0.0)
    return spec, scene, spp, frames, pred, reference, ref_meta, timing


def score_scenario(cfg: dict, denoised: Path, render_dir: Path, masks_dir: Path, out_csv: Path,
                   control_denoised: Path | None = None, control_render_dir: Path | None = None) -> dict[str, Any]:
    """Failure metrics of one denoised scenario clip (denoisers.stability_metrics.scenario_scores) against its
    reference, masks and events -> ``out_csv`` (per frame) and its .json (summary with the settings digest).
    An animated scenario needs its control clip's denoised output (same row and spp) and render directory: the
    lag metric's steady state. Refuses a denoised clip whose recorded digest is not this config's, a missing or
    mismatched control. Returns the summary."""
    import pandas as pd

    from denoisers.evaluate import EvaluationError
    from denoisers.experiment import DIGEST_KEY
    from denoisers.stability_metrics import scenario_scores
    from scenegen.atomic import write_text_atomic
    from scenegen.dataset import load_clip
    from scenegen.scenarios import scenario_control

    render_dir = Path(render_dir)
    spec, scene, spp, frames, pred, reference, ref_meta, timing = _load_denoised_clip(cfg, Path(denoised), render_dir)
    control_id = scenario_control(cfg, scene)
    control = None
    if control_id is not None:
        if control_denoised is None or control_render_dir is None:
            raise EvaluationError(f"{scene} is animated: scoring it needs its control clip {control_id} denoised by "
                                  f"{spec.id} at {spp} spp (--control-denoised, --control-render-dir)")
        control = _load_denoised_clip(cfg, Path(control_denoised), Path(control_render_dir),
                                      expected=(spec.id, control_id, spp))[4:6]
    elif control_denoised is not None:
        raise EvaluationError(f"{scene}: its scenario is not animated and has no control clip; got {control_denoised}")
    masks, events = load_masks(masks_dir, frames)
    clip = load_clip(render_dir, buffers=["radiance"], spp=1, reference=False)
    if pred.shape != reference.shape or masks["subject"].shape != (len(frames), *reference.shape[2:]):
        raise EvaluationError(f"{denoised}: shapes differ: denoised {pred.shape}, reference {reference.shape}, "
                              f"masks {masks['subject'].shape} in {masks_dir}")
    cuts = [bool(meta.get("camera_cut", False)) for meta in ref_meta]
    settings = stability_settings(cfg)
    per_frame, summary = scenario_scores(pred, reference, masks, events["focus"], events["events"], clip.motion,
                                         clip.valid[:, 0], cuts, cfg["evaluation"]["warmup_frames"],
                                         settings["margin"], control)
    table = pd.DataFrame({"frame": frames, **per_frame, "camera_cut": cuts})
    record = {"method_id": spec.id, "method": spec.method, "scene": scene, "scenario": events["scenario"], "spp": spp,
              "focus": events["focus"], "events": events["events"], "frames": len(frames), "control": control_id,
              **{key: _jsonable(value) for key, value in summary.items()},
              "mean_seconds": timing.get("mean_seconds"), "median_seconds": timing.get("median_seconds"),
              DIGEST_KEY: scores_lineage(cfg, spec, scene, spp)}
    write_text_atomic(Path(out_csv).with_suffix(".json"), json.dumps(record, indent=1) + "\n")
    write_text_atomic(Path(out_csv), table.to_csv(index=False))
    return record
