"""Published numbers of Isik et al. 2021 (../shared/papers/isik2021-affinity-of-neural-features.md), Tables 2-5,
and which of them stands beside which row of ours (denoisers.reproductions.isik2021).

1080p test scenes of the paper, other than ours: for context, never compared statistically.
"""
from __future__ import annotations

#: Table 2 (single frame): PSNR (dB) at TABLE2_SPP.
TABLE2_SPP = (2, 4, 8, 16, 32)
TABLE2 = {"KPCN": (27.95, 30.86, 32.79, 33.90, 34.54), "SBMC": (28.97, 32.33, 33.97, 34.57, 34.44),
          "NDLE": (30.08, 32.20, 33.63, 34.45, 34.73), "NDLE-ms": (29.47, 31.81, 33.14, 33.87, 34.12),
          "ONND": (29.40, 30.62, 31.79, 32.88, 33.91), "NBG*": (26.04, 27.58, 28.52, 29.11, 29.42),
          "NBG-large*": (28.58, 30.09, 31.20, 31.94, 32.58), "ours-K1": (29.13, 31.87, 33.28, 34.11, 34.42),
          "ours-single": (30.93, 32.67, 33.66, 34.34, 34.81)}
#: Table 3 (video): video PSNR (dB, Eq. 14) at TABLE3_SPP, then TRMAE (Eq. 16) at TABLE3_SPP.
TABLE3_SPP = (2, 4, 8)
TABLE3 = {"NDLE*": (30.98, 33.05, 34.37, 0.764, 0.618, 0.571), "NDLE-ms*": (31.02, 32.91, 33.96, 0.806, 0.662, 0.595),
          "ONND*": (30.66, 31.74, 32.74, 1.988, 1.693, 1.468), "NBG": (26.67, 28.48, 29.56, 2.058, 1.695, 1.453),
          "NBG-large": (29.31, 30.67, 31.60, 1.069, 1.001, 0.906),
          "ours-K1*": (30.48, 32.64, 33.97, 0.803, 0.650, 0.565),
          "ours-single*": (32.17, 33.67, 34.54, 0.640, 0.556, 0.511),
          "ours-wpred": (32.18, 33.48, 34.33, 0.513, 0.482, 0.462),
          "ours-heur": (32.05, 32.89, 33.33, 0.511, 0.485, 0.472),
          "ours-ntk": (32.55, 33.79, 34.44, 0.502, 0.474, 0.457),
          "ours-nar": (32.37, 33.76, 34.56, 0.508, 0.473, 0.454),
          "ours": (32.34, 33.93, 34.81, 0.517, 0.467, 0.446)}
#: Table 4 (ours-single, static images): PSNR (dB) per affinity dimension d at TABLE2_SPP.
TABLE4 = {1: (26.65, 27.77, 28.25, 28.44, 28.55), 2: (30.23, 31.98, 32.97, 33.61, 34.04),
          4: (30.73, 32.43, 33.40, 34.06, 34.53), 8: (30.93, 32.68, 33.67, 34.34, 34.81),
          12: (30.97, 32.62, 33.64, 34.35, 34.86), 16: (30.11, 32.63, 33.76, 34.44, 34.81)}
#: Table 5 (static images): PSNR (dB) at TABLE3_SPP per (kernel kind, K, kernel size). The affinity side is one
#: model per K run at each size at test time (its K = 3 column at 13 x 13 is ours-single of Table 2, its K = 1
#: column at 17 x 17 is ours-K1); the gather side is one model per size.
_K1_SIZES, _K3_SIZES = (9, 11, 13, 15, 17, 19, 21, 23), (5, 7, 9, 11, 13)
_TABLE5_ROWS = {  # (kind, K) -> per spp (2, 4, 8): PSNR per size
    ("affinity", 1): ((27.58, 28.19, 28.61, 28.91, 29.13, 29.28, 29.38, 29.44),
                      (30.39, 31.00, 31.40, 31.67, 31.87, 32.00, 32.07, 32.10),
                      (32.15, 32.63, 32.94, 33.14, 33.28, 33.36, 33.40, 33.41)),
    ("gather", 1): ((30.11, 29.13, 30.43, 30.25, 29.18, 30.40, 29.02, 30.26),
                    (32.03, 31.94, 32.29, 32.31, 31.98, 32.39, 32.11, 32.37),
                    (33.14, 33.31, 33.34, 33.42, 33.30, 33.43, 33.50, 33.38)),
    ("affinity", 3): ((29.43, 30.19, 30.57, 30.79, 30.93), (31.68, 32.26, 32.50, 32.62, 32.67),
                      (33.10, 33.49, 33.63, 33.67, 33.66)),
    ("gather", 3): ((30.23, 30.61, 30.98, 30.69, 30.82), (32.29, 32.35, 32.51, 32.44, 32.50),
                    (33.35, 33.36, 33.41, 33.34, 33.44)),
}
TABLE5: dict[tuple[str, int, int], tuple[float, ...]] = {
    (kind, k, size): tuple(per_spp[i] for per_spp in values)
    for (kind, k), values in _TABLE5_ROWS.items() for i, size in enumerate(_K1_SIZES if k == 1 else _K3_SIZES)}

#: Our Table 2 / 3 line labels -> the paper's row beside them (OIDN stands in for the OptiX denoiser, ONND;
#: d = 1 stands in for the NBG-like variant and takes Table 4's d = 1).
TABLE2_BESIDE = {"KPCN": TABLE2["KPCN"], "OIDN": TABLE2["ONND"], "ours-K1": TABLE2["ours-K1"],
                 "ours-single": TABLE2["ours-single"], "d=1": TABLE4[1]}
TABLE3_BESIDE = {"OIDN": TABLE3["ONND*"], "ours-K1": TABLE3["ours-K1*"], "ours-single": TABLE3["ours-single*"],
                 **{name: TABLE3[name] for name in ("ours-wpred", "ours-heur", "ours-ntk", "ours-nar", "ours")}}
BESIDE_NOTE = ("`paper` columns: the paper's number for that row at that spp (1080p scenes of the paper, not ours; "
               "for context only): OIDN beside the OptiX denoiser (ONND), d=1 beside Table 4's d = 1.")


def paper_values(values: tuple[float, ...], spps: tuple[int, ...], metrics: tuple[str, ...]) -> dict[tuple[str, int], float]:
    """{(metric, spp): value} of one paper row laid out as metrics x spps (metric-major, as Table 3)."""
    return {(metric, spp): values[i * len(spps) + j] for i, metric in enumerate(metrics) for j, spp in enumerate(spps)}
