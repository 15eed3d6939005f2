"""Colour balance of every evaluated row: does a method keep the reference's colour?

Per (row, spp) and evaluated scene, the ratio of the output's mean radiance to the reference's, per channel
(R, G, B), over all pixels and frames of the clip (linear HDR). Its mean over the three channels is the
brightness bias; the colour cast is the largest relative departure of one channel's ratio from that mean,
max_c |ratio_c / mean(ratio) - 1| (0: no cast; 0.5: one channel 50 % off the others). PSNR and SSIM barely
see a cast that FLIP and the eye do (a learned model that mixes channels shifts hues while keeping the
texture), hence this table. Means over the evaluated scenes; the largest cast over them beside it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from denoisers.evaluate import denoised_dir, read_frame_files, read_radiance_exr
from denoisers.report.collect import Results

#: A row whose mean colour cast over the scenes exceeds this is named in the report's text.
CAST_NOTE_THRESHOLD = 0.1


def channel_means(frames: list[np.ndarray]) -> np.ndarray:
    """(3,) mean linear radiance per channel of (3, H, W) frames, non-finite values ignored."""
    stacked = np.concatenate([np.asarray(frame, dtype=np.float64).reshape(3, -1) for frame in frames], axis=1)
    return np.nanmean(np.where(np.isfinite(stacked), stacked, np.nan), axis=1)


def cast_of(ratios: np.ndarray) -> float:
    """max_c |ratio_c / mean(ratio) - 1| of (3,) per-channel output / reference ratios."""
    mean = float(np.mean(ratios))
    return float(np.max(np.abs(ratios / mean - 1.0))) if mean > 0 else float("nan")


def _reference_means(render_dir: Path, frames: list[int]) -> np.ndarray:
    from denoisers.report.figures import reference_radiance

    return channel_means([reference_radiance(render_dir, t) for t in frames])


def color_balance_table(res: Results) -> pd.DataFrame:
    """One row per evaluated (row, spp) that ran, ablation rows included (role 'ablation': e.g. which input set
    of the RAE brings a cast): mean per-channel output / reference ratio over the
    evaluated scenes (ratio_r, ratio_g, ratio_b), brightness (their mean), cast (mean over scenes of each
    scene's cast) and cast_max (the largest scene's) and the scene it occurs on."""
    references: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}
    rows = []
    for spec in res.specs:
        for spp in sorted({int(r["spp"]) for r in res.runs if r["id"] == spec.id and r["status"] == "ran"}):
            per_scene = []
            for scene in res.scenes:
                files = read_frame_files(denoised_dir(res.results_dir, spec.id, scene, spp))
                frames = sorted(files)
                key = (scene, tuple(frames))
                if key not in references:
                    references[key] = _reference_means(res.results_dir / "renders" / scene, frames)
                output = channel_means([read_radiance_exr(files[t]) for t in frames])
                per_scene.append((scene, output / references[key]))
            ratios = np.array([r for _, r in per_scene])
            casts = np.array([cast_of(r) for _, r in per_scene])
            worst = int(np.nanargmax(casts))
            rows.append({"method_id": spec.id, "role": spec.role, "spp": int(spp), "scenes": len(per_scene),
                         "ratio_r": float(ratios[:, 0].mean()), "ratio_g": float(ratios[:, 1].mean()),
                         "ratio_b": float(ratios[:, 2].mean()), "brightness": float(ratios.mean()),
                         "cast": float(np.nanmean(casts)), "cast_max": float(casts[worst]),
                         "cast_max_scene": per_scene[worst][0]})
    return pd.DataFrame(rows, columns=["method_id", "role", "spp", "scenes", "ratio_r", "ratio_g", "ratio_b", "brightness",
                                       "cast", "cast_max", "cast_max_scene"])


def color_balance_section(res: Results, tables: Path) -> list[str]:
    """Writes tables/color_balance.{csv,md}; returns the report's lines."""
    from denoisers.report.stats import frame_to_markdown
    from denoisers.report.tables import write_table

    table = color_balance_table(res)
    shown = table.copy()
    for column in ("ratio_r", "ratio_g", "ratio_b", "brightness", "cast", "cast_max"):
        shown[column] = shown[column].map(lambda v: f"{v:.3f}")
    markdown = frame_to_markdown(shown) if len(table) else "no row ran\n"
    write_table(table, tables, "color_balance", markdown)
    cast = table[table["cast"] > CAST_NOTE_THRESHOLD]
    note = ("Rows with a mean colour cast above "
            f"{CAST_NOTE_THRESHOLD:g}: " + ", ".join(f"{r.method_id} @ {r.spp} spp ({r.cast:.2f})"
                                                      for r in cast.itertuples()) + "."
            if len(cast) else f"No row has a mean colour cast above {CAST_NOTE_THRESHOLD:g}.")
    return ["### Colour balance", "",
            "Mean output over mean reference radiance per channel, per evaluated scene, then averaged over the "
            "scenes; brightness = the mean of the three ratios; cast = max over channels of |ratio / brightness "
            "- 1| (0: the reference's colour; PSNR and SSIM hardly see a cast, FLIP does). " + note, "",
            markdown, ""]
