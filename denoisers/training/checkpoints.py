"""Checkpoint and model files of the trainer (denoisers.training.loop): atomic writes, checked reads, the
network rebuilt from its stored spec, and the RNG states and settings fingerprint a checkpoint carries."""
from __future__ import annotations

import hashlib
import io
import json
import os
import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from denoisers.errors import CheckpointError  # noqa: F401 (raised here, imported from here elsewhere)

CHECKPOINT_FORMAT = "mcdenoise-checkpoint"
CHECKPOINT_VERSION = 1


def save_atomic(obj: Any, path: Path) -> None:
    """torch.save into a hidden temporary sibling, fsync, rename: ``path`` is always a complete file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    with open(staging, "wb") as handle:
        handle.write(buffer.getbuffer())
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(staging, path)


def load_checkpoint(path: Path | str) -> dict[str, Any]:
    """Read a checkpoint or model file written by the trainer; :class:`CheckpointError` naming the file if
    it is missing, unreadable, truncated or not one of ours."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # zip/pickle errors of a truncated or overwritten file
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({type(error).__name__}: {error}); "
                              f"delete it to train from scratch") from error
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} file")
    if data.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {data.get('version')}, this code reads {CHECKPOINT_VERSION}")
    missing = [k for k in ("net", "model_state") if k not in data]
    if data.get("kind") == "training":
        missing += [k for k in ("optimizer_state", "step", "rng", "history", "fingerprint") if k not in data]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {missing}")
    return data


def load_model(path: Path | str) -> nn.Module:
    """The network stored in a checkpoint or model file (architecture rebuilt from its spec), in eval mode."""
    from denoisers.nets import build_net

    data = load_checkpoint(path)
    try:
        model = build_net(data["net"]["name"], data["net"]["config"])
        model.load_state_dict(data["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: cannot rebuild the network from the checkpoint ({error})") from error
    return model.eval()


def rng_state() -> dict[str, Any]:
    version, mt_state, gauss = random.getstate()
    name, keys, position, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": {"name": name, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(position),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": {"version": version, "state": list(mt_state), "gauss": gauss}}


def set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    numpy_state = state["numpy"]
    np.random.set_state((numpy_state["name"], numpy_state["keys"].numpy().astype(np.uint32), numpy_state["pos"],
                         numpy_state["has_gauss"], numpy_state["cached_gaussian"]))
    python_state = state["python"]
    random.setstate((python_state["version"], tuple(python_state["state"]), python_state["gauss"]))


def fingerprint(data: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()
