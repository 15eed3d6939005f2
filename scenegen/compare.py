"""Compare renders by their pixels (``python -m scenegen compare-renders A B``).

Two renders of the same frame never compare equal by checksum: the ``mcdn_meta`` header (and the sidecar JSON)
records the render's ``timing_s`` and ``samples_per_s``. This compares what a denoiser reads instead: the channel
names and every channel's values, file by file."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.exr import read_exr


@dataclass(frozen=True)
class FrameDifference:
    """One EXR (path relative to the compared folders) that differs, and how."""

    path: str
    reason: str


def _exr_files(root: Path) -> dict[str, Path]:
    """{path relative to ``root``: path} of every EXR below ``root`` (or ``root`` itself when it is one)."""
    if root.is_file():
        return {root.name: root}
    return {path.relative_to(root).as_posix(): path for path in sorted(root.rglob("*.exr"))}


def compare_exr(a: Path, b: Path, atol: float = 0.0) -> str | None:
    """Why EXR ``b`` differs from ``a`` by its pixels (channels, shapes, the largest difference per channel,
    non-finite values in different places), or None when every channel agrees within ``atol``."""
    planes_a, _ = read_exr(a)
    planes_b, _ = read_exr(b)
    if sorted(planes_a) != sorted(planes_b):
        only_a, only_b = sorted(set(planes_a) - set(planes_b)), sorted(set(planes_b) - set(planes_a))
        return f"channels differ (only in the first: {only_a}; only in the second: {only_b})"
    reasons = []
    for name in sorted(planes_a):
        x, y = planes_a[name].astype(np.float64), planes_b[name].astype(np.float64)
        if x.shape != y.shape:
            reasons.append(f"{name}: shape {x.shape} against {y.shape}")
            continue
        finite_x, finite_y = np.isfinite(x), np.isfinite(y)
        if not np.array_equal(finite_x, finite_y) or not np.array_equal(x[~finite_x], y[~finite_y], equal_nan=True):
            reasons.append(f"{name}: non-finite values differ")
            continue
        both = finite_x & finite_y
        largest = float(np.max(np.abs(x[both] - y[both]), initial=0.0))
        if largest > atol:
            reasons.append(f"{name}: max |difference| {largest:.6g} at {int(np.sum(np.abs(x - y)[both] > atol))} "
                           "pixel(s)")
    return "; ".join(reasons) or None


def compare_renders(a: Path, b: Path, atol: float = 0.0) -> list[FrameDifference]:
    """Every EXR below folder (or file) ``a`` and ``b`` that differs by its pixels, or exists on one side only;
    metadata (render time, throughput) is ignored. Empty when the renders agree."""
    files_a, files_b = _exr_files(Path(a)), _exr_files(Path(b))
    if not files_a and not files_b:
        raise FileNotFoundError(f"no EXR files below {a} or {b}")
    if Path(a).is_file() and Path(b).is_file():
        files_b = {next(iter(files_a)): Path(b)}
    differences = [FrameDifference(rel, "only in the first") for rel in sorted(set(files_a) - set(files_b))]
    differences += [FrameDifference(rel, "only in the second") for rel in sorted(set(files_b) - set(files_a))]
    for rel in sorted(set(files_a) & set(files_b)):
        reason = compare_exr(files_a[rel], files_b[rel], atol)
        if reason:
            differences.append(FrameDifference(rel, reason))
    return differences
