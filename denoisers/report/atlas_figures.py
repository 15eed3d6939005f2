"""Figures of the failure atlas (denoisers.report.atlas): per-frame error curves with the event marked, an
image strip at the worst frame with crops on the mask, and quality versus speed per scenario family. Missing
inputs give a placeholder figure naming what is missing, never an error."""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from denoisers.report.figures import placeholder, pyplot, row_styles

if TYPE_CHECKING:
    import pandas as pd


def plot_family(scores: pd.DataFrame, scenarios: Sequence[str], rows: Sequence[str], path: Path, title: str) -> None:
    """Masked PSNR (mean over the family's scenarios) against ms/frame (mean of the stability denoise jobs, log x),
    one point per row and spp."""
    data = scores[scores.scenario.isin(list(scenarios))] if len(scores) else scores
    if not len(data):
        placeholder(path, f"{title}: no scores")
        return
    plt = pyplot()
    styles = row_styles(rows)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for (row, spp), group in data.groupby(["method_id", "spp"], sort=False):
        x, y = float(np.nanmean(group["ms_per_frame"])), float(np.nanmean(group["masked_psnr"]))
        if not (math.isfinite(y) and math.isfinite(x) and x > 0):
            continue
        style = styles.get(row, {})
        ax.scatter([x], [y], color=style.get("color"), marker=style.get("marker", "o"), label=f"{row} ({spp} spp)")
        ax.annotate(row, (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("ms/frame (stability denoise jobs, median per frame; log scale)")
    ax.set_ylabel("masked PSNR (dB, mean over the family's scenarios)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _score_frames(results_dir: Path, row: str, scene: str, spp: int):
    import pandas as pd

    from denoisers.jobs.stability import scores_csv

    path = scores_csv(results_dir, row, scene, spp)
    return pd.read_csv(path) if path.is_file() else None


def plot_curves(scores: pd.DataFrame, results_dir: Path, scene: str, rows: Sequence[str], path: Path) -> None:
    """PSNR of the lag region per frame (-10 log10 lag_mse) of every row and spp, the event frame marked."""
    runs = scores[scores.scene == scene] if len(scores) else scores
    if not len(runs):
        placeholder(path, f"{scene}: not run")
        return
    plt = pyplot()
    styles = row_styles(rows)
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for run in runs.itertuples():
        frames = _score_frames(results_dir, run.method_id, scene, int(run.spp))
        if frames is None:
            continue
        with np.errstate(divide="ignore"):
            psnr = -10.0 * np.log10(frames["lag_mse"].to_numpy(np.float64))
        style = styles.get(run.method_id, {"marker": "o"})
        ax.plot(frames["frame"], psnr, markersize=3, **style, label=f"{run.method_id} ({run.spp} spp)")
    event = runs["event_frame"].dropna()
    if len(event):
        ax.axvline(float(event.iloc[0]), color="k", linestyle="--", linewidth=1, label="event")
    ax.set_xlabel("frame")
    ax.set_ylabel("PSNR in the lag region (dB)")
    ax.set_title(f"{scene}: per-frame error, focus {runs['focus'].iloc[0]}", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _mask_window(mask: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left (y, x) of a size x size window centred on the mask's centroid (image centre when empty)."""
    height, width = mask.shape
    ys, xs = np.nonzero(mask)
    cy, cx = (ys.mean(), xs.mean()) if ys.size else (height / 2, width / 2)
    return (int(np.clip(round(cy - size / 2), 0, height - size)), int(np.clip(round(cx - size / 2), 0, width - size)))


def plot_strip(cfg: dict, scores: pd.DataFrame, results_dir: Path, scene: str, rows: Sequence[str],
               path: Path) -> None:
    """Every row (first spp) and the reference at the worst frame (largest mean lag-region error over the rows):
    full frame with the mask outlined, and a crop centred on the mask, enlarged."""
    from denoisers.evaluate import preview_rgb8, read_frame_files, read_radiance_exr
    from denoisers.jobs.stability import load_masks, scenario_denoised_dir
    from denoisers.stability_metrics import focus_mask
    from scenegen.dataset import find_frames, load_reference_frame

    runs = scores[scores.scene == scene] if len(scores) else scores
    if not len(runs):
        placeholder(path, f"{scene}: not run")
        return
    spp = int(runs["spp"].min())
    runs = runs[runs.spp == spp]
    curves = [frames["lag_mse"].to_numpy(np.float64) for row in runs["method_id"]
              if (frames := _score_frames(results_dir, row, scene, spp)) is not None]
    references = find_frames(Path(results_dir) / "renders" / scene / "reference")
    if not curves or not references:
        placeholder(path, f"{scene}: scores or reference missing")
        return
    order = sorted(references)
    worst = order[int(np.nanargmax(np.nanmean(np.stack(curves), axis=0)))]
    masks, events = load_masks(Path(results_dir) / "stability" / scene, order)
    shape = masks["subject"].shape
    mask = focus_mask(masks, events["focus"], shape)[order.index(worst)]
    reference = load_reference_frame(references[worst], ["radiance"])[0]["radiance"]
    panels = []
    for row in runs["method_id"]:
        found = read_frame_files(scenario_denoised_dir(results_dir, row, scene, spp))
        if worst in found:
            panels.append((row, read_radiance_exr(found[worst])))
    panels.append(("reference", reference))
    size = max(8, min(shape[1:]) // 2)
    y, x = _mask_window(mask, size)
    plt = pyplot()
    fig, axes = plt.subplots(2, len(panels), figsize=(1.7 * len(panels), 3.8), squeeze=False)
    for col, (label, image) in enumerate(panels):
        rgb = preview_rgb8(image)
        axes[0][col].imshow(rgb, interpolation="nearest")
        if mask.any() and not mask.all():
            axes[0][col].contour(mask.astype(float), levels=[0.5], colors="red", linewidths=0.6)
        axes[0][col].set_title(label, fontsize=8)
        axes[1][col].imshow(rgb[y:y + size, x:x + size], interpolation="nearest")
        for row_axes in axes:
            row_axes[col].set_xticks([])
            row_axes[col].set_yticks([])
    axes[0][0].set_ylabel("full (mask: red)", fontsize=7)
    axes[1][0].set_ylabel("crop on the mask", fontsize=7)
    fig.suptitle(f"{scene} at frame {worst} (worst mean lag-region error), {spp} spp", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
