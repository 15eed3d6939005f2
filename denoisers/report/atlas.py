"""The failure atlas of the stability suite (issue 15 §3; rule build_atlas, linked from REPORT.md).

Reads every scores file of rule score_scenario (<out>/stability/scores/{row}/{scene}/spp{spp}.json, written by
denoisers.jobs.stability) and writes, below <out>/stability/:

* ``tables/atlas.csv`` / ``.md``: scenario x row table of the masked PSNR (the failure's region; whole frame for
  the scenarios without a focus mask), the worst cell of every row in bold: the scenario where the row falls
  furthest below the median of the rows on that scenario (raw PSNR is not comparable across scenarios);
* ``tables/failures.csv`` / ``.md``: every row x scenario x spp with every failure metric;
* ``figures/curves_{scene}.png`` (per-frame lag-region error of every row, event marked), ``strip_{scene}.png``
  (every row at the worst frame, with crops on the mask) and ``quality_vs_speed_{family}.png`` per family;
* ``ATLAS.md``: the definitions, the table, one sentence per row computed from it, the figures.

A missing scores file is "not run" with the reason (never a crash); files computed from other settings are
left out and listed. Light at import time (the Snakefile lists the outputs while it is parsed).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scenegen.catalog import STABILITY_PREFIX, stability_scene_ids

if TYPE_CHECKING:
    import pandas as pd

#: Scenario families of the quality-versus-speed charts: pick a method for the failure that matters.
FAMILIES: dict[str, tuple[str, ...]] = {
    "motion": ("disocclusion", "fast_motion", "thin_geometry", "texture_motion"),
    "lighting": ("moving_shadow", "low_light", "caustics"),
    "specular": ("moving_reflection", "transparent"),
    "events": ("camera_cut", "light_switch"),
}
#: What goes wrong in each scenario, for the sentences ("ghosting under moving shadows").
PHENOMENA: dict[str, str] = {
    "disocclusion": "disocclusions", "moving_shadow": "moving shadows", "moving_reflection": "moving reflections",
    "caustics": "caustics (fireflies)", "camera_cut": "a camera cut", "fast_motion": "fast motion",
    "light_switch": "a light switching on", "low_light": "low light", "thin_geometry": "thin geometry",
    "texture_motion": "moving texture", "transparent": "transparent surfaces",
}
ATLAS_METRIC = "masked_psnr"
FAILURE_COLUMNS = ("method_id", "scenario", "spp", "recovery", "psnr", "tpsnr", "trmae", "masked_psnr", "masked_tpsnr",
                   "masked_trmae", "event_frame", "frames_to_recover", "post_event_mse", "steady_state_mse",
                   "ghosting_ratio", "flicker_trmae", "relative_bias", "ms_per_frame")
BIAS_SHOWN = 0.1          # |relative bias| above which a sentence names it


def family_of(scenario: str) -> str:
    return next((family for family, members in FAMILIES.items() if scenario in members), "other")


def atlas_outputs(cfg: dict, root: str = "results") -> dict[str, list[str]]:
    """Files build_atlas writes (empty without stability scenes): 'markdown', 'tables', 'figures', 'all'."""
    scenes = stability_scene_ids(cfg)
    if not scenes:
        return {"markdown": [], "tables": [], "figures": [], "all": []}
    base = f"{root}/stability"
    families = sorted({family_of(scene[len(STABILITY_PREFIX):]) for scene in scenes})
    out = {"markdown": [f"{base}/ATLAS.md"],
           "tables": [f"{base}/tables/{name}.{ext}" for name in ("atlas", "failures") for ext in ("csv", "md")],
           "figures": [f"{base}/figures/{kind}_{scene}.png" for scene in scenes for kind in ("curves", "strip")]
           + [f"{base}/figures/quality_vs_speed_{family}.png" for family in families]}
    out["all"] = out["markdown"] + out["tables"] + out["figures"]
    return out


def collect_scores(cfg: dict, results_dir: Path) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """(one row per scores file that exists and matches this config's settings, not-run entries {row, spp, scene,
    reason}) for every (configured row, stability.denoise_spp, scenario)."""
    import pandas as pd

    from denoisers.experiment import DIGEST_KEY
    from denoisers.jobs.stability import scores_csv, scores_lineage, stability_rows, stability_runs, stability_settings

    scenes = stability_scene_ids(cfg)
    try:
        reasons = {(run.spec.id, run.spp): run.not_run for run in stability_runs(cfg)}
    except (KeyError, TypeError, ValueError) as error:       # a method that cannot be built: every run not run
        reasons = {(spec.id, spp): f"not run (method unavailable: {error})" for spec in stability_rows(cfg)
                   for spp in stability_settings(cfg)["denoise_spp"]}
    rows, not_run = [], []
    for spec in stability_rows(cfg):
        for spp in stability_settings(cfg)["denoise_spp"]:
            for scene in scenes:
                path = scores_csv(results_dir, spec.id, scene, spp).with_suffix(".json")
                reason = reasons.get((spec.id, spp), "")
                if not reason and not path.is_file():
                    reason = f"not run ({path} missing; rule score_scenario)"
                if not reason:
                    record = json.loads(path.read_text())
                    expected = scores_lineage(cfg, spec, scene, spp)
                    if record.get(DIGEST_KEY) not in (None, expected):
                        reason = (f"left out: {path} records settings digest {record.get(DIGEST_KEY)}, this config's "
                                  f"is {expected} (rerun rule score_scenario)")
                if reason:
                    not_run.append({"method_id": spec.id, "spp": spp, "scene": scene, "reason": reason})
                    continue
                seconds = record.get("median_seconds")
                rows.append({**{k: v for k, v in record.items() if k not in ("events", "focus")},
                             "focus": "+".join(record["focus"]) or "whole frame",
                             "ms_per_frame": seconds * 1e3 if seconds is not None else math.nan})
    table = pd.DataFrame(rows)
    if table.empty:
        table = pd.DataFrame(columns=[*FAILURE_COLUMNS, "scene", "focus"])
    return table.astype({c: float for c in FAILURE_COLUMNS[4:] if c in table}), not_run


def atlas_table(scores: pd.DataFrame, spp: int) -> tuple[pd.DataFrame, dict[str, str]]:
    """(scenario x row masked PSNR at ``spp``, {row: scenario of its worst cell}). Worst = the largest deficit
    below the median of the rows on that scenario."""
    at = scores[scores.spp == spp]
    table = at.pivot_table(index="scenario", columns="method_id", values=ATLAS_METRIC, aggfunc="mean", sort=False)
    deficit = table.sub(table.median(axis=1), axis=0)
    worst = {row: str(deficit[row].idxmin()) for row in table.columns if deficit[row].notna().any()}
    return table, worst


def atlas_markdown(table: pd.DataFrame, worst: dict[str, str], rows: list[str], scenarios: list[str]) -> str:
    """The table as Markdown: masked PSNR (dB), the worst cell per row in bold, 'not run' where absent."""
    from denoisers.report.stats import markdown_table

    body = []
    for scenario in scenarios:
        cells = []
        for row in rows:
            value = table.at[scenario, row] if scenario in table.index and row in table.columns else math.nan
            text = "not run" if math.isnan(value) else f"{value:.2f}"
            cells.append(f"**{text}**" if worst.get(row) == scenario else text)
        body.append([scenario, *cells])
    return markdown_table(["scenario (masked PSNR, dB ↑)", *rows], body)


def input_ratios(scores: pd.DataFrame, cfg: dict) -> dict[tuple[str, int], float]:
    """{(scenario, spp): ghosting ratio of the per-frame noisy input row} (empty without a configured ``noisy``
    row): how far the content change alone moves the lag-region error from the control clip's, the baseline a
    temporal row's ratio is read against."""
    from denoisers.jobs.stability import stability_rows

    inputs = [spec.id for spec in stability_rows(cfg) if spec.method == "noisy"]
    if not inputs or scores.empty:
        return {}
    at = scores[scores.method_id == inputs[0]]
    return {(str(s), int(p)): float(r) for s, p, r in zip(at.scenario, at.spp, at.ghosting_ratio)}


def sentence(row: str, scenario: str, record: dict[str, Any], deficit: float, margin: float,
             input_ratio: float = math.nan) -> str:
    """One line per row, computed from its worst scenario's scores: what goes wrong (ghosting when the error needs
    frames to settle after the event, else a bias above BIAS_SHOWN, else plain error), under which phenomenon,
    how long it takes to settle, the masked PSNR against the rows' median and the flicker. ``input_ratio``: the
    noisy input's ghosting ratio on the scenario (what the content change alone does; NaN if unknown)."""
    phenomenon = PHENOMENA.get(scenario, scenario)
    recover = record.get("frames_to_recover")
    bias = record.get("relative_bias", math.nan)
    status, ratio = record.get("recovery", "no event"), record.get("ghosting_ratio", math.nan)
    # Ghosting: the error needs frames to settle and its mean after the event exceeds the failure-free (control) level
    # by the margin, and by more than the content change alone moves the per-frame input's (a scenario that changes
    # in every frame never matches its control exactly).
    baseline = input_ratio if isinstance(input_ratio, float) and math.isfinite(input_ratio) else 1.0
    above = isinstance(ratio, float) and not math.isnan(ratio) and ratio > (1.0 + margin) * max(1.0, baseline)
    if status == "never":
        lag, lagging = f"not back within {margin:.0%} of its failure-free error within the clip", above
    elif status == "recovered":
        lag, lagging = f"{int(recover)} frame{'s' if int(recover) != 1 else ''} to recover", int(recover) > 0 and above
    elif status == "too short":
        lag, lagging = "clip too short after the event to measure recovery", False
    else:
        lag, lagging = "no event", False
    biased = isinstance(bias, float) and not math.isnan(bias) and abs(bias) > BIAS_SHOWN
    kinds = (["ghosting"] if lagging else []) + (
        [f"{'darkening' if bias < 0 else 'brightening'} by {abs(bias):.0%}"] if biased else [])
    relation = f"{-deficit:.2f} dB below" if deficit < 0 else f"{deficit:.2f} dB above"
    flicker = record.get("flicker_trmae", math.nan)
    flicker_text = (f"flicker TRMAE {flicker:.3g}" if isinstance(flicker, (int, float)) and math.isfinite(flicker)
                    else "no static pixels to measure flicker")   # e.g. a camera moving in every frame
    if isinstance(ratio, float) and math.isfinite(ratio) and status in ("never", "recovered"):
        lag += f", ghosting ratio {ratio:.2f}" + (f" (noisy input's {baseline:.2f})" if baseline != 1.0 else "")
    return (f"- **{row}**: {' and '.join(kinds) or 'error'} under {phenomenon}, {lag} (masked PSNR "
            f"{record['masked_psnr']:.2f} dB, {relation} the rows' median there; {flicker_text}).")


def build_atlas(cfg: dict, results_dir: Path) -> list[Path]:
    """Write ATLAS.md, the tables and figures below ``results_dir``/stability; returns the written paths."""
    import pandas as pd

    from denoisers.report import atlas_figures as figs
    from denoisers.report.stats import formatted, frame_to_markdown
    from denoisers.report.tables import write_table
    from denoisers.jobs.stability import stability_rows, stability_settings
    from scenegen.atomic import write_text_atomic

    results_dir = Path(results_dir)
    base = results_dir / "stability"
    (base / "tables").mkdir(parents=True, exist_ok=True)
    (base / "figures").mkdir(parents=True, exist_ok=True)
    settings = stability_settings(cfg)
    scores, not_run = collect_scores(cfg, results_dir)
    rows = [spec.id for spec in stability_rows(cfg)]
    scenes = stability_scene_ids(cfg)
    scenarios = [scene[len(STABILITY_PREFIX):] for scene in scenes]
    shown = [c for c in FAILURE_COLUMNS if c in scores]
    write_table(scores, base / "tables", "failures", frame_to_markdown(formatted(
        scores[shown], {c: "" for c in shown[4:] if c not in ("event_frame", "frames_to_recover")})))
    lines = ["# Failure atlas (stability scenarios)", "",
             f"{rows_sentence(cfg)} denoised every scenario clip (`stability`: "
             f"{cfg['stability']['frames']} frames at {cfg['stability']['width']}x{cfg['stability']['height']}) at "
             f"{', '.join(map(str, settings['denoise_spp']))} spp (rule denoise_scenario) and was scored against the "
             "reference inside the scenario's masks (rule score_scenario, `denoisers/stability_metrics.py`).", "",
             "Definitions: *masked PSNR* = PSNR of tonemapped radiance over the scenario's focus mask per frame (whole "
             "frame for camera cut and light switch), mean over frames; *event* = the first event of events.json, "
             "else the first frame with a non-empty focus mask; *lag region* = the union of the focus masks from the "
             "event on; *steady state* = the same row's median lag-region error (tonemapped MSE) over the last third "
             "of the scenario's failure-free control clip (`stab_<name>__still`: every animated thing held at the "
             "scenario's final frame, denoised by the same row at the same spp; a scenario in which nothing changes is "
             f"its own control); *frames to recover* = first frame after the event within {settings['margin']:.0%} "
             "of it (config `stability.margin`), else *never* (not back to the failure-free level before the clip "
             "ends); *ghosting ratio* = mean lag-region error "
             "from the event on / steady state (a scenario that changes in every frame never matches its control "
             "exactly: read a row's ratio against the noisy input's on the same scenario, which shows what the content "
             "change alone does; a sentence names ghosting only above (1 + margin) × that); *flicker* = TRMAE over "
             "static pixels (no motion, valid reprojection, "
             "no change or focus mask in t or t − 1); *bias* = mean signed luminance error in the focus mask / mean "
             "reference luminance there.", ""]
    lines += ["Speed: ms/frame of the stability denoise jobs themselves (median `denoise()` call without the first "
              "frame); they may have shared the machine, so the charts are indicative. The report's timing table "
              "(rule time_methods) is the careful measurement.", ""]
    baselines = input_ratios(scores, cfg)
    for spp in settings["denoise_spp"]:
        table, worst = atlas_table(scores, spp) if len(scores) else (pd.DataFrame(), {})
        markdown = atlas_markdown(table, worst, rows, scenarios)
        deficit = table.sub(table.median(axis=1), axis=0) if len(table) else table
        sentences = []
        for row in rows:
            if row not in worst:
                sentences.append(f"- **{row}**: not run on any scenario at {spp} spp.")
                continue
            record = scores[(scores.method_id == row) & (scores.spp == spp) & (scores.scenario == worst[row])].iloc[0]
            sentences.append(sentence(row, worst[row], record.to_dict(), float(deficit.at[worst[row], row]),
                                      settings["margin"], baselines.get((worst[row], spp), math.nan)))
        if spp == settings["denoise_spp"][0]:
            long = table.reset_index().melt(id_vars="scenario", var_name="method_id", value_name=ATLAS_METRIC) \
                if len(table) else pd.DataFrame(columns=["scenario", "method_id", ATLAS_METRIC])
            long["worst"] = [worst.get(m) == s for s, m in zip(long["scenario"], long["method_id"])]
            write_table(long, base / "tables", "atlas", markdown + "\n" + "\n".join(sentences) + "\n")
        lines += [f"## {spp} spp", "", "Masked PSNR per scenario and row; **bold**: the row's worst scenario (largest "
                  "deficit below the median of the rows there).", "", markdown, *sentences, ""]
    lines += ["## Quality versus speed per scenario family", ""]
    for family in sorted({family_of(s) for s in scenarios}):
        path = base / "figures" / f"quality_vs_speed_{family}.png"
        members = [s for s in scenarios if family_of(s) == family]
        figs.plot_family(scores, members, rows, path, f"{family}: {', '.join(members)}")
        lines += [f"![{family}](figures/{path.name})", ""]
    lines += ["## Per scenario", ""]
    for scene, scenario in zip(scenes, scenarios):
        figs.plot_curves(scores, results_dir, scene, rows, base / "figures" / f"curves_{scene}.png")
        figs.plot_strip(cfg, scores, results_dir, scene, rows, base / "figures" / f"strip_{scene}.png")
        lines += [f"- {scenario}: [per-frame error curves](figures/curves_{scene}.png), "
                  f"[image strip at the worst frame](figures/strip_{scene}.png)"]
    if not_run:
        from denoisers.report.stats import markdown_table

        lines += ["", "## Not run", "", markdown_table(["row", "spp", "scene", "reason"],
                                                       [[r["method_id"], r["spp"], r["scene"], r["reason"]]
                                                        for r in not_run])]
    lines += ["", "Every number: [failures (CSV)](tables/failures.csv); the table: [atlas (CSV)](tables/atlas.csv)."]
    write_text_atomic(base / "ATLAS.md", "\n".join(lines) + "\n")
    return [Path(p) for p in atlas_outputs(cfg, str(results_dir))["all"]]


def rows_sentence(cfg: dict) -> str:
    """Which rows the atlas holds: every configured row of evaluation.methods, or those ``stability.rows`` names
    with the ones it leaves out named."""
    from denoisers.evaluate import METHOD_ROLE, method_specs
    from denoisers.jobs.stability import stability_rows

    configured = [spec.id for spec in method_specs(cfg) if spec.role == METHOD_ROLE]
    chosen = [spec.id for spec in stability_rows(cfg)]
    left_out = [row for row in configured if row not in chosen]
    if not left_out:
        return "Every configured row of `evaluation.methods`"
    return (f"The rows named by `stability.rows` ({', '.join(chosen)}; not in the atlas: {', '.join(left_out)})")


def report_section(cfg: dict, results_dir: Path) -> list[str]:
    """REPORT.md's section: the atlas table and sentences (tables/atlas.md), linked to stability/ATLAS.md; or why
    there is none."""
    if not stability_scene_ids(cfg):
        return []
    table = Path(results_dir) / "stability" / "tables" / "atlas.md"
    lines = ["## Failure atlas (stability scenarios)", ""]
    if not table.is_file():
        return lines + [f"Not run ({table} missing; rule build_atlas, stage target `stability`).", ""]
    return lines + [f"Where each method fails: masked PSNR on every stability scenario of {rows_sentence(cfg)[0].lower()}"
                    f"{rows_sentence(cfg)[1:]}, the worst scenario per row in bold; per-frame curves, image strips and quality-versus-speed charts "
                    "per scenario family in [stability/ATLAS.md](stability/ATLAS.md).", "", table.read_text(), ""]
