"""Failure metrics of the stability suite (denoisers.stability_metrics) on hand-built arrays with known answers,
and the atlas' sentences and not-run handling (denoisers.report.atlas) on synthetic scores. No rendering."""
from __future__ import annotations

import numpy as np
import pytest

from denoisers import metrics
from denoisers import stability_metrics as sm

T, H, W = 12, 6, 8


def constant(value: float, frames: int = T) -> np.ndarray:
    return np.full((frames, 3, H, W), value, np.float64)


def test_full_masks_reproduce_the_clip_metrics() -> None:
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.1, 2.0, (5, 3, H, W))
    pred = ref * rng.uniform(0.8, 1.2, ref.shape)
    full, history = np.ones((5, H, W), bool), np.array([False, True, True, True, True])
    assert np.allclose(sm.masked_psnr(pred, ref, full), [metrics.psnr(p, r) for p, r in zip(pred, ref)])
    assert np.allclose(sm.masked_tpsnr(pred, ref, full, history)[1:], metrics.tpsnr(pred, ref)[1:])
    assert np.allclose(sm.masked_trmae(pred, ref, full, history)[1:], metrics.trmae(pred, ref)[1:])
    assert np.isnan(sm.masked_trmae(pred, ref, full, history)[0])


def test_masked_psnr_only_sees_the_mask_and_is_nan_when_empty() -> None:
    ref, pred = constant(1.0, 2), constant(1.0, 2)
    pred[:, :, :, :4] = 3.0                       # error only in the left half
    mask = np.zeros((2, H, W), bool)
    mask[0, :, 4:] = True                         # frame 0: right half (no error); frame 1: empty
    values = sm.masked_psnr(pred, ref, mask)
    assert values[0] == np.inf and np.isnan(values[1])
    mask[1, :, :4] = True
    expected = -10 * np.log10((metrics.tonemap(3.0) - metrics.tonemap(1.0)) ** 2)
    assert sm.masked_psnr(pred, ref, mask)[1] == pytest.approx(expected)


def test_steady_state_is_the_median_of_the_control_clips_last_third() -> None:
    control = np.array([9.0, 5.0, 3.0, 2.0, 1.0, 1.2, 0.8, 1.0, 1.1, 0.9, 1.0, 3.0])
    steady, window = sm.steady_state(control)
    assert window == T // 3 == 4 and steady == pytest.approx(np.median(control[-4:]))
    assert sm.steady_state(np.array([np.nan, 2.0]))[0] == 2.0 and np.isnan(sm.steady_state(np.full(3, np.nan))[0])


def test_lagging_ramp_recovers_in_exactly_three_frames() -> None:
    errors = np.array([1.0, 1.0, 1.0, 1.0, 5.0, 4.0, 3.0, 1.05, 1.0, 1.0, 1.0, 1.0])
    record = sm.recovery(errors, event=4, steady=1.0, margin=0.1)
    assert record["steady_state_mse"] == 1.0 and record["frames_to_recover"] == 3
    assert record["recovery"] == "recovered"
    assert record["post_event_mse"] == pytest.approx(errors[4:].mean())
    assert record["ghosting_ratio"] == pytest.approx(errors[4:].mean())
    # A per-frame method whose error equals its failure-free error has no lag.
    assert sm.recovery(np.ones(T), event=4, steady=1.0)["frames_to_recover"] == 0
    # Two frames after the event are too few to tell lag from noise.
    short = sm.recovery(np.array([1.0, 1.0, 5.0, 1.0]), event=2, steady=1.0)
    assert short["recovery"] == "too short" and short["frames_to_recover"] is None
    # A tighter margin moves the recovery later.
    assert sm.recovery(errors, event=4, steady=1.0, margin=0.01)["frames_to_recover"] == 4


def test_a_lag_that_lasts_the_whole_clip_never_recovers() -> None:
    """The defect the control clip fixes: an error that stays high until the clip ends settled at its own level, so
    a steady state taken from the clip's last frames read '0 frames to recover'. Against the failure-free level
    (the control clip's) it is 'never', with a ghosting ratio of 5."""
    errors = np.array([1.0] * 4 + [5.0] * 8)
    record = sm.recovery(errors, event=4, steady=1.0)
    assert record["recovery"] == "never" and record["frames_to_recover"] is None
    assert record["ghosting_ratio"] == pytest.approx(5.0)
    # A clip that only settles in its last frames recovers there (no window is excluded any more).
    late = sm.recovery(np.array([1, 1, 1, 1, 9, 8, 7, 6, 5, 4, 1, 1.0]), event=4, steady=1.0)
    assert late["recovery"] == "recovered" and late["frames_to_recover"] == 6


def test_constant_signed_offset_gives_that_bias() -> None:
    ref = constant(2.0, 3)
    pred = ref - 0.5
    mask = np.zeros((3, H, W), bool)
    mask[:, 2:4, 2:4] = True
    pred[:, :, 0, 0] = 100.0                      # outside the mask: ignored
    absolute, relative = sm.signed_bias(pred, ref, mask)
    assert absolute == pytest.approx(-0.5) and relative == pytest.approx(-0.25)
    assert np.isnan(sm.signed_bias(pred, ref, np.zeros_like(mask))[0])


def test_flicker_of_an_alternating_signal_on_static_pixels() -> None:
    ref = constant(1.0, 6)
    pred = ref.copy()
    pred[1::2] += 0.2                             # 1.0, 1.2, 1.0, 1.2, ...: |dp - dr| = 0.2 every frame
    motion = np.zeros((6, 2, H, W))
    motion[:, 0, :, :2] = 1.5                     # two moving columns are not static
    valid, changed = np.ones((6, H, W), bool), np.zeros((6, H, W), bool)
    changed[3, 0, :] = True                       # a change in frame 3 removes row 0 from frames 3 and 4
    history = sm.history_frames(6, [False] * 6, warmup=1)
    static = sm.static_mask(motion, valid, changed, history)
    assert not static[0].any() and not static[:, :, :2].any()
    assert not static[3, 0].any() and not static[4, 0].any() and static[5, 0, 2:].all()
    flicker = sm.masked_trmae(pred, ref, static, history)
    assert np.isnan(flicker[0]) and np.allclose(flicker[1:], 0.2 / metrics.TRMAE_EPS)
    assert np.allclose(sm.masked_trmae(ref, ref, static, history)[1:], 0.0)


def test_history_restarts_after_a_cut_and_warmup() -> None:
    cuts = [False, False, False, True, False, False]
    assert sm.history_frames(6, cuts, warmup=1).tolist() == [False, True, True, False, True, True]
    assert sm.history_frames(6, cuts, warmup=2).tolist() == [False, False, True, False, False, True]


def test_event_frame_and_scenario_scores_of_a_lagging_shadow() -> None:
    """A shadow appears in frame 4 in the left half; the 'denoiser' keeps the old (unshadowed) value for three
    frames, then follows: masked error after the event, 3 frames to recover, a positive bias (too bright)."""
    ref = constant(1.0)
    ref[4:, :, :, :4] = 0.2
    pred = ref.copy()
    pred[4:7, :, :, :4] = 1.0
    shadow = np.zeros((T, H, W), bool)
    shadow[4, :, :4] = True                       # the change happens in frame 4
    masks = {kind: np.zeros((T, H, W), bool) for kind in ("disocclusion", "shadow", "fast_motion", "subject")}
    masks["shadow"] = shadow
    assert sm.event_frame([], shadow) == 4 and sm.event_frame([{"frame": 2, "kind": "camera_cut"}], shadow) == 2
    assert sm.event_frame([], np.zeros_like(shadow)) is None
    frames, summary = sm.scenario_scores(pred, ref, masks, ["shadow"], [], np.zeros((T, 2, H, W)),
                                         np.ones((T, H, W), bool), [False] * T, warmup=1, margin=0.1)
    assert summary["event_frame"] == 4 and summary["frames_to_recover"] == 3
    assert summary["steady_state_source"].startswith("own clip")
    assert summary["lag_region_pixels"] == H * 4 and summary["steady_state_mse"] == 0.0
    assert summary["post_event_mse"] > 0 and summary["relative_bias"] == pytest.approx(4.0)
    assert np.isnan(frames["masked_psnr"][0]) and frames["mask_pixels"].tolist() == [0] * 4 + [H * 4] + [0] * 7
    # Static pixels: the right half everywhere, the left half except frames 4 and 5 (changed in t or t - 1).
    assert frames["static_pixels"][4] == H * 4 and frames["static_pixels"][6] == H * W


def test_whole_frame_scenarios_use_the_event_of_events_json() -> None:
    ref = constant(0.5)
    ref[6:] = 2.0                                 # the light switches on in frame 6
    pred = ref.copy()
    pred[6] = 1.0                                 # one frame late: recovered after 1 frame
    masks = {kind: np.zeros((T, H, W), bool) for kind in ("disocclusion", "shadow", "fast_motion")}
    _, summary = sm.scenario_scores(pred, ref, masks, [], [{"frame": 6, "kind": "light_switch"}],
                                    np.zeros((T, 2, H, W)), np.ones((T, H, W), bool), [False] * T)
    assert summary["event_frame"] == 6 and summary["frames_to_recover"] == 1
    assert summary["lag_region_pixels"] == H * W and summary["relative_bias"] < 0


def test_an_atlas_sentence_without_static_pixels_says_so_instead_of_nan() -> None:
    """A camera that moves in every frame leaves no static pixel: flicker is undefined (NaN) and the atlas sentence
    says why instead of printing 'nan'; a measured flicker is printed."""
    from denoisers.report.atlas import sentence

    record = {"masked_psnr": 21.5, "recovery": "no event", "relative_bias": 0.0, "flicker_trmae": float("nan")}
    text = sentence("eaw", "texture_motion", record, deficit=-1.25, margin=0.1)
    assert "no static pixels to measure flicker" in text and "nan" not in text.lower()
    assert "1.25 dB below" in text
    measured = sentence("eaw", "texture_motion", {**record, "flicker_trmae": 0.0123}, deficit=0.5, margin=0.1)
    assert "flicker TRMAE 0.0123" in measured and "0.50 dB above" in measured


def test_atlas_rows_get_distinct_styles_beyond_ten_rows() -> None:
    """The default config's 15 rows share tab10's ten colours: colour, marker and line style together differ."""
    from denoisers.report.figures import row_styles

    rows = [f"row{i}" for i in range(15)]
    styles = row_styles(rows)
    keys = {(tuple(style["color"]), style["marker"], style["linestyle"]) for style in styles.values()}
    assert len(keys) == len(rows)
    assert styles["row0"]["color"] == styles["row10"]["color"] and styles["row0"]["marker"] != styles["row10"]["marker"]


def test_scenario_scores_take_the_steady_state_from_the_control_clip() -> None:
    """A shadow that appears in frame 4 and a 'denoiser' that never shows it: its own last frames are as wrong as
    the frames after the event, but the control clip (the final state held still, denoised without error in the
    lag region except a small constant) sets the failure-free level: 'never', and the ratio says how far off."""
    ref = constant(1.0)
    ref[4:, :, :, :4] = 0.2
    pred = ref.copy()
    pred[4:, :, :, :4] = 1.0                      # the shadow never appears
    masks = {kind: np.zeros((T, H, W), bool) for kind in ("disocclusion", "shadow", "fast_motion", "subject")}
    masks["shadow"][4, :, :4] = True
    control_ref = np.broadcast_to(ref[-1:], ref.shape).copy()
    control_pred = control_ref + 0.01
    args = (masks, ["shadow"], [], np.zeros((T, 2, H, W)), np.ones((T, H, W), bool), [False] * T)
    frames, summary = sm.scenario_scores(pred, ref, *args, control=(control_pred, control_ref))
    expected_steady = float(np.mean((metrics.tonemap(0.21) - metrics.tonemap(0.2)) ** 2))
    assert summary["steady_state_source"] == "control clip" and summary["steady_state_frames"] == T // 3
    assert summary["steady_state_mse"] == pytest.approx(expected_steady)
    assert summary["recovery"] == "never" and summary["frames_to_recover"] is None
    assert summary["ghosting_ratio"] > 100
    assert np.allclose(frames["control_lag_mse"], expected_steady)
    # Without the control the same clip would read as settled from the event on (the old definition).
    assert sm.recovery(frames["lag_mse"], 4, sm.steady_state(frames["lag_mse"])[0])["frames_to_recover"] == 0
    with pytest.raises(ValueError, match="control clip shape"):
        sm.scenario_scores(pred, ref, *args, control=(control_pred[:-1], control_ref[:-1]))


def test_an_atlas_sentence_reads_ghosting_against_the_noisy_inputs_ratio() -> None:
    """A scenario that changes in every frame never matches its control exactly; the noisy input's ratio there is
    what the content change alone does. A row whose ratio is no larger (by the margin) is not called ghosting."""
    from denoisers.report.atlas import sentence

    record = {"masked_psnr": 20.0, "recovery": "never", "frames_to_recover": None, "ghosting_ratio": 1.95,
              "relative_bias": 0.0, "flicker_trmae": 0.1}
    assert "ghosting under moving shadows" in sentence("oidn", "moving_shadow", record, -1.0, 0.1)
    content = sentence("oidn", "moving_shadow", record, -1.0, 0.1, input_ratio=1.8)
    assert "ghosting" not in content.split(",")[0] and "noisy input's 1.80" in content
    lagging = sentence("svgf", "moving_shadow", {**record, "ghosting_ratio": 28.0}, -9.0, 0.1, input_ratio=1.8)
    assert lagging.startswith("- **svgf**: ghosting under moving shadows, not back within 10%")


def test_the_atlas_names_the_rows_stability_rows_leaves_out() -> None:
    """ATLAS.md and the report say which rows the atlas holds: all configured rows, or the ones stability.rows
    names with the others listed (the smoke config keeps noisy, svgf and oidn)."""
    from pathlib import Path

    from denoisers.report.atlas import rows_sentence
    from scenegen.config import load_config

    repo = Path(__file__).resolve().parents[1]
    smoke = load_config(repo / "config" / "smoke.yaml")
    sentence = rows_sentence(smoke)
    assert smoke["stability"]["rows"] == ["noisy", "svgf", "oidn"]
    assert sentence.startswith("The rows named by `stability.rows` (noisy, svgf, oidn; not in the atlas: ")
    assert "eaw" in sentence and "rae" in sentence
    assert rows_sentence(load_config(repo / "config" / "config.yaml")) == "Every configured row of `evaluation.methods`"
