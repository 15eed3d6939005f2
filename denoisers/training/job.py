"""One training job of the workflow (rule train_denoiser): train a configured model on the rendered
training scenes and publish it as ``<output_dir>/models/<id>/``.

The trainer works in ``<models>/.work/<id>-<digest>/`` (digest of everything that determines the
weights except the budget), so a killed job resumes from its last checkpoint when rerun, and raising
``budget.max_steps`` continues the previous run instead of starting over. Only when training has
finished is the output directory written (atomically) with:

* ``best.pt``         the model with the best validation loss (what evaluation rows load)
* ``curves.csv/.png`` training loss, validation loss and image metrics per step
* ``validation.csv``  per validation sequence: loss, loss terms, SSIM, PSNR, RMSE of ``best.pt``
* ``summary.json``    steps, wall time, which budget stopped training, parameters, best step, scenes, the
                      step arithmetic used (``compute``: precision bf16 / fp32, channels_last, why), and
                      ``settings_digest``: the digest of the model's settings and training data (the
                      workflow's rerun trigger, denoisers.experiment), which the report checks
* ``settings.json``   the resolved model settings

``summary.json`` also holds ``crop_check``: when the model trained on crops smaller than the frames, how much
worse ``best.pt`` is on whole validation frames than on crop-sized windows of them (denoisers.crop_check; the
report counts a gap below ``CROP_GAP_DB`` as a training defect), or why the check was skipped.

An ablation variant whose settings equal its base model's (``same_training_as``) is not trained again: its
directory holds the base's files with its own summary (``same_training_as`` names the base) and settings.

A half-budget twin ``{id}_half`` (training.half_budget) is the full model's run stopped at half its steps: its
job trains in the full model's work directory (same id, seed and fingerprint) up to that step and publishes the
state there, and the full model's job, which the workflow runs after it, continues the same run to the end. When
that directory already holds a later step, the twin trains afresh in a directory of its own.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path
from typing import Any

from scenegen.atomic import atomic_directory, write_text_atomic

from denoisers.provenance import provenance
from denoisers.training.digests import data_settings, model_digest as _model_digest  # noqa: F401 (re-exported)
from denoisers.training.models import (HALF_SUFFIX, ModelSpec, half_of, model_spec, same_training_as, settings_digest,
                                       training_split)
from denoisers.training.tasks import (clip_buffers, reference_buffers, sequence_config,  # noqa: F401 (re-exported)
                                      task_sequence_config)

log = logging.getLogger(__name__)

WORK_DIR_NAME = ".work"


def work_dir_for(models_root: Path, cfg: dict, spec: ModelSpec) -> Path:
    """The trainer's resumable directory: keyed by every setting but the budget, and by the step arithmetic
    ``compute`` resolves to on this machine (precision auto: bf16 or fp32), so a run moved to a machine that
    resolves it otherwise starts afresh instead of mixing the two."""
    from denoisers.device import key_device
    from denoisers.training.precision import resolve_compute

    unbudgeted = ModelSpec(**{**spec.__dict__, "budget": {}})
    digest = settings_digest(unbudgeted, {**data_settings(cfg, spec),
                                          "compute": resolve_compute(spec.compute).fingerprint(), **key_device(cfg)})
    return Path(models_root) / WORK_DIR_NAME / f"{spec.id}-{digest[:12]}"


def trainer_config(cfg: dict, spec: ModelSpec, threads: int, progress: bool = True) -> Any:
    from denoisers.training.loop import TrainerConfig
    from denoisers.training.precision import DEFAULT_COMPUTE

    optimizer, budget, training = spec.optimizer, spec.budget, cfg["training"]
    compute = {**DEFAULT_COMPUTE, **spec.compute}
    warmup = min(int(cfg["evaluation"]["warmup_frames"]), spec.data["length"] - 1)
    return TrainerConfig(seed=spec.seed, batch_size=optimizer["batch_size"], max_steps=budget["max_steps"],
                         max_seconds=budget.get("max_seconds"), lr=optimizer["lr"], betas=tuple(optimizer["betas"]),
                         schedule=dict(optimizer["schedule"]), grad_clip_norm=optimizer.get("grad_clip_norm"),
                         log_every=max(1, min(10, budget["max_steps"] // 10 or 1)),
                         validate_every=training["validate_every"], checkpoint_every=training["validate_every"],
                         checkpoint_seconds=300.0, best_metric="loss", validation_warmup_frames=warmup,
                         progress=progress, threads=threads, precision=compute["precision"],
                         channels_last=compute["channels_last"], ema_decay=optimizer.get("ema_decay"))


#: Files of a published model directory that do not depend on the model's id.
_PUBLISHED_FILES = ("best.pt", "curves.csv", "curves.png", "validation.csv")


def publish_same_training(cfg: dict, model_id: str, source_dir: Path, out_dir: Path) -> dict[str, Any]:
    """Publish ``out_dir`` for an ablation variant whose training is identical to the model published in
    ``source_dir`` (:func:`denoisers.training.models.same_training_as`): its weights, curves and validation
    metrics, with a summary under the variant's id, ablation and settings digest that records
    ``same_training_as``. Raises FileNotFoundError if the source is not trained, ValueError if it is stale."""
    spec = model_spec(cfg, model_id)
    source_id = source_dir.name
    summary_path = source_dir / "summary.json"
    if not summary_path.exists():
        raise FileNotFoundError(f"model {model_id!r} trains exactly as {source_id!r} and reuses its weights, but "
                                f"{summary_path} does not exist: train {source_id!r} first")
    summary = json.loads(summary_path.read_text())
    expected = _model_digest(cfg, model_spec(cfg, source_id))
    if summary.get("settings_digest") != expected:
        raise ValueError(f"model {model_id!r} reuses {source_dir}, which was trained with other settings "
                         f"(digest {summary.get('settings_digest')}, this config: {expected}): retrain {source_id!r}")
    summary.update({"model_id": model_id, "ablation": spec.ablation, "variant": spec.variant,
                    "same_training_as": source_id, "settings_digest": _model_digest(cfg, spec)})
    log.info("model %s: the same training as %s (same seed, data, settings and budget): its weights are reused",
             model_id, source_id)
    with atomic_directory(out_dir) as staging:
        for name in _PUBLISHED_FILES:
            shutil.copy2(source_dir / name, staging / name)
        write_text_atomic(staging / "summary.json", json.dumps(summary, indent=1, sort_keys=True, default=str) + "\n")
        write_text_atomic(staging / "settings.json", json.dumps(spec.settings(), indent=1, sort_keys=True) + "\n")
    return summary


def train_model(cfg: dict, model_id: str, render_root: Path, out_dir: Path, threads: int | None = None,
                progress: bool = True, stop_at_step: int | None = None) -> dict[str, Any]:
    """Train model ``model_id`` of ``cfg`` on ``render_root/<scene>`` clips; write ``out_dir``; return the summary.

    With the model store in use (config ``store``; denoisers.store) a model whose key is stored is installed
    instead (no render is read), unless ``store.force_training``; a stored part-way checkpoint of the run is
    continued. ``stop_at_step`` ends training early with every setting (schedule included) unchanged: the first
    steps of the configured run (``store verify``); it never installs from the store.

    The step runs on ``training.threads`` torch threads, which are part of the model's settings (the weights
    depend on them); ``threads``, if given, must agree (ValueError otherwise)."""
    import torch

    from denoisers.device import configured_device, default_device, device_info, key_device, torch_device
    from denoisers.training.data import fixed_batches, load_training_clips
    from denoisers.training.loop import Trainer, load_checkpoint
    from denoisers.training.tasks import task_builder

    spec = model_spec(cfg, model_id)
    if threads is not None and int(threads) != spec.threads:
        raise ValueError(f"model {model_id!r} trains on training.threads = {spec.threads} torch threads (its weights "
                         f"depend on the count), but {threads} were asked for: change training.threads instead")
    threads = spec.threads
    torch.set_num_threads(threads)
    source = same_training_as(cfg, model_id)
    if source is not None:
        return publish_same_training(cfg, model_id, Path(out_dir).parent / source, Path(out_dir))
    from denoisers.store import ModelStore, model_key, store_settings

    store_use = store_settings(cfg)
    store = ModelStore.of(cfg) if store_use["use"] else None
    if store is not None and not store_use["force_training"] and stop_at_step is None:
        entry = store.model_entry(cfg, model_id)
        if entry is not None:
            return store.install(entry, Path(out_dir))
    # The key of the code that is about to run (a module edited while training must not re-key these weights).
    key = model_key(cfg, model_id)
    # A half-budget twin is its full model's run (that spec's id, seed and fingerprint) stopped at its own max_steps.
    full_id = half_of(cfg, model_id)
    run_spec = model_spec(cfg, full_id) if full_id else spec
    if full_id:
        stop_at_step = spec.budget["max_steps"]
    builder = task_builder(run_spec.method)
    task = builder.build(run_spec)
    train_scenes, validation_scenes = training_split(cfg, spec)
    if not train_scenes or not validation_scenes:
        raise ValueError(f"model {model_id!r}: need training and validation scenes, got {train_scenes} / "
                         f"{validation_scenes}")
    render_root = Path(render_root)
    buffers = clip_buffers(builder)
    log.info("model %s (%s): training on %s, validating on %s", model_id, spec.method, ", ".join(train_scenes),
             ", ".join(validation_scenes))
    train_clips = load_training_clips([render_root / s for s in train_scenes], buffers)
    validation_clips = load_training_clips([render_root / s for s in validation_scenes], buffers)

    from denoisers.training.data import SequenceDataset

    sequences = task_sequence_config(builder, spec, train_clips + validation_clips)
    if builder.optional_reference_buffers:
        log.info("model %s: reference buffers %s (optional: %s)", model_id, ", ".join(sequences.reference_buffers),
                 ", ".join(builder.optional_reference_buffers))
    dataset = SequenceDataset(train_clips, sequences, seed=run_spec.seed)
    # The same validation sequences for every model of the config (seeded by the global seed), so
    # models are compared pairwise on identical data.
    validation = fixed_batches(validation_clips, sequences, cfg["training"]["validation_sequences"], batch_size=1,
                               seed=int(cfg["seed"]))
    config = trainer_config(cfg, run_spec, threads, progress)
    if stop_at_step is not None:
        config = dataclasses.replace(config, max_steps=min(int(stop_at_step), config.max_steps), max_seconds=None)
    work_dir = work_dir_for(Path(out_dir).parent, cfg, run_spec)
    if store is not None:
        from denoisers.training.precision import resolve_compute

        store.fetch_checkpoint(cfg, run_spec.id, work_dir, resolve_compute(run_spec.compute).fingerprint())
        # (the checkpoint key holds the device, denoisers.store.keys, so a CUDA run never continues a CPU one)
    checkpoint = work_dir / "checkpoint.pt"
    if full_id and checkpoint.exists() and int(load_checkpoint(checkpoint)["step"]) > spec.budget["max_steps"]:
        log.info("%s is past step %d: the half-budget model %s trains afresh in its own directory", checkpoint,
                 spec.budget["max_steps"], model_id)
        work_dir = work_dir.with_name(work_dir.name + HALF_SUFFIX)
        checkpoint = work_dir / "checkpoint.pt"
    if checkpoint.exists() and int(load_checkpoint(checkpoint)["step"]) > run_spec.budget["max_steps"]:
        log.info("%s holds more steps than budget.max_steps = %d: training from scratch", checkpoint,
                 run_spec.budget["max_steps"])
        shutil.rmtree(work_dir)
    from denoisers.training.on_device import place

    device = torch_device(cfg)
    if device.type != "cpu":
        # The CPU's bf16 autocast and oneDNN layouts do not apply on CUDA: the step runs in fp32 there.
        config = dataclasses.replace(config, precision="fp32", channels_last=False)
    task, dataset, validation = place(task, dataset, validation, device)
    trainer = Trainer(task, dataset, validation, config, work_dir,
                      fingerprint_extra={"model": run_spec.settings() | {"budget": None},
                                         "data": data_settings(cfg, run_spec), **key_device(cfg)})
    with default_device(device):
        result = trainer.run()

    # Per-sequence validation metrics of the selected model (paired comparisons between models).
    best = load_checkpoint(result.best)
    trainer.model.load_state_dict(best["model_state"])
    rows = []
    for index, batch in enumerate(validation):
        with default_device(device):
            metrics = trainer.evaluate([batch])
        rows.append({"sequence": index, "description": batch.describe(), **metrics})
    import pandas as pd

    stopped_by = ("max_steps" if result.steps >= spec.budget["max_steps"] else
                  "stop_at_step" if stop_at_step is not None and result.steps >= stop_at_step else "max_seconds")
    if full_id:
        log.info("model %s: the run of %s stopped at step %d (half its budget)", model_id, full_id, result.steps)
    summary = json.loads((work_dir / "summary.json").read_text())
    summary.update({"model_id": model_id, "method": spec.method, "ablation": spec.ablation, "variant": spec.variant,
                    "train_scenes": train_scenes, "validation_scenes": validation_scenes, "stopped_by": stopped_by,
                    "max_steps": spec.budget["max_steps"], "max_seconds": spec.budget.get("max_seconds"),
                    "threads": int(threads), "seconds_per_step": result.elapsed_seconds / max(result.steps, 1),
                    "settings_digest": _model_digest(cfg, spec), "store_key": key, "half_budget_of": full_id,
                    "provenance": provenance({"training": int(threads)},
                                             device=device_info(configured_device(cfg))),
                    "device": configured_device(cfg)})
    if hasattr(task, "config") and hasattr(task.config, "width"):
        from denoisers.nets import build_net, count_parameters

        full = build_net(task.net_spec()["name"], {**task.net_spec()["config"], "width": 1.0})
        summary["parameters_full_width"] = count_parameters(full)
    summary["crop_check"] = whole_frame_check(spec, sequences.crop, sequences.spp,
                                              [render_root / s for s in validation_scenes], result.best)
    if stopped_by == "max_seconds":
        log.warning("model %s: the time cap max_seconds = %s stopped training at step %d of %d; the weights "
                    "depend on this machine's speed", model_id, spec.budget.get("max_seconds"), result.steps,
                    spec.budget["max_steps"])
    with atomic_directory(Path(out_dir)) as staging:
        for name in ("best.pt", "curves.csv", "curves.png"):
            shutil.copy2(work_dir / name, staging / name)
        pd.DataFrame(rows).to_csv(staging / "validation.csv", index=False)
        write_text_atomic(staging / "summary.json", json.dumps(summary, indent=1, sort_keys=True, default=str) + "\n")
        write_text_atomic(staging / "settings.json", json.dumps(spec.settings(), indent=1, sort_keys=True) + "\n")
    return summary


def whole_frame_check(spec: ModelSpec, crop: int | None, spp: int, render_dirs: list[Path],
                      checkpoint: Path) -> dict[str, Any]:
    """denoisers.crop_check of ``checkpoint`` on the validation scenes at the training crop and spp, or
    ``{"skipped": why}`` (whole-frame training, an adaptive method, frames no larger than the crop)."""
    from denoisers import crop_check, registry
    from denoisers.training.data import load_training_clips

    info = registry.get(spec.method).info
    if crop is None:
        return {"skipped": "trained on whole frames"}
    if info.adaptive:
        return {"skipped": f"method {spec.method!r} is adaptive (a window moves its sample budget)"}
    method = registry.build(spec.method, {"checkpoint": str(checkpoint)})
    clips = load_training_clips(render_dirs, info.inputs, layers=spp * method.samples_factor)
    smallest = min(min(clip.samples[info.inputs[0]].shape[-2:]) for clip in clips)
    if crop >= smallest:
        return {"skipped": f"the crop {crop} covers the whole {smallest}-pixel frames"}
    check = crop_check.check_method(method, clips, spp, crop)
    log.info("model %s: whole validation frames minus %d-pixel windows: %+.2f dB (lowest scene)", spec.id, crop,
             check["gap_db"])
    return check
