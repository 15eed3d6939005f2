"""Does a trained denoiser work on whole frames as well as on its training crops? (denoisers/crop_check.py)

Each frame is denoised whole and as separate crop-sized windows; the same windows of both runs are scored
against the reference: gap = whole-frame run - window run (dB). A gap well below 0 means the model learned
its training crops' borders. Run it on validation scenes (never choose anything on test scenes).

    python benchmarks/crop_consistency.py --checkpoint results/isik2021/models/*/best.pt \
        --render-dir results/isik2021/renders/train_024 results/isik2021/renders/train_025 --spp 4 --crop 64
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from denoisers import crop_check, registry
from scenegen.dataset import load_clip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, nargs="+", required=True, help="best.pt of each model")
    parser.add_argument("--method", default="afn", help="registered method that reads the checkpoint")
    parser.add_argument("--render-dir", type=Path, nargs="+", required=True, help="rendered validation scenes")
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--crop", type=int, default=64, help="the models' training crop (pixels)")
    parser.add_argument("--frames", type=int, default=crop_check.FRAMES_PER_SCENE, help="frames per scene")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    print(f"crop {args.crop}, {args.spp} spp, {args.frames} frames per scene; gap = whole-frame run - window run "
          f"(dB, mean over windows; worst = the worst window)")
    print(f"{'model':<32} {'scene':<20} {'whole':>7} {'window':>7} {'gap':>7} {'worst':>7}")
    for checkpoint in args.checkpoint:
        method = registry.build(args.method, {"checkpoint": str(checkpoint)})
        layers = args.spp * method.samples_factor
        clips = [load_clip(d, buffers=method.info.inputs, spp=layers) for d in args.render_dir]
        result = crop_check.check_method(method, clips, args.spp, args.crop, args.frames)
        for scene, s in result["scenes"].items():
            print(f"{checkpoint.parent.name:<32} {scene:<20} {s['whole_psnr']:7.2f} {s['window_psnr']:7.2f} "
                  f"{s['gap_db']:+7.2f} {s['worst_window_gap_db']:+7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
