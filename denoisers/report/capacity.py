"""Capacity ablations (``training.ablations`` entries with ``kind: capacity``): is the network larger than the
data needs?

A capacity ablation trains the base model at several sizes (variants override only ``net``, e.g. the RAE's
``width`` and ``levels``) with the same data, seed and budget. The base model itself joins the sweep when the
ablation's step budget equals its own (then its configured size is one of the points). Per size the report
shows the parameters (the trained model's summary.json), the test PSNR (mean over the evaluated scenes with a
95 % Student-t interval, at an spp every variant is evaluated at: a variant's own ``spp``, else the
ablation's, else ``evaluation.ablation_spp``; the training spp where they share it), the paired
per-scene difference to the best size with its interval, ms/frame from the timing job (which times the
capacity variants too) and whether the run converged; a chart plots PSNR against parameters and against
ms/frame.

Selection rule: among the sizes that were trained, the *smallest within 0.2 dB* of the best mean
*validation* PSNR (fewest parameters; ties: lower ms/frame, then config order). Validation PSNR is each
model's ``validation.csv`` (``best.pt`` on the fixed validation sequences of the held-out training
scenes, the same sequences for every size): a default setting is never chosen on test scenes. The test
PSNR is reported beside it, with the paired per-scene difference to the selected size. The report says which size that is and
whether the base model's configured ``net`` matches it. It works for any learned family: nothing here is
RAE-specific. Missing inputs (a size not trained or not evaluated, timing disabled) become ``not run`` rows
with the reason, never an error.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from denoisers.report.stats import fmt, fmt_ci, frame_to_markdown, mean_ci, with_ci_columns
from denoisers.training.models import capacity_ablations, model_specs

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results
    from denoisers.report.trained import TrainedModel
    from denoisers.training.spec import ModelSpec

#: A size is adequate when its mean test PSNR is within this many dB of the best size's.
TOLERANCE_DB = 0.2
#: The quality metric of the sweep (frame-mean PSNR of the tonemapped output on the test scenes; per validation
#: sequence in validation.csv).
METRIC = "psnr"
BASE_VARIANT = "base"
#: The timing job's speed columns shown per size (median over rounds, fastest and slowest pass).
SPEED = "ms_per_frame"
SPEED_KEYS: tuple[str, ...] = (SPEED, f"{SPEED}_min", f"{SPEED}_max")


def output_name(ablation_id: str) -> str:
    """Name of the table (tables/{name}.csv, .md) and chart (figures/{name}.png) of one capacity ablation."""
    return f"capacity_{ablation_id}"


def output_names(cfg: dict) -> list[str]:
    """Table and figure names of every capacity ablation (config level, no pandas or matplotlib)."""
    return [output_name(ablation["id"]) for ablation in capacity_ablations(cfg)]


@dataclass(frozen=True)
class Member:
    """One size of a sweep: the variant id (``base`` for the base model), its model spec and evaluation row."""

    variant: str
    spec: ModelSpec
    row: str | None
    is_base: bool = False


def _base_row(res: Results, model_id: str) -> str | None:
    """The configured row that uses ``model_id`` plainly (params exactly {model: id}), if any."""
    return next((spec.id for spec in res.main_specs if dict(spec.params) == {"model": model_id}), None)


def sweep(res: Results, ablation: Mapping[str, Any]) -> tuple[list[Member], str]:
    """The sizes of one capacity ablation (variants in config order, then the base model when it trained with
    the same step budget) and a note on the base model ('' when it is part of the sweep)."""
    specs = model_specs(res.cfg)
    base = next(spec for spec in specs if spec.id == ablation["model"])
    rows = {spec.params.get("model"): spec.id for spec in res.specs if spec.role == "ablation"}
    members = [Member(spec.variant, spec, rows.get(spec.id)) for spec in specs if spec.ablation == ablation["id"]]
    budget = members[0].spec.budget.get("max_steps") if members else None
    if budget != base.budget.get("max_steps"):
        return members, (f"the base model {base.id} is not one of the sizes: it trains {base.budget.get('max_steps')} "
                         f"steps, the sweep {budget} (give the ablation the base model's budget to include it)")
    return members + [Member(BASE_VARIANT, base, _base_row(res, base.id), is_base=True)], ""


def swept_keys(members: Sequence[Member]) -> list[str]:
    """The ``net`` keys on which some variant differs from the base model (order of first appearance); keys a
    variant inherits unchanged from the base's ``net`` (e.g. the RAE's ``feature_init``) are not swept."""
    base_net = next((member.spec.net for member in members if member.is_base), {})
    keys: list[str] = []
    for member in members:
        if not member.is_base:
            keys += [key for key, value in member.spec.net.items()
                     if key not in keys and (key not in base_net or base_net[key] != value)]
    return keys


def net_values(spec: ModelSpec, model: TrainedModel | None, keys: Sequence[str]) -> dict[str, Any]:
    """The resolved value of each ``net`` key: the spec's own, else the trained model's recorded network config,
    else the network's default (built from the spec without training); None when none is known."""
    recorded = ((model.summary.get("net") or {}).get("config") or {}) if model is not None else {}
    defaults: dict[str, Any] = {}
    if any(key not in spec.net and key not in recorded for key in keys):
        try:
            from denoisers.training.tasks import build_task

            defaults = build_task(spec).net_spec()["config"]
        except (AttributeError, KeyError, TypeError, ValueError):
            defaults = {}
    return {key: spec.net.get(key, recorded.get(key, defaults.get(key))) for key in keys}


def _spp(res: Results, members: Sequence[Member]) -> int | None:
    """The spp the sizes are compared at: the variants' training spp if every variant's row is evaluated there,
    else the first spp they share (a variant may have its own spp), else the first variant's first (None: the
    variants are not evaluated)."""
    evaluated = [spec.spp for spec in res.specs if spec.role == "ablation"
                 and any(member.row == spec.id for member in members)]
    if not evaluated:
        return None
    shared = [spp for spp in evaluated[0] if all(spp in other for other in evaluated[1:])] or list(evaluated[0])
    trained = int(members[0].spec.data.get("spp", 1))
    return trained if trained in shared else shared[0]


def select_smallest(psnr: Mapping[str, float], parameters: Mapping[str, float],
                    ms: Mapping[str, float] | None = None, tolerance: float = TOLERANCE_DB) -> str | None:
    """The key with the fewest parameters among those whose PSNR is within ``tolerance`` dB of the best (ties:
    lower ms/frame, then the order of ``psnr``); keys with a NaN PSNR are ignored, unknown sizes count as
    infinitely large. None when no PSNR is known."""
    known = [key for key, value in psnr.items() if not math.isnan(value)]
    if not known:
        return None
    best = max(psnr[key] for key in known)
    adequate = [key for key in known if psnr[key] >= best - tolerance - 1e-9]

    def size(key: str) -> tuple[float, float, int]:
        params = parameters.get(key, math.nan)
        speed = (ms or {}).get(key, math.nan)
        return (math.inf if math.isnan(params) else params, math.inf if math.isnan(speed) else speed,
                known.index(key))

    return min(adequate, key=size)


def _timing_note(res: Results, row: str | None, spp: int | None) -> str:
    if row is None or spp is None:
        return ""
    if not res.cfg["evaluation"].get("timing", {}).get("enabled", True):
        return "not timed (evaluation.timing.enabled is false)"
    if res.timing is None:
        return "not timed (the timing job's output is missing)"
    return "" if res.speed(row, spp) else "not timed (no record in the timing job)"


def capacity_table(res: Results, ablation: Mapping[str, Any]) -> tuple[pd.DataFrame, str]:
    """One row per size of the sweep (see the module docstring) and the base-model note of :func:`sweep`."""
    import pandas as pd

    from denoisers.report.training_tables import converged_text

    members, base_note = sweep(res, ablation)
    keys = swept_keys(members)
    spp = _spp(res, members)
    models = res.models.models if res.models else {}
    rows: list[dict[str, Any]] = []
    scene_psnr: dict[str, pd.Series] = {}
    for member in members:
        model = models.get(member.spec.id)
        speed = (res.speed(member.row, spp) if spp is not None else None) or {}
        row: dict[str, Any] = {"variant": member.variant, "model": member.spec.id, "row": member.row or "",
                               **net_values(member.spec, model, keys),
                               "parameters": float(model.summary.get("parameters", math.nan)) if model else math.nan,
                               "steps": model.summary.get("steps") if model else None,
                               "stopped_by": model.summary.get("stopped_by", "") if model else "",
                               "spp": spp}
        reasons = []
        if model is None:
            reasons.append(f"model {member.spec.id} not trained (no complete model directory)")
        if spp is None:
            key = f"training.ablations {ablation['id']} spp" if "spp" in ablation else "evaluation.ablation_spp"
            reasons.append(f"the variants are not evaluated ({key} is empty)")
        elif member.row is None:
            reasons.append(f"no evaluation row uses model {member.spec.id} with params exactly {{model: "
                           f"{member.spec.id}}}" if member.is_base else f"no evaluation row for {member.spec.id}")
        elif not res.ran(member.row, spp):
            run = next((r for r in res.runs if r["id"] == member.row and r["spp"] == spp), None)
            reasons.append(run["reason"] if run else f"row {member.row} is not evaluated at {spp} spp")
        else:
            scene_psnr[member.variant] = res.scene_values(member.row, spp, METRIC).astype(float)
        mean, low, high, n = mean_ci(scene_psnr[member.variant].to_numpy()) if member.variant in scene_psnr \
            else (math.nan, math.nan, math.nan, 0)
        validation = model.validation if model is not None else None
        val = (validation[METRIC].astype(float).to_numpy() if validation is not None and METRIC in validation
               else np.array([]))
        val_mean, val_low, val_high, val_n = mean_ci(val) if val.size else (math.nan, math.nan, math.nan, 0)
        if model is not None and not val.size:
            reasons.append(f"model {member.spec.id} has no validation {METRIC} (validation.csv)")
        row.update({"val_psnr_mean": val_mean, "val_psnr_ci_low": val_low, "val_psnr_ci_high": val_high,
                    "n_validation_sequences": val_n,
                    "psnr_mean": mean, "psnr_ci_low": low, "psnr_ci_high": high, "n_scenes": n,
                    **{key: speed.get(key, math.nan) for key in SPEED_KEYS},
                    "converged": converged_text(model.undertrained(res.cfg)) if model else "",
                    "status": "not run" if reasons else "ran",
                    "note": "; ".join(reasons + ([_timing_note(res, member.row, spp)] if not reasons else []))
                    .strip("; ")})
        rows.append(row)
    table = pd.DataFrame(rows, columns=["variant", "model", "row", *keys, "parameters", "steps", "stopped_by", "spp",
                                        "val_psnr_mean", "val_psnr_ci_low", "val_psnr_ci_high",
                                        "n_validation_sequences", "psnr_mean", "psnr_ci_low", "psnr_ci_high", "n_scenes", "ms_per_frame",
                                        "ms_per_frame_min", "ms_per_frame_max", "converged", "status", "note"])
    # Chosen on validation PSNR (held-out training scenes), never on the test scenes.
    psnr = dict(zip(table["variant"], table["val_psnr_mean"].astype(float)))
    chosen = select_smallest(psnr, dict(zip(table["variant"], table["parameters"].astype(float))),
                             dict(zip(table["variant"], table["ms_per_frame"].astype(float))))
    best = max((v for v in psnr if not math.isnan(psnr[v])), key=lambda v: psnr[v], default=None)
    diffs = []
    for variant in table["variant"]:
        # Test PSNR, paired per scene, against the size chosen on validation.
        if variant in scene_psnr and chosen in scene_psnr:
            paired = (scene_psnr[variant] - scene_psnr[chosen]).dropna()
            diffs.append(mean_ci(paired.to_numpy())[:3])
        else:
            diffs.append((math.nan,) * 3)
    position = table.columns.get_loc("n_scenes") + 1
    for offset, part in enumerate(("mean", "ci_low", "ci_high")):
        table.insert(position + offset, f"diff_to_selected_{part}", [d[offset] for d in diffs])
    best_mean = psnr[best] if best is not None else math.nan
    table.insert(table.columns.get_loc("converged") + 1, "within_tolerance",
                 [bool(not math.isnan(p) and p >= best_mean - TOLERANCE_DB - 1e-9) for p in table["val_psnr_mean"]])
    table.insert(table.columns.get_loc("within_tolerance") + 1, "best", [v == best for v in table["variant"]])
    table.insert(table.columns.get_loc("best") + 1, "selected", [v == chosen for v in table["variant"]])
    return table, base_note


def _describe(row: Mapping[str, Any], keys: Sequence[str]) -> str:
    size = ", ".join(f"{key} {row[key]}" if not isinstance(row[key], float) else f"{key} {row[key]:g}"
                     for key in keys)
    params = f"{int(row['parameters']):,} parameters" if not math.isnan(row["parameters"]) else "parameters unknown"
    return f"`{row['model']}` ({size}; {params})"


def selection_statement(res: Results, ablation: Mapping[str, Any], table: pd.DataFrame, base_note: str) -> str:
    """The paragraph naming the smallest size within TOLERANCE_DB of the best and whether the base model's
    configured net matches it."""
    members, _ = sweep(res, ablation)
    keys = swept_keys(members)
    base = next(spec for spec in model_specs(res.cfg) if spec.id == ablation["model"])
    chosen = table[table["selected"]]
    if not len(chosen):
        return (f"Not decided: no size of `{ablation['id']}` has a validation PSNR (see the status and note "
                f"columns); the configured default `{base.id}` is unchecked.")
    row, best = chosen.iloc[0], table[table["best"]].iloc[0]
    text = (f"Smallest size within {TOLERANCE_DB:g} dB of the best mean validation PSNR "
            f"({int(row['n_validation_sequences'])} validation sequences of the held-out training scenes; a default is "
            f"never chosen on test scenes): {_describe(row, keys)}, {fmt(row['val_psnr_mean'], 'psnr')} dB against "
            f"the best, {_describe(best, keys)}, {fmt(best['val_psnr_mean'], 'psnr')} dB.")
    if not math.isnan(row["psnr_mean"]) and not math.isnan(best["psnr_mean"]):
        text += (f" On the test scenes at {int(row['spp'])} spp ({int(row['n_scenes'])} scene(s)) the selected size "
                 f"scores {fmt(row['psnr_mean'], 'psnr')} dB and the best-validating one {fmt(best['psnr_mean'], 'psnr')} dB "
                 f"(paired difference best - selected "
                 f"{fmt_ci(best['diff_to_selected_mean'], best['diff_to_selected_ci_low'], best['diff_to_selected_ci_high'], 'psnr')} dB).")
    models = res.models.models if res.models else {}
    configured = net_values(base, models.get(base.id), keys)
    matches = all(row[key] == configured[key] for key in keys)
    size = ", ".join(f"{key} {configured[key]}" for key in keys)
    text += (f" The configured default `{base.id}` ({size}) {'matches' if matches else 'does not match'} it"
             + ("." if matches else ": set its net to the selected size, or justify the larger one."))
    if base_note:
        text += f" Note: {base_note}."
    caveats = []
    ran = table[table["status"] == "ran"]
    unconverged = [m for m, c in zip(ran["model"], ran["converged"]) if c != "yes"]
    if unconverged:
        caveats.append(f"not converged (or unknown): {', '.join(unconverged)} - the choice then tests the training "
                       "budget as much as the size")
    short = [m for m, why in zip(ran["model"], ran["stopped_by"]) if why and why != "max_steps"]
    if short:
        caveats.append(f"stopped before the step budget (max_seconds): {', '.join(short)}")
    if len(ran) < len(table):
        caveats.append(f"not run: {', '.join(table[table['status'] != 'ran']['model'])}")
    if int(row["n_validation_sequences"]) < 2:
        caveats.append("one validation sequence: the choice rests on a single sequence")
    return text + (" Caveats: " + "; ".join(caveats) + "." if caveats else "")


def capacity_markdown(table: pd.DataFrame, keys: Sequence[str]) -> str:
    if not len(table):
        return "no size configured\n"
    shown = with_ci_columns(table, {"validation PSNR (dB, mean ± 95 % CI)": ("val_psnr", "psnr"),
                                    "test PSNR (dB, mean ± 95 % CI)": ("psnr", "psnr"),
                                    "test PSNR − selected (paired)": ("diff_to_selected", "psnr")},
                            ["variant", "model", *keys, "parameters", "steps", "spp"],
                            ["n_scenes", "ms_per_frame", "converged", "within_tolerance", "selected", "status", "note"])
    shown["parameters"] = [f"{int(v):,}" if not math.isnan(v) else "–" for v in table["parameters"]]
    shown["ms_per_frame"] = [f"{fmt(m, SPEED)} [{fmt(lo, SPEED)}, {fmt(hi, SPEED)}]" if not math.isnan(m) else "–"
                             for m, lo, hi in zip(*(table[key] for key in SPEED_KEYS))]
    return frame_to_markdown(shown.rename(columns={"ms_per_frame": "ms/frame (timing job)"}))


def plot_capacity(table: pd.DataFrame, path: Path, title: str) -> None:
    """Two panels: test PSNR (± 95 % CI) against parameters (log x) and against ms/frame ([min, max] over the
    timing rounds); the selected size (chosen on validation PSNR) is red, the base model drawn as a square."""
    from denoisers.report.figures import placeholder, pyplot

    ran = table[table["psnr_mean"].notna()]
    if not len(ran):
        placeholder(path, "no size of this capacity ablation was evaluated")
        return
    plt = pyplot()
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    low = (ran["psnr_mean"] - ran["psnr_ci_low"]).fillna(0).to_numpy()
    high = (ran["psnr_ci_high"] - ran["psnr_mean"]).fillna(0).to_numpy()
    timed = ran["ms_per_frame"].notna().to_numpy()
    for axes, column in ((left, "parameters"), (right, "ms_per_frame")):
        mask = ran[column].notna().to_numpy()
        x = ran[column].to_numpy(float)
        xerr = None
        if column == "ms_per_frame":
            xerr = np.vstack([(ran["ms_per_frame"] - ran["ms_per_frame_min"]).fillna(0).to_numpy(),
                              (ran["ms_per_frame_max"] - ran["ms_per_frame"]).fillna(0).to_numpy()])[:, mask]
        if mask.any():
            axes.errorbar(x[mask], ran["psnr_mean"].to_numpy()[mask], yerr=np.vstack([low, high])[:, mask],
                          xerr=xerr, fmt="none", ecolor="0.5", capsize=3)
        for index, ((_, row), valid) in enumerate(zip(ran.iterrows(), mask)):
            if not valid:
                continue
            axes.plot(row[column], row["psnr_mean"], "s" if row["variant"] == BASE_VARIANT else "o",
                      color="tab:red" if row["selected"] else "tab:blue", markersize=7)
            axes.annotate(row["variant"], (row[column], row["psnr_mean"]), textcoords="offset points",
                          xytext=(5, 4 if index % 2 == 0 else -11), fontsize=8)   # alternate: close sizes overlap
        axes.grid(True, which="both", alpha=0.3)
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    left.set_xscale("log")
    left.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    left.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:,.0f}"))
    left.xaxis.set_minor_formatter(NullFormatter())
    left.set_xlabel("trainable parameters (log scale)")
    left.set_ylabel("test PSNR (dB, mean ± 95 % CI over scenes)")
    right.set_xlabel("ms/frame (timing job: median, bars = range over rounds)")
    if not timed.any():
        right.text(0.5, 0.5, "not timed", transform=right.transAxes, ha="center", va="center")
    figure.suptitle(f"{title}: red = smallest within {TOLERANCE_DB:g} dB of the best validation PSNR, "
                    "square = base model",
                    fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def capacity_section(res: Results, tables: Path, figures: Path) -> list[str]:
    """Writes tables/capacity_{id}.csv/.md and figures/capacity_{id}.png per capacity ablation; returns the
    REPORT.md lines (empty when the config has none)."""
    from denoisers.report.tables import write_table

    ablations = capacity_ablations(res.cfg)
    if not ablations:
        return []
    lines = ["## Model capacity", "",
             "Each capacity ablation trains the base model at several sizes (only `net` differs: same data, seed "
             "and step budget; the base model is one of the sizes when its budget is the sweep's). The default size "
             f"should be the smallest within {TOLERANCE_DB:g} dB of the best mean validation PSNR (fewest "
             "parameters): validation sequences of the held-out training scenes, the same for every size, so no "
             "setting is chosen on a test scene. Test PSNR: mean over the evaluated scenes ± 95 % Student-t "
             "interval; `test PSNR − selected`: paired per-scene difference to the selected size; ms/frame from "
             "the timing job.", ""]
    for ablation in ablations:
        name = output_name(ablation["id"])
        table, base_note = capacity_table(res, ablation)
        keys = swept_keys(sweep(res, ablation)[0])
        markdown = capacity_markdown(table, keys)
        write_table(table, tables, name, markdown)
        plot_capacity(table, figures / f"{name}.png", f"{ablation['id']} (base model {ablation['model']})")
        lines += [f"### {ablation['id']} (base model `{ablation['model']}`)", "",
                  selection_statement(res, ablation, table, base_note), "", markdown,
                  f"![{ablation['id']}](figures/{name}.png)", "", f"[{name} (CSV)](tables/{name}.csv)", ""]
    return lines
