"""Hasselgren et al. 2020, neural temporal adaptive sampling and denoising (NTASD): claims C2.1-C2.5
(../shared/papers/hasselgren2020-neural-temporal-adaptive-sampling.md).

The method and its variants are not built yet: every claim is 'not run', naming the missing rows.
Table 1 and Fig. 7 join this module with the method.
"""
from __future__ import annotations

from denoisers.report.claims import Claim, RowNeed
from denoisers.reproductions.base import Reproduction

PAPER = "Hasselgren 2020"
TEMPORAL_ADAPTIVE = RowNeed("ntasd", "NTASD temporal adaptive (sample-map network + recurrent KPN)")
TEMPORAL_UNIFORM = RowNeed("ntasd", "NTASD temporal, uniform sampling", (("sampling", "uniform"),))
KPN = RowNeed("ntasd", "per-frame KPN (no recurrence)", (("variant", "kpn"),))
DIRECT = RowNeed("ntasd", "direct prediction (no kernels)", (("variant", "direct"),))
DASR = RowNeed("dasr", "DASR (adaptive sampling of Kuznetsov et al. 2018)")
RAE = RowNeed("rae", "RAE carrying its recurrent state", (("reset_state_every_frame", None),))
SVGF = RowNeed("svgf", "SVGF")
CLAIMS = (
    Claim("C2.1", PAPER, "kernel prediction beats direct prediction (PSNR)", (KPN, DIRECT)),
    Claim("C2.2", PAPER, "warped temporal recurrence improves PSNR and tPSNR over per-frame KPN",
          (TEMPORAL_UNIFORM, KPN)),
    Claim("C2.3", PAPER, "adaptive sampling at 4 spp on average beats uniform 4 spp", (TEMPORAL_ADAPTIVE,
                                                                                       TEMPORAL_UNIFORM)),
    Claim("C2.4", PAPER, "rMSE order: adaptive < uniform < DASR < direct prediction",
          (TEMPORAL_ADAPTIVE, TEMPORAL_UNIFORM, DASR, DIRECT)),
    Claim("C2.5", PAPER, "at 4 spp NTASD beats RAE and SVGF in PSNR and is more stable than RAE",
          (TEMPORAL_ADAPTIVE, RAE, SVGF)),
)

REPRODUCTION = Reproduction(
    key="hasselgren2020", paper="Hasselgren et al. 2020", order=2,
    title="Neural temporal adaptive sampling and denoising", source="hasselgren2020-neural-temporal-adaptive-sampling.md",
    claims=CLAIMS)
