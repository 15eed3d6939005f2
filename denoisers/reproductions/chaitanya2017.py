"""Chaitanya et al. 2017, recurrent denoising autoencoder (RAE): Fig. 8 table, the Fig. 3 input ablation,
the §4.4 loss ablation and claims C1.1-C1.5 (../shared/papers/chaitanya2017-recurrent-denoising-autoencoder.txt).

Training claims (C1.2, C1.3) are decided like every other claim: on each ablation model's remodulated
output against the reference, paired over the evaluated scenes (evaluation rows generated for the
ablation variants, ``evaluation.ablation_spp``). Training-loss curves stay as figures.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.report.claims import Claim, RowNeed, compare_rows, spp_available
from denoisers.report.verdicts import Decision, not_run
from denoisers.report.stats import LABELS, fmt, fmt_ci, formatted, frame_to_markdown, mean_ci, with_ci_columns
from denoisers.reproductions.base import Reproduction
from denoisers.training.models import INPUT_ABLATION, LOSS_ABLATION, model_specs

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

PAPER = "Chaitanya 2017"
#: Fig. 3 input sets, in the paper's legend order (our variant ids).
INPUT_VARIANT_ORDER = ("color", "untextured", "depth", "normal", "normal_depth", "all")
INPUT_VARIANT_LABELS = {"color": "colour only", "untextured": "untextured (demodulated)", "depth": "+ depth",
                        "normal": "+ normal", "normal_depth": "+ normal + depth",
                        "all": "+ all (normal, depth, roughness)"}
#: §4.4: "SSIM showed an improvement from 0.9335 for Ls to 0.9417 for the combined loss" (SponzaDiffuse).
PAPER_LOSS_ABLATION_SSIM = {"spatial": 0.9335, "combined": 0.9417}
#: Fig. 8: (RMSE, SSIM) per scene at 1 spp, still images of Fig. 7 (1080p, GPU).
PAPER_FIG8: dict[str, dict[str, tuple[float, float]]] = {
    "AAF": {"CornellBox": (0.018, 0.978), "Sponza": (0.029, 0.869), "GlossySponza": (0.069, 0.664),
            "SanMiguel": (0.079, 0.774), "Classroom": (0.064, 0.786)},
    "EAW": {"CornellBox": (0.019, 0.978), "Sponza": (0.043, 0.902), "GlossySponza": (0.089, 0.586),
            "SanMiguel": (0.088, 0.768), "Classroom": (0.059, 0.841)},
    "SBF": {"CornellBox": (0.044, 0.818), "Sponza": (0.060, 0.502), "GlossySponza": (0.057, 0.649),
            "SanMiguel": (0.087, 0.575), "Classroom": (0.072, 0.610)},
    "RAE (Our)": {"CornellBox": (0.014, 0.984), "Sponza": (0.016, 0.953), "GlossySponza": (0.034, 0.843),
                  "SanMiguel": (0.055, 0.844), "Classroom": (0.040, 0.909)},
}
#: Rows of the Fig. 8 table: the paper's EAW and RAE, plus SVGF, OIDN and the input (registry names).
FIG8_METHODS: tuple[str, ...] = ("noisy", "eaw", "svgf", "oidn", "rae")
FIG8_SPP = 1
RAE = RowNeed("rae", "RAE carrying its recurrent state", (("reset_state_every_frame", None),))
RAE_PER_FRAME = RowNeed("rae", "RAE with params.reset_state_every_frame: true", (("reset_state_every_frame", True),))
EAW = RowNeed("eaw", "EAW")
NOISY = RowNeed("noisy", "noisy input")


def loss_text(weights: dict[str, float]) -> str:
    """Loss weights as 'spatial 0.8 + gradient 0.1 + temporal 0.1' (zero terms left out)."""
    return " + ".join(f"{name} {value:g}" for name, value in weights.items() if value) or "no loss"


def _row(res: Results, need: RowNeed) -> str | None:
    return res.row_of(need.method, **dict(need.params))


def _rae_note(res: Results, row: str) -> str:
    model = res.model_of(row)
    return f"RAE {model.describe()}" if model else f"RAE row {row}"


def ablation_row(res: Results, ablation: str, variant: str) -> str | None:
    """The evaluation row of an ablation variant's model, if it is configured."""
    model_id = next((m.id for m in model_specs(res.cfg) if m.ablation == ablation and m.variant == variant), None)
    return next((s.id for s in res.specs if s.role == "ablation" and s.params.get("model") == model_id), None) \
        if model_id else None


# ------------------------------------------------------------------------------------------ claims
def decide_c11(res: Results) -> Decision:
    rae, eaw = _row(res, RAE), _row(res, EAW)
    missing = spp_available(res, 1, [rae, eaw])
    if missing:
        return not_run(missing)
    return Decision([compare_rows(res, rae, eaw, "rmse", 1, "lower"), compare_rows(res, rae, eaw, "ssim", 1, "higher")],
                    note=f"paper Fig. 8 setting (1 spp); {_rae_note(res, rae)}")


def _ablation_decision(res: Results, ablation: str, pairs: list[tuple[str, str, str, str]], what: str) -> Decision:
    """Parts comparing ablation variants (a, b, metric, claimed) at the spp the variants were trained at."""
    rows = {v: ablation_row(res, ablation, v) for pair in pairs for v in pair[:2]}
    absent = [v for v, row in rows.items() if row is None]
    if absent:
        return not_run(f"ablation {ablation} has no evaluation row for variant(s) {', '.join(absent)} "
                       "(train them and list the spp in evaluation.ablation_spp)")
    model = res.model_of(next(iter(rows.values())))
    spp = int(model.spec.data.get("spp", 1)) if model else 1
    missing = spp_available(res, spp, list(rows.values()))
    if missing:
        return not_run(f"{missing} (the variants' training spp)")
    parts = [compare_rows(res, rows[a], rows[b], metric, spp, claimed) for a, b, metric, claimed in pairs]
    steps = model.summary.get("steps") if model else None
    return Decision(parts, note=f"{what}; each variant's remodulated output scored against the reference on the "
                                f"evaluated scenes at {spp} spp; same data, seed and budget ({steps} steps); "
                                "training-loss curves are in the Fig. 3 / §4.4 figures")


def decide_c12(res: Results) -> Decision:
    return _ablation_decision(res, INPUT_ABLATION, [("untextured", "color", "rmse", "lower"),
                                                    ("all", "color", "rmse", "lower")],
                              "demodulation (untextured) and demodulation + normal, depth, roughness (all) versus "
                              "colour only, in one space (RMSE of the tonemapped output)")


def decide_c13(res: Results) -> Decision:
    return _ablation_decision(res, LOSS_ABLATION, [("combined", "spatial", "ssim", "higher")],
                              "combined loss versus spatial L1 alone (paper: validation SSIM 0.9417 vs 0.9335)")


def decide_c14(res: Results) -> Decision:
    rae, noisy = _row(res, RAE), _row(res, NOISY)
    missing = spp_available(res, 4, [rae, noisy])
    if missing:
        return not_run(missing)
    model = res.model_of(rae)
    trained_spp = model.spec.data.get("spp") if model else None
    return Decision([compare_rows(res, rae, noisy, "rmse", 4, "lower"),
                     compare_rows(res, rae, noisy, "ssim", 4, "higher")],
                    note=f"RAE trained at {trained_spp} spp, evaluated at 4 spp (paper Fig. 9)")


def decide_c15(res: Results) -> Decision:
    carried, reset = _row(res, RAE), _row(res, RAE_PER_FRAME)
    missing = spp_available(res, 1, [carried, reset])
    if missing:
        return not_run(missing)
    return Decision([compare_rows(res, carried, reset, "trmae", 1, "lower")],
                    note="same weights; the per-frame row starts every frame from a zero recurrent state")


CLAIMS = (
    Claim("C1.1", PAPER, "RAE has lower RMSE and higher SSIM than EAW at 1 spp", (RAE, EAW), decide_c11),
    Claim("C1.2", PAPER, "albedo demodulation and auxiliary features lower the error versus colour-only input",
          (), decide_c12),
    Claim("C1.3", PAPER, "the combined loss gives higher SSIM than spatial L1 alone", (), decide_c13),
    Claim("C1.4", PAPER, "RAE trained at 1 spp still improves on its input at 4 spp", (RAE, NOISY), decide_c14),
    Claim("C1.5", PAPER, "the recurrent network has lower TRMAE than the same network per frame",
          (RAE, RAE_PER_FRAME), decide_c15),
)


# ------------------------------------------------------------------------------------------ tables
def fig8_table(res: Results) -> pd.DataFrame:
    """Fig. 8 layout at 1 spp: a row per method, RMSE and SSIM per scene, then the mean with its 95 % CI."""
    import pandas as pd

    rows = []
    for spec in res.main_specs:
        if spec.method not in FIG8_METHODS:
            continue
        row: dict[str, Any] = {"method": spec.id, "spp": FIG8_SPP}
        ran = res.ran(spec.id, FIG8_SPP)
        for scene in res.scenes:
            for metric in ("rmse", "ssim"):
                row[f"{scene} {LABELS[metric]}"] = float(res.scene_values(spec.id, FIG8_SPP, metric)[scene]) \
                    if ran else math.nan
        for metric in ("rmse", "ssim"):
            mean, low, high, _ = mean_ci(res.scene_values(spec.id, FIG8_SPP, metric).to_numpy(float)) if ran \
                else (math.nan,) * 3 + (0,)
            row[f"{metric}_mean"], row[f"{metric}_ci_low"], row[f"{metric}_ci_high"] = mean, low, high
        rows.append(row)
    return pd.DataFrame(rows)


def paper_fig8_table() -> pd.DataFrame:
    """The paper's Fig. 8 (RMSE and SSIM per paper scene at 1 spp), with the mean over its scenes."""
    import pandas as pd

    rows = []
    for method, scenes in PAPER_FIG8.items():
        row: dict[str, Any] = {"method": method}
        for scene, (rmse, ssim) in scenes.items():
            row[f"{scene} RMSE"], row[f"{scene} SSIM"] = rmse, ssim
        row["mean RMSE"] = round(sum(v[0] for v in scenes.values()) / len(scenes), 4)
        row["mean SSIM"] = round(sum(v[1] for v in scenes.values()) / len(scenes), 4)
        rows.append(row)
    return pd.DataFrame(rows)


def _fig8_markdown(table: pd.DataFrame, paper: pd.DataFrame) -> str:
    scene_columns = [c for c in table.columns if c.endswith((" RMSE", " SSIM"))]
    shown = formatted(table, {c: "rmse" if c.endswith("RMSE") else "ssim" for c in scene_columns})
    shown = shown[[c for c in ("method", "spp", *scene_columns) if c in shown]].copy()
    for metric, title in (("rmse", "mean RMSE"), ("ssim", "mean SSIM")):
        if f"{metric}_mean" in table:
            shown[title] = [fmt_ci(m, lo, hi, metric) for m, lo, hi in
                            zip(table[f"{metric}_mean"], table[f"{metric}_ci_low"], table[f"{metric}_ci_high"])]
    return (frame_to_markdown(shown) if len(shown) else "no Fig. 8 method configured\n") + (
        "\nPaper (Chaitanya et al. 2017, Fig. 8; 1 spp, 1-bounce GI, 1080p, 2000-4000 spp targets; other scenes, "
        "for context only):\n\n" + frame_to_markdown(paper))


def _scene_metric(res: Results, row: str | None, spp: int, metric: str) -> tuple[float, float, float]:
    if row is None or not res.ran(row, spp):
        return math.nan, math.nan, math.nan
    return mean_ci(res.scene_values(row, spp, metric).to_numpy(float))[:3]


def ablation_table(res: Results, ablation: str, order: tuple[str, ...] = ()) -> pd.DataFrame:
    """Per variant: final training loss, validation loss / RMSE / SSIM (± over validation sequences) and
    RMSE / SSIM of its output on the evaluated scenes (± over scenes)."""
    import pandas as pd

    variants = res.models.variants(ablation) if res.models else {}
    rows = []
    for variant in [v for v in order if v in variants] + sorted(set(variants) - set(order)):
        model = variants[variant]
        row: dict[str, Any] = {"variant": variant, "inputs": INPUT_VARIANT_LABELS.get(variant, variant)
                               if ablation == INPUT_ABLATION else loss_text(model.spec.loss),
                               "model": model.spec.id, "steps": model.summary.get("steps"),
                               "final_train_loss": model.final_training_loss()}
        for column in ("loss", "rmse", "ssim"):
            mean, low, high, _ = mean_ci(model.validation[column].to_numpy(float))
            row.update({f"val_{column}_mean": mean, f"val_{column}_ci_low": low, f"val_{column}_ci_high": high})
        row["val_sequences"] = len(model.validation)
        spp = int(model.spec.data.get("spp", 1))
        row["test_spp"] = spp
        for metric in ("rmse", "ssim"):
            mean, low, high = _scene_metric(res, ablation_row(res, ablation, variant), spp, metric)
            row.update({f"test_{metric}_mean": mean, f"test_{metric}_ci_low": low, f"test_{metric}_ci_high": high})
        if ablation == LOSS_ABLATION:
            row["paper_val_ssim"] = PAPER_LOSS_ABLATION_SSIM.get(variant, math.nan)
        rows.append(row)
    return pd.DataFrame(rows)


def _ablation_markdown(table: pd.DataFrame) -> str:
    if not len(table):
        return "no variant trained\n"
    shown = with_ci_columns(table, {"val loss": ("val_loss", "rmse"), "val RMSE": ("val_rmse", "rmse"),
                                    "val SSIM": ("val_ssim", "ssim"), "scenes RMSE": ("test_rmse", "rmse"),
                                    "scenes SSIM": ("test_ssim", "ssim")},
                            ["variant", "inputs", "model", "steps"], ["val_sequences", "test_spp", "paper_val_ssim"])
    shown.insert(4, "final train loss", [fmt(v, "rmse") for v in table["final_train_loss"]])
    return frame_to_markdown(shown)


# ----------------------------------------------------------------------------------------- figures
#: Per ablation: curve column, running-mean window, log y, y label, title.
ABLATION_PLOTS = {
    INPUT_ABLATION: ("train_loss", 5, True, "training loss (running mean; colour only in a different space)",
                     "RAE input ablation (Chaitanya et al. 2017, Fig. 3)"),
    LOSS_ABLATION: ("val_ssim", 1, False, "validation SSIM", "RAE loss ablation (Chaitanya et al. 2017, §4.4)"),
}


def plot_ablation(res: Results, ablation: str, path: Path) -> None:
    """Fig. 3 (training loss of every input set) or §4.4 (validation SSIM of each loss) against step."""
    from denoisers.report.figures import placeholder, pyplot, save_step_plot, smoothed

    column, window, log_y, ylabel, title = ABLATION_PLOTS[ablation]
    variants = res.models.variants(ablation) if res.models else {}
    if not variants:
        placeholder(path, f"no {ablation} model was trained")
        return
    figure, axes = pyplot().subplots(figsize=(7, 4.5))
    order = INPUT_VARIANT_ORDER if ablation == INPUT_ABLATION else ()
    for variant in [v for v in order if v in variants] + sorted(set(variants) - set(order)):
        model = variants[variant]
        curves = model.curves.dropna(subset=[column]) if column in model.curves else model.curves.iloc[0:0]
        label = INPUT_VARIANT_LABELS.get(variant, variant) if ablation == INPUT_ABLATION \
            else f"{variant} ({loss_text(model.spec.loss)})"
        axes.plot(curves["step"], smoothed(curves[column], window), marker="." if window == 1 else None, label=label)
    save_step_plot(figure, axes, path, ylabel, title, log_y=log_y, legend_size=8)


# ------------------------------------------------------------------------------------ registration
def _ablations(cfg: dict) -> list[str]:
    present = {spec.ablation for spec in model_specs(cfg) if spec.ablation}
    return [name for name in (INPUT_ABLATION, LOSS_ABLATION) if name in present]


def table_names(cfg: dict) -> list[str]:
    return ["chaitanya_fig8", "chaitanya_fig8_paper", *_ablations(cfg)]


def figure_names(cfg: dict) -> list[str]:
    return [f"{name}_curves" for name in _ablations(cfg)]


def write(res: Results, tables: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table

    fig8, paper = fig8_table(res), paper_fig8_table()
    fig8_md = _fig8_markdown(fig8, paper)
    write_table(fig8, tables, "chaitanya_fig8", fig8_md)
    write_table(paper, tables, "chaitanya_fig8_paper")
    lines = ["### Fig. 8: RMSE and SSIM per scene at 1 spp", "",
             fig8_md if FIG8_SPP in res.cfg["evaluation"]["spp"] else "not run: 1 spp was not evaluated\n"]
    ablations = _ablations(res.cfg)
    titles = {INPUT_ABLATION: ("Input ablation (Fig. 3)", INPUT_VARIANT_ORDER), LOSS_ABLATION: ("Loss ablation (§4.4)", ())}
    for name in ablations:
        title, order = titles[name]
        table = ablation_table(res, name, order)
        markdown = _ablation_markdown(table)
        write_table(table, tables, name, markdown)
        plot_ablation(res, name, figures / f"{name}_curves.png")
        lines += [f"### {title}", "",
                  "Same data, seed and budget for every variant. Validation: ± over validation sequences; "
                  "scenes: each variant's output on the evaluated scenes, ± over scenes (what C1.2/C1.3 are "
                  "decided on). The colour-only training loss is on non-demodulated colour, the others on "
                  "demodulated colour, so training losses are not comparable across that line.", "", markdown,
                  f"![{title}](figures/{name}_curves.png)", ""]
    return "\n".join(lines)


REPRODUCTION = Reproduction(
    key="chaitanya2017", paper="Chaitanya et al. 2017", order=1,
    title="Interactive reconstruction of Monte Carlo image sequences using a recurrent denoising autoencoder",
    source="chaitanya2017-recurrent-denoising-autoencoder.txt", claims=CLAIMS, tables=table_names,
    figures=figure_names, write=write)
