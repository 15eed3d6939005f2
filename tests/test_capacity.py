"""Capacity ablations (training.ablations with kind: capacity): config validation, the timing job's rows and the
report's table, selection rule, statement and chart (denoisers/report/capacity.py) on hand-made results."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from denoisers.evaluate import evaluation_problems, method_specs
from denoisers.report import report_outputs
from denoisers.report.capacity import (capacity_section, capacity_table, output_name, select_smallest,
                                       selection_statement)
from denoisers.report.collect import Results
from denoisers.report.trained import TrainedModel, TrainedModels
from denoisers.jobs.timing import TimingJob, timed_runs
from denoisers.training.models import capacity_model_ids, model_specs, training_problems
from scenegen.config import ConfigError, validate_config
from tests.test_evaluate import smoke_config as _smoke_config

def smoke_config(**evaluation) -> dict:
    """The smoke config with its RAE capacity sweep only (these tests build results for the RAE sizes)."""
    cfg = _smoke_config(**evaluation)
    cfg["training"]["ablations"] = [a for a in cfg["training"]["ablations"] if a["id"] != "ntasd_capacity"]
    return validate_config(cfg)


SCENES = ("test_000", "test_001", "test_002")
#: Per size: per-scene test PSNR, parameters, ms/frame. The base rae (width 0.25) is one of the sizes.
PSNR = {"rae": [30.0, 31.0, 29.0], "rae_capacity_width0125": [29.5, 30.6, 28.3],
        "rae_capacity_width05": [30.1, 31.2, 29.2], "rae_capacity_levels4": [30.0, 30.9, 29.1]}
PARAMETERS = {"rae": 121_855, "rae_capacity_width0125": 30_930, "rae_capacity_width05": 490_489,
              "rae_capacity_levels4": 70_000}
#: Per size: PSNR per validation sequence (validation.csv of best.pt), what the selection uses. Best: width05
#: (25.15); within 0.2 dB: rae and levels4 (25.0); levels4 has the fewest parameters among them.
VAL_PSNR = {"rae": [25.0, 26.0, 24.0, 25.0], "rae_capacity_width0125": [24.5, 25.5, 23.5, 24.5],
            "rae_capacity_width05": [25.2, 26.1, 24.2, 25.1], "rae_capacity_levels4": [25.1, 25.9, 24.1, 24.9]}
MS = {"rae": 4.0, "rae_capacity_width0125": 2.0, "rae_capacity_width05": 9.0, "rae_capacity_levels4": 3.5}
VARIANTS = [{"id": "width0125", "net": {"width": 0.125}}, {"id": "width05", "net": {"width": 0.5}},
            {"id": "levels4", "net": {"levels": 4}}]


def capacity_config(**evaluation) -> dict:
    """The smoke config (3 test scenes) whose capacity ablation has three sizes beside the base rae (width 0.25)."""
    cfg = smoke_config(**{"ablation_spp": [1], **evaluation})
    cfg["scenes"]["n_test"] = len(SCENES)
    ablation = next(a for a in cfg["training"]["ablations"] if a["id"] == "rae_capacity")
    ablation["variants"] = copy.deepcopy(VARIANTS)
    return validate_config(cfg)


def trained(spec, converged: bool = True) -> TrainedModel:
    """A complete model directory's contents: 4 steps, validation every step (flat, or still falling)."""
    val = [1.0, 1.0, 1.0, 1.0] if converged else [1.0, 0.9, 0.8, 0.5]
    curves = pd.DataFrame({"step": [1, 2, 3, 4], "train_loss": [1.0] * 4, "val_loss": val})
    levels = spec.net.get("levels", 5)
    summary = {"steps": 4, "stopped_by": "max_steps", "parameters": PARAMETERS[spec.id],
               "net": {"name": "rae", "config": {"width": spec.net.get("width", 1.0), "levels": levels}}}
    validation = pd.DataFrame({"sequence": range(4), "loss": [1.0] * 4, "rmse": [0.1] * 4, "ssim": [0.9] * 4,
                               "psnr": VAL_PSNR[spec.id]})
    return TrainedModel(spec, summary, curves, validation)


def make_results(cfg: dict, *, missing: tuple[str, ...] = (), unconverged: tuple[str, ...] = (),
                 timing: bool = True, tmp: Path | None = None) -> Results:
    """Results with the sizes of PSNR evaluated at 1 spp (except ``missing``: not trained, not evaluated)."""
    specs = {spec.id: spec for spec in model_specs(cfg)}
    rows = [model for model in PSNR if model not in missing]
    per_scene = pd.DataFrame([{"method_id": model, "spp": 1, "scene": scene, "psnr": value}
                              for model in rows for scene, value in zip(SCENES, PSNR[model])])
    runs = [{"id": spec.id, "method": spec.method, "role": spec.role, "spp": spp,
             "status": "ran" if spec.id in rows and spp == 1 else "not run",
             "reason": "" if spec.id in rows and spp == 1 else "not run (results missing for test_000)"}
            for spec in method_specs(cfg) for spp in spec.spp]
    models = TrainedModels(list(specs.values()), {m: trained(specs[m], m not in unconverged) for m in rows})
    job = TimingJob({"rows": [{"method_id": m, "spp": 1, "ms_per_frame": MS[m], "ms_per_frame_min": 0.9 * MS[m],
                               "ms_per_frame_max": 1.2 * MS[m]} for m in rows], "renderers": {}, "threads": 2})
    return Results(cfg, method_specs(cfg), list(SCENES), runs, pd.DataFrame(), per_scene, results_dir=tmp or Path("."),
                   models=models, timing=job if timing else None)


def ablation_of(cfg: dict) -> dict:
    return next(a for a in cfg["training"]["ablations"] if a["id"] == "rae_capacity")


def t_interval(values: list[float]) -> tuple[float, float, float]:
    data = np.asarray(values)
    half = stats.t.ppf(0.975, len(data) - 1) * data.std(ddof=1) / math.sqrt(len(data))
    return data.mean(), data.mean() - half, data.mean() + half


# ------------------------------------------------------------------------------------------ selection rule
def test_the_smallest_size_within_two_tenths_of_a_db_of_the_best_is_selected() -> None:
    psnr = {"a": 30.0, "b": 30.25, "c": 30.05, "d": math.nan}
    params = {"a": 100.0, "b": 400.0, "c": 50.0, "d": 1.0}
    assert select_smallest(psnr, params) == "c"                       # c and b within 0.2 of 30.25; c is smaller
    assert select_smallest({**psnr, "c": 30.04}, params) == "b"       # 0.21 dB below the best: out
    assert select_smallest(psnr, params, tolerance=0.3) == "c"
    assert select_smallest({"a": 30.0, "b": 30.1}, {"a": 10.0, "b": 10.0}, {"a": 5.0, "b": 2.0}) == "b"  # tie: faster
    assert select_smallest({"a": 30.0, "b": 30.1}, {"a": math.nan, "b": 10.0}) == "b"   # unknown size: last resort
    assert select_smallest({"a": math.nan}, {"a": 1.0}) is None


# ------------------------------------------------------------------------------------------ report table
def test_the_table_has_every_size_with_hand_computed_values() -> None:
    cfg = capacity_config()
    table, note = capacity_table(make_results(cfg, unconverged=("rae_capacity_width05",)), ablation_of(cfg))
    assert note == ""                                                  # same budget: the base model is a size
    assert list(table["variant"]) == ["width0125", "width05", "levels4", "base"]
    assert list(table.columns[:5]) == ["variant", "model", "row", "width", "levels"]
    by = table.set_index("model")
    # net keys resolved: the spec's own value, else the trained model's recorded config.
    assert by.loc["rae", "width"] == 0.25 and by.loc["rae", "levels"] == 5
    assert by.loc["rae_capacity_levels4", "width"] == 0.25 and by.loc["rae_capacity_levels4", "levels"] == 4
    assert by.loc["rae", "row"] == "rae" and by.loc["rae_capacity_levels4", "row"] == "rae_capacity_levels4"
    for model, values in PSNR.items():
        mean, low, high = t_interval(values)
        assert by.loc[model, "psnr_mean"] == pytest.approx(mean)
        assert (by.loc[model, "psnr_ci_low"], by.loc[model, "psnr_ci_high"]) == pytest.approx((low, high))
        diff = t_interval(list(np.subtract(values, PSNR["rae_capacity_levels4"])))   # paired to the selected size
        assert (by.loc[model, "diff_to_selected_mean"], by.loc[model, "diff_to_selected_ci_low"],
                by.loc[model, "diff_to_selected_ci_high"]) == pytest.approx(diff, nan_ok=True)
        assert (by.loc[model, "val_psnr_mean"], by.loc[model, "val_psnr_ci_low"], by.loc[model, "val_psnr_ci_high"]) \
            == pytest.approx(t_interval(VAL_PSNR[model]))
        assert by.loc[model, "n_validation_sequences"] == 4
        assert by.loc[model, "parameters"] == PARAMETERS[model] and by.loc[model, "ms_per_frame"] == MS[model]
        assert by.loc[model, "n_scenes"] == 3 and by.loc[model, "spp"] == 1 and by.loc[model, "status"] == "ran"
    assert by.loc["rae_capacity_levels4", "diff_to_selected_mean"] == 0.0
    # Best validation PSNR 25.15 dB (width05): base and levels4 (25.0) are within 0.2 dB, width0125 (24.5) is not;
    # levels4 is smaller.
    assert list(table["best"]) == [False, True, False, False]
    assert list(table["within_tolerance"]) == [False, True, True, True]
    assert list(table["selected"]) == [False, False, True, False]
    assert list(table["converged"]) == ["yes", "no (under-trained)", "yes", "yes"]


def test_the_statement_names_the_selected_size_and_whether_the_default_matches() -> None:
    cfg = capacity_config()
    res = make_results(cfg)
    table, note = capacity_table(res, ablation_of(cfg))
    text = selection_statement(res, ablation_of(cfg), table, note)
    assert "`rae_capacity_levels4` (width 0.25, levels 4; 70,000 parameters)" in text
    assert "the best, `rae_capacity_width05`" in text
    assert "configured default `rae` (width 0.25, levels 5) does not match it" in text
    assert "validation PSNR" in text and "never chosen on test scenes" in text and "Caveats" not in text
    assert "25.00 dB against the best" in text or "25.0 dB against the best" in text, text
    res.models.models["rae_capacity_width05"].summary["stopped_by"] = "max_seconds"   # the time cap cut it short
    table, note = capacity_table(res, ablation_of(cfg))
    assert "stopped before the step budget (max_seconds): rae_capacity_width05" in \
        selection_statement(res, ablation_of(cfg), table, note)
    # Without levels4 the base model itself is the smallest adequate size.
    res = make_results(cfg, missing=("rae_capacity_levels4",))
    table, note = capacity_table(res, ablation_of(cfg))
    text = selection_statement(res, ablation_of(cfg), table, note)
    assert "Smallest size within 0.2 dB" in text and "`rae` (width 0.25, levels 5; 121,855 parameters)" in text
    assert "(width 0.25, levels 5) matches it." in text and "not run: rae_capacity_levels4" in text


def test_the_choice_ignores_test_psnr() -> None:
    """A default is chosen on validation sequences only: making width0125 the best on the test scenes changes the
    test columns, not the selection."""
    cfg = capacity_config()
    saved = PSNR["rae_capacity_width0125"]
    PSNR["rae_capacity_width0125"] = [40.0, 41.0, 39.0]
    try:
        table, _ = capacity_table(make_results(cfg), ablation_of(cfg))
    finally:
        PSNR["rae_capacity_width0125"] = saved
    assert list(table["selected"]) == [False, False, True, False]
    assert table.set_index("model").loc["rae_capacity_width0125", "psnr_mean"] == pytest.approx(40.0)


def test_section_writes_the_table_and_the_two_panel_chart(tmp_path: Path) -> None:
    cfg = capacity_config()
    (tmp_path / "tables").mkdir()
    (tmp_path / "figures").mkdir()
    lines = capacity_section(make_results(cfg), tmp_path / "tables", tmp_path / "figures")
    name = output_name("rae_capacity")
    assert name == "capacity_rae_capacity"
    chart = tmp_path / "figures" / f"{name}.png"
    assert chart.is_file() and chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and chart.stat().st_size > 5000
    written = pd.read_csv(tmp_path / "tables" / f"{name}.csv")
    assert written["selected"].tolist() == [False, False, True, False]
    markdown = (tmp_path / "tables" / f"{name}.md").read_text()
    assert "test PSNR − selected (paired)" in markdown and "validation PSNR" in markdown and "ms/frame (timing job)" in markdown and "490,489" in markdown
    assert "## Model capacity" in lines and any("does not match" in line for line in lines)
    expected = report_outputs(cfg, root="r")
    assert expected["capacity_tables"] == [f"r/tables/{name}.csv", f"r/tables/{name}.md"]
    assert expected["capacity_figures"] == [f"r/figures/{name}.png"]


def test_missing_sizes_and_timing_are_not_run_rows_not_errors(tmp_path: Path) -> None:
    cfg = capacity_config()
    res = make_results(cfg, missing=("rae_capacity_width05",), timing=False)
    table, _ = capacity_table(res, ablation_of(cfg))
    row = table.set_index("model").loc["rae_capacity_width05"]
    assert row["status"] == "not run" and math.isnan(row["psnr_mean"]) and math.isnan(row["parameters"])
    assert "not trained" in row["note"] and "results missing" in row["note"]
    assert row["width"] == 0.5 and row["levels"] == 5                # from the network's defaults, untrained
    ran = table[table["status"] == "ran"]
    assert ran["ms_per_frame"].isna().all()
    assert (ran["note"] == "not timed (the timing job's output is missing)").all()
    cfg["evaluation"]["timing"] = {"enabled": False}
    table, _ = capacity_table(make_results(cfg, timing=False), ablation_of(cfg))
    assert (table["note"] == "not timed (evaluation.timing.enabled is false)").all()
    # Variants not evaluated on the test scenes: every size "not run" there, but the choice (validation) stands.
    cfg = capacity_config(ablation_spp=[])
    res = make_results(cfg)
    table, note = capacity_table(res, ablation_of(cfg))
    assert (table["status"] == "not run").all() and list(table["selected"]) == [False, False, True, False]
    assert "evaluation.ablation_spp is empty" in table["note"].iloc[0] and table["psnr_mean"].isna().all()
    assert selection_statement(res, ablation_of(cfg), table, note).startswith("Smallest size within 0.2 dB")
    # No size trained: undecided, and a placeholder chart.
    res = make_results(cfg, missing=tuple(PSNR))
    table, note = capacity_table(res, ablation_of(cfg))
    assert not table["selected"].any()
    assert selection_statement(res, ablation_of(cfg), table, note).startswith("Not decided")
    (tmp_path / "t").mkdir()
    (tmp_path / "f").mkdir()
    capacity_section(res, tmp_path / "t", tmp_path / "f")
    assert (tmp_path / "f" / "capacity_rae_capacity.png").is_file()


def test_a_sweep_with_another_budget_leaves_the_base_model_out() -> None:
    cfg = capacity_config()
    ablation_of(cfg)["budget"] = {"max_steps": 2}
    res = make_results(cfg)
    table, note = capacity_table(res, ablation_of(cfg))
    assert "base" not in list(table["variant"]) and "trains 4 steps, the sweep 2" in note
    assert "Note: the base model rae is not one of the sizes" in selection_statement(res, ablation_of(cfg), table, note)


# ------------------------------------------------------------------------------------------ config
def test_kind_is_validated_by_the_schema_and_defaults_to_comparison() -> None:
    cfg = smoke_config()
    assert [a["kind"] for a in cfg["training"]["ablations"]] == ["comparison", "comparison", "capacity"]
    broken = copy.deepcopy(cfg)
    broken["training"]["ablations"][2]["kind"] = "size"
    with pytest.raises(ConfigError, match="capacity"):
        validate_config(broken)


@pytest.mark.parametrize("override", [{"loss": {"spatial": 1.0}}, {"data": {"crop": 16}}])
def test_a_capacity_variant_may_only_override_net(override: dict) -> None:
    cfg = smoke_config()
    assert training_problems(cfg) == []
    ablation_of(cfg)["variants"][0].update(override)
    problems = training_problems(cfg)
    key = next(iter(override))
    assert any("'rae_capacity' (kind capacity) variant 'width0125' overrides " + key in p and "only net" in p
               for p in problems), problems
    # The same override in a comparison ablation is allowed.
    cfg = smoke_config()
    ablation_of(cfg)["kind"] = "comparison"
    ablation_of(cfg)["variants"][0].update(override)
    assert training_problems(cfg) == []


# ------------------------------------------------------------------------------------------ timing job
def test_the_timing_job_times_capacity_variants_but_not_comparison_variants() -> None:
    cfg = smoke_config(ablation_spp=[1])
    runs = timed_runs(cfg)
    assert capacity_model_ids(cfg) == {"rae_capacity_width0125", "rae_capacity_levels4"}
    assert runs[-2:] == [("rae_capacity_width0125", 1), ("rae_capacity_levels4", 1)]
    assert ("rae", 1) in runs and ("rae", 2) in runs
    assert not [row for row, _ in runs if row.startswith(("rae_inputs_", "rae_loss_"))]
    # Evaluated at ablation_spp only; none when the variants are not evaluated.
    assert not [row for row, _ in timed_runs(smoke_config(ablation_spp=[])) if row.startswith("rae_capacity")]


# ------------------------------------------------------------------------------------------ per-ablation spp
def test_an_ablation_may_set_its_own_evaluated_spp() -> None:
    """A family trained at another sample count (NTASD at an average of 4 spp) sets ``spp`` on its ablation: its
    variants' rows (and timing) use it, the other ablations keep evaluation.ablation_spp."""
    cfg = smoke_config(ablation_spp=[1])
    ablation_of(cfg)["spp"] = [2]
    cfg = validate_config(cfg)
    rows = {spec.id: spec.spp for spec in method_specs(cfg) if spec.role == "ablation"}
    assert rows["rae_capacity_width0125"] == (2,) and rows["rae_capacity_levels4"] == (2,)
    assert all(spp == (1,) for row, spp in rows.items() if not row.startswith("rae_capacity"))
    assert timed_runs(cfg)[-2:] == [("rae_capacity_width0125", 2), ("rae_capacity_levels4", 2)]
    ablation_of(cfg)["spp"] = []
    assert not [s for s in method_specs(validate_config(cfg)) if s.id.startswith("rae_capacity")]


def test_a_variant_may_set_its_own_evaluated_spp() -> None:
    """A size a claim compares at every spp (Isik's KPCN at ours-single's parameter count, C3.1) sets ``spp`` on
    its variant: its rows (seed replicas included) and timing use it, the other sizes keep the ablation's."""
    cfg = smoke_config(ablation_spp=[1])
    ablation = ablation_of(cfg)
    ablation["seeds"] = 2
    ablation["variants"] = [{**ablation["variants"][0], "spp": [1, 2]}, *ablation["variants"][1:]]
    cfg = validate_config(cfg)
    assert training_problems(cfg, build_tasks=False) == [] and evaluation_problems(cfg) == []
    rows = {spec.id: spec.spp for spec in method_specs(cfg) if spec.id.startswith("rae_capacity")}
    assert rows["rae_capacity_width0125"] == rows["rae_capacity_width0125_seed1"] == (1, 2)
    assert rows["rae_capacity_levels4"] == rows["rae_capacity_levels4_seed1"] == (1,)
    assert [run for run in timed_runs(cfg) if run[0].startswith("rae_capacity")] == [
        ("rae_capacity_width0125", 1), ("rae_capacity_width0125", 2), ("rae_capacity_levels4", 1)]
    ablation_of(cfg)["variants"][0]["spp"] = [3]
    problems = "\n".join(evaluation_problems(validate_config(cfg)))
    assert "'training.ablations' entry 'rae_capacity' variant 'width0125' has spp [3]" in problems


def test_the_sizes_are_compared_at_an_spp_every_size_ran_at() -> None:
    """With one size evaluated at more spp than the others (its own ``spp``), the table compares every size at an
    spp they share: the training spp only where all of them ran there."""
    cfg = capacity_config()
    ablation_of(cfg)["variants"][0]["spp"] = [1, 2]
    for model in cfg["training"]["models"]:
        if model["id"] == "rae":
            model.setdefault("data", {})["spp"] = 2          # trained at 2 spp, which only width0125 is scored at
    cfg = validate_config(cfg)
    table, _ = capacity_table(make_results(cfg), ablation_of(cfg))
    assert set(table["spp"]) == {1} and table["psnr_mean"].notna().all()


def test_an_ablation_spp_outside_the_evaluated_spp_is_refused() -> None:
    cfg = smoke_config(ablation_spp=[1])
    ablation_of(cfg)["spp"] = [3]
    problems = "\n".join(evaluation_problems(validate_config(cfg)))
    assert "'training.ablations' entry 'rae_capacity' has spp [3]" in problems


def test_an_empty_own_spp_is_named_in_the_capacity_table() -> None:
    cfg = capacity_config()
    ablation_of(cfg)["spp"] = []
    table, _ = capacity_table(make_results(validate_config(cfg)), ablation_of(cfg))
    assert "training.ablations rae_capacity spp is empty" in table["note"].iloc[0]
