"""``store verify``: retrain a stored model from the renders at hand and compare the result with the stored run.

Two modes (``steps``):

* the whole budget (``steps`` None): the retrained ``best.pt`` against the stored one, tensor by tensor, and the
  whole curve;
* the first ``steps`` steps with every setting unchanged (the schedule stays the full run's): the curve's rows up
  to that step against the stored curve.

Bit-identical or within a tolerance: where this machine's CPU instruction-set flags
(:data:`denoisers.provenance.ISA_FLAGS`) and the resolved step arithmetic (precision, layout) equal the stored
run's, the trainer's arithmetic is the same and every compared value must be equal (curves at the 8 significant
digits curves.csv keeps, weights exactly). Elsewhere oneDNN picks other kernels, whose rounding differs in the
last bits and grows over the steps: then every training and validation loss must lie within
:data:`RELATIVE_TOLERANCE` of the stored value, and the weights are not compared.
"""
from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path
from typing import Any

import pandas as pd

from denoisers.provenance import cpu_isa
from denoisers.store.entries import ModelStore, StoreError, store_settings
from scenegen.atomic import write_text_atomic

#: Largest relative difference of a loss between a stored run and its retraining on another instruction set.
RELATIVE_TOLERANCE = 0.05
#: Curve columns compared (those present in both curves).
COMPARED_COLUMNS = ("train_loss", "val_loss")


def _curve(path: Path, steps: int) -> pd.DataFrame:
    frame = pd.read_csv(path, dtype=str)
    frame = frame[frame["step"].astype(int) <= steps]
    return frame.set_index("step")


def compare_curves(stored: Path, retrained: Path, steps: int, exact: bool) -> dict[str, Any]:
    """Compare :data:`COMPARED_COLUMNS` of two curves.csv files up to ``steps``: equal strings (``exact``) or
    relative differences within :data:`RELATIVE_TOLERANCE`. Returns counts, the largest difference and the verdict."""
    a, b = _curve(stored, steps), _curve(retrained, steps)
    compared, mismatches, largest = 0, [], 0.0
    for column in COMPARED_COLUMNS:
        if column not in a.columns or column not in b.columns:
            continue
        for step in a.index.intersection(b.index):
            x, y = a.at[step, column], b.at[step, column]
            if pd.isna(x) and pd.isna(y):
                continue
            compared += 1
            if pd.isna(x) or pd.isna(y):
                mismatches.append(f"{column}@{step}: {x} vs {y}")
                continue
            relative = abs(float(x) - float(y)) / max(abs(float(x)), 1e-12)
            largest = max(largest, relative)
            if (x != y) if exact else not relative <= RELATIVE_TOLERANCE:
                mismatches.append(f"{column}@{step}: stored {x}, retrained {y}")
    missing = sorted(set(a.index) - set(b.index))
    if missing:
        mismatches.append(f"steps missing from the retrained curve: {missing[:5]}")
    return {"values_compared": compared, "largest_relative_difference": largest, "mismatches": mismatches[:20],
            "passed": compared > 0 and not mismatches}


def compare_weights(stored: Path, retrained: Path) -> dict[str, Any]:
    """Tensor-by-tensor equality of two model files' ``model_state``."""
    import torch

    from denoisers.training.checkpoints import load_checkpoint

    a, b = load_checkpoint(stored)["model_state"], load_checkpoint(retrained)["model_state"]
    if a.keys() != b.keys():
        return {"tensors": len(a), "differing": sorted(set(a) ^ set(b)), "largest_abs_difference": math.inf,
                "passed": False}
    differing = [name for name in a if not torch.equal(a[name], b[name])]
    largest = max((float((a[n].float() - b[n].float()).abs().max()) for n in differing), default=0.0)
    return {"tensors": len(a), "differing": differing[:20], "largest_abs_difference": largest,
            "passed": not differing}


def verify_model(cfg: dict, model_id: str, render_root: Path, out: Path, steps: int | None = None) -> dict[str, Any]:
    """Retrain stored model ``model_id`` (``steps`` None: the whole budget) next to ``out`` and write the
    comparison to ``out`` (JSON). Raises StoreError when the model is not stored or the comparison fails (the
    record is then written beside ``out`` as ``<name>.failed.json``, so no output looks complete)."""
    from denoisers.training.job import train_model
    from denoisers.training.precision import resolve_compute
    from denoisers.training.models import model_spec

    store = ModelStore.of(cfg)
    entry = store.model_entry(cfg, model_id)
    if entry is None:
        raise StoreError(f"model {model_id!r} is not in the store {store.root} under this config's key: nothing to "
                         "verify")
    stored = entry.summary()
    spec = model_spec(cfg, model_id)
    total = int(stored["steps"])
    steps = total if steps is None else min(int(steps), total)
    compute = resolve_compute(spec.compute).fingerprint()
    stored_isa = (stored.get("provenance") or {}).get("cpu_isa")
    stored_compute = {key: (stored.get("compute") or {}).get(key) for key in compute}
    exact = stored_isa == cpu_isa() and stored_compute == compute
    work = Path(out).parent / f".{Path(out).stem}.work"
    shutil.rmtree(work, ignore_errors=True)
    local = {**cfg, "store": {**store_settings(cfg), "use": False}}
    started = time.perf_counter()
    train_model(local, model_id, render_root, work / model_id, progress=False,
                stop_at_step=None if steps == total else steps)
    seconds = time.perf_counter() - started
    record: dict[str, Any] = {
        "model_id": model_id, "key": entry.key, "entry": entry.path.as_posix(), "steps": steps, "stored_steps": total,
        "mode": "bit-identical" if exact else f"relative tolerance {RELATIVE_TOLERANCE}",
        "why": ("same CPU instruction-set flags and step arithmetic as the stored run" if exact else
                f"stored run: ISA {stored_isa}, compute {stored_compute}; here: ISA {cpu_isa()}, compute {compute}"),
        "retrain_seconds": seconds,
        "curves": compare_curves(entry.path / "curves.csv", work / model_id / "curves.csv", steps, exact)}
    if steps == total and exact:
        record["weights"] = compare_weights(entry.path / "best.pt", work / model_id / "best.pt")
    record["passed"] = record["curves"]["passed"] and record.get("weights", {"passed": True})["passed"]
    shutil.rmtree(work, ignore_errors=True)
    text = json.dumps(record, indent=1, sort_keys=True, default=str) + "\n"
    if not record["passed"]:
        failed = Path(out).with_name(f"{Path(out).stem}.failed.json")
        write_text_atomic(failed, text)
        raise StoreError(f"model {model_id!r}: the retrained run differs from the stored one ({record['mode']}; "
                         f"{record['curves']['mismatches'][:3]}{'; weights differ' if not record.get('weights', {}).get('passed', True) else ''}); "
                         f"details in {failed}")
    write_text_atomic(Path(out), text)
    return record
