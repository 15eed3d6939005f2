"""Reference rendering rate: Mitsuba's ``path`` against the feature integrator, side by side per scene.

``render.reference_integrator`` chooses the integrator of the reference renders (docs/default-run.md, "Measured stage
costs"). For each scene of a scenes folder (``--scenes``: results/<experiment>/scenes) this renders one
frame's reference (two halves, ``render_reference_frame``, the config's ``reference_batch_spp``) with both
integrators, alternating which goes first per round, after one small warm-up render each (kernel
compilation excluded), and prints the seconds, samples/s and the ratio path rate / feature rate; then
the median and range of the ratio and of the path rate over the scenes. ``--json`` writes them for
``benchmarks/dag_budget.py --reference-speed``.

Usage: python benchmarks/reference_speed.py --scenes results/data-scale/scenes [--scene train_000 ...]
           [--config config/config.yaml] [--spp 256] [--frame 1] [--repeats 1] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--scenes", type=Path, required=True, help="folder of generated scenes ({scene}/manifest.json)")
    parser.add_argument("--scene", nargs="*", default=None, help="scene ids (default: every scene in --scenes)")
    parser.add_argument("--spp", type=int, default=256, help="reference spp per frame (even)")
    parser.add_argument("--frame", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=1, help="rounds per scene (median)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.spp < 2 or args.spp % 2:
        parser.error(f"--spp must be even and >= 2, got {args.spp}")

    from scenegen.config import load_config
    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_reference_frame

    cfg = load_config(args.config)
    settings = RenderSettings.from_config(cfg["render"])
    variant = init_mitsuba(settings.variant)
    scenes = args.scene or sorted(p.parent.name for p in args.scenes.glob("*/manifest.json"))
    if not scenes:
        raise SystemExit(f"no scenes in {args.scenes}")
    half = args.spp // 2
    batches = -(-half // settings.reference_batch_spp)
    print(f"{len(scenes)} scenes, frame {args.frame}, {settings.width}x{settings.height}, {args.spp} spp in passes "
          f"of {settings.reference_batch_spp}, max_depth {settings.max_depth}, variant {variant}")
    rows = []
    for scene_id in scenes:
        scene_dir = args.scenes / scene_id
        manifest = json.loads((scene_dir / "manifest.json").read_text())
        loaded = {mode: load_frame_scene(manifest, scene_dir, args.frame, settings, mode=mode)
                  for mode in ("path", "samples")}

        def render(mode: str, spp: int, seed: int) -> float:
            start = time.perf_counter()
            seeds = ([seed + b for b in range(batches)], [seed + batches + b for b in range(batches)])
            render_reference_frame(loaded[mode], spp=spp, batch_spp=settings.reference_batch_spp,
                                   seeds_half=seeds, counter=NonFiniteCounter(), features=mode == "samples")
            return time.perf_counter() - start

        for mode in loaded:
            render(mode, 2, 0)   # warm-up
        times: dict[str, list[float]] = {"path": [], "samples": []}
        for round_ in range(args.repeats):
            order = ("path", "samples") if round_ % 2 == 0 else ("samples", "path")
            for mode in order:
                times[mode].append(render(mode, args.spp, 1000 * round_ + 1))
        seconds = {mode: statistics.median(t) for mode, t in times.items()}
        samples = args.spp * settings.width * settings.height
        row = {"scene": scene_id, "path_s": seconds["path"], "features_s": seconds["samples"],
               "path_samples_per_s": samples / seconds["path"],
               "features_samples_per_s": samples / seconds["samples"],
               "path_rate_ratio": seconds["samples"] / seconds["path"]}
        rows.append(row)
        print(f"  {scene_id}: path {row['path_s']:6.1f} s ({row['path_samples_per_s'] / 1e6:.3f} M/s), features "
              f"{row['features_s']:6.1f} s ({row['features_samples_per_s'] / 1e6:.3f} M/s), "
              f"path rate / features rate {row['path_rate_ratio']:.2f}", flush=True)
    ratios = [r["path_rate_ratio"] for r in rows]
    rates = [r["path_samples_per_s"] for r in rows]
    summary = {"scenes": rows, "spp": args.spp, "frame": args.frame, "variant": variant,
               "median_path_rate_ratio": statistics.median(ratios),
               "median_path_samples_per_s": statistics.median(rates)}
    print(f"path rate / features rate: median {summary['median_path_rate_ratio']:.2f} "
          f"(range {min(ratios):.2f}-{max(ratios):.2f}); path median {summary['median_path_samples_per_s'] / 1e6:.3f} "
          f"M samples/s (range {min(rates) / 1e6:.3f}-{max(rates) / 1e6:.3f})")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
