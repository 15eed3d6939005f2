"""Iglesias-Guitian et al. 2022, wRLS for volumetric path tracing: PSNR / TRMAE / FLIP of the MC input,
RAE, SVGF and wRLS at the paper's 2 spp, and claims C4.1-C4.4
(../shared/papers/iglesias-guitian2022-wrls-volumetric.txt).

The paper's scenes are volumetric; until volumes are rendered, the evaluated scenes are surfaces and
every claim says so. FLIP stands in for LPIPS (no network weights can be downloaded here).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.report.claims import Claim, Decision, Fact, Part, RowNeed, compare_rows, compare_speed, not_run, spp_available
from denoisers.report.stats import LABELS, fmt_ci, frame_to_markdown, mean_ci
from denoisers.reproductions.base import Reproduction

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

PAPER = "Iglesias-Guitian 2022"
PAPER_SPP = 2
SURFACES = "our evaluated scenes are surfaces, not volumes (the paper's setting)"
WRLS, RLS, SVGF, NOISY = (RowNeed("wrls", "wRLS"), RowNeed("rls", "RLS"), RowNeed("svgf", "SVGF"),
                          RowNeed("noisy", "noisy input"))
RAE = RowNeed("rae", "RAE carrying its recurrent state", (("reset_state_every_frame", None),))
TABLE_METHODS = ("noisy", "rae", "svgf", "wrls", "rls")
#: PSNR (dB) printed under the MANIX frames of the paper's Figs. 10-12 (one per scenario, 2 spp, 720p):
#: MC input, RAE, SVGF, wRLS.
PAPER_MANIX_PSNR = {"camera animation (Fig. 10)": (29.22, 35.96, 35.22, 35.62),
                    "moving light (Fig. 11)": (28.15, 35.86, 33.45, 33.54),
                    "transfer-function edit (Fig. 12)": (28.60, 36.19, 35.34, 36.23)}


def _row(res: Results, need: RowNeed) -> str | None:
    return res.row_of(need.method, **dict(need.params))


def decide_c41(res: Results) -> Decision:
    wrls, svgf = _row(res, WRLS), _row(res, SVGF)
    missing = spp_available(res, PAPER_SPP, [wrls, svgf])
    if missing:
        return not_run(missing)
    return Decision([compare_rows(res, wrls, svgf, "psnr", PAPER_SPP, "higher"),
                     compare_rows(res, wrls, svgf, "trmae", PAPER_SPP, "lower")], note=f"{PAPER_SPP} spp; {SURFACES}")


def decide_c42(res: Results) -> Decision:
    wrls, rls = _row(res, WRLS), _row(res, RLS)
    if res.robustness is None:
        return not_run("robustness scenario disabled (evaluation.robustness.enabled)")
    spp = res.cfg["evaluation"]["robustness"]["spp"]
    have = set(res.robustness.method_id)
    if wrls not in have or rls not in have:
        return not_run("no robustness results for wrls or rls")
    missing = spp_available(res, spp, [wrls, rls])
    if missing:
        return not_run(missing)
    spiked = {m: res.robustness[res.robustness.method_id == m].set_index("scene")["psnr_spiked"] for m in (wrls, rls)}
    drop = {m: res.scene_values(m, spp, "psnr") - spiked[m] for m in (wrls, rls)}
    return Decision([Part.paired(spiked[wrls], spiked[rls], "psnr", f"{wrls} spiked @ {spp} spp",
                                 f"{rls} spiked @ {spp} spp", "higher", rows=((wrls, spp), (rls, spp))),
                     Part.paired(drop[wrls], drop[rls], "psnr_drop", f"{wrls} drop", f"{rls} drop", "lower",
                                 rows=((wrls, spp), (rls, spp)))],
                    note="spikes (up to 500x the frame mean) and NaN/Inf injected into the noisy samples: needs "
                         "higher PSNR and a smaller PSNR drop than RLS")


def decide_c43(res: Results) -> Decision:
    wrls, noisy, rae = _row(res, WRLS), _row(res, NOISY), _row(res, RAE)
    spps = list(res.cfg["evaluation"]["spp"])
    missing = "; ".join(filter(None, (spp_available(res, s, [wrls, noisy, rae]) for s in spps)))
    if missing:
        return not_run(missing)
    if len(spps) < 2:
        return not_run("needs two or more evaluated spp (RAE's gain at the lowest versus the highest)")
    parts = [compare_rows(res, wrls, noisy, "psnr", s, "higher") for s in spps]
    gain = {s: res.scene_values(rae, s, "psnr") - res.scene_values(noisy, s, "psnr") for s in (spps[0], spps[-1])}
    parts.append(Part.paired(gain[spps[-1]], gain[spps[0]], "psnr", f"RAE gain over input @ {spps[-1]} spp",
                             f"RAE gain @ {spps[0]} spp", "lower",
                             rows=((rae, spps[0]), (rae, spps[-1]), (noisy, spps[0]), (noisy, spps[-1]))))
    return Decision(parts, note=f"wRLS above its input at every evaluated spp {spps}, and RAE's PSNR gain smaller "
                                f"at {spps[-1]} than at {spps[0]} spp; {SURFACES}")


def decide_c44(res: Results) -> Decision:
    from denoisers import registry

    wrls, rae = _row(res, WRLS), _row(res, RAE)
    missing = spp_available(res, PAPER_SPP, [wrls, rae])
    if missing:
        return not_run(missing)
    model = res.model_of(rae)
    facts = [Fact("wRLS needs no training", not registry.get("wrls").info.trainable),
             Fact("RAE is trained", registry.get("rae").info.trainable)]
    speed = compare_speed(res, wrls, rae, PAPER_SPP, "lower")
    if isinstance(speed, str):
        return not_run(speed)
    return Decision([speed], facts,
                    note=f"time per frame from the timing job ({res.timing.threads} thread(s), one scene, interleaved "
                         f"rounds); RAE {model.describe() if model else rae}")


CLAIMS = (
    Claim("C4.1", PAPER, "wRLS beats SVGF in PSNR and flickers less (TRMAE)", (WRLS, SVGF), decide_c41),
    Claim("C4.2", PAPER, "wRLS is more robust to spike noise than plain RLS", (WRLS, RLS), decide_c42),
    Claim("C4.3", PAPER, "wRLS improves on its input at every spp, while RAE's gain shrinks as spp grows",
          (WRLS, NOISY, RAE), decide_c43),
    Claim("C4.4", PAPER, "wRLS needs no training and runs faster than RAE", (WRLS, RAE), decide_c44),
)


def comparison_table(res: Results) -> pd.DataFrame:
    """Rows: the paper's methods that are configured; columns: PSNR, TRMAE, FLIP per evaluated spp."""
    import pandas as pd

    rows = []
    for spec in res.main_specs:
        if spec.method not in TABLE_METHODS or spec.params.get("reset_state_every_frame"):
            continue
        row: dict[str, Any] = {"method": spec.id}
        for metric in ("psnr", "trmae", "flip"):
            for spp in res.cfg["evaluation"]["spp"]:
                value = fmt_ci(*mean_ci(res.scene_values(spec.id, spp, metric).to_numpy(float))[:3], metric) \
                    if res.ran(spec.id, spp) else "not run"
                row[f"{LABELS[metric]} @ {spp} spp"] = value
        rows.append(row)
    return pd.DataFrame(rows)


def write(res: Results, tables: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table

    import pandas as pd

    table = comparison_table(res)
    paper = pd.DataFrame([{"scenario (MANIX)": name, **dict(zip(("MC input", "RAE", "SVGF", "wRLS"), values))}
                          for name, values in PAPER_MANIX_PSNR.items()])
    markdown = (frame_to_markdown(table) if len(table) else "none of the paper's methods is configured\n") + (
        "\nPaper (PSNR in dB of single MANIX frames in Figs. 10-12, volumes, 2 spp, 720p; for context only):\n\n"
        + frame_to_markdown(paper))
    write_table(table, tables, "iglesias_comparison", markdown)
    return "\n".join([f"MC input, RAE, SVGF, (w)RLS on the evaluated scenes ({SURFACES}; FLIP in place of LPIPS). "
                      "The paper evaluates at 2 spp.", "", markdown])


REPRODUCTION = Reproduction(
    key="iglesias2022", paper="Iglesias-Guitian et al. 2022", order=4,
    title="Real-time denoising of volumetric path tracing for direct volume rendering (wRLS)",
    source="iglesias-guitian2022-wrls-volumetric.txt", claims=CLAIMS,
    tables=lambda cfg: ["iglesias_comparison"], write=write)
