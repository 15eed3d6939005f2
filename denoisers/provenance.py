"""Where a result came from: code version, package versions, machine and thread settings, date.

Recorded in every trained model's summary.json and stated in REPORT.md, so that two numbers can be
compared only when they were produced under known, comparable conditions.
"""
from __future__ import annotations

import datetime
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Distributions whose versions decide rendering, training and denoising results.
PACKAGES: tuple[str, ...] = ("mitsuba", "drjit", "torch", "pyoidn", "snakemake", "numpy", "flip-evaluator")


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=20,
                              check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_state() -> dict[str, Any]:
    """{'commit': sha or None, 'dirty': bool or None} of the checkout this code runs from."""
    commit = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, platform.processor() elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


#: CPU flags recorded with a trained model: the instruction sets oneDNN chooses its kernels by (two machines with
#: the same flags and threads give bit-identical training steps; others differ in the last bits).
ISA_FLAGS = frozenset({"sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_vnni",
                       "avx512_bf16", "amx_bf16", "amx_tile", "asimd", "sve"})


def cpu_isa() -> list[str]:
    """The :data:`ISA_FLAGS` this CPU has (sorted; empty where /proc/cpuinfo is missing)."""
    flags: set[str] = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    return sorted(flags & ISA_FLAGS)


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def provenance(threads: dict[str, int] | None = None, device: dict[str, Any] | None = None) -> dict[str, Any]:
    """Everything above as one JSON-serialisable dict; ``threads`` names the thread settings in force, ``device``
    what torch and Mitsuba computed on (:func:`denoisers.device.device_info` of config ``compute.device``: the
    GPU's model, driver and CUDA runtime on CUDA)."""
    record = {**git_state(), "packages": package_versions(), "python": platform.python_version(),
              "cpu_model": cpu_model(), "cpu_isa": cpu_isa(), "cpu_count": os.cpu_count(),
              "threads": dict(threads or {}),
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if device is not None:
        record["device"] = dict(device)
    return record


def describe(record: dict[str, Any]) -> list[str]:
    """Markdown bullet lines of a provenance record."""
    commit = record.get("commit")
    dirty = record.get("dirty")
    code = (f"`{commit[:12]}`" + (" with uncommitted changes" if dirty else " (clean tree)" if dirty is False else "")
            if commit else "not a git checkout")
    packages = ", ".join(f"{name} {version or 'not installed'}" for name, version in record["packages"].items())
    threads = ", ".join(f"{key} {value}" for key, value in record.get("threads", {}).items()) or "–"
    device = record.get("device") or {}
    computes = (f"; torch and Mitsuba on {device['model']} (CUDA, driver {device.get('driver') or 'unknown'})"
                if device.get("device") == "cuda" else "; torch and Mitsuba on the CPU" if device else "")
    return [f"- Code: {code}; Python {record['python']}; {packages}.",
            f"- Machine: {record['cpu_model']}, {record['cpu_count']} logical cores; threads: {threads}{computes}.",
            f"- Generated {record['date']}."]
