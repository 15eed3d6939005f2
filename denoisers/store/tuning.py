"""Tuned baseline parameters in the store: a hand-set method's grid-search result (rule tune_method) is fitted on
the training scenes like a model's weights, so it is stored the same way, under ``store/tuning/<method>/<key16>/``
(``result.json`` and ``meta.json`` with its SHA-256), keyed by the tuning settings (denoisers.experiment
.tuning_digest), the render digests of the scenes it searches on and the method's code
(denoisers.store.code.method_code_digest). With every tuning result and model stored, the DAG renders no
training scene."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

from denoisers.store.code import method_code_digest
from denoisers.store.entries import ModelStore, StoreCollisionError, StoreError, _check_files, _now, file_digest
from denoisers.store.keys import STORE_FORMAT, short
from scenegen.atomic import atomic_directory, write_text_atomic

RESULT_FILE = "result.json"


def tuning_key(cfg: dict, method: str) -> str:
    from denoisers.experiment import tuning_digest
    from denoisers.training.models import training_split
    from scenegen.digests import render_digest

    scenes = sum(training_split(cfg), [])
    payload = {"format": STORE_FORMAT, "tuning": tuning_digest(cfg, method),
               "renders": {s: [render_digest(cfg, s, kind) for kind in ("noisy", "reference")] for s in scenes},
               "code": method_code_digest(method)}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def tuning_entry(store: ModelStore, cfg: dict, method: str) -> Path | None:
    """The stored tuning result folder of ``method`` under ``cfg``'s key, or None."""
    path = store.root / "tuning" / method / short(tuning_key(cfg, method))
    return path if (path / "meta.json").exists() else None


def install_tuning(folder: Path, out: Path) -> dict[str, Any]:
    """Copy a stored result to ``out`` after checking its digest (StoreError naming the file otherwise)."""
    meta = json.loads((folder / "meta.json").read_text())
    _check_files(folder, meta.get("files", {}))
    result = json.loads((folder / RESULT_FILE).read_text())
    write_text_atomic(Path(out), json.dumps(result, indent=1) + "\n")
    return result


def publish_tuning(store: ModelStore, cfg: dict, method: str, result_file: Path) -> tuple[Path, str]:
    """Store the tuning result ``result_file`` of ``method`` (refused when it was computed from other settings,
    or when the key holds another result)."""
    from denoisers.experiment import DIGEST_KEY, Lineage

    result = json.loads(Path(result_file).read_text())
    if result.get(DIGEST_KEY) != Lineage(cfg).tuning(method):
        raise StoreError(f"{result_file}: computed from other settings than this config's; rerun tune_method")
    key = tuning_key(cfg, method)
    folder = store.root / "tuning" / method / short(key)
    digest = file_digest(Path(result_file))
    if (folder / "meta.json").exists():
        meta = json.loads((folder / "meta.json").read_text())
        if meta.get("key") != key or json.loads((folder / RESULT_FILE).read_text()).get("best_params") != result.get("best_params"):
            raise StoreCollisionError(f"{folder}: key {key[:16]} already holds another tuning result; refusing")
        return folder, "already published"
    with atomic_directory(folder) as staging:
        shutil.copy2(result_file, staging / RESULT_FILE)
        write_text_atomic(staging / "meta.json", json.dumps({"format": STORE_FORMAT, "key": key, "method": method,
                                                             "files": {RESULT_FILE: digest}, "published": _now()},
                                                            indent=1, sort_keys=True) + "\n")
    return folder, "published"
