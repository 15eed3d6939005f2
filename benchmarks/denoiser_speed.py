"""Speed of the non-trainable denoisers side by side, and how their time scales with the pixel count.

One process, one synthetic input per resolution (a procedural scene of boxes and a sphere-like bump
with per-sample multiplicative noise, camera panning by 0.5 px per frame, every buffer a method may
declare). Methods run interleaved, one frame each per round, so a change in machine load hits all
of them alike; temporal methods see a continuous stream (reset once, then frame after frame).
Per method and resolution: median seconds per ``denoise()`` call over ``--repeats`` rounds after
``--warmup`` rounds; printed as ms/frame, Mpix/s and the ratio to OIDN at ``--size``; then the time at
every ``--sizes`` resolution and the slope of log(time) against log(pixels) (1 = linear scaling).
The native kernels of ``denoisers.native`` (EAW, SVGF) are built before any timing; the "path" column
says which implementation each method ran (native / torch; "-" for methods without a choice).
``MCDN_NATIVE=0`` times the torch implementations instead.

Usage: python benchmarks/denoiser_speed.py [--methods eaw svgf rls wrls oidn] [--size 256]
           [--sizes 128 256 512] [--spp 2] [--repeats 7] [--warmup 2] [--threads 1]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from denoisers import native, registry
from denoisers.registry import Frame

DEFAULT_METHODS = ("eaw", "svgf", "rls", "wrls", "oidn")
TARGET_SPEEDUP = 5.0            # issue 3, section 8: EAW, SVGF and wRLS at least 5x faster than OIDN
TARGET_METHODS = ("eaw", "svgf", "wrls")


def synthetic_frames(size: int, spp: int, count: int, seed: int = 0) -> list[Frame]:
    """``count`` consecutive frames of a size x size synthetic clip with every per-sample and per-pixel buffer."""
    rng = np.random.default_rng(seed)
    frames = []
    for t in range(count):
        shift = 0.5 * t  # camera pans right by half a pixel per frame: content moves left
        y, x = np.mgrid[0:size, 0:size].astype(np.float32)
        u, v = (x + shift) / size, y / size
        boxes = ((np.floor(u * 6) + np.floor(v * 6)) % 2).astype(np.float32)
        bump = np.clip(1.0 - ((u - 0.6) ** 2 + (v - 0.5) ** 2) / 0.06, 0.0, 1.0)
        height = np.sqrt(bump)
        gy, gx = np.gradient(height * 4.0)
        normal = np.stack([-gx, -gy, np.ones_like(gx)])
        normal /= np.linalg.norm(normal, axis=0, keepdims=True)
        albedo = np.stack([0.3 + 0.5 * boxes, 0.4 + 0.2 * bump, 0.6 - 0.3 * boxes]).astype(np.float32)
        shading = np.clip(normal[2] * 0.8 + 0.2, 0.0, None)
        depth = (3.0 - height)[None].astype(np.float32)
        position = np.stack([u * 4.0, v * 4.0, -depth[0]]).astype(np.float32)
        clean = albedo * shading[None] * 2.0
        noise = rng.exponential(1.0, (spp, 1, size, size)).astype(np.float32)  # heavy-tailed like MC samples
        radiance = clean[None] * noise

        def per_sample(array: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(np.repeat(array[None], spp, 0), dtype=np.float32))

        samples = {
            "radiance": torch.from_numpy(radiance), "diffuse": torch.from_numpy(radiance),
            "specular": torch.zeros_like(torch.from_numpy(radiance)), "albedo": per_sample(albedo),
            "normal": per_sample(normal), "depth": per_sample(depth), "roughness": per_sample(np.ones_like(depth)),
            "flags": per_sample(np.zeros((4, size, size))), "position": per_sample(position),
        }
        pixel = {
            "motion": torch.from_numpy(np.stack([np.full_like(x, 0.5), np.zeros_like(x)])),
            "valid": torch.full((1, size, size), float(t > 0)),
            "gbuffer.position": torch.from_numpy(position), "gbuffer.normal": torch.from_numpy(normal.astype(np.float32)),
            "gbuffer.depth": torch.from_numpy(depth), "gbuffer.object": torch.zeros(1, size, size),
        }
        frames.append(Frame(samples=samples, pixel=pixel, index=t, camera_cut=t == 0))
    return frames


def only_declared(frame: Frame, info: registry.MethodInfo) -> Frame:
    """The frame restricted to the buffers a method declares (as the evaluation hands it over)."""
    return Frame(samples={b: frame.samples[b] for b in info.inputs},
                 pixel={b: frame.pixel[b] for b in info.pixel_inputs}, index=frame.index, camera_cut=frame.camera_cut)


def time_methods(names: list[str], size: int, spp: int, repeats: int, warmup: int
                 ) -> tuple[dict[str, float], dict[str, str]]:
    """Median seconds per denoise() call of each method at size x size, interleaved round by round, and
    the implementation each method used ("native", "torch" or "-")."""
    frames = synthetic_frames(size, spp, warmup + repeats)
    methods = {name: registry.build(name) for name in names}
    inputs = {name: [only_declared(f, method.info) for f in frames] for name, method in methods.items()}
    for method in methods.values():
        method.reset()
    seconds: dict[str, list[float]] = {name: [] for name in names}
    with torch.no_grad():
        for step in range(warmup + repeats):
            for name, method in methods.items():
                start = time.perf_counter()
                method.denoise(inputs[name][step])
                elapsed = time.perf_counter() - start
                if step >= warmup:
                    seconds[name].append(elapsed)
    paths = {name: getattr(method, "backend", "-") for name, method in methods.items()}
    return {name: statistics.median(values) for name, values in seconds.items()}, paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    parser.add_argument("--size", type=int, default=256, help="resolution of the side-by-side comparison")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="resolutions of the scaling fit")
    parser.add_argument("--spp", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the workflow's evaluation.threads)")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    known = registry.available()
    names = [name for name in args.methods if name in known]
    for name in sorted(set(args.methods) - set(names)):
        print(f"skipping {name!r}: not registered (registered: {', '.join(known)})")
    sizes = sorted(set(args.sizes) | {args.size})
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.spp} spp, median of "
          f"{args.repeats} frames after {args.warmup} warm-up frames, methods interleaved")
    # Build (or load from torch's cache) the native kernels now, so that no build lands in a timed call.
    start = time.perf_counter()
    kernels = native.load()
    state = ("disabled (MCDN_NATIVE=0)" if not native.enabled() else
             "unavailable, torch fallback" if kernels is None else f"ready in {time.perf_counter() - start:.1f} s")
    print(f"native kernels: {state}\n")
    timings, paths = {}, {}
    for size in sizes:
        timings[size], paths[size] = time_methods(names, size, args.spp, args.repeats, args.warmup)

    at_size = timings[args.size]
    pixels = args.size * args.size
    oidn = at_size.get("oidn")
    print(f"side by side at {args.size}x{args.size}:")
    print(f"  {'method':8s} {'path':>6s} {'ms/frame':>10s} {'Mpix/s':>9s} {'x faster than OIDN':>20s}")
    for name in names:
        ratio = f"{oidn / at_size[name]:.2f}" if oidn else "n/a"
        flag = ""
        if oidn and name in TARGET_METHODS:
            flag = "  (target >= 5x: " + ("met)" if oidn / at_size[name] >= TARGET_SPEEDUP else "NOT met)")
        print(f"  {name:8s} {paths[args.size][name]:>6s} {at_size[name] * 1e3:10.2f} "
              f"{pixels / at_size[name] / 1e6:9.3f} {ratio:>20s}{flag}")

    print("\nscaling with pixel count (ms/frame; slope of log time vs log pixels, 1 = linear):")
    print("  " + f"{'method':8s}" + "".join(f"{f'{s}x{s}':>11s}" for s in sizes) + f"{'slope':>8s}")
    log_pixels = np.log([s * s for s in sizes])
    for name in names:
        times = [timings[s][name] for s in sizes]
        slope = np.polyfit(log_pixels, np.log(times), 1)[0] if len(sizes) > 1 else float("nan")
        print("  " + f"{name:8s}" + "".join(f"{t * 1e3:11.2f}" for t in times) + f"{slope:8.2f}")


if __name__ == "__main__":
    main()
