"""The generated report: tables, figures, the claims table and REPORT.md (rule build_report).

Everything is computed from the evaluation outputs and the trained models; nothing is typed in.

* ``collect``  -- reading the results (per-frame metrics, timings, robustness, trained models)
* ``stats``    -- confidence intervals, Isik's pooled video PSNR, formatting
* ``tables``   -- cross-paper tables (summary, timing, equal time, noise floor, robustness, split, training)
* ``figures``  -- quality vs speed, per-frame curves, image grids, training curves
* ``claims``   -- paired comparisons over scenes and the four verdicts
* ``capacity`` -- capacity ablations: size sweep table and chart, the smallest size within 0.2 dB of the best
* ``writer``   -- REPORT.md and ``build_report``
* ``outputs``  -- the list of written files (parse time)

Each paper's tables, figures and claims live in ``denoisers.reproductions`` (one module per paper).
"""
from __future__ import annotations

from pathlib import Path


def report_outputs(cfg: dict, root: str = "results") -> dict[str, list[str]]:
    """Files the report writes (see denoisers.report.outputs); light enough for Snakefile parsing."""
    from denoisers.report.outputs import report_outputs as outputs

    return outputs(cfg, root)


def build_report(cfg: dict, results_dir: Path | None = None, out_dir: Path | None = None) -> list[Path]:
    """Compute every table, figure and REPORT.md (see denoisers.report.writer.build_report)."""
    from denoisers.report.writer import build_report as build

    return build(cfg, results_dir, out_dir)
