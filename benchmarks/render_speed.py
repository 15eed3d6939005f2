"""Per-sample rendering cost versus Mitsuba's built-in ``path`` + ``aov`` integrators, side by side.

Renders the same scene, resolution and total spp three ways in one process and prints times,
samples/s and ratios:
  * ours: ``render_sample_layers`` -- S independent 1-spp layers with every feature buffer,
    converted to numpy (what ``render-noisy`` does per frame);
  * path+aov: one ``mi.render`` of Mitsuba's ``aov`` integrator (albedo, shading normal, depth,
    position) wrapping ``path`` at S spp;
  * path: Mitsuba's ``path`` alone at S spp.
Each measurement is the median of ``--repeats`` runs after a warm-up (kernel compilation excluded).

Usage: python benchmarks/render_speed.py [--config config/config.yaml] [--scene train_000] [--spp 8]
"""
from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up: JIT compilation and scene upload
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--scene", default="train_000")
    parser.add_argument("--spp", type=int, default=None, help="total spp (default: the config's render.spp)")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    from scenegen.config import load_config
    from scenegen.jobs import run_generate
    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_sample_layers

    cfg = load_config(args.config)
    settings = RenderSettings.from_config(cfg["render"])
    spp = args.spp or settings.spp
    variant = init_mitsuba(settings.variant)
    import mitsuba as mi

    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = Path(tmp) / args.scene
        manifest = run_generate(cfg, args.scene, scene_dir)
        scene = load_frame_scene(manifest, scene_dir, args.frame, settings)
        pixels = settings.width * settings.height

        def ours() -> None:
            render_sample_layers(scene, n_layers=spp, n_radiance_only=0, seed=1, counter=NonFiniteCounter())

        aov = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth,pp:position",
                            "integrator": {"type": "path", "max_depth": settings.max_depth,
                                           "rr_depth": settings.rr_depth}})
        path = mi.load_dict({"type": "path", "max_depth": settings.max_depth, "rr_depth": settings.rr_depth})

        def builtin(integrator) -> None:
            np.array(mi.render(scene, spp=spp, seed=1, integrator=integrator))

        t_ours = _median_time(ours, args.repeats)
        t_aov = _median_time(lambda: builtin(aov), args.repeats)
        t_path = _median_time(lambda: builtin(path), args.repeats)

    samples = pixels * spp
    print(f"scene {args.scene} frame {args.frame}, {settings.width}x{settings.height}, {spp} spp, "
          f"max_depth {settings.max_depth}, variant {variant}")
    for name, seconds in (("ours (per-sample layers, all buffers)", t_ours), ("path+aov", t_aov), ("path", t_path)):
        print(f"  {name:40s} {seconds * 1e3:9.1f} ms  {samples / seconds / 1e6:7.2f} M samples/s")
    print(f"ratio ours / (path+aov) = {t_ours / t_aov:.2f}  (target <= 1.5)")
    print(f"ratio ours / path       = {t_ours / t_path:.2f}")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
