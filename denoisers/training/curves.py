"""Training curves of the trainer (``denoisers.training.loop``): ``curves.png`` from its history rows."""
from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


def plot_curves(history: Sequence[Mapping[str, Any]], path: Path, title: str = "training") -> None:
    """Training loss (log scale) with the validation loss, and the validation image metrics, per step."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = sorted(history, key=lambda r: r["step"])

    def series(key: str) -> tuple[list[int], list[float]]:
        points = [(r["step"], r[key]) for r in rows if r.get(key) is not None and math.isfinite(r[key])]
        return [p[0] for p in points], [p[1] for p in points]

    figure = Figure(figsize=(10, 4), constrained_layout=True)
    FigureCanvasAgg(figure)
    loss_axes, metric_axes = figure.subplots(1, 2)
    for key, label in (("train_loss", "training loss"), ("val_loss", "validation loss")):
        steps, values = series(key)
        if steps:
            loss_axes.plot(steps, values, marker="." if key.startswith("val") else None, label=label)
    if any(v > 0 for r in rows for k, v in r.items() if k.endswith("loss") and v is not None and math.isfinite(v)):
        loss_axes.set_yscale("log")
    loss_axes.set_xlabel("step")
    loss_axes.set_ylabel("loss")
    loss_axes.set_title(title)
    loss_axes.legend(loc="best")
    steps, values = series("val_ssim")
    if steps:
        metric_axes.plot(steps, values, marker=".", label="validation SSIM")
        metric_axes.set_ylabel("SSIM")
        metric_axes.legend(loc="best")
    else:
        metric_axes.text(0.5, 0.5, "no validation metrics", ha="center", va="center", transform=metric_axes.transAxes)
    metric_axes.set_xlabel("step")
    path = Path(path)
    staging = path.with_name(f".{path.name}.tmp-{os.getpid()}.png")
    figure.savefig(staging, dpi=100)
    os.replace(staging, path)
