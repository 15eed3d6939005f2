"""The training part of the report: trained models, the RAE ablations (Chaitanya et al. 2017 Fig. 3 and
§4.4) and the paper's Fig. 8 numbers printed beside ours.

Read from ``results/models/<id>/`` (rule train_denoiser): ``summary.json``, ``curves.csv`` (training loss
per logged step, validation metrics per validated step) and ``validation.csv`` (per validation sequence,
model ``best.pt``). Like the rest of the report, every number is computed from those files.

* Final training loss of a model: mean ``train_loss`` over the last :data:`FINAL_FRACTION` of its logged
  steps (the logged values are already means over ``log_every`` steps).
* Validation comparisons are paired per validation sequence (identical sequences for every model of a
  config): mean difference with a 95 % Student-t interval over sequences.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.training.models import INPUT_ABLATION, LOSS_ABLATION, ModelSpec, model_dir, model_specs

if TYPE_CHECKING:
    import pandas as pd

FINAL_FRACTION = 0.2
#: Fig. 3 input sets, in the paper's legend order (our variant ids).
INPUT_VARIANT_ORDER = ("color", "untextured", "depth", "normal", "normal_depth", "all")
INPUT_VARIANT_LABELS = {"color": "colour only", "untextured": "untextured (demodulated)", "depth": "+ depth",
                        "normal": "+ normal", "normal_depth": "+ normal + depth", "all": "+ all (normal, depth, roughness)"}
#: §4.4: "SSIM showed an improvement from 0.9335 for Ls to 0.9417 for the combined loss" (SponzaDiffuse, 100 epochs).
PAPER_LOSS_ABLATION_SSIM = {"spatial": 0.9335, "combined": 0.9417}
#: Chaitanya et al. 2017 Fig. 8: (RMSE, SSIM) per scene at 1 spp, still images of Fig. 7 (1080p, GPU).
PAPER_FIG8: dict[str, dict[str, tuple[float, float]]] = {
    "AAF": {"CornellBox": (0.018, 0.978), "Sponza": (0.029, 0.869), "GlossySponza": (0.069, 0.664),
            "SanMiguel": (0.079, 0.774), "Classroom": (0.064, 0.786)},
    "EAW": {"CornellBox": (0.019, 0.978), "Sponza": (0.043, 0.902), "GlossySponza": (0.089, 0.586),
            "SanMiguel": (0.088, 0.768), "Classroom": (0.059, 0.841)},
    "SBF": {"CornellBox": (0.044, 0.818), "Sponza": (0.060, 0.502), "GlossySponza": (0.057, 0.649),
            "SanMiguel": (0.087, 0.575), "Classroom": (0.072, 0.610)},
    "RAE (Our)": {"CornellBox": (0.014, 0.984), "Sponza": (0.016, 0.953), "GlossySponza": (0.034, 0.843),
                  "SanMiguel": (0.055, 0.844), "Classroom": (0.040, 0.909)},
}


@dataclass
class TrainedModel:
    spec: ModelSpec
    summary: dict[str, Any]
    curves: pd.DataFrame
    validation: pd.DataFrame

    def final_training_loss(self) -> float:
        rows = self.curves.dropna(subset=["train_loss"]) if "train_loss" in self.curves else self.curves.iloc[0:0]
        if not len(rows):
            return math.nan
        tail = max(1, int(math.ceil(len(rows) * FINAL_FRACTION)))
        return float(rows["train_loss"].iloc[-tail:].mean())


@dataclass
class TrainedModels:
    specs: list[ModelSpec]
    models: dict[str, TrainedModel] = field(default_factory=dict)   # models whose directory is complete

    def variants(self, ablation: str) -> dict[str, TrainedModel]:
        return {m.spec.variant: m for m in self.models.values() if m.spec.ablation == ablation}

    @property
    def missing(self) -> list[str]:
        return [spec.id for spec in self.specs if spec.id not in self.models]


def collect_models(cfg: dict, results_dir: Path) -> TrainedModels:
    """Every configured model whose directory holds summary.json, curves.csv and validation.csv."""
    import pandas as pd

    found = TrainedModels(model_specs(cfg))
    for spec in found.specs:
        folder = model_dir(results_dir, spec.id)
        files = [folder / name for name in ("summary.json", "curves.csv", "validation.csv")]
        if all(path.is_file() for path in files):
            found.models[spec.id] = TrainedModel(spec, json.loads(files[0].read_text()), pd.read_csv(files[1]),
                                                 pd.read_csv(files[2]))
    return found


def training_outputs(cfg: dict, root: str = "results") -> dict[str, list[str]]:
    """Files of the training part of the report (none when the config trains nothing)."""
    specs = model_specs(cfg)
    if not specs:
        return {"tables": [], "figures": []}
    ablations = {spec.ablation for spec in specs if spec.ablation}
    tables = ["training", "chaitanya_fig8_paper"] + [name for name in (INPUT_ABLATION, LOSS_ABLATION) if name in ablations]
    figures = ["training_curves"] + [f"{name}_curves" for name in (INPUT_ABLATION, LOSS_ABLATION) if name in ablations]
    return {"tables": [f"{root}/tables/{t}.{ext}" for t in tables for ext in ("csv", "md")],
            "figures": [f"{root}/figures/{f}.png" for f in figures]}


# ------------------------------------------------------------------------------------------ tables
def training_table(models: TrainedModels) -> pd.DataFrame:
    """One row per configured model: size, budget used and validation metrics of best.pt."""
    import pandas as pd

    rows = []
    for spec in models.specs:
        model = models.models.get(spec.id)
        row: dict[str, Any] = {"model": spec.id, "method": spec.method, "ablation": spec.ablation or "",
                               "variant": spec.variant or "", "status": "trained" if model else "not trained"}
        if model:
            s = model.summary
            validation = model.validation
            row.update({"parameters": s.get("parameters"), "parameters_full_width": s.get("parameters_full_width"),
                        "width": s.get("net", {}).get("config", {}).get("width"),
                        "steps": s.get("steps"), "stopped_by": s.get("stopped_by"),
                        "train_minutes": s.get("elapsed_seconds", math.nan) / 60.0,
                        "seconds_per_step": s.get("seconds_per_step"), "best_step": s.get("best_step"),
                        "final_train_loss": model.final_training_loss(),
                        **{f"val_{k}": float(validation[k].mean()) for k in ("loss", "ssim", "psnr", "rmse")
                           if k in validation}})
        rows.append(row)
    return pd.DataFrame(rows)


def paired(a: TrainedModel, b: TrainedModel, column: str) -> tuple[float, float, float, int]:
    """mean_ci of a - b per validation sequence."""
    from denoisers.report import mean_ci

    merged = a.validation[["sequence", column]].merge(b.validation[["sequence", column]], on="sequence",
                                                      suffixes=("_a", "_b"))
    return mean_ci((merged[f"{column}_a"] - merged[f"{column}_b"]).to_numpy(float))


def input_ablation_table(models: TrainedModels) -> pd.DataFrame:
    """Fig. 3: per input set, final training loss and validation loss / RMSE / SSIM (mean ± CI over sequences)."""
    import pandas as pd

    from denoisers.report import mean_ci

    rows = []
    variants = models.variants(INPUT_ABLATION)
    order = [v for v in INPUT_VARIANT_ORDER if v in variants] + sorted(set(variants) - set(INPUT_VARIANT_ORDER))
    for variant in order:
        model = variants[variant]
        row: dict[str, Any] = {"variant": variant, "inputs": INPUT_VARIANT_LABELS.get(variant, variant),
                               "model": model.spec.id, "steps": model.summary.get("steps"),
                               "final_train_loss": model.final_training_loss()}
        for column in ("loss", "rmse", "ssim"):
            mean, low, high, n = mean_ci(model.validation[column].to_numpy(float))
            row.update({f"val_{column}": mean, f"val_{column}_low": low, f"val_{column}_high": high})
        row["val_sequences"] = len(model.validation)
        rows.append(row)
    return pd.DataFrame(rows)


def loss_ablation_table(models: TrainedModels) -> pd.DataFrame:
    """§4.4: validation SSIM per loss (mean ± CI over sequences), the paper's SSIM beside."""
    import pandas as pd

    from denoisers.report import mean_ci

    rows = []
    for variant, model in sorted(models.variants(LOSS_ABLATION).items(), key=lambda kv: kv[0] != "spatial"):
        mean, low, high, n = mean_ci(model.validation["ssim"].to_numpy(float))
        rows.append({"variant": variant, "model": model.spec.id, "loss_weights": json.dumps(model.spec.loss),
                     "steps": model.summary.get("steps"), "val_ssim": mean, "val_ssim_low": low,
                     "val_ssim_high": high, "val_sequences": n,
                     "paper_ssim": PAPER_LOSS_ABLATION_SSIM.get(variant, math.nan)})
    return pd.DataFrame(rows)


def paper_fig8_table() -> pd.DataFrame:
    """The paper's Fig. 8 (RMSE and SSIM per paper scene at 1 spp), with the mean over its scenes."""
    import pandas as pd

    rows = []
    for method, scenes in PAPER_FIG8.items():
        row: dict[str, Any] = {"method": method}
        for scene, (rmse, ssim) in scenes.items():
            row[f"{scene} RMSE"], row[f"{scene} SSIM"] = rmse, ssim
        row["mean RMSE"] = round(sum(v[0] for v in scenes.values()) / len(scenes), 4)
        row["mean SSIM"] = round(sum(v[1] for v in scenes.values()) / len(scenes), 4)
        rows.append(row)
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------- figures
def _smoothed(values: Any, window: int) -> Any:
    import numpy as np

    values = np.asarray(values, dtype=float)
    if window <= 1 or len(values) < window:
        return values
    kernel = np.ones(window) / window
    padded = np.concatenate([np.full(window - 1, values[0]), values])
    return np.convolve(padded, kernel, mode="valid")


def plot_input_ablation(models: TrainedModels, path: Path) -> None:
    """Fig. 3: training loss against step for every input set (log y, running mean over 5 logged points)."""
    from denoisers.report import _pyplot, placeholder

    variants = models.variants(INPUT_ABLATION)
    if not variants:
        placeholder(path, f"no {INPUT_ABLATION} model was trained")
        return
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for variant in [v for v in INPUT_VARIANT_ORDER if v in variants] + sorted(set(variants) - set(INPUT_VARIANT_ORDER)):
        curves = variants[variant].curves.dropna(subset=["train_loss"])
        axes.plot(curves["step"], _smoothed(curves["train_loss"], 5), label=INPUT_VARIANT_LABELS.get(variant, variant))
    axes.set_yscale("log")
    axes.set_xlabel("training step")
    axes.set_ylabel("training loss (running mean)")
    axes.set_title("RAE input ablation (Chaitanya et al. 2017, Fig. 3)")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_loss_ablation(models: TrainedModels, path: Path) -> None:
    """§4.4: validation SSIM against step for each loss."""
    from denoisers.report import _pyplot, placeholder

    variants = models.variants(LOSS_ABLATION)
    if not variants:
        placeholder(path, f"no {LOSS_ABLATION} model was trained")
        return
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for variant, model in sorted(variants.items()):
        curves = model.curves.dropna(subset=["val_ssim"]) if "val_ssim" in model.curves else model.curves.iloc[0:0]
        axes.plot(curves["step"], curves["val_ssim"], marker=".", label=f"{variant} ({json.dumps(model.spec.loss)})")
    axes.set_xlabel("training step")
    axes.set_ylabel("validation SSIM")
    axes.set_title("RAE loss ablation (Chaitanya et al. 2017, §4.4)")
    axes.grid(True, alpha=0.3)
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_training_curves(models: TrainedModels, path: Path) -> None:
    """Training and validation loss of the models that are not ablation variants."""
    from denoisers.report import _pyplot, placeholder

    main = [m for m in models.models.values() if not m.spec.ablation]
    if not main:
        placeholder(path, "no model was trained")
        return
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for model in main:
        train = model.curves.dropna(subset=["train_loss"])
        line, = axes.plot(train["step"], _smoothed(train["train_loss"], 5), label=f"{model.spec.id} training")
        if "val_loss" in model.curves:
            val = model.curves.dropna(subset=["val_loss"])
            axes.plot(val["step"], val["val_loss"], marker="o", linestyle="--", color=line.get_color(),
                      label=f"{model.spec.id} validation")
    axes.set_yscale("log")
    axes.set_xlabel("training step")
    axes.set_ylabel("loss")
    axes.set_title("Training curves")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
