"""The statistics behind a claim's verdict beyond one part's interval: Holm's correction over a claim's parts,
the number of scenes an inconclusive part would need, and means over the joined scenes.

References are hand computations (stated in the comments) and scipy's one-sample t-test, not the code under test.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from denoisers.report.verdicts import (CONTRADICTED, INCONCLUSIVE, REPRODUCED, Decision, Part, holm_rejected,
                                       scenes_needed)


def part(diffs: list[float], claimed: str = "higher") -> Part:
    values = np.asarray(diffs, np.float64)
    return Part("psnr", "a", "b", claimed, values, [f"s{k}" for k in range(len(values))], 0.0, 0.0)


def test_holm_against_a_hand_computed_case() -> None:
    # m = 4 at 0.025: sorted p 0.001 <= 0.025/4 = 0.00625 rejected; 0.02 > 0.025/3 = 0.00833 stops.
    assert holm_rejected([0.03, 0.001, 0.5, 0.02]) == [False, True, False, False]
    # m = 2: 0.004 <= 0.0125, then 0.01 <= 0.025: both rejected.
    assert holm_rejected([0.01, 0.004]) == [True, True]
    # A NaN (too few units) is never rejected and stops nothing before it.
    assert holm_rejected([0.001, float("nan")]) == [True, False]
    assert holm_rejected([]) == []


def test_p_value_is_scipys_one_sided_t_test() -> None:
    diffs = [-1.0, -0.4, -1.6, -0.7, -1.3]
    assert part(diffs).p_other_side == pytest.approx(stats.ttest_1samp(diffs, 0.0, alternative="less").pvalue)
    assert part(diffs, "lower").p_other_side == pytest.approx(
        stats.ttest_1samp(diffs, 0.0, alternative="greater").pvalue)


def test_a_part_on_the_other_side_contradicts_alone_but_not_among_many() -> None:
    """One part whose interval lies wholly below 0 with p about 0.01: alone it contradicts the claim; among six
    parts it does not survive Holm (0.01 > 0.025 / 6), so the claim is inconclusive and the note says why."""
    against = [-1.0, -0.4, -1.6, -0.7, -1.3]
    p = stats.ttest_1samp(against, 0.0, alternative="less").pvalue
    assert 0.025 / 6 < p < 0.025
    assert part(against).outcome == CONTRADICTED
    assert Decision(parts=[part(against)]).verdict == CONTRADICTED
    spanning = [1.5, -1.0, 0.8, -0.2, 0.3]
    many = Decision(parts=[part(against)] + [part(spanning) for _ in range(5)])
    assert many.verdict == INCONCLUSIVE
    assert many.contradicting_parts == [False] * 6
    assert "do not survive Holm's correction over 6 parts" in many.holm_note()
    # A part far on the other side survives the correction: the claim is contradicted.
    far = [-3.0, -3.1, -2.9, -3.05, -2.95]
    assert Decision(parts=[part(far)] + [part(spanning) for _ in range(5)]).verdict == CONTRADICTED
    # Reproduced needs every part (no correction: an intersection-union test).
    clear = [1.0, 1.2, 0.9, 1.1, 1.05]
    assert Decision(parts=[part(clear)] * 6).verdict == REPRODUCED


def test_scenes_needed_against_a_hand_computation() -> None:
    # Mean 0.5, sd 1: n = 17 gives t(0.975, 16) / sqrt(17) = 2.120 / 4.123 = 0.514 > 0.5; n = 18 gives
    # 2.110 / 4.243 = 0.497 < 0.5.
    assert scenes_needed([-0.5, 0.5, 1.5]) == 18
    assert scenes_needed([0.5, -0.5, 1.5]) == 18          # order does not matter
    assert scenes_needed([-1.5, -0.5, 0.5]) == 18         # the sign neither
    assert scenes_needed([1.0, 1.0]) == 2                 # no spread: any interval excludes 0
    assert scenes_needed([1.0, -1.0]) is None             # no effect: never
    assert scenes_needed([2.0]) is None                   # no spread estimate


def test_means_are_over_the_joined_scenes() -> None:
    a = pd.Series([10.0, 12.0, 50.0], index=["s0", "s1", "s2"])
    b = pd.Series([9.0, 11.0], index=["s0", "s1"])
    joined = Part.paired(a, b, "psnr", "a", "b")
    assert joined.n == 2 and joined.mean_a == pytest.approx(11.0) and joined.mean_b == pytest.approx(10.0)


def test_a_stated_margin_moves_the_bound() -> None:
    """"Much worse" (C3.2, MUCH_WORSE_MARGIN_DB): a - b > 0.5 dB. Worse by about 0.3 dB is not much worse
    (contradicted); by about 0.8 dB it is. The p-value is scipy's t-test against 0.5."""
    from denoisers.report.stats import MUCH_WORSE_MARGIN_DB

    assert MUCH_WORSE_MARGIN_DB == 0.5
    mild, clear = [0.3, 0.25, 0.35, 0.28, 0.32], [0.8, 0.75, 0.85, 0.78, 0.82]
    for diffs, expected in ((mild, CONTRADICTED), (clear, REPRODUCED)):
        shifted = Part("psnr", "a", "b", "higher", np.asarray(diffs), ["s"] * 5, 0.0, 0.0, threshold=0.5)
        assert shifted.outcome == expected
        assert shifted.p_other_side == pytest.approx(stats.ttest_1samp(diffs, 0.5, alternative="less").pvalue)
        assert "> 0.50" in shifted.claim_text()
    assert part(mild).outcome == REPRODUCED      # without the margin: merely worse


def test_steady_frames_leave_out_each_shots_warm_up() -> None:
    """Frames 0-7 with a cut at 4 and warm-up 2: frames 0, 1 (clip start) and 4, 5 (after the cut) are left out."""
    from denoisers.report.collect import steady_frames

    frames = pd.DataFrame({"method_id": ["a"] * 8 + ["b"] * 3, "spp": [1] * 11, "scene": ["s"] * 11,
                           "frame": [*range(8), 0, 1, 2], "camera_cut": [False] * 4 + [True] + [False] * 6})
    assert steady_frames(frames, 2).tolist() == [False, False, True, True, False, False, True, True,
                                                 False, False, True]
    assert steady_frames(frames, 0).all()


def test_claims_decide_on_steady_frames_and_pool_video_psnr_over_them() -> None:
    """A temporal row bad in its two warm-up frames only: the claim values are the steady frames' means (by
    hand), the report's scene_values keep every frame."""
    from denoisers.report.collect import Results
    from denoisers.report.stats import pooled_psnr

    psnr = [20.0, 25.0, 30.0, 31.0, 32.0, 33.0]
    frames = pd.DataFrame({"method_id": "t", "spp": 1, "scene": "s0", "frame": range(6), "camera_cut": False,
                           "psnr": psnr})
    per_scene = pd.DataFrame({"method_id": ["t"], "spp": [1], "scene": ["s0"], "psnr": [np.mean(psnr)]})
    res = Results({"evaluation": {"warmup_frames": 2}, "output_dir": "."}, [], ["s0"], [], frames, per_scene)
    assert res.claim_values("t", 1, "psnr")["s0"] == pytest.approx(31.5)
    assert res.scene_values("t", 1, "psnr")["s0"] == pytest.approx(np.mean(psnr))
    assert res.claim_values("t", 1, "video_psnr")["s0"] == pytest.approx(pooled_psnr(psnr[2:]))
