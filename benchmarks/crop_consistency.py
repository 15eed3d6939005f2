"""Does a trained denoiser work on whole frames as well as on its training crops?

A network trained on crops smaller than its receptive field can learn the crop's borders (zero padding) as a
cue; on a larger frame its interior then lies farther from every border than any training pixel did, and the
output degrades there. This diagnostic denoises each frame twice, whole and as separate crop-sized windows,
and scores the same windows of both runs against the reference (PSNR of tau-tonemapped radiance, Isik Eq. 15):

    gap = PSNR(window of the whole-frame run) - PSNR(the window run on its own)

A gap well below 0 means the model is worse on whole frames than on what it was trained on. Run it on
validation scenes (never choose anything on test scenes). Temporal models are reset before every frame, so
each frame is scored as a shot's first frame.

    python benchmarks/crop_consistency.py --checkpoint results/isik2021/models/afn_single/best.pt \
        --render-dir results/isik2021/renders/train_024 --spp 4 --crop 64
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from denoisers import registry
from denoisers.metrics import psnr
from scenegen.dataset import load_clip


def windows(height: int, width: int, crop: int) -> list[tuple[int, int]]:
    """Top-left corners of crop x crop windows tiling the frame (the last row/column flush with the edge)."""
    rows = sorted({min(y, height - crop) for y in range(0, height, crop)})
    cols = sorted({min(x, width - crop) for x in range(0, width, crop)})
    return [(y, x) for y in rows for x in cols]


def crop_frame(frame: registry.Frame, y: int, x: int, crop: int) -> registry.Frame:
    """The frame cut to one window (every per-sample and per-pixel buffer)."""
    cut = {name: value[..., y:y + crop, x:x + crop] for name, value in frame.samples.items()}
    pixel = {name: value[..., y:y + crop, x:x + crop] for name, value in frame.pixel.items()}
    return dataclasses.replace(frame, samples=cut, pixel=pixel)


def output_image(result: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float32 of a method's (3, H, W) output."""
    return result.detach().float().permute(1, 2, 0).numpy()


def frame_gaps(method: registry.Denoiser, frame: registry.Frame, reference: np.ndarray,
               crop: int) -> list[tuple[float, float]]:
    """(PSNR of the window in the whole-frame run, PSNR of the window run alone) per window, dB;
    reference (3, H, W) linear radiance."""
    method.reset()
    whole = output_image(method.denoise(frame))
    scores = []
    for y, x in windows(frame.height, frame.width, crop):
        method.reset()
        alone = output_image(method.denoise(crop_frame(frame, y, x, crop)))
        target = reference[:, y:y + crop, x:x + crop].transpose(1, 2, 0)
        scores.append((psnr(whole[y:y + crop, x:x + crop], target), psnr(alone, target)))
    return scores


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, nargs="+", required=True, help="best.pt of each model")
    parser.add_argument("--method", default="afn", help="registered method that reads the checkpoint")
    parser.add_argument("--render-dir", type=Path, nargs="+", required=True, help="rendered validation scenes")
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--crop", type=int, default=64, help="the models' training crop (pixels)")
    parser.add_argument("--frames", type=int, default=4, help="frames per scene, evenly spaced")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    print(f"crop {args.crop}, {args.spp} spp; gap = whole-frame run - window run (dB, mean over windows and "
          f"frames; min = worst window)")
    print(f"{'model':<48} {'scene':<12} {'whole':>7} {'alone':>7} {'gap':>7} {'min':>7}")
    for checkpoint in args.checkpoint:
        method = registry.build(args.method, {"checkpoint": str(checkpoint)})
        if method.info.adaptive:
            parser.error(f"method {args.method!r} is adaptive: a window changes where its sample budget goes, "
                         f"so whole-frame and window runs are not comparable")
        for render_dir in args.render_dir:
            clip = load_clip(render_dir, buffers=method.info.inputs, spp=args.spp * method.samples_factor)
            frames = list(registry.clip_frames(clip, method.info, args.spp * method.samples_factor))
            picks = np.unique(np.linspace(0, len(frames) - 1, args.frames).round().astype(int))
            scores = [s for t in picks
                      for s in frame_gaps(method, frames[t], clip.reference["radiance"][t], args.crop)]
            whole, alone = (float(np.mean([s[i] for s in scores])) for i in (0, 1))
            gaps = [a - b for a, b in scores if math.isfinite(a - b)]
            print(f"{checkpoint.parent.name!s:<48} {render_dir.name:<12} {whole:7.2f} {alone:7.2f} "
                  f"{float(np.mean(gaps)):+7.2f} {min(gaps):+7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
