"""The Isik et al. 2021 reproduction module (denoisers/reproductions/isik2021.py): AFN rows identified by their
models' net settings, claims C3.1-C3.5 on constructed per-scene numbers (each outcome, at every claim spp),
the Table 2-5 layouts and the Fig. 8 figure.

Results are built in memory with the helpers of tests/test_claims.py; the models and rows are set here.
"""
from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from denoisers.report.claims import evaluate_claim
from denoisers.report.verdicts import CONTRADICTED, INCONCLUSIVE, NOT_RUN, REPRODUCED
from denoisers.reproductions import isik2021 as isik
from scenegen.config import validate_config
from tests.test_claims import AGAINST, CLEAR, SPANNING, TWO_SCENES, Table, build, claims_config

SPP = (2, 4, 8)
BASE_MODEL = {"method": "afn", "net": {"width": 0.25}, "data": {"spp": 8, "backward_prob": 0.0, "length": 3},
              "budget": {"max_steps": 10}}
#: model id -> net overrides (the variant is what the module must recognise).
MODELS = {"afn": {}, "afn_single": {"temporal": False}, "afn_k1": {"temporal": False, "kernels": 1, "dilate": False,
                                                                    "kernel_size": 17},
          "afn_d1": {"temporal": False, "affinity_dim": 1}, "afn_d2": {"temporal": False, "affinity_dim": 2},
          "afn_heur": {"fixed_lambda": 0.8}, "afn_gather": {"temporal": False, "kernel_kind": "gather", "kernels": 1,
                                                              "kernel_size": 5}}
ROWS = [{"id": "noisy", "method": "noisy"}, {"id": "oidn", "method": "oidn"},
        {"id": "kpcn", "method": "kpcn", "params": {"model": "kpcn"}},
        *[{"id": m, "method": "afn", "params": {"model": m}} for m in MODELS],
        {"id": "afn_k7", "method": "afn", "params": {"model": "afn", "kernel_size": 7}},
        {"id": "afn_single_k7", "method": "afn", "params": {"model": "afn_single", "kernel_size": 7}}]
#: (a, b, metric, claimed) per claim, at every claim spp.
PARTS = {
    "C3.1": [("afn_single", "afn_k1", "psnr", "higher"), ("afn_single", "kpcn", "psnr", "higher")],
    "C3.2": [("afn_single", "afn_d1", "psnr", "higher"), ("afn_d2", "afn_d1", "psnr", "higher")],
    "C3.3": [("afn", "afn_single", "trmae", "lower")],
    "C3.4": [("afn", "afn_heur", "video_psnr", "higher")],
}
CLAIMS = {claim.id: claim for claim in isik.CLAIMS}
#: Per-unit step of each metric (the d_i of the fixtures are ~1).
STEP = {"psnr": 1.0, "video_psnr": 1.0, "trmae": 0.01}


def shift(table: Table, a: tuple[str, int], b: tuple[str, int], metric: str, claimed: str, d: list[float]) -> None:
    """a's metric = b's + d_i (in steps of STEP[metric]) per scene on the claimed side."""
    sign = 1.0 if claimed == "higher" else -1.0
    table.values[a][metric] = [v + sign * STEP[metric] * di for v, di in zip(table.values[b][metric], d)]


def config() -> dict:
    cfg = claims_config(SPP)
    models = [{**BASE_MODEL, "id": m, "net": {**BASE_MODEL["net"], **net}} for m, net in MODELS.items()]
    models.append({"id": "kpcn", "method": "kpcn", "data": {"spp": 8, "length": 1}, "budget": {"max_steps": 10}})
    cfg["training"]["models"] = models
    cfg["training"]["ablations"] = []
    cfg["evaluation"]["methods"] = ROWS
    cfg["evaluation"]["ablation_spp"] = []
    return validate_config(cfg)


def shifted(claim: str, d: list[float], cfg: dict | None = None) -> tuple[dict, Table]:
    """A table where every part of ``claim`` at every claim spp differs by d_i per scene (parts applied from the
    last to the first, so each part's paired difference is exactly d even when parts share a row)."""
    cfg = cfg or config()
    table = Table(cfg, len(d))
    for spp in SPP:
        for a, b, metric, claimed in reversed(PARTS[claim]):
            shift(table, (a, spp), (b, spp), metric, claimed, d)
    return cfg, table


def test_rows_are_identified_by_their_models_net_settings() -> None:
    cfg, table = shifted("C3.3", CLEAR)
    rows = isik.afn_rows(build(cfg, table))
    assert {row: variant for row, (variant, _) in rows.items()} == {
        "afn": "ours", "afn_single": "ours-single", "afn_k1": "ours-K1", "afn_d1": "d=1", "afn_d2": "d=2",
        "afn_heur": "ours-heur", "afn_gather": "gather K1"}
    assert list(isik.afn_rows(build(cfg, table), test_time_size=True)) == ["afn_k7", "afn_single_k7"]


@pytest.mark.parametrize("claim", sorted(PARTS))
@pytest.mark.parametrize("d, expected", [(CLEAR, REPRODUCED), (AGAINST, CONTRADICTED), (SPANNING, INCONCLUSIVE),
                                         (TWO_SCENES, INCONCLUSIVE)])
def test_every_claim_has_each_outcome(claim: str, d: list[float], expected: str) -> None:
    cfg, table = shifted(claim, d)
    decision = evaluate_claim(build(cfg, table), CLAIMS[claim])
    assert decision.verdict == expected, (claim, [(p.claim_text(), p.interval_text()) for p in decision.parts])
    expected_labels = [(f"{a} @ {spp} spp", f"{b} @ {spp} spp") for a, b, _, _ in PARTS[claim] for spp in SPP]
    assert sorted((p.a, p.b) for p in decision.parts) == sorted(expected_labels)
    assert all(p.n == len(d) for p in decision.parts)


def test_claims_use_only_the_evaluated_claim_spp() -> None:
    cfg = config()
    cfg["evaluation"]["spp"] = [1, 2, 4]
    table = Table(cfg, 4)
    for spp in (2, 4):
        shift(table, ("afn", spp), ("afn_single", spp), "trmae", "lower", CLEAR)
    decision = evaluate_claim(build(cfg, table), CLAIMS["C3.3"])
    assert decision.verdict == REPRODUCED and "at 2, 4 spp" in decision.note
    assert len(decision.parts) == 2


def test_a_missing_variant_makes_the_claim_not_run() -> None:
    cfg, table = shifted("C3.4", CLEAR)
    results = build(cfg, table, drop=tuple(("afn_heur", s) for s in SPP))
    decision = evaluate_claim(results, CLAIMS["C3.4"])
    assert decision.verdict == NOT_RUN and "ours-heur" in decision.not_run


def test_c35_larger_kernels_help_more_at_low_spp() -> None:
    """Rows: the full model at its trained 13 x 13 and at 7 x 7 (params.kernel_size). Part (a): 13 beats 7 at
    2 spp; part (b): the gain at 2 spp exceeds the gain at 8 spp."""
    cfg = config()
    table = Table(cfg, 4)
    gains = {2: [2.0, 2.2, 1.9, 2.1], 4: [1.0] * 4, 8: [0.5, 0.4, 0.6, 0.5]}
    for spp, gain in gains.items():
        table.values[("afn", spp)]["psnr"] = [v + g for v, g in zip(table.values[("afn_k7", spp)]["psnr"], gain)]
    decision = evaluate_claim(build(cfg, table), CLAIMS["C3.5"])
    assert decision.verdict == REPRODUCED, [(p.claim_text(), p.interval_text()) for p in decision.parts]
    assert (decision.parts[0].a, decision.parts[0].b) == ("afn @ 2 spp", "afn_k7 @ 2 spp")
    assert decision.parts[1].a == "gain @ 2 spp" and decision.parts[1].b == "gain @ 8 spp"
    assert decision.parts[1].interval[0] == pytest.approx(1.55)
    # Equal gains at every spp: part (b) spans 0 only if the gains differ by noise; here exactly 0 -> not above.
    for spp in SPP:
        table.values[("afn", spp)]["psnr"] = [v + 1.0 for v in table.values[("afn_k7", spp)]["psnr"]]
    assert evaluate_claim(build(cfg, table), CLAIMS["C3.5"]).verdict != REPRODUCED
    without = build(cfg, table, drop=tuple(("afn_k7", s) for s in SPP))
    assert evaluate_claim(without, CLAIMS["C3.5"]).verdict == NOT_RUN


def test_tables_and_figure_are_written(tmp_path: Path) -> None:
    cfg, table = shifted("C3.3", CLEAR)
    table.values[("afn_d1", 4)]["psnr"] = [20.0] * 4
    results = build(cfg, table)
    (tmp_path / "tables").mkdir()
    (tmp_path / "figures").mkdir()
    section = isik.write(results, tmp_path / "tables", tmp_path / "figures")
    assert isik.table_names(cfg) == list(isik.TABLES) and isik.figure_names(cfg) == [isik.FIG8, isik.FIG5]
    for name in isik.TABLES:
        assert (tmp_path / "tables" / f"{name}.csv").is_file() and (tmp_path / "tables" / f"{name}.md").is_file()
    assert (tmp_path / "figures" / f"{isik.FIG8}.png").stat().st_size > 0 and "isik_fig8.png" in section
    # The section goes into REPORT.md beside tables/ and figures/: every link resolves from there.
    links = re.findall(r"\]\(([^)]+)\)", section)
    assert f"figures/{isik.FIG8}.png" in links
    for link in links:
        assert (tmp_path / link).is_file(), link
    # No denoised outputs in this fixture: the lambda figure is a placeholder and the section says why.
    assert (tmp_path / "figures" / f"{isik.FIG5}.png").stat().st_size > 0
    assert "no lambda maps of the full AFN model" in section
    table2 = pd.read_csv(tmp_path / "tables" / "isik_table2.csv").set_index("method")
    assert list(table2.index) == ["KPCN", "OIDN", "d=1", "ours-K1", "ours-single"]
    table3 = pd.read_csv(tmp_path / "tables" / "isik_table3.csv").set_index("method")
    assert table3.loc["ours", "TRMAE @ 4 spp"].startswith(f"{1.0 - STEP['trmae'] * 1.05:.4f}")
    table4 = pd.read_csv(tmp_path / "tables" / "isik_table4.csv").set_index("method")
    assert list(table4.index) == ["d=1", "d=2", "d=8"]
    assert table4.loc["d=1", "PSNR (dB, frame mean) @ 4 spp"].startswith("20.00")
    table5 = pd.read_csv(tmp_path / "tables" / "isik_table5.csv").set_index("method")
    # The single-frame model at a test-time size joins its trained size; the full temporal model's does not.
    assert list(table5.index) == ["affinity K=1, 17x17", "affinity K=3, 7x7 (trained 13x13)", "affinity K=3, 13x13",
                                  "gather K=1, 5x5"]
    # The paper's numbers stand beside ours (values typed from the paper's Tables 2-5, not from the module).
    assert table2.loc["ours-single", "paper @ 4 spp"] == 32.67 and table2.loc["OIDN", "paper @ 8 spp"] == 31.79
    assert table2.loc["d=1", "paper @ 2 spp"] == 26.65
    columns = list(table2.columns)
    assert columns.index("paper @ 4 spp") == columns.index("PSNR (dB, frame mean) @ 4 spp") + 1
    assert table3.loc["ours", "paper TRMAE @ 8 spp"] == 0.446 and table3.loc["OIDN", "paper video PSNR (dB, Isik Eq. 14) @ 2 spp"] == 30.66
    assert table4.loc["d=2", "paper @ 8 spp"] == 32.97
    assert table5.loc["affinity K=3, 7x7 (trained 13x13)", "paper @ 2 spp"] == 30.19
    assert table5.loc["affinity K=1, 17x17", "paper @ 4 spp"] == 31.87
    assert pd.isna(table5.loc["gather K=1, 5x5", "paper @ 4 spp"])   # the paper has no 5 x 5 gather K = 1


def test_c31_compares_kpcn_at_its_width_and_at_ours_singles_parameter_count() -> None:
    """KPCN's size is a free choice: ours-single must beat it as configured and at ours-single's parameter count
    (issue 46 "match parameter counts"), the width of the kpcn capacity sweep within 10 % of its parameters.
    The other widths are a capacity measurement, named in the note, not parts. The parameter counts are those the
    trainer recorded for config/isik2021.yaml's models (store/models/*/summary.json): ours-single at width 0.5
    239,790, KPCN at width 0.125 240,770 and at 0.5 1,666,378."""
    cfg = config()
    for model in cfg["training"]["models"]:
        if model["id"] == "afn_single":
            model["net"] = {**model["net"], "width": 0.5}
    cfg["training"]["ablations"] = [{"id": "kpcn_capacity", "kind": "capacity", "model": "kpcn", "spp": [4],
                                     "variants": [{"id": "width0125", "net": {"width": 0.125}},
                                                  {"id": "width05", "net": {"width": 0.5}}]}]
    cfg = validate_config(cfg)
    _, table = shifted("C3.1", CLEAR, cfg)
    res = build(cfg, table)
    assert [isik.trained_parameters(res, row) for row in ("afn_single", "kpcn_capacity_width0125",
                                                           "kpcn_capacity_width05")] == [239_790, 240_770, 1_666_378]
    # Losing to the parameter-matched KPCN (at the sweep's 4 spp) contradicts C3.1.
    shift(table, ("kpcn_capacity_width0125", 4), ("afn_single", 4), "psnr", "higher", CLEAR)
    decision = evaluate_claim(build(cfg, table), CLAIMS["C3.1"])
    matched = [part for part in decision.parts if "kpcn_capacity" in part.b]
    assert [part.b for part in matched] == ["kpcn_capacity_width0125 @ 4 spp"]
    assert matched[0].outcome == CONTRADICTED and decision.verdict == CONTRADICTED
    assert "kpcn_capacity_width0125 (240,770)" in decision.note
    assert "not parts (capacity measurements): kpcn_capacity_width05 (1,666,378)" in decision.note
    # The wider KPCN winning is a measurement, not a part: the claim stands on the others.
    _, table = shifted("C3.1", CLEAR, cfg)
    shift(table, ("kpcn_capacity_width05", 4), ("afn_single", 4), "psnr", "higher", CLEAR)
    assert evaluate_claim(build(cfg, table), CLAIMS["C3.1"]).verdict == REPRODUCED
