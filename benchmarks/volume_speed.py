"""Volumetric rendering rate: our per-sample feature integrator against Mitsuba's ``volpath``, side by side.

Issue 14 asks the noisy renders of the volumetric clips to cost at most 1.5x ``volpath`` for the same scene and
total spp. For each field kind and a few seeds this draws a clip (scenegen.volumes.scenes, frame 0), then renders
``--spp`` samples per pixel both ways, alternating which goes first per round, after one warm-up render each
(kernel compilation excluded):

* ours: ``--spp`` independent 1-spp layers of ``mcdn_volpath_features`` in one wavefront with every feature
  (scenegen.render.sample_wavefront, as rule render_noisy does);
* volpath: ``mi.render(scene, spp=--spp)`` with Mitsuba's ``volpath`` (same depths), radiance only.

It prints seconds per frame and the ratio ours / volpath per clip (median over rounds), then the median and range
of the ratios. A ratio measured in one process, interleaved, is meaningful on a loaded machine; the absolute
times are not.

Usage: python benchmarks/volume_speed.py [--size 64] [--spp 8] [--rounds 3] [--seeds 0 1] [--resolution 24]
"""
from __future__ import annotations

import argparse
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=64, help="image width and height (pixels)")
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--resolution", type=int, default=24, help="voxels per axis of the field")
    parser.add_argument("--max-depth", type=int, default=8)
    args = parser.parse_args()

    from scenegen.mitsuba_env import init_mitsuba

    variant = init_mitsuba("llvm_ad_rgb")
    import drjit as dr
    import mitsuba as mi

    import scenegen.volumes.integrator  # noqa: F401 -- registers mcdn_volpath_features
    from scenegen.render import sample_wavefront
    from scenegen.volumes.scenes import FIELD_KINDS, generate_volume_clip

    print(f"variant {variant}, {args.size}x{args.size}, {args.spp} spp, {args.rounds} rounds, "
          f"{dr.thread_count()} threads")
    ratios = []
    for kind in FIELD_KINDS:
        for seed in args.seeds:
            clip = generate_volume_clip(seed, "camera", 2, kind, resolution=args.resolution)
            scenes = {}
            for name, integrator in (("ours", "mcdn_volpath_features"), ("volpath", "volpath")):
                scene = clip.scene_dict(0, width=args.size, height=args.size, spp=args.spp)
                scene["integrator"] = {"type": integrator, "max_depth": args.max_depth, "rr_depth": 5}
                scenes[name] = mi.load_dict(scene)

            def run(name: str, seed_value: int) -> float:
                start = time.perf_counter()
                if name == "ours":
                    sample_wavefront(scenes[name], n_layers=args.spp, seed=seed_value)
                else:
                    image = mi.render(scenes[name], spp=args.spp, seed=seed_value)
                    dr.eval(image)
                    dr.sync_thread()
                return time.perf_counter() - start

            run("ours", 999)
            run("volpath", 999)
            times: dict[str, list[float]] = {"ours": [], "volpath": []}
            for round_index in range(args.rounds):
                order = ("ours", "volpath") if round_index % 2 == 0 else ("volpath", "ours")
                for name in order:
                    times[name].append(run(name, round_index))
            ours, volpath = statistics.median(times["ours"]), statistics.median(times["volpath"])
            ratios.append(ours / volpath)
            print(f"{kind:12s} seed {seed} ({clip.setting}): ours {ours:7.3f} s, volpath {volpath:7.3f} s, "
                  f"ratio {ours / volpath:.2f}")
    print(f"ratio ours / volpath: median {statistics.median(ratios):.2f}, range {min(ratios):.2f}-{max(ratios):.2f} "
          f"over {len(ratios)} clips (target <= 1.5)")


if __name__ == "__main__":
    main()
