"""Figures of the Isik et al. 2021 reproduction (denoisers.reproductions.isik2021): Fig. 8, PSNR against
throughput (Mpix/s of the timing job, every row timed with the same threads) for every row and spp.

A module of its own (leading underscore: denoisers.reproductions skips it when collecting papers).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from denoisers.report.figures import placeholder, pyplot

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
