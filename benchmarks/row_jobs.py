"""What one job per row saves: a row's clips denoised and scored as one process per clip (the workflow's jobs before
the row rules) against one `denoise-row` and one `evaluate-row` process, interleaved, on the same machine.

Both sides run the command line the rules run, on the renders of a finished run; the Snakemake scheduling of each
job (about 0.5-1 s locally, 20-25 s on SLURM) comes on top of the per-clip side and is not counted. Prints the wall
seconds of each side per round, their medians and the ratio; the outputs of both sides are compared (frames and
metrics identical).

Usage: python benchmarks/row_jobs.py --config results/smoke/.config/<digest>.yaml --results results/smoke
           --row rae [--rounds 3] [--kind evaluation]
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd


def _run(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
    return time.perf_counter() - start


def per_clip(config: Path, results: Path, row: str, clips: list[tuple[str, int]], out: Path) -> float:
    """Seconds of one `denoise` and one `evaluate` process per clip."""
    seconds = 0.0
    for scene, spp in clips:
        clip = out / "denoised" / scene / f"spp{spp}"
        seconds += _run([sys.executable, "-m", "denoisers", "denoise", "--config", str(config), "--method-id", row,
                         "--scene", scene, "--spp", str(spp), "--render-dir", str(results / "renders" / scene),
                         "--results", str(results), "--out", str(clip)])
        seconds += _run([sys.executable, "-m", "denoisers", "evaluate", "--config", str(config), "--denoised",
                         str(clip), "--render-dir", str(results / "renders" / scene), "--out",
                         str(out / "metrics" / scene / f"spp{spp}.csv")])
    return seconds


def per_row(config: Path, results: Path, row: str, kind: str, out: Path) -> float:
    """Seconds of one `denoise-row` and one `evaluate-row` process."""
    return (_run([sys.executable, "-m", "denoisers", "denoise-row", "--kind", kind, "--config", str(config),
                  "--method-id", row, "--render-root", str(results / "renders"), "--results", str(results),
                  "--out", str(out / "denoised")])
            + _run([sys.executable, "-m", "denoisers", "evaluate-row", "--config", str(config), "--denoised",
                    str(out / "denoised"), "--render-root", str(results / "renders"), "--out", str(out / "metrics")]))


def same_outputs(a: Path, b: Path, clips: list[tuple[str, int]]) -> bool:
    from denoisers.evaluate import read_radiance_exr

    for scene, spp in clips:
        frames = sorted((a / "denoised" / scene / f"spp{spp}").glob("frame_*.exr"))
        if not frames or not all(np.array_equal(read_radiance_exr(f), read_radiance_exr(b / "denoised" / scene /
                                                                                          f"spp{spp}" / f.name))
                                 for f in frames):
            return False
        if not pd.read_csv(a / "metrics" / scene / f"spp{spp}.csv").equals(
                pd.read_csv(b / "metrics" / scene / f"spp{spp}.csv")):
            return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, required=True, help="a finished run's resolved config")
    parser.add_argument("--results", type=Path, required=True, help="its experiment folder (renders, models)")
    parser.add_argument("--row", required=True)
    parser.add_argument("--kind", default="evaluation", choices=("evaluation", "stability", "volumes"))
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()

    from denoisers.cli import load_evaluation_config
    from denoisers.jobs.rows import row_clips

    clips = row_clips(load_evaluation_config(args.config), args.row, args.kind)
    clip_s, row_s = [], []
    with tempfile.TemporaryDirectory() as scratch:
        for round_ in range(args.rounds):
            a, b = Path(scratch) / f"clips{round_}", Path(scratch) / f"row{round_}"
            first, second = (per_clip, per_row) if round_ % 2 == 0 else (per_row, per_clip)
            for side in (first, second):
                if side is per_clip:
                    clip_s.append(per_clip(args.config, args.results, args.row, clips, a))
                else:
                    row_s.append(per_row(args.config, args.results, args.row, args.kind, b))
            if not same_outputs(a, b, clips):
                sys.exit(f"round {round_}: the two sides wrote different frames or metrics")
    print(f"row {args.row}: {len(clips)} clips, {args.rounds} interleaved rounds (denoise + evaluate)")
    print(f"  one process per clip: {', '.join(f'{s:.1f}' for s in clip_s)} s (median {statistics.median(clip_s):.1f})")
    print(f"  one process per row:  {', '.join(f'{s:.1f}' for s in row_s)} s (median {statistics.median(row_s):.1f})")
    print(f"  ratio per clip / per row: {statistics.median(clip_s) / statistics.median(row_s):.2f}x "
          "(Snakemake's per-job scheduling not counted)")


if __name__ == "__main__":
    main()
