"""Hasselgren et al. 2020, neural temporal adaptive sampling and denoising (NTASD): Table 1 (rMSE), the Fig. 7
breakdown (PSNR and tPSNR of direct prediction, KPN, temporal uniform, temporal adaptive and uniform 8 spp),
the Fig. 6 sample maps and claims C2.1-C2.5 (../shared/papers/hasselgren2020-neural-temporal-adaptive-sampling.md).

Every comparison is at the paper's 4 spp, paired over the evaluated scenes (denoisers.report.claims). The
rows are found by registry method and params: ``ntasd`` (temporal adaptive), ``ntasd_uniform`` (temporal
uniform; the row with ``budget_factor: 2`` spends 8 spp at an evaluated 4 spp, the paper's "uniform 8 spp"),
``ntasd_kpn``, ``ntasd_direct``, ``dasr``; RAE and SVGF as in the other papers. Figures:
denoisers.reproductions._hasselgren2020_figures.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.evaluate import TIMING_FILE, denoised_dir, method_specs
from denoisers.report.claims import Claim, RowNeed, compare_rows, missing_rows, spp_available
from denoisers.report.verdicts import Decision, not_run
from denoisers.report.claims import row_at as claims_row_at
from denoisers.report.stats import fmt, fmt_ci, frame_to_markdown, mean_ci
from denoisers.reproductions.base import Reproduction
from scenegen.catalog import evaluated_reference_text

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

PAPER = "Hasselgren 2020"
#: Every claim, table and figure of the paper is at an (average) 4 spp.
SPP = 4
#: Rows spending the evaluated spp (budget_factor 1, the methods' default); the 8-spp row sets budget_factor 2.
AT_BUDGET = (("budget_factor", 1),)
TEMPORAL_ADAPTIVE = RowNeed("ntasd", "NTASD temporal adaptive (sample-map network + recurrent KPN)", AT_BUDGET)
TEMPORAL_UNIFORM = RowNeed("ntasd_uniform", "NTASD temporal, uniform 4 spp", AT_BUDGET)
UNIFORM_8SPP = RowNeed("ntasd_uniform", "NTASD temporal, uniform 8 spp (params.budget_factor: 2)",
                       (("budget_factor", 2),))
KPN = RowNeed("ntasd_kpn", "per-frame KPN (no recurrence)", AT_BUDGET)
DIRECT = RowNeed("ntasd_direct", "direct prediction (no kernels)", AT_BUDGET)
DASR = RowNeed("dasr", "DASR (1-spp initial pass + adaptive sampling, Kuznetsov et al. 2018)", AT_BUDGET)
RAE = RowNeed("rae", "RAE carrying its recurrent state", (("reset_state_every_frame", None),))
SVGF = RowNeed("svgf", "SVGF")
#: The rows this paper's tables and figures are made of (RAE and SVGF belong to the other papers too).
OWN_NEEDS = (TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM, UNIFORM_8SPP, KPN, DIRECT, DASR)
#: Table 1 columns: (label, row).
TABLE1 = (("adaptive", TEMPORAL_ADAPTIVE), ("uniform", TEMPORAL_UNIFORM), ("DASR", DASR), ("direct prediction", DIRECT))
#: Table 1 of the paper: rMSE x 1000 per scene (1080p validation images, 4 spp).
PAPER_TABLE1 = {"SUNTEMPLE": (7.0, 9.8, 10.0, 14.8), "CLASSROOM": (7.0, 10.6, 12.4, 15.0),
                "BATHROOM": (7.3, 9.7, 12.6, 12.1)}
RMSE_FACTOR = 1000.0
#: rMSE x 1000 is shown with the 2 decimals of a dB column (denoisers.report.stats.DECIMALS).
SCALED_DECIMALS = "psnr"
OURS, THEIRS = "ours (evaluated scenes, 4 spp)", "paper (Hasselgren et al. 2020, Table 1; other scenes)"
#: Fig. 7 curves in the paper's legend order: (label, row).
FIG7 = (("direct prediction", DIRECT), ("KPN", KPN), ("temporal uniform", TEMPORAL_UNIFORM),
        ("temporal adaptive", TEMPORAL_ADAPTIVE), ("uniform 8 spp", UNIFORM_8SPP))
#: Fig. 6 columns beside the reference: (label, row).
SAMPLE_MAP_ROWS = (("NTASD", TEMPORAL_ADAPTIVE), ("DASR", DASR))
TABLE1_NAME, FIG7_NAME, SAMPLE_MAPS_NAME = "hasselgren2020_table1", "hasselgren2020_fig7", "hasselgren2020_sample_maps"


def row_at(res: Results, need: RowNeed, spp: int = SPP) -> str | None:
    """:func:`denoisers.report.claims.row_at` at the paper's 4 spp by default."""
    return claims_row_at(res, need, spp)


def realised_spp(res: Results, row: str | None, spp: int = SPP) -> float:
    """Mean over the evaluated scenes of the samples per pixel a row really spent (its sample maps): the
    ``realised_spp`` column of the per-frame metrics, else timing.json's ``realised_spp``; NaN if neither."""
    import numpy as np

    if row is None or not res.ran(row, spp):
        return math.nan
    frames = res.frames
    if "realised_spp" in frames and "method_id" in frames:
        part = frames[(frames.method_id == row) & (frames.spp == spp)]
        per_scene = part.groupby("scene")["realised_spp"].mean().dropna()
        if len(per_scene):
            return float(per_scene.mean())
    values = []
    for scene in res.scenes:
        path = denoised_dir(res.results_dir, row, scene, spp) / TIMING_FILE
        value = json.loads(path.read_text()).get("realised_spp") if path.is_file() else None
        if value is not None:
            values.append(float(value))
    return float(np.mean(values)) if values else math.nan


#: A row whose sample maps give at least this share of the pixels one and the same count (per frame, averaged)
#: samples uniformly in effect: its sampler has not learnt to adapt, which the report says beside Fig. 6.
FLAT_MAP_SHARE = 0.98


def map_spread(res: Results, row: str | None, spp: int = SPP) -> dict[str, float] | None:
    """How adaptive a row's sample maps are, over every evaluated scene and frame: ``modal_share`` = mean per frame
    of the share of pixels at the frame's most frequent count (1.0 = a flat map) and ``cv`` = mean per frame of
    std / mean of the counts. None without sample maps."""
    import numpy as np

    from denoisers.adaptive import SAMPLE_MAPS_FILE

    if row is None or not res.ran(row, spp):
        return None
    shares, cvs = [], []
    for scene in res.scenes:
        path = denoised_dir(res.results_dir, row, scene, spp) / SAMPLE_MAPS_FILE
        if not path.is_file():
            continue
        with np.load(path) as data:
            maps = np.asarray(data["sample_maps"], dtype=np.int64).reshape(len(data["sample_maps"]), -1)
        for counts in maps:
            shares.append(np.bincount(counts).max() / counts.size)
            cvs.append(counts.std() / counts.mean() if counts.mean() > 0 else math.nan)
    if not shares:
        return None
    return {"modal_share": float(np.mean(shares)), "cv": float(np.nanmean(cvs))}


def _spread_text(res: Results) -> str:
    parts = []
    for label, need in SAMPLE_MAP_ROWS:
        row = row_at(res, need)
        spread = map_spread(res, row)
        if spread is None:
            continue
        flat = spread["modal_share"] >= FLAT_MAP_SHARE
        parts.append(f"{label} ({row}): {spread['modal_share']:.1%} of the pixels at one count per frame, coefficient "
                     f"of variation {spread['cv']:.2f}" + (" -- flat: its sampler does not adapt, so the claims "
                                                          "comparing it test uniform sampling" if flat else ""))
    return ("Spread of the maps over every evaluated frame: " + "; ".join(parts) + ".") if parts else ""


# ------------------------------------------------------------------------------------------ claims
def _decide(res: Results, parts: list[tuple[RowNeed, RowNeed, str, str]], note: str) -> Decision:
    """Paired parts (row a, row b, metric, claimed direction of a - b) at 4 spp over the evaluated scenes."""
    needs = list(dict.fromkeys(need for part in parts for need in part[:2]))
    absent = missing_rows(res, needs)
    if absent:
        return not_run("missing rows: " + "; ".join(f"{n.description} (method '{n.method}')" for n in absent))
    rows = {need: row_at(res, need) for need in needs}
    missing = spp_available(res, SPP, list(rows.values()))
    if missing:
        return not_run(missing)
    return Decision([compare_rows(res, rows[a], rows[b], metric, SPP, claimed) for a, b, metric, claimed in parts],
                    note=note)


def decide_c21(res: Results) -> Decision:
    return _decide(res, [(KPN, DIRECT, "psnr", "higher")], "same U-Net, kernels versus colours predicted per frame")


def decide_c22(res: Results) -> Decision:
    return _decide(res, [(TEMPORAL_UNIFORM, KPN, "psnr", "higher"), (TEMPORAL_UNIFORM, KPN, "tpsnr", "higher")],
                   "both sample 4 spp uniformly; the temporal row adds the warped previous output and temporal kernel")


def decide_c23(res: Results) -> Decision:
    spent = realised_spp(res, row_at(res, TEMPORAL_ADAPTIVE))
    return _decide(res, [(TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM, "psnr", "higher")],
                   (f"the adaptive row spent {fmt(spent)} spp on average (its sample maps)" if not math.isnan(spent)
                    else "the adaptive row's realised spp is not recorded") + f"; budget {SPP} spp per frame")


def decide_c24(res: Results) -> Decision:
    return _decide(res, [(TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM, "relmse", "lower"),
                         (TEMPORAL_UNIFORM, DASR, "relmse", "lower"), (DASR, DIRECT, "relmse", "lower")],
                   "Table 1 order as three paired steps; rMSE of linear HDR radiance, frame mean per scene")


def decide_c25(res: Results) -> Decision:
    rae = row_at(res, RAE)
    model = res.model_of(rae) if rae else None
    trained = f"; RAE {model.describe()}, trained at {model.spec.data.get('spp')} spp" if model else ""
    return _decide(res, [(TEMPORAL_ADAPTIVE, RAE, "psnr", "higher"), (TEMPORAL_ADAPTIVE, SVGF, "psnr", "higher"),
                         (TEMPORAL_ADAPTIVE, RAE, "trmae", "lower")],
                   "temporal stability as TRMAE (as C1.5; the paper judged it from video)" + trained)


CLAIMS = (
    Claim("C2.1", PAPER, "kernel prediction beats direct prediction (PSNR)", (KPN, DIRECT), decide_c21),
    Claim("C2.2", PAPER, "warped temporal recurrence improves PSNR and tPSNR over per-frame KPN",
          (TEMPORAL_UNIFORM, KPN), decide_c22),
    Claim("C2.3", PAPER, "adaptive sampling at 4 spp on average beats uniform 4 spp",
          (TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM), decide_c23),
    Claim("C2.4", PAPER, "rMSE order: adaptive < uniform < DASR < direct prediction",
          (TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM, DASR, DIRECT), decide_c24),
    Claim("C2.5", PAPER, "at 4 spp NTASD beats RAE and SVGF in PSNR and is more stable than RAE",
          (TEMPORAL_ADAPTIVE, RAE, SVGF), decide_c25),
)


# ------------------------------------------------------------------------------------------ tables
def table1_values(res: Results) -> dict[str, pd.Series | None]:
    """Column -> rMSE x 1000 per evaluated scene of the Table 1 row (None where it did not run at 4 spp)."""
    columns = {}
    for label, need in TABLE1:
        row = row_at(res, need)
        ran = row is not None and res.ran(row, SPP)
        columns[f"{label} rMSE x1000"] = res.scene_values(row, SPP, "relmse") * RMSE_FACTOR if ran else None
    return columns


def table1(res: Results) -> pd.DataFrame:
    """Table 1 layout: rMSE x 1000 per evaluated scene and their mean (ours), then the paper's rows and mean
    (its scenes, not paired with ours); a column per method, NaN where a row did not run."""
    import pandas as pd

    values = table1_values(res)
    rows: list[dict[str, Any]] = []
    for scene in res.scenes:
        rows.append({"source": OURS, "scene": scene,
                     **{c: float(v.get(scene, math.nan)) if v is not None else math.nan for c, v in values.items()}})
    rows.append({"source": OURS, "scene": "mean",
                 **{c: mean_ci(v.to_numpy(float))[0] if v is not None else math.nan for c, v in values.items()}})
    for scene, published in PAPER_TABLE1.items():
        rows.append({"source": THEIRS, "scene": scene, **dict(zip(values, published))})
    rows.append({"source": THEIRS, "scene": "mean", **{c: round(sum(p[i] for p in PAPER_TABLE1.values())
                                                                / len(PAPER_TABLE1), 2) for i, c in enumerate(values)}})
    return pd.DataFrame(rows, columns=["source", "scene", *values])


def _table1_markdown(res: Results, table: pd.DataFrame) -> str:
    ours = table[table.source == OURS].drop(columns="source")
    shown = ours.astype(object)
    for column, scaled in table1_values(res).items():
        shown[column] = [fmt(float(v), SCALED_DECIMALS) for v in ours[column]]
        if scaled is not None:   # the mean with its interval over scenes
            shown.loc[shown.scene == "mean", column] = fmt_ci(*mean_ci(scaled.to_numpy(float))[:3], SCALED_DECIMALS)
    used = ", ".join(f"{label} = `{row_at(res, need) or 'missing'}`" for label, need in TABLE1)
    return (f"Ours: rMSE × 1000 per evaluated scene at {SPP} spp, mean ± 95 % CI over scenes (rows: {used}):\n\n"
            + frame_to_markdown(shown) + "\nPaper (Table 1: 1080p validation images of SUNTEMPLE, CLASSROOM, "
            "BATHROOM, 4k-spp references; other scenes than ours, for context only, not paired):\n\n"
            + frame_to_markdown(table[table.source == THEIRS].drop(columns="source")))


def fig7_table(res: Results) -> pd.DataFrame:
    """Per Fig. 7 curve: its row, budget and realised spp, mean PSNR and tPSNR over the evaluated scenes at 4 spp
    (95 % CI bounds) and the number of scenes."""
    import pandas as pd

    rows = []
    for label, need in FIG7:
        row = row_at(res, need)
        ran = row is not None and res.ran(row, SPP)
        factor = int(res.spec(row).params.get("budget_factor") or 1) if row else 1
        record: dict[str, Any] = {"curve": label, "row": row or "not configured", "status": "ran" if ran else "not run",
                                  "spp": SPP, "budget_spp": SPP * factor, "realised_spp": realised_spp(res, row),
                                  "n_scenes": len(res.scene_values(row, SPP, "psnr").dropna()) if ran else 0}
        for metric in ("psnr", "tpsnr"):
            mean, low, high, _ = mean_ci(res.scene_values(row, SPP, metric).to_numpy(float)) if ran \
                else (math.nan, math.nan, math.nan, 0)
            record.update({f"{metric}_mean": mean, f"{metric}_ci_low": low, f"{metric}_ci_high": high})
        rows.append(record)
    return pd.DataFrame(rows)


def _fig7_markdown(table: pd.DataFrame) -> str:
    import pandas as pd

    shown = pd.DataFrame({"curve": table["curve"], "row": table["row"], "budget spp": table["budget_spp"],
                          "realised spp": [fmt(v) for v in table["realised_spp"]],
                          **{title: [fmt_ci(m, lo, hi, metric) if s == "ran" else "not run" for m, lo, hi, s in
                                     zip(table[f"{metric}_mean"], table[f"{metric}_ci_low"],
                                         table[f"{metric}_ci_high"], table["status"])]
                             for title, metric in (("PSNR (dB)", "psnr"), ("tPSNR (dB)", "tpsnr"))},
                          "scenes": table["n_scenes"]})
    return frame_to_markdown(shown)


# ------------------------------------------------------------------------------------ registration
def has_rows(cfg: dict) -> bool:
    """Whether the config evaluates any NTASD or DASR row at 4 spp (config level: no results, no heavy imports)."""
    methods = {need.method for need in OWN_NEEDS}
    return any(spec.role == "method" and spec.method in methods and SPP in spec.spp for spec in method_specs(cfg))


def table_names(cfg: dict) -> list[str]:
    return [TABLE1_NAME, FIG7_NAME] if has_rows(cfg) else []


def figure_names(cfg: dict) -> list[str]:
    return [FIG7_NAME, SAMPLE_MAPS_NAME] if has_rows(cfg) else []


def _missing_text(res: Results) -> str:
    needs = [*OWN_NEEDS, RAE, SVGF]
    absent = [f"{n.description} (method '{n.method}')" for n in needs if not res.ran(row_at(res, n), SPP)]
    return ("Rows missing at 4 spp (not configured or without results; their columns, curves and claims are not "
            "run): " + "; ".join(absent) + ".") if absent else ""


def _deviations(res: Results) -> list[str]:
    from denoisers.training.data import COLOUR_AUGMENTATION_KEYS
    from denoisers.training.models import model_specs

    methods = {need.method for need in OWN_NEEDS}
    specs = [spec for spec in model_specs(res.cfg) if spec.method in methods and not spec.ablation]
    widths = sorted({float(spec.net.get("width", 1.0)) for spec in specs})

    def common(data: dict) -> dict:        # direct prediction's colour augmentation is the paper's (Sec. 2.2)
        return {k: v for k, v in data.items() if k not in COLOUR_AUGMENTATION_KEYS}

    shared = len({repr((spec.seed, common(spec.data), spec.budget, spec.optimizer)) for spec in specs}) == 1
    recoloured = [spec.id for spec in specs if any(spec.data.get(k) for k in COLOUR_AUGMENTATION_KEYS)]
    budget = specs[0].budget.get("max_steps") if specs else None
    render = res.cfg["render"]
    return [(f"- Networks: our U-Nets at width {', '.join(f'{w:g}' for w in widths)} of the paper's (~850 k weights "
             f"at width 1, Fig. 3); the variants {'share' if shared else 'do NOT share'} data, seed, optimiser and "
             f"budget (at most {budget} steps; the paper trains 1000 epochs)"
             + (f"; {', '.join(recoloured)} also trains with the hue permutation and grayscale augmentation the "
                f"paper adds for direct prediction (Sec. 2.2)" if recoloured else "") + ".") if specs
            else "- Networks: no NTASD or DASR model is configured.",
            f"- Scenes: our procedurally generated test scenes at {render['width']}×{render['height']} with "
            f"references of {evaluated_reference_text(res.cfg)}, not SUNTEMPLE / CLASSROOM / BATHROOM at 1080p with 4k-spp "
            "references: the paper's numbers are context, never paired with ours.",
            "- DASR uses the same sample-map U-Net and kernel-predicting denoiser as NTASD, as Hasselgren et al. "
            "altered it, per frame, after a 1-spp initial pass that counts toward the 4-spp budget.",
            "- rMSE: per-channel relative MSE of linear HDR radiance, eps 0.01 (the paper gives no formula); "
            "tPSNR: PSNR of temporal differences of the tonemapped frames (Sec. 3); C2.5's stability is TRMAE "
            "(as C1.5), where the paper relies on its video.",
            "- Uniform 8 spp: the temporal-uniform network given 8 spp (budget_factor 2), evaluated beside the "
            "4-spp rows."]


def write(res: Results, tables: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table

    missing = _missing_text(res)
    if not has_rows(res.cfg):
        return "Not run: the config evaluates no NTASD or DASR row at 4 spp. " + missing
    from denoisers.reproductions._hasselgren2020_figures import plot_fig7, plot_sample_maps

    t1, f7 = table1(res), fig7_table(res)
    md1, md7 = _table1_markdown(res, t1), _fig7_markdown(f7)
    write_table(t1, tables, TABLE1_NAME, md1)
    write_table(f7, tables, FIG7_NAME, md7)
    scene = plot_fig7(res, figures / f"{FIG7_NAME}.png", [(label, row_at(res, need)) for label, need in FIG7], SPP)
    plot_sample_maps(res, figures / f"{SAMPLE_MAPS_NAME}.png",
                     [(label, row_at(res, need)) for label, need in SAMPLE_MAP_ROWS], SPP)
    spread = _spread_text(res)
    return "\n".join([
        f"NTASD and its ablations (direct prediction, per-frame KPN, temporal uniform, temporal adaptive, uniform "
        f"8 spp) and DASR at an average of {SPP} spp, RAE and SVGF at {SPP} spp; every claim paired over the "
        f"{len(res.scenes)} evaluated scene(s).", "", *([missing, ""] if missing else []),
        "### Table 1: rMSE (× 1000)", "", md1,
        f"### Fig. 7: PSNR and tPSNR at {SPP} spp", "",
        "Mean ± 95 % CI over the evaluated scenes; budget = spp × budget_factor; realised = the mean samples per "
        "pixel of the row's sample maps. The paper shows Fig. 7 as curves only (no numbers in its text), so no "
        "published values stand beside these.", "", md7,
        f"![Fig. 7: per-frame PSNR and tPSNR on {scene or 'no scene'}](figures/{FIG7_NAME}.png)", "",
        "### Fig. 6: sample maps of NTASD and DASR", "",
        f"![Fig. 6: sample maps](figures/{SAMPLE_MAPS_NAME}.png)", "", *([spread, ""] if spread else []),
        "### Deviations from the paper", "", *_deviations(res)])


REPRODUCTION = Reproduction(
    key="hasselgren2020", paper="Hasselgren et al. 2020", order=2,
    title="Neural temporal adaptive sampling and denoising",
    source="hasselgren2020-neural-temporal-adaptive-sampling.md",
    claims=CLAIMS, tables=table_names, figures=figure_names, write=write)
