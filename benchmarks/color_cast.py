"""Colour cast of trained RAE models on the held-out validation scenes (never the test scenes), to tell where a
cast comes from without touching the evaluation.

For each ``--models`` entry (a model directory holding ``best.pt``: ``results/models/<id>`` or a saved copy) and
each validation scene of ``--config`` (``training.validation_scenes``, the last train_* ids), the model streams
the whole clip at ``--spp`` through the evaluation's own method (``denoisers.methods.rae``, recurrent state
carried) and the script prints the per-channel ratio of the mean output to the mean reference radiance over all
pixels and frames, and the cast as in the report (``denoisers.report.color_balance``: max over channels of
|ratio / mean ratio - 1|). The noisy input's ratios are printed per scene as the unbiased baseline. With
``--albedo-layers k`` > spp a second line per model divides by the mean albedo of k layers instead of the
input's own (is the noisy 1-spp divisor the cause?); colour-only models ignore it.

``--scenes`` names other scenes instead (training scenes: does a model show the cast on data it was trained on?);
test scenes are refused. ``--rows`` adds untrained method rows (e.g. ``oidn svgf eaw`` with their registered
defaults) for comparison. ``--brightness-bins`` adds, per model or row, the ratio of mean output to mean reference
luminance (channel mean) within bins of the reference's per-pixel luminance (at most its median, median to 90th
percentile, 90th to 99th, above the 99th; pixels of every frame): where the excess or deficit sits; and the
darker half split by the mean albedo of the loaded layers (channel mean >= 0.1: lit surfaces in shadow or dim
light; < 0.1: dark materials and the background). ``--psnr`` adds each line's mean per-frame PSNR (the
evaluation's ``denoisers.metrics.psnr``): what a cast or a noisy divisor costs in the metric.

Usage: python benchmarks/color_cast.py --results results --models results/models/rae results/models/rae_inputs_color
           [--config config/config.yaml] [--spp 1] [--albedo-layers 8] [--threads 2] [--scenes train_003 ...]
           [--rows oidn svgf eaw] [--brightness-bins] [--psnr]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from denoisers.methods.rae import GBufferRecurrentAutoencoderDenoiser, RecurrentAutoencoderDenoiser  # noqa: E402
from denoisers import registry  # noqa: E402
from denoisers.registry import Denoiser, clip_frames  # noqa: E402
from denoisers.metrics import psnr  # noqa: E402
from denoisers.report.color_balance import cast_of, channel_means  # noqa: E402
from denoisers.training.checkpoints import load_model  # noqa: E402
from denoisers.training.models import training_split  # noqa: E402
from scenegen.config import load_config  # noqa: E402
from scenegen.dataset import load_clip  # noqa: E402


def method_class_of(checkpoint: Path) -> type[RecurrentAutoencoderDenoiser]:
    """The evaluation's RAE method for a checkpoint: ``rae`` for a model trained on G-buffer features (net
    features_from gbuffer), ``rae_samples`` for one trained on the sample means."""
    model = load_model(checkpoint)
    gbuffer = getattr(model.config, "features_from", "samples") == "gbuffer"
    return GBufferRecurrentAutoencoderDenoiser if gbuffer else RecurrentAutoencoderDenoiser


def stream(method: Denoiser, frames: list, albedo: list[torch.Tensor] | None) -> list[np.ndarray]:
    """(3, H, W) outputs of ``method`` over ``frames``; ``albedo`` (per frame (S, 3, H, W)) replaces the frames'."""
    method.reset()
    outputs = []
    for t, frame in enumerate(frames):
        if albedo is not None:
            frame = dataclasses.replace(frame, samples={**frame.samples, "albedo": albedo[t]})
        with torch.no_grad():
            outputs.append(method.denoise(frame).numpy())
    return outputs


#: Upper percentiles of the reference luminance bounding the bins of ``--brightness-bins``.
BRIGHTNESS_PERCENTILES = (50.0, 90.0, 99.0)


def brightness_bin_ratios(outputs: list[np.ndarray], references: np.ndarray) -> np.ndarray:
    """(4,) mean output / mean reference luminance (channel mean) within bins of the reference's per-pixel
    luminance: <= p50, p50-p90, p90-p99, > p99 of ``references`` (T, 3, H, W); outputs: T arrays (3, H, W)."""
    reference = references.mean(axis=1)
    output = np.stack(outputs).mean(axis=1)
    edges = np.percentile(reference, BRIGHTNESS_PERCENTILES)
    index = np.searchsorted(edges, reference, side="left")      # 0: <= p50, ..., 3: > p99
    return np.array([output[index == b].mean() / reference[index == b].mean() for b in range(len(edges) + 1)])


#: Channel-mean albedo below which a dark pixel counts as a dark material rather than a surface in shadow.
DARK_ALBEDO = 0.1


def dark_half_ratios(outputs: list[np.ndarray], references: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(2,) mean output / mean reference luminance over the pixels at most the reference's median luminance with
    channel-mean ``albedo`` (T, H, W) >= DARK_ALBEDO (surfaces in shadow), then < DARK_ALBEDO; NaN if empty."""
    reference = references.mean(axis=1)
    output = np.stack(outputs).mean(axis=1)
    dark = reference <= np.median(reference)
    groups = (dark & (albedo >= DARK_ALBEDO), dark & (albedo < DARK_ALBEDO))
    return np.array([output[g].mean() / reference[g].mean() if g.any() else np.nan for g in groups])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="results folder holding renders/<scene>")
    parser.add_argument("--models", type=Path, nargs="+", required=True, help="model directories (best.pt)")
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--spp", type=int, default=1)
    parser.add_argument("--albedo-layers", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scene ids instead of the validation scenes (e.g. training scenes: is it generalisation?)")
    parser.add_argument("--rows", nargs="+", default=[], help="untrained method rows to compare (registered defaults)")
    parser.add_argument("--brightness-bins", action="store_true",
                        help="also print output / reference luminance per bin of reference luminance")
    parser.add_argument("--psnr", action="store_true", help="also print the mean per-frame PSNR of every line")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    scenes = args.scenes or training_split(cfg)[1]
    if any(scene.startswith("test_") for scene in scenes):
        parser.error("test scenes are for the evaluation only: pick validation or training scenes")
    print(f"scenes {', '.join(scenes)} at {args.spp} spp; ratio = mean output / mean reference per "
          f"channel (R, G, B); cast = max |ratio / mean - 1|")
    for scene in scenes:
        layers = max(args.spp, args.albedo_layers)
        clip = load_clip(args.results / "renders" / scene, buffers=RecurrentAutoencoderDenoiser.info.inputs,
                         spp=layers, reference=True)        # the sample-mean RAE's inputs cover the G-buffer RAE's
        references = np.stack(list(clip.reference["radiance"]))
        reference = channel_means(list(references))
        bins = (references, clip.samples["albedo"].mean(axis=(1, 2))) if args.brightness_bins else None
        scored = references if args.psnr else None
        noisy = channel_means(list(clip.samples["radiance"][:, :args.spp].mean(axis=1)))
        print(f"{scene}  {'noisy input':34s} ratio {np.round(noisy / reference, 3)}  cast {cast_of(noisy / reference):.3f}")
        wide_albedo = None
        if args.albedo_layers > args.spp:
            wide = clip.samples["albedo"].mean(axis=1, keepdims=True)          # (T, 1, 3, H, W)
            wide_albedo = [torch.from_numpy(np.repeat(frame, args.spp, axis=0)) for frame in wide]
        for model_dir in args.models:
            method_class = method_class_of(model_dir / "best.pt")
            method = method_class(checkpoint=str(model_dir / "best.pt"))
            frames = list(clip_frames(clip, method_class.info, args.spp))
            variants = [("own albedo", None)]
            # A G-buffer model reads its albedo from the pixel-centre G-buffer: the layer mean does not apply.
            if (wide_albedo is not None and method.model.config.demodulate
                    and method_class is RecurrentAutoencoderDenoiser):
                variants.append((f"albedo of {args.albedo_layers} layers", wide_albedo))
            for label, albedo in variants:
                outputs = stream(method, frames, albedo)
                report(scene, f"{model_dir.name} ({label})", outputs, reference, bins, scored)
        for row in args.rows:
            method = registry.build(row)
            row_clip = load_clip(args.results / "renders" / scene, buffers=method.info.inputs, spp=args.spp)
            report(scene, row, stream(method, list(clip_frames(row_clip, method.info, args.spp)), None), reference,
                   bins, scored)


def report(scene: str, name: str, outputs: list[np.ndarray], reference: np.ndarray,
           bins: tuple[np.ndarray, np.ndarray] | None, scored: np.ndarray | None = None) -> None:
    """One line: per-channel ratios and cast; with ``bins`` = (references (T, 3, H, W), albedo (T, H, W)) also
    the luminance ratios per brightness bin and over the darker half by albedo; with ``scored`` (the references
    (T, 3, H, W)) the mean per-frame PSNR."""
    ratio = channel_means(outputs) / reference
    line = f"{scene}  {name:34s} ratio {np.round(ratio, 3)}  cast {cast_of(ratio):.3f}"
    if scored is not None:
        line += f"  PSNR {np.mean([psnr(out, ref) for out, ref in zip(outputs, scored)]):.2f} dB"
    if bins is not None:
        references, albedo = bins
        line += f"\n    luminance ratio by reference bin (<=p50, p50-90, p90-99, >p99) " \
                f"{np.round(brightness_bin_ratios(outputs, references), 3)}; darker half, albedo >= {DARK_ALBEDO} / " \
                f"< {DARK_ALBEDO}: {np.round(dark_half_ratios(outputs, references, albedo), 3)}"
    print(line, flush=True)


if __name__ == "__main__":
    main()
