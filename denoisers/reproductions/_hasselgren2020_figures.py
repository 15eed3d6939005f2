"""Figures of the Hasselgren et al. 2020 reproduction (denoisers.reproductions.hasselgren2020): the Fig. 7
per-frame PSNR / tPSNR curves and the Fig. 6 sample-map heatmaps.

A module of its own (leading underscore: denoisers.reproductions skips it when collecting papers). Matplotlib
is imported inside the functions (Agg backend, denoisers.report.figures.pyplot).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from denoisers.evaluate import EvaluationError, preview_rgb8
from denoisers.report.figures import _grid_frame, placeholder, pyplot, reference_radiance, sample_maps_of

if TYPE_CHECKING:
    from collections.abc import Sequence

    from denoisers.report.collect import Results

#: Fig. 7 panels: (per-frame column, axis label).
FIG7_PANELS = (("psnr", "PSNR (dB)"), ("tpsnr", "tPSNR (dB)"))


def fig7_scene(res: Results) -> str | None:
    """The scene of the Fig. 7 curves: the first evaluated test scene (else the first evaluated scene)."""
    return next((s for s in res.scenes if s.startswith("test_")), res.scenes[0] if res.scenes else None)


def plot_fig7(res: Results, path: Path, rows: Sequence[tuple[str, str | None]], spp: int) -> str | None:
    """Per-frame PSNR and tPSNR of the Fig. 7 ``rows`` (label, row id) at ``spp`` on one scene (camera cuts
    dotted); returns the scene (None, and a placeholder figure, when there is no scene or none of the rows ran)."""
    scene, frames = fig7_scene(res), res.frames
    curves = []
    if scene is not None and len(frames) and "method_id" in frames:
        for label, row in rows:
            part = frames[(frames.method_id == row) & (frames.spp == spp) & (frames.scene == scene)]
            if row is not None and len(part):
                curves.append((label, row, part.sort_values("frame")))
    if not curves:
        placeholder(path, f"no Fig. 7 row ran at {spp} spp")
        return None
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, len(FIG7_PANELS), figsize=(11, 4.0), squeeze=False)
    for ax, (metric, ylabel) in zip(axes[0], FIG7_PANELS):
        for label, row, part in curves:
            if metric in part:
                ax.plot(part["frame"], part[metric], marker=".", label=f"{label} ({row})")
        cuts = curves[0][2]
        if "camera_cut" in cuts:
            for t in cuts.loc[cuts.camera_cut.astype(bool), "frame"]:
                ax.axvline(t, color="grey", linestyle=":", linewidth=0.8)
        ax.set_xlabel("frame")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{ylabel}, {spp} spp", fontsize=9)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 3), fontsize=8)
    fig.suptitle(f"{scene}: per-frame PSNR and tPSNR (Hasselgren et al. 2020, Fig. 7 layout; higher is better)\n"
                 "tPSNR is undefined on the first frame and during warm-up; dotted: camera cut", fontsize=9)
    fig.tight_layout(rect=(0, 0.12, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return scene


def _sample_map(res: Results, row: str | None, scene: str, spp: int) -> tuple[int, np.ndarray] | None:
    """(frame, (H, W) sample map) of the grid frame of one row's clip, None without sample maps."""
    if row is None or not res.ran(row, spp):
        return None
    by_frame = sample_maps_of(res.results_dir, row, scene, spp)
    if not by_frame:
        return None
    frame = _grid_frame(res.cfg, sorted(by_frame))
    return frame, by_frame[frame]


def plot_sample_maps(res: Results, path: Path, rows: Sequence[tuple[str, str | None]], spp: int) -> None:
    """Fig. 6 layout: per evaluated scene the reference (tonemapped) of the grid frame (evaluation.grid_frame)
    beside the sample maps of the adaptive ``rows`` (label, row id) at ``spp``, one colour scale in samples
    per pixel."""
    maps = {(scene, label): _sample_map(res, row, scene, spp) for scene in res.scenes for label, row in rows}
    shown = [m for m in maps.values() if m is not None]
    if not shown:
        placeholder(path, f"no sample maps of {' or '.join(label for label, _ in rows)} at {spp} spp")
        return
    plt = pyplot()
    vmax = max(1.0, max(float(m.max()) for _, m in shown))
    fig, axes = plt.subplots(len(res.scenes), 1 + len(rows), squeeze=False,
                             figsize=(2.6 * (1 + len(rows)) + 0.8, 2.6 * len(res.scenes)))
    image = None
    for r, scene in enumerate(res.scenes):
        frame = next((m[0] for (s, _), m in maps.items() if s == scene and m is not None), None)
        ax = axes[r][0]
        try:
            if frame is None:
                raise EvaluationError("no sample map")
            ax.imshow(preview_rgb8(reference_radiance(res.results_dir / "renders" / scene, frame)),
                      interpolation="nearest")
            ax.set_title(f"{scene}, frame {frame}\nreference", fontsize=8)
        except (EvaluationError, OSError) as error:
            ax.text(0.5, 0.5, f"{scene}\nno reference:\n{str(error)[:60]}", ha="center", va="center", fontsize=7)
        for c, (label, row) in enumerate(rows, start=1):
            ax, found = axes[r][c], maps[(scene, label)]
            if found is None:
                ax.text(0.5, 0.5, f"{label}: not run", ha="center", va="center", fontsize=8)
            else:
                image = ax.imshow(found[1], cmap="viridis", vmin=0.0, vmax=vmax, interpolation="nearest")
                ax.set_title(f"{label} ({row}), frame {found[0]}\nmean {found[1].mean():.2f} spp",
                             fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(f"Sample maps at an average of {spp} spp (Hasselgren et al. 2020, Fig. 6 layout)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 0.9, 0.96))
    bar = fig.colorbar(image, ax=axes.ravel().tolist(), fraction=0.03, pad=0.02)
    bar.set_label("samples per pixel", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
