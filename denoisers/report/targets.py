"""The harness's quality targets: the outcomes its issues expect, decided from paired per-scene differences.

A target is not a paper's claim (those are in denoisers.reproductions); it says what a working harness should
show, e.g. "the RAE beats EAW at 1 and 2 spp". Each target is a list of comparisons ``a - b`` of one metric at
one spp, paired over the evaluated scenes as the claims are (denoisers.report.claims.compare_rows):

* a *better* comparison holds when the 95 % interval of the mean difference lies wholly on the better side of
  0, fails when it lies wholly on the worse side, and is open otherwise;
* a *no worse* comparison is a non-inferiority test at the metric's stated margin δ
  (``stats.NON_INFERIORITY_MARGIN``): it holds when the interval lies wholly on the better side of −δ (a is
  worse by less than δ, if at all), fails when it lies wholly beyond −δ, and is open otherwise.

A target is **met** when every comparison holds, **not met** when any fails, **inconclusive** otherwise, and
**not run** when a row or spp it needs did not run.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from denoisers.report.claims import RowNeed, compare_rows, row_at
from denoisers.report.verdicts import CONTRADICTED, REPRODUCED, Part
from denoisers.report.stats import HIGHER_IS_BETTER, NON_INFERIORITY_MARGIN

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

MET, NOT_MET, OPEN, NOT_RUN = "met", "not met", "inconclusive", "not run"
BETTER, NO_WORSE = "better", "no worse"
RULE = ("paired per-scene difference a−b per comparison; 'better' holds if its 95 % t-interval lies wholly on the "
        "better side of 0 and fails if wholly on the worse side; 'no worse' holds if wholly on the better side of the "
        "metric's non-inferiority margin −δ and fails if wholly beyond it; met = every comparison holds, not met = "
        "any fails")

#: Finds the evaluation row of one side at an spp (None: no such row configured).
RowFinder = Callable[["Results", int], "str | None"]


def by_method(need: RowNeed) -> RowFinder:
    """:func:`denoisers.report.claims.row_at`: a row of ``need`` that ran at the spp (trained there first)."""
    def find(res: Results, spp: int) -> str | None:
        return row_at(res, need, spp)
    return find


def afn_full(res: Results, spp: int) -> str | None:
    """The full temporal AFN model's row (identified by its net settings, as in the Isik module)."""
    from denoisers.reproductions.isik2021 import variant_row

    return variant_row(res, "ours")


@dataclass(frozen=True)
class Comparison:
    """Row ``a`` against row ``b`` on ``metric`` at ``spp``; ``mode`` is BETTER or NO_WORSE."""

    a: RowFinder
    b: RowFinder
    metric: str
    spp: int
    mode: str = BETTER


@dataclass(frozen=True)
class Target:
    id: str
    issue: int
    statement: str
    needs: tuple[tuple[str, RowFinder], ...]   # (description, finder) of every side, for 'not run' reasons
    comparisons: tuple[Comparison, ...]


RAE = by_method(RowNeed("rae", "RAE", (("reset_state_every_frame", None),)))
EAW = by_method(RowNeed("eaw", "EAW"))
SVGF = by_method(RowNeed("svgf", "SVGF"))
OIDN = by_method(RowNeed("oidn", "OIDN"))
NTASD = by_method(RowNeed("ntasd", "NTASD temporal adaptive", (("budget_factor", 1),)))

TARGETS: tuple[Target, ...] = (
    Target("T11", 11, "the RAE beats EAW in PSNR at 1 and 2 spp, and its FLIP is no worse than EAW's",
           (("RAE (method 'rae')", RAE), ("EAW (method 'eaw')", EAW)),
           tuple(Comparison(RAE, EAW, "psnr", spp) for spp in (1, 2))
           + tuple(Comparison(RAE, EAW, "flip", spp, NO_WORSE) for spp in (1, 2))),
    Target("T12", 12, "temporal adaptive NTASD at an average of 4 spp beats SVGF at 4 spp in PSNR",
           (("NTASD (method 'ntasd')", NTASD), ("SVGF (method 'svgf')", SVGF)),
           (Comparison(NTASD, SVGF, "psnr", 4),)),
    Target("T13", 13, "the full temporal AFN beats SVGF and OIDN in PSNR at 4 and 8 spp, and its TRMAE is lower "
           "than OIDN's", (("full temporal AFN (method 'afn', net defaults)", afn_full), ("SVGF (method 'svgf')", SVGF),
                           ("OIDN (method 'oidn')", OIDN)),
           tuple(Comparison(afn_full, other, "psnr", spp) for spp in (4, 8) for other in (SVGF, OIDN))
           + tuple(Comparison(afn_full, OIDN, "trmae", spp) for spp in (4, 8))),
)


def comparison_state(part: Part, mode: str) -> str:
    """MET (holds), NOT_MET (fails) or OPEN for one measured comparison (a learned one needs its seeds:
    Part.decided)."""
    outcome = part.decided
    if outcome == CONTRADICTED:
        return NOT_MET
    if outcome == REPRODUCED:
        return MET
    return OPEN


def decide(res: Results, target: Target) -> tuple[str, list[tuple[Part, str]], str]:
    """(status, [(part, mode)], not-run reason) of one target."""
    missing = sorted({text for text, finder in target.needs
                      for comp in target.comparisons if finder in (comp.a, comp.b) and finder(res, comp.spp) is None})
    if missing:
        return NOT_RUN, [], "missing rows: " + "; ".join(missing)
    absent = sorted({f"{row} @ {comp.spp} spp" for comp in target.comparisons
                     for row in (comp.a(res, comp.spp), comp.b(res, comp.spp)) if not res.ran(row, comp.spp)})
    if absent:
        return NOT_RUN, [], "no results for " + ", ".join(absent)
    parts = []
    for comp in target.comparisons:
        better = "higher" if HIGHER_IS_BETTER.get(comp.metric, True) else "lower"
        # "no worse": a - b beyond -delta on the better side (the margin moves the bound to the worse side).
        threshold = 0.0 if comp.mode == BETTER else (-1.0 if better == "higher" else 1.0) * \
            NON_INFERIORITY_MARGIN[comp.metric]
        parts.append((compare_rows(res, comp.a(res, comp.spp), comp.b(res, comp.spp), comp.metric, comp.spp, better,
                                   threshold=threshold), comp.mode))
    states = [comparison_state(part, mode) for part, mode in parts]
    status = MET if all(s == MET for s in states) else NOT_MET if NOT_MET in states else OPEN
    return status, parts, ""


def targets_table(res: Results, targets: tuple[Target, ...] = TARGETS) -> pd.DataFrame:
    """One line per target: status, each comparison with its interval and state, flags of the rows used."""
    import pandas as pd

    lines = []
    for target in targets:
        status, parts, reason = decide(res, target)
        flags = []
        for part, _ in parts:
            for row, spp in part.rows:
                text = res.flag(row, spp)               # names the row and spp itself
                if text and text not in flags:
                    flags.append(text)
        lines.append({
            "target": target.id, "issue": target.issue, "statement": target.statement, "status": status,
            "comparisons": "; ".join(f"{p.a} − {p.b} ({LABEL[mode]} {p.quantity}): {comparison_state(p, mode)}"
                                     for p, mode in parts),
            "mean_diff_ci_95": "; ".join(p.interval_text() for p, _ in parts),
            "measured": "; ".join(p.measured_text() for p, _ in parts),
            "n": ", ".join(map(str, sorted({p.n for p, _ in parts}))),
            "flags": "; ".join(flags),
            "note": reason + "".join(f"; {p.seed_problem()}" for p, _ in parts if p.seed_problem())})
    return pd.DataFrame(lines, columns=list(COLUMNS))


LABEL = {BETTER: "better", NO_WORSE: "no worse"}
COLUMNS = ("target", "issue", "statement", "status", "n", "comparisons", "mean_diff_ci_95", "measured", "flags",
           "note")
SHOWN = ("target", "statement", "status", "n", "comparisons", "mean_diff_ci_95", "flags", "note")
