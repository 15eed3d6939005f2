"""The Hasselgren et al. 2020 reproduction module (denoisers/reproductions/hasselgren2020.py): claims C2.1-C2.5
on constructed per-scene numbers, Table 1 (rMSE x 1000), the Fig. 7 table, that the uniform 8-spp row is never
taken for temporal uniform, and that the figures are written.

Results are built in memory with the helpers of tests/test_claims.py (every metric at a base value per scene,
then one row shifted by d_i per scene on the claimed side); the evaluation rows are set here, so the tests do
not depend on which rows config/config.yaml lists.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from denoisers import evaluate
from denoisers.adaptive import SAMPLE_MAPS_FILE
from denoisers.report.claims import evaluate_claim
from denoisers.report.verdicts import CONTRADICTED, INCONCLUSIVE, NOT_RUN, REPRODUCED
from denoisers.report.collect import Results
from denoisers.reproductions import hasselgren2020 as h
from tests.test_claims import AGAINST, CLEAR, ONE_SCENE, SPANNING, TWO_SCENES, Table, build, claims_config
from tests.test_evaluate import write_synthetic_scene

ROWS = [  # the 8-spp row first: a lookup that ignored budget_factor would find it before ntasd_uniform
    {"id": "ntasd_uniform_8spp", "method": "ntasd_uniform", "params": {"model": "ntasd_uniform", "budget_factor": 2},
     "spp": [4]},
    {"id": "ntasd", "method": "ntasd", "params": {"model": "ntasd"}, "spp": [4]},
    {"id": "ntasd_uniform", "method": "ntasd_uniform", "params": {"model": "ntasd_uniform"}, "spp": [4]},
    {"id": "ntasd_kpn", "method": "ntasd_kpn", "params": {"model": "ntasd_kpn"}, "spp": [4]},
    {"id": "ntasd_direct", "method": "ntasd_direct", "params": {"model": "ntasd_direct"}, "spp": [4]},
    {"id": "dasr", "method": "dasr", "params": {"model": "dasr"}, "spp": [4]},
    {"id": "noisy", "method": "noisy"},
    {"id": "svgf", "method": "svgf"},
    {"id": "rae", "method": "rae", "params": {"model": "rae"}},
    {"id": "rae_per_frame", "method": "rae", "params": {"model": "rae", "reset_state_every_frame": True}},
]
#: Per-unit step of each metric (the d_i of the fixtures are ~1).
STEP = {"psnr": 1.0, "tpsnr": 1.0, "relmse": 0.001, "trmae": 0.01}
#: (a, b, metric, claimed) per claim, all at 4 spp.
PARTS = {
    "C2.1": [("ntasd_kpn", "ntasd_direct", "psnr", "higher")],
    "C2.2": [("ntasd_uniform", "ntasd_kpn", "psnr", "higher"), ("ntasd_uniform", "ntasd_kpn", "tpsnr", "higher")],
    "C2.3": [("ntasd", "ntasd_uniform", "psnr", "higher")],
    "C2.4": [("ntasd", "ntasd_uniform", "relmse", "lower"), ("ntasd_uniform", "dasr", "relmse", "lower"),
             ("dasr", "ntasd_direct", "relmse", "lower")],
    "C2.5": [("ntasd", "rae", "psnr", "higher"), ("ntasd", "svgf", "psnr", "higher"),
             ("ntasd", "rae", "trmae", "lower")],
}
CLAIMS = {claim.id: claim for claim in h.CLAIMS}


def config(rows: list[dict] | None = None) -> dict:
    cfg = claims_config((1, 2, 4))
    cfg["evaluation"]["methods"] = ROWS if rows is None else rows
    return cfg


def shift(table: Table, a: str, b: str, metric: str, claimed: str, d: list[float]) -> None:
    """a's metric at 4 spp = b's + d_i per scene on the claimed side (in steps of STEP[metric])."""
    sign = 1.0 if claimed == "higher" else -1.0
    base = table.values[(b, 4)][metric]
    table.values[(a, 4)][metric] = [v + sign * STEP[metric] * di for v, di in zip(base, d)]


def results_for(claim: str, d: list[float], cfg: dict | None = None, **kwargs) -> Results:
    """Results where every part of ``claim`` differs by d_i per scene, chained parts included: the rows are
    shifted from the last part to the first, so each part's paired difference is exactly d."""
    cfg = cfg or config()
    table = Table(cfg, len(d))
    for a, b, metric, claimed in reversed(PARTS[claim]):
        shift(table, a, b, metric, claimed, d)
    return build(cfg, table, **kwargs)


@pytest.mark.parametrize("claim", sorted(PARTS))
@pytest.mark.parametrize("d, expected", [(CLEAR, REPRODUCED), (AGAINST, CONTRADICTED), (SPANNING, INCONCLUSIVE),
                                         (ONE_SCENE, INCONCLUSIVE), (TWO_SCENES, INCONCLUSIVE)])
def test_every_claim_has_each_outcome(claim: str, d: list[float], expected: str) -> None:
    decision = evaluate_claim(results_for(claim, d), CLAIMS[claim])
    assert decision.verdict == expected, (claim, [(p.claim_text(), p.interval_text()) for p in decision.parts])
    assert [p.quantity for p in decision.parts] == [m for _, _, m, _ in PARTS[claim]]
    assert all(p.n == len(d) for p in decision.parts)
    assert all(p.a.startswith(f"{a} @ 4 spp") and p.b.startswith(f"{b} @ 4 spp")
               for p, (a, b, _, _) in zip(decision.parts, PARTS[claim]))


@pytest.mark.parametrize("claim", ["C2.2", "C2.4", "C2.5"])
def test_a_multi_part_claim_needs_every_part(claim: str) -> None:
    """Every part clear but the last: spanning -> inconclusive, against -> contradicted."""
    cfg = config()
    for last, expected in ((SPANNING, INCONCLUSIVE), (AGAINST, CONTRADICTED)):
        table = Table(cfg, 4)
        parts = PARTS[claim]
        for i, (a, b, metric, claimed) in reversed(list(enumerate(parts))):
            shift(table, a, b, metric, claimed, last if i == len(parts) - 1 else CLEAR)
        decision = evaluate_claim(build(cfg, table), CLAIMS[claim])
        assert [p.outcome for p in decision.parts] == [REPRODUCED] * (len(parts) - 1) + [expected]
        assert decision.verdict == expected


@pytest.mark.parametrize("claim, dropped, named", [("C2.1", "ntasd_direct", "ntasd_direct"),
                                                   ("C2.2", "ntasd_kpn", "ntasd_kpn"),
                                                   ("C2.3", "ntasd_uniform", "ntasd_uniform"),
                                                   ("C2.4", "dasr", "dasr"), ("C2.5", "svgf", "svgf")])
def test_a_missing_row_makes_the_claim_not_run(claim: str, dropped: str, named: str) -> None:
    cfg = config()
    spec = evaluate.method_spec(cfg, dropped)
    results = results_for(claim, CLEAR, cfg, drop=tuple((dropped, s) for s in spec.spp))
    decision = evaluate_claim(results, CLAIMS[claim])
    assert decision.verdict == NOT_RUN and f"'{named}'" in decision.not_run, decision.not_run


def test_the_8spp_row_is_never_temporal_uniform() -> None:
    """Without the 4-spp uniform row, C2.3 is not run (the 8-spp row does not stand in for it); with it, the
    8-spp row's numbers (far better) change nothing in C2.3, Table 1 or the temporal-uniform curve."""
    cfg = config()
    table = Table(cfg, 4)
    shift(table, "ntasd", "ntasd_uniform", "psnr", "higher", CLEAR)
    table.values[("ntasd_uniform_8spp", 4)]["psnr"] = [40.0] * 4
    table.values[("ntasd_uniform_8spp", 4)]["relmse"] = [0.0001] * 4
    results = build(cfg, table)
    assert h.row_at(results, h.TEMPORAL_UNIFORM) == "ntasd_uniform"
    assert h.row_at(results, h.UNIFORM_8SPP) == "ntasd_uniform_8spp"
    assert evaluate_claim(results, CLAIMS["C2.3"]).verdict == REPRODUCED
    t1 = h.table1(results).set_index(["source", "scene"])
    assert t1.loc[(h.OURS, "mean"), "uniform rMSE x1000"] == pytest.approx(table.values[("ntasd_uniform", 4)]
                                                                           ["relmse"][0] * 1000)
    fig7 = h.fig7_table(results).set_index("curve")
    assert fig7.loc["temporal uniform", "row"] == "ntasd_uniform" and fig7.loc["temporal uniform", "budget_spp"] == 4
    assert fig7.loc["uniform 8 spp", "row"] == "ntasd_uniform_8spp" and fig7.loc["uniform 8 spp", "budget_spp"] == 8
    assert fig7.loc["uniform 8 spp", "psnr_mean"] == pytest.approx(40.0)
    without = build(cfg, table, drop=(("ntasd_uniform", 4),))
    decision = evaluate_claim(without, CLAIMS["C2.3"])
    assert decision.verdict == NOT_RUN and "uniform 4 spp" in decision.not_run, decision.not_run
    assert math.isnan(h.table1(without).set_index(["source", "scene"]).loc[(h.OURS, "mean"), "uniform rMSE x1000"])


def test_a_row_that_states_the_default_budget_factor_is_at_budget() -> None:
    """``budget_factor: 1`` written out is the methods' default: the row is the temporal-uniform (and
    temporal-adaptive) row, and the 8-spp row still is not."""
    rows = [dict(row, params={**row.get("params", {}), "budget_factor": 1})
            if row["id"] in ("ntasd", "ntasd_uniform") else row for row in ROWS]
    cfg = config(rows)
    table = Table(cfg, 4)
    shift(table, "ntasd", "ntasd_uniform", "psnr", "higher", CLEAR)
    results = build(cfg, table)
    assert h.row_at(results, h.TEMPORAL_UNIFORM) == "ntasd_uniform"
    assert h.row_at(results, h.TEMPORAL_ADAPTIVE) == "ntasd"
    assert h.row_at(results, h.UNIFORM_8SPP) == "ntasd_uniform_8spp"
    assert evaluate_claim(results, CLAIMS["C2.3"]).verdict == REPRODUCED


def test_rae_and_svgf_are_taken_at_4_spp_from_the_row_that_ran_there() -> None:
    """Smoke-config layout: rae / svgf at 1, 2 spp and rae_4spp / svgf_4spp at 4 spp."""
    rows = [{**r, "spp": [1, 2]} if r["id"] in ("svgf", "rae", "rae_per_frame", "noisy") else r for r in ROWS]
    rows += [{"id": "svgf_4spp", "method": "svgf", "spp": [4]},
             {"id": "rae_4spp", "method": "rae", "params": {"model": "rae"}, "spp": [4]}]
    cfg = config(rows)
    table = Table(cfg, 4)
    for a, b, metric, claimed in PARTS["C2.5"]:
        b = f"{b}_4spp"
        shift(table, a, b, metric, claimed, CLEAR)
    decision = evaluate_claim(build(cfg, table), CLAIMS["C2.5"])
    assert decision.verdict == REPRODUCED
    assert [p.b for p in decision.parts] == ["rae_4spp @ 4 spp", "svgf_4spp @ 4 spp", "rae_4spp @ 4 spp"]
    no_4spp = config([r for r in rows if not r["id"].endswith("_4spp")])
    decision = evaluate_claim(build(no_4spp, Table(no_4spp, 4)), CLAIMS["C2.5"])
    assert decision.verdict == NOT_RUN and "4 spp" in decision.not_run and "rae" in decision.not_run


RELMSE = {"ntasd": [0.0070, 0.0060, 0.0080], "ntasd_uniform": [0.0098, 0.0090, 0.0110],
          "dasr": [0.0118, 0.0111, 0.0130], "ntasd_direct": [0.0148, 0.0142, 0.0161]}


def table1_results() -> tuple[Results, Table]:
    cfg = config()
    table = Table(cfg, 3)
    for row, values in RELMSE.items():
        table.values[(row, 4)]["relmse"] = list(values)
    return build(cfg, table), table


def test_table1_is_rmse_times_1000_per_scene_with_the_mean_and_the_papers_block() -> None:
    results, _ = table1_results()
    t1 = h.table1(results)
    ours = t1[t1.source == h.OURS].set_index("scene")
    columns = {"adaptive rMSE x1000": "ntasd", "uniform rMSE x1000": "ntasd_uniform", "DASR rMSE x1000": "dasr",
               "direct prediction rMSE x1000": "ntasd_direct"}
    assert list(ours.index) == [*results.scenes, "mean"]
    for column, row in columns.items():
        assert ours.loc[results.scenes, column].tolist() == pytest.approx([v * 1000 for v in RELMSE[row]])
        assert ours.loc["mean", column] == pytest.approx(np.mean(RELMSE[row]) * 1000)
    paper = t1[t1.source == h.THEIRS].set_index("scene")
    assert paper.loc["SUNTEMPLE"].tolist()[1:] == [7.0, 9.8, 10.0, 14.8]
    assert paper.loc["CLASSROOM"].tolist()[1:] == [7.0, 10.6, 12.4, 15.0]
    assert paper.loc["BATHROOM"].tolist()[1:] == [7.3, 9.7, 12.6, 12.1]
    assert paper.loc["mean", "adaptive rMSE x1000"] == pytest.approx(7.1)
    markdown = h._table1_markdown(results, t1)
    assert "| test_000 | 7.00 | 9.80 | 11.80 | 14.80 |" in markdown          # ours, 2 decimals
    assert "Paper (Table 1" in markdown and "not paired" in markdown
    assert evaluate_claim(results, CLAIMS["C2.4"]).verdict == REPRODUCED   # the same numbers decide C2.4


def test_outputs_are_listed_only_with_the_papers_rows() -> None:
    assert h.table_names(config()) == ["hasselgren2020_table1", "hasselgren2020_fig7"]
    assert h.figure_names(config()) == ["hasselgren2020_fig7", "hasselgren2020_sample_maps"]
    bare = config([r for r in ROWS if not r["method"].startswith(("ntasd", "dasr"))])
    assert h.table_names(bare) == [] and h.figure_names(bare) == []
    assert not h.has_rows(config([{**r, "spp": [1]} if r["method"].startswith(("ntasd", "dasr")) else r
                                  for r in ROWS]))


FRAMES, SIZE = 4, (8, 10)


def with_files(results: Results, root: Path, realised: float = 3.9) -> Results:
    """Per-frame metrics of the 4-spp rows, sample maps of ntasd and dasr and the test scenes' references."""
    results.results_dir = root
    rows = []
    for spec in results.specs:
        if 4 not in spec.spp or not results.ran(spec.id, 4):
            continue
        for k, scene in enumerate(results.scenes):
            psnr = results.scene_values(spec.id, 4, "psnr")[scene]
            for t in range(FRAMES):
                rows.append({"method_id": spec.id, "spp": 4, "scene": scene, "frame": t, "psnr": psnr + 0.1 * t,
                             "tpsnr": math.nan if t == 0 else psnr + 5.0, "camera_cut": t == 2,
                             "realised_spp": realised if spec.method.startswith(("ntasd", "dasr")) else math.nan})
            if spec.id in ("ntasd", "dasr"):
                folder = evaluate.denoised_dir(root, spec.id, scene, 4)
                folder.mkdir(parents=True, exist_ok=True)
                maps = np.random.default_rng(k).integers(0, 9, (FRAMES, *SIZE)).astype(np.uint8)
                np.savez(folder / SAMPLE_MAPS_FILE, frames=np.arange(FRAMES), sample_maps=maps)
    for scene in results.scenes:
        write_synthetic_scene(root / "renders" / scene, scene=scene, frames=FRAMES, layers=2, height=SIZE[0],
                              width=SIZE[1])
    results.frames = pd.DataFrame(rows)
    return results


def test_write_produces_tables_figures_and_the_section(tmp_path: Path) -> None:
    results, _ = table1_results()
    with_files(results, tmp_path / "results")
    tables, figures = tmp_path / "tables", tmp_path / "figures"
    tables.mkdir()
    figures.mkdir()
    section = h.write(results, tables, figures)
    for name in h.table_names(results.cfg):
        for ext in ("csv", "md"):
            assert (tables / f"{name}.{ext}").stat().st_size > 0
    for name in h.figure_names(results.cfg):
        assert (figures / f"{name}.png").stat().st_size > 0
    assert "figures/hasselgren2020_fig7.png" in section and "figures/hasselgren2020_sample_maps.png" in section
    assert "### Table 1" in section and "Deviations from the paper" in section and "width" in section
    assert "Rows missing" not in section
    fig7 = pd.read_csv(tables / "hasselgren2020_fig7.csv").set_index("curve")
    assert fig7.loc["temporal adaptive", "realised_spp"] == pytest.approx(3.9)
    tpsnr = results.scene_values("ntasd", 4, "tpsnr").mean()
    assert fig7.loc["temporal adaptive", "tpsnr_mean"] == pytest.approx(tpsnr)


def test_write_names_the_missing_rows_and_still_writes_its_outputs(tmp_path: Path) -> None:
    cfg = config()
    results = with_files(build(cfg, Table(cfg, 3), drop=(("dasr", 4), ("ntasd_kpn", 4))), tmp_path / "results")
    tables, figures = tmp_path / "tables", tmp_path / "figures"
    tables.mkdir()
    figures.mkdir()
    section = h.write(results, tables, figures)
    assert "Rows missing at 4 spp" in section and "'dasr'" in section and "'ntasd_kpn'" in section
    for name in h.figure_names(cfg):
        assert (figures / f"{name}.png").stat().st_size > 0
    fig7 = pd.read_csv(tables / "hasselgren2020_fig7.csv").set_index("curve")
    assert fig7.loc["KPN", "status"] == "not run" and fig7.loc["temporal adaptive", "status"] == "ran"
    # Without any row (and without files), the figures are placeholders and the section says so.
    bare = config([r for r in ROWS if not r["method"].startswith(("ntasd", "dasr"))])
    assert h.write(build(bare, Table(bare, 3)), tables, figures).startswith("Not run")
    results = build(cfg, Table(cfg, 3))
    results.results_dir = tmp_path / "empty"
    h.write(results, tables, figures)
    assert all((figures / f"{name}.png").stat().st_size > 0 for name in h.figure_names(cfg))


def test_a_flat_sample_map_is_named_in_the_report(tmp_path: Path) -> None:
    """The spread of a row's sample maps: a map with every pixel but one at 4 spp (what a sampler that has not
    learnt gives) is 'flat'; random counts are not. modal_share and cv computed by hand for the flat case."""
    results, _ = table1_results()
    with_files(results, tmp_path / "results")
    for k, scene in enumerate(results.scenes):
        maps = np.full((FRAMES, *SIZE), 4, np.uint8)
        maps[:, 0, 0] = 32
        np.savez(evaluate.denoised_dir(tmp_path / "results", "ntasd", scene, 4) / SAMPLE_MAPS_FILE,
                 frames=np.arange(FRAMES), sample_maps=maps)
    flat = h.map_spread(results, "ntasd")
    pixels = SIZE[0] * SIZE[1]
    counts = np.full(pixels, 4.0)
    counts[0] = 32
    assert flat["modal_share"] == pytest.approx((pixels - 1) / pixels)
    assert flat["cv"] == pytest.approx(counts.std() / counts.mean())
    assert h.map_spread(results, "dasr")["modal_share"] < h.FLAT_MAP_SHARE     # random counts 0..8
    tables, figures = tmp_path / "tables", tmp_path / "figures"
    tables.mkdir()
    figures.mkdir()
    section = h.write(results, tables, figures)
    assert "NTASD (ntasd): 98.8% of the pixels at one count" in section and "flat: its sampler does not adapt" in section
    assert "DASR (dasr)" in section and section.count("flat: its sampler") == 1


def test_the_image_grids_show_the_adaptive_rows_sample_maps(tmp_path: Path) -> None:
    """Issue 12: sample maps beside the image grids. sample_maps_of reads an adaptive row's maps per frame; a grid
    given a map for one of its columns gains a fourth row (taller figure), one without maps keeps three."""
    from PIL import Image

    from denoisers.report.figures import image_grid, sample_maps_of

    results, _ = table1_results()
    with_files(results, tmp_path / "results")
    scene = results.scenes[0]
    maps = sample_maps_of(tmp_path / "results", "ntasd", scene, 4)
    written = np.load(evaluate.denoised_dir(tmp_path / "results", "ntasd", scene, 4) / SAMPLE_MAPS_FILE)
    assert sorted(maps) == list(range(FRAMES)) and np.array_equal(maps[2], written["sample_maps"][2])
    assert sample_maps_of(tmp_path / "results", "svgf", scene, 4) == {}
    reference = np.ones((3, *SIZE), np.float32)
    columns = [("svgf", reference * 0.9), ("ntasd", reference * 1.1)]
    image_grid(columns, reference, tmp_path / "plain.png", "plain")
    image_grid(columns, reference, tmp_path / "maps.png", "maps", sample_maps=[None, maps[2]])
    plain, with_maps = (Image.open(tmp_path / name).size for name in ("plain.png", "maps.png"))
    assert with_maps[1] > 1.2 * plain[1]
