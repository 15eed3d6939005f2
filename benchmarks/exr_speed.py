"""Speed of the per-sample OpenEXR files (scenegen.exr): write_exr and read_exr of a file of many planes beside a
raw write and read of the same bytes (numpy ``tofile`` / ``fromfile``), timed in the same interleaved rounds.

    python benchmarks/exr_speed.py [--size 128] [--planes 200] [--half-fraction 0.4] [--repeats 9]

The default file is a render chunk's size: 8 samples x 5 buffers x 5 planes at 128 x 128, two planes of every
buffer in HALF (as the render stores the per-sample normals and depth). Independent noise per plane, so the
lossless compression has nothing to find. Items run round-robin (every item once per round, median over rounds),
so a load change on this shared machine hits all of them alike; the ratios to the raw write are the result.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from rae_speed import Item, load_average, time_rounds
from scenegen.exr import read_exr, write_exr


def planes(size: int, count: int, half_fraction: float, seed: int = 0) -> tuple[dict[str, np.ndarray], set[str]]:
    """``count`` float32 planes (size, size) of independent noise, and the names of the first ``half_fraction``
    of them, written as HALF."""
    rng = np.random.default_rng(seed)
    channels = {f"s{i // 25:02d}.buf{(i // 5) % 5}.{'XYZRG'[i % 5]}": rng.uniform(0, 1, (size, size)).astype(np.float32)
                for i in range(count)}
    half = set(list(channels)[:int(round(half_fraction * count))])
    return channels, half


def build_items(folder: Path, channels: dict[str, np.ndarray], half: set[str]) -> list[Item]:
    """The four timed calls; the raw file holds the same bytes the EXR stores uncompressed (HALF planes as float16)."""
    exr, raw = folder / "chunk.exr", folder / "chunk.raw"
    stored = np.concatenate([(plane.astype(np.float16) if name in half else plane).view(np.uint8).ravel()
                             for name, plane in channels.items()])
    size = next(iter(channels.values())).shape[0]
    write_exr(exr, channels, half=half)
    stored.tofile(raw)
    return [Item("raw write (tofile)", size, None, lambda _: stored.tofile(raw)),
            Item("write_exr", size, None, lambda _: write_exr(exr, channels, half=half)),
            Item("raw read (fromfile)", size, None, lambda _: np.fromfile(raw, dtype=np.uint8)),
            Item("read_exr", size, None, lambda _: read_exr(exr))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--planes", type=int, default=200)
    parser.add_argument("--half-fraction", type=float, default=0.4)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=1)
    args = parser.parse_args()
    channels, half = planes(args.size, args.planes, args.half_fraction)
    print(f"{args.planes} planes of {args.size}x{args.size} ({len(half)} HALF); median of {args.repeats} "
          f"interleaved rounds after {args.warmup}; load average {load_average()}")
    with tempfile.TemporaryDirectory() as folder:
        items = build_items(Path(folder), channels, half)
        medians = dict(zip((item.label for item in items), time_rounds(items, args.repeats, args.warmup)))
        mib = (Path(folder) / "chunk.exr").stat().st_size / 2**20
    for label, seconds in medians.items():
        print(f"  {label:22s} {seconds * 1e3:8.1f} ms")
    print(f"  write_exr = {medians['write_exr'] / medians['raw write (tofile)']:.1f}x the raw write, read_exr = "
          f"{medians['read_exr'] / medians['raw read (fromfile)']:.1f}x the raw read ({mib:.1f} MiB file); load "
          f"average {load_average()} at the end")


if __name__ == "__main__":
    main()
