"""The timing job (rule time_methods): every evaluated (row, spp) timed on the same frames and threads
(the configured rows and the capacity ablations' variants, :func:`timed_runs`).

Timings taken inside the denoise jobs vary with whatever else the machine runs at the time (two
identical smoke runs gave OIDN 28.9 vs 14.1 ms/frame), so the report's speed numbers come from one job
that runs alone (the rule takes every core). It loads the first ``frames`` frames of one evaluated
scene for every (row, spp), runs each once as a warm-up, then makes ``repeats`` rounds; in each round
every (row, spp) runs one pass from a reset state, one after another. Interleaving puts pass k of every
row in the same stretch of time, so a slow spell of the machine hits all rows of a round alike and the
per-round ratio between two rows is stable even when absolute times drift.

A pass's time is the median of its per-frame seconds, the first frame excluded (it pays one-off costs of
temporal state); a row's time is the median over rounds, its spread the smallest and largest pass.
Speed claims compare two rows by their per-round ratios (:func:`speed_ratios`).

Every round ends with a float32 sgemm (n x n x n, the faster of MKL ``torch.mm`` and oneDNN) at the same
threads, so the record says how fast the machine was while the rows ran (on this shared host one row's time
varied about 2x between runs of the same day). A row whose ``denoise()`` runs torch matrix products or
convolutions (the learned rows) gets its FLOPs per frame, counted by ``torch.utils.flop_counter`` on one
extra untimed pass (native kernels, e.g. kernel application, are not counted), and from them GFLOP/s and
the per-round fraction of that round's sgemm rate.

In the same job, the renderer's rate is measured with the same thread count for every evaluated scene
(scenes differ in cost): its first frame rendered as ``render.spp`` full-feature 1-spp layers (the noisy
data every method reads), once as a warm-up (kernel compilation), then ``repeats`` times; samples/s =
layers x pixels / median seconds. The equal-time view reads each scene's rate, so rows and renderer are
compared at equal threads.
"""
from __future__ import annotations

import json
import logging
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

TIMING_SCHEMA = 4
#: Side of the square sgemm timed in every round.
SGEMM_SIZE = 1024
#: Where the timing job writes, below the experiment folder.
TIMING_JOB_FILE = "timing/timing.json"

log = logging.getLogger(__name__)


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


@dataclass
class TimedRun:
    """One (row, spp) prepared for timing: its built method and frames (loaded once, not timed)."""

    spec: Any
    spp: int
    method: Any
    frames: list
    frame_ids: list[int]
    passes: list[float] = field(default_factory=list)     # seconds per frame, one per round
    flops_per_frame: int = 0                               # torch FLOPs of denoise() (count_flops), 0 if none

    @property
    def pixels(self) -> int:
        return int(self.frames[0].height * self.frames[0].width)

    def run_pass(self, threads: int) -> float:
        from denoisers.jobs.denoise import run_method

        return pass_seconds(run_method(self.method, self.frames, threads).seconds)

    def count_flops(self, threads: int) -> int:
        """FLOPs per frame of one extra, untimed pass (torch operators only), stored in ``flops_per_frame``."""
        from denoisers.jobs.denoise import run_method

        counter = flop_counter()
        with counter:
            run_method(self.method, self.frames, threads)
        self.flops_per_frame = int(counter.get_total_flops()) // len(self.frames)
        return self.flops_per_frame

    def record(self, threads: int, sgemm_gflops: Sequence[float] = ()) -> dict[str, Any]:
        """The row's timing; with the per-round sgemm rates, its GFLOP/s and fraction of sgemm (None without
        counted FLOPs)."""
        out = {"method_id": self.spec.id, "method": self.spec.method, "spp": int(self.spp), "threads": int(threads),
               "frames": self.frame_ids, "width": int(self.frames[0].width), "height": int(self.frames[0].height),
               **summarise_passes(self.passes, self.pixels), "gflop_per_frame": self.flops_per_frame / 1e9,
               "gflops_per_s": None, "fraction_of_sgemm": None, "fraction_of_sgemm_min": None,
               "fraction_of_sgemm_max": None}
        if self.flops_per_frame and self.passes:
            rates = [self.flops_per_frame / 1e9 / s for s in self.passes]
            out["gflops_per_s"] = float(np.median(rates))
            if len(sgemm_gflops) == len(rates):
                fractions = [r / g for r, g in zip(rates, sgemm_gflops)]   # same round
                out.update(fraction_of_sgemm=float(np.median(fractions)), fraction_of_sgemm_min=min(fractions),
                           fraction_of_sgemm_max=max(fractions))
        return out


def _fused_conv_flops(x_shape: Sequence[int], w_shape: Sequence[int], *_: Any, out_shape: Sequence[int],
                      **__: Any) -> int:
    """FLOPs of oneDNN's convolution with a fused activation: those of the plain convolution."""
    from torch.utils.flop_counter import conv_flop_count

    return conv_flop_count(list(x_shape), list(w_shape), list(out_shape))


def flop_counter() -> Any:
    """torch's FlopCounterMode, also counting the fused oneDNN convolution the RAE's inference path calls
    (``torch.ops.mkldnn._convolution_pointwise``; torch's counter knows only aten's convolutions)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    mapping = {}
    if hasattr(torch.ops.mkldnn, "_convolution_pointwise"):
        mapping[torch.ops.mkldnn._convolution_pointwise] = _fused_conv_flops
    return FlopCounterMode(display=False, custom_mapping=mapping)


def prepare_run(cfg: dict, method_id: str, spp: int, render_dir: Path, *, frames: int,
                results: Path | str) -> TimedRun:
    """Build row ``method_id`` and load the first ``frames`` frames of ``render_dir`` at ``spp``."""
    from denoisers.jobs.denoise import _frames, _load_method_clip, _prepare

    if frames < 1:
        raise ValueError(f"timing needs frames >= 1, got {frames}")
    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=False)
    frame_list = _frames(clip, method, layers)[:frames]
    return TimedRun(spec, int(spp), method, frame_list, [int(t) for t in clip.frames[:frames]])


def sgemm_probe(n: int = SGEMM_SIZE) -> Callable[[int], float]:
    """A callable(threads) -> GFLOP/s of one float32 n x n x n sgemm, the faster of MKL ``torch.mm`` and
    oneDNN (as the training-speed job measures it)."""
    import torch

    from denoisers.training.speed import gemm_timers

    timers = [t for t in gemm_timers(n) if t.key.startswith("sgemm")]

    def rate(threads: int) -> float:
        torch.set_num_threads(max(1, int(threads)))
        best = 0.0
        for timer in timers:
            start = time.perf_counter()
            timer.run()
            best = max(best, timer.flops / (time.perf_counter() - start) / 1e9)
        return best

    return rate


def time_interleaved(runs: Sequence[TimedRun], *, repeats: int, threads: int,
                     sgemm: Callable[[int], float] | None = None) -> list[float]:
    """A warm-up pass of every run (and of ``sgemm``), then ``repeats`` rounds of one pass per run (appended
    to run.passes), each round ending with one ``sgemm(threads)``; returns its GFLOP/s per round ([] without)."""
    if repeats < 1:
        raise ValueError(f"timing needs repeats >= 1, got {repeats}")
    for run in runs:
        run.run_pass(threads)                      # caches, native kernels, allocator
    if sgemm is not None:
        sgemm(threads)
    rates = []
    for round_index in range(repeats):
        for run in runs:
            run.passes.append(run.run_pass(threads))
        if sgemm is not None:
            rates.append(sgemm(threads))
        log.info("timing round %d/%d done", round_index + 1, repeats)
    return rates


def time_run(cfg: dict, method_id: str, spp: int, render_dir: Path, *, frames: int, repeats: int, threads: int,
             results: Path | str) -> dict[str, Any]:
    """Time one (row, spp) alone on the first ``frames`` frames of ``render_dir``: warm-up pass, then ``repeats``."""
    run = prepare_run(cfg, method_id, spp, render_dir, frames=frames, results=results)
    time_interleaved([run], repeats=repeats, threads=threads)
    return run.record(threads)


def render_rate(cfg: dict, manifest: dict, scene_dir: Path, *, repeats: int, threads: int) -> dict[str, Any]:
    """samples/s of the noisy render (render.spp full-feature layers of frame 0) with ``threads`` Dr.Jit threads."""
    from scenegen.mitsuba_env import init_mitsuba, set_render_threads
    from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_sample_layers

    settings = RenderSettings.from_config(cfg["render"])
    init_mitsuba(settings.variant)
    render_threads = set_render_threads(threads)   # >= 2: see scenegen.mitsuba_env.MIN_DRJIT_THREADS
    scene = load_frame_scene(manifest, Path(scene_dir), 0, settings)
    width, height = (int(v) for v in scene.sensors()[0].film().size())

    def render(seed: int) -> float:
        start = time.perf_counter()
        render_sample_layers(scene, n_layers=settings.spp, n_radiance_only=0, seed=seed, counter=NonFiniteCounter())
        return time.perf_counter() - start

    render(0)                                        # warm-up: kernel compilation
    seconds = [render(1 + k) for k in range(repeats)]
    samples = settings.spp * width * height
    median = float(statistics.median(seconds))
    return {"threads": int(threads), "drjit_threads": render_threads, "layers": settings.spp, "pixels": width * height,
            "repeats": repeats, "seconds": seconds, "samples_per_s": samples / median,
            "samples_per_s_min": samples / max(seconds), "samples_per_s_max": samples / min(seconds)}


def time_methods(cfg: dict, scene: str, render_dir: Path, scene_dirs: dict[str, Path],
                 runs: Sequence[tuple[str, int]], *, frames: int, repeats: int, threads: int,
                 results: Path | str) -> dict[str, Any]:
    """The timing job's record: every (row id, spp) of ``runs`` timed interleaved on ``scene``, then the
    renderer's rate on every scene of ``scene_dirs`` ({scene id: scene folder})."""
    from denoisers.device import configured_device, device_info
    from denoisers.provenance import provenance

    prepared = [prepare_run(cfg, method_id, spp, render_dir, frames=frames, results=results)
                for method_id, spp in runs]
    log.info("timing %d (row, spp) on %s: %d frame(s), %d round(s), %d thread(s)", len(prepared), scene, frames,
             repeats, threads)
    for run in prepared:
        run.count_flops(threads)
    sgemm = time_interleaved(prepared, repeats=repeats, threads=threads, sgemm=sgemm_probe())
    return {"schema": TIMING_SCHEMA, "scene": scene, "frames": frames, "repeats": repeats, "threads": threads,
            "sgemm": {"size": SGEMM_SIZE, "gflops_per_s": sgemm, "gflops_per_s_median": float(np.median(sgemm))},
            "rows": [run.record(threads, sgemm) for run in prepared],
            "renderers": {name: render_rate(cfg, json.loads((Path(folder) / "manifest.json").read_text()), folder,
                                            repeats=repeats, threads=threads)
                          for name, folder in scene_dirs.items()},
            "provenance": provenance({"timing": threads}, device=device_info(configured_device(cfg)))}


# ------------------------------------------------------------------------------------------ config
def timing_settings(cfg: dict) -> dict[str, Any]:
    """evaluation.timing with defaults (enabled, scene, frames, repeats, threads)."""
    return {"enabled": True, "scene": None, "frames": 6, "repeats": 5, "threads": None,
            **cfg["evaluation"].get("timing", {})}


def timing_scene(cfg: dict) -> str | None:
    """The scene the timing job reads: evaluation.timing.scene, else the first evaluated scene (None: none)."""
    from denoisers.evaluate import evaluated_scene_ids

    scene = timing_settings(cfg)["scene"]
    scenes = evaluated_scene_ids(cfg)
    return scene if scene is not None else (scenes[0] if scenes else None)


def timed_runs(cfg: dict) -> list[tuple[str, int]]:
    """(row id, spp) the timing job times, in table order: every runnable configured row at every spp it is
    evaluated at, then the rows of the capacity ablations' variants (training.ablations with kind capacity) at
    their evaluated spp (the ablation's spp or evaluation.ablation_spp), whose networks differ in size.
    Comparison variants are not timed: they share their base row's network size."""
    from denoisers.evaluate import plan_runs
    from denoisers.training.models import capacity_model_ids

    if not timing_settings(cfg)["enabled"]:
        return []
    capacity = capacity_model_ids(cfg)
    return [(run.spec.id, run.spp) for run in plan_runs(cfg) if run.runnable and (
        run.spec.role == "method" or run.spec.params.get("model") in capacity)]


# ----------------------------------------------------------------------------------------- reading
@dataclass
class TimingJob:
    """The timing job's record, looked up by (row id, spp)."""

    record: dict[str, Any]
    path: Path | None = None

    @property
    def rows(self) -> dict[tuple[str, int], dict[str, Any]]:
        return {(row["method_id"], int(row["spp"])): row for row in self.record["rows"]}

    def row(self, method_id: str, spp: int) -> dict[str, Any] | None:
        return self.rows.get((method_id, int(spp)))

    def renderer_samples_per_s(self, scene: str) -> float:
        """The renderer's samples/s on ``scene`` (NaN if the job did not render it)."""
        rate = self.record["renderers"].get(scene)
        return float(rate["samples_per_s"]) if rate else float("nan")

    @property
    def threads(self) -> int:
        return int(self.record["threads"])


def speed_ratios(job: TimingJob, a: tuple[str, int], b: tuple[str, int]) -> np.ndarray:
    """Per-round ratios ms_a / ms_b of two timed (row, spp): pass k of a against pass k of b (same round)."""
    row_a, row_b = job.row(*a), job.row(*b)
    if row_a is None or row_b is None:
        missing = [f"{r[0]} @ {r[1]} spp" for r, row in ((a, row_a), (b, row_b)) if row is None]
        raise KeyError(f"timing job has no record for {', '.join(missing)}")
    return np.asarray(row_a["pass_ms_per_frame"], np.float64) / np.asarray(row_b["pass_ms_per_frame"], np.float64)


def read_timing_job(path: Path) -> TimingJob:
    """The timing job's JSON (ValueError naming the file if it is not one)."""
    record = json.loads(Path(path).read_text())
    if record.get("schema") != TIMING_SCHEMA or not isinstance(record.get("rows"), list):
        raise ValueError(f"{path}: not a timing-job record of schema {TIMING_SCHEMA} (rerun rule time_methods)")
    return TimingJob(record, Path(path))
