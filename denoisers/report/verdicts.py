"""Verdicts of measured comparisons: a claim part's paired statistics and the decision rule of a claim.

The units are the evaluated scenes (``Results.scenes``: the test scenes and the external XML scenes, each
an independent scene; nothing here depends on which kind a unit is). A claim has one or more measured
*parts*; each part is a paired comparison ``a - b`` of one quantity per scene with a claimed direction.
Its outcome:

* ``reproduced``   -- n >= :data:`MIN_UNITS` and the 95 % Student-t interval of the mean paired
  difference lies wholly on the claimed side of 0;
* ``contradicted`` -- n >= MIN_UNITS and the interval lies wholly on the other side;
* ``inconclusive`` -- otherwise (the interval touches or spans 0, or n < MIN_UNITS).

Speed parts (:class:`SpeedPart`) are the exception: the timing job times every row on one scene in
interleaved rounds, so their units are the rounds and the statistic is the per-round log time ratio
ln(a / b), with the same t-interval (shown back as a ratio), and at least :data:`MIN_SPEED_ROUNDS` rounds.

A claim is reproduced when every part is (an intersection-union test: no multiplicity correction is
needed), ``not run`` when a row, spp or model it needs is missing. It is contradicted when at least one
part is contradicted *after Holm's correction over its parts*: each part's one-sided p-value for the
other side (t-test of its mean difference) is compared, smallest first, with 0.025 / (m - i), the one-sided
level of the 95 % interval shared among the m parts. A single-part claim is contradicted exactly when its
interval lies wholly on the other side. Otherwise inconclusive.

Frame metrics enter a part as each clip's mean over its steady frames (``Results.claim_values``: the first
``evaluation.warmup_frames`` frames of a clip and after each camera cut are left out for every method, since
a temporal method is still warming up there). Means shown beside a part are over the scenes it is decided on
(the joined scenes of a and b). For an
inconclusive part, :func:`scenes_needed` is the number of scenes at which a t-interval with the observed
mean difference and spread would exclude 0.
*Facts* (:class:`Fact`, e.g. "needs no training", read from the method registry) are shown beside the parts and
do not decide the verdict. Which parts a claim has and how its rows are found: denoisers.report.claims.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from denoisers.report.stats import HIGHER_IS_BETTER, LABELS, fmt, mean_ci

if TYPE_CHECKING:
    import pandas as pd

REPRODUCED, CONTRADICTED, INCONCLUSIVE, NOT_RUN = "reproduced", "contradicted", "inconclusive", "not run"
VERDICTS = (REPRODUCED, CONTRADICTED, INCONCLUSIVE, NOT_RUN)
MIN_UNITS = 3
MIN_SPEED_ROUNDS = 5
#: Training seeds a part with a learned row needs before it can be decided (issue 46: at least 3).
MIN_SEEDS = 3
#: One-sided level of each side of the 95 % two-sided interval; Holm shares it among a claim's parts.
ALPHA_ONE_SIDED = 0.025
#: Largest scene count :func:`scenes_needed` searches (beyond it: "more than" this).
MAX_SCENES_NEEDED = 10_000
RULE = (f"each part: paired per-scene difference a−b of steady-frame means (warm-up frames of each shot left out); reproduced if its 95 % t-interval lies wholly on the "
        f"claimed side of 0 (n ≥ {MIN_UNITS}), contradicted if wholly on the other side, else inconclusive; "
        "the claim needs every part and is contradicted when a part is after Holm's correction over its parts; "
        f"a part with a trained model is decided on seed-averaged per-scene values, needs ≥ {MIN_SEEDS} seeds and "
        "must be seed-robust (each seed alone on the decided side), else inconclusive")
SPEED_RULE = (f"; a speed part: per-round log time ratio ln(a/b) of the timing job, t-interval over ≥ {MIN_SPEED_ROUNDS} "
              "rounds, shown as a ratio")


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
    #: The claimed bound: a - b > threshold ('higher') or < threshold ('lower'); 0 unless a claim states a
    #: margin ("much worse": a positive margin on the claimed side; "no worse": the non-inferiority margin on
    #: the other side).
    threshold: float = 0.0
    #: Training seeds behind the part's trained models (the fewest of its learned rows'); 0: no learned row;
    #: None: not known yet (:func:`attach_seeds` fills it from the rows).
    seeds: int | None = None
    #: Per seed k (seed k of every learned side; a side without seeds repeats): mean of a - b over the scenes.
    seed_means: tuple[float, ...] = ()
    #: The same comparison with every learned row's half-budget twin (training.half_budget); None: not made.
    half: Part | None = None
    #: Whether this part is itself the half-budget comparison of another (it is not checked at half again).
    at_half_budget: bool = False

    @classmethod
    def paired(cls, a: pd.Series, b: pd.Series, quantity: str, a_label: str, b_label: str,
               claimed: str | None = None, rows: Sequence[tuple[str, int]] = (), threshold: float = 0.0,
               a_seeds: Sequence[pd.Series] = (), b_seeds: Sequence[pd.Series] = (), seeds: int | None = None) -> Part:
        """From two per-scene series (indexed by scene); ``claimed`` defaults to 'a is better' for the metric.
        ``a_seeds`` / ``b_seeds``: the same per seed (a side with one entry is paired with every seed of the
        other), for the seed-robustness of a part with ``seeds`` trained seeds."""
        if claimed is None:
            claimed = "higher" if HIGHER_IS_BETTER.get(quantity, True) else "lower"
        if claimed not in ("higher", "lower"):
            raise ValueError(f"claimed must be 'higher' or 'lower', got {claimed!r}")
        joined = a.to_frame("a").join(b.to_frame("b"), how="inner").astype(float).dropna()
        seed_means = []
        for k in range(max(len(a_seeds), len(b_seeds)) if a_seeds and b_seeds else 0):
            one = a_seeds[min(k, len(a_seeds) - 1)].to_frame("a").join(
                b_seeds[min(k, len(b_seeds) - 1)].to_frame("b"), how="inner").astype(float).dropna()
            seed_means.append(float((one["a"] - one["b"]).mean()))
        return cls(quantity, a_label, b_label, claimed, (joined["a"] - joined["b"]).to_numpy(np.float64),
                   [str(u) for u in joined.index], float(joined["a"].mean()), float(joined["b"].mean()),
                   tuple(rows), float(threshold), seeds, tuple(seed_means))

    @property
    def n(self) -> int:
        return len(self.diffs)

    @property
    def interval(self) -> tuple[float, float, float]:
        mean, low, high, _ = mean_ci(self.diffs)
        return mean, low, high

    @property
    def min_units(self) -> int:
        return MIN_UNITS

    @property
    def p_other_side(self) -> float:
        """One-sided p-value of the t-test that the mean difference lies on the side opposite to the claim
        (small: evidence against the claim); NaN with fewer than two units. Zero spread: 0 when the mean is
        on the other side, 1 when on the claimed side, 0.5 at exactly 0."""
        from scipy import stats

        if self.n < 2:
            return math.nan
        sign = 1.0 if self.claimed == "higher" else -1.0
        mean, spread = float(np.mean(self.diffs)) - self.threshold, float(np.std(self.diffs, ddof=1))
        if spread == 0.0:
            return 0.5 if mean == 0.0 else (0.0 if sign * mean < 0 else 1.0)
        t_value = sign * mean / (spread / math.sqrt(self.n))
        return float(stats.t.cdf(t_value, self.n - 1))

    @property
    def outcome(self) -> str:
        mean, low, high = self.interval
        if self.n < self.min_units or math.isnan(low):
            return INCONCLUSIVE
        sign = 1.0 if self.claimed == "higher" else -1.0
        low, high = low - self.threshold, high - self.threshold
        if sign * low > 0 and sign * high > 0:
            return REPRODUCED
        if sign * low < 0 and sign * high < 0:
            return CONTRADICTED
        return INCONCLUSIVE

    def seed_problem(self) -> str:
        """'' when the part's outcome stands for its trained models' seeds; else why not: fewer than
        :data:`MIN_SEEDS` seeds, or a seed whose own mean difference is not on the decided side (seed-sensitive).
        Parts without a learned row, and undecided parts, have none."""
        outcome = self.outcome
        if not self.seeds or outcome not in (REPRODUCED, CONTRADICTED):
            return ""
        if self.seeds < MIN_SEEDS:
            return (f"{self.a} vs {self.b}: {self.seeds} training seed(s), fewer than the {MIN_SEEDS} a learned "
                    "verdict needs (training.seeds)")
        if len(self.seed_means) < self.seeds:
            return f"{self.a} vs {self.b}: the per-seed differences are not computed (seed-robustness unknown)"
        side = self.claimed if outcome == REPRODUCED else ("lower" if self.claimed == "higher" else "higher")
        sign = 1.0 if side == "higher" else -1.0
        off = [k for k, mean in enumerate(self.seed_means) if not sign * (mean - self.threshold) > 0]
        if not off:
            return ""
        means = ", ".join(fmt(mean, self.quantity) for mean in self.seed_means)
        return (f"{self.a} vs {self.b}: seed-sensitive (seed(s) {', '.join(map(str, off))} alone not on the "
                f"{outcome} side; per-seed mean a−b: {means})")

    def budget_problem(self) -> str:
        """'' when the part's outcome is the same at half its trained models' budget (:attr:`half`); else why
        not: not compared at half the budget, or another decision there (budget-sensitive). Parts without a
        learned row, undecided parts and half-budget parts themselves have none."""
        outcome = self.outcome
        if not self.seeds or self.at_half_budget or outcome not in (REPRODUCED, CONTRADICTED):
            return ""
        if self.half is None:
            return (f"{self.a} vs {self.b}: not compared at half the training budget (training.half_budget), so "
                    "not known to be budget-stable")
        if self.half.decided != outcome:
            return (f"{self.a} vs {self.b}: budget-sensitive (at half the budget {self.half.decided}: "
                    f"{self.half.interval_text()})")
        return ""

    @property
    def decided(self) -> str:
        """:attr:`outcome`, except inconclusive when :meth:`seed_problem` says the seeds do not carry it or
        :meth:`budget_problem` that half the budget decides otherwise."""
        return INCONCLUSIVE if self.seed_problem() or self.budget_problem() else self.outcome

    @property
    def budget_stable(self) -> bool | None:
        """Whether the decision is the same at half the budget (None: no learned row, or no decided outcome)."""
        if not self.seeds or self.at_half_budget or self.outcome not in (REPRODUCED, CONTRADICTED):
            return None
        return not self.budget_problem()

    @property
    def seed_robust(self) -> bool | None:
        """Whether every seed alone lies on the decided side (None: no learned row, or no decided outcome)."""
        if not self.seeds or self.outcome not in (REPRODUCED, CONTRADICTED):
            return None
        return not self.seed_problem()

    def measured_text(self) -> str:
        label = LABELS.get(self.quantity, self.quantity)
        return f"{label}: {self.a} {fmt(self.mean_a, self.quantity)} vs {self.b} {fmt(self.mean_b, self.quantity)}"

    def interval_text(self) -> str:
        mean, low, high = self.interval
        if math.isnan(low):
            return f"{fmt(mean, self.quantity)} (no interval)"
        return f"{fmt(mean, self.quantity)} [{fmt(low, self.quantity)}, {fmt(high, self.quantity)}]"

    def claim_text(self) -> str:
        bound = fmt(self.threshold, self.quantity) if self.threshold else "0"
        return f"{self.a} − {self.b} {'>' if self.claimed == 'higher' else '<'} {bound} ({self.outcome})"


@dataclass
class SpeedPart(Part):
    """A speed part: per-round log time ratios ln(ms_a / ms_b) of the timing job (``diffs``), claimed < 0 (a
    faster, 'lower') or > 0 ('higher'); decided like a Part with the rounds as units (at least
    MIN_SPEED_ROUNDS) and shown as ratios exp(.)."""

    @property
    def min_units(self) -> int:
        return MIN_SPEED_ROUNDS

    def measured_text(self) -> str:
        return (f"ms/frame (timing job, median over {self.n} rounds): {self.a} {fmt(self.mean_a, 'ms_per_frame')} "
                f"vs {self.b} {fmt(self.mean_b, 'ms_per_frame')}")

    def interval_text(self) -> str:
        mean, low, high = self.interval
        if math.isnan(low):
            return f"time ratio {math.exp(mean):.3g} over {self.n} rounds (no interval)"
        return f"time ratio {math.exp(mean):.3g} [{math.exp(low):.3g}, {math.exp(high):.3g}] over {self.n} rounds"

    def claim_text(self) -> str:
        return f"{self.a} / {self.b} time {'<' if self.claimed == 'lower' else '>'} 1 ({self.outcome})"


def holm_rejected(p_values: Sequence[float], alpha: float = ALPHA_ONE_SIDED) -> list[bool]:
    """Holm's step-down procedure: which hypotheses are rejected at family-wise level ``alpha``. Sorted
    ascending, p_(i) (i = 0..m-1) is rejected while p_(i) <= alpha / (m - i); the first that is not stops it.
    NaN p-values are never rejected."""
    order = sorted(range(len(p_values)), key=lambda k: (math.isnan(p_values[k]), p_values[k]))
    rejected = [False] * len(p_values)
    m = len(p_values)
    for rank, index in enumerate(order):
        p = p_values[index]
        if math.isnan(p) or p > alpha / (m - rank):
            break
        rejected[index] = True
    return rejected


def scenes_needed(diffs: Sequence[float], confidence: float = 0.95) -> int | None:
    """The smallest number of scenes n at which a Student-t interval with the observed mean difference and
    standard deviation would exclude 0: t_{(1+c)/2, n-1} s / sqrt(n) < |mean|. None when it cannot (fewer than
    two values, or a zero mean); MAX_SCENES_NEEDED + 1 when it needs more than that."""
    from scipy import stats

    data = np.asarray(diffs, dtype=np.float64)
    if len(data) < 2:
        return None
    mean, spread = abs(float(data.mean())), float(data.std(ddof=1))
    if mean == 0.0:
        return None
    if spread == 0.0:
        return 2
    quantile = 0.5 + confidence / 2.0
    for n in range(2, MAX_SCENES_NEEDED + 1):
        if stats.t.ppf(quantile, n - 1) * spread / math.sqrt(n) < mean:
            return n
    return MAX_SCENES_NEEDED + 1


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
    def contradicting_parts(self) -> list[bool]:
        """Per part: contradicted after Holm's correction over the claim's parts (see the module docstring)."""
        # Holm over all m parts; a part with too few units has no p-value (never rejected) but counts in m.
        family = [part.p_other_side if part.n >= part.min_units else math.nan for part in self.parts]
        return [part.decided == CONTRADICTED and hit for part, hit in zip(self.parts, holm_rejected(family))]

    @property
    def verdict(self) -> str:
        if self.not_run or not self.parts:
            return NOT_RUN
        outcomes = [part.decided for part in self.parts]
        if all(o == REPRODUCED for o in outcomes):
            return REPRODUCED
        if any(self.contradicting_parts):
            return CONTRADICTED
        return INCONCLUSIVE

    def holm_note(self) -> str:
        """Why a part whose interval lies on the other side does not contradict the claim ('' otherwise)."""
        kept = [part for part, hit in zip(self.parts, self.contradicting_parts)
                if part.decided == CONTRADICTED and not hit]
        if not kept:
            return ""
        return (f"{len(kept)} part(s) on the other side do not survive Holm's correction over {len(self.parts)} "
                f"parts ({'; '.join(part.claim_text() for part in kept)}); ")


    def seed_note(self) -> str:
        """Why parts whose interval is decided do not decide the claim: too few seeds, seed-sensitive, not
        compared at half the budget or budget-sensitive."""
        problems = [problem for part in self.parts for problem in (part.seed_problem(), part.budget_problem())
                    if problem]
        return "".join(f"{problem}; " for problem in problems)


def not_run(reason: str) -> Decision:
    return Decision(not_run=reason)
