"""The trained models of a run as the report reads them (rule train_denoiser's folders: summary.json, curves.csv,
validation.csv): training loss, step time, validation trends, and the flags (under-trained, diverged, stopped by its
time cap, crop borders learned) shown beside every row that uses a model.

Every summary read is checked against the model's settings digest (denoisers.experiment.Lineage.model) through the
caller's DigestLedger.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.experiment import DIGEST_KEY, DigestLedger, Lineage
from denoisers.training.models import ModelSpec, half_budget_specs, model_dir, model_specs, seed_replicas

if TYPE_CHECKING:
    import pandas as pd

#: Fraction of logged training steps whose mean is a model's final training loss.
FINAL_FRACTION = 0.2
#: A row whose model trained fewer steps is flagged (e.g. the smoke config's few-step models): its
#: numbers test the budget, not the method.
MIN_TRAINING_STEPS = 100
#: A model whose whole validation frames score this many dB below crop-sized windows of them (summary
#: crop_check) is flagged. On the 2026-12-03 Isik models the sound ones lay above -0.4 dB, those that had
#: learned their 64-pixel crops' borders at -1.0 to -2.9 (docs/findings.md).
CROP_GAP_DB = 1.0


@dataclass
class TrainedModel:
    """A complete model directory: summary.json, curves.csv (per logged step), validation.csv (per sequence)."""

    spec: ModelSpec
    summary: dict[str, Any]
    curves: pd.DataFrame
    validation: pd.DataFrame

    def final_training_loss(self) -> float:
        """Mean train_loss over the last FINAL_FRACTION of the logged steps."""
        rows = self.curves.dropna(subset=["train_loss"]) if "train_loss" in self.curves else self.curves.iloc[0:0]
        if not len(rows):
            return math.nan
        tail = max(1, int(math.ceil(len(rows) * FINAL_FRACTION)))
        return float(rows["train_loss"].iloc[-tail:].mean())

    def median_step_seconds(self) -> float:
        """Median seconds per step between consecutive logged rows of curves.csv without validation (a
        stretch in which the job was stopped or a validation ran is one outlier among many; NaN if unknown)."""
        if not {"step", "elapsed_s"} <= set(self.curves):
            return math.nan
        rows = self.curves[["step", "elapsed_s"]].assign(
            validated=self.curves["val_loss"].notna() if "val_loss" in self.curves else False)
        steps, seconds = rows["step"].diff(), rows["elapsed_s"].diff()
        clean = (steps > 0) & ~rows["validated"] & ~rows["validated"].shift(1, fill_value=True)
        rates = (seconds[clean] / steps[clean]).dropna()
        return float(rates.median()) if len(rates) else math.nan

    def validation_improvement(self, window_fraction: float) -> float:
        """Relative fall of the best validation loss over the last ``window_fraction`` of the steps run:
        (best before the window - best overall) / best before the window; NaN when no validation lies
        before the window (too few validations to tell)."""
        if "val_loss" not in self.curves:
            return math.nan
        val, start = self._window_validations(window_fraction)
        before = val[val["step"] <= start]["val_loss"]
        if not len(before) or not len(val):
            return math.nan
        best_before, best = float(before.min()), float(val["val_loss"].min())
        return (best_before - best) / best_before if best_before > 0 else math.nan

    def _window_validations(self, window_fraction: float) -> tuple[pd.DataFrame, float]:
        """(validated rows of curves.csv, first step of the last ``window_fraction`` of the steps run)."""
        val = self.curves.dropna(subset=["val_loss"]) if "val_loss" in self.curves else self.curves.iloc[0:0]
        return val, int(self.summary.get("steps") or 0) * (1.0 - window_fraction)

    def validation_trend(self, window_fraction: float) -> tuple[float, float]:
        """(relative fall, its 95 % half-width) of a least-squares line through the validation losses of the last
        ``window_fraction`` of the steps: (line at the window's start - line at its end) / the window's mean loss,
        so a steady fall reads the same as validation_improvement and a flat noisy curve reads about 0. Shown
        beside the flag, which reads the running minimum: on a noisy curve the minimum keeps falling while the
        line does not. NaN for fewer than 3 validations in the window (no interval)."""
        from scipy import stats

        val, start = self._window_validations(window_fraction)
        window = val[val["step"] >= start]
        if len(window) < 3:
            return math.nan, math.nan
        steps, loss = window["step"].to_numpy(float), window["val_loss"].to_numpy(float)
        fit = stats.linregress(steps, loss)
        span = float(self.summary.get("steps") or steps[-1]) - start
        scale = span / float(loss.mean())
        half = float(stats.t.ppf(0.975, len(window) - 2)) * fit.stderr * scale
        return -fit.slope * scale, half

    def validation_psnr_gain(self, window_fraction: float) -> float:
        """Best validation PSNR (dB, curves.csv val_psnr) over the whole run minus the best before the last
        ``window_fraction`` of the steps: what the last part of the budget bought in the metric the claims test.
        NaN without val_psnr or without a validation before the window."""
        val, start = self._window_validations(window_fraction)
        if "val_psnr" not in val:
            return math.nan
        psnr = val.dropna(subset=["val_psnr"])
        before = psnr[psnr["step"] <= start]["val_psnr"]
        if not len(before):
            return math.nan
        return float(psnr["val_psnr"].max()) - float(before.max())

    def final_rise(self) -> tuple[float, int | None]:
        """(relative rise of the last validation loss above the best one, step of the best); (NaN, None)
        without validation."""
        if "val_loss" not in self.curves:
            return math.nan, None
        val = self.curves.dropna(subset=["val_loss"])
        if not len(val):
            return math.nan, None
        best = val.loc[val["val_loss"].idxmin()]
        last = float(val["val_loss"].iloc[-1])
        return ((last - float(best["val_loss"])) / float(best["val_loss"]) if best["val_loss"] > 0 else math.nan,
                int(best["step"]))

    def undertrained(self, cfg: dict) -> str:
        """'' or why the model counts as under-trained (training.convergence): stopped by its time cap before
        its step budget, diverged (its last validation loss far above its best, so best.pt is an early model),
        or its best validation loss still falling over the last part of the run."""
        rule = {"window_fraction": 0.2, "min_improvement": 0.01, "max_final_rise": 0.1,
                **cfg.get("training", {}).get("convergence", {})}
        steps, max_steps = self.summary.get("steps"), self.summary.get("max_steps")
        reasons = []
        if self.summary.get("stopped_by") == "max_seconds" and steps is not None and max_steps is not None:
            reasons.append(f"stopped by its time cap (max_seconds {self.summary.get('max_seconds')}) at {steps} of "
                           f"{max_steps} steps")
        rise, best_step = self.final_rise()
        if not math.isnan(rise) and rise > rule["max_final_rise"]:
            reasons.append(f"training diverged: the last validation loss is {rise:.0%} above the best, which "
                           f"best.pt keeps from step {best_step} of {steps} (threshold {rule['max_final_rise']:.0%})")
        fall = self.validation_improvement(rule["window_fraction"])
        window = f"the last {rule['window_fraction']:.0%} of its {steps} steps"
        if fall > rule["min_improvement"]:
            reasons.append(f"best validation loss fell {fall:.1%} over {window} "
                           f"(threshold {rule['min_improvement']:.1%})")
        crop_gap = self.crop_gap_reason()
        if crop_gap:
            reasons.append(crop_gap)
        if reasons:
            return f"model {self.spec.id} under-trained: " + "; ".join(reasons)
        if math.isnan(fall):
            return f"model {self.spec.id} convergence unknown: no validation before {window}"
        return ""

    def crop_gap_reason(self) -> str:
        """'' or how much worse best.pt is on whole validation frames than on windows of its training crop's
        size (summary crop_check, denoisers.crop_check): below -CROP_GAP_DB it learned the crops' borders."""
        check = self.summary.get("crop_check") or {}
        scenes = check.get("scenes") or {}
        gap = check.get("gap_db")
        if not scenes or gap is None or not gap < -CROP_GAP_DB:
            return ""
        worst = min(scenes, key=lambda scene: scenes[scene]["gap_db"])
        return (f"whole validation frames score {-gap:.1f} dB below their {check['crop']}-pixel windows "
                f"({worst}, threshold {CROP_GAP_DB:.1f} dB): it learned its training crops' borders")

    def describe(self) -> str:
        s = self.summary
        width = s.get("net", {}).get("config", {}).get("width")
        width_text = f"width {width:g}, " if isinstance(width, (int, float)) else ""
        return (f"{self.spec.id}: {width_text}{s.get('parameters', 0):,} parameters, {s.get('steps')} steps "
                f"({s.get('elapsed_seconds', 0) / 60:.0f} min) on {len(s.get('train_scenes', []))} scenes")


@dataclass
class TrainedModels:
    specs: list[ModelSpec]
    models: dict[str, TrainedModel] = field(default_factory=dict)   # models whose directory is complete
    replicas: frozenset[str] = frozenset()   # ids of seed replicas ({id}_seed{k}) and half-budget twins ({id}_half)

    def variants(self, ablation: str) -> dict[str, TrainedModel]:
        """variant id -> the first seed's model of each trained variant of ``ablation``."""
        return {m.spec.variant: m for m in self.models.values()
                if m.spec.ablation == ablation and m.spec.id not in self.replicas}

    @property
    def missing(self) -> list[str]:
        return [spec.id for spec in self.specs if spec.id not in self.models]


def collect_models(cfg: dict, results_dir: Path, ledger: DigestLedger | None = None) -> TrainedModels:
    """Every configured model whose directory holds summary.json, curves.csv and validation.csv; their
    settings digests go to ``ledger``."""
    import pandas as pd

    secondary = seed_replicas(cfg) + half_budget_specs(cfg)
    found = TrainedModels(model_specs(cfg) + secondary, replicas=frozenset(spec.id for spec in secondary))
    lineage = Lineage(cfg)
    for spec in found.specs:
        folder = model_dir(results_dir, spec.id)
        files = [folder / name for name in ("summary.json", "curves.csv", "validation.csv")]
        if all(path.is_file() for path in files):
            summary = json.loads(files[0].read_text())
            if ledger is not None:
                ledger.add(files[0], summary.get(DIGEST_KEY), lineage.model(spec.id))
            found.models[spec.id] = TrainedModel(spec, summary, pd.read_csv(files[1]), pd.read_csv(files[2]))
    return found
