"""Keys of the model store: the digest of everything that determines a trained model's weights.

``model_key`` covers the resolved settings (``ModelSpec.settings()``: method, seed, net, loss, data,
optimizer with its resolved schedule, budget, compute as configured, threads), what its training data
depend on (``denoisers.training.job.data_settings``: the render digests of its training and validation
scenes, the split, the validation sequences) and the code version of its method
(:func:`denoisers.store.code.code_digest`); a model trained on CUDA also has ``device`` (CPU keys have none,
:func:`denoisers.device.key_device`). ``checkpoint_key`` is the same without the budget, so a
part-way checkpoint serves any budget of the same run (as the local ``models/.work`` directories do).

The render digests are the config-level digests the workflow's render jobs are keyed by
(scenegen.digests.render_digest), known before anything is rendered: that is what lets the DAG leave a
stored model's training renders out. The renderer's code is not in the key; ``verify`` retrains against
the renders of the checkout at hand and would show a change there.
"""
from __future__ import annotations

import hashlib
import json
from typing import Any

from denoisers.device import key_device
from denoisers.store.code import code_digest
from denoisers.training.models import ModelSpec, model_spec

#: Bumped when the layout of a store entry or the meaning of a key changes.
STORE_FORMAT = 1


def key_inputs(cfg: dict, spec: ModelSpec, budget: bool = True) -> dict[str, Any]:
    """What the key of ``spec`` digests (JSON-serialisable)."""
    from denoisers.training.digests import data_settings

    settings = spec.settings()
    if not budget:
        settings = {**settings, "budget": None}
    return {"format": STORE_FORMAT, "settings": settings, "data": data_settings(cfg, spec),
            "code": code_digest(spec.method), **key_device(cfg)}


def _digest(payload: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def model_key(cfg: dict, model_id: str) -> str:
    """SHA-256 key of model ``model_id`` of ``cfg`` (KeyError naming the configured models)."""
    return _digest(key_inputs(cfg, model_spec(cfg, model_id)))


def checkpoint_key(cfg: dict, model_id: str) -> str:
    """The key of a part-way checkpoint of ``model_id``: :func:`model_key` without the budget."""
    return _digest(key_inputs(cfg, model_spec(cfg, model_id), budget=False))


def short(key: str) -> str:
    """The folder name of a key in the store (16 hex digits; the summary keeps the full key)."""
    return key[:16]
