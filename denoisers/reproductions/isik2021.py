"""Isik et al. 2021, affinity of neural features (AFN): Tables 2-5 laid out like the paper, Fig. 8 (PSNR against
throughput) and claims C3.1-C3.5 (../shared/papers/isik2021-affinity-of-neural-features.md).

AFN rows are found by what their model is, not by their names: a row of registry method ``afn`` names a model
(``params.model``) whose ``net`` settings, completed with denoisers.nets.afn.AFNConfig's defaults, say which
variant it is (:data:`VARIANTS`: full, single, K1, d, heur, ntk, nar, wpred, gather K1 / K3). A row with
``params.kernel_size`` runs a model with another kernel size at test time (C3.5); the other tables use rows
without it. Single-frame tables (2, 4, 5) use the frame-mean PSNR, the video table (3) the paper's video PSNR
(Eq. 14: MSE pooled over a clip's frames) and TRMAE (Eq. 16). The paper evaluates at 2-32 spp; claims use
the spp of 2, 4, 8 that the config evaluates (evaluation.spp) and say which.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.report.claims import Claim, RowNeed, compare_rows, seed_differences, seeds_of
from denoisers.report.verdicts import Decision, Part, not_run
from denoisers.report.seeds import seed_mean
from denoisers.report.stats import LABELS, MUCH_WORSE_MARGIN_DB, fmt_ci, frame_to_markdown, mean_ci
from denoisers.reproductions import _isik2021_paper as paper
from denoisers.reproductions.base import Reproduction

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

PAPER = "Isik 2021"
CLAIM_SPP = (2, 4, 8)
#: Variant -> the AFNConfig values that define it (every other key may take any value).
FULL_FLAGS: dict[str, Any] = {"temporal": True, "kernels": 3, "dilate": True, "affinity_dim": 8,
                              "kernel_kind": "affinity", "temporal_kernel": True, "accumulate_radiance": True,
                              "fixed_lambda": None, "history_input": "embedding"}
SINGLE_FLAGS: dict[str, Any] = {"temporal": False, "kernels": 3, "dilate": True, "affinity_dim": 8,
                                "kernel_kind": "affinity"}
VARIANTS: dict[str, dict[str, Any]] = {
    "ours": FULL_FLAGS,
    "ours-single": SINGLE_FLAGS,
    "ours-K1": {"temporal": False, "kernels": 1, "kernel_kind": "affinity"},
    "ours-heur": {**FULL_FLAGS, "fixed_lambda": 0.8},
    "ours-ntk": {**FULL_FLAGS, "temporal_kernel": False},
    "ours-nar": {**FULL_FLAGS, "accumulate_radiance": False},
    # Sec. 5.5.4: both accumulations (Eq. 3 and 5) off, the warped previous prediction fed instead, temporal kernel kept.
    "ours-wpred": {**FULL_FLAGS, "history_input": "prediction", "accumulate_radiance": False},
    **{f"d={d}": {**SINGLE_FLAGS, "affinity_dim": d} for d in (1, 2, 4)},
    "gather K1": {"temporal": False, "kernels": 1, "kernel_kind": "gather"},
    "gather K3": {"temporal": False, "kernels": 3, "kernel_kind": "gather"},
}
AFN = RowNeed("afn", "AFN, the full temporal model (net defaults)")
KPCN = RowNeed("kpcn", "KPCN (Bako et al. 2017)")
OIDN = RowNeed("oidn", "OIDN (standing in for the OptiX denoiser)")

TABLES = ("isik_table2", "isik_table3", "isik_table4", "isik_table5")
FIG8 = "isik_fig8"
FIG5 = "isik_fig5_lambda"


# ------------------------------------------------------------------------------------------ rows
def row_net(res: Results, row: str) -> dict[str, Any] | None:
    """The AFNConfig (as a dict, defaults filled) of the model an ``afn`` row runs; None when unknown."""
    from denoisers.nets.afn import AFNConfig
    from denoisers.training.models import model_spec

    model = res.spec(row).params.get("model")
    if not model:
        return None
    try:
        return AFNConfig.from_dict(model_spec(res.cfg, model).net).to_dict()
    except (KeyError, TypeError, ValueError):
        return None


def variant_of(net: Mapping[str, Any]) -> str | None:
    """The first variant of :data:`VARIANTS` whose flags ``net`` has (None: none)."""
    return next((name for name, flags in VARIANTS.items() if all(net.get(k) == v for k, v in flags.items())), None)


def afn_rows(res: Results, test_time_size: bool = False) -> dict[str, tuple[str, dict[str, Any]]]:
    """row id -> (variant, net) of the ``afn`` rows that ran; rows with params.kernel_size only when
    ``test_time_size`` (then only those)."""
    found = {}
    for row in res.rows_of("afn"):
        if bool(res.spec(row).params.get("kernel_size")) != test_time_size:
            continue
        net = row_net(res, row)
        variant = variant_of(net) if net else None
        if variant is not None:
            found[row] = (variant, net)
    return found


def variant_row(res: Results, variant: str) -> str | None:
    return next((row for row, (name, _) in afn_rows(res).items() if name == variant), None)


def trained_parameters(res: Results, row: str) -> int | None:
    """Parameters of the network of the model row ``row`` runs (``params.model``), built from its settings at their
    width; None for a row without a trained model."""
    from denoisers.nets import build_net, count_parameters
    from denoisers.training.models import method_model, model_spec
    from denoisers.training.tasks import build_task

    model = method_model(res.spec(row).params)
    if not model:
        return None
    net = build_task(model_spec(res.cfg, model)).net_spec()
    return count_parameters(build_net(net["name"], net["config"]))


def claim_spps(res: Results, rows: list[str | None]) -> list[int]:
    """The claim spp (2, 4, 8) the config evaluates and every row ran at."""
    return [spp for spp in CLAIM_SPP if spp in res.cfg["evaluation"]["spp"] and all(res.ran(r, spp) for r in rows)]


# ------------------------------------------------------------------------------------------ claims
def _pairs(res: Results, pairs: list[tuple[str | None, str | None, str, str, str]], note: str,
           threshold: float = 0.0) -> Decision:
    """Parts (row a, row b, metric, claimed, label) at every claim spp both rows ran at, claimed beyond
    ``threshold`` (verdicts.Part.threshold)."""
    missing = sorted({label for a, b, _, _, label in pairs if a is None or b is None})
    if missing:
        return not_run("missing rows: " + "; ".join(missing))
    rows = [r for a, b, *_ in pairs for r in (a, b)]
    spps = claim_spps(res, rows)
    if not spps:
        return not_run(f"no row set ran at any of {list(CLAIM_SPP)} spp (evaluation.spp = "
                       f"{res.cfg['evaluation']['spp']})")
    parts = [compare_rows(res, a, b, metric, spp, claimed, threshold=threshold)
             for a, b, metric, claimed, _ in pairs for spp in spps]
    return Decision(parts, note=f"{note}; at {', '.join(map(str, spps))} spp")


#: A KPCN size matches ours-single's capacity (C3.1) when its parameter count is within this fraction of ours-single's.
PARAMETER_MATCH = 0.1


def decide_c31(res: Results) -> Decision:
    """ours-single against ours-K1 and KPCN at the claim spp. KPCN's capacity is a free choice, so (issue 46: "match
    parameter counts, or sweep KPCN") ours-single must also beat KPCN at its own parameter count: every width of
    the kpcn capacity sweep whose network is within :data:`PARAMETER_MATCH` of ours-single's parameters is a part
    (at the spp the sweep is scored at). The sweep's other widths are a capacity measurement, named in the note."""
    kpcn = res.row_of("kpcn")
    single, k1 = variant_row(res, "ours-single"), variant_row(res, "ours-K1")
    decision = _pairs(res, [(single, k1, "psnr", "higher", "AFN ours-single / ours-K1 (afn models with net.temporal false)"),
                            (single, kpcn, "psnr", "higher", "KPCN (method 'kpcn')")],
                      "frame-mean PSNR (Table 2 is single-frame)")
    if decision.not_run:
        return decision
    own = trained_parameters(res, single)
    sizes = {row: trained_parameters(res, row) for row in res.rows_of("kpcn", role="ablation")}
    if own is None:
        return decision
    matched = [row for row, count in sizes.items() if count is not None and abs(count - own) <= PARAMETER_MATCH * own]
    for row in matched:
        spps = [spp for spp in CLAIM_SPP if res.ran(row, spp) and res.ran(single, spp)]
        decision.parts += [compare_rows(res, single, row, "psnr", spp, "higher") for spp in spps]
    decision.note += f"; ours-single has {own:,} parameters, {kpcn} {trained_parameters(res, kpcn):,}"
    if matched:
        decision.note += "; KPCN at its parameter count too: " + ", ".join(f"{row} ({sizes[row]:,})" for row in matched)
    others = [row for row in sizes if row not in matched]
    if others:
        decision.note += ("; not parts (capacity measurements): " + ", ".join(f"{row} ({sizes[row]:,})" for row in others))
    return decision


def decide_c32(res: Results) -> Decision:
    """d = 1 against every other d of the same variant flags (the single-frame model, d = 2, 4, 8)."""
    rows = afn_rows(res)
    d1 = next((row for row, (name, _) in rows.items() if name == "d=1"), None)
    others = [row for row, (name, _) in rows.items() if name in ("ours-single", "d=2", "d=4")]
    if d1 is None or not others:
        return not_run("missing rows: a single-frame afn model with net.affinity_dim 1 and one with 2, 4 or 8")
    return _pairs(res, [(other, d1, "psnr", "higher", "") for other in others],
                  f"single-frame models, d >= 2 minus d = 1; 'much worse' = by more than {MUCH_WORSE_MARGIN_DB:g} dB",
                  threshold=MUCH_WORSE_MARGIN_DB)


def decide_c33(res: Results) -> Decision:
    return _pairs(res, [(variant_row(res, "ours"), variant_row(res, "ours-single"), "trmae", "lower",
                         "AFN full and ours-single")], "TRMAE (Eq. 16) of the full temporal model minus the single-frame model's")


def decide_c34(res: Results) -> Decision:
    return _pairs(res, [(variant_row(res, "ours"), variant_row(res, "ours-heur"), "video_psnr", "higher",
                         "AFN full and ours-heur (net.fixed_lambda 0.8)")], "video PSNR (Eq. 14), Table 3")


def decide_c35(res: Results) -> Decision:
    """The full model run at its trained size and at other kernel sizes (rows with params.kernel_size):
    (a) the largest size beats the smallest at the lowest claim spp; (b) that gain is larger at the lowest
    claim spp than at the highest (paired per scene)."""
    full = variant_row(res, "ours")
    if full is None:
        return not_run("missing rows: AFN full model")
    trained = int(row_net(res, full)["kernel_size"])
    sized = {trained: full}
    for row, (name, net) in afn_rows(res, test_time_size=True).items():
        if name == "ours" and net == row_net(res, full):
            sized.setdefault(int(res.spec(row).params["kernel_size"]), row)
    if len(sized) < 2:
        return not_run("missing rows: the full AFN model at another kernel size (params.kernel_size)")
    small, large = sized[min(sized)], sized[max(sized)]
    spps = claim_spps(res, [small, large])
    if not spps:
        return not_run(f"the kernel-size rows ran at none of {list(CLAIM_SPP)} spp")
    low, high = spps[0], spps[-1]
    parts = [compare_rows(res, large, small, "psnr", low, "higher")]
    note = f"kernel sizes {min(sized)} and {max(sized)} of a model trained at {trained}"
    if high != low:
        parts.append(kernel_gain_part(res, large, small, low, high))
    else:
        note += "; only one claim spp ran, so part (b) (larger gain at low spp) is not decided"
    return Decision(parts, note=note)


def kernel_gain_part(res: Results, large: str, small: str, low: int, high: int, at_half_budget: bool = False) -> Part:
    """Part 'the larger kernel's PSNR gain over the smaller is larger at ``low`` than at ``high`` spp', seed-averaged,
    with its half-budget comparison when both rows have one."""
    seed_gain = {s: seed_differences(res.scene_values_per_seed(large, s, "psnr"),
                                     res.scene_values_per_seed(small, s, "psnr")) for s in (low, high)}
    rows = ((large, low), (small, low), (large, high), (small, high))
    part = Part.paired(seed_mean(seed_gain[low]), seed_mean(seed_gain[high]), "psnr", f"gain @ {low} spp",
                       f"gain @ {high} spp", "higher", rows=rows, a_seeds=seed_gain[low], b_seeds=seed_gain[high],
                       seeds=seeds_of(res, rows))
    part.at_half_budget = at_half_budget
    halves = {row: {res.half_row(row, s) for s in (low, high)} for row in (large, small)}
    if not at_half_budget and part.seeds and all(len(h) == 1 and None not in h for h in halves.values()):
        part.half = kernel_gain_part(res, *(next(iter(halves[row])) for row in (large, small)), low, high,
                                     at_half_budget=True)
    return part


CLAIMS = (
    Claim("C3.1", PAPER, "ours-single beats ours-K1 and KPCN at 2-8 spp", (AFN, KPCN), decide_c31),
    Claim("C3.2", PAPER, "affinity dimension d=1 is much worse than d>=2", (AFN,), decide_c32),
    Claim("C3.3", PAPER, "the temporal model has lower TRMAE than the single-frame model", (AFN,), decide_c33),
    Claim("C3.4", PAPER, "the learned temporal weight beats a fixed 0.8", (AFN,), decide_c34),
    Claim("C3.5", PAPER, "kernel size can change at test time; larger kernels help more at low spp", (AFN,),
          decide_c35),
)


# ------------------------------------------------------------------------------------------ tables
def _cell(res: Results, row: str, spp: int, metric: str) -> str:
    if not res.ran(row, spp):
        return "not run"
    return fmt_ci(*mean_ci(res.scene_values(row, spp, metric).to_numpy(float))[:3], metric)


#: {(metric, spp): published value} per line label: the paper's number shown beside ours.
PaperBeside = Mapping[str, Mapping[tuple[str, int], float]]


def _layout(res: Results, rows: list[tuple[str, str]], metrics: tuple[str, ...],
            beside: PaperBeside | None = None) -> pd.DataFrame:
    """One line per (label, row id), columns (metric, spp) 'mean ± CI' over scenes, spp = evaluation.spp; a
    ``paper`` column beside each of ours where the paper has a number for some line at that metric and spp."""
    import pandas as pd

    beside = beside or {}
    lines = []
    for label, row in rows:
        line: dict[str, Any] = {"method": label, "row": row}
        for metric in metrics:
            for spp in res.cfg["evaluation"]["spp"]:
                line[f"{LABELS[metric]} @ {spp} spp"] = _cell(res, row, spp, metric)
                if any((metric, spp) in values for values in beside.values()):
                    line[f"paper @ {spp} spp" if len(metrics) == 1 else f"paper {LABELS[metric]} @ {spp} spp"] = \
                        (beside.get(label) or {}).get((metric, spp))
        lines.append(line)
    return pd.DataFrame(lines)


def _paper_table(values: dict[str, tuple[float, ...]], columns: list[str]) -> pd.DataFrame:
    import pandas as pd

    return pd.DataFrame([{"method": name, **dict(zip(columns, row))} for name, row in values.items()])


def _baselines(res: Results) -> list[tuple[str, str]]:
    return [(label, row) for label, row in (("KPCN", res.row_of("kpcn")), ("OIDN", res.row_of("oidn"))) if row]


def _variant_lines(res: Results, names: tuple[str, ...]) -> list[tuple[str, str]]:
    rows = afn_rows(res)
    return [(name, row) for name in names for row, (variant, _) in rows.items() if variant == name]


def _kernel_lines(res: Results) -> tuple[list[tuple[str, str]], dict[str, tuple[str, int, int]]]:
    """Table 5 lines: the single-frame affinity models (ours-single, ours-K1) at their trained size and at the
    sizes their test-time rows run (params.kernel_size), and the gather models; with each line's paper key
    (kind, K, size)."""
    lines, keys = [], {}
    candidates = [(row, name, net, int(net["kernel_size"]), False) for row, (name, net) in afn_rows(res).items()]
    candidates += [(row, name, net, int(res.spec(row).params["kernel_size"]), True)
                   for row, (name, net) in afn_rows(res, test_time_size=True).items()]
    for row, name, net, size, test_time in candidates:
        if net["temporal"] or name not in ("ours-single", "ours-K1", "gather K1", "gather K3"):
            continue
        kind = "gather" if net["kernel_kind"] == "gather" else "affinity"
        label = f"{kind} K={net['kernels']}, {size}x{size}"
        if test_time:
            label += f" (trained {net['kernel_size']}x{net['kernel_size']})"
        lines.append((label, row))
        keys[label] = (kind, int(net["kernels"]), size)
    lines.sort(key=lambda line: (keys[line[0]][0], keys[line[0]][1], keys[line[0]][2], line[0]))
    return lines, keys


def tables(res: Results) -> dict[str, pd.DataFrame]:
    """Tables 2-5 (module docstring) with the paper's numbers beside ours; each lists only rows that ran."""
    rows = afn_rows(res)
    nets = {row: net for row, (_, net) in rows.items()}
    d_lines = sorted(((f"d={net['affinity_dim']}", row) for row, (name, net) in rows.items()
                      if name in ("ours-single", "d=1", "d=2", "d=4")), key=lambda x: nets[x[1]]["affinity_dim"])
    kernel_lines, kernel_keys = _kernel_lines(res)
    single = ("psnr",)
    beside2 = {label: paper.paper_values(v, paper.TABLE2_SPP, single) for label, v in paper.TABLE2_BESIDE.items()}
    beside3 = {label: paper.paper_values(v, paper.TABLE3_SPP, ("video_psnr", "trmae"))
               for label, v in paper.TABLE3_BESIDE.items()}
    beside4 = {f"d={d}": paper.paper_values(v, paper.TABLE2_SPP, single) for d, v in paper.TABLE4.items()}
    beside5 = {label: paper.paper_values(paper.TABLE5[key], paper.TABLE3_SPP, single)
               for label, key in kernel_keys.items() if key in paper.TABLE5}
    return {
        "isik_table2": _layout(res, _baselines(res) + _variant_lines(res, ("d=1", "ours-K1", "ours-single")), single,
                               beside2),
        "isik_table3": _layout(res, [(label, row) for label, row in _baselines(res) if label == "OIDN"]
                               + _variant_lines(res, ("ours-K1", "ours-single", "ours-wpred", "ours-heur", "ours-ntk",
                                                      "ours-nar", "ours")), ("video_psnr", "trmae"), beside3),
        "isik_table4": _layout(res, d_lines, single, beside4),
        "isik_table5": _layout(res, kernel_lines, single, beside5),
    }


def table_names(cfg: dict) -> list[str]:
    return list(TABLES) if any(m["method"] == "afn" for m in cfg["evaluation"]["methods"]) else []


def figure_names(cfg: dict) -> list[str]:
    return [FIG8, FIG5] if table_names(cfg) else []


def write(res: Results, tables_dir: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table
    from denoisers.reproductions._isik2021_figures import plot_fig8, plot_lambda_maps

    if not table_names(res.cfg):
        return "No `afn` rows are configured (evaluation.methods): the AFN tables are not built."
    built = tables(res)
    paper2 = _paper_table(paper.TABLE2, [f"PSNR @ {s} spp" for s in paper.TABLE2_SPP])
    paper3 = _paper_table(paper.TABLE3, [f"PSNR @ {s} spp" for s in paper.TABLE3_SPP]
                          + [f"TRMAE @ {s} spp" for s in paper.TABLE3_SPP])
    context = {"isik_table2": "\nPaper, every row (Table 2, single frame, 1080p; for context only):\n\n"
                              + frame_to_markdown(paper2),
               "isik_table3": "\nPaper, every row (Table 3, video; for context only):\n\n" + frame_to_markdown(paper3),
               "isik_table5": "\nThe paper's affinity lines are one model per K run at every size at test time; its "
                              "gather lines are one model per size."}
    titles = {"isik_table2": "Table 2 layout: single-frame PSNR (frame mean)",
              "isik_table3": "Table 3 layout: video PSNR (Eq. 14) and TRMAE (Eq. 16)",
              "isik_table4": "Table 4 layout: affinity feature dimension d (single-frame models)",
              "isik_table5": "Table 5 layout: affinity versus gather kernels (single-frame models)"}
    lines = ["AFN rows are identified by their model's net settings (module denoisers.reproductions.isik2021); "
             "mean ± 95 % CI over the evaluated scenes. " + paper.BESIDE_NOTE]
    for name, table in built.items():
        markdown = frame_to_markdown(table) if len(table) else "No row of this layout ran.\n"
        markdown += context.get(name, "")
        write_table(table, tables_dir, name, markdown)
        lines += ["", f"### {titles[name]}", "", markdown]
    reason = plot_fig8(res, figures / f"{FIG8}.png")
    lines += ["", "### Fig. 8 layout: PSNR against throughput", "",
              f"![PSNR against Mpix/s](figures/{FIG8}.png)" if not reason else f"Not drawn: {reason}."]
    full = variant_row(res, "ours")
    spp = next((s for s in (4, 2, 8) if full and res.ran(full, s)), None)
    reason = plot_lambda_maps(res, figures / f"{FIG5}.png", full, spp)
    lines += ["", "### Fig. 5 layout: temporal accumulation weight lambda", "",
              f"![lambda maps](figures/{FIG5}.png)" if not reason else f"Not drawn: {reason}."]
    return "\n".join(lines)


REPRODUCTION = Reproduction(
    key="isik2021", paper="Isik et al. 2021", order=3,
    title="Interactive Monte Carlo denoising using affinity of neural features",
    source="isik2021-affinity-of-neural-features.md", claims=CLAIMS,
    tables=table_names, figures=figure_names, write=write)
