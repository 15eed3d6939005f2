"""REPORT.md's first section: the rows whose method belongs to no paper and is not one the harness ships (a
user's own denoiser) against the shipped baselines -- the same metrics, paired differences over the evaluated
scenes, the equal-time view and the failure-atlas lines, so a new method is judged without reading the papers'
sections."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from denoisers.report.verdicts import Part
from denoisers.report.collect import Results
from denoisers.report.stats import fmt, fmt_ci, markdown_table, mean_ci
from denoisers.report.tables import equal_time_table, speed_text

#: Every method the harness registers itself (tests/test_report_own_rows.py keeps it equal to the registry).
HARNESS_METHODS: tuple[str, ...] = (
    "afn", "dasr", "eaw", "kpcn", "noisy", "ntasd", "ntasd_direct", "ntasd_kpn", "ntasd_uniform", "oidn",
    "oidn_albedo", "oidn_color", "path_tracing", "rae", "rae_color", "rae_samples", "rls", "svgf", "svgf_volume",
    "uniform_adaptive", "variance_adaptive", "wrls")
#: What a new method is compared with, where the config has rows of them: the input and the shipped baselines.
BASELINE_METHODS: tuple[str, ...] = ("noisy", "eaw", "svgf", "rls", "wrls", "oidn")
SHOWN_METRICS: tuple[str, ...] = ("psnr", "ssim", "flip", "trmae")


def own_rows(res: Results) -> list[str]:
    """Configured rows (table order) whose registry method the harness does not ship."""
    return [spec.id for spec in res.main_specs if spec.method not in HARNESS_METHODS]


def baseline_rows(res: Results) -> list[str]:
    """Configured rows of :data:`BASELINE_METHODS` (table order)."""
    return [spec.id for spec in res.main_specs if spec.method in BASELINE_METHODS]


def paired_difference(res: Results, row: str, baseline: str, spp: int, metric: str = "psnr"
                      ) -> tuple[float, float, float, int]:
    """(mean, low, high, n) of row - baseline per evaluated scene (both ran there), Student-t 95 % interval: the
    claims' paired comparison (:meth:`Part.paired`)."""
    part = Part.paired(res.scene_values(row, spp, metric), res.scene_values(baseline, spp, metric), metric, row,
                       baseline)
    return (*part.interval, part.n)


def _metrics_table(res: Results, rows: list[str], spps: list[int]) -> str:
    header = ["row", "spp", *(name.upper() for name in SHOWN_METRICS), "ms/frame [min, max]"]
    lines = []
    for row in rows:
        for spp in spps:
            if not res.ran(row, spp):
                continue
            cells = [fmt_ci(*mean_ci(res.scene_values(row, spp, m).to_numpy(np.float64))[:3], m)
                     for m in SHOWN_METRICS]
            lines.append([row, spp, *cells, speed_text(res, row, spp)])
    return markdown_table(header, lines)


def _differences_table(res: Results, rows: list[str], baselines: list[str], spps: list[int]) -> str:
    header = ["row", "spp", *(f"− {baseline}" for baseline in baselines)]
    lines = []
    for row in rows:
        for spp in spps:
            if not res.ran(row, spp):
                continue
            cells = []
            for baseline in baselines:
                if not res.ran(baseline, spp):
                    cells.append("not run")
                    continue
                mean, low, high, n = paired_difference(res, row, baseline, spp)
                side = "" if np.isnan(low) else (" (better)" if low > 0 else " (worse)" if high < 0 else " (tie)")
                cells.append(f"{fmt(mean, 'psnr')} [{fmt(low, 'psnr')}, {fmt(high, 'psnr')}] n={n}{side}")
            lines.append([row, spp, *cells])
    return markdown_table(header, lines)


def _atlas_lines(results_dir: Path, rows: list[str]) -> list[str]:
    """The failure atlas's sentence of each row (stability/tables/atlas.md), if the atlas was built."""
    table = Path(results_dir) / "stability" / "tables" / "atlas.md"
    if not table.is_file():
        return ["The failure atlas was not built (stability.enabled false), so there are no atlas lines."]
    sentences = [line for line in table.read_text().splitlines()
                 if any(line.startswith(f"- **{row}**") for row in rows)]
    return sentences or ["The failure atlas has no line for these rows (stability.rows leaves them out)."]


def _equal_time_lines(res: Results, rows: list[str]) -> list[str]:
    table = equal_time_table(res)
    if not len(table) or not table["method_id"].isin(rows).any():
        return ["Equal time: the timing job did not time these rows.", ""]
    mine = table[table["method_id"].isin(rows)]
    shown = [[r.method_id, r.spp, fmt(r.denoise_ms_per_frame, "ms_per_frame"), fmt(r.equal_time_spp),
              r.path_tracing_row or "–", fmt(r.psnr_diff_mean, "psnr"), r.better] for r in mine.itertuples()]
    return ["Equal time (as in the [equal-time view](#equal-time-view)): plain path tracing at the spp it reaches in "
            "the time of rendering plus denoising.", "",
            markdown_table(["row", "spp", "ms/frame", "equal-time spp", "path-tracing row", "PSNR − path tracing",
                            "better"], shown), ""]


def own_rows_section(res: Results) -> list[str]:
    """Markdown lines of the section; none when every configured row is one the harness ships."""
    rows = own_rows(res)
    if not rows:
        return []
    spps = list(res.cfg["evaluation"]["spp"])
    baselines = [row for row in baseline_rows(res) if row not in rows]
    lines = ["## Your methods against the baselines", "",
             f"Rows whose method the harness does not ship: {', '.join(rows)}. Means with 95 % intervals over the "
             f"{len(res.scenes)} evaluated scenes (frame metrics averaged per clip); ms/frame from the timing job.", "",
             _metrics_table(res, rows, spps), "",
             "PSNR difference to each baseline (dB), paired over the scenes both ran, 95 % t-interval; better / "
             "worse when the interval lies wholly on one side:", "",
             _differences_table(res, rows, baselines, spps), ""]
    lines += _equal_time_lines(res, rows)
    lines += ["Failure atlas:", "", *_atlas_lines(res.results_dir, rows), ""]
    return lines
