"""The timing job: every evaluated (row, spp) timed one after another on the same frames and threads.

Timings taken inside the denoise jobs vary with whatever else the machine runs at the time (two
identical smoke runs gave OIDN 28.9 vs 14.1 ms/frame), so speed comparisons come from one job that
runs alone (rule time_methods takes every core): for each runnable row and spp it loads the first
``frames`` frames of one evaluated scene, runs the method over them once as a warm-up, then
``repeats`` more times, each pass from a reset state, with ``threads`` torch threads. A pass's time is
the median of its per-frame seconds, the first frame excluded (it pays one-off costs of temporal
state); a row's time is the median over passes, its spread the smallest and largest pass.

In the same job, the renderer's rate is measured with the same thread count: the scene's first frame
rendered as ``render.spp`` full-feature 1-spp layers (the noisy data every method reads), once as a
warm-up (kernel compilation), then ``repeats`` times; samples/s = layers x pixels / seconds. The
equal-time view reads this rate, so rows and renderer are compared at equal threads.
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

TIMING_SCHEMA = 1


def pass_seconds(per_frame: Sequence[float]) -> float:
    """Time of one pass: the median of its per-frame seconds without the first frame (kept when alone)."""
    timed = list(per_frame[1:]) if len(per_frame) > 1 else list(per_frame)
    return float(statistics.median(timed))


def summarise_passes(passes: Sequence[float], pixels: int) -> dict[str, Any]:
    """Median and range over passes (seconds per frame) -> ms/frame, Mpix/s and their spread."""
    ms = np.asarray(passes, dtype=np.float64) * 1e3
    median = float(np.median(ms))
    return {"repeats": len(passes), "pass_ms_per_frame": [float(v) for v in ms], "ms_per_frame": median,
            "ms_per_frame_min": float(ms.min()), "ms_per_frame_max": float(ms.max()),
            "spread": float((ms.max() - ms.min()) / median) if median > 0 else float("inf"),
            "mpix_per_s": pixels / (median / 1e3) / 1e6 if median > 0 else float("inf")}


def time_run(cfg: dict, method_id: str, spp: int, render_dir: Path, *, frames: int, repeats: int, threads: int,
             results: Path | str) -> dict[str, Any]:
    """Time one (row, spp) on the first ``frames`` frames of ``render_dir``: warm-up pass, then ``repeats``."""
    from denoisers.evaluate import _frames, _load_method_clip, _prepare, run_method

    if repeats < 1 or frames < 1:
        raise ValueError(f"timing needs repeats >= 1 and frames >= 1, got {repeats}, {frames}")
    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=False)
    frame_list = _frames(clip, method, layers)[:frames]
    height, width = frame_list[0].height, frame_list[0].width
    run_method(method, frame_list, threads)        # warm-up: caches, native kernels, allocator
    passes = [pass_seconds(run_method(method, frame_list, threads).seconds) for _ in range(repeats)]
    return {"method_id": spec.id, "method": spec.method, "spp": int(spp), "threads": int(threads),
            "frames": [int(t) for t in clip.frames[:frames]], "width": int(width), "height": int(height),
            **summarise_passes(passes, width * height)}


def render_rate(cfg: dict, manifest: dict, scene_dir: Path, *, repeats: int, threads: int) -> dict[str, Any]:
    """samples/s of the noisy render (render.spp full-feature layers of frame 0) with ``threads`` Dr.Jit threads."""
    import drjit as dr

    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_sample_layers

    settings = RenderSettings.from_config(cfg["render"])
    init_mitsuba(settings.variant)
    dr.set_thread_count(max(1, int(threads)))
    scene = load_frame_scene(manifest, Path(scene_dir), 0, settings)

    def render(seed: int) -> float:
        start = time.perf_counter()
        render_sample_layers(scene, n_layers=settings.spp, n_radiance_only=0, seed=seed, counter=NonFiniteCounter())
        return time.perf_counter() - start

    render(0)                                        # warm-up: kernel compilation
    seconds = [render(1 + k) for k in range(repeats)]
    samples = settings.spp * settings.width * settings.height
    median = float(statistics.median(seconds))
    return {"threads": int(threads), "layers": settings.spp, "pixels": settings.width * settings.height,
            "repeats": repeats, "seconds": seconds, "samples_per_s": samples / median,
            "samples_per_s_min": samples / max(seconds), "samples_per_s_max": samples / min(seconds)}


def time_methods(cfg: dict, scene: str, render_dir: Path, scene_dir: Path, runs: Sequence[tuple[str, int]], *,
                 frames: int, repeats: int, threads: int, results: Path | str) -> dict[str, Any]:
    """The timing job's record: every (row id, spp) of ``runs`` in order, then the renderer's rate."""
    import json

    from denoisers.provenance import provenance

    manifest = json.loads((Path(scene_dir) / "manifest.json").read_text())
    rows = [time_run(cfg, method_id, spp, render_dir, frames=frames, repeats=repeats, threads=threads,
                     results=results) for method_id, spp in runs]
    return {"schema": TIMING_SCHEMA, "scene": scene, "frames": frames, "repeats": repeats, "threads": threads,
            "rows": rows, "renderer": render_rate(cfg, manifest, scene_dir, repeats=repeats, threads=threads),
            "provenance": provenance({"timing": threads})}
