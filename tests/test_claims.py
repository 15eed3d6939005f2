"""Every claim's decision on synthetic result tables: reproduced, contradicted, inconclusive, not run.

Results are built in memory (no files): per-scene values chosen so that the paired difference of each
part of a claim is ``d_i`` on the claimed side. The expected outcome follows from the rule written in
the reproduction targets (95 % Student-t interval of the paired difference wholly on one side of 0,
n >= 3), recomputed here with scipy where the margin matters.
"""
from __future__ import annotations


import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy import stats

from denoisers import evaluate
from denoisers.report.claims import claims_table, evaluate_claim
from denoisers.report.verdicts import CONTRADICTED, INCONCLUSIVE, MIN_SEEDS, MIN_SPEED_ROUNDS, NOT_RUN, REPRODUCED, Part
from denoisers.report.collect import Results
from denoisers.jobs.timing import TIMING_SCHEMA, TimingJob
from denoisers.reproductions import all_claims, all_reproductions
from scenegen.config import validate_config

REPO_ROOT = Path(__file__).resolve().parents[1]
CLEAR = [1.0, 1.2, 0.9, 1.1]              # wholly on the claimed side
AGAINST = [-1.0, -1.2, -0.9, -1.1]        # wholly on the other side
SPANNING = [1.5, -1.0, 0.8, -0.2]         # mean > 0, interval spans 0
ONE_SCENE = [5.0]                         # n = 1: no interval
TWO_SCENES = [1.0, 1.1]                   # n = 2 < 3
BASE = {"psnr": 25.0, "ssim": 0.7, "rmse": 0.08, "relmse": 0.05, "smape": 0.1, "flip": 0.2, "tpsnr": 30.0,
        "trmae": 1.0, "video_psnr": 25.0, "ms_per_frame": 10.0}
SCALE = {"psnr": 1.0, "ssim": 0.01, "rmse": 0.001, "trmae": 0.01, "ms_per_frame": 0.5}
# (a, spp, b, spp, metric, claimed) for the claims whose parts compare rows directly.
PARTS = {
    "C1.1": [("rae", 1, "eaw", 1, "rmse", "lower"), ("rae", 1, "eaw", 1, "ssim", "higher")],
    "C1.2": [("rae_inputs_untextured", 1, "rae_inputs_color", 1, "rmse", "lower"),
             ("rae_inputs_all", 1, "rae_inputs_color", 1, "rmse", "lower")],
    "C1.3": [("rae_loss_combined", 1, "rae_loss_spatial", 1, "ssim", "higher")],
    "C1.4": [("rae", 4, "noisy", 4, "rmse", "lower"), ("rae", 4, "noisy", 4, "ssim", "higher")],
    "C1.5": [("rae", 1, "rae_per_frame", 1, "trmae", "lower")],
    "C4.1s": [("wrls", 2, "svgf", 2, "psnr", "higher"), ("wrls", 2, "svgf", 2, "trmae", "lower")],
}
#: C4.4 is a speed part: per-round time ratios wrls / rae of the timing job; d_i > 0 (as claimed) gives a
#: ratio below 1 in round i.
SPEED_PARTS = {"C4.4": (("wrls", 2), ("rae", 2))}
#: Training seeds of the synthetic configs: a learned part needs MIN_SEEDS; every seed row repeats its row's
#: values unless a test sets them (tests/test_seed_verdicts.py varies them and the half-budget rows').
SEEDS = MIN_SEEDS
#: Roles of the rows the config adds for trained models; the synthetic configs also train half-budget twins.
ADDED_ROLES = (evaluate.SEED_ROLE, evaluate.BUDGET_ROLE)
DECIDED = ("C1.1", "C1.2", "C1.3", "C1.4", "C1.5", "C4.1s", "C4.2s", "C4.3s", "C4.4")


def claims_config(spp: tuple[int, ...] = (1, 2, 4)) -> dict:
    cfg = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    cfg["evaluation"]["spp"] = list(spp)
    cfg["evaluation"]["robustness"]["spp"] = 2 if 2 in spp else spp[0]
    cfg["training"]["seeds"] = SEEDS
    cfg["training"]["half_budget"] = True
    return validate_config(cfg)


class Table:
    """Per-scene values {(row, spp): {metric: [per scene]}} with a default for every metric."""

    def __init__(self, cfg: dict, n: int) -> None:
        self.n = n
        self.specs = {spec.id: spec for spec in evaluate.method_specs(cfg)}
        self.values = {(spec.id, s): {m: [v] * n for m, v in BASE.items()}
                       for spec in self.specs.values() for s in spec.spp if spec.role not in ADDED_ROLES}
        #: Values a test sets for rows the config adds (seed rows {row}_seed{k}, half-budget rows {row}_half); any
        #: other such row repeats the values of the row it is a seed (half-budget run) of.
        self.added_values: dict[tuple[str, int], dict[str, list[float]]] = {}

    def row_values(self, spec: evaluate.MethodSpec, spp: int) -> dict[str, list[float]]:
        if spec.role == evaluate.BUDGET_ROLE:
            base = self.row_values(self.specs[spec.budget_of], spp)
        elif spec.role == evaluate.SEED_ROLE:
            base = self.values[(spec.seed_of, spp)]
        else:
            return self.values[(spec.id, spp)]
        return {**base, **self.added_values.get((spec.id, spp), {})}
        self.spiked: dict[str, list[float]] = {}

    def shift(self, a: tuple[str, int], b: tuple[str, int], metric: str, claimed: str, d: list[float]) -> None:
        """Set a's metric to b's + d_i on the claimed side (scaled to the metric)."""
        sign = 1.0 if claimed == "higher" else -1.0
        self.values[a][metric] = [bv + sign * SCALE[metric] * di for bv, di in zip(self.values[b][metric], d)]


def timing_job(cfg: dict, ratios: dict[tuple[str, int], list[float]] | None = None, rounds: int = 4) -> TimingJob:
    """A timing-job record: every row at 10 ms per pass, except rows given per-round factors in ``ratios``."""
    rows = []
    for spec in evaluate.method_specs(cfg):
        for spp in spec.spp:
            passes = [10.0 * f for f in (ratios or {}).get((spec.id, spp), [1.0] * rounds)]
            rows.append({"method_id": spec.id, "spp": spp, "threads": 2, "width": 64, "height": 64,
                         "pass_ms_per_frame": passes, "ms_per_frame": float(np.median(passes)),
                         "ms_per_frame_min": min(passes), "ms_per_frame_max": max(passes), "repeats": len(passes),
                         "mpix_per_s": 64 * 64 / float(np.median(passes)) / 1e3})
    return TimingJob({"schema": TIMING_SCHEMA, "scene": "test_000", "frames": 4, "repeats": rounds, "threads": 2,
                      "rows": rows,
                      "renderers": {"test_000": {"samples_per_s": 1e6, "repeats": rounds, "layers": 8}}})


def build(cfg: dict, table: Table, drop: tuple[tuple[str, int], ...] = (), flagged: tuple[str, int] | None = None,
          spiked: dict[str, list[float]] | None = None, timing: TimingJob | None = None) -> Results:
    scenes = [f"test_{i:03d}" for i in range(table.n)]
    rows, runs = [], []
    for spec in evaluate.method_specs(cfg):
        for spp in spec.spp:
            ran = (spec.id, spp) not in drop
            runs.append({"id": spec.id, "method": spec.method, "role": spec.role, "spp": spp,
                         "status": "ran" if ran else "not run", "reason": "" if ran else "removed by the test"})
            if not ran:
                continue
            for i, scene in enumerate(scenes):
                rows.append({"method_id": spec.id, "spp": spp, "scene": scene,
                             **{m: v[i] for m, v in table.row_values(spec, spp).items()},
                             "nonfinite_outputs": 0, "out_of_range_factor": 10.0,
                             "out_of_range_outputs": 123 if flagged == (spec.id, spp) else 0})
    robustness = None
    if spiked is not None:
        robustness = pd.DataFrame([{"method_id": m, "scene": s, "spp": 2, "psnr_spiked": v[i]}
                                   for m, v in spiked.items() for i, s in enumerate(scenes)])
    return Results(cfg, evaluate.method_specs(cfg), scenes, runs, pd.DataFrame(), pd.DataFrame(rows), robustness,
                   timing=timing if timing is not None else timing_job(cfg, rounds=table.n))


def results_for(claim: str, d: list[float], cfg: dict | None = None, **kwargs) -> Results:
    """Results where every part of ``claim`` has the paired differences d (positive = as claimed)."""
    cfg = cfg or claims_config()
    table = Table(cfg, len(d))
    spiked, timing = None, None
    if claim in SPEED_PARTS:
        a, _ = SPEED_PARTS[claim]
        # A speed part needs MIN_SPEED_ROUNDS rounds: the 4-value fixtures get a fifth round at their mean.
        rounds = d + [float(np.mean(d))] if len(d) == MIN_SPEED_ROUNDS - 1 else d
        timing = timing_job(cfg, {a: [1.0 - 0.1 * di for di in rounds]}, rounds=len(rounds))
    elif claim in PARTS:
        for a, a_spp, b, b_spp, metric, claimed in PARTS[claim]:
            table.shift((a, a_spp), (b, b_spp), metric, claimed, d)
    elif claim == "C4.2s":   # spiked PSNR wrls - rls = d; clean PSNR equal, so drop(wrls) - drop(rls) = -d
        spiked = {"wrls": [20.0 + di for di in d], "rls": [20.0] * len(d)}
    elif claim == "C4.3s":   # wrls above noisy by d at every spp; RAE gain at 4 spp smaller than at 1 spp by d
        for s in cfg["evaluation"]["spp"]:
            table.shift(("wrls", s), ("noisy", s), "psnr", "higher", d)
        high = rae_trained_at(cfg, 4)
        table.values[("rae", 1)]["psnr"] = [v + 5.0 for v in table.values[("noisy", 1)]["psnr"]]
        table.values[(high, 4)]["psnr"] = [v + 5.0 - di for v, di in zip(table.values[("noisy", 4)]["psnr"], d)]
    return build(cfg, table, spiked=spiked, timing=timing, **kwargs)


CLAIMS = {claim.id: claim for claim in all_claims()}


def rae_trained_at(cfg: dict, spp: int) -> str:
    """The recurrent RAE row whose model the config trains at ``spp`` (data.spp, read here from the config's
    training entries), else ``rae``."""
    trained = {m["id"]: m.get("data", {}).get("spp") for m in cfg["training"]["models"]}
    return next((r["id"] for r in cfg["evaluation"]["methods"] if r["method"] == "rae" and spp in r.get("spp", [spp])
                 and not r.get("params", {}).get("reset_state_every_frame")
                 and trained.get(r.get("params", {}).get("model")) == spp), "rae")


@pytest.mark.parametrize("claim", DECIDED)
@pytest.mark.parametrize("d, expected", [(CLEAR, REPRODUCED), (AGAINST, CONTRADICTED), (SPANNING, INCONCLUSIVE),
                                         (ONE_SCENE, INCONCLUSIVE), (TWO_SCENES, INCONCLUSIVE)])
def test_every_claim_has_each_outcome(claim: str, d: list[float], expected: str) -> None:
    decision = evaluate_claim(results_for(claim, d), CLAIMS[claim])
    assert decision.verdict == expected, (claim, [(p.claim_text(), p.interval_text()) for p in decision.parts])
    units = MIN_SPEED_ROUNDS if claim in SPEED_PARTS and len(d) == MIN_SPEED_ROUNDS - 1 else len(d)
    assert all(part.n == units for part in decision.parts)


def test_spanning_case_is_what_the_rule_calls_inconclusive() -> None:
    """The fixture's numbers themselves: CLEAR's interval excludes 0, SPANNING's mean is positive and its
    interval includes 0 (scipy)."""
    for values, excludes in ((CLEAR, True), (SPANNING, False)):
        low, high = stats.t.interval(0.95, len(values) - 1, loc=np.mean(values), scale=stats.sem(values))
        assert np.mean(values) > 0 and (low > 0) == excludes


@pytest.mark.parametrize("claim", ["C1.1", "C1.4", "C4.1s"])
def test_a_claim_needs_every_part(claim: str) -> None:
    cfg = claims_config()
    (a, a_spp, b, b_spp, m1, c1), (_, _, _, _, m2, c2) = PARTS[claim]
    for second, expected in ((SPANNING, INCONCLUSIVE), (AGAINST, CONTRADICTED)):
        table = Table(cfg, 4)
        table.shift((a, a_spp), (b, b_spp), m1, c1, CLEAR)
        table.shift((a, a_spp), (b, b_spp), m2, c2, second)
        decision = evaluate_claim(build(cfg, table), CLAIMS[claim])
        assert [p.outcome for p in decision.parts] == [REPRODUCED, expected]
        assert decision.verdict == expected


def test_c43_needs_both_halves() -> None:
    """wRLS above its input at every spp, but RAE's gain does not shrink: contradicted."""
    results = results_for("C4.3s", CLEAR)
    high = rae_trained_at(results.cfg, 4)
    noisy = results.per_scene[(results.per_scene.method_id == "noisy") & (results.per_scene.spp == 4)]["psnr"]
    for row in results.seed_rows(high, 4) + results.seed_rows(f"{high}_half", 4):     # every seed and budget alike
        mask = (results.per_scene.method_id == row) & (results.per_scene.spp == 4)
        results.per_scene.loc[mask, "psnr"] = noisy.to_numpy() + 5.0 + np.array(CLEAR)
    decision = evaluate_claim(results, CLAIMS["C4.3s"])
    assert [p.outcome for p in decision.parts] == [REPRODUCED] * 3 + [CONTRADICTED]
    assert decision.verdict == CONTRADICTED


def test_c43_takes_the_rae_trained_at_each_spp_and_says_so() -> None:
    """The default config trains rae at 1 spp and rae_4spp at 4 (issue 46 §4): RAE's gain at 4 spp is
    rae_4spp's, at 1 spp rae's. Without the 4-spp row the 1-spp model stands in at 4 spp, and the note says
    which model trained at which spp."""
    cfg = claims_config()
    assert rae_trained_at(cfg, 4) == "rae_4spp" and rae_trained_at(cfg, 1) == "rae"
    decision = evaluate_claim(results_for("C4.3s", CLEAR, cfg), CLAIMS["C4.3s"])
    gain = decision.parts[-1]
    assert decision.verdict == REPRODUCED
    assert "(rae_4spp)" in gain.a and "(rae)" in gain.b, (gain.a, gain.b)
    assert "rae trained at 1 spp, rae_4spp trained at 4 spp" in decision.note
    c25 = evaluate_claim(results_for("C4.3s", CLEAR, cfg), CLAIMS["C2.5"])    # Hasselgren's RAE at 4 spp too
    assert {p.b for p in c25.parts if "rae" in p.b} == {"rae_4spp @ 4 spp"}, [p.b for p in c25.parts]
    # The 1-spp row's gain at 4 spp shrinks by d; the 4-spp row is dropped.
    table = Table(cfg, 4)
    for s in cfg["evaluation"]["spp"]:
        table.shift(("wrls", s), ("noisy", s), "psnr", "higher", CLEAR)
    table.values[("rae", 1)]["psnr"] = [v + 5.0 for v in table.values[("noisy", 1)]["psnr"]]
    table.values[("rae", 4)]["psnr"] = [v + 5.0 - di for v, di in zip(table.values[("noisy", 4)]["psnr"], CLEAR)]
    decision = evaluate_claim(build(cfg, table, drop=(("rae_4spp", 4),)), CLAIMS["C4.3s"])
    assert decision.verdict == REPRODUCED and "(rae)" in decision.parts[-1].a
    assert "rae trained at 1 spp" in decision.note and "rae_4spp" not in decision.note


@pytest.mark.parametrize("claim, spp, stated", [("C1.1", (2, 4), 1), ("C1.4", (1, 2), 4), ("C4.1s", (1, 4), 2),
                                                ("C4.4", (1, 4), 2), ("C1.2", (2, 4), 1)])
def test_a_claim_at_an_spp_not_evaluated_is_not_run(claim: str, spp: tuple[int, ...], stated: int) -> None:
    cfg = claims_config(spp)
    if claim == "C1.2":
        cfg["evaluation"]["ablation_spp"] = [spp[0]]
    decision = evaluate_claim(build(cfg, Table(cfg, 4)), CLAIMS[claim])
    assert decision.verdict == NOT_RUN
    assert f"stated at {stated} spp" in decision.not_run or f"{stated} spp" in decision.not_run, decision.not_run


@pytest.mark.parametrize("claim, row, named", [("C1.1", ("eaw", 1), "eaw"), ("C1.5", ("rae_per_frame", 1), "reset"),
                                               ("C1.2", ("rae_inputs_all", 1), "rae_inputs_all"),
                                               ("C4.1s", ("svgf", 2), "svgf"), ("C4.3s", ("rae", 1), "rae")])
def test_a_missing_row_makes_the_claim_not_run(claim: str, row: tuple[str, int], named: str) -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    spec = next(s for s in evaluate.method_specs(cfg) if s.id == row[0])
    whole_row = tuple((spec.id, s) for s in spec.spp) if named != spec.id or claim != "C4.3s" else (row,)
    decision = evaluate_claim(build(cfg, table, drop=whole_row), CLAIMS[claim])
    assert decision.verdict == NOT_RUN and named in decision.not_run, decision.not_run


def test_c13_without_a_variant_and_c42_without_the_scenario_are_not_run() -> None:
    cfg = claims_config()
    decision = evaluate_claim(build(cfg, Table(cfg, 4), drop=(("rae_loss_spatial", 1),)), CLAIMS["C1.3"])
    assert decision.verdict == NOT_RUN and "rae_loss_spatial" in decision.not_run, decision.not_run
    decision = evaluate_claim(build(cfg, Table(cfg, 4)), CLAIMS["C4.2s"])        # no robustness results
    assert decision.verdict == NOT_RUN and "robustness" in decision.not_run, decision.not_run
    results = results_for("C4.2s", CLEAR)
    results.robustness = results.robustness[results.robustness.method_id != "rls"]
    decision = evaluate_claim(results, CLAIMS["C4.2s"])
    assert decision.verdict == NOT_RUN and "rls" in decision.not_run, decision.not_run


def test_unbuilt_papers_name_their_missing_rows() -> None:
    table = claims_table(results_for("C1.1", CLEAR), all_claims()).set_index("claim")
    for claim in ("C3.1", "C3.2", "C3.5"):
        assert table.loc[claim, "verdict"] == NOT_RUN
        assert table.loc[claim, "note"].startswith("missing rows: ")
    assert "'kpcn'" in table.loc["C3.1", "note"]


def test_facts_are_shown_and_do_not_decide() -> None:
    table = claims_table(results_for("C4.4", AGAINST), all_claims()).set_index("claim")
    assert table.loc["C4.4", "verdict"] == CONTRADICTED
    assert "wRLS needs no training: yes (declared, not measured)" in table.loc["C4.4", "facts"]


def test_claims_table_shows_n_interval_and_flags() -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    for a, a_spp, b, b_spp, metric, claimed in PARTS["C1.1"]:
        table.shift((a, a_spp), (b, b_spp), metric, claimed, CLEAR)
    row = claims_table(build(cfg, table, flagged=("rae", 1)), all_claims()).set_index("claim").loc["C1.1"]
    assert row["verdict"] == REPRODUCED and row["n"] == "4"
    diffs = -SCALE["rmse"] * np.array(CLEAR)
    low, high = stats.t.interval(0.95, 3, loc=diffs.mean(), scale=stats.sem(diffs))
    shown = [float(v) for v in re.match(r"(\S+) \[(\S+), (\S+)\];", row["mean_diff_ci_95"]).groups()]
    assert shown == pytest.approx([diffs.mean(), low, high], abs=1e-4)   # printed with 4 decimals
    assert "rae @ 1 spp: 492 output values beyond 10x the largest input sample" in row["flags"]  # 4 x 123
    assert "rae @ 1 spp − eaw @ 1 spp < 0 (reproduced)" in row["parts"]


def test_part_outcomes_at_the_boundary() -> None:
    a = pd.Series([1.0, 2.0, 3.0], index=["s0", "s1", "s2"])
    assert Part.paired(a + 1.0, a, "psnr", "a", "b").outcome == REPRODUCED        # zero variance, +1
    assert Part.paired(a, a, "psnr", "a", "b").outcome == INCONCLUSIVE            # exactly 0
    assert Part.paired(a - 1.0, a, "rmse", "a", "b").outcome == REPRODUCED        # lower error
    assert Part.paired(a, a.iloc[:2], "psnr", "a", "b").n == 2                    # paired on common scenes only
    with pytest.raises(ValueError):
        Part.paired(a, a, "psnr", "a", "b", claimed="better")


def test_every_claim_of_the_targets_is_in_one_paper_module() -> None:
    ids = [claim.id for claim in all_claims()]
    expected = [f"C{p}.{i}" for p, n in ((1, 5), (2, 5), (3, 5), (4, 4)) for i in range(1, n + 1)]
    # Iglesias-Guitian's C4.1-C4.3 are decided on the volumetric clips; their surface versions follow them.
    for claim in ("C4.1", "C4.2", "C4.3"):
        expected.insert(expected.index(claim) + 1, f"{claim}s")
    assert ids == expected
    assert [r.key for r in all_reproductions()] == ["chaitanya2017", "hasselgren2020", "isik2021", "iglesias2022"]


def test_speed_claims_are_decided_on_a_t_interval_of_log_time_ratios() -> None:
    """C4.4 compares per-round time ratios of the timing job by the t-interval of their logarithms (scipy
    here): one slow round among fast ones widens the interval; fewer than MIN_SPEED_ROUNDS rounds decide
    nothing; without the timing job the claim is not run."""
    cfg = claims_config()
    table = Table(cfg, 4)
    for factors, expected in (([0.2, 0.3, 0.25, 1.05, 0.22], REPRODUCED), ([0.2, 0.3, 0.25, 3.0, 0.22], INCONCLUSIVE),
                              ([1.2, 1.3, 1.25, 1.1, 1.22], CONTRADICTED)):
        timing = timing_job(cfg, {("wrls", 2): factors}, rounds=5)
        decision = evaluate_claim(build(cfg, table, timing=timing), CLAIMS["C4.4"])
        logs = np.log(factors)
        low, high = stats.t.interval(0.95, 4, loc=logs.mean(), scale=stats.sem(logs))
        assert decision.verdict == expected, factors
        assert decision.parts[0].interval == pytest.approx((logs.mean(), low, high))
        shown = re.match(r"time ratio (\S+) \[(\S+), (\S+)\] over 5 rounds", decision.parts[0].interval_text())
        assert [float(v) for v in shown.groups()] == pytest.approx(np.exp([logs.mean(), low, high]), rel=2e-3)
    four_rounds = timing_job(cfg, {("wrls", 2): [0.5, 0.6, 0.7, 0.55], ("rae", 2): [1.0] * 4}, rounds=4)
    decision = evaluate_claim(build(cfg, table, timing=four_rounds), CLAIMS["C4.4"])
    assert decision.verdict == INCONCLUSIVE and decision.parts[0].n == 4 and MIN_SPEED_ROUNDS == 5
    results = build(cfg, table)
    results.timing = None
    decision = evaluate_claim(results, CLAIMS["C4.4"])
    assert decision.verdict == NOT_RUN and "timing job" in decision.not_run
