"""Importance-sampled training crops: crops are drawn where the noisy input differs most from the reference,
in the spirit of Bako et al. 2017 ("Kernel-predicting convolutional networks for denoising Monte Carlo
renderings"), who train on patches chosen by importance rather than uniformly, so that training spends
its steps on the noisy, hard regions instead of flat, converged ones. The error metric below is ours (the
brief of issue 11 §2), not a transcription of theirs.

Per clip, once (:class:`ImportanceCrops`):

1. a per-frame error map ``e[t, y, x]``: the relative squared error of the mean of *all* stored noisy
   radiance layers against the reference radiance, ``|mean - ref|^2 / (ref^2 + eps)`` averaged over the
   colour channels (eps = :data:`RELATIVE_EPS`; non-finite values count as 0). The mean of many layers
   locates the noise more reliably than one layer; its scale does not matter after step 3.
2. a crop score per top-left position: the mean of ``e`` over the ``crop x crop`` window starting there
   (box mean from an integral image, so cost O(H W) per frame whatever the crop);
3. per frame, the scores normalised to a distribution over the ``(H - crop + 1) x (W - crop + 1)``
   positions (uniform for a frame without any error).

Per sequence (:meth:`ImportanceCrops.probabilities`): the mean of the distributions of the sequence's output
frames (a camera stop's repeated frame counts once per output frame, as it does in the loss), mixed with
the uniform distribution, ``p = (1 - floor) * p_error + floor / positions``, so that with ``floor > 0`` every
position keeps a nonzero probability. The crop is then drawn with the batch's generator (one uniform draw),
so batch ``i`` stays a pure function of (seed, i).

Memory: float32 (T, H - crop + 1, W - crop + 1) per clip, i.e. O(frames * H * W).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scenegen.dataset import Clip

#: Regulariser of the relative squared error (radiance units squared), the usual value of relMSE.
RELATIVE_EPS: float = 1e-2
#: Crop position strategies (SequenceConfig.crops).
CROP_MODES: tuple[str, ...] = ("uniform", "importance")


def relative_error(noisy_mean: np.ndarray, reference: np.ndarray, eps: float = RELATIVE_EPS) -> np.ndarray:
    """(..., C, H, W) noisy estimate and reference radiance -> (..., H, W) float32 relative squared error
    ``|noisy - ref|^2 / (ref^2 + eps)`` averaged over C; non-finite values become 0."""
    noisy_mean = np.asarray(noisy_mean, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        error = ((noisy_mean - reference) ** 2 / (reference ** 2 + np.float32(eps))).mean(axis=-3)
    return np.where(np.isfinite(error), error, np.float32(0.0)).astype(np.float32, copy=False)


def box_mean(image: np.ndarray, size: int) -> np.ndarray:
    """(..., H, W) -> (..., H - size + 1, W - size + 1) float32: mean over the ``size x size`` window whose
    top-left corner is each position (integral image in float64)."""
    height, width = image.shape[-2:]
    if not 1 <= size <= min(height, width):
        raise ValueError(f"box size {size} does not fit an image of {height}x{width} pixels")
    integral = np.zeros(image.shape[:-2] + (height + 1, width + 1), np.float64)
    np.cumsum(np.cumsum(image, axis=-2, dtype=np.float64), axis=-1, out=integral[..., 1:, 1:])
    window = (integral[..., size:, size:] - integral[..., :-size, size:]
              - integral[..., size:, :-size] + integral[..., :-size, :-size])
    return (window / (size * size)).astype(np.float32)


def normalise(scores: np.ndarray) -> np.ndarray:
    """(T, h, w) non-negative scores -> (T, h, w) float32, each frame summing to 1 (uniform where a frame's
    scores sum to 0)."""
    scores = np.maximum(scores, 0.0)
    totals = scores.sum(axis=(-2, -1), keepdims=True, dtype=np.float64)
    uniform = np.full_like(scores, 1.0 / (scores.shape[-2] * scores.shape[-1]))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(totals > 0, scores / np.where(totals > 0, totals, 1.0), uniform).astype(np.float32)


class ImportanceCrops:
    """Per-frame crop-position distributions of one clip (module docstring); built once per clip."""

    def __init__(self, clip: Clip, crop: int, eps: float = RELATIVE_EPS) -> None:
        if "radiance" not in clip.samples:
            raise KeyError(f"crops: importance needs the per-sample buffer 'radiance' of clip {clip.scene!r} "
                           f"(loaded: {', '.join(clip.samples)})")
        if clip.reference is None or "radiance" not in clip.reference:
            raise KeyError(f"crops: importance needs the reference radiance of clip {clip.scene!r}")
        samples, reference = clip.samples["radiance"], clip.reference["radiance"]
        # One frame at a time: temporaries stay O(H W) (the layer mean of a (S, C, H, W) frame).
        frames = [normalise(box_mean(relative_error(samples[t].mean(axis=0), reference[t], eps)[None], crop))[0]
                  for t in range(samples.shape[0])]
        #: (T, H - crop + 1, W - crop + 1) float32, each frame summing to 1.
        self.frame_probabilities = np.stack(frames)
        self.crop = int(crop)

    def probabilities(self, frames: Sequence[int], floor: float) -> np.ndarray:
        """(H - crop + 1, W - crop + 1) float64 distribution of the crop's top-left corner for a sequence of
        clip-local ``frames``: mean of their distributions, mixed with uniform by ``floor``."""
        mean = self.frame_probabilities[np.asarray(frames)].mean(axis=0, dtype=np.float64)
        return (1.0 - floor) * mean + floor / mean.size

    def draw(self, rng: np.random.Generator, frames: Sequence[int], floor: float) -> tuple[int, int]:
        """(row, column) of the crop's top-left corner, drawn from :meth:`probabilities` with one uniform of ``rng``."""
        probabilities = self.probabilities(frames, floor)
        cdf = np.cumsum(probabilities.ravel())
        # The first position whose cdf exceeds u in [0, total): its own probability is > 0 (cdf rises there).
        index = min(int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right")), cdf.size - 1)
        row, column = divmod(index, probabilities.shape[1])
        return int(row), int(column)
