"""Figures of the Isik et al. 2021 reproduction (denoisers.reproductions.isik2021): Fig. 8, PSNR against
throughput (Mpix/s of the timing job, every row timed with the same threads) for every row and spp, and
Fig. 5, the temporal accumulation weight lambda of the full model beside the reference and its output.

A module of its own (leading underscore: denoisers.reproductions skips it when collecting papers).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from denoisers.evaluate import FRAME_EXR, MAPS_FILE, EvaluationError, denoised_dir, preview_rgb8
from denoisers.report.figures import _grid_frame, placeholder, pyplot, reference_radiance

if TYPE_CHECKING:
    from denoisers.report.collect import Results


def fig8_points(res: Results) -> list[tuple[str, int, float, float]]:
    """(row, spp, Mpix/s, mean frame PSNR over scenes) of every configured row the timing job timed."""
    points = []
    for spec in res.main_specs:
        for spp in res.cfg["evaluation"]["spp"]:
            speed = res.speed(spec.id, spp)
            if speed is None or not res.ran(spec.id, spp):
                continue
            psnr = res.scene_values(spec.id, spp, "psnr")
            if len(psnr):
                points.append((spec.id, int(spp), float(speed["mpix_per_s"]), float(psnr.mean())))
    return points


def plot_fig8(res: Results, path: Path) -> str:
    """Draw Fig. 8 (log throughput on x); '' when drawn, else why not (and a placeholder figure)."""
    points = fig8_points(res)
    if not points:
        reason = "no row has both a timing-job record and scores (rule time_methods)"
        placeholder(path, reason)
        return reason
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    for row in dict.fromkeys(p[0] for p in points):
        mine = sorted((p for p in points if p[0] == row), key=lambda p: p[1])
        ax.plot([p[2] for p in mine], [p[3] for p in mine], marker="o", label=row,
                linewidth=1.5 if row.startswith("afn") else 0.8)
        for _, spp, x, y in mine:
            ax.annotate(f"{spp}", (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel(f"throughput (Mpix/s, {res.timing.threads if res.timing else '?'} threads, timing job)")
    ax.set_ylabel("PSNR (dB, frame mean over scenes)")
    ax.set_title("PSNR against throughput (Isik et al. 2021, Fig. 8 layout); labels: spp", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return ""


def lambda_map(res: Results, row: str, scene: str, spp: int) -> tuple[int, np.ndarray] | None:
    """(grid frame, (H, W) lambda) from a row's maps.npz (denoisers.jobs.denoise), None without one."""
    path = denoised_dir(res.results_dir, row, scene, spp) / MAPS_FILE
    if not res.ran(row, spp) or not path.is_file():
        return None
    with np.load(path) as data:
        if "lambda" not in data:
            return None
        by_frame = dict(zip(data["frames"].tolist(), data["lambda"]))
    frame = _grid_frame(res.cfg, sorted(by_frame))
    return frame, np.asarray(by_frame[frame], dtype=np.float64)


def plot_lambda_maps(res: Results, path: Path, row: str | None, spp: int | None) -> str:
    """Fig. 5 layout: per evaluated scene the reference, the row's output and its lambda map at the grid frame
    (lambda = 0: the warped history is discarded, e.g. at disocclusions); '' when drawn, else why not (row or
    spp None: the full model did not run)."""
    from denoisers.evaluate import read_radiance_exr

    maps = {scene: lambda_map(res, row, scene, spp) for scene in res.scenes} if row and spp else {}
    scenes = [scene for scene, found in maps.items() if found is not None]
    if not scenes:
        reason = (f"no lambda maps of the full AFN model at {spp} spp" if row and spp
                  else "the full AFN model did not run")
        placeholder(path, reason)
        return reason
    plt = pyplot()
    fig, axes = plt.subplots(len(scenes), 3, squeeze=False, figsize=(8.6, 2.7 * len(scenes)))
    image = None
    for r, scene in enumerate(scenes):
        frame, weights = maps[scene]
        panels = [("reference", lambda: reference_radiance(res.results_dir / "renders" / scene, frame)),
                  (f"{row} @ {spp} spp", lambda: read_radiance_exr(
                      denoised_dir(res.results_dir, row, scene, spp) / FRAME_EXR.format(frame)))]
        for c, (title, load) in enumerate(panels):
            ax = axes[r][c]
            try:
                ax.imshow(preview_rgb8(load()), interpolation="nearest")
                ax.set_title(f"{scene}, frame {frame}\n{title}", fontsize=8)
            except (EvaluationError, OSError) as error:
                ax.text(0.5, 0.5, f"{title}: {str(error)[:60]}", ha="center", va="center", fontsize=7)
        image = axes[r][2].imshow(weights, cmap="magma", vmin=0.0, vmax=1.0, interpolation="nearest")
        axes[r][2].set_title(f"lambda (mean {weights.mean():.2f})", fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Temporal accumulation weight lambda (Isik et al. 2021, Fig. 5 layout; 0 = history discarded)",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 0.9, 0.95))
    fig.colorbar(image, ax=axes.ravel().tolist(), fraction=0.03, pad=0.02).ax.tick_params(labelsize=7)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return ""
