"""Where torch and Mitsuba compute: config ``compute.device`` (``auto`` | ``cpu`` | ``cuda``).

* ``cpu``: torch on the CPU, Mitsuba's ``render.variant`` (``llvm_ad_rgb``), OIDN's CPU device. Today's results.
* ``cuda``: torch training and inference on ``cuda:0``, Mitsuba's ``cuda_ad_rgb`` (a configured ``llvm_ad_rgb``
  becomes ``cuda_ad_rgb``; ``scalar_rgb`` stays scalar), OIDN's CUDA device where pyoidn has one. A machine where
  CUDA does not work is an error naming the reason, never a silent fall-back.
* ``auto``: ``cuda`` when an NVIDIA driver is present and a torch CUDA tensor operation works, else ``cpu``.

The workflow resolves ``auto`` once, on the machine that plans the DAG, and writes the concrete device into the
resolved config every job reads (:func:`resolve_config_device`), so a plan and its jobs never disagree. On a
cluster whose login node has no GPU, set ``cuda`` explicitly.

What a device changes, and so keys: render digests include the variant (``cuda_ad_rgb`` renders are statistically
equal to ``llvm_ad_rgb`` ones, not bit-identical), and a model trained on CUDA is a different store key from the
CPU one (:func:`key_device`: absent for the CPU, so every CPU key is what it was before the setting existed).
"""
from __future__ import annotations

import dataclasses
import functools
import os
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")
#: The Mitsuba variant each CPU variant becomes on CUDA.
CUDA_VARIANTS: dict[str, str] = {"llvm_ad_rgb": "cuda_ad_rgb"}
#: Files whose presence shows an NVIDIA kernel driver (checked before torch is imported, which is slow).
NVIDIA_DRIVER_FILES: tuple[str, ...] = ("/proc/driver/nvidia/version", "/dev/nvidiactl")


class DeviceError(RuntimeError):
    """``compute.device`` asks for a device this machine cannot use."""


def _driver_present() -> bool:
    return any(Path(path).exists() for path in NVIDIA_DRIVER_FILES)


@functools.lru_cache(maxsize=1)
def cuda_status() -> tuple[bool, str]:
    """(whether torch can compute on CUDA here, why): a driver, a CUDA build of torch, and one tensor operation."""
    if not _driver_present():
        return False, "no NVIDIA driver (" + ", ".join(NVIDIA_DRIVER_FILES) + " absent)"
    import torch

    if not torch.cuda.is_available():
        return False, f"torch {torch.__version__} sees no CUDA device (CPU build or driver mismatch)"
    try:
        value = float((torch.ones(4, device="cuda") * 2).sum())
    except Exception as error:  # noqa: BLE001 -- any failure of the first kernel means CUDA does not work
        return False, f"a CUDA tensor operation failed: {type(error).__name__}: {error}"
    if value != 8.0:
        return False, f"a CUDA tensor operation returned {value} instead of 8"
    return True, f"CUDA works: {torch.cuda.get_device_name(0)}"


def resolve_device(setting: str, verify: bool = False) -> str:
    """``cpu`` or ``cuda`` for a ``compute.device`` setting (ValueError for an unknown one). ``auto`` probes this
    machine. An explicit ``cuda`` is taken as it is (a cluster's login node plans GPU jobs without a GPU) unless
    ``verify``, where it raises DeviceError when CUDA does not work here."""
    if setting not in DEVICES:
        raise ValueError(f"compute.device {setting!r} is not one of {', '.join(DEVICES)}")
    if setting == "cpu" or (setting == "cuda" and not verify):
        return setting
    works, why = cuda_status()
    if setting == "cuda" and not works:
        raise DeviceError(f"compute.device is cuda, but CUDA cannot be used on this machine: {why}; "
                          "set compute.device to cpu or auto")
    return "cuda" if works else "cpu"


def configured_device(cfg: Mapping[str, Any]) -> str:
    """The resolved device (``cpu`` / ``cuda``) of a config (``compute.device``, default ``auto``)."""
    return resolve_device(str((cfg.get("compute") or {}).get("device", "auto")))


def torch_device(cfg: Mapping[str, Any]) -> Any:
    """``torch.device`` of a config: ``cpu`` or ``cuda:0`` (DeviceError when CUDA is configured and does not
    work on this machine)."""
    import torch

    setting = str((cfg.get("compute") or {}).get("device", "auto"))
    return torch.device("cuda", 0) if resolve_device(setting, verify=True) == "cuda" else torch.device("cpu")


def render_variant(variant: str, device: str) -> str:
    """The Mitsuba variant a configured ``render.variant`` runs as on a resolved ``device``."""
    if device == "cuda":
        return CUDA_VARIANTS.get(variant, variant)
    if variant.startswith("cuda"):
        raise DeviceError(f"render.variant {variant!r} needs compute.device cuda (the device resolved to {device})")
    return variant


def resolve_config_device(cfg: dict[str, Any]) -> dict[str, Any]:
    """In place: ``compute.device`` resolved to ``cpu`` / ``cuda`` and ``render.variant`` to the variant it runs
    as there (a CPU config is unchanged apart from ``auto`` -> ``cpu``). Returns ``cfg``."""
    compute = cfg.setdefault("compute", {})
    device = resolve_device(str(compute.get("device", "auto")))
    compute["device"] = device
    if isinstance(cfg.get("render"), dict) and "variant" in cfg["render"]:
        cfg["render"]["variant"] = render_variant(cfg["render"]["variant"], device)
    return cfg


def key_device(cfg: Mapping[str, Any]) -> dict[str, str]:
    """What a model's store key and work directory add for the device: nothing on the CPU (keys made before the
    setting stay valid), ``{"device": "cuda"}`` on CUDA."""
    device = configured_device(cfg)
    return {} if device == "cpu" else {"device": device}


def to_device(value: Any, device: Any) -> Any:
    """``value`` with every tensor moved to ``device``: tensors in dicts, lists, tuples and dataclass fields
    (a dataclass is rebuilt with ``dataclasses.replace``); anything else is returned as it is."""
    import torch

    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return type(value)((key, to_device(item, device)) for key, item in value.items())
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        return type(value)(to_device(item, device) for item in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{f.name: to_device(getattr(value, f.name), device)
                                             for f in dataclasses.fields(value) if f.init})
    return value


def default_device(device: Any) -> Any:
    """A context in which torch's tensor factories (``torch.zeros``, ``arange``, ...) without a ``device``
    argument allocate on ``device``: how the jobs run code written for the CPU on CUDA without editing it (its
    source keys stored models). Nothing changes on the CPU. ``torch.from_numpy`` stays on the CPU."""
    import contextlib

    import torch

    device = torch.device(device)
    return contextlib.nullcontext() if device.type == "cpu" else device


def synchronize(device: Any) -> None:
    """Wait for ``device``'s queued kernels (so a wall-clock timer measures them); nothing on the CPU."""
    import torch

    if getattr(device, "type", str(device)).startswith("cuda"):
        torch.cuda.synchronize(device)


def _nvidia_smi(query: str) -> str | None:
    try:
        out = subprocess.run(["nvidia-smi", f"--query-gpu={query}", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=20, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return out.strip().splitlines()[0].strip() if out.strip() else None


@functools.lru_cache(maxsize=2)
def device_info(device: str) -> dict[str, Any]:
    """What provenance and timings record about a resolved device: its kind and model; for CUDA also the
    driver, torch's CUDA runtime and the GPU's memory (MiB)."""
    if device != "cuda":
        from denoisers.provenance import cpu_model

        return {"device": "cpu", "model": cpu_model(), "cores": os.cpu_count()}
    import torch

    properties = torch.cuda.get_device_properties(0)
    return {"device": "cuda", "model": properties.name, "driver": _nvidia_smi("driver_version"),
            "cuda_runtime": torch.version.cuda, "memory_mib": int(properties.total_memory // 2**20),
            "multiprocessors": int(properties.multi_processor_count)}
