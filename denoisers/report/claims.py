"""Claims: a paper's statement, the evaluation rows it needs, and how its parts are computed from the results.

A :class:`Claim` names the rows it needs (:class:`RowNeed`); its ``decide`` function builds the parts with
:func:`compare_rows` / :func:`compare_speed` from a run's :class:`~denoisers.report.collect.Results` (seed-averaged
per-scene values, every learned row's seeds and half-budget twin attached), and :func:`claims_table` writes one
row per claim. The statistics and the verdict rule of the parts: denoisers.report.verdicts.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from denoisers.report.verdicts import (INCONCLUSIVE, MAX_SCENES_NEEDED, RULE, SPEED_RULE, Decision, Part, SpeedPart,
                                       not_run, scenes_needed)

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results
    from denoisers.report.seeds import SeedAveraged


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


def training_spp(cfg: dict, model_id: str | None) -> int | None:
    """The spp model ``model_id`` trains at (its ``data.spp``); None for no model or one the config lacks."""
    from denoisers.training.models import model_spec

    if not model_id:
        return None
    try:
        return model_spec(cfg, model_id).data.get("spp")
    except KeyError:
        return None


def row_at(res: Results, need: RowNeed, spp: int) -> str | None:
    """The row of ``need`` to compare at ``spp``: among the matching rows that ran there, one whose model was
    trained at ``spp`` (its ``data.spp``) first, else the first that ran; else the first matching row (so that
    the not-run reason names it); None when no configured row matches. E.g. ``rae`` (trained at 1 spp) at 1, 2, 4
    spp and ``rae_4spp`` (trained at 4) at 4 spp give ``rae_4spp`` at 4 spp and ``rae`` at 1."""
    rows = res.rows_of(need.method, **dict(need.params))
    ran = [row for row in rows if res.ran(row, spp)]

    def trained_at_spp(row: str) -> bool:
        return training_spp(res.cfg, res.spec(row).params.get("model")) == spp

    return next((row for row in ran if trained_at_spp(row)), ran[0] if ran else rows[0] if rows else None)


def missing_rows(res: Results, needs: Sequence[RowNeed]) -> list[RowNeed]:
    return [need for need in needs if res.row_of(need.method, **dict(need.params)) is None]


def evaluate_claim(res: Results, claim: Claim) -> Decision:
    """The claim's decision; 'not run' when a needed row is missing or no decision exists yet."""
    missing = missing_rows(res, claim.needs)
    if missing:
        return not_run("missing rows: " + "; ".join(f"{n.description} (method '{n.method}')" for n in missing))
    if claim.decide is None:
        return not_run("no decision implemented")
    decision = claim.decide(res)
    for part in decision.parts:
        attach_seeds(res, part)
    return decision


def attach_seeds(res: Results, part: Part) -> Part:
    """Fill ``part.seeds`` when its decide function left it unknown: the fewest seeds (Results.seed_rows) of its
    learned rows, 0 without one. A part so filled has no per-seed differences, so a learned part with two or more
    seeds stays undecided (:meth:`Part.seed_problem`) until its decide function computes them."""
    if part.seeds is None:
        part.seeds = seeds_of(res, part.rows)
    return part


def seeds_of(res: SeedAveraged, rows: Sequence[tuple[str, int]]) -> int:
    """The fewest seed rows (Results.seed_rows) among the learned rows of ``rows`` ((row, spp) pairs); 0 when
    none is learned."""
    counts = [len(res.seed_rows(row, spp)) for row, spp in rows if res.learned(row)]
    return min(counts) if counts else 0


def budget_text(res: Results, parts: Sequence[Part]) -> str:
    """The training budget of every trained model the parts use, e.g. 'rae 4000 steps' (the claims table's
    ``budget`` column)."""
    from denoisers.training.models import model_spec

    specs = {spec.id: spec for spec in res.specs}
    if res.volumes is not None:
        specs.update({spec.id: spec for spec in res.volumes.specs})
    models = []
    for part in parts:
        for row, _ in part.rows:
            model = specs[row].params.get("model") if row in specs else None
            if model and model not in models:
                models.append(model)
    texts = []
    for model in models:
        try:
            texts.append(f"{model} {model_spec(res.cfg, model).budget['max_steps']} steps")
        except KeyError:
            texts.append(f"{model} (not configured)")
    return ", ".join(texts)


def seed_differences(a: Sequence[pd.Series], b: Sequence[pd.Series]) -> list[pd.Series]:
    """Per seed k: a[k] - b[k] per scene, a side with one Series paired with every seed of the other."""
    return [a[min(k, len(a) - 1)] - b[min(k, len(b) - 1)] for k in range(max(len(a), len(b)))]


def spp_available(res: Results, spp: int, rows: Sequence[str | None]) -> str:
    """'' if every row ran at ``spp``; else the not-run reason (the claim's stated spp is never substituted)."""
    if spp not in res.cfg["evaluation"]["spp"]:
        return (f"stated at {spp} spp, which was not evaluated (evaluation.spp = {res.cfg['evaluation']['spp']})")
    absent = [str(row) for row in rows if not res.ran(row, spp)]
    return f"no results at {spp} spp for: {', '.join(absent)}" if absent else ""


def compare_rows(res: Results, a: str, b: str, metric: str, spp: int, claimed: str | None = None,
                 b_spp: int | None = None, threshold: float = 0.0, at_half_budget: bool = False) -> Part:
    """Part comparing row a at ``spp`` with row b at ``b_spp`` (default the same) on a per-scene metric, claimed
    beyond ``threshold`` (Part.threshold); with its half-budget comparison (Part.half) when every learned row
    has a half-budget row that ran."""
    b_spp = spp if b_spp is None else b_spp
    part = Part.paired(res.claim_values(a, spp, metric), res.claim_values(b, b_spp, metric), metric,
                       f"{a} @ {spp} spp", f"{b} @ {b_spp} spp", claimed, rows=((a, spp), (b, b_spp)),
                       threshold=threshold, a_seeds=res.claim_values_per_seed(a, spp, metric),
                       b_seeds=res.claim_values_per_seed(b, b_spp, metric), seeds=seeds_of(res, ((a, spp), (b, b_spp))))
    part.at_half_budget = at_half_budget
    half_a, half_b = res.half_row(a, spp), res.half_row(b, b_spp)
    if not at_half_budget and part.seeds and half_a and half_b:
        part.half = compare_rows(res, half_a, half_b, metric, spp, part.claimed, b_spp, threshold, at_half_budget=True)
    return part


def compare_speed(res: Results, a: str, b: str, spp: int, claimed: str = "lower") -> SpeedPart | str:
    """Speed part 'row a @ spp is faster (claimed 'lower') than row b @ spp' from the timing job's per-round
    ratios, or the reason it cannot be decided (no timing job, or a row it did not time)."""
    from denoisers.jobs.timing import speed_ratios

    if res.timing is None:
        return "no timing job output (rule time_methods; evaluation.timing.enabled)"
    row_a, row_b = res.speed(a, spp), res.speed(b, spp)
    if row_a is None or row_b is None:
        absent = [f"{r} @ {spp} spp" for r, row in ((a, row_a), (b, row_b)) if row is None]
        return f"the timing job did not time {', '.join(absent)}"
    ratios = np.asarray(speed_ratios(res.timing, (a, spp), (b, spp)), np.float64)
    # A network's speed does not depend on its training seed: no seed condition.
    return SpeedPart("ms_per_frame", f"{a} @ {spp} spp", f"{b} @ {spp} spp", claimed, np.log(ratios),
                     [f"round {k + 1}" for k in range(len(ratios))], float(row_a["ms_per_frame"]),
                     float(row_b["ms_per_frame"]), ((a, spp), (b, spp)), seeds=0)


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
    learned = [part for part in parts if part.seeds]
    robust = [part.seed_robust for part in learned if part.seed_robust is not None]
    stable = [part.budget_stable for part in learned if part.budget_stable is not None]
    needed = []
    for part in parts:
        if part.outcome == INCONCLUSIVE and not isinstance(part, SpeedPart):
            count = scenes_needed(part.diffs)
            needed.append("–" if count is None else (f"> {MAX_SCENES_NEEDED}" if count > MAX_SCENES_NEEDED
                                                     else str(count)))
        else:
            needed.append("")
    return {"claim": claim.id, "paper": claim.paper, "statement": claim.statement, "verdict": decision.verdict,
            "n": ", ".join(map(str, ns)) if parts else "",
            "seeds": min(part.seeds for part in learned) if learned else "",
            "seed_robust": ("yes" if all(robust) else "no") if robust else "",
            "budget_stable": ("yes" if all(stable) else "no") if stable else "",
            "budget": budget_text(res, parts),
            "scenes_needed": "; ".join(needed) if any(needed) else "",
            "mean_diff_ci_95": "; ".join(p.interval_text() for p in parts),
            "parts": "; ".join(p.claim_text() for p in parts),
            "measured": "; ".join(p.measured_text() for p in parts),
            "facts": "; ".join(f"{f.text}: {'yes' if f.holds else 'NO'} (declared, not measured)"
                               for f in decision.facts),
            "flags": "; ".join(flags),
            "note": decision.not_run or (UNDERTRAINED_NOTE if any(UNDERTRAINED in f for f in flags) else "")
            + decision.seed_note() + decision.holm_note() + decision.note,
            "rule": (RULE + (SPEED_RULE if any(isinstance(p, SpeedPart) for p in parts) else "")) if parts else ""}


UNDERTRAINED = "under-trained"
# Issue 46 §2: the flag is shown, the decision is guarded by budget stability (the `budget_stable` column).
UNDERTRAINED_NOTE = ("involves a model flagged under-trained (still learning at its budget; see flags): "
                     "`budget_stable` says whether the decision holds at half the budget; ")
CLAIM_COLUMNS = ("claim", "paper", "statement", "verdict", "n", "seeds", "seed_robust", "budget_stable", "budget",
                 "mean_diff_ci_95", "scenes_needed", "parts",
                 "measured", "facts", "flags", "note", "rule")


def claims_table(res: Results, claims: Sequence[Claim]) -> pd.DataFrame:
    """Verdict per claim, computed from the results."""
    import pandas as pd

    rows = [claim_row(res, claim, evaluate_claim(res, claim)) for claim in claims]
    return pd.DataFrame(rows, columns=list(CLAIM_COLUMNS))
