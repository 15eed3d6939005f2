"""What re-modulating by a per-pixel albedo costs at best: the PSNR of an oracle that knows the exact untextured
illumination and multiplies it back by a given albedo, as the demodulating RAE does (Chaitanya et al. 2017, §3.2).

The reference pixel integrates radiance over the pixel footprint, L_ref = mean over the footprint of albedo x
illumination. A method that predicts the illumination E and re-modulates by a single albedo a_x per pixel can at
best output E * a_x with E = L_ref / a_bar, a_bar the footprint's mean albedo. Where a_x differs from a_bar
(texture and object edges inside a pixel) that output is wrong however well E is predicted. This script prints,
per scene, the mean per-frame PSNR (the evaluation's ``denoisers.metrics.psnr``) of

    oracle_x = L_ref / max(a_bar, floor) * max(a_x, floor)

against L_ref for a_x = the pixel-centre G-buffer albedo (method ``rae``) and the first jittered sample's albedo
(method ``rae_samples`` at 1 spp), and the fraction of pixels where |a_x / a_bar - 1| > 10 %. a_bar is the mean
albedo of the other stored layers (layers 1..S-1, independent of layer 0), a finite-sample estimate: its own
noise lowers the printed PSNR somewhat, so the figures are pessimistic bounds, not exact ones; the control line
re-modulates by the mean of one half of those layers against the other half's, which shows the size of that noise. ``floor`` is the
RAE's ``albedo_floor`` (its divisor's lower bound). A colour-only method has no such ceiling. Refuses test scenes.

Usage: python benchmarks/remodulation_ceiling.py --results results [--config config/config.yaml]
           [--scenes train_024 train_025 ...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from denoisers.metrics import psnr  # noqa: E402
from denoisers.nets.rae import RAEConfig  # noqa: E402
from denoisers.training.models import training_split  # noqa: E402
from scenegen.config import load_config  # noqa: E402
from scenegen.dataset import load_clip  # noqa: E402

#: Relative albedo mismatch above which a pixel counts as aliased in the printed fraction.
MISMATCH = 0.10


def oracle(reference: np.ndarray, footprint_albedo: np.ndarray, albedo: np.ndarray, floor: float) -> np.ndarray:
    """(T, 3, H, W) best output of a method re-modulating by ``albedo``: reference / max(footprint, floor) *
    max(albedo, floor); all inputs (T, 3, H, W), linear."""
    return reference / np.maximum(footprint_albedo, floor) * np.maximum(albedo, floor)


def mismatch_fraction(footprint_albedo: np.ndarray, albedo: np.ndarray, floor: float) -> float:
    """Fraction of pixel channels where max(albedo, floor) differs from max(footprint, floor) by > MISMATCH."""
    ratio = np.maximum(albedo, floor) / np.maximum(footprint_albedo, floor)
    return float(np.mean(np.abs(ratio - 1.0) > MISMATCH))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="results folder holding renders/<scene>")
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--scenes", nargs="+", default=None, help="scene ids (default: the validation scenes)")
    args = parser.parse_args()
    cfg = load_config(args.config)
    scenes = args.scenes or training_split(cfg)[1]
    if any(scene.startswith("test_") for scene in scenes):
        parser.error("test scenes are for the evaluation only: pick validation or training scenes")
    floor = RAEConfig().albedo_floor
    print(f"oracle PSNR (dB, mean per frame) of re-modulating the exact illumination by an albedo; "
          f"floor {floor}; 'aliased' = pixel channels with |a_x / a_bar - 1| > {MISMATCH:.0%}")
    rows = []
    for scene in scenes:
        clip = load_clip(args.results / "renders" / scene, buffers=("albedo",), reference=True)
        layers = clip.samples["albedo"]                                   # (T, S, 3, H, W)
        if layers.shape[1] < 2:
            raise SystemExit(f"{scene}: needs >= 2 albedo layers, has {layers.shape[1]}")
        if "albedo" not in clip.gbuffer:
            raise SystemExit(f"{scene}: no G-buffer albedo (noisy format version < 2); re-render it")
        reference = clip.reference["radiance"]
        footprint = layers[:, 1:].mean(axis=1)
        line = [scene]
        half = 1 + (layers.shape[1] - 1) // 2
        candidates = (("G-buffer centre", footprint, clip.gbuffer["albedo"]),
                      ("1-spp sample", footprint, layers[:, 0]),
                      ("control: half vs half", layers[:, 1:half].mean(axis=1), layers[:, half:].mean(axis=1)))
        for name, estimate, albedo in candidates:
            out = oracle(reference, estimate, albedo, floor)
            score = float(np.mean([psnr(o, r) for o, r in zip(out, reference)]))
            line.append((name, score, mismatch_fraction(estimate, albedo, floor)))
        rows.append(line)
        print(f"{scene} ({layers.shape[1] - 1} layers for a_bar): " + "; ".join(
            f"{name} {score:.2f} dB, aliased {frac:.1%}" for name, score, frac in line[1:]), flush=True)
    if len(rows) > 1:
        means = np.mean([[entry[1] for entry in row[1:]] for row in rows], axis=0)
        print(f"mean over {len(rows)} scenes: " + "; ".join(
            f"{entry[0]} {mean:.2f} dB" for entry, mean in zip(rows[0][1:], means)))


if __name__ == "__main__":
    main()
