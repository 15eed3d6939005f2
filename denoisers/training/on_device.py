"""Training on a device other than the CPU, without touching the code that keys stored models.

The trainer (``denoisers.training.loop``), the tasks and the data stream are hashed into every model's store key
(``denoisers.store.code``), so placing them on a device there would re-key every stored model. Instead the
training job wraps what it hands the trainer: :class:`DeviceTask` builds the network on the device and moves each
batch there before the task's loss or prediction, which run with the device as torch's default device
(:func:`denoisers.device.default_device`: tensors the task creates without a ``device`` argument land there too);
:class:`DeviceBatches` moves the training batches, and the validation batches are moved once. The job runs the
trainer inside the same default device (validation metrics, the optimizer). On the CPU nothing is wrapped
(:func:`place`).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from denoisers.device import default_device, to_device


class DeviceTask:
    """A training task (``denoisers.training.loop.TrainingTask``) whose model and batches live on ``device``.
    ``predict`` exists exactly when the wrapped task has it (the trainer checks ``hasattr``)."""

    def __init__(self, task: Any, device: torch.device) -> None:
        self.task, self.device = task, device
        self.name = task.name
        if hasattr(task, "predict"):
            self.predict = self._predict

    def build_model(self) -> nn.Module:
        with default_device(self.device):
            return self.task.build_model().to(self.device)

    def net_spec(self) -> dict[str, Any]:
        return self.task.net_spec()

    def describe(self) -> dict[str, Any]:
        return self.task.describe()

    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        with default_device(self.device):
            return self.task.loss(model, to_device(batch, self.device))

    def _predict(self, model: nn.Module, batch: Any) -> torch.Tensor:
        with default_device(self.device):
            return self.task.predict(model, to_device(batch, self.device))

    def __getattr__(self, name: str) -> Any:   # config, spp, ... of the wrapped task
        if name == "task":
            raise AttributeError(name)
        return getattr(self.task, name)


class DeviceBatches:
    """A batch source whose batches are moved to ``device``; its description is the wrapped source's."""

    def __init__(self, source: Any, device: torch.device) -> None:
        self.source, self.device = source, device

    def batch(self, index: int, batch_size: int) -> Any:
        return to_device(self.source.batch(index, batch_size), self.device)

    def describe(self) -> dict[str, Any]:
        return self.source.describe()


def place(task: Any, train_data: Any, validation: Sequence[Any], device: torch.device
          ) -> tuple[Any, Any, list[Any]]:
    """(task, training batches, validation batches) for ``device``: unchanged on the CPU."""
    if device.type == "cpu":
        return task, train_data, list(validation)
    return DeviceTask(task, device), DeviceBatches(train_data, device), [to_device(b, device) for b in validation]
