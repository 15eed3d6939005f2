"""Isik et al. 2021, affinity of neural features (AFN): Tables 2 and 3 laid out like the paper, with video
PSNR as the paper's Eq. 14 (MSE pooled over a clip's frames), and claims C3.1-C3.5
(../shared/papers/isik2021-affinity-of-neural-features.md).

The AFN and KPCN methods are not built yet: their claims are 'not run', naming the missing rows.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.report.claims import Claim, RowNeed
from denoisers.report.stats import LABELS, fmt_ci, frame_to_markdown, mean_ci
from denoisers.reproductions.base import Reproduction

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.report.collect import Results

PAPER = "Isik 2021"
AFN = RowNeed("afn", "AFN, the full temporal model")
AFN_SINGLE = RowNeed("afn", "AFN ours-single (temporal accumulation and filtering off)", (("variant", "single"),))
AFN_K1 = RowNeed("afn", "AFN ours-K1 (one 17x17 kernel)", (("variant", "k1"),))
AFN_D1 = RowNeed("afn", "AFN with affinity dimension d = 1", (("variant", "d1"),))
AFN_HEUR = RowNeed("afn", "AFN ours-heur (fixed temporal weight 0.8)", (("variant", "heur"),))
KPCN = RowNeed("kpcn", "KPCN")
CLAIMS = (
    Claim("C3.1", PAPER, "ours-single beats ours-K1 and KPCN at 2-8 spp", (AFN_SINGLE, AFN_K1, KPCN)),
    Claim("C3.2", PAPER, "affinity dimension d=1 is much worse than d>=2", (AFN, AFN_D1)),
    Claim("C3.3", PAPER, "the temporal model has lower TRMAE than the single-frame model", (AFN, AFN_SINGLE)),
    Claim("C3.4", PAPER, "the learned temporal weight beats a fixed 0.8", (AFN, AFN_HEUR)),
    Claim("C3.5", PAPER, "kernel size can change at test time; larger kernels help more at low spp", (AFN,)),
)
#: Published PSNR (dB) of Table 2 (single frame) at 2/4/8/16/32 spp, rows relevant to our targets.
PAPER_TABLE2 = {"KPCN": (27.95, 30.86, 32.79, 33.90, 34.54), "NBG*": (26.04, 27.58, 28.52, 29.11, 29.42),
                "ours-K1": (29.13, 31.87, 33.28, 34.11, 34.42), "ours-single": (30.93, 32.67, 33.66, 34.34, 34.81)}
PAPER_TABLE2_SPP = (2, 4, 8, 16, 32)
#: Published PSNR (dB) and TRMAE of Table 3 (video) at 2/4/8 spp.
PAPER_TABLE3 = {"NBG": (26.67, 28.48, 29.56, 2.058, 1.695, 1.453),
                "ours-K1*": (30.48, 32.64, 33.97, 0.803, 0.650, 0.565),
                "ours-single*": (32.17, 33.67, 34.54, 0.640, 0.556, 0.511),
                "ours-wpred": (32.18, 33.48, 34.33, 0.513, 0.482, 0.462),
                "ours-heur": (32.05, 32.89, 33.33, 0.511, 0.485, 0.472),
                "ours-ntk": (32.55, 33.79, 34.44, 0.502, 0.474, 0.457),
                "ours-nar": (32.37, 33.76, 34.56, 0.508, 0.473, 0.454),
                "ours": (32.34, 33.93, 34.81, 0.517, 0.467, 0.446)}
PAPER_TABLE3_SPP = (2, 4, 8)


def pivot(res: Results, metrics: tuple[str, ...]) -> pd.DataFrame:
    """Rows = configured methods, columns = (metric, spp) 'mean ± CI' over scenes (Isik's layout)."""
    import pandas as pd

    rows = []
    for spec in res.main_specs:
        row: dict[str, Any] = {"method": spec.id}
        for metric in metrics:
            for spp in res.cfg["evaluation"]["spp"]:
                row[f"{LABELS[metric]} @ {spp} spp"] = fmt_ci(
                    *mean_ci(res.scene_values(spec.id, spp, metric).to_numpy(float))[:3], metric) \
                    if res.ran(spec.id, spp) else "not run"
        rows.append(row)
    return pd.DataFrame(rows)


def _paper_table(values: dict[str, tuple[float, ...]], columns: list[str]) -> pd.DataFrame:
    import pandas as pd

    return pd.DataFrame([{"method": name, **dict(zip(columns, row))} for name, row in values.items()])


def write(res: Results, tables: Path, figures: Path) -> str:
    from denoisers.report.tables import write_table

    note = ("Video PSNR is Isik et al. Eq. 14: the MSE of the tonemapped frames pooled over a clip, then "
            "−10 log10; mean ± 95 % CI over scenes.")
    table2 = pivot(res, ("video_psnr",))
    paper2 = _paper_table(PAPER_TABLE2, [f"PSNR @ {s} spp" for s in PAPER_TABLE2_SPP])
    md2 = (frame_to_markdown(table2) + "\nPaper (Table 2, single frame, 1080p; for context only):\n\n"
           + frame_to_markdown(paper2))
    write_table(table2, tables, "isik_table2", md2)
    table3 = pivot(res, ("video_psnr", "trmae"))
    paper3 = _paper_table(PAPER_TABLE3, [f"PSNR @ {s} spp" for s in PAPER_TABLE3_SPP]
                          + [f"TRMAE @ {s} spp" for s in PAPER_TABLE3_SPP])
    md3 = (frame_to_markdown(table3) + "\nPaper (Table 3, video; for context only):\n\n" + frame_to_markdown(paper3))
    write_table(table3, tables, "isik_table3", md3)
    return "\n".join([note, "", "### Table 2 layout: video PSNR by spp", "", md2,
                      "### Table 3 layout: video PSNR and TRMAE by spp", "", md3])


REPRODUCTION = Reproduction(
    key="isik2021", paper="Isik et al. 2021", order=3,
    title="Interactive Monte Carlo denoising using affinity of neural features",
    source="isik2021-affinity-of-neural-features.md", claims=CLAIMS,
    tables=lambda cfg: ["isik_table2", "isik_table3"], write=write)
