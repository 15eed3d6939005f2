"""Cross-paper figures: quality versus speed, per-frame error curves, image grids with crops and error
maps, training curves. Matplotlib is imported inside the functions (Agg backend)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from denoisers.evaluate import (
    REFERENCE_METHODS,
    ROBUSTNESS_LAST_EXR,
    EvaluationError,
    MethodSpec,
    denoised_dir,
    read_frame_files,
    read_radiance_exr,
    robustness_dir,
)
from denoisers.report.collect import Results
from denoisers.report.trained import TrainedModels
from denoisers.report.tables import RANK_SPREAD_LIMIT, summary_lookup, too_wide_to_rank

if TYPE_CHECKING:
    import pandas as pd


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: Markers and line styles that tell apart rows sharing one of tab10's ten colours (the default config has 22 rows).
_MARKERS = ("o", "s", "^", "D")
_LINESTYLES = ("-", "--", ":", "-.")


def row_styles(rows: Sequence[str]) -> dict[str, dict[str, Any]]:
    """row -> matplotlib style (color, marker, linestyle): tab10's colours in order, then again with the next
    marker and line style, so up to 40 rows get distinct styles."""
    cmap = pyplot().get_cmap("tab10")
    return {row: {"color": cmap(i % 10), "marker": _MARKERS[(i // 10) % len(_MARKERS)],
                  "linestyle": _LINESTYLES[(i // 10) % len(_LINESTYLES)]} for i, row in enumerate(rows)}


def _styles(specs: Sequence[MethodSpec]) -> dict[str, dict[str, Any]]:
    """:func:`row_styles` of the rows of ``specs``."""
    return row_styles([spec.id for spec in specs])


def legend_entries(axes: Sequence[Any]) -> tuple[list[Any], list[str]]:
    """(handles, labels) of every labelled line of every axis, each label once, in first-seen order (a row that
    ran only at some spp is missing from the first panel)."""
    legend: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    return list(legend.values()), list(legend)


#: A log axis is cut this many times above the median of the rows' per-frame medians (an exploding model
#: would otherwise flatten every other row).
LOG_AXIS_SPAN = 1e3


def _cut_log_axis(ax: Any, values: Sequence[np.ndarray]) -> None:
    """Cut a log y axis at LOG_AXIS_SPAN x the median row median, and say so on the axis, when some row lies above."""
    finite = [v[np.isfinite(v) & (v > 0)] for v in values]
    medians = [float(np.median(v)) for v in finite if len(v)]
    if not medians:
        return
    top = LOG_AXIS_SPAN * float(np.median(medians))
    highest = max(float(v.max()) for v in finite if len(v))
    if highest > top:
        ax.set_ylim(top=top)
        ax.annotate(f"cut: values up to {highest:.3g} above", (0.99, 0.98), xycoords="axes fraction", ha="right",
                    va="top", fontsize=7, color="firebrick")


def smoothed(values: Any, window: int) -> np.ndarray:
    """Running mean over ``window`` points (the first value repeated before the start)."""
    values = np.asarray(values, dtype=float)
    if window <= 1 or len(values) < window:
        return values
    padded = np.concatenate([np.full(window - 1, values[0]), values])
    return np.convolve(padded, np.ones(window) / window, mode="valid")


def save_step_plot(figure: Any, axes: Any, path: Path, ylabel: str, title: str, log_y: bool = False,
                   legend_size: int | None = None) -> None:
    """Label a plot against training step (grid, legend), write it to ``path`` and close it."""
    if log_y:
        axes.set_yscale("log")
    axes.set_xlabel("training step")
    axes.set_ylabel(ylabel)
    axes.set_title(title)
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=legend_size)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    pyplot().close(figure)


def plot_quality_vs_speed(res: Results, summary: pd.DataFrame, paths: Sequence[Path]) -> list[str]:
    """PSNR against denoiser throughput (Mpix/s from the timing job, log x), a point per method and spp with
    95 % CI bars over scenes (PSNR) and the range over timing rounds (throughput); the non-denoising rows
    (noisy input, plain path tracing) are horizontal reference lines. Rows the timing job did not time are
    left out. A second panel puts the learned rows' PSNR against the wall time their model trained
    (summary.json ``elapsed_seconds``), so a method's training cost is charted beside its inference speed.
    Returns the rows drawn in the first panel (points and reference lines), in table order."""
    plt = pyplot()
    lookup = summary_lookup(summary)
    styles = _styles(res.main_specs)
    colours = {row: style["color"] for row, style in styles.items()}
    fig, (ax, train_ax) = plt.subplots(1, 2, figsize=(13.0, 5.0), gridspec_kw={"width_ratios": [3, 2]})
    xs, drawn = [], []
    for spec in res.main_specs:
        spps = [s for s in res.cfg["evaluation"]["spp"] if res.ran(spec.id, s) and res.speed(spec.id, s)]
        if not spps or spec.method in REFERENCE_METHODS:
            continue
        speeds = [res.speed(spec.id, s) for s in spps]
        x = [row["mpix_per_s"] for row in speeds]
        # Throughput range over rounds: the fastest and slowest pass.
        slowest = [row["mpix_per_s"] * row["ms_per_frame"] / row["ms_per_frame_max"] for row in speeds]
        fastest = [row["mpix_per_s"] * row["ms_per_frame"] / row["ms_per_frame_min"] for row in speeds]
        xerr = [[xi - lo for xi, lo in zip(x, slowest)], [hi - xi for xi, hi in zip(x, fastest)]]
        y = [lookup[(spec.id, s, "psnr")] for s in spps]
        ax.errorbar(x, [v[0] for v in y], xerr=xerr, yerr=_ci_yerr(y), marker=styles[spec.id]["marker"],
                    color=colours[spec.id], label=spec.id, capsize=3)
        drawn.append(spec.id)
        # Timing ranges too wide to rank (tables.RANK_SPREAD_LIMIT): hollow markers over the filled ones.
        wide = [i for i, row in enumerate(speeds) if too_wide_to_rank(row)]
        if wide:
            ax.plot([x[i] for i in wide], [y[i][0] for i in wide], linestyle="none", marker=styles[spec.id]["marker"],
                    markersize=11, markerfacecolor="white", markeredgecolor=colours[spec.id], zorder=3)
        # Only the spp next to each point (the colour says the method): long labels overlapped.
        for xi, yi, s in zip(x, y, spps):
            ax.annotate(str(s), (xi, yi[0]), textcoords="offset points", xytext=(4, -9), fontsize=7,
                        color=colours[spec.id])
        xs += x
    for spec in res.main_specs:
        if spec.method not in REFERENCE_METHODS:
            continue
        for s in res.cfg["evaluation"]["spp"]:
            if res.ran(spec.id, s):
                drawn += [] if spec.id in drawn else [spec.id]
                level = lookup[(spec.id, s, "psnr")][0]
                ax.axhline(level, color=colours[spec.id], linestyle="--", linewidth=0.8, alpha=0.7)
                # Noisy rows labelled on the right, path-tracing rows on the left: equal totals coincide.
                right = spec.method == "noisy"
                ax.annotate(f"{spec.id} {s}spp", (0.995 if right else 0.005, level),
                            xycoords=("axes fraction", "data"), ha="right" if right else "left", va="bottom",
                            fontsize=7, color=colours[spec.id])
    ax.set_xscale("log")
    if not xs:
        ax.set_xlim(0.1, 10)
    # Plain numbers at 1, 2, 5 x 10^k instead of sparse powers of ten.
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    threads = f", {res.timing.threads} thread(s)" if res.timing is not None else ", no timing job"
    ax.set_xlabel(f"throughput (Mpix/s, denoising only, timing job{threads}, log scale)")
    ax.set_ylabel("PSNR (dB, tonemapped)")
    ax.set_title(f"Quality vs speed (PSNR: mean ± 95 % CI over {len(res.scenes)} scene(s);\nthroughput: median, "
                 "bars = range over timing rounds; numbers = spp; hollow: range too wide to rank\n"
                 f"(> {RANK_SPREAD_LIMIT:g} x median); dashed: noisy input / path tracing at that spp)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    _plot_quality_vs_training_time(res, lookup, colours, train_ax)
    if xs:   # outside the axes, so it covers no data
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    for path in paths:
        fig.savefig(path, dpi=150)
    plt.close(fig)
    order = [spec.id for spec in res.main_specs]
    return sorted(drawn, key=order.index)


def _ci_yerr(y: Sequence[tuple[float, float, float, int]]) -> list[list[float]]:
    """matplotlib yerr (below, above) from summary_lookup values (mean, CI low, CI high, n); 0 without a CI."""
    return [[0 if math.isnan(v[1]) else v[0] - v[1] for v in y], [0 if math.isnan(v[2]) else v[2] - v[0] for v in y]]


def _plot_quality_vs_training_time(res: Results, lookup: dict, colours: dict[str, Any], ax: Any) -> None:
    """PSNR (mean ± 95 % CI over scenes) of every row backed by a trained model against its training wall
    time in minutes (log x); one point per evaluated spp, numbers = spp."""
    labels: dict[str, dict[str, Any]] = {}   # model id -> where and what to label (rows sharing a model share one)
    for spec in res.main_specs:
        model = res.model_of(spec.id)
        seconds = float(model.summary.get("elapsed_seconds") or 0.0) if model is not None else 0.0
        spps = [s for s in res.cfg["evaluation"]["spp"] if res.ran(spec.id, s) and (spec.id, s, "psnr") in lookup]
        if model is None or seconds <= 0 or not spps:
            continue
        minutes = seconds / 60.0
        y = [lookup[(spec.id, s, "psnr")] for s in spps]
        ax.errorbar([minutes] * len(spps), [v[0] for v in y], yerr=_ci_yerr(y), marker="s", linestyle="none",
                    color=colours[spec.id], capsize=3)
        for yi, s in zip(y, spps):
            ax.annotate(str(s), (minutes, yi[0]), textcoords="offset points", xytext=(4, -9), fontsize=7,
                        color=colours[spec.id])
        label = labels.setdefault(model.spec.id, {"minutes": minutes, "top": -math.inf, "rows": [],
                                                  "steps": model.summary.get("steps")})
        label["top"] = max(label["top"], max(v[0] for v in y))
        label["rows"].append(spec.id)
    for model_id, label in labels.items():
        rows = label["rows"]
        model_text = "" if rows == [model_id] else f" [model {model_id}]"
        ax.annotate(f"{', '.join(rows)}{model_text}, {label['steps']} steps", (label["minutes"], label["top"]),
                    textcoords="offset points", xytext=(4, 4), fontsize=7, color=colours[rows[0]])
    if not labels:
        ax.text(0.5, 0.5, "no row with a trained model", ha="center", va="center", transform=ax.transAxes)
    else:
        from matplotlib.ticker import FuncFormatter

        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.margins(x=0.25)
    ax.set_xlabel("training wall time (min, log scale; summary.json elapsed_seconds)")
    ax.set_ylabel("PSNR (dB, tonemapped)")
    ax.set_title("Learned rows: quality vs training time\n(numbers = spp; same colours as the left panel)",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)


def plot_frame_curves(res: Results, scene: str, path: Path) -> list[str]:
    """Per-frame relMSE (log), 1 - SSIM and tPSNR of every method, one row per spp, camera cuts dotted.
    Returns the rows drawn (the legend's entries)."""
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    spps = res.cfg["evaluation"]["spp"]
    styles = _styles(res.main_specs)
    panels = (("relmse", "rMSE (log)"), ("ssim", "1 − SSIM"), ("tpsnr", "tPSNR (dB)"))
    fig, axes = plt.subplots(len(spps), len(panels), figsize=(12, 2.6 * len(spps)), squeeze=False)
    data = res.frames[res.frames.scene == scene]
    for row, spp in enumerate(spps):
        for col, (metric, label) in enumerate(panels):
            ax = axes[row][col]
            plotted = []
            for spec in res.main_specs:
                part = data[(data.method_id == spec.id) & (data.spp == spp)].sort_values("frame")
                if part.empty:
                    continue
                values = 1.0 - part[metric] if metric == "ssim" else part[metric]
                ax.plot(part["frame"], values, marker=styles[spec.id]["marker"], markersize=3,
                        color=styles[spec.id]["color"], label=spec.id)
                plotted.append(np.asarray(values, np.float64))
                for t in part.loc[part.camera_cut.astype(bool), "frame"]:
                    ax.axvline(t, color="grey", linestyle=":", linewidth=0.8)
            if metric == "relmse" and ax.has_data():
                ax.set_yscale("log")
                _cut_log_axis(ax, plotted)
            ax.set_title(f"{label}, {spp} spp", fontsize=9)
            ax.set_ylabel(label, fontsize=8)
            ax.set_xlabel("frame")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(True, alpha=0.3)
    handles, labels = legend_entries(axes.ravel())
    drawn = list(labels)
    if handles:
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="grey", linestyle=":", linewidth=0.8))
        labels.append("camera cut")
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 9), fontsize=8)
    fig.suptitle(f"{scene}: per-frame error (lower rMSE / 1−SSIM, higher tPSNR is better)", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return drawn


def _grid_frame(cfg: dict, frames: Sequence[int]) -> int:
    """The frame shown in the grids: evaluation.grid_frame indexes the clip's frames (range checked with the
    config, so it never wraps around)."""
    return list(frames)[int(cfg["evaluation"]["grid_frame"])] if frames else 0


def _crop_window(error: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left (y, x) of the size x size window with the largest summed error (integral image)."""
    height, width = error.shape
    size = min(size, height, width)
    integral = np.pad(error.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = (integral[size:, size:] - integral[:-size, size:] - integral[size:, :-size] + integral[:-size, :-size])
    y, x = np.unravel_index(np.argmax(sums), sums.shape)
    return int(y), int(x)


def sample_maps_of(results_dir: Path, row: str, scene: str, spp: int) -> dict[int, np.ndarray]:
    """{frame: (H, W) samples per pixel} of an adaptive row's clip (its sample_maps.npz beside the denoised
    frames); empty for a row without sample maps."""
    from denoisers.adaptive import SAMPLE_MAPS_FILE

    path = denoised_dir(results_dir, row, scene, spp) / SAMPLE_MAPS_FILE
    if not path.is_file():
        return {}
    with np.load(path) as data:
        return {int(f): np.asarray(m, dtype=np.float64) for f, m in zip(data["frames"].tolist(), data["sample_maps"])}


#: Image grids wrap into bands: at most this many panels (columns + the reference) side by side, i.e. about
#: GRID_MAX_WIDTH_PX wide at GRID_DPI.
GRID_MAX_WIDTH_PX = 1600
GRID_DPI = 120
GRID_PANEL_INCHES = 1.9
GRID_PANELS_PER_BAND = max(2, int(GRID_MAX_WIDTH_PX // (GRID_PANEL_INCHES * GRID_DPI)))


def image_grid(columns: Sequence[tuple[str, np.ndarray]], reference: np.ndarray, path: Path, title: str,
               sample_maps: Sequence[np.ndarray | None] = ()) -> None:
    """Columns of (label, (3, H, W) radiance) plus the reference: full frame with the crop marked, the crop
    enlarged, and the error map |tonemap(x) - tonemap(ref)| (channel mean, common colour scale). With
    ``sample_maps`` (one (H, W) map or None per column) a fourth row shows the adaptive columns' sample maps
    (samples per pixel, one colour scale)."""
    from denoisers import metrics
    from denoisers.evaluate import preview_rgb8

    plt = pyplot()
    from matplotlib.patches import Rectangle

    ref_tm = np.asarray(metrics.tonemap(reference))
    errors = [np.abs(np.asarray(metrics.tonemap(np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0))) - ref_tm)
              .mean(axis=0) for _, img in columns]
    size = max(8, min(reference.shape[1:]) // 4)
    y, x = _crop_window(errors[0] if errors else np.zeros(reference.shape[1:]), size)
    vmax = float(np.percentile(errors[0], 99)) if errors else 1.0
    vmax = vmax if vmax > 0 else 1.0
    maps = [*sample_maps, *[None] * (len(columns) - len(sample_maps))]
    rows = 4 if any(m is not None for m in maps) else 3
    # Bands of at most GRID_PANELS_PER_BAND panels (the reference closes every band), so a grid of many rows wraps
    # instead of growing wider than about GRID_MAX_WIDTH_PX.
    per_band = GRID_PANELS_PER_BAND - 1
    bands = [list(range(start, min(start + per_band, len(columns)))) for start in range(0, max(len(columns), 1),
                                                                                        per_band)]
    width = min(GRID_PANELS_PER_BAND, len(columns) + 1)
    fig, axes = plt.subplots(rows * len(bands), width, figsize=(GRID_PANEL_INCHES * width, 2.0 * rows * len(bands)),
                             squeeze=False)
    error_axes, map_axes = [], []
    for band, members in enumerate(bands):
        grid = axes[band * rows:(band + 1) * rows]
        panels = [(columns[i][0], columns[i][1], maps[i], errors[i]) for i in members]
        panels.append(("reference", reference, None, None))
        for col in range(width):
            if col >= len(panels):
                for row in range(rows):
                    grid[row][col].set_axis_off()
                continue
            label, img, found, error = panels[col]
            rgb = preview_rgb8(img)
            psnr = "" if error is None else (
                f"\n{float(metrics.psnr(np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0), reference)):.2f} dB")
            grid[0][col].imshow(rgb, interpolation="nearest")
            grid[0][col].add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, edgecolor="cyan",
                                             linewidth=1))
            grid[0][col].set_title(f"{label}{psnr}", fontsize=8)
            grid[1][col].imshow(rgb[y:y + size, x:x + size], interpolation="nearest")
            grid[2][col].imshow(np.zeros_like(ref_tm[0]) if error is None else error, cmap="inferno", vmin=0,
                                vmax=vmax, interpolation="nearest")
            error_axes.append(grid[2][col])
            for row in range(rows):
                grid[row][col].set_xticks([])
                grid[row][col].set_yticks([])
            if rows == 4:
                if found is None:
                    grid[3][col].set_axis_off()
                else:
                    map_axes.append((grid[3][col], found))
        grid[1][0].set_ylabel("crop", fontsize=8)
        grid[2][0].set_ylabel("|error|, tonemapped", fontsize=8)
        if rows == 4:
            grid[3][0].set_ylabel("sample map", fontsize=8)
    if map_axes:
        spp_max = max(1.0, max(float(found.max()) for _, found in map_axes))
        for ax, found in map_axes:
            ax.imshow(found, cmap="viridis", vmin=0.0, vmax=spp_max, interpolation="nearest")
            ax.set_title(f"mean {found.mean():.2f} spp", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    mappable = plt.cm.ScalarMappable(cmap="inferno", norm=plt.Normalize(0.0, vmax))
    bar = fig.colorbar(mappable, ax=error_axes, fraction=0.02, pad=0.01, format="%.2g")
    bar.ax.tick_params(labelsize=7)
    if map_axes:
        spp_bar = fig.colorbar(plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0.0, spp_max)),
                               ax=[ax for ax, _ in map_axes], fraction=0.02, pad=0.01)
        spp_bar.set_label("spp", fontsize=7)
        spp_bar.ax.tick_params(labelsize=7)
    fig.savefig(path, dpi=GRID_DPI, bbox_inches="tight")
    plt.close(fig)


def placeholder(path: Path, text: str) -> None:
    """A small figure that only says why there is nothing to show."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4, 1.5))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.set_axis_off()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def reference_radiance(render_dir: Path, frame: int) -> np.ndarray:
    """(3, H, W) reference radiance of ``frame`` below ``render_dir``; EvaluationError naming a missing frame."""
    from scenegen.dataset import find_frames, load_reference_frame

    found = find_frames(Path(render_dir) / "reference")
    if frame not in found:
        raise EvaluationError(f"{render_dir}/reference: frame {frame} missing (needed for the report)")
    return load_reference_frame(found[frame], ["radiance"])[0]["radiance"]


def plot_grids(res: Results, figures: Path) -> dict[str, list[str]]:
    """One image grid per evaluated scene and evaluated spp, plus the robustness grid. Returns figure file name ->
    the rows shown as its columns."""
    written: dict[str, list[str]] = {}
    for scene, spp in ((scene, spp) for scene in res.scenes for spp in res.cfg["evaluation"]["spp"]):
        columns, frame, maps = [], None, []
        for spec in res.main_specs:
            if not res.ran(spec.id, spp):
                continue
            files = read_frame_files(denoised_dir(res.results_dir, spec.id, scene, spp))
            frame = _grid_frame(res.cfg, sorted(files)) if frame is None else frame
            columns.append((spec.id, read_radiance_exr(files[frame])))
            maps.append(sample_maps_of(res.results_dir, spec.id, scene, spp).get(frame))
        frame = frame if frame is not None else 0
        path = figures / f"grid_{scene}_spp{spp}.png"
        reference = reference_radiance(res.results_dir / "renders" / scene, frame)
        image_grid(columns, reference, path, f"{scene}, frame {frame}, {spp} spp", sample_maps=maps)
        written[path.name] = [label for label, _ in columns]
    robustness = res.cfg["evaluation"]["robustness"]
    path = figures / "robustness_grid.png"
    if not (robustness["enabled"] and res.scenes):
        placeholder(path, "robustness scenario disabled" if res.scenes else "no evaluated scenes")
        written[path.name] = []
    else:
        scene, columns = res.scenes[0], []
        for spec in res.main_specs:
            exr = robustness_dir(res.results_dir, spec.id, scene, robustness["spp"]) / ROBUSTNESS_LAST_EXR
            if exr.is_file():
                columns.append((spec.id, read_radiance_exr(exr)))
        from scenegen.dataset import find_frames

        last = max(find_frames(res.results_dir / "renders" / scene / "reference"), default=0)
        image_grid(columns, reference_radiance(res.results_dir / "renders" / scene, last), path,
                   f"{scene}, frame {last}, {robustness['spp']} spp, spikes + NaN/Inf injected")
        written[path.name] = [label for label, _ in columns]
    return written


def plot_training_curves(models: TrainedModels, path: Path) -> None:
    """Training and validation loss of the models that are not ablation variants."""
    main = [m for m in models.models.values() if not m.spec.ablation]
    if not main:
        placeholder(path, "no model was trained")
        return
    plt = pyplot()
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for model in main:
        train = model.curves.dropna(subset=["train_loss"])
        line, = axes.plot(train["step"], smoothed(train["train_loss"], 5), label=f"{model.spec.id} training")
        if "val_loss" in model.curves:
            val = model.curves.dropna(subset=["val_loss"])
            axes.plot(val["step"], val["val_loss"], marker="o", linestyle="--", color=line.get_color(),
                      label=f"{model.spec.id} validation")
    save_step_plot(figure, axes, path, "loss", "Training curves", log_y=True)
