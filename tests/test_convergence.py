"""The report's convergence check: a model whose best validation loss still falls over the last part of its
run is under-trained, and every claim using it says so (issue: learned denoisers that learn on two cores)."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from denoisers.report.claims import UNDERTRAINED_NOTE, claims_table
from denoisers.report.trained import TrainedModel, TrainedModels
from denoisers.report.training_tables import training_table
from denoisers.reproductions import all_claims
from denoisers.training.models import model_specs
from tests.test_claims import CLEAR, claims_config, results_for

STEPS = 1000


def curves(val_loss: list[float], every: int = 100) -> pd.DataFrame:
    """Training curves validated every ``every`` steps from step ``every`` on (train loss at every step)."""
    steps = np.arange(1, STEPS + 1)
    val = np.full(STEPS, np.nan)
    for k, value in enumerate(val_loss):
        val[(k + 1) * every - 1] = value
    return pd.DataFrame({"step": steps, "train_loss": 1.0, "val_loss": val})


def trained(cfg: dict, model_id: str, val_loss: list[float]) -> TrainedModel:
    spec = next(s for s in model_specs(cfg) if s.id == model_id)
    return TrainedModel(spec, {"steps": STEPS, "parameters": 10}, curves(val_loss),
                        pd.DataFrame({"loss": [min(val_loss)], "psnr": [20.0]}))


# Validations at steps 100..1000; the window is the last 20 %: steps after 800.
FLAT = [1.0, 0.6, 0.5, 0.45, 0.44, 0.43, 0.43, 0.43, 0.429, 0.4289]       # best 0.43 by 800, 0.4289 after
FALLING = [1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.40, 0.35, 0.30]          # 0.40 by 800, 0.30 after: 25 %


@pytest.mark.parametrize("val_loss, fall", [(FLAT, (0.43 - 0.4289) / 0.43), (FALLING, 0.25)])
def test_the_fall_of_the_best_validation_loss_over_the_window(val_loss: list[float], fall: float) -> None:
    model = trained(claims_config(), "rae", val_loss)
    assert model.validation_improvement(0.2) == pytest.approx(fall)


def test_under_trained_models_are_flagged_in_the_table_and_in_every_claim_using_them() -> None:
    cfg = claims_config()
    res = results_for("C1.1", CLEAR, cfg=cfg)
    res.models = TrainedModels(model_specs(cfg))
    for spec in res.models.specs:
        res.models.models[spec.id] = trained(cfg, spec.id, FLAT)
    res.models.models["rae"] = trained(cfg, "rae", FALLING)
    assert "rae under-trained: best validation loss fell 25.0% over the last 20% of its 1000 steps" in res.flag("rae", 1)
    assert res.flag("eaw", 1) == "" and res.flag("rae_inputs_all", 1) == ""
    table = training_table(res.models, cfg).set_index("model")
    assert table.loc["rae", "converged"] == "no (under-trained)" and table.loc["rae_inputs_all", "converged"] == "yes"
    claims = claims_table(res, all_claims()).set_index("claim")
    # C1.1 compares the RAE with EAW: the note says the verdict tests the budget; C4.1s (wRLS vs SVGF) does not.
    assert claims.loc["C1.1", "note"].startswith(UNDERTRAINED_NOTE) and "under-trained" in claims.loc["C1.1", "flags"]
    assert UNDERTRAINED_NOTE not in claims.loc["C4.1s", "note"]
    # A stricter threshold than the fall of FLAT flags it too; with no validation before the window: unknown.
    cfg["training"]["convergence"] = {"window_fraction": 0.2, "min_improvement": 0.001}
    assert "under-trained" in res.models.models["rae_inputs_all"].undertrained(cfg)
    late = trained(cfg, "rae", [math.nan] * 9 + [0.5])
    assert "convergence unknown" in late.undertrained(cfg)


# Best 0.40 at step 400, then the run blows up and settles at 1.6: its last validation is 300 % above the best.
DIVERGED = [1.0, 0.6, 0.5, 0.40, 1.9, 1.8, 1.7, 1.6, 1.6, 1.6]


def test_a_diverged_run_is_under_trained_although_its_best_no_longer_falls() -> None:
    cfg = claims_config()
    model = trained(cfg, "rae", DIVERGED)
    # The window rule alone would call it converged: the best (step 400) lies before the window.
    assert model.validation_improvement(0.2) == 0.0
    assert model.final_rise() == (pytest.approx(3.0), 400)
    reason = model.undertrained(cfg)
    assert "under-trained" in reason and "diverged" in reason and "step 400 of 1000" in reason
    assert _converged_column(cfg, model) == "no (under-trained)"
    # A rise within the stated threshold (FLAT ends at its best) is not divergence.
    assert trained(cfg, "rae", FLAT).final_rise()[0] == pytest.approx(0.0)
    cfg["training"]["convergence"] = {"max_final_rise": 3.5}
    assert model.undertrained(cfg) == ""


def test_a_run_stopped_by_its_time_cap_is_under_trained_and_its_claims_say_so() -> None:
    cfg = claims_config()
    res = results_for("C1.1", CLEAR, cfg=cfg)
    res.models = TrainedModels(model_specs(cfg))
    for spec in res.models.specs:
        res.models.models[spec.id] = trained(cfg, spec.id, FLAT)
    capped = res.models.models["rae"] = trained(cfg, "rae", [1.0, 0.5, 0.43, 0.43, 0.43, 0.43, 0.43, 0.43, 0.43, 0.43])
    capped.summary.update({"steps": 700, "max_steps": STEPS, "max_seconds": 3600, "stopped_by": "max_seconds"})
    capped.curves = capped.curves[capped.curves.step <= 700]
    assert "stopped by its time cap (max_seconds 3600) at 700 of 1000 steps" in res.flag("rae", 1)
    claims = claims_table(res, all_claims()).set_index("claim")
    assert claims.loc["C1.1", "note"].startswith(UNDERTRAINED_NOTE)
    # The same curves stopped by the step budget are not flagged.
    capped.summary.update({"stopped_by": "max_steps", "max_steps": 700})
    assert res.flag("rae", 1) == ""


def _converged_column(cfg: dict, model: TrainedModel) -> str:
    models = TrainedModels(model_specs(cfg))
    models.models[model.spec.id] = model
    return training_table(models, cfg).set_index("model").loc[model.spec.id, "converged"]


def test_step_minutes_leave_out_pauses_and_validations() -> None:
    """Logged every 10 steps at 0.5 s/step; a validation adds 20 s to the rows that end with it and a 600-s stop
    of the run falls into one interval: the median step time stays 0.5 s, the elapsed time does not."""
    steps = np.arange(10, 1010, 10)
    elapsed = steps * 0.5 + 20.0 * (steps // 100) + np.where(steps >= 450, 600.0, 0.0)
    val = np.where(steps % 100 == 0, 0.5, np.nan)
    frame = pd.DataFrame({"step": steps, "elapsed_s": elapsed, "train_loss": 1.0, "val_loss": val})
    cfg = claims_config()
    spec = next(s for s in model_specs(cfg) if s.id == "rae")
    model = TrainedModel(spec, {"steps": 1000, "elapsed_seconds": float(elapsed[-1])}, frame,
                         pd.DataFrame({"loss": [0.5]}))
    assert model.median_step_seconds() == pytest.approx(0.5)
    models = TrainedModels([spec], {"rae": model})
    row = training_table(models, cfg).iloc[0]
    assert row["step_minutes"] == pytest.approx(1000 * 0.5 / 60)
    assert row["train_minutes"] == pytest.approx(float(elapsed[-1]) / 60) and row["train_minutes"] > 20
    assert row["precision"] == "" and row["cpu"] == ""          # a summary without compute / provenance records
    recorded = TrainedModel(spec, {"steps": 1000, "compute": {"precision": "bf16", "configured": "auto"},
                                   "provenance": {"cpu_model": "Intel(R) Xeon(R) Processor"}}, frame, pd.DataFrame())
    row = training_table(TrainedModels([spec], {"rae": recorded}), cfg).iloc[0]
    assert (row["precision"], row["cpu"]) == ("bf16", "Intel(R) Xeon(R) Processor")
    no_times = TrainedModel(spec, {"steps": 1000}, frame.drop(columns=["elapsed_s"]), pd.DataFrame())
    assert math.isnan(no_times.median_step_seconds())


def test_the_line_fit_beside_the_flag_reads_a_steady_fall_exactly_and_a_flat_noisy_curve_as_about_zero() -> None:
    """The trend column against scipy.stats.linregress done by hand and an exact line; not part of the rule."""
    from scipy import stats

    cfg = claims_config()
    # FALLING is a straight line from step 300 on (0.05 per 100 steps): over the window (steps 800-1000) the
    # line falls 0.10, relative to the window's mean loss 0.35, with a zero-width interval.
    fall, half = trained(cfg, "rae", FALLING).validation_trend(0.2)
    assert fall == pytest.approx(0.10 / 0.35) and half == pytest.approx(0.0, abs=1e-9)
    # A flat curve with alternating noise: the running minimum falls (flag), the line's interval holds 0.
    noisy = [1.0, 0.5, 0.44, 0.45, 0.44, 0.45, 0.44, 0.45, 0.435, 0.45]
    model = trained(cfg, "rae", noisy)
    assert model.validation_improvement(0.2) == pytest.approx((0.44 - 0.435) / 0.44)
    fall, half = model.validation_trend(0.2)
    window = np.array([0.45, 0.435, 0.45])      # steps 800, 900, 1000
    fit = stats.linregress([800.0, 900.0, 1000.0], window)
    assert fall == pytest.approx(-fit.slope * 200 / window.mean())
    assert half == pytest.approx(stats.t.ppf(0.975, 1) * fit.stderr * 200 / window.mean())
    assert fall - half < 0 < fall + half
    # Too few validations in the window for an interval.
    assert math.isnan(trained(cfg, "rae", FALLING).validation_trend(0.05)[0])


def test_the_validation_psnr_gained_over_the_window() -> None:
    cfg = claims_config()
    model = trained(cfg, "rae", FALLING)
    model.curves["val_psnr"] = np.where(model.curves["val_loss"].notna(), 20.0 + model.curves["step"] / 1000.0,
                                        np.nan)
    assert model.validation_psnr_gain(0.2) == pytest.approx(1.0 - 0.8)     # best 21.0 at 1000, 20.8 at 800
    table = training_table(_models_of(cfg, model), cfg).set_index("model")
    assert table.loc["rae", "val_psnr_gain_in_window"] == pytest.approx(0.2)
    assert table.loc["rae", "val_loss_trend_in_window"] == pytest.approx(0.10 / 0.35)
    del model.curves["val_psnr"]
    assert math.isnan(model.validation_psnr_gain(0.2))


def _models_of(cfg: dict, model: TrainedModel) -> TrainedModels:
    models = TrainedModels(model_specs(cfg))
    models.models[model.spec.id] = model
    return models


def _crop_check(gaps: dict[str, float]) -> dict:
    return {"crop": 64, "spp": 4, "frames_per_scene": 4, "gap_db": min(gaps.values()),
            "scenes": {scene: {"whole_psnr": 30.0, "window_psnr": 30.0 - gap, "gap_db": gap,
                               "worst_window_gap_db": gap - 1.0} for scene, gap in gaps.items()}}


def test_a_model_worse_on_whole_frames_than_on_its_crops_is_flagged() -> None:
    cfg = claims_config()
    model = trained(cfg, "rae", FLAT)
    model.summary["crop_check"] = _crop_check({"train_024": 0.4, "train_025": -2.94})
    reason = model.undertrained(cfg)
    assert "under-trained" in reason and "2.9 dB below their 64-pixel windows (train_025" in reason
    assert _converged_column(cfg, model) == "no (under-trained)"
    # Within the threshold, skipped, or absent (models trained before the check): no flag.
    model.summary["crop_check"] = _crop_check({"train_024": 0.4, "train_025": -0.38})
    assert model.undertrained(cfg) == ""
    model.summary["crop_check"] = {"skipped": "trained on whole frames"}
    assert model.undertrained(cfg) == ""
    del model.summary["crop_check"]
    assert model.undertrained(cfg) == ""
