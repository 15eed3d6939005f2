"""Parameters of the hand-set baselines chosen on training scenes only (grid search).

A baseline whose paper leaves a parameter to the user (EAW's sigmas, the wRLS prior) is tuned like a
learned method is trained: on the training scenes (``train_*``, validation scenes included), never on a
test or external scene. ``tune_method`` runs the method with every combination of its configured grid
on the first ``tuning.max_frames`` frames of every training clip at every ``tuning.spp`` and keeps the
combination with the highest score: the mean over (scene, spp) of the frame-mean PSNR (dB) against the
reference. Ties go to the earlier combination in grid order. The result (every combination's score, the
chosen parameters, the scenes used) is written as JSON, printed as a table, and read by evaluation rows
that set ``params: {tuned: true}`` (:func:`tuned_params`; explicit row params win).
"""
from __future__ import annotations

import itertools
import json
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("denoisers")

TUNED_KEY = "tuned"
"""Row param: ``tuned: true`` takes the method's parameters from its tuning result."""


class TuningError(ValueError):
    """The tuning request cannot be honoured (bad grid, a non-training scene, no result file)."""


def tuning_entry(cfg: dict, method: str) -> dict:
    """The ``tuning.methods`` entry of ``method``; TuningError naming the configured ones."""
    entries = (cfg.get("tuning") or {}).get("methods", [])
    for entry in entries:
        if entry["method"] == method:
            return entry
    raise TuningError(f"method {method!r} has no entry in config key 'tuning.methods'; "
                      f"configured: {[e['method'] for e in entries]}")


def tuning_file(results: Path | str, method: str) -> Path:
    """<results>/tuning/{method}.json (<results>: the experiment folder, the config's output_dir)"""
    return Path(results) / "tuning" / f"{method}.json"


def grid_combinations(grid: Mapping[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """Every combination of a {param: [values]} grid, in row-major order of the sorted param names."""
    names = sorted(grid)
    if not names:
        raise TuningError("tuning grid is empty")
    for name in names:
        if not isinstance(grid[name], (list, tuple)) or not grid[name]:
            raise TuningError(f"tuning grid of {name!r} must be a non-empty list, got {grid[name]!r}")
    return [dict(zip(names, values)) for values in itertools.product(*(grid[n] for n in names))]


def check_training_scenes(scenes: Sequence[str]) -> None:
    """Tuning sees training scenes only: anything but ``train_*`` is a TuningError."""
    bad = [scene for scene in scenes if not scene.startswith("train_")]
    if bad:
        raise TuningError(f"tuning may only use training scenes (train_*), got {bad}")
    if not scenes:
        raise TuningError("no training scenes to tune on")


def _score_clip(method, frames: list, reference: np.ndarray) -> float:
    """Frame-mean PSNR (dB) of the method's outputs over ``frames`` against ``reference`` (T, 3, H, W)."""
    import torch

    from denoisers import metrics

    method.reset()
    values = []
    with torch.no_grad():
        for frame, ref in zip(frames, reference):
            output = torch.as_tensor(method.denoise(frame)).detach().to(torch.float32).cpu().numpy()
            values.append(metrics.psnr(np.nan_to_num(output, nan=0.0, posinf=0.0, neginf=0.0), ref))
    return float(np.mean(values))


def tune_method(cfg: dict, method: str, render_dirs: Mapping[str, Path], threads: int = 1) -> dict[str, Any]:
    """Grid-search ``method``'s configured parameters on the training clips ``render_dirs``
    ({scene id: <output_dir>/renders/{scene}}, train_* only). Returns the JSON-ready result."""
    import torch

    from denoisers import registry
    from denoisers.registry import clip_frames
    from scenegen.dataset import load_clip

    check_training_scenes(list(render_dirs))
    entry = tuning_entry(cfg, method)
    tuning = cfg["tuning"]
    combinations = grid_combinations(entry["grid"])
    fixed = dict(entry.get("params") or {})
    overlap = sorted(set(fixed) & set(entry["grid"]))
    if overlap:
        raise TuningError(f"tuning entry of {method!r} sets {overlap} both in 'params' and in 'grid'")
    methods = [registry.build(method, {**fixed, **combo}, row=f"tuning.{method}") for combo in combinations]
    torch.set_num_threads(max(1, int(threads)))
    start = time.perf_counter()
    scores = np.zeros((len(combinations), len(render_dirs), len(tuning["spp"])))
    for s, (scene, render_dir) in enumerate(sorted(render_dirs.items())):
        for k, spp in enumerate(tuning["spp"]):
            layers = spp * methods[0].samples_factor
            clip = load_clip(Path(render_dir), buffers=methods[0].info.inputs, spp=layers, reference=True)
            keep = min(len(clip.frames), int(tuning["max_frames"]))
            frames = list(clip_frames(clip, methods[0].info, layers))[:keep]
            reference = clip.reference["radiance"][:keep]
            for c, instance in enumerate(methods):
                scores[c, s, k] = _score_clip(instance, frames, reference)
            log.info("tuning %s: %s at %d spp done (%d combinations)", method, scene, spp, len(combinations))
    mean = scores.mean(axis=(1, 2))
    best = int(np.argmax(mean))
    return {
        "method": method, "scenes": sorted(render_dirs), "spp": list(tuning["spp"]),
        "frames_per_scene": int(tuning["max_frames"]), "fixed_params": fixed, "grid": entry["grid"],
        "score": "mean over (scene, spp) of the frame-mean PSNR (dB) against the reference",
        "results": [{"params": combo, "score_db": float(mean[c]),
                     "per_scene_spp_db": scores[c].round(4).tolist()} for c, combo in enumerate(combinations)],
        "best_params": {**fixed, **combinations[best]}, "best_score_db": float(mean[best]),
        "seconds": time.perf_counter() - start,
    }


def format_result(result: Mapping[str, Any]) -> str:
    """Plain-text table of every combination's score, best marked, then the chosen parameters."""
    lines = [f"tuning {result['method']} on {', '.join(result['scenes'])} at spp {result['spp']} "
             f"({result['frames_per_scene']} frames each); score = {result['score']}"]
    ranked = sorted(result["results"], key=lambda r: -r["score_db"])
    for row in ranked:
        mark = "*" if row["params"] == {k: result["best_params"][k] for k in row["params"]} else " "
        lines.append(f" {mark} {row['score_db']:8.3f} dB  {json.dumps(row['params'], sort_keys=True)}")
    lines.append(f"chosen: {json.dumps(result['best_params'], sort_keys=True)}")
    return "\n".join(lines)


def tuned_params(results: Path | str, method: str) -> dict[str, Any]:
    """The chosen parameters of ``method`` from <results>/tuning/{method}.json; TuningError if missing."""
    path = tuning_file(results, method)
    if not path.is_file():
        raise TuningError(f"evaluation row uses tuned parameters of {method!r} but {path} does not exist; "
                          f"run the tuning rule first (snakemake {path})")
    try:
        record = json.loads(path.read_text())
        return dict(record["best_params"])
    except (json.JSONDecodeError, KeyError, TypeError) as error:
        raise TuningError(f"{path}: not a tuning result ({error})") from error


def tuning_problems(cfg: dict) -> list[str]:
    """Constraints of the ``tuning`` section and of rows with ``tuned`` that the JSON schema cannot
    express: registered methods, grid keys that are parameters, a tuning entry for every tuned row."""
    from denoisers import registry

    tuning = cfg.get("tuning") or {}
    problems: list[str] = []
    entries = tuning.get("methods", [])
    names = [entry["method"] for entry in entries]
    for duplicate in sorted({n for n in names if names.count(n) > 1}):
        problems.append(f"config key 'tuning.methods' lists method {duplicate!r} more than once")
    for entry in entries:
        method = entry["method"]
        if method not in registry.available():
            problems.append(f"config key 'tuning.methods': unknown method {method!r}; registered: "
                            f"{registry.available()}")
            continue
        allowed = registry.parameters(method)
        for key in [*entry.get("grid", {}), *(entry.get("params") or {})]:
            if key not in allowed:
                problems.append(f"config key 'tuning.methods' entry {method!r}: {key!r} is not a parameter of "
                                f"{method!r}; allowed: {sorted(allowed)}")
    rendered = int(cfg["render"]["spp"])
    for spp in tuning.get("spp", []):
        if spp > rendered:
            problems.append(f"config key 'tuning.spp': {spp} spp asked, render.spp is {rendered}")
    for row in (cfg.get("evaluation") or {}).get("methods", []):
        value = (row.get("params") or {}).get(TUNED_KEY)
        if value is None:
            continue
        if not isinstance(value, bool):
            problems.append(f"evaluation row {row['id']!r}: params.{TUNED_KEY} must be true or false, got {value!r}")
        elif value and row["method"] not in names:
            problems.append(f"evaluation row {row['id']!r} sets params.{TUNED_KEY} but method {row['method']!r} "
                            f"has no entry in config key 'tuning.methods'")
    return problems
