"""Running methods on the evaluated clips and scoring them: the jobs behind the workflow's evaluation rules.

The evaluated scenes are the held-out test scenes (``test_*``) and the external scenes (``custom_*``,
bring-your-own XML); each is an independent unit of every comparison. The robustness scenario runs
on all of them too (its cost is one job per scene and row, like the evaluation's).

* ``denoise_clip``    (rule denoise_clip):    one method on one evaluated scene at one spp -> EXR + PNG + timing.json
* ``evaluate_clip``   (rule evaluate_clip):   per-frame metrics of a denoised clip against the reference -> CSV
* ``robustness_clip`` (rule robustness_clip): one method on a clip with injected spikes and NaN/Inf -> CSV

The config-level helpers at the top (method list, test scenes, which (method, spp) pairs can run)
import nothing heavy: the Snakefile calls them while it is parsed, and importing torch there would
slow down every ``snakemake`` invocation. torch, the registry and the metrics are imported by the
functions that run jobs.
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

from scenegen.atomic import atomic_directory, write_text_atomic
from denoisers import native
from denoisers.training.models import resolve_method_params
from scenegen.config import CUSTOM_PREFIX, SCENE_SPLITS, scene_frame_count, scene_ids

TEST_PREFIX = f"{SCENE_SPLITS[1]}_"
#: Per-frame metrics of the CSVs, in column order (names of denoisers.metrics.frame_metrics).
FRAME_METRICS: tuple[str, ...] = ("psnr", "ssim", "rmse", "relmse", "smape", "flip")
#: Temporal metrics (denoisers.metrics.temporal_metrics); NaN during warm-up and after camera cuts.
TEMPORAL_METRICS: tuple[str, ...] = ("tpsnr", "trmae")
ALL_METRICS: tuple[str, ...] = FRAME_METRICS + TEMPORAL_METRICS
#: Methods that do not denoise: the noisy input and plain path tracing at more spp.
REFERENCE_METHODS: frozenset[str] = frozenset({"noisy", "path_tracing"})
FRAME_EXR = "frame_{:04d}.exr"
FRAME_PNG = "frame_{:04d}.png"
TIMING_FILE = "timing.json"
ROBUSTNESS_CSV = "metrics.csv"
ROBUSTNESS_SUMMARY = "summary.json"
ROBUSTNESS_LAST_EXR = "last_frame.exr"
RADIANCE_CHANNELS = ("radiance.R", "radiance.G", "radiance.B")


class EvaluationError(ValueError):
    """Denoised output and reference do not match (frame count, resolution) or a run is impossible."""


# ---------------------------------------------------------------------------------------------------
# Config-level helpers (no torch)
# ---------------------------------------------------------------------------------------------------

#: MethodSpec.role of the rows of ``evaluation.methods`` and of the rows added for ablation variants.
METHOD_ROLE, ABLATION_ROLE = "method", "ablation"
#: Default of ``evaluation.out_of_range_factor`` (the schema's default).
OUT_OF_RANGE_FACTOR = 10.0


@dataclass(frozen=True)
class MethodSpec:
    """One evaluation row: row name, registry name, constructor parameters, the sample counts it is
    evaluated at, whether it runs in the spike/NaN scenario, and its role: ``"method"`` for a row of
    ``evaluation.methods``, ``"ablation"`` for a row added for a trained ablation variant."""

    id: str
    method: str
    params: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    spp: tuple[int, ...] = ()
    robustness: bool = True
    role: str = METHOD_ROLE

    @property
    def label(self) -> str:
        """Name used in messages: the row id, plus the registry name when they differ."""
        return self.id if self.id == self.method else f"{self.id} ({self.method})"


def _row_spp(cfg: dict, wanted: Sequence[int] | None) -> tuple[int, ...]:
    """The evaluated spp (``evaluation.spp`` order) that are in ``wanted`` (all of them when None);
    values outside ``evaluation.spp`` are dropped here and reported by :func:`evaluation_problems`."""
    evaluated = [int(s) for s in cfg["evaluation"]["spp"]]
    if wanted is None:
        return tuple(evaluated)
    wanted = set(wanted)
    return tuple(s for s in evaluated if s in wanted)


def ablation_method_specs(cfg: dict) -> list[MethodSpec]:
    """Rows evaluating every trained ablation variant (denoisers.training.models.model_specs with
    ``ablation`` set): id and ``params.model`` = the model id, at ``evaluation.ablation_spp`` (default
    [1]; [] = none), not in the robustness scenario. Empty when ``ablation_spp`` is empty."""
    from denoisers.training.models import model_specs

    spp = _row_spp(cfg, cfg["evaluation"].get("ablation_spp", [1]))
    if not spp:
        return []
    return [MethodSpec(model.id, model.method, {"model": model.id}, spp, robustness=False, role=ABLATION_ROLE)
            for model in model_specs(cfg) if model.ablation]


def method_specs(cfg: dict) -> list[MethodSpec]:
    """The evaluation rows in table order: ``evaluation.methods`` (spp default: every evaluated spp;
    robustness default: true), then one row per trained ablation variant (:func:`ablation_method_specs`)."""
    configured = [MethodSpec(entry["id"], entry["method"], dict(entry.get("params") or {}),
                             _row_spp(cfg, entry.get("spp")), bool(entry.get("robustness", True)), METHOD_ROLE)
                  for entry in cfg["evaluation"]["methods"]]
    return configured + ablation_method_specs(cfg)


def method_spec(cfg: dict, method_id: str) -> MethodSpec:
    """The spec of row ``method_id`` (configured or ablation row); KeyError listing the ids otherwise."""
    specs = method_specs(cfg)
    for spec in specs:
        if spec.id == method_id:
            return spec
    known = ", ".join(spec.id for spec in specs)
    raise KeyError(f"no evaluation method with id {method_id!r}; configured ids: {known}")


def evaluated_scene_ids(cfg: dict) -> list[str]:
    """Scenes that are evaluated, each an independent unit of the comparisons: the held-out ``test_*``
    ids, then the external ``custom_*`` scenes of ``extra_scenes`` (training scenes never are)."""
    return [scene for scene in scene_ids(cfg) if scene.startswith((TEST_PREFIX, CUSTOM_PREFIX))]


def rendered_layers(cfg: dict) -> dict[str, int]:
    """Sample layers on disk per buffer: radiance has spp + extra_radiance_spp, every other buffer spp."""
    from scenegen.dataset import RADIANCE_BUFFER, SAMPLE_BUFFERS

    render = cfg["render"]
    return {buffer: render["spp"] + (render["extra_radiance_spp"] if buffer == RADIANCE_BUFFER else 0)
            for buffer in SAMPLE_BUFFERS}


def evaluation_problems(cfg: dict) -> list[str]:
    """Constraints of the ``evaluation`` section the JSON schema cannot express (schema-valid cfg)."""
    evaluation, render = cfg["evaluation"], cfg["render"]
    problems = []
    layers = render["spp"] + render["extra_radiance_spp"]
    evaluated = list(evaluation["spp"])
    too_many = [spp for spp in evaluated if spp > layers]
    if too_many:
        problems.append(f"config key 'evaluation.spp' = {evaluation['spp']!r} has values {too_many} above the "
                        f"rendered sample layers; allowed: each <= render.spp + render.extra_radiance_spp = {layers}")
    ids = [entry["id"] for entry in evaluation["methods"]]
    for method_id in sorted({i for i in ids if ids.count(i) > 1}):
        problems.append(f"config key 'evaluation.methods' has the id {method_id!r} more than once; allowed: unique ids")
    for index, entry in enumerate(evaluation["methods"]):
        outside = [spp for spp in entry.get("spp") or [] if spp not in evaluated]
        if outside:
            problems.append(f"config key 'evaluation.methods[{index}].spp' (row {entry['id']!r}) = {entry['spp']!r} "
                            f"has values {outside} that are not in 'evaluation.spp' = {evaluated!r}; allowed: "
                            "values of evaluation.spp")
    from denoisers.training.models import model_specs

    variants = [model.id for model in model_specs(cfg) if model.ablation]
    ablation_spp = list(evaluation.get("ablation_spp", [1]))
    outside = [spp for spp in ablation_spp if spp not in evaluated]
    if variants and outside:
        problems.append(f"config key 'evaluation.ablation_spp' = {ablation_spp!r} has values {outside} that are not in "
                        f"'evaluation.spp' = {evaluated!r}; allowed: values of evaluation.spp, or [] to not "
                        "evaluate the ablation variants")
    if variants and ablation_spp:
        for method_id in sorted(set(ids) & set(variants)):
            problems.append(f"config key 'evaluation.methods' has the id {method_id!r}, which is the id of the row "
                            "added for that trained ablation variant (evaluation.ablation_spp); allowed: ids other "
                            f"than the ablation variants {variants}, or evaluation.ablation_spp: []")
    frames, grid_frame = cfg["scenes"]["frames"], evaluation["grid_frame"]
    if not -frames <= grid_frame < frames:
        problems.append(f"config key 'evaluation.grid_frame' = {grid_frame} is outside the clips' frames; allowed: "
                        f"{-frames}..{frames - 1} (scenes.frames = {frames}; negative counts from the end)")
    else:
        for scene in (s for s in evaluated_scene_ids(cfg) if s.startswith(CUSTOM_PREFIX)):
            count = scene_frame_count(cfg, scene)
            if not -count <= grid_frame < count:
                problems.append(f"config key 'evaluation.grid_frame' = {grid_frame} is outside the {count} frames of "
                                f"the evaluated scene {scene}; allowed: {-count}..{count - 1}, or more frames in its "
                                "extra_scenes entry")
    robustness = evaluation["robustness"]
    if robustness["enabled"] and robustness["spp"] not in evaluated:
        problems.append(f"config key 'evaluation.robustness.spp' = {robustness['spp']} is not one of "
                        f"'evaluation.spp' = {evaluation['spp']!r}; allowed: one of the evaluated spp")
    timing_scene = evaluation.get("timing", {}).get("scene")
    if timing_scene is not None and timing_scene not in evaluated_scene_ids(cfg):
        problems.append(f"config key 'evaluation.timing.scene' = {timing_scene!r} is not an evaluated scene; allowed: "
                        f"{', '.join(evaluated_scene_ids(cfg)) or 'none'} (or null: the first of them)")
    return problems


@dataclass(frozen=True)
class Run:
    """One (method row, spp) combination; ``not_run`` says why it cannot run ('' when it can)."""

    spec: MethodSpec
    spp: int
    samples_factor: int
    not_run: str = ""

    @property
    def runnable(self) -> bool:
        return not self.not_run

    @property
    def layers(self) -> int:
        """Sample layers the method reads: spp x samples_factor."""
        return self.spp * self.samples_factor


def _plan(cfg: dict, specs: Sequence[MethodSpec], spps_of) -> list[Run]:
    from denoisers import registry

    available = rendered_layers(cfg)
    runs = []
    for spec in specs:
        spps = spps_of(spec)
        if not spps:
            continue
        method = registry.build(spec.method, resolve_method_params(cfg, spec.params), row=spec.id)
        for spp in spps:
            layers = spp * method.samples_factor
            short = [buffer for buffer in method.info.inputs if available[buffer] < layers]
            reason = ""
            if short:
                reason = (f"not run (needs {layers} layers of {short[0]!r}, {available[short[0]]} rendered; "
                          "raise render.spp or render.extra_radiance_spp)")
            runs.append(Run(spec, spp, method.samples_factor, reason))
    return runs


def plan_runs(cfg: dict, spps: Sequence[int] | None = None, rows: Sequence[MethodSpec] | None = None) -> list[Run]:
    """Every (row, spp) of the config (or of ``rows``), in table order: each row at its own ``spp``
    (MethodSpec.spp), intersected with ``spps`` when given. A run is marked not runnable when it needs
    more sample layers than were rendered (e.g. path tracing at k x spp). Builds each planned method
    once to read its declared inputs and samples_factor (constructors must be cheap)."""
    return _plan(cfg, method_specs(cfg) if rows is None else rows,
                 lambda spec: [s for s in (spps if spps is not None else spec.spp) if s in spec.spp])


def robustness_runs(cfg: dict) -> list[Run]:
    """The runs of the spike/NaN scenario: every row with ``robustness`` true (the ablation rows never)
    at ``evaluation.robustness.spp``, whatever the row's evaluated spp; none if the scenario is disabled."""
    robustness = cfg["evaluation"]["robustness"]
    if not robustness["enabled"]:
        return []
    return _plan(cfg, [spec for spec in method_specs(cfg) if spec.robustness], lambda spec: [robustness["spp"]])


def denoised_dir(results: Path, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "denoised" / method_id / scene / f"spp{spp}"


def metrics_csv(results: Path, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "metrics" / method_id / scene / f"spp{spp}.csv"


def metrics_sidecar(csv: Path) -> Path:
    """The JSON next to a metrics CSV (spp{spp}.json): the row, scene, spp and settings digest it came from."""
    return Path(csv).with_suffix(".json")


def robustness_dir(results: Path, method_id: str, scene: str, spp: int) -> Path:
    return Path(results) / "robustness" / method_id / scene / f"spp{spp}"


# ---------------------------------------------------------------------------------------------------
# File helpers
# ---------------------------------------------------------------------------------------------------

def write_radiance_exr(path: Path, radiance: np.ndarray, meta: dict | None = None) -> None:
    """(3, H, W) linear radiance -> EXR with FLOAT channels radiance.R/G/B."""
    from scenegen.exr import write_exr

    attributes = {"mcdn_meta": json.dumps(meta, sort_keys=True)} if meta else None
    write_exr(path, dict(zip(RADIANCE_CHANNELS, np.asarray(radiance, dtype=np.float32))), attributes=attributes)


def read_radiance_exr(path: Path) -> np.ndarray:
    """EXR with channels radiance.R/G/B -> (3, H, W) float32."""
    from scenegen.exr import read_exr

    planes, _ = read_exr(path, RADIANCE_CHANNELS)
    return np.stack([planes[name] for name in RADIANCE_CHANNELS])


def preview_rgb8(radiance: np.ndarray) -> np.ndarray:
    """(3, H, W) linear radiance -> (H, W, 3) uint8 with the metrics' tonemap (non-finite shown black)."""
    from denoisers.metrics import tonemap

    mapped = np.asarray(tonemap(np.nan_to_num(np.asarray(radiance, np.float32), nan=0.0, posinf=0.0, neginf=0.0)))
    return (np.clip(mapped, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).transpose(1, 2, 0)


def write_preview_png(path: Path, radiance: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(preview_rgb8(radiance)).save(path)


def read_frame_files(directory: Path) -> dict[int, Path]:
    """frame index -> path of ``frame_TTTT.exr`` in a denoised directory."""
    frames = {}
    for path in sorted(Path(directory).glob("frame_*.exr")):
        frames[int(path.stem.split("_")[1])] = path
    return frames


# ---------------------------------------------------------------------------------------------------
# Running a method
# ---------------------------------------------------------------------------------------------------

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


def _load_method_clip(render_dir: Path, spec: MethodSpec, method, layers: int, reference: bool):
    """Load exactly the buffers the method declares with ``layers`` sample layers; a buffer that was
    not rendered (or has too few layers) raises MissingInputError naming the buffer and the method."""
    from denoisers.registry import MissingInputError
    from scenegen.dataset import MissingBufferError, NotEnoughSamplesError, load_clip

    try:
        return load_clip(render_dir, buffers=method.info.inputs, spp=layers, reference=reference)
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

    torch.set_num_threads(max(1, int(threads)))
    native.load()     # build or import the native kernels now, never inside the timed loop
    outputs, seconds, inputs_bad, outputs_bad, out_of_range = [], [], [], [], []
    # Input bounds before the memory measurement (their temporaries are not the method's memory).
    bounds = [input_radiance_bound(frame) for frame in frames]
    checked = all(bound is not None for bound in bounds)
    maxrss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    method.reset()
    with torch.no_grad(), PeakRSS() as memory:
        for frame, bound in zip(frames, bounds):
            inputs_bad.append(int(sum((~torch.isfinite(t)).sum().item()
                                      for t in (*frame.samples.values(), *frame.pixel.values()))))
            start = time.perf_counter()
            result = method.denoise(frame)
            seconds.append(time.perf_counter() - start)
            result = torch.as_tensor(result).detach().to(torch.float32).cpu()
            expected = (3, frame.height, frame.width)
            if tuple(result.shape) != expected:
                raise EvaluationError(f"method {method.info.name!r} returned shape {tuple(result.shape)} "
                                      f"for frame {frame.index}; expected {expected} (3, H, W)")
            outputs_bad.append(int((~torch.isfinite(result)).sum().item()))
            out_of_range.append(count_out_of_range(result, bound, out_of_range_factor))
            outputs.append(result.numpy())
    maxrss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return MethodOutput(np.stack(outputs), seconds, inputs_bad, outputs_bad, memory.extra_mb, memory.peak_mb,
                        (maxrss_after - maxrss_before) / 1024.0,  # ru_maxrss is in KiB on Linux
                        out_of_range, checked, float(out_of_range_factor))


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

    spec = method_spec(cfg, method_id)
    method = registry.build(spec.method, resolve_method_params(cfg, spec.params, results, method=spec.method),
                            row=spec.id)
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
    from denoisers.experiment import DIGEST_KEY, Lineage

    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=False)
    frames = _frames(clip, method, layers)
    result = run_method(method, frames, threads, cfg["evaluation"]["out_of_range_factor"])
    height, width = result.radiance.shape[-2:]
    # Steady-state cost of one path sample with every feature buffer: the reference renders' rate
    # (large batches); the noisy frames' rate also carries per-frame scene loading.
    render_rates = _reference_render_rates(Path(render_dir))
    record = {
        "method_id": spec.id, "method": spec.method, "params": spec.params, "scene": scene, "spp": spp,
        "samples_factor": method.samples_factor, "sample_layers": layers, "threads": int(threads),
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
        DIGEST_KEY: Lineage(cfg).denoised(spec, scene, spp),
    }
    with atomic_directory(out_dir) as staging:
        for t, radiance in zip(clip.frames, result.radiance):
            write_radiance_exr(staging / FRAME_EXR.format(t), radiance,
                               {"method_id": spec.id, "scene": scene, "spp": spp, "frame": int(t)})
            write_preview_png(staging / FRAME_PNG.format(t), radiance)
        (staging / TIMING_FILE).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    return record


# ---------------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------------

def load_references(render_dir: Path) -> tuple[list[int], list[Path], np.ndarray, list[dict]]:
    """Reference radiance of a clip: (frame indices, paths, (T, 3, H, W), reference sidecars)."""
    from scenegen.dataset import find_frames, load_reference_frame

    found = find_frames(Path(render_dir) / "reference")
    if not found:
        raise EvaluationError(f"{Path(render_dir) / 'reference'}: no reference frames found")
    frames = sorted(found)
    images, metas = [], []
    for t in frames:
        data, meta = load_reference_frame(found[t], ["radiance"])
        images.append(data["radiance"])
        metas.append(meta)
    return frames, [found[t] for t in frames], np.stack(images), metas


def _check_match(denoised: dict[int, Path], denoised_dir_: Path, ref_frames: list[int], render_dir: Path) -> None:
    if sorted(denoised) != ref_frames:
        raise EvaluationError(
            f"frame count mismatch: {denoised_dir_} holds {len(denoised)} denoised frames {sorted(denoised)}, "
            f"but {Path(render_dir) / 'reference'} holds {len(ref_frames)} reference frames {ref_frames}")


def _temporal_mask(n_frames: int, cuts: Sequence[bool], warmup: int) -> np.ndarray:
    """True where temporal metrics are defined: at least ``warmup`` frames (and >= 1) since the clip
    start or the last camera cut, so the predecessor belongs to the same shot."""
    mask = np.zeros(n_frames, dtype=bool)
    since = 0
    for t in range(n_frames):
        since = 0 if (t == 0 or cuts[t]) else since + 1
        mask[t] = since >= max(1, warmup)
    return mask


def score_sequence(pred: np.ndarray, ref: np.ndarray, cuts: Sequence[bool], warmup: int) -> dict[str, np.ndarray]:
    """Per-frame metrics of (T, 3, H, W) predictions against references. Non-finite predicted values are
    set to 0 before scoring (they are counted separately); temporal metrics are NaN during the first
    ``warmup`` frames and the first ``warmup`` frames after a camera cut."""
    from denoisers import metrics

    pred = np.nan_to_num(np.asarray(pred, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    ref = np.asarray(ref, np.float32)
    per_frame = [metrics.frame_metrics(p, r) for p, r in zip(pred, ref)]
    scores = {name: np.array([float(row[name]) for row in per_frame]) for name in FRAME_METRICS}
    temporal = metrics.temporal_metrics(pred, ref, warmup)
    mask = _temporal_mask(len(pred), cuts, warmup)
    for name in TEMPORAL_METRICS:
        values = np.asarray(temporal[name], dtype=np.float64).copy()
        values[~mask] = np.nan
        scores[name] = values
    return scores


def _metrics_record(cfg: dict, denoised_path: Path) -> dict[str, Any] | None:
    """The sidecar of the metrics of a denoised clip: the row, scene and spp its timing.json names and the
    settings digest of the metrics (None without timing.json). SettingsMismatchError if the clip was
    denoised with other settings than ``cfg``'s."""
    from denoisers.experiment import DIGEST_KEY, Lineage, check_recorded

    path = denoised_path / TIMING_FILE
    timing = json.loads(path.read_text()) if path.is_file() else {}
    if not {"method_id", "scene", "spp"} <= timing.keys():
        return None
    spec, scene, spp, lineage = method_spec(cfg, timing["method_id"]), timing["scene"], timing["spp"], Lineage(cfg)
    check_recorded(path, timing.get(DIGEST_KEY), lineage.denoised(spec, scene, spp))
    return {"method_id": spec.id, "scene": scene, "spp": spp, DIGEST_KEY: lineage.metrics(spec, scene, spp)}


def evaluate_clip(cfg: dict, denoised_path: Path, render_dir: Path, out_csv: Path):
    """Per-frame metrics of one denoised clip against clip.reference radiance -> CSV with columns
    frame, psnr, ssim, rmse, relmse, smape, flip, tpsnr, trmae, camera_cut, nonfinite_output,
    reference_psnr_halves, and its sidecar (metrics_sidecar: the settings digest the metrics came from;
    not written when the denoised clip has no timing.json). Raises EvaluationError when frame counts or
    resolutions differ."""
    import pandas as pd

    denoised_path, render_dir = Path(denoised_path), Path(render_dir)
    record = _metrics_record(cfg, denoised_path)
    denoised = read_frame_files(denoised_path)
    if not denoised:
        raise EvaluationError(f"{denoised_path}: no denoised frames (frame_TTTT.exr)")
    ref_frames, ref_paths, reference, ref_meta = load_references(render_dir)
    _check_match(denoised, denoised_path, ref_frames, render_dir)
    pred = []
    for t, ref_path, ref_image in zip(ref_frames, ref_paths, reference):
        image = read_radiance_exr(denoised[t])
        if image.shape != ref_image.shape:
            raise EvaluationError(f"resolution mismatch: {denoised[t]} is {image.shape[1]}x{image.shape[2]} (HxW), "
                                  f"reference {ref_path} is {ref_image.shape[1]}x{ref_image.shape[2]}")
        pred.append(image)
    pred = np.stack(pred)
    cuts = [bool(m.get("camera_cut", False)) for m in ref_meta]
    scores = score_sequence(pred, reference, cuts, cfg["evaluation"]["warmup_frames"])
    table = pd.DataFrame({"frame": ref_frames, **scores, "camera_cut": cuts,
                          "nonfinite_output": (~np.isfinite(pred)).sum(axis=(1, 2, 3)),
                          "reference_psnr_halves": [m.get("psnr_halves", np.nan) for m in ref_meta]})
    if record is not None:   # first: a CSV on disk always has its sidecar
        write_text_atomic(metrics_sidecar(out_csv), json.dumps(record, indent=1) + "\n")
    write_text_atomic(out_csv, table.to_csv(index=False))
    return table


# ---------------------------------------------------------------------------------------------------
# Robustness: spikes and NaN/Inf injected into the noisy samples
# ---------------------------------------------------------------------------------------------------

def inject_corruption(samples: dict[str, np.ndarray], *, seed: int, scene: str, spike_fraction: float,
                      spike_max_factor: float, nonfinite_fraction: float, frames: Sequence[int]) -> dict[str, int]:
    """Corrupt per-sample buffers {buffer: (T, S, C, H, W)} in place and return the counts.

    Per frame: in ``radiance``, ``max(1, round(spike_fraction * S*H*W))`` random samples get
    ``m * mean`` added to every channel, m ~ U(0, spike_max_factor) and mean = the frame's mean
    radiance (Isik et al. 2021, Fig. 3: perturbations up to 500x the image mean). In every buffer,
    ``max(1, round(nonfinite_fraction * S*H*W))`` random samples have all channels set to NaN, +Inf or
    -Inf in turn (the cycle starts one step later in every frame). Positions depend only on (seed, scene, buffer, frame), so every method sees the same
    corruption of the buffers it reads.
    """
    from scenegen.seeds import derive_seed

    counts = {"spikes": 0, "nan_values": 0, "inf_values": 0}
    for buffer, stack in samples.items():
        _, n_samples, n_channels, height, width = stack.shape
        positions = n_samples * height * width
        for i, t in enumerate(frames):
            rng = np.random.default_rng(derive_seed(seed, "robustness", scene, buffer, int(t)))
            # (S, C, H, W) -> (C, S*H*W) copy so that one index picks one sample of one pixel.
            flat = np.moveaxis(stack[i], 1, 0).reshape(n_channels, positions)
            if buffer == "radiance":
                n_spikes = max(1, round(spike_fraction * positions))
                where = rng.choice(positions, n_spikes, replace=False)
                frame_mean = float(flat.mean())
                flat[:, where] += rng.uniform(0.0, spike_max_factor, n_spikes)[None, :] * frame_mean
                counts["spikes"] += n_spikes
            n_bad = max(1, round(nonfinite_fraction * positions))
            where = rng.choice(positions, n_bad, replace=False)
            # Cycle NaN, +Inf, -Inf, starting one further each frame so that every kind occurs even
            # when a frame gets a single bad sample.
            values = np.array([np.nan, np.inf, -np.inf], np.float32)[(np.arange(n_bad) + i) % 3]
            flat[:, where] = values[None, :]
            counts["nan_values"] += int(np.isnan(values).sum()) * n_channels
            counts["inf_values"] += int(np.isinf(values).sum()) * n_channels
            stack[i] = np.moveaxis(flat.reshape(n_channels, n_samples, height, width), 0, 1)
    return counts


def robustness_clip(cfg: dict, method_id: str, scene: str, spp: int, render_dir: Path, out_dir: Path,
                    threads: int = 1, results: Path | str | None = None) -> dict[str, Any]:
    """Run one method at ``spp`` on a clip whose noisy samples carry injected spikes and NaN/Inf (settings
    in ``evaluation.robustness``) and score it against the reference. Writes ``out_dir`` atomically:
    metrics.csv (per frame), summary.json (counts, settings digest), last_frame.exr (the output of the last frame)."""
    import pandas as pd

    from denoisers.experiment import DIGEST_KEY, Lineage

    settings = cfg["evaluation"]["robustness"]
    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=True)
    injected = inject_corruption(clip.samples, seed=cfg["seed"], scene=scene, frames=clip.frames,
                                 spike_fraction=settings["spike_fraction"],
                                 spike_max_factor=settings["spike_max_factor"],
                                 nonfinite_fraction=settings["nonfinite_fraction"])
    result = run_method(method, _frames(clip, method, layers), threads,
                        cfg["evaluation"]["out_of_range_factor"])
    cuts = [bool(m.get("camera_cut", False)) for m in clip.meta]
    scores = score_sequence(result.radiance, clip.reference["radiance"], cuts, cfg["evaluation"]["warmup_frames"])
    table = pd.DataFrame({"frame": clip.frames, **scores, "camera_cut": cuts,
                          "nonfinite_input": result.nonfinite_inputs, "nonfinite_output": result.nonfinite_outputs,
                          "out_of_range_output": result.out_of_range_outputs})
    summary = {"method_id": spec.id, "method": spec.method, "scene": scene, "spp": spp,
               "settings": dict(settings), "injected": injected,
               "nonfinite_inputs": int(sum(result.nonfinite_inputs)),
               "nonfinite_outputs": int(sum(result.nonfinite_outputs)),
               **out_of_range_record(result),
               "mean_psnr": float(np.nanmean(scores["psnr"])), DIGEST_KEY: Lineage(cfg).robustness(spec, scene, spp)}
    with atomic_directory(out_dir) as staging:
        (staging / ROBUSTNESS_CSV).write_text(table.to_csv(index=False), encoding="utf-8")
        (staging / ROBUSTNESS_SUMMARY).write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
        write_radiance_exr(staging / ROBUSTNESS_LAST_EXR, result.radiance[-1])
    return summary
