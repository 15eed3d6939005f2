"""Per-sample rendering cost versus Mitsuba's built-in ``path`` + ``aov`` integrators, side by side.

Renders the same scene, resolution and total spp three ways in one process and prints times,
samples/s and ratios:
  * ours: ``render_sample_layers`` -- S independent 1-spp layers with every feature buffer,
    converted to numpy (what ``render-noisy`` does per frame);
  * path+aov: one ``mi.render`` of Mitsuba's ``aov`` integrator (albedo, shading normal, depth,
    position) wrapping ``path`` at S spp;
  * path: Mitsuba's ``path`` alone at S spp;
  * with ``--extra-radiance E`` (default: the config's ``render.extra_radiance_spp``): ours with E more
    radiance-only layers (what adaptive sampling reads, issue 12 §1), its time over ours without them, and
    the size of one frame's noisy EXR written both ways by the dataset writer.
Each measurement is the median of ``--repeats`` runs after a warm-up (kernel compilation excluded).

Usage: python benchmarks/render_speed.py [--config config/config.yaml] [--scene train_000] [--spp 8]
                                       [--extra-radiance 24]
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


def _frame_bytes(scene, gbuffer: dict, spp: int, extra: int, folder: Path) -> int:
    """Bytes of one noisy frame EXR (sample layers, the frame's G-buffer, zero motion) as render-noisy writes it."""
    from scenegen.channels import noisy_channels, pixel_channels
    from scenegen.dataset import write_frame
    from scenegen.render import NonFiniteCounter, render_sample_layers

    samples = render_sample_layers(scene, n_layers=spp, n_radiance_only=extra, seed=1, counter=NonFiniteCounter())
    channels, half = noisy_channels(samples)
    height, width = samples["radiance"].shape[-2:]
    pixel, pixel_half = pixel_channels(np.zeros((2, height, width), np.float32), np.ones((1, height, width), bool),
                                       gbuffer)
    channels.update(pixel)
    path = folder / f"frame_extra{extra}.exr"
    write_frame(path, channels, {"spp": spp, "extra_radiance_spp": extra}, half=half | pixel_half)
    return path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--scene", default="train_000")
    parser.add_argument("--spp", type=int, default=None, help="total spp (default: the config's render.spp)")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--extra-radiance", type=int, default=None,
                        help="radiance-only layers beside the full ones (default: render.extra_radiance_spp; 0: skip)")
    args = parser.parse_args()

    from scenegen.config import load_config
    from scenegen.jobs import run_generate
    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import (NonFiniteCounter, RenderSettings, load_frame_scene, render_gbuffer,
                                 render_sample_layers)

    cfg = load_config(args.config)
    settings = RenderSettings.from_config(cfg["render"])
    spp = args.spp or settings.spp
    extra = settings.extra_radiance_spp if args.extra_radiance is None else args.extra_radiance
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

        def ours_extra() -> None:
            render_sample_layers(scene, n_layers=spp, n_radiance_only=extra, seed=1, counter=NonFiniteCounter())

        t_ours = _median_time(ours, args.repeats)
        t_aov = _median_time(lambda: builtin(aov), args.repeats)
        t_path = _median_time(lambda: builtin(path), args.repeats)
        t_extra = _median_time(ours_extra, args.repeats) if extra else None
        gbuffer = render_gbuffer(manifest, scene_dir, args.frame, settings, scene=scene) if extra else {}
        sizes = {n: _frame_bytes(scene, gbuffer, spp, n, Path(tmp)) for n in ((0, extra) if extra else ())}

    samples = pixels * spp
    print(f"scene {args.scene} frame {args.frame}, {settings.width}x{settings.height}, {spp} spp, "
          f"max_depth {settings.max_depth}, variant {variant}")
    for name, seconds in (("ours (per-sample layers, all buffers)", t_ours), ("path+aov", t_aov), ("path", t_path)):
        print(f"  {name:40s} {seconds * 1e3:9.1f} ms  {samples / seconds / 1e6:7.2f} M samples/s")
    print(f"ratio ours / (path+aov) = {t_ours / t_aov:.2f}  (target <= 1.5)")
    print(f"ratio ours / path       = {t_ours / t_path:.2f}")
    if extra:
        print(f"  {f'ours + {extra} radiance-only layers':40s} {t_extra * 1e3:9.1f} ms  "
              f"{pixels * (spp + extra) / t_extra / 1e6:7.2f} M samples/s")
        print(f"ratio (ours + {extra} radiance-only) / ours = {t_extra / t_ours:.2f}  "
              f"(sample count ratio {(spp + extra) / spp:.2f})")
        print(f"noisy EXR per frame (pixel buffers included): {sizes[0] / 2**20:.2f} MiB without, "
              f"{sizes[extra] / 2**20:.2f} MiB with the {extra} radiance-only layers "
              f"(x{sizes[extra] / sizes[0]:.2f})")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
