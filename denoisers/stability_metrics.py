"""Failure metrics of a denoised stability clip (issue 15 §2): where and how long a method fails.

Inputs are numpy arrays: predicted and reference linear HDR radiance (T, 3, H, W), masks (T, H, W) bool,
motion vectors (T, 2, H, W) in pixels, per-frame flags (T,) bool. Everything is vectorised over pixels
and frames; results are (T,) float64 per-frame series (NaN where undefined) or floats.

Definitions (each repeated on its function):

* **Error** of a pixel: squared difference of tau-tonemapped radiance (denoisers.metrics.tonemap, Isik 2021
  Eq. 15), averaged over the three channels; the metrics' PSNR space, so masked PSNR = -10 log10 of its mean.
* **Focus mask** M_t: union of the scenario's focus masks (scenegen.scenarios; e.g. ``shadow``) in frame t;
  a scenario without focus masks (camera cut, light switch) uses the whole frame.
* **Event frame** e: the first event of events.json (camera cut, light switch, fast motion), else the first
  frame whose focus mask is non-empty (frame 0 counts: a cold start); None when the mask is always empty.
* **Lag region** R: the union of M_t over t >= e (whole frame if empty), fixed, so every frame's error in R
  is over the same pixels; per-frame lag error l_t = mean error over R.
* **Steady state** S: the same row's lag error over the same region R on the scenario's failure-free control
  clip (stab_{name}__still: every animated thing held at the scenario's final-frame state, denoised by the same
  row at the same spp), median over its last ``steady_frames(T)`` = max(1, T // 3) frames: the error the method
  settles to on what the scenario ends with when nothing changes. A scenario in which nothing changes
  (caustics, low light) is its own control.
* **Margin** m (config ``stability.margin``, default 0.1): frames-to-recover = the first k >= 0 with
  l_{e+k} <= (1 + m) S; None ("never") when no frame after the event gets there, i.e. the error stays above
  the failure-free level for the rest of the clip; undetermined ("too short") with fewer than 3 frames from
  the event to the clip's end.
* **Ghosting**: mean of l_t over t >= e (the masked error after the event), and its ratio to S.
* **Flicker**: TRMAE (Isik 2021 Eq. 16) over static pixels: valid reprojection, |motion| < STATIC_MOTION_PX, in
  neither frame t nor t - 1 inside a change or focus mask, in frames with history (not frame 0, not a cut, past
  the warm-up) that are not event frames of events.json (those belong to the lag metric).
* **Bias**: mean signed luminance error pred - ref over the focus masks of all frames, relative to the mean
  reference luminance there (negative = darker, e.g. fireflies clamped away or a shadow lagging behind).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from denoisers.metrics import TRMAE_EPS, tonemap

#: Motion below this length (pixels) counts as static for the flicker region.
STATIC_MOTION_PX = 0.01
#: Default margin over the steady-state error within which a method counts as recovered (10 %).
DEFAULT_MARGIN = 0.1
#: Masks that mark a change between t - 1 and t (besides the scenario's focus): never static.
CHANGE_MASKS: tuple[str, ...] = ("disocclusion", "shadow", "fast_motion")
#: Fewer frames from the event to the clip's end leave recovery undetermined ("too short"): one frame to settle
#: in, one to compare, one steady-state frame.
MIN_POST_EVENT_FRAMES = 3
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _check(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    pred, ref = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    if pred.shape != ref.shape or pred.ndim != 4:
        raise ValueError(f"expected pred and ref of the same shape (T, C, H, W); got {pred.shape} and {ref.shape}")
    if mask is not None and np.shape(mask) != (pred.shape[0], *pred.shape[2:]):
        raise ValueError(f"mask shape {np.shape(mask)} does not match (T, H, W) = {(pred.shape[0], *pred.shape[2:])}")
    return pred, ref


def masked_mean(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(T,) mean of ``values`` (T, H, W) over the pixels of ``mask`` (T, H, W) in every frame; NaN if empty."""
    mask = np.asarray(mask, bool)
    count = mask.sum(axis=(1, 2))
    total = np.where(mask, values, 0.0).sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def pixel_error(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(T, H, W) squared error of tau-tonemapped radiance, mean over channels (unitless, in [0, 1])."""
    pred, ref = _check(pred, ref)
    return np.mean((tonemap(pred) - tonemap(ref)) ** 2, axis=1)


def masked_mse(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(T,) mean tau-space squared error over ``mask`` per frame (NaN where the mask is empty)."""
    _check(pred, ref, mask)
    return masked_mean(pixel_error(pred, ref), mask)


def psnr_of_mse(mse: np.ndarray | float) -> np.ndarray:
    """-10 log10(mse) in dB (peak 1); +inf for 0, NaN stays NaN."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return -10.0 * np.log10(np.asarray(mse, np.float64))


def masked_psnr(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(T,) PSNR (dB) of tau images over the pixels of ``mask`` per frame; with a full mask = metrics.psnr."""
    return psnr_of_mse(masked_mse(pred, ref, mask))


def masked_tpsnr(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray, history: np.ndarray) -> np.ndarray:
    """(T,) temporal PSNR (Hasselgren 2020) over ``mask``: -10 log10 mean_{mask, c} (d tau(p)_t - d tau(r)_t)^2,
    d x_t = x_t - x_{t-1}; NaN in frames without ``history`` (T,) (frame 0, cuts, warm-up) or an empty mask."""
    pred, ref = _check(pred, ref, mask)
    out = np.full(pred.shape[0], np.nan)
    if pred.shape[0] > 1:
        tp, tr = tonemap(pred), tonemap(ref)
        diff = np.mean(((tp[1:] - tp[:-1]) - (tr[1:] - tr[:-1])) ** 2, axis=1)
        out[1:] = psnr_of_mse(masked_mean(diff, np.asarray(mask, bool)[1:]))
    out[~np.asarray(history, bool)] = np.nan
    return out


def masked_trmae(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray, history: np.ndarray) -> np.ndarray:
    """(T,) TRMAE (Isik 2021 Eq. 16, eps 0.01) over ``mask``: mean_{mask, c} |dp - dr| / (|dr| + eps) on linear
    radiance; NaN in frames without ``history`` (T,) or with an empty mask. With a full mask = metrics.trmae."""
    pred, ref = _check(pred, ref, mask)
    out = np.full(pred.shape[0], np.nan)
    if pred.shape[0] > 1:
        dp, dr = pred[1:] - pred[:-1], ref[1:] - ref[:-1]
        out[1:] = masked_mean(np.mean(np.abs(dp - dr) / (np.abs(dr) + TRMAE_EPS), axis=1), np.asarray(mask, bool)[1:])
    out[~np.asarray(history, bool)] = np.nan
    return out


def signed_bias(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(absolute, relative) mean signed luminance error pred - ref over every masked pixel of every frame
    (linear radiance; relative = divided by the mean reference luminance there). NaN for an empty mask."""
    pred, ref = _check(pred, ref, mask)
    mask = np.asarray(mask, bool)
    if not mask.any():
        return float("nan"), float("nan")
    diff = np.tensordot(pred - ref, LUMINANCE, axes=([1], [0]))[mask]
    level = np.tensordot(ref, LUMINANCE, axes=([1], [0]))[mask].mean()
    absolute = float(diff.mean())
    return absolute, float(absolute / level) if level > 0 else float("nan")


def history_frames(n_frames: int, cuts: Sequence[bool], warmup: int = 1) -> np.ndarray:
    """(T,) bool: frames with a usable predecessor: not the first max(warmup, 1) frames of the clip or of a
    shot after a camera cut (``cuts`` (T,): frame t starts a new shot)."""
    cuts = np.asarray(cuts, bool)
    since = np.zeros(n_frames, int)
    for t in range(1, n_frames):   # T steps, not per pixel
        since[t] = 0 if cuts[t] else since[t - 1] + 1
    return since >= max(int(warmup), 1)


def focus_mask(masks: Mapping[str, np.ndarray], focus: Sequence[str], shape: tuple[int, int, int]) -> np.ndarray:
    """(T, H, W) union of the ``focus`` masks; the whole frame when ``focus`` is empty."""
    if not focus:
        return np.ones(shape, bool)
    return np.logical_or.reduce([np.asarray(masks[kind], bool) for kind in focus])


def static_mask(motion: np.ndarray, valid: np.ndarray, changed: np.ndarray, history: np.ndarray) -> np.ndarray:
    """(T, H, W) static pixels: valid reprojection (``valid`` (T, H, W)), motion (T, 2, H, W) shorter than
    STATIC_MOTION_PX, in neither t nor t - 1 inside ``changed`` (T, H, W), in frames with ``history`` (T,)."""
    still = np.linalg.norm(np.asarray(motion, np.float64), axis=1) < STATIC_MOTION_PX
    changed = np.asarray(changed, bool)
    before = np.concatenate([changed[:1], changed[:-1]])
    return still & np.asarray(valid, bool) & ~changed & ~before & np.asarray(history, bool)[:, None, None]


def event_frame(events: Sequence[Mapping[str, Any]], focus: np.ndarray) -> int | None:
    """The frame of the first event (events.json ``events``), else the first frame whose ``focus`` (T, H, W) mask
    is non-empty (0 = the clip start), else None."""
    if events:
        return int(min(int(event["frame"]) for event in events))
    filled = np.flatnonzero(np.asarray(focus, bool).any(axis=(1, 2)))
    return int(filled[0]) if filled.size else None


def steady_frames(frames: int) -> int:
    """Frames at the end of a control clip whose median error is the steady state: max(1, frames // 3)."""
    return max(1, int(frames) // 3)


def steady_state(control_errors: np.ndarray) -> tuple[float, int]:
    """(S, frames): median of the last steady_frames(T) per-frame lag errors (T,) of the control clip (NaN
    frames ignored; NaN when none is finite)."""
    errors = np.asarray(control_errors, np.float64)
    window = steady_frames(errors.size)
    tail = errors[-window:]
    return (float(np.nanmedian(tail)) if np.isfinite(tail).any() else float("nan")), int(window)


def recovery(errors: np.ndarray, event: int, steady: float, margin: float = DEFAULT_MARGIN) -> dict[str, Any]:
    """Lag after ``event`` from the per-frame lag errors (T,) against the steady state ``steady`` (the control
    clip's, :func:`steady_state`): frames_to_recover = first k >= 0 with errors[event + k] <= (1 + margin) S
    (NaN frames never count); recovery = 'recovered', 'never' (no frame gets there before the clip ends) or
    'too short' (fewer than MIN_POST_EVENT_FRAMES frames from the event on: frames_to_recover None);
    ghosting = mean error from the event on, and its ratio to S."""
    errors = np.asarray(errors, np.float64)
    post = errors[event:]
    with np.errstate(all="ignore"):
        ghosting = float(np.nanmean(post)) if np.isfinite(post).any() else float("nan")
        within = np.flatnonzero(post <= (1.0 + margin) * steady)
    status = "too short" if post.size < MIN_POST_EVENT_FRAMES else "recovered" if within.size else "never"
    return {"event_frame": int(event), "steady_state_mse": float(steady), "margin": float(margin), "recovery": status,
            "frames_to_recover": int(within[0]) if within.size and status == "recovered" else None,
            "post_event_mse": ghosting, "ghosting_ratio": ghosting / steady if steady > 0 else float("nan")}


def scenario_scores(pred: np.ndarray, ref: np.ndarray, masks: Mapping[str, np.ndarray], focus: Sequence[str],
                    events: Sequence[Mapping[str, Any]], motion: np.ndarray, valid: np.ndarray, cuts: Sequence[bool],
                    warmup: int = 1, margin: float = DEFAULT_MARGIN,
                    control: tuple[np.ndarray, np.ndarray] | None = None,
                    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Every failure metric of one denoised clip: (per-frame columns (T,) each, clip summary).

    ``control``: (pred, ref) of the scenario's failure-free control clip (same shape as the clip), denoised by
    the same row; None for a scenario in which nothing changes, which is its own control.
    Per frame: psnr, tpsnr, trmae over the whole frame; masked_psnr, masked_tpsnr, masked_trmae over the focus
    mask M_t; lag_mse over the lag region R (control_lag_mse: the control's); flicker_trmae over the static
    pixels (event frames excluded); mask_pixels, static_pixels.
    Summary: frame means of those (NaN-aware), the recovery record (:func:`recovery`; None fields without an
    event), the steady state's source and frames, bias (absolute, relative) over M."""
    pred, ref = _check(pred, ref)
    if control is not None:
        control = _check(*control)
        if control[0].shape != pred.shape:
            raise ValueError(f"control clip shape {control[0].shape} differs from the clip's {pred.shape}")
    n_frames, _, height, width = pred.shape
    shape = (n_frames, height, width)
    history = history_frames(n_frames, cuts, warmup)
    everything = np.ones(shape, bool)
    focus_t = focus_mask(masks, focus, shape)
    changed = np.logical_or.reduce([np.asarray(masks[k], bool) for k in CHANGE_MASKS if k in masks] + [
        focus_t if focus else np.zeros(shape, bool)])
    # Flicker is measured away from events (their frames belong to the lag metric).
    calm = history.copy()
    calm[[int(e["frame"]) for e in events if 0 <= int(e["frame"]) < n_frames]] = False
    static = static_mask(motion, valid, changed, calm)
    event = event_frame(events, focus_t)
    region = focus_t[event:].any(axis=0) if event is not None else np.zeros((height, width), bool)
    region = np.broadcast_to(region if region.any() else np.ones((height, width), bool), shape)
    frames = {
        "psnr": masked_psnr(pred, ref, everything), "tpsnr": masked_tpsnr(pred, ref, everything, history),
        "trmae": masked_trmae(pred, ref, everything, history),
        "masked_psnr": masked_psnr(pred, ref, focus_t), "masked_tpsnr": masked_tpsnr(pred, ref, focus_t, history),
        "masked_trmae": masked_trmae(pred, ref, focus_t, history),
        "lag_mse": masked_mse(pred, ref, region), "flicker_trmae": masked_trmae(pred, ref, static, history),
        "control_lag_mse": masked_mse(*control, region) if control is not None else np.full(n_frames, np.nan),
        "mask_pixels": focus_t.sum(axis=(1, 2)).astype(np.int64), "static_pixels": static.sum(axis=(1, 2)),
    }
    bias, relative = signed_bias(pred, ref, focus_t)

    def mean(name: str) -> float:
        values = np.asarray(frames[name], np.float64)
        values = values[np.isfinite(values)]
        return float(values.mean()) if values.size else float("nan")

    summary: dict[str, Any] = {name: mean(name) for name in ("psnr", "tpsnr", "trmae", "masked_psnr", "masked_tpsnr",
                                                              "masked_trmae", "flicker_trmae")}
    summary.update(bias=bias, relative_bias=relative, mask_frames=int((frames["mask_pixels"] > 0).sum()),
                   lag_region_pixels=int(region[0].sum()))
    steady, window = steady_state(frames["control_lag_mse"] if control is not None else frames["lag_mse"])
    summary.update(steady_state_source="control clip" if control is not None else "own clip (nothing changes)",
                   steady_state_frames=window)
    summary.update(recovery(frames["lag_mse"], event, steady, margin) if event is not None else
                   {"event_frame": None, "steady_state_mse": float("nan"), "margin": float(margin),
                    "recovery": "no event", "frames_to_recover": None, "post_event_mse": float("nan"),
                    "ghosting_ratio": float("nan")})
    return frames, summary
