"""Does a trained denoiser work on whole frames as well as on its training crops?

A network trained on crops smaller than its receptive field can learn the crops' borders (zero padding) as a
cue; on a larger frame its interior lies farther from every border than any training pixel did, and the output
degrades there (docs/findings.md, "AFN: 64-pixel training crops and whole frames"). The check denoises each
frame twice, whole and as separate crop-sized windows, and scores the same windows of both runs against the
reference (PSNR of tau-tonemapped radiance, Isik 2021 Eq. 15):

    gap = PSNR(window of the whole-frame run) - PSNR(the window denoised alone)   (dB)

A sound model gains from the whole frame (a window loses its neighbours at its edge), so a gap well below 0
means the model is worse on whole frames than on what it was trained on. Run on validation scenes only.
Temporal models are reset before every frame (each frame is scored as a shot's first frame); adaptive methods
are not checked (a window moves their sample budget).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from denoisers import registry
from denoisers.metrics import psnr

#: Frames per scene, evenly spaced over the clip.
FRAMES_PER_SCENE = 4


def windows(height: int, width: int, crop: int) -> list[tuple[int, int]]:
    """Top-left corners of crop x crop windows tiling an H x W frame (the last row/column flush with the edge)."""
    rows = sorted({min(y, height - crop) for y in range(0, height, crop)})
    cols = sorted({min(x, width - crop) for x in range(0, width, crop)})
    return [(y, x) for y in rows for x in cols]


def crop_frame(frame: registry.Frame, y: int, x: int, crop: int) -> registry.Frame:
    """The frame cut to one window (every per-sample and per-pixel buffer)."""
    samples = {name: value[..., y:y + crop, x:x + crop] for name, value in frame.samples.items()}
    pixel = {name: value[..., y:y + crop, x:x + crop] for name, value in frame.pixel.items()}
    return dataclasses.replace(frame, samples=samples, pixel=pixel)


def _image(output: torch.Tensor) -> np.ndarray:
    return output.detach().float().numpy()


def frame_gaps(method: registry.Denoiser, frame: registry.Frame, reference: np.ndarray,
               crop: int) -> list[tuple[float, float]]:
    """(PSNR of the window in the whole-frame run, PSNR of the window denoised alone) per window (dB);
    reference (3, H, W) linear radiance."""
    method.reset()
    whole = _image(method.denoise(frame))
    scores = []
    for y, x in windows(frame.height, frame.width, crop):
        method.reset()
        alone = _image(method.denoise(crop_frame(frame, y, x, crop)))
        target = reference[:, y:y + crop, x:x + crop]
        scores.append((psnr(whole[:, y:y + crop, x:x + crop], target), psnr(alone, target)))
    return scores


def scene_summary(scores: Sequence[tuple[float, float]]) -> dict[str, float]:
    """Mean whole-run and window-run PSNR, the mean gap and the worst window's gap (dB)."""
    gaps = [whole - alone for whole, alone in scores if math.isfinite(whole - alone)]
    return {"whole_psnr": float(np.mean([s[0] for s in scores])), "window_psnr": float(np.mean([s[1] for s in scores])),
            "gap_db": float(np.mean(gaps)) if gaps else math.nan, "worst_window_gap_db": min(gaps, default=math.nan)}


def check_method(method: registry.Denoiser, clips: Sequence[Any], spp: int, crop: int,
                 frames: int = FRAMES_PER_SCENE) -> dict[str, Any]:
    """The check on loaded clips (scenegen.dataset.Clip with references): per scene the
    :func:`scene_summary`, and ``gap_db``, the lowest scene's mean gap."""
    if method.info.adaptive:
        raise ValueError(f"method {method.info.name!r} is adaptive: a window moves its sample budget, so whole "
                         f"frames and windows are not comparable")
    layers = spp * method.samples_factor
    scenes = {}
    for clip in clips:
        clip_frames = list(registry.clip_frames(clip, method.info, layers))
        height, width = clip_frames[0].height, clip_frames[0].width
        if crop >= min(height, width):
            raise ValueError(f"clip {clip.scene!r} is {height}x{width} pixels, not larger than the crop {crop}")
        picks = np.unique(np.linspace(0, len(clip_frames) - 1, frames).round().astype(int))
        scores = [score for t in picks
                  for score in frame_gaps(method, clip_frames[t], clip.reference["radiance"][t], crop)]
        scenes[clip.scene] = scene_summary(scores)
    return {"crop": int(crop), "spp": int(spp), "frames_per_scene": int(frames), "scenes": scenes,
            "gap_db": min((s["gap_db"] for s in scenes.values()), default=math.nan)}

