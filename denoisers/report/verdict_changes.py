"""What moved between two published runs of a config: the claims tally of each and every claim whose verdict
changed, with both runs' evidence (n, paired difference with its interval) and the new run's note.

``publish_run`` writes it as ``runs/<name>/CHANGES.md`` when it replaces an earlier published run, and records
the earlier run's commit, date and tally in ``run.json`` (``previous``), so the README shows both tallies.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import pandas as pd

CHANGES_FILE = "CHANGES.md"
#: Verdict order of a tally (others follow in the order met).
VERDICT_ORDER = ("reproduced", "contradicted", "inconclusive", "not run")


def tally(claims: pd.DataFrame) -> dict[str, int]:
    """Verdict -> number of claims, in :data:`VERDICT_ORDER` (zero counts kept), then any other verdict."""
    counts = claims["verdict"].value_counts().to_dict()
    ordered = {verdict: int(counts.pop(verdict, 0)) for verdict in VERDICT_ORDER}
    return {**ordered, **{str(k): int(v) for k, v in counts.items()}}


def tally_text(counts: dict[str, int]) -> str:
    """'7 reproduced, 1 contradicted, 9 inconclusive, 5 not run' (:data:`VERDICT_ORDER` first, whatever the
    mapping's order: run.json stores it with sorted keys)."""
    order = [v for v in VERDICT_ORDER if v in counts] + [v for v in counts if v not in VERDICT_ORDER]
    return ", ".join(f"{counts[verdict]} {verdict}" for verdict in order)


def moved(old: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """One row per claim whose verdict differs (a claim in one run only counts as moved from / to 'absent'):
    claim, statement, old / new verdict, old / new n and paired difference, the new note."""
    import pandas as pd

    columns = ["claim", "statement", "old_verdict", "new_verdict", "old_n", "new_n", "old_diff", "new_diff",
               "new_note"]
    joined = old.set_index("claim").add_suffix("_old").join(new.set_index("claim").add_suffix("_new"), how="outer")
    rows: list[dict[str, Any]] = []
    for claim, row in joined.iterrows():
        before = row.get("verdict_old") if isinstance(row.get("verdict_old"), str) else "absent"
        after = row.get("verdict_new") if isinstance(row.get("verdict_new"), str) else "absent"
        if before == after:
            continue
        statement = row.get("statement_new") if isinstance(row.get("statement_new"), str) else row.get("statement_old")
        rows.append({"claim": claim, "statement": statement, "old_verdict": before, "new_verdict": after,
                     "old_n": row.get("n_old"), "new_n": row.get("n_new"), "old_diff": row.get("mean_diff_ci_95_old"),
                     "new_diff": row.get("mean_diff_ci_95_new"), "new_note": row.get("note_new")})
    return pd.DataFrame(rows, columns=columns)


def _cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and value != value):
        return ""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return str(value).replace("|", "\\|").replace("\n", " ")


def changes_markdown(old: pd.DataFrame, new: pd.DataFrame, old_label: str, new_label: str) -> str:
    """CHANGES.md: both tallies and the claims that moved (``*_label``: e.g. 'code 7c89cb4, 2026-12-04')."""
    changed = moved(old, new)
    lines = ["# Verdicts that moved", "",
             f"Against the previously published run of this config ({old_label}); this run: {new_label}.", "",
             "| run | " + " | ".join(VERDICT_ORDER) + " | claims |", "|---|" + "---|" * (len(VERDICT_ORDER) + 1)]
    for label, claims in ((f"previous ({old_label})", old), (f"this ({new_label})", new)):
        counts = tally(claims)
        lines.append(f"| {label} | " + " | ".join(str(counts[v]) for v in VERDICT_ORDER) + f" | {len(claims)} |")
    lines.append("")
    if not len(changed):
        lines.append("No claim's verdict moved.")
        return "\n".join(lines) + "\n"
    lines += [f"{len(changed)} claim(s) moved. n = evaluated scenes; difference = the paired mean difference with its "
              "95 % interval, per part; the note is this run's.", "",
              "| claim | statement | before | now | n before | n now | difference before | difference now | note now |",
              "|---|---|---|---|---|---|---|---|---|"]
    for row in changed.itertuples(index=False):
        lines.append("| " + " | ".join(_cell(getattr(row, c)) for c in changed.columns) + " |")
    return "\n".join(lines) + "\n"
