"""The harness's quality targets (denoisers/report/targets.py) on constructed per-scene numbers.

Per-scene values are built in memory with tests/test_claims.py's helpers; each case sets the paired differences
so that the expected state of every comparison follows from the rule (95 % t-interval wholly on one side).
"""
from __future__ import annotations

import pytest
from scipy import stats

from denoisers.report import targets
from scenegen.config import validate_config
from tests.test_claims import AGAINST, CLEAR, SPANNING, Table, build, claims_config
from tests.test_isik_report import config as isik_config

TARGETS = {t.id: t for t in targets.TARGETS}


def set_diff(table: Table, a: tuple[str, int], b: tuple[str, int], metric: str, diffs: list[float]) -> None:
    """a's metric = b's + diffs (raw units)."""
    table.values[a][metric] = [v + d for v, d in zip(table.values[b][metric], diffs)]


def test_spanning_fixture_interval_spans_zero_and_clear_does_not() -> None:
    """The fixtures mean what the cases below assume (checked with scipy, independently of the code)."""
    for d, spans in ((CLEAR, False), (SPANNING, True)):
        low, high = stats.t.interval(0.95, len(d) - 1, loc=sum(d) / len(d), scale=stats.sem(d))
        assert (low < 0 < high) == spans


#: FLIP's non-inferiority margin (denoisers.report.stats.NON_INFERIORITY_MARGIN): RAE may be worse by < 0.01.
FLIP_MARGIN = 0.01


def test_flip_fixtures_lie_where_the_cases_below_assume() -> None:
    """scipy's intervals of the FLIP differences against the margin (independent of the code under test)."""
    def interval(d: list[float]) -> tuple[float, float]:
        return stats.t.interval(0.95, len(d) - 1, loc=sum(d) / len(d), scale=stats.sem(d))
    assert interval([0.001 * d for d in SPANNING])[1] < FLIP_MARGIN                      # within the margin
    assert interval([0.01 * d for d in SPANNING])[1] > FLIP_MARGIN > interval([0.01 * d for d in SPANNING])[0]
    assert interval([0.01 * d for d in CLEAR])[0] < FLIP_MARGIN < interval([0.01 * d for d in CLEAR])[1]
    assert interval([0.03 * d for d in CLEAR])[0] > FLIP_MARGIN                          # beyond the margin


@pytest.mark.parametrize("psnr2, flip, expected", [
    (CLEAR, [0.0] * 4, targets.MET),                          # better PSNR, identical FLIP: no worse holds
    (CLEAR, [0.001 * d for d in SPANNING], targets.MET),      # FLIP difference wholly within the margin
    (CLEAR, [0.01 * d for d in SPANNING], targets.OPEN),      # FLIP interval reaches beyond the margin
    (CLEAR, [0.01 * d for d in CLEAR], targets.OPEN),         # worse, but not shown worse by more than 0.01
    (CLEAR, [0.03 * d for d in CLEAR], targets.NOT_MET),      # FLIP wholly worse by more than the margin
    (SPANNING, [0.0] * 4, targets.OPEN),                      # PSNR at 2 spp undecided
    (AGAINST, [0.0] * 4, targets.NOT_MET),                    # PSNR at 2 spp wholly lower
])
def test_t11_rae_against_eaw(psnr2: list[float], flip: list[float], expected: str) -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    set_diff(table, ("rae", 1), ("eaw", 1), "psnr", CLEAR)
    set_diff(table, ("rae", 2), ("eaw", 2), "psnr", psnr2)
    for spp in (1, 2):
        set_diff(table, ("rae", spp), ("eaw", spp), "flip", flip)
    status, parts, reason = targets.decide(build(cfg, table), TARGETS["T11"])
    assert status == expected and not reason
    assert [(p.a, p.b, p.quantity, mode) for p, mode in parts] == [
        ("rae @ 1 spp", "eaw @ 1 spp", "psnr", targets.BETTER), ("rae @ 2 spp", "eaw @ 2 spp", "psnr", targets.BETTER),
        ("rae @ 1 spp", "eaw @ 1 spp", "flip", targets.NO_WORSE), ("rae @ 2 spp", "eaw @ 2 spp", "flip", targets.NO_WORSE)]
    assert parts[0][0].interval[1] == pytest.approx(stats.t.interval(0.95, 3, loc=1.05, scale=stats.sem(CLEAR))[0])


def test_t11_not_run_names_the_missing_spp() -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    status, parts, reason = targets.decide(build(cfg, table, drop=(("eaw", 2),)), TARGETS["T11"])
    assert status == targets.NOT_RUN and not parts and "eaw @ 2 spp" in reason


def test_t12_ntasd_against_svgf_at_4_spp() -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    set_diff(table, ("ntasd", 4), ("svgf", 4), "psnr", CLEAR)
    status, parts, _ = targets.decide(build(cfg, table), TARGETS["T12"])
    assert status == targets.MET and [p.a for p, _ in parts] == ["ntasd @ 4 spp"]
    set_diff(table, ("ntasd", 4), ("svgf", 4), "psnr", AGAINST)
    assert targets.decide(build(cfg, table), TARGETS["T12"])[0] == targets.NOT_MET


def test_t13_needs_afn_and_svgf_rows() -> None:
    cfg = claims_config()
    status, _, reason = targets.decide(build(cfg, Table(cfg, 4)), TARGETS["T13"])
    assert status == targets.NOT_RUN and "full temporal AFN" in reason


def t13_config() -> dict:
    cfg = isik_config()
    cfg["evaluation"]["methods"] = [*cfg["evaluation"]["methods"], {"id": "svgf", "method": "svgf"}]
    return validate_config(cfg)


@pytest.mark.parametrize("trmae, expected", [(-0.01, targets.MET), (0.01, targets.NOT_MET)])
def test_t13_full_afn_against_svgf_and_oidn(trmae: float, expected: str) -> None:
    cfg = t13_config()
    table = Table(cfg, 4)
    for spp in (4, 8):
        set_diff(table, ("afn", spp), ("svgf", spp), "psnr", CLEAR)     # svgf and oidn share the base values
        set_diff(table, ("afn", spp), ("oidn", spp), "trmae", [trmae * d for d in CLEAR])
    status, parts, _ = targets.decide(build(cfg, table), TARGETS["T13"])
    assert status == expected
    assert sorted({p.a for p, _ in parts}) == ["afn @ 4 spp", "afn @ 8 spp"]
    assert {p.b.split(" @ ")[0] for p, _ in parts} == {"svgf", "oidn"} and len(parts) == 6


def test_targets_table_lists_every_target_with_flags() -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    set_diff(table, ("ntasd", 4), ("svgf", 4), "psnr", CLEAR)
    frame = targets.targets_table(build(cfg, table, flagged=("ntasd", 4)))
    assert list(frame["target"]) == ["T11", "T12", "T13"]
    line = frame.set_index("target").loc["T12"]
    assert line["status"] == targets.MET and line["flags"].startswith("ntasd @ 4 spp:") and "beyond" in line["flags"]
    assert frame.set_index("target").loc["T13", "status"] == targets.NOT_RUN
