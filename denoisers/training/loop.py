"""A generic trainer for the learned denoisers: Adam, learning-rate schedules, step or time budgets, exact
resume from checkpoints, validation with best-checkpoint selection, training curves and a progress bar.

A method plugs in a *task* (see :class:`TrainingTask`; the RAE's is ``denoisers.nets.rae_task.RAETask``) and a
data source with ``batch(index, batch_size)`` (``denoisers.training.data.SequenceDataset``). Files in
the output directory:

* ``checkpoint.pt`` -- everything needed to continue exactly: model, Adam state, schedule, step, elapsed
  time, the torch / numpy / python RNG states, the data stream position (batch ``i`` is a pure function
  of the data seed and ``i``, so the position is the step count), history and best-so-far. Written
  atomically (temporary file, fsync, rename), every ``checkpoint_every`` steps, every
  ``checkpoint_seconds`` and at the end. A new :class:`Trainer` on the same directory resumes from it,
  and N uninterrupted steps give bit-identical weights to N/2 + kill + resume + N/2.
* ``best.pt`` -- the model with the best validation metric so far (the last model without validation).
* ``curves.csv`` / ``curves.png`` -- training loss (mean over each ``log_every`` steps) and validation
  metrics per step; ``summary.json`` -- the outcome, with the step arithmetic used (``compute``).

The step's arithmetic (``precision`` fp32 / bf16 autocast / auto, ``channels_last`` weights) is
``denoisers.training.precision``; the resolved choice is logged once per run and fingerprinted.

Errors: a non-finite loss stops training with :class:`NonFiniteLossError` naming the step and the batch
(its sequences); an unreadable, truncated or foreign checkpoint raises :class:`CheckpointError` naming
the file, as does a checkpoint written for a different configuration.
"""
from __future__ import annotations

import copy
import json
import math
import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from denoisers.errors import NonFiniteLossError  # noqa: F401 (raised here, imported from here elsewhere)
from denoisers.training.checkpoints import (CHECKPOINT_FORMAT, CHECKPOINT_VERSION, CheckpointError, fingerprint,
                                            load_checkpoint, load_model, rng_state, save_atomic, set_rng_state)
from denoisers.training.curves import plot_curves
from denoisers.training.precision import log_choice, loss_model, prepare_model, resolve
from denoisers.training.schedules import lr_factor
from scenegen.atomic import write_text_atomic

__all__ = ["BatchSource", "CheckpointError", "NonFiniteLossError", "Trainer", "TrainerConfig", "TrainResult",
           "TrainingTask", "load_checkpoint", "load_model", "lr_factor"]

CHECKPOINT_NAME = "checkpoint.pt"
BEST_NAME = "best.pt"
CURVES_CSV = "curves.csv"
CURVES_PNG = "curves.png"
SUMMARY_NAME = "summary.json"
#: curves.png is redrawn at most this often during training (drawing takes ~0.3 s), and at the end.
PLOT_INTERVAL_SECONDS = 60.0
#: Validation metrics where larger is better (everything else is minimised).
HIGHER_IS_BETTER: frozenset[str] = frozenset({"ssim", "psnr"})
#: Trainer settings that do not change the weights after a given step (excluded from the fingerprint,
#: so a run can be resumed with a longer budget or other logging).
_NOT_FINGERPRINTED = frozenset({"max_steps", "max_seconds", "progress", "threads", "checkpoint_every",
                                "checkpoint_seconds", "log_every",
                                "precision", "channels_last"})  # fingerprinted as resolved ("compute")


class TrainingTask(Protocol):
    """What the trainer needs from a method (see ``denoisers.nets.rae_task.RAETask``)."""

    name: str

    def build_model(self) -> nn.Module: ...                                   # fresh, initialised network
    def net_spec(self) -> dict[str, Any]: ...                                 # {'name', 'config'} for nets.build_net
    def describe(self) -> dict[str, Any]: ...                                 # everything that changes training
    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]: ...


class BatchSource(Protocol):
    def batch(self, index: int, batch_size: int) -> Any: ...
    def describe(self) -> dict[str, Any]: ...


# ---------------------------------------------------------------------------------------- config
@dataclass
class TrainerConfig:
    """Optimisation and bookkeeping settings (defaults: the RAE's Adam settings, §5.3).

    At least one budget, ``max_steps`` or ``max_seconds`` (training wall time, summed over resumed
    runs), must be set; training stops at whichever comes first. ``best_metric`` is a validation key
    ('loss', 'ssim', 'psnr', 'rmse'); ssim and psnr are maximised, the others minimised.
    ``validation_warmup_frames`` skips the first frames of each validation sequence in the image metrics.
    ``precision`` ('fp32', 'bf16' or 'auto') and ``channels_last`` (bool or 'auto'): the training step's arithmetic
    (:func:`denoisers.training.precision.resolve`); validation always runs in fp32.
    ``ema_decay`` (None = off): validate and save an exponential moving average of the weights, updated after
    every step with decay min(ema_decay, (1 + step) / (10 + step)) (the early steps average over fewer steps).
    A ``cosine`` schedule without ``total_steps`` decays over ``max_steps`` (the step budget).
    """

    seed: int = 0
    batch_size: int = 4
    max_steps: int | None = None
    max_seconds: float | None = None
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-8
    weight_decay: float = 0.0
    schedule: dict[str, Any] = field(default_factory=lambda: {"name": "ramp_inv_sqrt", "ramp_steps": 100,
                                                              "ramp_factor": 10.0})
    grad_clip_norm: float | None = None
    log_every: int = 10
    validate_every: int = 100
    checkpoint_every: int = 100
    checkpoint_seconds: float | None = 600.0
    best_metric: str = "loss"
    validation_warmup_frames: int = 0
    progress: bool = True
    threads: int | None = None
    precision: str = "fp32"
    channels_last: bool | str = False
    ema_decay: float | None = None

    def __post_init__(self) -> None:
        self.betas = tuple(float(b) for b in self.betas)
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in (0, 1) or None, got {self.ema_decay}")
        if self.max_steps is None and self.max_seconds is None:
            raise ValueError("training needs a budget: set max_steps and/or max_seconds")
        if self.batch_size < 1 or self.log_every < 1 or self.validate_every < 0 or self.checkpoint_every < 0:
            raise ValueError(f"need batch_size >= 1, log_every >= 1, validate_every >= 0, checkpoint_every >= 0: {self}")
        if self.schedule.get("name") == "cosine" and self.schedule.get("total_steps") is None:
            if self.max_steps is None:
                raise ValueError("a cosine schedule without total_steps decays over max_steps: set max_steps")
            self.schedule = {**self.schedule, "total_steps": int(self.max_steps)}   # fingerprinted as resolved
        lr_factor(self.schedule, 0)  # rejects unknown schedules early
        resolve(self.precision, self.channels_last)  # and unknown precisions

    def fingerprint_data(self) -> dict[str, Any]:
        data = {k: v for k, v in asdict(self).items() if k not in _NOT_FINGERPRINTED}
        if data["ema_decay"] is None:   # runs from before the key existed resume unchanged
            del data["ema_decay"]
        return data


@dataclass
class TrainResult:
    """Outcome of :meth:`Trainer.run`."""

    steps: int
    elapsed_seconds: float
    resumed_from: int | None
    best_step: int | None
    best_metric: str
    best_value: float | None
    checkpoint: Path
    best: Path
    curves_csv: Path
    curves_png: Path


# --------------------------------------------------------------------------------------- trainer
class Trainer:
    """Trains ``task``'s model on ``train_data`` batches, validating on ``validation`` batches.

    ``out_dir`` holds the files of the module docstring; an existing ``checkpoint.pt`` there is resumed.
    ``fingerprint_extra`` adds anything else that should forbid resuming when it changes.
    """

    def __init__(self, task: TrainingTask, train_data: BatchSource, validation: Sequence[Any], config: TrainerConfig,
                 out_dir: Path | str, fingerprint_extra: Mapping[str, Any] | None = None) -> None:
        self.task, self.train_data, self.validation, self.config = task, train_data, list(validation), config
        self.out_dir = Path(out_dir)
        self.compute = resolve(config.precision, config.channels_last)
        self.checkpoint_path = self.out_dir / CHECKPOINT_NAME
        self.best_path = self.out_dir / BEST_NAME
        self.fingerprint_data = {
            "trainer": config.fingerprint_data(), "task": task.describe(), "data": train_data.describe(),
            "validation": [getattr(b, "describe", lambda: repr(b))() for b in self.validation],
            "extra": dict(fingerprint_extra or {}), "compute": self.compute.fingerprint(),
        }
        self.fingerprint = fingerprint(self.fingerprint_data)
        self.model: nn.Module | None = None
        self.ema: nn.Module | None = None                 # averaged weights (config.ema_decay), else None
        self._loss_model: nn.Module | None = None          # what task.loss calls (see _setup)
        self.optimizer: torch.optim.Optimizer | None = None
        self.step = 0
        self.elapsed = 0.0
        self.history: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None
        self.last_validation_step = -1
        self._accumulator: dict[str, float] = {}
        self._last_plot = -math.inf
        self._checkpoint_step: int | None = None

    # --------------------------------------------------------------------------------- set-up
    def _setup(self) -> int | None:
        """Build model and optimiser from the seed, then load ``checkpoint.pt`` if present.
        Returns the step resumed from (None for a fresh start)."""
        config = self.config
        torch.manual_seed(config.seed)
        np.random.seed(config.seed % 2**32)
        random.seed(config.seed)
        self.model = prepare_model(self.task.build_model(), self.compute)
        self._loss_model = loss_model(self.model, self.compute)  # the model, or its bf16 autocast forward
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr, betas=config.betas, eps=config.eps,
                                          weight_decay=config.weight_decay)
        if config.ema_decay is not None:
            self.ema = copy.deepcopy(self.model).requires_grad_(False)
        if not self.checkpoint_path.exists():
            return None
        data = load_checkpoint(self.checkpoint_path)
        if data.get("kind") != "training":
            raise CheckpointError(f"{self.checkpoint_path}: a model file, not a training checkpoint")
        if data["fingerprint"] != self.fingerprint:
            try:
                stored = json.loads(data.get("fingerprint_data", "{}"))
            except json.JSONDecodeError:
                stored = {}
            current = json.loads(json.dumps(self.fingerprint_data, sort_keys=True, default=str))
            changed = sorted(k for k in set(stored) | set(current) if stored.get(k) != current.get(k))
            raise CheckpointError(f"{self.checkpoint_path}: written for a different training configuration "
                                  f"(changed: {', '.join(changed) or 'unknown'}); delete {self.out_dir} to retrain")
        try:
            self.model.load_state_dict(data["model_state"])
            self.optimizer.load_state_dict(data["optimizer_state"])
            if self.ema is not None:
                self.ema.load_state_dict(data["ema_state"])
            set_rng_state(data["rng"])
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CheckpointError(f"{self.checkpoint_path}: cannot restore the training state ({error})") from error
        self.step = self._checkpoint_step = int(data["step"])
        self.elapsed = float(data.get("elapsed_seconds", 0.0))
        self.history = [dict(row) for row in data["history"]]
        self.best = dict(data["best"]) if data.get("best") else None
        self.last_validation_step = int(data.get("last_validation_step", -1))
        self._accumulator = dict(data.get("accumulator", {}))
        return self.step

    def _budget_left(self) -> bool:
        config = self.config
        if config.max_steps is not None and self.step >= config.max_steps:
            return False
        return config.max_seconds is None or self.elapsed < config.max_seconds

    # ------------------------------------------------------------------------------- training
    def run(self, on_step: Callable[[int], None] | None = None) -> TrainResult:
        """Train until the budget is used up (resuming ``checkpoint.pt`` if present) and return the outcome.

        ``on_step(step)`` is called after every optimiser step (tests use it to simulate a kill).
        """
        from tqdm.auto import tqdm

        config = self.config
        if config.threads:
            torch.set_num_threads(int(config.threads))
        resumed_from = self._setup()
        assert self.model is not None and self.optimizer is not None
        log_choice(self.compute, self.task.name)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        elapsed_at_start = self.elapsed
        last_checkpoint = started
        log_started, log_step = started, self.step
        first_step = self.step
        progress = tqdm(total=config.max_steps, initial=self.step, disable=not config.progress, unit="step",
                        desc=f"train {self.task.name}", dynamic_ncols=True, mininterval=1.0)
        try:
            while self._budget_left():
                loss_value, terms = self._train_step()
                self.elapsed = elapsed_at_start + (time.perf_counter() - started)
                self._accumulate(loss_value, terms)
                if self.step % config.log_every == 0:
                    now = time.perf_counter()
                    self._log_row(steps_per_s=(self.step - log_step) / max(now - log_started, 1e-9))
                    log_started, log_step = now, self.step
                if config.validate_every and self.step % config.validate_every == 0:
                    self._validate()
                time_due = config.checkpoint_seconds is not None and \
                    time.perf_counter() - last_checkpoint >= config.checkpoint_seconds
                if (config.checkpoint_every and self.step % config.checkpoint_every == 0) or time_due:
                    self.save_checkpoint()
                    last_checkpoint = time.perf_counter()
                progress.update(1)
                progress.set_postfix(loss=f"{loss_value:.4g}", refresh=False, steps_per_s=
                                     f"{(self.step - first_step) / max(time.perf_counter() - started, 1e-9):.3g}")
                if on_step is not None:
                    on_step(self.step)
        finally:
            progress.close()
        if self._accumulator.get("count"):
            now = time.perf_counter()
            self._log_row(steps_per_s=(self.step - log_step) / max(now - log_started, 1e-9))
        if self.validation and self.last_validation_step != self.step:
            self._validate()
        if not self.validation or self.best is None or not self.best_path.exists():
            # Without validation (or before any finite validation result) the last model is the best guess.
            self._save_model(self.best_path, metrics={})
            self.best = {"step": self.step, "metric": config.best_metric, "value": None, "metrics": {}}
        self.save_checkpoint()
        self.write_curves(plot=True)
        result = TrainResult(steps=self.step, elapsed_seconds=self.elapsed, resumed_from=resumed_from,
                             best_step=self.best.get("step"), best_metric=config.best_metric,
                             best_value=self.best.get("value"), checkpoint=self.checkpoint_path, best=self.best_path,
                             curves_csv=self.out_dir / CURVES_CSV, curves_png=self.out_dir / CURVES_PNG)
        self._write_summary(result)
        return result

    def _train_step(self) -> tuple[float, dict[str, float]]:
        """One optimiser step on batch number ``self.step``; returns (loss, loss terms)."""
        config, model, optimizer = self.config, self.model, self.optimizer
        batch = self.train_data.batch(self.step, config.batch_size)
        lr = config.lr * lr_factor(config.schedule, self.step)
        for group in optimizer.param_groups:
            group["lr"] = lr
        model.train()
        optimizer.zero_grad(set_to_none=True)
        loss, terms = self.task.loss(self._loss_model, batch)
        if not bool(torch.isfinite(loss)):
            description = batch.describe() if hasattr(batch, "describe") else f"batch {self.step}"
            raise NonFiniteLossError(
                f"training stopped: non-finite loss ({float(loss.detach())}) at step {self.step} ({description}); "
                f"last checkpoint: {self._checkpoint_note()}", step=self.step, batch=description)
        loss.backward()
        if config.grad_clip_norm is not None:
            nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip_norm)
        optimizer.step()
        if self.ema is not None:
            self._update_ema()
        self.step += 1
        self._last_lr = lr
        return float(loss.detach()), terms

    @torch.no_grad()
    def _update_ema(self) -> None:
        """ema <- decay * ema + (1 - decay) * model for parameters; buffers are copied."""
        decay = min(float(self.config.ema_decay), (1.0 + self.step) / (10.0 + self.step))
        torch._foreach_lerp_(list(self.ema.parameters()), [p.detach() for p in self.model.parameters()], 1.0 - decay)
        for mine, theirs in zip(self.ema.buffers(), self.model.buffers()):
            mine.copy_(theirs)

    @property
    def evaluated_model(self) -> nn.Module:
        """The weights validation scores and best.pt stores: the moving average when enabled."""
        return self.ema if self.ema is not None else self.model

    def _checkpoint_note(self) -> str:
        if not self.checkpoint_path.exists():
            return "none written yet"
        return f"{self.checkpoint_path} (step {self._checkpoint_step})"

    def _accumulate(self, loss: float, terms: Mapping[str, float]) -> None:
        acc = self._accumulator
        acc["count"] = acc.get("count", 0.0) + 1
        acc["loss"] = acc.get("loss", 0.0) + loss
        for name, value in terms.items():
            acc[f"loss_{name}"] = acc.get(f"loss_{name}", 0.0) + float(value)

    def _row(self, step: int) -> dict[str, Any]:
        for row in reversed(self.history):
            if row["step"] == step:
                return row
        row = {"step": step}
        self.history.append(row)
        return row

    def _log_row(self, steps_per_s: float) -> None:
        acc, self._accumulator = self._accumulator, {}
        count = acc.pop("count", 0.0)
        if not count:
            return
        row = self._row(self.step)
        row.update(elapsed_s=self.elapsed, lr=getattr(self, "_last_lr", self.config.lr), steps_per_s=steps_per_s)
        row.update({f"train_{key}": value / count for key, value in acc.items()})

    # ----------------------------------------------------------------------------- validation
    def evaluate(self, batches: Sequence[Any] | None = None) -> dict[str, float]:
        """Validation metrics of the current model: mean loss (and its terms) over the batches, and, when
        the task has ``predict``, mean SSIM / PSNR / RMSE (denoisers.metrics) of the linear outputs
        against ``reference.radiance`` per sequence, skipping ``validation_warmup_frames``."""
        from denoisers import metrics

        batches = self.validation if batches is None else list(batches)
        model = self.evaluated_model
        model.eval()
        sums: dict[str, float] = {}
        counts: dict[str, int] = {}

        def add(key: str, value: float) -> None:
            sums[key] = sums.get(key, 0.0) + value
            counts[key] = counts.get(key, 0) + 1

        warmup = self.config.validation_warmup_frames
        with torch.no_grad():
            for batch in batches:
                loss, terms = self.task.loss(model, batch)
                add("loss", float(loss))
                for name, value in terms.items():
                    add(f"loss_{name}", float(value))
                if hasattr(self.task, "predict"):
                    prediction = self.task.predict(model, batch)
                    reference = batch["reference.radiance"]
                    for n in range(prediction.shape[0]):
                        pred, ref = prediction[n, warmup:], reference[n, warmup:]
                        for name, function in (("ssim", metrics.ssim), ("psnr", metrics.psnr), ("rmse", metrics.rmse)):
                            try:
                                add(name, function(pred, ref))
                            except ValueError:  # non-finite output, or frames too small for SSIM
                                add(name, float("nan"))
        model.train()
        return {key: sums[key] / counts[key] for key in sums}

    def _validate(self) -> None:
        self.last_validation_step = self.step
        if not self.validation:
            return
        results = self.evaluate()
        row = self._row(self.step)
        row.update({f"val_{key}": value for key, value in results.items()})
        row.setdefault("elapsed_s", self.elapsed)
        metric = self.config.best_metric
        if metric not in results:
            raise KeyError(f"best_metric {metric!r} is not a validation result; available: {sorted(results)}")
        value = results[metric]
        better = (value > self.best["value"] if metric in HIGHER_IS_BETTER else value < self.best["value"]) \
            if self.best and self.best.get("value") is not None else True
        if math.isfinite(value) and better:
            self.best = {"step": self.step, "metric": metric, "value": value, "metrics": results}
            self._save_model(self.best_path, metrics=results)
        self.write_curves()

    # ---------------------------------------------------------------------------------- files
    def _save_model(self, path: Path, metrics: Mapping[str, float]) -> None:
        save_atomic({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": "model",
                      "net": self.task.net_spec(), "model_state": self.evaluated_model.state_dict(),
                      "step": self.step, "metrics": dict(metrics)}, path)

    def save_checkpoint(self) -> None:
        """Write ``checkpoint.pt`` (atomically) and refresh the curves."""
        save_atomic({
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": "training",
            "fingerprint": self.fingerprint,
            "fingerprint_data": json.dumps(self.fingerprint_data, sort_keys=True, default=str),
            "net": self.task.net_spec(), "model_state": self.model.state_dict(),
            "optimizer_state": self.optimizer.state_dict(),
            **({"ema_state": self.ema.state_dict()} if self.ema is not None else {}),
            "scheduler": {"schedule": dict(self.config.schedule), "base_lr": self.config.lr,
                          "next_lr": self.config.lr * lr_factor(self.config.schedule, self.step)},
            "step": self.step, "elapsed_seconds": self.elapsed,
            "sampler": {"next_batch": self.step, "batch_size": self.config.batch_size},
            "rng": rng_state(), "history": self.history, "accumulator": dict(self._accumulator),
            "best": self.best, "last_validation_step": self.last_validation_step,
        }, self.checkpoint_path)
        self._checkpoint_step = self.step
        self.write_curves()

    def write_curves(self, plot: bool | None = None) -> None:
        """``curves.csv`` (one row per logged or validated step) and ``curves.png``; the plot is redrawn
        when ``plot`` is True, or (None) when it is older than :data:`PLOT_INTERVAL_SECONDS`."""
        if not self.history:
            return
        columns = ["step"] + sorted({key for row in self.history for key in row} - {"step"})
        lines = [",".join(columns)]
        for row in sorted(self.history, key=lambda r: r["step"]):
            lines.append(",".join("" if row.get(c) is None else f"{row[c]:.8g}" if isinstance(row[c], float)
                                  else str(row[c]) for c in columns))
        write_text_atomic(self.out_dir / CURVES_CSV, "\n".join(lines) + "\n")
        now = time.perf_counter()
        if plot or (plot is None and now - self._last_plot >= PLOT_INTERVAL_SECONDS):
            plot_curves(self.history, self.out_dir / CURVES_PNG, title=f"{self.task.name} training")
            self._last_plot = now

    def _write_summary(self, result: TrainResult) -> None:
        from denoisers.nets import count_parameters

        summary = {
            "task": self.task.name, "steps": result.steps, "elapsed_seconds": result.elapsed_seconds,
            "resumed_from": result.resumed_from, "best_step": result.best_step, "best_metric": result.best_metric,
            "best_value": result.best_value, "best_metrics": (self.best or {}).get("metrics", {}),
            "parameters": count_parameters(self.model), "net": self.task.net_spec(),
            "fingerprint": self.fingerprint, "compute": self.compute.to_dict(),
        }
        write_text_atomic(self.out_dir / SUMMARY_NAME, json.dumps(summary, indent=1, sort_keys=True, default=str) + "\n")
