"""`python -m scenegen compare-renders`: renders that differ only in their render-time metadata agree, a changed
pixel, a changed channel set or a missing frame is named."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from scenegen.cli import main
from scenegen.compare import compare_renders
from scenegen.dataset import write_frame


def frame_channels(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.random((6, 7), dtype=np.float32) for name in ("radiance.R", "radiance.G", "radiance.B")}


def write_render(root: Path, channels: dict[str, np.ndarray], timing_s: float, frames: int = 2) -> Path:
    (root / "noisy" / "chunk_000").mkdir(parents=True, exist_ok=True)
    for frame in range(frames):
        write_frame(root / "noisy" / "chunk_000" / f"frame_{frame:04d}.exr", channels,
                    {"frame": frame, "timing_s": timing_s, "samples_per_s": 1000.0 / timing_s}, half=set())
    return root


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_renders_that_differ_only_in_their_timing_agree(tmp_path: Path, capsys) -> None:
    a = write_render(tmp_path / "a", frame_channels(), timing_s=1.5)
    b = write_render(tmp_path / "b", frame_channels(), timing_s=2.5)
    exr = Path("noisy/chunk_000/frame_0000.exr")
    assert digest(a / exr) != digest(b / exr)       # the header holds the timing: checksums differ
    assert compare_renders(a, b) == []
    assert main(["compare-renders", str(a), str(b)]) == 0
    assert "agree pixel by pixel" in capsys.readouterr().out
    assert compare_renders(a / exr, b / exr) == []


def test_a_changed_pixel_a_channel_and_a_missing_frame_are_named(tmp_path: Path, capsys) -> None:
    a = write_render(tmp_path / "a", frame_channels(), timing_s=1.0)
    changed = frame_channels()
    changed["radiance.G"][3, 4] += 0.25
    b = write_render(tmp_path / "b", changed, timing_s=1.0, frames=1)
    differences = compare_renders(a, b)
    assert [(d.path, d.reason.split(":")[0]) for d in differences] == [
        ("noisy/chunk_000/frame_0001.exr", "only in the first"), ("noisy/chunk_000/frame_0000.exr", "radiance.G")]
    assert "max |difference| 0.25 at 1 pixel(s)" in differences[1].reason
    assert compare_renders(a / "noisy/chunk_000/frame_0000.exr", b / "noisy/chunk_000/frame_0000.exr", atol=0.3) == []
    assert main(["compare-renders", str(a), str(b)]) == 1
    assert "2 EXR file(s) differ" in capsys.readouterr().out
    fewer = frame_channels()
    del fewer["radiance.B"]
    c = write_render(tmp_path / "c", fewer, timing_s=1.0)
    assert "only in the first: ['radiance.B']" in compare_renders(a, c)[0].reason


def test_non_finite_values_compare_by_position(tmp_path: Path) -> None:
    channels = frame_channels()
    channels["radiance.R"][0, 0] = np.nan
    a = write_render(tmp_path / "a", channels, timing_s=1.0, frames=1)
    assert compare_renders(a, write_render(tmp_path / "b", channels, timing_s=2.0, frames=1)) == []
    moved = {name: plane.copy() for name, plane in channels.items()}
    moved["radiance.R"][0, 0], moved["radiance.R"][1, 1] = 0.5, np.nan
    assert "non-finite values differ" in compare_renders(a, write_render(tmp_path / "c", moved, 1.0, 1))[0].reason
    with pytest.raises(FileNotFoundError):
        compare_renders(tmp_path / "empty1", tmp_path / "empty2")
