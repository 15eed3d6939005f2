"""Summarise a finished workflow run from Snakemake's ``benchmark:`` files and the render sidecars.

Prints, per rule, the number of jobs, total and longest wall time, and the peak resident memory
(max_rss, MB) of any job; then the rendering throughput recorded in the frame sidecars and the size
of the dataset on disk. Usage: python benchmarks/run_summary.py [results]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd


def benchmark_jobs(results: Path) -> pd.DataFrame:
    """One row per job with a Snakemake ``benchmark:`` file under ``results``/benchmarks: ``rule`` (the
    file's top folder, or its name for one-job rules), ``seconds`` (wall) and ``max_rss_mb``."""
    rows = []
    for tsv in sorted((results / "benchmarks").rglob("*.tsv")):
        parts = tsv.relative_to(results / "benchmarks").parts
        rule = parts[0] if len(parts) > 1 else tsv.stem  # one-job rules write benchmarks/<rule>.tsv
        table = pd.read_csv(tsv, sep="\t")
        rows.append({"rule": rule, "seconds": float(table["s"].iloc[-1]),
                     "max_rss_mb": float(pd.to_numeric(table["max_rss"], errors="coerce").iloc[-1])})
    return pd.DataFrame(rows, columns=["rule", "seconds", "max_rss_mb"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="?", type=Path, default=Path("results"),
                        help="the run's output directory (default: results)")
    results = parser.parse_args().results
    jobs = benchmark_jobs(results)
    if jobs.empty:
        sys.exit(f"no benchmark files under {results / 'benchmarks'}")
    summary = jobs.groupby("rule").agg(jobs=("seconds", "size"), total_s=("seconds", "sum"),
                                       longest_s=("seconds", "max"), peak_rss_mb=("max_rss_mb", "max"))
    print(summary.to_string(float_format=lambda v: f"{v:.1f}"))
    render_rules = [r for r in summary.index if r.startswith("render_")]
    print(f"\nrendering wall time (sum over render jobs): {summary.loc[render_rules, 'total_s'].sum() / 60:.1f} min")
    print(f"all jobs (sum): {summary['total_s'].sum() / 60:.1f} min; peak RSS of any job: "
          f"{summary['peak_rss_mb'].max():.0f} MB")

    for kind in ("noisy", "reference"):
        rates = [json.loads(p.read_text())["samples_per_s"]
                 for p in (results / "renders").glob(f"*/{kind}/chunk_*/frame_*.json")]
        if rates:
            print(f"{kind}: {len(rates)} frames, median {pd.Series(rates).median() / 1e6:.2f} M samples/s")
    renders = results / "renders"
    if renders.exists():
        size = sum(p.stat().st_size for p in renders.rglob("*") if p.is_file())
        print(f"dataset on disk (results/renders): {size / 1e9:.2f} GB")


if __name__ == "__main__":
    main()
