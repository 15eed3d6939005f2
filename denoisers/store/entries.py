"""The model store: published models and part-way training checkpoints, committed with the code.

Layout below the store folder (config key ``store.path``, default ``store/`` in the repository)::

    budget.json                                   {"max_megabytes": ...}: the size budget (tests check it)
    models/<model_id>/<key16>/                    a finished model
        best.pt            weights only (the trainer's model file; no optimizer state)
        settings.json      the resolved settings (ModelSpec.settings())
        curves.csv         training and validation curves
        validation.csv     per validation sequence metrics of best.pt
        summary.json       the training job's summary (provenance: commit, packages, CPU model and ISA flags,
                           threads, precision, wall time, steps) plus "store": key, key inputs' digests and
                           the SHA-256 of every file above
    checkpoints/<model_id>/<key16>/               a training run part-way (key without the budget)
        checkpoint.pt      weights, Adam state, EMA, RNG states, step (= data-stream position), history
        best.pt            the best model so far
        meta.json          step, compute, key, file digests, provenance

Installing checks every file's digest and that ``best.pt`` loads: a corrupt or truncated file is a
:class:`StoreError` naming it, never used.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import logging
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from denoisers.errors import CheckpointError
from denoisers.store.keys import STORE_FORMAT, checkpoint_key, key_inputs, model_key, short
from denoisers.training.models import model_spec, same_training_as
from scenegen.atomic import atomic_directory, write_text_atomic
from scenegen.reference_store import file_digest  # noqa: F401 -- re-exported (denoisers.store)

log = logging.getLogger(__name__)

MODEL_FILES = ("best.pt", "settings.json", "curves.csv", "validation.csv")
CHECKPOINT_FILES = ("checkpoint.pt", "best.pt")
BUDGET_FILE = "budget.json"
STORE_KEY = "store"
INSTALLED_KEY = "installed_from_store"


class StoreError(RuntimeError):
    """A store entry cannot be used or written; the message names the entry or file and why."""


class StoreCollisionError(StoreError):
    """Publishing would put different weights under a key that already holds a model."""



def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def store_settings(cfg: dict) -> dict[str, Any]:
    """The config's ``store`` section with its defaults."""
    return {"path": "store", "use": True, "force_training": False, **(cfg.get("store") or {})}


@dataclass(frozen=True)
class Entry:
    """One stored model (or checkpoint) folder."""

    model_id: str
    key: str
    path: Path

    def summary(self) -> dict[str, Any]:
        return _read_json(self.path / ("summary.json" if (self.path / "summary.json").exists() else "meta.json"))


def arithmetic_text(compute: dict[str, Any] | None) -> str:
    """A training step's arithmetic as stored (``{"precision": "bf16", "channels_last": True}``) in words, e.g.
    ``bf16 channels-last``."""
    if not compute:
        return "an unrecorded arithmetic"
    return f"{compute.get('precision', '?')} {'channels-last' if compute.get('channels_last') else 'NCHW'}"


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as error:
        raise StoreError(f"{path}: missing from the store entry") from error
    except json.JSONDecodeError as error:
        raise StoreError(f"{path}: not valid JSON ({error})") from error


def _check_files(folder: Path, expected: dict[str, str]) -> None:
    """Every file of ``expected`` exists in ``folder`` with that SHA-256 (StoreError naming it otherwise)."""
    if not expected:
        raise StoreError(f"{folder}: the entry records no file digests")
    for name, digest in expected.items():
        path = folder / name
        if not path.is_file():
            raise StoreError(f"{path}: missing from the store entry")
        actual = file_digest(path)
        if actual != digest:
            raise StoreError(f"{path}: corrupt or truncated (SHA-256 {actual[:12]}…, published {digest[:12]}…, "
                             f"{path.stat().st_size} bytes); restore it from git (git checkout -- {path}) or "
                             f"retrain with store.force_training")


class ModelStore:
    """The store folder ``root`` (see the module docstring)."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)

    @classmethod
    def of(cls, cfg: dict) -> "ModelStore":
        return cls(store_settings(cfg)["path"])

    # ------------------------------------------------------------------------------ lookup
    def model_entry(self, cfg: dict, model_id: str) -> Entry | None:
        """The stored model of ``model_id`` under ``cfg``'s key, or None."""
        key = model_key(cfg, model_id)
        path = self.root / "models" / model_id / short(key)
        return Entry(model_id, key, path) if (path / "summary.json").exists() else None

    def checkpoint_entry(self, cfg: dict, model_id: str) -> Entry | None:
        key = checkpoint_key(cfg, model_id)
        path = self.root / "checkpoints" / model_id / short(key)
        return Entry(model_id, key, path) if (path / "meta.json").exists() else None

    def entries(self, kind: str = "models") -> Iterator[Entry]:
        """Every entry of ``kind`` ('models' or 'checkpoints') in the store."""
        name = "summary.json" if kind == "models" else "meta.json"
        for path in sorted((self.root / kind).glob(f"*/*/{name}")):
            record = _read_json(path)
            yield Entry(path.parent.parent.name, record.get(STORE_KEY, record).get("key", ""), path.parent)

    def size_bytes(self) -> int:
        return sum(p.stat().st_size for p in self.root.rglob("*") if p.is_file())

    def budget_bytes(self) -> int:
        budget = _read_json(self.root / BUDGET_FILE)
        return int(float(budget["max_megabytes"]) * 1e6)

    # ----------------------------------------------------------------------------- install
    def install(self, entry: Entry, out_dir: Path) -> dict[str, Any]:
        """Write model directory ``out_dir`` from ``entry`` (atomically) after checking every file; return the
        summary (with ``installed_from_store``)."""
        from denoisers.training.checkpoints import load_checkpoint

        summary = _read_json(entry.path / "summary.json")
        record = summary.get(STORE_KEY) or {}
        if record.get("key") != entry.key:
            raise StoreError(f"{entry.path / 'summary.json'}: records key {str(record.get('key'))[:16]}, but the "
                             f"entry is filed under {entry.key[:16]}")
        _check_files(entry.path, record.get("files", {}))
        try:
            load_checkpoint(entry.path / "best.pt")
        except CheckpointError as error:
            raise StoreError(f"stored model {entry.model_id!r}: {error}") from error
        summary[INSTALLED_KEY] = {"entry": entry.path.as_posix(), "key": entry.key, "installed": _now()}
        with atomic_directory(Path(out_dir)) as staging:
            for name in MODEL_FILES:
                shutil.copy2(entry.path / name, staging / name)
            _plot_curves(staging / "curves.csv", staging / "curves.png", entry.model_id)
            write_text_atomic(staging / "summary.json", json.dumps(summary, indent=1, sort_keys=True, default=str)
                              + "\n")
        log.info("model %s: installed from the store (%s, key %s); not trained", entry.model_id, entry.path,
                 entry.key[:16])
        return summary

    # ----------------------------------------------------------------------------- publish
    def publish_model(self, cfg: dict, model_dir: Path) -> tuple[Entry, str]:
        """Copy the finished model in ``model_dir`` (``<output_dir>/models/<id>``) into the store.

        Returns (entry, what happened: 'published' or 'already published'). Refuses (StoreError) a model whose
        summary was computed from other settings than ``cfg``'s, a variant that reuses another model's weights
        (publish the base), and (StoreCollisionError) different weights under an existing key."""
        from denoisers.training.digests import model_digest

        model_dir = Path(model_dir)
        model_id = model_dir.name
        spec = model_spec(cfg, model_id)
        summary = _read_json(model_dir / "summary.json")
        if summary.get(INSTALLED_KEY):
            raise StoreError(f"{model_dir}: installed from the store ({summary[INSTALLED_KEY]['entry']}), not trained")
        if same_training_as(cfg, model_id) or summary.get("same_training_as"):
            raise StoreError(f"model {model_id!r} reuses the weights of {summary.get('same_training_as') or same_training_as(cfg, model_id)!r} "
                             f"(same training): publish that model; this one is installed from it")
        if summary.get("stopped_by") == "stop_at_step":
            raise StoreError(f"{model_dir}: stopped early at step {summary.get('steps')} of {summary.get('max_steps')} "
                             "(stop_at_step); publish its checkpoint instead (store checkpoint)")
        expected = model_digest(cfg, spec)
        if summary.get("settings_digest") != expected:
            raise StoreError(f"{model_dir}: trained with other settings or data (digest {summary.get('settings_digest')}, "
                             f"this config: {expected}); retrain it before publishing")
        key = model_key(cfg, model_id)
        if summary.get("store_key") != key:
            raise StoreError(f"{model_dir}: trained under key {str(summary.get('store_key'))[:16]}, the code at hand "
                             f"gives {key[:16]} (the network, its inputs or the training step changed since, or it "
                             f"was trained before keys were recorded); retrain it before publishing")
        entry = Entry(model_id, key, self.root / "models" / model_id / short(key))
        weights = file_digest(model_dir / "best.pt")
        if (entry.path / "summary.json").exists():
            stored = _read_json(entry.path / "summary.json").get(STORE_KEY, {})
            if stored.get("key") != key:
                raise StoreCollisionError(f"{entry.path}: holds key {str(stored.get('key'))[:16]}…, not {key[:16]}… "
                                          f"(a 16-digit prefix collision); refusing to overwrite")
            if stored.get("files", {}).get("best.pt") != weights:
                raise StoreCollisionError(
                    f"{entry.path}: key {key[:16]} already holds different weights (published "
                    f"{stored.get('files', {}).get('best.pt', '?')[:12]}…, {model_dir / 'best.pt'}: {weights[:12]}…). "
                    f"Same key, different weights: the run was not deterministic or the key misses something that "
                    f"changed them; refusing to publish")
            return entry, "already published"
        inputs = key_inputs(cfg, spec)
        summary[STORE_KEY] = {
            "format": STORE_FORMAT, "key": key, "published": _now(), "source": model_dir.as_posix(),
            "code_digest": inputs["code"], "files": {name: file_digest(model_dir / name) for name in MODEL_FILES},
            "key_inputs_digests": {part: hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode())
                                   .hexdigest()[:16] for part, value in inputs.items()}}
        with atomic_directory(entry.path) as staging:
            for name in MODEL_FILES:
                shutil.copy2(model_dir / name, staging / name)
            write_text_atomic(staging / "summary.json", json.dumps(summary, indent=1, sort_keys=True, default=str)
                              + "\n")
        self._drop_superseded_checkpoint(cfg, model_id, int(summary.get("steps", 0)))
        return entry, "published"

    def publish_checkpoint(self, cfg: dict, work_dir: Path, replace_other_arithmetic: bool = False) -> Entry:
        """Copy the trainer's resumable state in ``work_dir`` (``models/.work/<id>-<digest>``) into the store,
        replacing an earlier checkpoint of the same run (StoreError if it holds fewer steps than the stored one, or if
        the store holds the finished model of this config: nothing would continue the checkpoint). A stored
        checkpoint of another step arithmetic (precision, layout), which this run could not continue, is replaced
        only with ``replace_other_arithmetic`` (a run restarted on purpose); else StoreError says so."""
        from denoisers.device import configured_device, device_info
        from denoisers.provenance import provenance
        from denoisers.training.checkpoints import load_checkpoint

        work_dir = Path(work_dir)
        model_id = work_dir.name.rsplit("-", 1)[0]
        spec = model_spec(cfg, model_id)
        finished = self.model_entry(cfg, model_id)
        if finished is not None:
            raise StoreError(f"not checkpointing {model_id!r}: the store holds it finished ({finished.path}), so "
                             "nothing would continue the checkpoint (e.g. the run its half-budget twin trained in)")
        try:
            data = load_checkpoint(work_dir / "checkpoint.pt")
        except CheckpointError as error:
            raise StoreError(f"cannot publish a checkpoint of {model_id!r}: {error}") from error
        key = checkpoint_key(cfg, model_id)
        entry = Entry(model_id, key, self.root / "checkpoints" / model_id / short(key))
        step = int(data["step"])
        try:
            best_step = int(load_checkpoint(work_dir / "best.pt").get("step", 0))
        except CheckpointError as error:
            raise StoreError(f"cannot publish a checkpoint of {model_id!r} before its first validation: {error}") \
                from error
        best_recorded = (data.get("best") or {}).get("step")
        if best_step > step or (best_recorded is not None and int(best_recorded) != best_step):
            raise StoreError(f"{work_dir}: best.pt (step {best_step}) does not belong to checkpoint.pt (step {step}, "
                             f"best step {best_recorded}): the trainer is writing; pause it (kill -STOP) and retry")
        fingerprint = json.loads(data["fingerprint_data"])
        if (entry.path / "meta.json").exists():
            stored = _read_json(entry.path / "meta.json")
            if stored.get("compute") != fingerprint.get("compute"):
                if not replace_other_arithmetic:
                    raise StoreError(f"{entry.path}: holds step {stored['step']} of a run trained with "
                                     f"{arithmetic_text(stored.get('compute'))}, not {work_dir}'s "
                                     f"{arithmetic_text(fingerprint.get('compute'))}: neither can continue the other; "
                                     "replace it only on purpose (store checkpoint --replace-other-arithmetic)")
            elif int(stored["step"]) > step:
                raise StoreError(f"{entry.path}: holds step {stored['step']}, later than {work_dir}'s {step}")
        meta = {"format": STORE_FORMAT, "key": key, "model_id": model_id, "step": step,
                "max_steps": spec.budget.get("max_steps"), "elapsed_seconds": float(data.get("elapsed_seconds", 0)),
                "compute": fingerprint.get("compute"), "fingerprint": data["fingerprint"],
                "files": {name: file_digest(work_dir / name) for name in CHECKPOINT_FILES},
                "provenance": provenance({"training": spec.threads}, device=device_info(configured_device(cfg))),
                "published": _now()}
        with atomic_directory(entry.path) as staging:
            for name in CHECKPOINT_FILES:
                shutil.copy2(work_dir / name, staging / name)
            write_text_atomic(staging / "meta.json", json.dumps(meta, indent=1, sort_keys=True, default=str) + "\n")
        return entry

    def fetch_checkpoint(self, cfg: dict, model_id: str, work_dir: Path, compute: dict[str, Any]) -> int | None:
        """Seed an empty ``work_dir`` with the stored checkpoint of ``model_id``'s run, if there is one of the same
        step arithmetic ``compute`` and no later than the budget; returns its step (None when nothing was fetched)."""
        entry = self.checkpoint_entry(cfg, model_id)
        if entry is None or (Path(work_dir) / "checkpoint.pt").exists():
            return None
        meta = _read_json(entry.path / "meta.json")
        if meta.get("compute") != compute:
            log.warning("model %s: the stored checkpoint (%s, step %s) was trained with %s, this machine resolves %s: "
                        "training from scratch", model_id, entry.path, meta.get("step"),
                        arithmetic_text(meta.get("compute")), arithmetic_text(compute))
            return None
        if int(meta["step"]) > int(model_spec(cfg, model_id).budget["max_steps"]):
            return None
        _check_files(entry.path, meta.get("files", {}))
        Path(work_dir).mkdir(parents=True, exist_ok=True)
        for name in CHECKPOINT_FILES:
            shutil.copy2(entry.path / name, Path(work_dir) / name)
        log.info("model %s: continuing the stored checkpoint %s at step %d", model_id, entry.path, meta["step"])
        return int(meta["step"])

    def _drop_superseded_checkpoint(self, cfg: dict, model_id: str, steps: int) -> None:
        entry = self.checkpoint_entry(cfg, model_id)
        if entry is not None and int(_read_json(entry.path / "meta.json")["step"]) <= steps:
            shutil.rmtree(entry.path)
            if not any(entry.path.parent.iterdir()):
                entry.path.parent.rmdir()       # the model's folder: nothing else is checkpointed under its id
            log.info("model %s: removed the stored checkpoint %s (the finished model supersedes it)", model_id,
                     entry.path)


def _plot_curves(csv_path: Path, png_path: Path, title: str) -> None:
    """curves.png from a stored curves.csv (the store keeps the table, not the picture)."""
    import math

    import pandas as pd

    from denoisers.training.curves import plot_curves

    frame = pd.read_csv(csv_path)
    rows = [{k: v for k, v in row.items() if not (isinstance(v, float) and math.isnan(v))}
            for row in frame.to_dict(orient="records")]
    if rows:
        plot_curves(rows, png_path, title=f"{title} training")
