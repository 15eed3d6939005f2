"""Scoring a denoised clip against its reference: what rule evaluate_row does for each clip of a row.

* ``evaluate_clip`` (each clip of rule evaluate_row): per-frame metrics of a denoised clip against the reference -> CSV

``score_sequence`` (per-frame and temporal metrics of a (T, 3, H, W) sequence) is shared with the
robustness job (denoisers.jobs.robustness). The metrics and pandas are imported by the functions that use them.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from denoisers.evaluate import (
    FRAME_METRICS,
    TEMPORAL_METRICS,
    TIMING_FILE,
    EvaluationError,
    method_spec,
    metrics_sidecar,
    read_frame_files,
    read_radiance_exr,
)
from scenegen.atomic import write_text_atomic


def load_references(render_dir: Path) -> tuple[list[int], list[Path], np.ndarray, list[dict]]:
    """Reference radiance of a clip: (frame indices, paths, (T, 3, H, W), reference sidecars)."""
    from scenegen.dataset import find_frames, load_reference_frame

    found = find_frames(Path(render_dir) / "reference")
    if not found:
        raise EvaluationError(f"{Path(render_dir) / 'reference'}: no reference frames found")
    frames = sorted(found)
    images, metas = [], []
    for t in frames:
        data, meta = load_reference_frame(found[t], ["radiance"])
        images.append(data["radiance"])
        metas.append(meta)
    return frames, [found[t] for t in frames], np.stack(images), metas


def _check_match(denoised: dict[int, Path], denoised_dir_: Path, ref_frames: list[int], render_dir: Path) -> None:
    if sorted(denoised) != ref_frames:
        raise EvaluationError(
            f"frame count mismatch: {denoised_dir_} holds {len(denoised)} denoised frames {sorted(denoised)}, "
            f"but {Path(render_dir) / 'reference'} holds {len(ref_frames)} reference frames {ref_frames}")


def _temporal_mask(n_frames: int, cuts: Sequence[bool], warmup: int) -> np.ndarray:
    """True where temporal metrics are defined: at least ``warmup`` frames (and >= 1) since the clip
    start or the last camera cut, so the predecessor belongs to the same shot."""
    mask = np.zeros(n_frames, dtype=bool)
    since = 0
    for t in range(n_frames):
        since = 0 if (t == 0 or cuts[t]) else since + 1
        mask[t] = since >= max(1, warmup)
    return mask


def score_sequence(pred: np.ndarray, ref: np.ndarray, cuts: Sequence[bool], warmup: int) -> dict[str, np.ndarray]:
    """Per-frame metrics of (T, 3, H, W) predictions against references. Non-finite predicted values are
    set to 0 before scoring (they are counted separately); temporal metrics are NaN during the first
    ``warmup`` frames and the first ``warmup`` frames after a camera cut."""
    from denoisers import metrics

    pred = np.nan_to_num(np.asarray(pred, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    ref = np.asarray(ref, np.float32)
    per_frame = [metrics.frame_metrics(p, r) for p, r in zip(pred, ref)]
    scores = {name: np.array([float(row[name]) for row in per_frame]) for name in FRAME_METRICS}
    temporal = metrics.temporal_metrics(pred, ref, warmup)
    mask = _temporal_mask(len(pred), cuts, warmup)
    for name in TEMPORAL_METRICS:
        values = np.asarray(temporal[name], dtype=np.float64).copy()
        values[~mask] = np.nan
        scores[name] = values
    return scores


def _metrics_record(cfg: dict, denoised_path: Path) -> dict[str, Any] | None:
    """The sidecar of the metrics of a denoised clip: the row, scene and spp its timing.json names and the
    settings digest of the metrics (None without timing.json). SettingsMismatchError if the clip was
    denoised with other settings than ``cfg``'s."""
    from denoisers.experiment import DIGEST_KEY, Lineage, check_recorded

    path = denoised_path / TIMING_FILE
    timing = json.loads(path.read_text()) if path.is_file() else {}
    if not {"method_id", "scene", "spp"} <= timing.keys():
        return None
    spec, scene, spp, lineage = method_spec(cfg, timing["method_id"]), timing["scene"], timing["spp"], Lineage(cfg)
    check_recorded(path, timing.get(DIGEST_KEY), lineage.denoised(spec, scene, spp))
    return {"method_id": spec.id, "scene": scene, "spp": spp, DIGEST_KEY: lineage.metrics(spec, scene, spp)}


def adaptive_accounting(denoised_path: Path, frames: Sequence[int]) -> dict[str, list[float]] | None:
    """Realised spp per frame of an adaptive row's clip (None for other rows), recomputed from its
    sample_maps.npz. EvaluationError naming the row, scene and frame when a frame's sample map is
    missing or its mean exceeds the row's budget (denoisers.adaptive.budget_problems, rounding included)."""
    path = Path(denoised_path) / TIMING_FILE
    timing = json.loads(path.read_text()) if path.is_file() else {}
    if not timing.get("adaptive"):
        return None
    # Imported here: denoisers.adaptive imports torch (~2 s per process), which no other clip's scoring needs.
    from denoisers.adaptive import SAMPLE_MAPS_FILE, budget_problems

    where = f"row {timing.get('method_id')!r}, scene {timing.get('scene')}"
    maps_path = Path(denoised_path) / SAMPLE_MAPS_FILE
    if not maps_path.is_file():
        raise EvaluationError(f"{where}: adaptive clip {denoised_path} has no {SAMPLE_MAPS_FILE}")
    with np.load(maps_path) as data:
        by_frame = dict(zip(data["frames"].tolist(), data["sample_maps"]))
    absent = [t for t in frames if t not in by_frame]
    if absent:
        raise EvaluationError(f"{where}: {maps_path} has no sample map for frame(s) {absent}")
    budget = float(timing["budget_spp"])
    problems = budget_problems([by_frame[t] for t in frames], budget, frames, where)
    if problems:
        raise EvaluationError("adaptive sample budget exceeded: " + "; ".join(problems))
    return {"realised_spp": [float(np.mean(by_frame[t], dtype=np.float64)) for t in frames],
            "budget_spp": [budget] * len(frames)}


def evaluate_clip(cfg: dict, denoised_path: Path, render_dir: Path, out_csv: Path):
    """Per-frame metrics of one denoised clip against clip.reference radiance -> CSV with columns
    frame, psnr, ssim, rmse, relmse, smape, flip, tpsnr, trmae, camera_cut, nonfinite_output,
    reference_psnr_halves (adaptive rows also realised_spp, budget_spp: adaptive_accounting), and its
    sidecar (metrics_sidecar: the settings digest the metrics came from; not written when the denoised
    clip has no timing.json). Raises EvaluationError when frame counts or resolutions differ, or an
    adaptive row's frame exceeds its sample budget."""
    import pandas as pd

    denoised_path, render_dir = Path(denoised_path), Path(render_dir)
    record = _metrics_record(cfg, denoised_path)
    denoised = read_frame_files(denoised_path)
    if not denoised:
        raise EvaluationError(f"{denoised_path}: no denoised frames (frame_TTTT.exr)")
    ref_frames, ref_paths, reference, ref_meta = load_references(render_dir)
    _check_match(denoised, denoised_path, ref_frames, render_dir)
    accounting = adaptive_accounting(denoised_path, ref_frames) or {}
    pred = []
    for t, ref_path, ref_image in zip(ref_frames, ref_paths, reference):
        image = read_radiance_exr(denoised[t])
        if image.shape != ref_image.shape:
            raise EvaluationError(f"resolution mismatch: {denoised[t]} is {image.shape[1]}x{image.shape[2]} (HxW), "
                                  f"reference {ref_path} is {ref_image.shape[1]}x{ref_image.shape[2]}")
        pred.append(image)
    pred = np.stack(pred)
    cuts = [bool(m.get("camera_cut", False)) for m in ref_meta]
    scores = score_sequence(pred, reference, cuts, cfg["evaluation"]["warmup_frames"])
    table = pd.DataFrame({"frame": ref_frames, **scores, "camera_cut": cuts,
                          "nonfinite_output": (~np.isfinite(pred)).sum(axis=(1, 2, 3)),
                          "reference_psnr_halves": [m.get("psnr_halves", np.nan) for m in ref_meta],
                          **accounting})
    if record is not None:   # first: a CSV on disk always has its sidecar
        write_text_atomic(metrics_sidecar(out_csv), json.dumps(record, indent=1) + "\n")
    write_text_atomic(out_csv, table.to_csv(index=False))
    return table
