"""Running one evaluation row on one clip: what rule denoise_row does for each clip of a row (denoisers.jobs.rows).

* ``denoise_clip`` (each clip of rule denoise_row): one method on one evaluated scene at one spp -> EXR + PNG + timing.json
  (+ sample_maps.npz for an adaptive method: its per-frame sample maps; the evaluated spp is its average
  budget, checked per frame with denoisers.adaptive.budget_problems, realised spp in timing.json; + maps.npz
  for a method with per-pixel diagnostics, Denoiser.diagnostics: e.g. AFN's temporal weight lambda)

``run_method`` is the measured loop (per-frame time, peak RSS, non-finite and out-of-range counts)
that the robustness job (denoisers.jobs.robustness) and the timing job (denoisers.jobs.timing) reuse, with the
loading helpers ``_prepare``, ``_load_method_clip`` and ``_frames``. Rows, output paths and the EXR/PNG
writers come from denoisers.evaluate; torch, the registry and the dataset loader are imported by the
functions that use them.
"""
from __future__ import annotations

import json
import resource
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np

from denoisers import native
from denoisers.evaluate import (
    FRAME_EXR,
    FRAME_PNG,
    MAPS_FILE,
    OUT_OF_RANGE_FACTOR,
    TIMING_FILE,
    EvaluationError,
    MethodSpec,
    method_spec,
    write_preview_png,
    write_radiance_exr,
)
from denoisers.training.models import resolve_method_params
from scenegen.atomic import atomic_directory


class PeakRSS:
    """Peak resident set size while the ``with`` block runs, by sampling this process's RSS with psutil
    from a background thread every ``interval_s`` (tracemalloc does not see torch's or OIDN's native
    allocations). ``extra_mb`` = peak minus the RSS at entry; allocations shorter than the interval
    can be missed, so it is a lower bound."""

    def __init__(self, interval_s: float = 0.005) -> None:
        import psutil

        self._process = psutil.Process()
        self._interval_s = interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.baseline_bytes = 0
        self.peak_bytes = 0

    def _sample(self) -> None:
        self.peak_bytes = max(self.peak_bytes, self._process.memory_info().rss)

    def _loop(self) -> None:
        while not self._stop.wait(self._interval_s):
            self._sample()

    def __enter__(self) -> Self:
        self.baseline_bytes = self.peak_bytes = self._process.memory_info().rss
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()

    @property
    def extra_mb(self) -> float:
        return (self.peak_bytes - self.baseline_bytes) / 2**20

    @property
    def peak_mb(self) -> float:
        return self.peak_bytes / 2**20


@dataclass
class MethodOutput:
    """What running a method over a clip produced."""

    radiance: np.ndarray            # (T, 3, H, W) float32 as returned (non-finite values kept)
    seconds: list[float]            # in-process time of each denoise() call
    nonfinite_inputs: list[int]     # per frame: non-finite values in the inputs handed to the method
    nonfinite_outputs: list[int]    # per frame: non-finite values in the output
    peak_rss_extra_mb: float
    peak_rss_mb: float
    maxrss_delta_mb: float
    # per frame: finite output values with |value| > factor x the largest finite |radiance sample| of the
    # frame's input (all 0 when the method reads no radiance: out_of_range_checked False)
    out_of_range_outputs: list[int] = field(default_factory=list)
    out_of_range_checked: bool = True
    out_of_range_factor: float = OUT_OF_RANGE_FACTOR
    # adaptive methods only: (T, H, W) int64 samples used per pixel (registry.AdaptiveOutput.sample_map)
    sample_maps: np.ndarray | None = None
    # name -> (T, H, W) float32 of Denoiser.diagnostics() after every frame (empty when the method has none)
    maps: dict[str, np.ndarray] = field(default_factory=dict)


def _load_method_clip(render_dir: Path, spec: MethodSpec, method, layers: int, reference: bool):
    """Load exactly the buffers the method declares with ``layers`` sample layers; a buffer that was
    not rendered (or has too few layers) raises MissingInputError naming the buffer and the method."""
    from denoisers.registry import MissingInputError
    from scenegen.dataset import MissingBufferError, NotEnoughSamplesError, load_clip

    try:    # an adaptive method gets every stored layer (registry.clip_frames checks there are enough)
        return load_clip(render_dir, buffers=method.info.inputs, spp=None if method.info.adaptive else layers,
                         reference=reference)
    except MissingBufferError as error:
        raise MissingInputError(spec.label, error.buffer, str(error)) from error
    except NotEnoughSamplesError as error:
        buffer = next((b for b in method.info.inputs if f"{b!r}" in str(error)), method.info.inputs[0])
        raise MissingInputError(spec.label, buffer, f"{layers} sample layers needed: {error}") from error


def input_radiance_bound(frame) -> float | None:
    """Largest finite |value| among the frame's radiance samples (0.0 if none is finite); None when the
    frame carries no radiance buffer (the method does not read it)."""
    import torch

    radiance = frame.samples.get("radiance")
    if radiance is None:
        return None
    magnitude = torch.where(torch.isfinite(radiance), radiance.abs(), torch.zeros((), dtype=radiance.dtype))
    return float(magnitude.amax()) if magnitude.numel() else 0.0


def count_out_of_range(output, bound: float | None, factor: float) -> int:
    """Finite values of ``output`` with |value| > factor x ``bound`` (0 when ``bound`` is None). A denoiser
    averages samples, so an output far above every input sample is an artefact (e.g. an exploding network)."""
    import torch

    if bound is None:
        return 0
    return int((torch.isfinite(output) & (output.abs() > factor * bound)).sum().item())


def run_method(method, frames: Sequence, threads: int,
               out_of_range_factor: float = OUT_OF_RANGE_FACTOR) -> MethodOutput:
    """reset(), then denoise() every frame in order, timing each call (frames are built beforehand, so
    no I/O or data preparation is timed). Counts non-finite inputs and outputs per frame, and finite
    outputs above ``out_of_range_factor`` x the frame's largest finite input radiance sample (measured
    before denoise(), which may modify its inputs; not timed)."""
    import torch

    from denoisers.device import default_device, synchronize

    torch.set_num_threads(max(1, int(threads)))
    native.load()     # build or import the native kernels now, never inside the timed loop
    device = getattr(method, "device", torch.device("cpu"))
    outputs, seconds, inputs_bad, outputs_bad, out_of_range, sample_maps = [], [], [], [], [], []
    maps: dict[str, list[np.ndarray]] = {}
    # Input bounds before the memory measurement (their temporaries are not the method's memory).
    bounds = [input_radiance_bound(frame) for frame in frames]
    checked = all(bound is not None for bound in bounds)
    if device.type != "cpu":
        frames = [frame.to(device) for frame in frames]   # copied to the method's device untimed, like the loading
    maxrss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    method.reset()
    with torch.no_grad(), PeakRSS() as memory:
        for frame, bound in zip(frames, bounds):
            inputs_bad.append(int(sum((~torch.isfinite(t)).sum().item()
                                      for t in (*frame.samples.values(), *frame.pixel.values()))))
            synchronize(device)
            start = time.perf_counter()
            with default_device(device):  # tensors a method creates without a device argument land there too
                result = method.denoise(frame)
            synchronize(device)       # a GPU method's time includes its queued kernels
            seconds.append(time.perf_counter() - start)
            if method.info.adaptive:
                result, sample_map = _adaptive_result(method, frame, result)
                sample_maps.append(sample_map)
            result = torch.as_tensor(result).detach().to(torch.float32).cpu()
            expected = (3, frame.height, frame.width)
            if tuple(result.shape) != expected:
                raise EvaluationError(f"method {method.info.name!r} returned shape {tuple(result.shape)} "
                                      f"for frame {frame.index}; expected {expected} (3, H, W)")
            outputs_bad.append(int((~torch.isfinite(result)).sum().item()))
            out_of_range.append(count_out_of_range(result, bound, out_of_range_factor))
            outputs.append(result.numpy())
            for name, image in method.diagnostics().items():
                maps.setdefault(name, []).append(torch.as_tensor(image).detach().float().cpu().numpy())
    maxrss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return MethodOutput(np.stack(outputs), seconds, inputs_bad, outputs_bad, memory.extra_mb, memory.peak_mb,
                        (maxrss_after - maxrss_before) / 1024.0,  # ru_maxrss is in KiB on Linux
                        out_of_range, checked, float(out_of_range_factor),
                        np.stack(sample_maps) if sample_maps else None,
                        {name: np.stack(images) for name, images in maps.items() if len(images) == len(frames)})


def _adaptive_result(method, frame, result):
    """(radiance, (H, W) int64 sample map as numpy) of an adaptive method's AdaptiveOutput; EvaluationError
    naming the method and frame when it is not one, or the map's shape, type or range is wrong."""
    import torch

    from denoisers.registry import AdaptiveOutput

    where = f"adaptive method {method.info.name!r}, frame {frame.index}"
    if not isinstance(result, AdaptiveOutput):
        raise EvaluationError(f"{where}: denoise() returned {type(result).__name__}; expected "
                              "registry.AdaptiveOutput(radiance, sample_map)")
    sample_map = torch.as_tensor(result.sample_map).detach().cpu()
    available = frame.samples["radiance"].shape[0] if "radiance" in frame.samples else frame.spp
    if tuple(sample_map.shape) != (frame.height, frame.width) or sample_map.dtype.is_floating_point:
        raise EvaluationError(f"{where}: sample map must be integer ({frame.height}, {frame.width}), got "
                              f"{sample_map.dtype} {tuple(sample_map.shape)}")
    if sample_map.numel() and (int(sample_map.min()) < 0 or int(sample_map.max()) > available):
        raise EvaluationError(f"{where}: sample map values {int(sample_map.min())}..{int(sample_map.max())} "
                              f"outside 0..{available} (the stored radiance layers)")
    return result.radiance, sample_map.to(torch.int64).numpy()


def adaptive_record(maps: np.ndarray, budget: float, frames: Sequence[int]) -> dict[str, Any]:
    """timing.json keys of an adaptive row: budget, realised spp per frame and over the clip."""
    from denoisers.adaptive import SAMPLE_MAPS_FILE

    per_frame = [float(m.mean()) for m in maps.astype(np.float64)]
    return {"adaptive": True, "budget_spp": float(budget), "realised_spp_per_frame": per_frame,
            "realised_spp": float(np.mean(per_frame)), "sample_maps_file": SAMPLE_MAPS_FILE,
            "sample_map_frames": [int(t) for t in frames]}


def timing_summary(seconds: Sequence[float], width: int, height: int) -> dict[str, Any]:
    """Mean/median seconds per frame and Mpix/s, the first frame excluded as warm-up (kept if it is the only one)."""
    timed = list(seconds[1:]) if len(seconds) > 1 else list(seconds)
    mean = float(np.mean(timed))
    return {
        "seconds_per_frame": [float(s) for s in seconds],
        "warmup_frames_excluded": 1 if len(seconds) > 1 else 0,
        "mean_seconds": mean,
        "median_seconds": float(np.median(timed)),
        "mpix_per_s": width * height / mean / 1e6 if mean > 0 else float("inf"),
    }


def out_of_range_record(result: MethodOutput) -> dict[str, Any]:
    """timing.json / summary.json keys of the out-of-range count (totals; per frame added by the caller)."""
    return {"out_of_range_outputs": int(sum(result.out_of_range_outputs)),
            "out_of_range_factor": result.out_of_range_factor,
            # False: the method reads no radiance samples, so there is no input range and nothing was counted.
            "out_of_range_checked": result.out_of_range_checked}


def _prepare(cfg: dict, method_id: str, spp: int, results: Path | str | None = None):
    """(row spec, built method, sample layers); trained models and tuning results are read below ``results``
    (default: the config's output_dir)."""
    from denoisers import registry

    from denoisers.device import torch_device

    spec = method_spec(cfg, method_id)
    method = registry.build(spec.method, resolve_method_params(cfg, spec.params, results, method=spec.method),
                            row=spec.id)
    method.to(torch_device(cfg))     # compute.device
    return spec, method, spp * method.samples_factor


def _frames(clip, method, layers: int) -> list:
    from denoisers.registry import clip_frames

    return list(clip_frames(clip, method.info, layers))


def _reference_render_rates(render_dir: Path) -> list[float]:
    """samples/s of every reference frame of a clip, from the sidecar JSONs."""
    from scenegen.dataset import find_frames

    sidecars = [path.with_suffix(".json") for path in find_frames(render_dir / "reference").values()]
    rates = [json.loads(p.read_text()).get("samples_per_s") for p in sidecars if p.is_file()]
    return [float(rate) for rate in rates if rate]


def denoise_clip(cfg: dict, method_id: str, scene: str, spp: int, render_dir: Path, out_dir: Path,
                 threads: int = 1, results: Path | str | None = None) -> dict[str, Any]:
    """Run one configured method on one clip at ``spp`` and write ``out_dir`` atomically:
    frame_TTTT.exr (radiance.R/G/B, linear HDR), frame_TTTT.png (tonemapped preview), timing.json (with
    the clip's settings digest, denoisers.experiment). A row with ``params: {model: <id>}`` loads
    ``<results>/models/<id>/best.pt`` (default: the config's output_dir). Returns the timing record."""
    from denoisers.device import device_info
    from denoisers.experiment import DIGEST_KEY, Lineage

    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=False)
    frames = _frames(clip, method, layers)
    result = run_method(method, frames, threads, cfg["evaluation"]["out_of_range_factor"])
    height, width = result.radiance.shape[-2:]
    adaptive = {}
    if result.sample_maps is not None:
        from denoisers.adaptive import SAMPLE_MAPS_FILE, budget_problems

        # The row's budget: the evaluated spp times its samples_factor (e.g. a uniform 8-spp row at 4 spp).
        problems = budget_problems(result.sample_maps, layers, clip.frames, f"row {spec.id!r}, scene {scene}")
        if problems:
            raise EvaluationError("adaptive sample budget exceeded: " + "; ".join(problems))
        adaptive = adaptive_record(result.sample_maps, layers, clip.frames)
        adaptive["available_layers"] = {buffer: int(v.shape[0]) for buffer, v in frames[0].samples.items()}
    # Steady-state cost of one path sample with every feature buffer: the reference renders' rate
    # (large batches); the noisy frames' rate also carries per-frame scene loading.
    render_rates = _reference_render_rates(Path(render_dir))
    record = {
        "method_id": spec.id, "method": spec.method, "params": spec.params, "scene": scene, "spp": spp,
        "samples_factor": method.samples_factor, "sample_layers": layers, "threads": int(threads),
        "device": device_info(method.device.type),          # compute.device: where denoise() ran
        "width": int(width), "height": int(height), "frames": [int(t) for t in clip.frames],
        **timing_summary(result.seconds, width, height),
        "peak_memory_mb": result.peak_rss_extra_mb,
        "peak_rss_mb": result.peak_rss_mb,
        "maxrss_delta_mb": result.maxrss_delta_mb,
        "memory_method": "psutil RSS sampled every 5 ms during the denoise loop, minus the RSS before it "
                         "(peak_memory_mb); maxrss_delta_mb = growth of getrusage ru_maxrss over the loop",
        "nonfinite_inputs": int(sum(result.nonfinite_inputs)),
        "nonfinite_outputs": int(sum(result.nonfinite_outputs)),
        "nonfinite_outputs_per_frame": result.nonfinite_outputs,
        **out_of_range_record(result),
        "out_of_range_outputs_per_frame": result.out_of_range_outputs,
        # Cost of rendering one sample with every buffer (for the equal-time view of the report).
        "render_samples_per_s": float(np.mean(render_rates)) if render_rates else None,
        **adaptive,
        "maps": sorted(result.maps),           # names of the per-frame diagnostic maps in MAPS_FILE (if any)
        DIGEST_KEY: Lineage(cfg).denoised(spec, scene, spp),
    }
    with atomic_directory(out_dir) as staging:
        for t, radiance in zip(clip.frames, result.radiance):
            write_radiance_exr(staging / FRAME_EXR.format(t), radiance,
                               {"method_id": spec.id, "scene": scene, "spp": spp, "frame": int(t)})
            write_preview_png(staging / FRAME_PNG.format(t), radiance)
        if result.sample_maps is not None:     # uint8: at most 32 layers
            np.savez_compressed(staging / SAMPLE_MAPS_FILE, frames=np.asarray(clip.frames, np.int64),
                                sample_maps=result.sample_maps.astype(np.uint8))
        if result.maps:                       # e.g. AFN's lambda: float16 is plenty for a figure
            np.savez_compressed(staging / MAPS_FILE, frames=np.asarray(clip.frames, np.int64),
                                **{name: images.astype(np.float16) for name, images in result.maps.items()})
        (staging / TIMING_FILE).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    return record
