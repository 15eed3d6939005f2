"""Figures of the Iglesias-Guitian et al. 2022 reproduction on the volumetric clips
(denoisers.reproductions.iglesias2022): per-frame PSNR curves per scenario (the paper's Figs. 10-12) and an
image grid per scenario (reference, then every volume row at the paper's spp).

A module of its own (leading underscore: denoisers.reproductions skips it when collecting papers).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from denoisers.evaluate import FRAME_EXR, EvaluationError, preview_rgb8, read_radiance_exr
from denoisers.report.figures import placeholder, pyplot
from denoisers.jobs.volumes import volume_denoised_dir

if TYPE_CHECKING:
    from denoisers.report.volumes import VolumeResults

SCENARIO_TITLES = {"camera": "camera animation (Fig. 10)", "light": "moving light (Fig. 11)",
                   "transfer_function": "transfer-function edit (Fig. 12)"}


def plot_curves(vol: VolumeResults, spp: int, path: Path) -> str:
    """Per-frame PSNR (mean over a scenario's clips) of every volume row that ran at ``spp``, one panel per
    scenario; '' when drawn, else why not (and a placeholder)."""
    frames = vol.frames[vol.frames.spp == spp]
    scenarios = list(dict.fromkeys(vol.scenarios.values()))
    if frames.empty:
        reason = f"no volume row ran at {spp} spp"
        placeholder(path, reason)
        return reason
    plt = pyplot()
    fig, axes = plt.subplots(1, len(scenarios), figsize=(4.2 * len(scenarios), 3.4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        mine = frames[frames.scenario == scenario]
        for row, table in mine.groupby("method_id", sort=False):
            curve = table.groupby("frame")["psnr"].mean()
            ax.plot(curve.index, curve.to_numpy(), marker=".", label=row, linewidth=1.0)
        n = len([s for s, k in vol.scenarios.items() if k == scenario])
        ax.set_title(f"{SCENARIO_TITLES.get(scenario, scenario)}; {n} clip(s)", fontsize=8)
        ax.set_xlabel("frame")
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel(f"PSNR (dB) @ {spp} spp")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return ""


def plot_grid(vol: VolumeResults, results_dir: Path, spp: int, path: Path) -> str:
    """For the first clip of each scenario, its last frame: reference, then every row that ran at ``spp`` (the
    frame's PSNR in the title); '' when drawn, else why not (and a placeholder)."""
    from scenegen.dataset import find_frames, load_reference_frame

    rows = [spec.id for spec in vol.specs if vol.ran(spec.id, spp)]
    clips = {}
    for scene, scenario in vol.scenarios.items():
        clips.setdefault(scenario, scene)
    if not rows or not clips:
        reason = f"no volume row ran at {spp} spp"
        placeholder(path, reason)
        return reason
    plt = pyplot()
    fig, axes = plt.subplots(len(clips), len(rows) + 1, figsize=(1.9 * (len(rows) + 1), 2.1 * len(clips)),
                             squeeze=False)
    for line, (scenario, scene) in enumerate(clips.items()):
        references = find_frames(results_dir / "renders" / scene / "reference")
        if not references:
            raise EvaluationError(f"{results_dir}/renders/{scene}/reference: no frames (needed for the volume grid)")
        frame = max(references)
        images = [("reference", load_reference_frame(references[frame], ["radiance"])[0]["radiance"])]
        for row in rows:
            images.append((row, read_radiance_exr(volume_denoised_dir(results_dir, row, scene, spp)
                                                  / FRAME_EXR.format(frame))))
        psnr = vol.frames[(vol.frames.scene == scene) & (vol.frames.spp == spp) & (vol.frames.frame == frame)]
        psnr = psnr.set_index("method_id")["psnr"]
        for column, (name, image) in enumerate(images):
            ax = axes[line][column]
            ax.imshow(preview_rgb8(np.asarray(image)))
            title = name if name == "reference" else f"{name}\n{psnr.get(name, float('nan')):.2f} dB"
            ax.set_title(title, fontsize=7)
            ax.set_xticks([])
            ax.set_yticks([])
        axes[line][0].set_ylabel(f"{scenario}\n{scene}, frame {frame}", fontsize=7)
    fig.suptitle(f"Volumetric clips at {spp} spp (last frame)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return ""
