"""What a trained model's weights depend on besides its settings: the training data's config values
(:func:`data_settings`), and the model's recorded settings digest (:func:`model_digest`). Config level, no torch;
shared by the training job, the experiment digests and the model store."""
from __future__ import annotations

from typing import Any

from denoisers.training.models import ModelSpec, settings_digest, training_split
from scenegen.config import short_digest
from scenegen.digests import render_digest


def data_settings(cfg: dict, spec: ModelSpec | None = None) -> dict[str, Any]:
    """Config values the rendered training data of model ``spec`` depend on (changing them invalidates
    checkpoints): the settings digests of its training and validation scenes' renders, not the whole
    scenes/render sections, so that adding a test scene (scenes.n_test) or an external scene retrains nothing."""
    split = training_split(cfg, spec)
    renders = {scene: [render_digest(cfg, scene, kind) for kind in ("noisy", "reference")] for scene in sum(split, [])}
    return {"renders": renders, "split": split, "validation_sequences": cfg["training"]["validation_sequences"],
            "validate_every": cfg["training"]["validate_every"],
            # Validation image metrics skip these first frames of each sequence (see trainer_config).
            "validation_warmup_frames": cfg["evaluation"]["warmup_frames"]}


def model_digest(cfg: dict, spec: ModelSpec) -> str:
    """The recorded settings digest of a trained model (summary.json ``settings_digest``; = denoisers.experiment
    .Lineage(cfg).model(spec.id))."""
    return short_digest(settings_digest(spec, data_settings(cfg, spec)))
