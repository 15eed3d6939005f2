"""Arithmetic of a training step: precision (bfloat16 autocast or float32) and the weights' memory layout.

Per model, config ``training.models[].compute`` (schema ``$defs/training_compute``):

* ``precision``: ``auto`` | ``bf16`` | ``fp32``. ``auto`` is ``bf16`` when the CPU has native bfloat16
  arithmetic (flag ``avx512_bf16`` or ``amx_bf16`` in /proc/cpuinfo, and a torch whose oneDNN runs bf16
  convolutions), else ``fp32``. ``bf16`` runs the network's forward pass under
  ``torch.autocast("cpu", torch.bfloat16)``: convolutions and their backward in bf16, everything else
  as autocast decides. The network's outputs are cast back to float32 before the loss, so the loss, the
  gradients of the (float32 master) weights, Adam's state and validation stay float32. ``bf16`` on a CPU
  without native bf16 still runs (oneDNN / torch emulate it) but slower than float32; a warning says so.
* ``channels_last``: ``auto`` | ``true`` | ``false``: weights (and with them every activation, since oneDNN
  follows the weights' layout) in NHWC, which oneDNN's convolution kernels use directly instead of
  reordering NCHW tensors to a blocked layout and back on every call. ``auto`` = with bf16 only: there it
  made the RAE's step 2.4x faster than bf16 in NCHW, while in fp32 it measured 0.91-1.00x of NCHW
  (benchmarks/train_speed.py on an AVX2 machine), so an fp32 run stays the step it was before this
  setting existed.

``benchmarks/train_speed.py`` and rule time_training (``denoisers.training.speed``, the report's "Training step
speed" table) measure both against the float32 NCHW step;
``benchmarks/train_precision_quality.py`` measures what bf16 costs in validation PSNR.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

log = logging.getLogger(__name__)

PRECISIONS: tuple[str, ...] = ("auto", "bf16", "fp32")
#: The config schema's defaults of ``$defs/training_compute`` (tests/test_train_precision.py checks they agree).
DEFAULT_COMPUTE: dict[str, Any] = {"precision": "auto", "channels_last": "auto"}
#: /proc/cpuinfo flags of x86 CPUs with native bfloat16 dot products (AVX-512 BF16, AMX).
BF16_CPU_FLAGS: tuple[str, ...] = ("avx512_bf16", "amx_bf16")
CPUINFO = Path("/proc/cpuinfo")


def cpu_flags(path: Path = CPUINFO) -> frozenset[str]:
    """The ``flags`` of the first CPU in /proc/cpuinfo (empty where there is no such file, e.g. macOS)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return frozenset()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return frozenset(value.split())
    return frozenset()


def torch_has_bf16() -> bool:
    """Whether this torch build's oneDNN runs bf16 convolutions on this CPU."""
    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


def bf16_support() -> tuple[bool, str]:
    """(whether this machine has native bf16 arithmetic for training, why): a bf16 flag of
    :data:`BF16_CPU_FLAGS` and torch's oneDNN bf16 path (which alone also accepts plain AVX-512, emulated)."""
    found = sorted(set(BF16_CPU_FLAGS) & cpu_flags())
    if not found:
        return False, f"CPU has none of {', '.join(BF16_CPU_FLAGS)}"
    if not torch_has_bf16():
        return False, f"CPU has {', '.join(found)} but this torch build has no oneDNN bf16 path"
    return True, f"CPU has {', '.join(found)}"


@dataclass(frozen=True)
class StepPrecision:
    """How a training step computes: ``precision`` 'bf16' or 'fp32' (resolved), ``channels_last``,
    ``configured`` (the setting it was resolved from) and ``reason`` (why, for ``auto``)."""

    precision: str
    channels_last: bool
    configured: str
    reason: str

    @property
    def dtype(self) -> torch.dtype:
        return torch.bfloat16 if self.precision == "bf16" else torch.float32

    def fingerprint(self) -> dict[str, Any]:
        """What changes the trained weights (not how it was chosen)."""
        return {"precision": self.precision, "channels_last": self.channels_last}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def describe(self) -> str:
        """One line: e.g. 'bf16 autocast (fp32 weights, optimizer state and loss), channels-last (auto: CPU has
        avx512_bf16)'."""
        arithmetic = ("bf16 autocast (fp32 weights, optimizer state and loss)" if self.precision == "bf16"
                      else "fp32")
        layout = "channels-last" if self.channels_last else "NCHW"
        return f"{arithmetic}, {layout} (precision: {self.configured}; {self.reason})"


def resolve(precision: str = "auto", channels_last: bool | str = "auto") -> StepPrecision:
    """The step arithmetic of a setting; ValueError naming the allowed values for an unknown one."""
    if precision not in PRECISIONS:
        raise ValueError(f"training precision {precision!r} is not one of {', '.join(PRECISIONS)}")
    if not isinstance(channels_last, bool) and channels_last != "auto":
        raise ValueError(f"training channels_last {channels_last!r} is not one of auto, true, false")
    supported, why = bf16_support()
    if precision == "auto":
        resolved = "bf16" if supported else "fp32"
        reason = f"auto: {why}"
    else:
        resolved = precision
        reason = "set explicitly" + ("" if precision == "fp32" or supported else
                                     f"; {why}, so bf16 is emulated and slower than fp32")
    layout = resolved == "bf16" if channels_last == "auto" else channels_last
    return StepPrecision(resolved, layout, precision, reason)


def resolve_compute(compute: Mapping[str, Any] | None) -> StepPrecision:
    """:func:`resolve` of a model's ``compute`` settings (missing keys: the schema's defaults)."""
    compute = {**DEFAULT_COMPUTE, **(compute or {})}
    unknown = set(compute) - set(DEFAULT_COMPUTE)
    if unknown:
        raise ValueError(f"training compute: unknown keys {sorted(unknown)}; known: {sorted(DEFAULT_COMPUTE)}")
    return resolve(compute["precision"], compute["channels_last"])


def _to_float32(value: Any) -> Any:
    """Floating tensors (nested in tuples, lists, dicts) cast to float32; everything else unchanged."""
    if isinstance(value, torch.Tensor):
        return value.float() if value.is_floating_point() and value.dtype != torch.float32 else value
    if isinstance(value, (tuple, list)):
        return type(value)(_to_float32(item) for item in value)
    if isinstance(value, dict):
        return {key: _to_float32(item) for key, item in value.items()}
    return value


class AutocastForward(nn.Module):
    """``model``'s forward under CPU autocast to ``dtype``, its floating outputs cast back to float32
    (so a loss computed on them runs in float32). Holds ``model``; its parameters are ``model``'s."""

    def __init__(self, model: nn.Module, dtype: torch.dtype = torch.bfloat16) -> None:
        super().__init__()
        self.model, self.dtype = model, dtype

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        with torch.autocast("cpu", dtype=self.dtype):
            out = self.model(*args, **kwargs)
        return _to_float32(out)


def prepare_model(model: nn.Module, step: StepPrecision) -> nn.Module:
    """``model`` with its 4-D weights converted to channels-last when ``step`` asks for it (in place, before
    the optimizer is built, so Adam's state takes the same layout). Weights stay float32."""
    return model.to(memory_format=torch.channels_last) if step.channels_last else model


def loss_model(model: nn.Module, step: StepPrecision) -> nn.Module:
    """What the task's loss calls: ``model`` itself (fp32) or its :class:`AutocastForward` (bf16)."""
    return AutocastForward(model, step.dtype) if step.precision == "bf16" else model


def log_choice(step: StepPrecision, name: str) -> None:
    """The one line saying which arithmetic a training run uses (a warning when bf16 is emulated)."""
    if step.precision == "bf16" and "emulated" in step.reason:
        log.warning("train %s: %s", name, step.describe())
    else:
        log.info("train %s: %s", name, step.describe())
