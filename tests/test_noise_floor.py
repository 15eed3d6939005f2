"""The reference noise floor per evaluated scene and the headroom check (issue 46 §3).

The floor is psnr(half0, half1) + 10 log10(4): with independent halves of variance v each, MSE(h0, h1) = 2v
and the reference (h0 + h1) / 2 has MSE v / 2 against the truth, a quarter. Checked here on simulated halves
against the truth the simulation knows; then the table's headroom against the best method and its flag.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from denoisers.report.tables import floor_headroom_text, min_floor_headroom, noise_floor_table


def psnr(a: np.ndarray, b: np.ndarray, peak: float = 1.0) -> float:
    return 10 * math.log10(peak ** 2 / float(np.mean((a - b) ** 2)))


def test_the_floor_is_the_references_own_psnr_against_the_truth() -> None:
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.2, 0.8, (256, 256, 3))
    half0, half1 = (truth + rng.normal(0.0, 0.01, truth.shape) for _ in range(2))
    floor = psnr(half0, half1) + 10 * math.log10(4.0)
    assert floor == pytest.approx(psnr((half0 + half1) / 2, truth), abs=0.05)


def results(halves: dict[str, float], best: dict[str, float], headroom_db: float | None = None) -> SimpleNamespace:
    """Results-like: per-frame reference_psnr_halves per scene; at 4 spp one method scoring ``best`` and a worse one."""
    evaluation = {"spp": [1, 4]} if headroom_db is None else {"spp": [1, 4], "min_floor_headroom_db": headroom_db}
    frames = pd.DataFrame([{"scene": s, "frame": f, "reference_psnr_halves": v + (0.5 if f else -0.5)}
                           for s, v in halves.items() for f in (0, 1)])
    per_scene = pd.DataFrame([{"scene": s, "spp": 4, "method_id": m, "psnr": v + shift}
                              for s, v in best.items() for m, shift in (("good", 0.0), ("worse", -3.0))]
                             + [{"scene": s, "spp": 1, "method_id": "good", "psnr": 99.0} for s in best])
    return SimpleNamespace(cfg={"evaluation": evaluation}, scenes=list(halves), frames=frames, per_scene=per_scene,
                           main_specs=[SimpleNamespace(id="good"), SimpleNamespace(id="worse")])


def test_headroom_is_floor_minus_the_best_method_at_the_top_spp_and_is_flagged_below_the_margin() -> None:
    res = results({"test_000": 40.0, "test_001": 30.0}, {"test_000": 30.0, "test_001": 27.0})
    table = noise_floor_table(res).set_index("scene")
    floor = {"test_000": 40.0 + 10 * math.log10(4.0), "test_001": 30.0 + 10 * math.log10(4.0)}
    assert table.reference_noise_floor_psnr.to_dict() == pytest.approx(floor)
    assert table.best_method.tolist() == ["good", "good"] and table.spp.tolist() == [4, 4]
    assert table.headroom_db.to_dict() == pytest.approx({"test_000": floor["test_000"] - 30.0,
                                                         "test_001": floor["test_001"] - 27.0})
    assert min_floor_headroom(res.cfg) == 10.0                    # the schema default
    assert table.headroom_ok.tolist() == [True, False]            # 16.02 and 9.02 dB
    text = floor_headroom_text(res.cfg, noise_floor_table(res))
    assert "test_001 (9.02 dB)" in text and "test_000" not in text and "render.test_reference_spp" in text
    # A smaller stated margin passes both.
    loose = results({"test_000": 40.0, "test_001": 30.0}, {"test_000": 30.0, "test_001": 27.0}, headroom_db=9.0)
    assert noise_floor_table(loose).headroom_ok.all()
    assert floor_headroom_text(loose.cfg, noise_floor_table(loose)).startswith(
        "Every scene's reference noise floor is at least 9 dB above its best method")
