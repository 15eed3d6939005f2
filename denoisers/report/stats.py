"""Statistics and formatting shared by every part of the report.

Aggregation: a metric is first averaged over the frames of a clip (NaN frames, e.g. temporal metrics
during warm-up, skipped), then over the evaluated scenes, with a 95 % Student-t confidence interval
over the per-scene means (undefined with fewer than two scenes).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

CONFIDENCE = 0.95
#: Metrics whose larger value is better (the others are errors or costs).
HIGHER_IS_BETTER = {"psnr": True, "video_psnr": True, "ssim": True, "tpsnr": True, "rmse": False,
                    "relmse": False, "smape": False, "flip": False, "trmae": False, "ms_per_frame": False,
                    "mpix_per_s": True, "peak_memory_mb": False, "psnr_drop": False}
LABELS = {"psnr": "PSNR (dB, frame mean)", "video_psnr": "video PSNR (dB, Isik Eq. 14)", "ssim": "SSIM",
          "rmse": "RMSE", "relmse": "rMSE", "smape": "SMAPE", "flip": "FLIP", "tpsnr": "tPSNR (dB)",
          "trmae": "TRMAE", "ms_per_frame": "ms/frame", "mpix_per_s": "Mpix/s", "peak_memory_mb": "peak MB",
          "psnr_drop": "PSNR drop under spikes (dB)"}
#: Non-inferiority margins ("a is no worse than b"): a - b may be worse by at most this much, in the metric's
#: units. Chosen well below the differences between methods the papers report and below this harness's
#: seed-to-seed spread (about 0.5 dB PSNR): 0.1 dB PSNR (2.3 % in MSE), 0.005 SSIM, 0.01 FLIP and SMAPE (both
#: in [0, 1]; denoised 1-spp frames score about 0.1-0.3 here). A "no worse" on another metric is an error.
NON_INFERIORITY_MARGIN = {"psnr": 0.1, "video_psnr": 0.1, "tpsnr": 0.1, "ssim": 0.005, "flip": 0.01, "smape": 0.01}
#: "Much worse" (Isik et al. C3.2: affinity dimension d = 1): worse by more than this many dB PSNR.
MUCH_WORSE_MARGIN_DB = 0.5
DECIMALS = {"psnr": 2, "video_psnr": 2, "tpsnr": 2, "ssim": 4, "flip": 4, "smape": 4, "trmae": 4, "rmse": 4,
            "relmse": 4, "ms_per_frame": 2, "mpix_per_s": 3, "peak_memory_mb": 1, "psnr_drop": 2}


def mean_ci(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float, float, int]:
    """(mean, low, high, n) of the non-NaN values: Student-t interval mean +- t_{(1+c)/2, n-1} s / sqrt(n),
    s the sample standard deviation; low = high = NaN when n < 2."""
    from scipy import stats

    data = np.asarray(values, dtype=np.float64)
    data = data[~np.isnan(data)]
    n = len(data)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    mean = float(data.mean())
    if n < 2:
        return mean, math.nan, math.nan, n
    half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1) * data.std(ddof=1) / math.sqrt(n))
    return mean, mean - half, mean + half, n


def pooled_psnr(frame_psnr: Sequence[float]) -> float:
    """Video PSNR of Isik et al. 2021 Eq. 14 from per-frame PSNRs (dB, peak 1) of equally sized frames:
    -10 log10 of the MSE pooled over the frames, MSE_t = 10^(-PSNR_t / 10). NaN frames are skipped."""
    values = np.asarray(frame_psnr, dtype=np.float64)
    values = values[~np.isnan(values)]
    if not len(values):
        return math.nan
    mse = float(np.mean(np.power(10.0, -values / 10.0)))
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def fmt(value: Any, metric: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    decimals = DECIMALS.get(metric)
    if metric == "mpix_per_s":
        return f"{value:.3g}"
    return f"{value:.{decimals}f}" if decimals is not None else f"{value:.4g}"


def fmt_ci(mean: float, low: float, high: float, metric: str = "") -> str:
    """'mean ± half-width' (or just the mean when the interval is undefined)."""
    if math.isnan(low) or math.isnan(high):
        return fmt(mean, metric)
    half = (high - low) / 2.0
    if abs(half) <= 1e-9 * max(abs(mean), 1e-30):  # identical scenes: round-off only
        half = 0.0
    return f"{fmt(mean, metric)} ± {fmt(half, metric)}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table; cells are str()-ed and pipes escaped."""
    def cell(value: Any) -> str:
        return str(value).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def frame_to_markdown(table: pd.DataFrame) -> str:
    return markdown_table(list(table.columns), table.astype(object).where(table.notna(), "–").values.tolist())


def with_ci_columns(table: pd.DataFrame, merged: dict[str, tuple[str, str]], before: Sequence[str],
                    after: Sequence[str]) -> pd.DataFrame:
    """Display copy: each {prefix}_mean/_ci_low/_ci_high triple becomes one 'mean ± half-width' column."""
    shown = table[[c for c in before if c in table]].copy()
    for title, (prefix, metric) in merged.items():
        if f"{prefix}_mean" in table:
            shown[title] = [fmt_ci(m, lo, hi, metric) for m, lo, hi in
                            zip(table[f"{prefix}_mean"], table[f"{prefix}_ci_low"], table[f"{prefix}_ci_high"])]
    for column in after:
        if column in table:
            shown[column] = table[column]
    return shown


def formatted(table: pd.DataFrame, metric_columns: dict[str, str]) -> pd.DataFrame:
    """A copy with numeric columns formatted for Markdown (column -> metric whose decimals apply)."""
    shown = table.copy()
    for column, metric in metric_columns.items():
        if column in shown:
            shown[column] = [fmt(float(v), metric) if v is not None else "–" for v in shown[column]]
    return shown
