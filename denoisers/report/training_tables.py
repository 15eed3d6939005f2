"""The trained models' tables: tables/training.csv (size, budget, convergence and cost of every configured model)
and tables/training_speed.csv (the rule time_training record)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from denoisers.report.trained import TrainedModels

if TYPE_CHECKING:
    import pandas as pd


def converged_text(reason: str) -> str:
    """The `converged` cell for a model's under-trained reason (empty: none; unknown: not checked)."""
    return "no (under-trained)" if "under-trained" in reason else "unknown" if reason else "yes"


def _doubling_gain(curves: pd.DataFrame) -> float:
    """Validation-PSNR gain (dB) of doubling the model's budget, from a power law fitted to its validation
    curve (denoisers.report.budget); NaN without val_psnr."""
    from denoisers.report.budget import doubling_gain

    if "val_psnr" not in curves or "step" not in curves:
        return math.nan
    val = curves.dropna(subset=["val_psnr"])
    return doubling_gain(val["step"].to_numpy(), val["val_psnr"].to_numpy())


def shares_run(twin_curves: pd.DataFrame, full_curves: pd.DataFrame) -> bool:
    """Whether a half-budget twin's logged curve (curves.csv: step, train_loss) is the head of its full model's,
    i.e. the twin was published from the full model's run rather than trained on its own."""
    columns = ["step", "train_loss"]
    if any(c not in twin_curves or c not in full_curves for c in columns) or not 0 < len(twin_curves) <= len(full_curves):
        return False
    return twin_curves[columns].reset_index(drop=True).equals(
        full_curves[columns].iloc[:len(twin_curves)].reset_index(drop=True))


def training_table(models: TrainedModels, cfg: dict | None = None) -> pd.DataFrame:
    """One row per configured model: size, budget used, validation metrics of best.pt and convergence (the
    relative fall of the best validation loss over the last part of the run, training.convergence, which
    decides; beside it the line fit's fall with its 95 % half-width, the validation PSNR gained there and the gain
    a doubled budget would bring by a power law fitted to the validation curve, denoisers.report.budget), and
    whole_frame_gap_db: whole validation frames minus crop-sized windows of them, lowest scene (NaN: not checked;
    denoisers.crop_check). ``run_of``: for a half-budget twin published from its full model's run
    (:func:`shares_run`), that model's id (its time is part of that run's), else empty."""
    import pandas as pd

    from denoisers.training.models import half_of

    rule = {"window_fraction": 0.2, "min_improvement": 0.01, **((cfg or {}).get("training", {}).get("convergence", {}))}

    rows = []
    for spec in models.specs:
        model = models.models.get(spec.id)
        row: dict[str, Any] = {"model": spec.id, "method": spec.method, "ablation": spec.ablation or "",
                               "variant": spec.variant or "", "status": "trained" if model else "not trained"}
        if model:
            s = model.summary
            validation = model.validation
            trend, trend_half = model.validation_trend(rule["window_fraction"])
            if s.get("same_training_as"):   # the base's weights, not a training of its own (its time is the base's)
                row["status"] = f"trained = {s['same_training_as']}"
            full = half_of(cfg, spec.id) if cfg else None
            row["run_of"] = (full if full in models.models and shares_run(model.curves, models.models[full].curves)
                             else "")
            row.update({"parameters": s.get("parameters"), "parameters_full_width": s.get("parameters_full_width"),
                        "width": s.get("net", {}).get("config", {}).get("width"),
                        "steps": s.get("steps"), "stopped_by": s.get("stopped_by"),
                        "train_minutes": s.get("elapsed_seconds", math.nan) / 60.0,
                        "step_minutes": model.median_step_seconds() * (s.get("steps") or math.nan) / 60.0,
                        "seconds_per_step": s.get("seconds_per_step"), "best_step": s.get("best_step"),
                        "final_train_loss": model.final_training_loss(),
                        "val_loss_fall_in_window": model.validation_improvement(rule["window_fraction"]),
                        "val_loss_trend_in_window": trend,
                        "val_loss_trend_ci95": trend_half,
                        "val_psnr_gain_in_window": model.validation_psnr_gain(rule["window_fraction"]),
                        "val_psnr_gain_if_doubled": _doubling_gain(model.curves),
                        "converged": converged_text(model.undertrained(cfg or {})),
                        "whole_frame_gap_db": (s.get("crop_check") or {}).get("gap_db", math.nan),
                        # Seeds may mix step arithmetic (bf16 autocast on CPUs that have it, else fp32): shown per model.
                        "precision": (s.get("compute") or {}).get("precision", ""),
                        "cpu": s.get("provenance", {}).get("cpu_model", ""),
                        "commit": (s.get("provenance", {}).get("commit") or "")[:12],
                        "dirty": s.get("provenance", {}).get("dirty"),
                        **{f"val_{k}": float(validation[k].mean()) for k in ("loss", "ssim", "psnr", "rmse")
                           if k in validation}})
        rows.append(row)
    return pd.DataFrame(rows)


#: Columns of tables/training_speed.csv (the rule time_training record, one row per model and variant).
TRAINING_SPEED_COLUMNS: tuple[str, ...] = (
    "model", "variant", "label", "configured", "status", "rounds", "ms_per_step", "ms_per_step_min",
    "ms_per_step_max", "mpix_per_s", "gflops_per_s", "fraction_of_sgemm", "speedup", "speedup_min", "speedup_max",
    "note")


def training_speed_table(record: dict[str, Any]) -> pd.DataFrame:
    """One row per model and variant of the training-speed record: ms/step (median, min, max over rounds),
    training Mpix/s (pixels per step / median), GFLOP/s and its fraction of the same-run sgemm, speed-up over
    fp32 NCHW (median, min, max of the per-round ratios); NaN where a variant was not timed (``note``)."""
    import pandas as pd

    rows = []
    for model in record["models"]:
        for v in model["variants"]:
            timed = v["status"] == "timed"

            def value(key: str, scale: float = 1.0, v: dict = v, timed: bool = timed) -> float:
                return float(v[key]) * scale if timed and v.get(key) is not None else math.nan

            rows.append({"model": model["model"], "variant": v["variant"], "label": v["label"],
                         "configured": bool(v["configured"]), "status": v["status"], "rounds": v["rounds"],
                         "ms_per_step": value("ms_per_step_median"), "ms_per_step_min": value("ms_per_step_min"),
                         "ms_per_step_max": value("ms_per_step_max"), "mpix_per_s": value("pixels_per_s", 1e-6),
                         "gflops_per_s": value("gflops_per_s"), "fraction_of_sgemm": value("fraction_of_sgemm"),
                         "speedup": value("speedup_median"), "speedup_min": value("speedup_min"),
                         "speedup_max": value("speedup_max"), "note": v.get("note", "")})
    return pd.DataFrame(rows, columns=list(TRAINING_SPEED_COLUMNS))


def training_speed_markdown(table: pd.DataFrame) -> str:
    """The table as REPORT.md shows it: ms/step median [min, max], Mpix/s, GFLOP/s, of sgemm, speed-up median
    [min, max] (x), the configured variant marked *."""
    import pandas as pd

    from denoisers.report.stats import frame_to_markdown

    def cell(row: Any, key: str, digits: int, unit: str = "") -> str:
        median, low, high = (getattr(row, name) for name in (key, f"{key}_min", f"{key}_max"))
        return f"{median:.{digits}f}{unit} [{low:.{digits}f}, {high:.{digits}f}]" if row.status == "timed" else ""

    shown = [{"model": row.model, "step": f"{row.label}{' *' if row.configured else ''}",
              "ms/step": cell(row, "ms_per_step", 1) or f"not timed: {row.note}",
              "Mpix/s": f"{row.mpix_per_s:.3f}" if row.status == "timed" else "",
              "GFLOP/s": f"{row.gflops_per_s:.1f}" if row.status == "timed" else "",
              "of sgemm": f"{row.fraction_of_sgemm:.1%}" if row.status == "timed" else "",
              "speed-up vs fp32 NCHW": cell(row, "speedup", 2, "x"), "rounds": row.rounds}
             for row in table.itertuples()]
    return frame_to_markdown(pd.DataFrame(shown))


def training_speed_verdict(record: dict[str, Any]) -> str:
    """Per model one sentence: the configured step's speed-up over the fp32 eager step against issue 11's
    target, and why not when precision auto resolved to fp32 (the resolved reason)."""
    target, sentences = record["target_speedup"], []
    for model in record["models"]:
        by_key = {v["variant"]: v for v in model["variants"]}
        v, compute = by_key[model["configured_variant"]], model["compute"]
        met = v["speedup_median"] >= target
        text = (f"Model {model['model']}: the configured step ({v['label']}, precision {compute['configured']}) ran "
                f"at {v['speedup_median']:.2f}x the fp32 eager (NCHW) step (median over {v['rounds']} rounds, range "
                f"{v['speedup_min']:.2f}-{v['speedup_max']:.2f}x), so issue 11's {target:g}x target is "
                f"{'met' if met else 'not met'}")
        reason = compute["reason"].removeprefix("auto: ")
        if not met and compute["precision"] == "fp32":
            why = (f"precision auto resolved to fp32 ({reason})" if compute["configured"] == "auto"
                   else "the config sets precision fp32")
            text += f": {why}, so the bf16 step that gives the speed-up on CPUs with native bf16 is not used"
            bf16 = [b for b in model["variants"] if b["precision"] == "bf16" and b["status"] == "timed"]
            if bf16:
                best = max(bf16, key=lambda b: b["speedup_median"])
                emulated = "" if record["cpu"]["native_bf16"] else ", where bf16 is emulated,"
                text += f"; here{emulated} the faster bf16 variant ({best['label']}) ran at {best['speedup_median']:.2f}x"
        elif not met:
            text += f" ({reason})"
        sentences.append(text + ".")
    return " ".join(sentences)
