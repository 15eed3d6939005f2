"""Claims and their verdicts: every claim is decided from paired differences over independent units.

The units are the evaluated scenes (``Results.scenes``: the test scenes and the external XML scenes, each
an independent scene; nothing here depends on which kind a unit is). A claim has one or more measured
*parts*; each part is a paired comparison ``a - b`` of one quantity per scene with a claimed direction.
Its outcome:

* ``reproduced``   -- n >= :data:`MIN_UNITS` and the 95 % Student-t interval of the mean paired
  difference lies wholly on the claimed side of 0;
* ``contradicted`` -- n >= MIN_UNITS and the interval lies wholly on the other side;
* ``inconclusive`` -- otherwise (the interval touches or spans 0, or n < MIN_UNITS).

Speed parts (:class:`SpeedPart`) are the exception: the timing job times every row on one scene in
interleaved rounds, so their units are the rounds and the statistic is the per-round time ratio a / b;
reproduced when every round's ratio is on the claimed side of 1 (the whole spread), contradicted when
every round's is on the other side, inconclusive otherwise or with fewer than MIN_UNITS rounds.

A claim is reproduced when every part is, contradicted when any part is (a conjunction with one false
part is false), inconclusive otherwise, and ``not run`` when a row, spp or model it needs is missing.
*Facts* (e.g. "needs no training", read from the method registry) are shown beside the parts and do
not decide the verdict.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from denoisers.report.stats import HIGHER_IS_BETTER, LABELS, fmt, mean_ci

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

REPRODUCED, CONTRADICTED, INCONCLUSIVE, NOT_RUN = "reproduced", "contradicted", "inconclusive", "not run"
VERDICTS = (REPRODUCED, CONTRADICTED, INCONCLUSIVE, NOT_RUN)
MIN_UNITS = 3
RULE = (f"each part: paired per-scene difference a−b; reproduced if its 95 % t-interval lies wholly on the "
        f"claimed side of 0 (n ≥ {MIN_UNITS}), contradicted if wholly on the other side, else inconclusive; "
        "the claim needs every part")
SPEED_RULE = (f"; a speed part: per-round time ratio a/b of the timing job, reproduced if every round's ratio is on "
              f"the claimed side of 1 (≥ {MIN_UNITS} rounds)")


@dataclass
class Part:
    """One measured part of a claim: ``a - b`` per unit (scene), claimed ``> 0`` (better='higher') or ``< 0``."""

    quantity: str                 # metric name (sets the formatting), e.g. 'rmse'
    a: str                        # label of side a, e.g. 'rae @ 1 spp'
    b: str
    claimed: str                  # 'higher' (a - b > 0) or 'lower' (a - b < 0)
    diffs: np.ndarray             # per-unit differences, NaN-free
    units: list[str]
    mean_a: float
    mean_b: float
    rows: tuple[tuple[str, int], ...] = ()   # (row id, spp) the part is computed from (for flags)

    @classmethod
    def paired(cls, a: pd.Series, b: pd.Series, quantity: str, a_label: str, b_label: str,
               claimed: str | None = None, rows: Sequence[tuple[str, int]] = ()) -> Part:
        """From two per-scene series (indexed by scene); ``claimed`` defaults to 'a is better' for the metric."""
        if claimed is None:
            claimed = "higher" if HIGHER_IS_BETTER.get(quantity, True) else "lower"
        if claimed not in ("higher", "lower"):
            raise ValueError(f"claimed must be 'higher' or 'lower', got {claimed!r}")
        joined = a.to_frame("a").join(b.to_frame("b"), how="inner").astype(float).dropna()
        return cls(quantity, a_label, b_label, claimed, (joined["a"] - joined["b"]).to_numpy(np.float64),
                   [str(u) for u in joined.index], float(a.mean()), float(b.mean()), tuple(rows))

    @property
    def n(self) -> int:
        return len(self.diffs)

    @property
    def interval(self) -> tuple[float, float, float]:
        mean, low, high, _ = mean_ci(self.diffs)
        return mean, low, high

    @property
    def outcome(self) -> str:
        mean, low, high = self.interval
        if self.n < MIN_UNITS or math.isnan(low):
            return INCONCLUSIVE
        sign = 1.0 if self.claimed == "higher" else -1.0
        if sign * low > 0 and sign * high > 0:
            return REPRODUCED
        if sign * low < 0 and sign * high < 0:
            return CONTRADICTED
        return INCONCLUSIVE

    def measured_text(self) -> str:
        label = LABELS.get(self.quantity, self.quantity)
        return f"{label}: {self.a} {fmt(self.mean_a, self.quantity)} vs {self.b} {fmt(self.mean_b, self.quantity)}"

    def interval_text(self) -> str:
        mean, low, high = self.interval
        if math.isnan(low):
            return f"{fmt(mean, self.quantity)} (no interval)"
        return f"{fmt(mean, self.quantity)} [{fmt(low, self.quantity)}, {fmt(high, self.quantity)}]"

    def claim_text(self) -> str:
        return f"{self.a} − {self.b} {'>' if self.claimed == 'higher' else '<'} 0 ({self.outcome})"


@dataclass
class SpeedPart(Part):
    """A speed part: per-round ratios ms_a / ms_b of the timing job (``diffs`` holds the ratios), claimed
    < 1 (a faster, 'lower') or > 1 ('higher'); decided on the whole spread of the ratios."""

    @property
    def interval(self) -> tuple[float, float, float]:
        if not self.n:
            return math.nan, math.nan, math.nan
        return float(np.median(self.diffs)), float(self.diffs.min()), float(self.diffs.max())

    @property
    def outcome(self) -> str:
        _, low, high = self.interval
        if self.n < MIN_UNITS or math.isnan(low):
            return INCONCLUSIVE
        faster = high < 1.0 and low < 1.0
        slower = low > 1.0 and high > 1.0
        if (faster and self.claimed == "lower") or (slower and self.claimed == "higher"):
            return REPRODUCED
        if faster or slower:
            return CONTRADICTED
        return INCONCLUSIVE

    def measured_text(self) -> str:
        return (f"ms/frame (timing job, median over {self.n} rounds): {self.a} {fmt(self.mean_a, 'ms_per_frame')} "
                f"vs {self.b} {fmt(self.mean_b, 'ms_per_frame')}")

    def interval_text(self) -> str:
        median, low, high = self.interval
        return f"time ratio {median:.3g} [{low:.3g}, {high:.3g}] over {self.n} rounds"

    def claim_text(self) -> str:
        return f"{self.a} / {self.b} time {'<' if self.claimed == 'lower' else '>'} 1 ({self.outcome})"


@dataclass
class Fact:
    """A declared property that is part of a claim's statement but not a measurement."""

    text: str
    holds: bool


@dataclass
class Decision:
    """What a claim's decide function found: its parts and facts, or why it could not run."""

    parts: list[Part] = field(default_factory=list)
    facts: list[Fact] = field(default_factory=list)
    note: str = ""
    not_run: str = ""            # non-empty: a needed row, spp or model is missing (the reason)

    @property
    def verdict(self) -> str:
        if self.not_run or not self.parts:
            return NOT_RUN
        outcomes = [part.outcome for part in self.parts]
        if all(o == REPRODUCED for o in outcomes):
            return REPRODUCED
        if any(o == CONTRADICTED for o in outcomes):
            return CONTRADICTED
        return INCONCLUSIVE


def not_run(reason: str) -> Decision:
    return Decision(not_run=reason)


@dataclass(frozen=True)
class RowNeed:
    """An evaluation row a claim needs: a registry method (with params, e.g. a model id), described."""

    method: str
    description: str
    params: tuple[tuple[str, object], ...] = ()


@dataclass
class Claim:
    """One row of the claims table. ``decide`` computes the decision from the results; while the paper's
    methods are not built, ``decide`` is None and the row is 'not run' naming the missing rows."""

    id: str
    paper: str
    statement: str
    needs: tuple[RowNeed, ...] = ()
    decide: Callable[[Results], Decision] | None = None


def missing_rows(res: Results, needs: Sequence[RowNeed]) -> list[RowNeed]:
    return [need for need in needs if res.row_of(need.method, **dict(need.params)) is None]


def evaluate_claim(res: Results, claim: Claim) -> Decision:
    """The claim's decision; 'not run' when a needed row is missing or no decision exists yet."""
    missing = missing_rows(res, claim.needs)
    if missing:
        return not_run("missing rows: " + "; ".join(f"{n.description} (method '{n.method}')" for n in missing))
    if claim.decide is None:
        return not_run("no decision implemented")
    return claim.decide(res)


def spp_available(res: Results, spp: int, rows: Sequence[str | None]) -> str:
    """'' if every row ran at ``spp``; else the not-run reason (the claim's stated spp is never substituted)."""
    if spp not in res.cfg["evaluation"]["spp"]:
        return (f"stated at {spp} spp, which was not evaluated (evaluation.spp = {res.cfg['evaluation']['spp']})")
    absent = [str(row) for row in rows if not res.ran(row, spp)]
    return f"no results at {spp} spp for: {', '.join(absent)}" if absent else ""


def compare_rows(res: Results, a: str, b: str, metric: str, spp: int, claimed: str | None = None,
                 b_spp: int | None = None) -> Part:
    """Part comparing row a at ``spp`` with row b at ``b_spp`` (default the same) on a per-scene metric."""
    b_spp = spp if b_spp is None else b_spp
    return Part.paired(res.scene_values(a, spp, metric), res.scene_values(b, b_spp, metric), metric,
                       f"{a} @ {spp} spp", f"{b} @ {b_spp} spp", claimed, rows=((a, spp), (b, b_spp)))


def compare_speed(res: Results, a: str, b: str, spp: int, claimed: str = "lower") -> SpeedPart | str:
    """Speed part 'row a @ spp is faster (claimed 'lower') than row b @ spp' from the timing job's per-round
    ratios, or the reason it cannot be decided (no timing job, or a row it did not time)."""
    from denoisers.timing import speed_ratios

    if res.timing is None:
        return "no timing job output (rule time_methods; evaluation.timing.enabled)"
    row_a, row_b = res.speed(a, spp), res.speed(b, spp)
    if row_a is None or row_b is None:
        absent = [f"{r} @ {spp} spp" for r, row in ((a, row_a), (b, row_b)) if row is None]
        return f"the timing job did not time {', '.join(absent)}"
    ratios = speed_ratios(res.timing, (a, spp), (b, spp))
    return SpeedPart("ms_per_frame", f"{a} @ {spp} spp", f"{b} @ {spp} spp", claimed, ratios,
                     [f"round {k + 1}" for k in range(len(ratios))], float(row_a["ms_per_frame"]),
                     float(row_b["ms_per_frame"]), ((a, spp), (b, spp)))


def claim_row(res: Results, claim: Claim, decision: Decision) -> dict[str, object]:
    """One row of claims.csv."""
    parts = decision.parts
    flags = []
    for part in parts:
        for row, spp in part.rows:
            text = res.flag(row, spp)
            if text and text not in flags:
                flags.append(text)
    ns = sorted({part.n for part in parts})
    return {"claim": claim.id, "paper": claim.paper, "statement": claim.statement, "verdict": decision.verdict,
            "n": ", ".join(map(str, ns)) if parts else "",
            "mean_diff_ci_95": "; ".join(p.interval_text() for p in parts),
            "parts": "; ".join(p.claim_text() for p in parts),
            "measured": "; ".join(p.measured_text() for p in parts),
            "facts": "; ".join(f"{f.text}: {'yes' if f.holds else 'NO'} (declared, not measured)"
                               for f in decision.facts),
            "flags": "; ".join(flags),
            "note": decision.not_run or (UNDERTRAINED_NOTE if any(UNDERTRAINED in f for f in flags) else "")
            + decision.note,
            "rule": (RULE + (SPEED_RULE if any(isinstance(p, SpeedPart) for p in parts) else "")) if parts else ""}


UNDERTRAINED = "under-trained"
UNDERTRAINED_NOTE = ("involves an under-trained model (see flags): the verdict tests the training budget, not the "
                     "method; ")
CLAIM_COLUMNS = ("claim", "paper", "statement", "verdict", "n", "mean_diff_ci_95", "parts", "measured", "facts",
                 "flags", "note", "rule")


def claims_table(res: Results, claims: Sequence[Claim]) -> pd.DataFrame:
    """Verdict per claim, computed from the results."""
    import pandas as pd

    rows = [claim_row(res, claim, evaluate_claim(res, claim)) for claim in claims]
    return pd.DataFrame(rows, columns=list(CLAIM_COLUMNS))
