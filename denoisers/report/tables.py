"""Cross-paper tables: summary (method x spp x metric), timing, equal-time view, reference noise floor,
robustness, split, tuning. The trained models' tables are in denoisers.report.training_tables; paper-specific
layouts live in denoisers.reproductions."""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from denoisers.evaluate import ALL_METRICS, REFERENCE_METHODS
from denoisers.report.collect import DERIVED_METRICS, TIMING_COLUMNS, Results
from denoisers.report.stats import HIGHER_IS_BETTER, LABELS, fmt, fmt_ci, markdown_table, mean_ci
from denoisers.training.models import method_model
from scenegen.catalog import SCENE_SPLITS, scene_ids

if TYPE_CHECKING:
    import pandas as pd

SUMMARY_METRICS: tuple[str, ...] = (*ALL_METRICS, *DERIVED_METRICS, *TIMING_COLUMNS)
#: Columns of the Markdown summary (video PSNR is in the Isik layouts); ms/frame from the timing job follows.
SUMMARY_SHOWN: tuple[str, ...] = (*ALL_METRICS, *TIMING_COLUMNS)


#: A timing range wider than this fraction of its median (spread = (max - min) / median over the timing rounds)
#: cannot rank two rows whose medians differ by less than that: the machine was busy. Such timings are flagged in
#: the tables, the quality-vs-speed chart (hollow markers) and the equal-time view.
RANK_SPREAD_LIMIT = 0.5
TOO_WIDE = "⚠ range too wide to rank"


def too_wide_to_rank(speed: dict[str, Any] | None) -> bool:
    """Whether a timing-job record's range over rounds exceeds :data:`RANK_SPREAD_LIMIT` of its median."""
    if not speed:
        return False
    median, low, high = speed["ms_per_frame"], speed["ms_per_frame_min"], speed["ms_per_frame_max"]
    return not median > 0 or (high - low) / median > RANK_SPREAD_LIMIT


def speed_text(res: Results, method_id: str, spp: int) -> str:
    """'median [min, max]' ms/frame of the timing job (flagged when too wide to rank), or '–' when it did not
    time the row."""
    row = res.speed(method_id, spp)
    if row is None:
        return "–"
    return (f"{fmt(row['ms_per_frame'], 'ms_per_frame')} [{fmt(row['ms_per_frame_min'], 'ms_per_frame')}, "
            f"{fmt(row['ms_per_frame_max'], 'ms_per_frame')}]" + (f" {TOO_WIDE}" if too_wide_to_rank(row) else ""))


def summary_table(res: Results) -> pd.DataFrame:
    """Long table: row x spp x metric -> mean, 95 % CI over evaluated scenes, number of scenes; for a row of a
    trained model with seed rows (training.seeds > 1) the mean is over its seeds' per-scene means, ``n_seeds``
    says how many and ``seed_sd`` is the standard deviation over seeds of each seed's mean over scenes (NaN
    with one seed). Seed rows keep their own (one-seed) lines, role 'seed'."""
    import pandas as pd

    rows = []
    for run in res.runs:
        if run["status"] != "ran":
            continue
        for metric in SUMMARY_METRICS:
            mean, low, high, n = mean_ci(res.scene_values(run["id"], run["spp"], metric).to_numpy(np.float64))
            seeds = [float(values.mean()) for values in res.scene_values_per_seed(run["id"], run["spp"], metric)]
            rows.append({"method_id": run["id"], "method": run["method"], "role": run["role"], "spp": run["spp"],
                         "metric": metric, "higher_is_better": HIGHER_IS_BETTER[metric], "mean": mean,
                         "ci_low": low, "ci_high": high, "n_scenes": n, "n_seeds": len(seeds),
                         "seed_sd": float(np.std(seeds, ddof=1)) if len(seeds) > 1 else math.nan})
    return pd.DataFrame(rows, columns=["method_id", "method", "role", "spp", "metric", "higher_is_better", "mean",
                                       "ci_low", "ci_high", "n_scenes", "n_seeds", "seed_sd"])


def summary_lookup(summary: pd.DataFrame) -> dict[tuple[str, int, str], tuple[float, float, float, int]]:
    return {(r.method_id, r.spp, r.metric): (r.mean, r.ci_low, r.ci_high, r.n_scenes) for r in summary.itertuples()}


def _seed_label(summary: pd.DataFrame, method_id: str, spp: int, trained: bool = False) -> str:
    """The row's name, with its seed count and the PSNR spread over seeds when it has more than one seed, and
    "(1 seed)" on a trained row that trains once where other trained rows of the summary train more often (a
    model's own ``seeds: 1``, issue 48: its tables say so)."""
    line = summary[(summary.method_id == method_id) & (summary.spp == spp) & (summary.metric == "psnr")]
    if line.empty or int(line.n_seeds.iloc[0]) < 2:
        several = not summary.empty and int(summary.n_seeds.max()) > 1
        return f"{method_id} (1 seed)" if trained and several and not line.empty else method_id
    return f"{method_id} ({int(line.n_seeds.iloc[0])} seeds, PSNR sd {float(line.seed_sd.iloc[0]):.2f} dB)"


def summary_markdown(res: Results, summary: pd.DataFrame) -> str:
    """One Markdown table per spp: rows = configured methods, columns = metrics as 'mean ± 95 % CI half-width'."""
    lookup = summary_lookup(summary)
    arrows = {True: "↑", False: "↓"}
    parts = []
    for spp in res.cfg["evaluation"]["spp"]:
        rows = [[_seed_label(summary, spec.id, spp, method_model(spec.params) is not None),
                 *[fmt_ci(*lookup[(spec.id, spp, m)][:3], m) for m in SUMMARY_SHOWN],
                 speed_text(res, spec.id, spp), "⚠" if res.flag(spec.id, spp) else "ok"]
                for spec in res.main_specs if res.ran(spec.id, spp)]
        flags = [res.flag(spec.id, spp) for spec in res.main_specs if res.ran(spec.id, spp)]
        n = max((lookup[k][3] for k in lookup if k[1] == spp), default=0)
        parts.append(f"### {spp} spp ({n} scene{'s' if n != 1 else ''})\n\n")
        parts.append(markdown_table(["method", *[f"{LABELS[m]} {arrows[HIGHER_IS_BETTER[m]]}" for m in SUMMARY_SHOWN],
                                     "ms/frame ↓ (timing job: median [range])", "outputs"],
                                    rows) if rows else "no method ran at this spp\n")
        parts += [f"\n⚠ {flag}\n" for flag in flags if flag]
        parts.append("\n")
    return "".join(parts)


def timing_table(res: Results) -> pd.DataFrame:
    """Per row and spp: the timing job's ms/frame (median over rounds, min, max, spread = range / median),
    Mpix/s and, for rows running torch products, GFLOP per frame, GFLOP/s and its fraction of the same
    round's sgemm (NaN otherwise), the denoise jobs' peak memory (mean with CI over scenes) and the summed
    non-finite / out-of-range counts."""
    import pandas as pd

    rows = []
    for run in res.runs:
        if run["status"] != "ran":
            continue
        values = {c: res.scene_values(run["id"], run["spp"], c) for c in
                  (*TIMING_COLUMNS, "nonfinite_inputs", "nonfinite_outputs", "out_of_range_outputs")}
        out_of_range = values["out_of_range_outputs"]
        speed = res.speed(run["id"], run["spp"]) or {}
        rows.append({"method_id": run["id"], "spp": run["spp"],
                     **{key: speed.get(key, math.nan) for key in
                        ("ms_per_frame", "ms_per_frame_min", "ms_per_frame_max", "spread", "mpix_per_s",
                         "gflop_per_frame", "gflops_per_s", "fraction_of_sgemm")},
                     "timing_rounds": speed.get("repeats", 0), "timing_threads": speed.get("threads", math.nan),
                     "too_wide_to_rank": too_wide_to_rank(speed),
                     **{f"{c}_{part}": value for c in TIMING_COLUMNS
                        for part, value in zip(("mean", "ci_low", "ci_high"), mean_ci(values[c].to_numpy(float))[:3])},
                     "nonfinite_inputs": int(values["nonfinite_inputs"].sum()),
                     "nonfinite_outputs": int(values["nonfinite_outputs"].sum()),
                     "out_of_range_outputs": int(out_of_range.sum()) if out_of_range.notna().all() else math.nan,
                     "flag": res.flag(run["id"], run["spp"])})
    return pd.DataFrame(rows)


def equal_time_table(res: Results) -> pd.DataFrame:
    """For each denoiser and spp: the spp plain path tracing reaches in the same time (render time of
    spp samples + denoise time; denoise time and each scene's renderer samples/s both from the timing job, at
    the same threads; the equal-time spp is the mean over scenes), the plain path-tracing row whose total spp
    is nearest to it (in log ratio), and which of the two has the higher PSNR. Rows the timing job did not time get no equal-time spp."""
    import pandas as pd

    main = {spec.id for spec in res.main_specs}
    baselines = []  # (row id, evaluated spp, total spp)
    for run in res.runs:
        if run["status"] == "ran" and run["id"] in main and res.spec(run["id"]).method in REFERENCE_METHODS:
            factor = int(res.scene_values(run["id"], run["spp"], "samples_factor").iloc[0])
            baselines.append((run["id"], run["spp"], run["spp"] * factor))
    rows = []
    for run in res.runs:
        if run["status"] != "ran" or run["id"] not in main or res.spec(run["id"]).method in REFERENCE_METHODS:
            continue
        speed = res.speed(run["id"], run["spp"])
        ms = speed["ms_per_frame"] if speed else math.nan
        # Per scene: its own renderer rate (scenes differ in cost); the denoiser's time from the timing scene.
        rates = np.array([res.timing.renderer_samples_per_s(scene) if res.timing is not None else math.nan
                          for scene in res.scenes], dtype=np.float64)
        pixels = speed["width"] * speed["height"] if speed else math.nan
        equal_spp = float(np.mean(run["spp"] + ms / 1e3 * rates / pixels)) if len(rates) else math.nan
        row = {"method_id": run["id"], "spp": run["spp"], "denoise_ms_per_frame": ms,
               "render_msamples_per_s": float(np.mean(rates)) / 1e6 if len(rates) else math.nan,
               "equal_time_spp": equal_spp,
               "path_tracing_row": None, "path_tracing_spp": math.nan, "psnr_denoiser": math.nan,
               "psnr_path_tracing": math.nan, "psnr_diff_mean": math.nan, "psnr_diff_ci_low": math.nan,
               "psnr_diff_ci_high": math.nan, "better": "no path-tracing row",
               "too_wide_to_rank": too_wide_to_rank(speed)}
        if baselines and not math.isnan(equal_spp):
            best = min(baselines, key=lambda b: (abs(math.log(b[2] / equal_spp)), -b[2]))
            ours = res.scene_values(run["id"], run["spp"], "psnr")
            theirs = res.scene_values(best[0], best[1], "psnr")
            mean, low, high, _ = mean_ci((ours - theirs).dropna().to_numpy(float))
            better = (run["id"] if low > 0 else "path tracing" if high < 0 else "neither (interval spans 0)") \
                if not math.isnan(low) else "undecided (fewer than 2 scenes)"
            row.update({"path_tracing_row": f"{best[0]} @ {best[1]} spp", "path_tracing_spp": best[2],
                        "psnr_denoiser": float(ours.mean()), "psnr_path_tracing": float(theirs.mean()),
                        "psnr_diff_mean": mean, "psnr_diff_ci_low": low, "psnr_diff_ci_high": high,
                        "better": better})
            if best[2] < equal_spp / 1.5:
                row["better"] += f" (nearest rendered PT has {best[2]} spp < {equal_spp:.1f})"
        if row["too_wide_to_rank"]:
            row["better"] += f" ({TOO_WIDE}: the equal-time spp rests on it)"
        rows.append(row)
    return pd.DataFrame(rows)


def noise_floor_table(res: Results) -> pd.DataFrame:
    """Per scene: PSNR between the two reference halves and the implied noise floor of the
    reference (+6.02 dB, docs/data-format.md), beside the best method PSNR at the highest spp."""
    import pandas as pd

    rows = []
    top_spp = max(res.cfg["evaluation"]["spp"])
    main = {spec.id for spec in res.main_specs}
    for scene in res.scenes:
        halves = res.frames.loc[res.frames.scene == scene, "reference_psnr_halves"]
        at_top = res.per_scene[(res.per_scene.scene == scene) & (res.per_scene.spp == top_spp)
                               & res.per_scene.method_id.isin(main)].dropna(subset=["psnr"])
        best = at_top.loc[at_top.psnr.idxmax()] if len(at_top) else None
        floor = float(halves.mean()) + 10 * math.log10(4.0) if len(halves) else math.nan
        rows.append({"scene": scene, "psnr_halves": float(halves.mean()) if len(halves) else math.nan,
                     "reference_noise_floor_psnr": floor, "best_method": best.method_id if best is not None else None,
                     "best_psnr": float(best.psnr) if best is not None else math.nan, "spp": top_spp,
                     "headroom_db": floor - float(best.psnr) if best is not None else math.nan})
    table = pd.DataFrame(rows)
    if len(table):
        table["headroom_ok"] = table.headroom_db >= min_floor_headroom(res.cfg)
    return table


def min_floor_headroom(cfg: dict) -> float:
    """evaluation.min_floor_headroom_db (dB; schema default 10)."""
    return float(cfg["evaluation"].get("min_floor_headroom_db", 10.0))


def floor_headroom_text(cfg: dict, table: pd.DataFrame) -> str:
    """One line under the noise-floor table: whether every scene's floor is far enough above the best method."""
    need = min_floor_headroom(cfg)
    if not len(table) or table.headroom_db.isna().all():
        return "No scene has both a reference noise floor and a scored method."
    low = table[~table.headroom_ok.astype(bool)]
    if not len(low):
        return (f"Every scene's reference noise floor is at least {need:g} dB above its best method "
                f"(evaluation.min_floor_headroom_db; least {table.headroom_db.min():.2f} dB).")
    named = ", ".join(f"{r.scene} ({r.headroom_db:.2f} dB)" for r in low.itertuples())
    return (f"**Below the {need:g} dB headroom** (evaluation.min_floor_headroom_db): {named}. There the reference's "
            "own noise limits the metrics of the best methods; raise render.test_reference_spp.")


def robustness_table(res: Results) -> pd.DataFrame:
    """Per row at the robustness spp: PSNR on clean and on spiked input (mean ± CI over scenes), the
    drop, and the summed counts of injected, non-finite and out-of-range values."""
    import pandas as pd

    spp = res.cfg["evaluation"]["robustness"]["spp"]
    rows = []
    for spec in res.specs:
        if not spec.robustness:
            continue
        spiked = res.robustness[res.robustness.method_id == spec.id].set_index("scene") \
            if res.robustness is not None else None
        if spiked is None or spiked.empty:
            rows.append({"method_id": spec.id, "spp": spp, "status": "not run"})
            continue
        clean = res.scene_values(spec.id, spp, "psnr") if res.ran(spec.id, spp) else None
        drop = (clean - spiked["psnr_spiked"]).dropna() if clean is not None else None
        row: dict[str, Any] = {"method_id": spec.id, "spp": spp, "status": "ran"}
        for name, values in (("psnr_clean", clean), ("psnr_spiked", spiked["psnr_spiked"]), ("psnr_drop", drop)):
            mean, low, high, _ = mean_ci(values.to_numpy(float)) if values is not None else (math.nan,) * 4
            row.update({f"{name}_mean": mean, f"{name}_ci_low": low, f"{name}_ci_high": high})
        for count in ("spikes", "nan_values", "inf_values", "nonfinite_inputs", "nonfinite_outputs"):
            row[count] = int(spiked[count].sum())
        absurd = spiked["out_of_range_outputs"]
        row["out_of_range_outputs"] = int(absurd.sum()) if absurd.notna().all() else math.nan
        rows.append(row)
    return pd.DataFrame(rows)


def split_table(cfg: dict) -> pd.DataFrame:
    """The seeded train/test split: every scene id, its split ('custom' for external scenes), whether it is
    evaluated (test and custom scenes) and its derived seed (none for custom scenes)."""
    import pandas as pd

    from denoisers.evaluate import evaluated_scene_ids
    from scenegen.seeds import scene_seed

    evaluated = set(evaluated_scene_ids(cfg))
    rows = []
    for scene in scene_ids(cfg):
        split = next((s for s in SCENE_SPLITS if scene.startswith(f"{s}_")), "custom")
        rows.append({"scene": scene, "split": split, "evaluated": scene in evaluated,
                     "scene_seed": scene_seed(cfg["seed"], scene) if split != "custom" else None})
    return pd.DataFrame(rows)


EXTERNAL_COLUMNS: tuple[str, ...] = (*ALL_METRICS, "video_psnr")
SUBSTITUTION_COLUMNS: tuple[str, ...] = ("scene", "what", "authored", "used", "why")


def external_table(res: Results) -> pd.DataFrame:
    """Per row, spp and external scene: the frame means of every metric and video PSNR."""
    rows = res.per_scene[res.per_scene.scene.isin(res.external_scenes)]
    roles = {spec.id: spec.role for spec in res.specs}
    table = rows[["method_id", "spp", "scene", *[c for c in EXTERNAL_COLUMNS if c in rows]]].copy()
    table.insert(1, "role", table["method_id"].map(roles))
    return table.reset_index(drop=True)


def _resolved_use(cfg: dict, row: dict[str, str]) -> str:
    """A substitution's ``used`` with the config's values where the manifest names config keys."""
    render = cfg["render"]
    if row["what"] == "resolution":
        return f"{render['width']}x{render['height']} (render.width x render.height)"
    if row["what"] == "sampler":     # external scenes are evaluated scenes (render.test_reference_spp)
        from scenegen.catalog import evaluated_reference_text

        return (f"independent: {render['spp']} 1-spp layers (+{render['extra_radiance_spp']} radiance-only); "
                f"references of {evaluated_reference_text(cfg)} in two halves")
    return row["used"]


def substitutions_table(res: Results) -> pd.DataFrame:
    """Every substitution recorded in the external scenes' manifests (scenegen.custom.parse.substitutions),
    one row each: scene, what, authored, used (config values filled in), why."""
    import pandas as pd

    rows = []
    for scene in res.external_scenes:
        manifest = res.external.get(scene)
        if manifest is None:
            rows.append({"scene": scene, "what": "manifest", "authored": "", "used": "",
                         "why": f"results/scenes/{scene}/manifest.json is missing"})
        elif "substitutions" not in manifest:
            rows.append({"scene": scene, "what": "substitutions", "authored": "", "used": "not recorded",
                         "why": "the manifest predates their recording; re-run generate_scene for this scene"})
        else:
            rows += [{"scene": scene, **row, "used": _resolved_use(res.cfg, row)} for row in manifest["substitutions"]]
    return pd.DataFrame(rows, columns=list(SUBSTITUTION_COLUMNS))


def tuning_table(res: Results) -> pd.DataFrame:
    """One row per tuned method (tuning.methods): the evaluation rows that use its result, the chosen
    parameters, their score (mean frame PSNR over the training clips and tuning spp), the margin to the
    runner-up, the grid size and the scenes; 'not run' where results/tuning/{method}.json is missing."""
    import json

    import pandas as pd

    from denoisers.jobs.tuning import tuning_file

    rows = []
    for entry in (res.cfg.get("tuning") or {}).get("methods", []):
        method = entry["method"]
        users = [spec.id for spec in res.specs if spec.method == method and spec.params.get("tuned")]
        path = tuning_file(res.results_dir, method)
        row: dict[str, Any] = {"method": method, "rows": ", ".join(users) or "none"}
        if not path.is_file():
            rows.append({**row, "status": "not run"})
            continue
        record = json.loads(path.read_text())
        scores = sorted((r["score_db"] for r in record["results"]), reverse=True)
        rows.append({**row, "status": "ran", "chosen": json.dumps(record["best_params"], sort_keys=True),
                     "score_db": round(record["best_score_db"], 3),
                     "margin_db": round(scores[0] - scores[1], 3) if len(scores) > 1 else None,
                     "grid_points": len(record["results"]), "scenes": ", ".join(record["scenes"]),
                     "spp": ", ".join(map(str, record["spp"])), "frames_per_scene": record["frames_per_scene"]})
    return pd.DataFrame(rows)


def write_table(table: pd.DataFrame, folder: Path, name: str, markdown: str | None = None) -> None:
    """{folder}/{name}.csv and {name}.md (``markdown`` or the table as Markdown), each written atomically."""
    from denoisers.report.stats import frame_to_markdown
    from scenegen.atomic import write_text_atomic

    write_text_atomic(folder / f"{name}.csv", table.to_csv(index=False))
    write_text_atomic(folder / f"{name}.md", markdown if markdown is not None else frame_to_markdown(table))
