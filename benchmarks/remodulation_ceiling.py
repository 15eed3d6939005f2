"""What re-modulating by a per-pixel albedo costs at best: the PSNR of an oracle that knows the exact untextured
illumination and multiplies it back by a given albedo, as the demodulating RAE does (Chaitanya et al. 2017, §3.2).

The reference pixel integrates radiance over the pixel footprint, L_ref = mean over the footprint of albedo x
illumination. A method that predicts the illumination E and re-modulates by a single albedo a_x per pixel can at
best output E * a_x with E = L_ref / a_bar, a_bar the footprint's mean of the same albedo. Where a_x differs from
a_bar (texture and object edges inside a pixel) that output is wrong however well E is predicted. This script
prints, per scene, the mean per-frame PSNR (the evaluation's ``denoisers.metrics.psnr``) of

    oracle_x = L_ref / max(a_bar, floor) * max(a_x, floor)

against L_ref, and the fraction of pixel channels where |a_x / a_bar - 1| > 10 %, for two remodulators:

* the pixel-centre G-buffer albedo (method ``rae``): the primary hit's own albedo through the pixel centre, as
  stored in the noisy frame; a_bar = the same G-buffer albedo averaged over ``--footprint-spp`` jittered primary
  rays per pixel (rendered here with the G-buffer integrator).
* the first stored sample's albedo (method ``rae_samples`` at 1 spp): the per-sample feature albedo (that of the
  first non-specular vertex, through mirrors and glass); a_bar = the per-sample albedo averaged over
  ``--footprint-spp`` jittered samples (rendered here with the feature integrator, samples mode).

Both renders use the scene's own render settings (box-filtered film) and seeds of their own. ``floor`` is the
RAE's ``albedo_floor`` (its divisor's lower bound). A colour-only method has no such ceiling. Refuses test scenes.

Usage: python benchmarks/remodulation_ceiling.py --results results [--config config/config.yaml]
           [--scenes train_024 train_025 ...] [--footprint-spp 256]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from denoisers.metrics import psnr  # noqa: E402
from denoisers.nets.rae import RAEConfig  # noqa: E402
from denoisers.training.models import training_split  # noqa: E402
from scenegen.catalog import scene_render_config
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


def rendered_footprint_albedo(cfg: dict, scene_dir: Path, frames: list[int], spp: int, mode: str) -> np.ndarray:
    """(T, 3, H, W) mean albedo of ``spp`` jittered camera rays per pixel of ``frames``: the G-buffer albedo (the
    primary hit's own) with ``mode="gbuffer"``, the per-sample feature albedo with ``mode="samples"``."""
    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import RenderSettings, gbuffer_albedo_mean, load_frame_scene, split_channels

    if mode not in ("gbuffer", "samples"):
        raise ValueError(f"mode must be 'gbuffer' or 'samples', got {mode!r}")
    settings = RenderSettings.from_config(scene_render_config(cfg, scene_dir.name))
    init_mitsuba(settings.variant)
    import mitsuba as mi

    from scenegen.integrator import SAMPLE_AOVS     # needs the variant set
    manifest = json.loads((scene_dir / "manifest.json").read_text())
    gbuffer_integrator = mi.load_dict({"type": "mcdn_features", "mode": "gbuffer"})   # as render_gbuffer's
    out = []
    for frame in frames:
        scene = load_frame_scene(manifest, scene_dir, frame, settings, mode="samples")
        seed = 1_000_003 + frame
        if mode == "gbuffer":
            out.append(gbuffer_albedo_mean(scene, gbuffer_integrator, spp=spp, seed=seed))
        else:
            image = np.array(mi.render(scene, spp=spp, seed=seed), np.float32)
            out.append(split_channels(image, [("radiance", 3), *SAMPLE_AOVS])["albedo"])
    return np.stack(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="results folder holding renders/<scene>")
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--scenes", nargs="+", default=None, help="scene ids (default: the validation scenes)")
    parser.add_argument("--footprint-spp", type=int, default=256,
                        help="jittered camera rays per pixel for each footprint mean a_bar")
    args = parser.parse_args()
    cfg = load_config(args.config)
    scenes = args.scenes or training_split(cfg)[1]
    if any(scene.startswith("test_") for scene in scenes):
        parser.error("test scenes are for the evaluation only: pick validation or training scenes")
    floor = RAEConfig().albedo_floor
    print(f"oracle PSNR (dB, mean per frame) of re-modulating the exact illumination by an albedo; floor {floor}; "
          f"a_bar from {args.footprint_spp} jittered rays per pixel; 'aliased' = pixel channels with "
          f"|a_x / a_bar - 1| > {MISMATCH:.0%}")
    rows = []
    for scene in scenes:
        clip = load_clip(args.results / "renders" / scene, buffers=("albedo",), reference=True)
        if "albedo" not in clip.gbuffer:
            raise SystemExit(f"{scene}: no G-buffer albedo (noisy format version < 2); re-render it")
        reference = clip.reference["radiance"]
        scene_dir = args.results / "scenes" / scene
        line = []
        stored_spp = int(clip.meta[0].get("gbuffer_albedo_spp", 1))     # render.gbuffer_albedo_spp of the renders
        gbuffer_name = "G-buffer centre" if stored_spp == 1 else f"G-buffer ({stored_spp} rays)"
        for name, mode, albedo in ((gbuffer_name, "gbuffer", clip.gbuffer["albedo"]),
                                   ("1-spp sample", "samples", clip.samples["albedo"][:, 0])):
            footprint = rendered_footprint_albedo(cfg, scene_dir, clip.frames, args.footprint_spp, mode)
            if footprint.shape != reference.shape:
                raise SystemExit(f"{scene}: rendered albedo {footprint.shape} != reference {reference.shape}")
            out = oracle(reference, footprint, albedo, floor)
            score = float(np.mean([psnr(o, r) for o, r in zip(out, reference)]))
            line.append((name, score, mismatch_fraction(footprint, albedo, floor)))
        rows.append(line)
        print(f"{scene}: " + "; ".join(f"{name} {score:.2f} dB, aliased {frac:.1%}" for name, score, frac in line),
              flush=True)
    if len(rows) > 1:
        means = np.mean([[entry[1] for entry in row] for row in rows], axis=0)
        print(f"mean over {len(rows)} scenes: " + "; ".join(
            f"{entry[0]} {mean:.2f} dB" for entry, mean in zip(rows[0], means)))

if __name__ == "__main__":
    main()
