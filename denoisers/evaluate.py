"""Evaluation planning: which rows, scenes and (row, spp) runs the workflow's evaluation rules have,
where their outputs go, and the radiance EXR/PNG helpers the evaluation jobs and the report share.

The evaluated scenes are the held-out test scenes (``test_*``) and the external scenes (``custom_*``,
bring-your-own XML); each is an independent unit of every comparison. The robustness scenario runs
on all of them too (its cost is one job per scene and row, like the evaluation's).

The jobs behind the evaluation rules live in modules that import this one (never the reverse):

* denoisers.jobs.denoise: rule denoise_row (per clip), one method on one evaluated scene at one spp -> EXR + PNG + timing.json
* denoisers.jobs.scoring:     rule evaluate_row (per clip), per-frame metrics of a denoised clip against the reference -> CSV
* denoisers.jobs.robustness:  rule robustness_row (per clip), one method on a clip with injected spikes and NaN/Inf -> CSV

This module imports nothing heavy: the Snakefile calls the config-level helpers (method list, test
scenes, which (method, spp) pairs can run) while it is parsed, and importing torch there would slow
down every ``snakemake`` invocation. The registry, the metrics and the EXR/PNG libraries are imported
by the functions that use them.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from denoisers.training.models import resolve_method_params
from scenegen.catalog import CUSTOM_PREFIX, SCENE_SPLITS, scene_frame_count, scene_ids

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
#: Per-frame diagnostic maps of a method (Denoiser.diagnostics, e.g. AFN's lambda): arrays (T, H, W) + frames.
MAPS_FILE = "maps.npz"
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
METHOD_ROLE, ABLATION_ROLE, VOLUME_ROLE = "method", "ablation", "volume"
#: Role of a row that evaluates a seed replica (training.seeds > 1) of another row's model: id
#: ``{row}_seed{k}``; tables fold it into its row's seed mean and spread, claims into seed-averaged values.
SEED_ROLE = "seed"
#: Role of a row that evaluates a half-budget twin (training.half_budget) of another row's model: id
#: ``{row}_half``; the claims compare their decisions at half the budget with those at the full budget.
BUDGET_ROLE = "budget"
#: Default of ``evaluation.out_of_range_factor`` (the schema's default).
OUT_OF_RANGE_FACTOR = 10.0


@dataclass(frozen=True)
class MethodSpec:
    """One evaluation row: row name, registry name, constructor parameters, the sample counts it is
    evaluated at, whether it runs in the spike/NaN scenario, and its role: ``"method"`` for a row of
    ``evaluation.methods``, ``"ablation"`` for a row added for a trained ablation variant, ``"volume"`` for a
    row of ``volumes.rows`` (run on the volumetric clips only, denoisers.jobs.volumes)."""

    id: str
    method: str
    params: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    spp: tuple[int, ...] = ()
    robustness: bool = True
    role: str = METHOD_ROLE
    #: A seed row's first-seed row and replica index k >= 1 (also on the half-budget rows of seed rows, pointing to
    #: the first seed's half-budget row); None and 0 for every other row.
    seed_of: str | None = None
    replica: int = 0
    #: A half-budget row's (role ``budget``) full-budget row; None for every other row.
    budget_of: str | None = None

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
    ``ablation`` set): id and ``params.model`` = the model id, at the variant's own ``spp``, else its ablation's,
    else ``evaluation.ablation_spp`` (default [1]; [] = none), not in the robustness scenario."""
    from denoisers.training.models import model_specs

    default = cfg["evaluation"].get("ablation_spp", [1])
    ablations = (cfg.get("training") or {}).get("ablations", [])
    own = {entry["id"]: entry["spp"] for entry in ablations if "spp" in entry}
    own_variant = {(entry["id"], variant["id"]): variant["spp"] for entry in ablations
                   for variant in entry["variants"] if "spp" in variant}
    specs = []
    for model in model_specs(cfg):
        spp = (_row_spp(cfg, own_variant.get((model.ablation, model.variant), own.get(model.ablation, default)))
               if model.ablation else [])
        if spp:
            specs.append(MethodSpec(model.id, model.method, {"model": model.id}, spp, robustness=False,
                                    role=ABLATION_ROLE))
    return specs


def seed_method_specs(cfg: dict, rows: Sequence[MethodSpec]) -> list[MethodSpec]:
    """For every row of ``rows`` that uses a trained model (``params.model``) and k = 1 .. the model's seeds - 1
    (training.seeds, or its ablation's ``seeds``):
    row ``{row}_seed{k}`` with the model's seed replica k (denoisers.training.models.replica_id), at the row's
    spp, not in the robustness scenario, role ``seed``. Empty with one seed."""
    from denoisers.training.models import SEED_SUFFIX, method_model, model_seed_count, replica_id

    return [MethodSpec(f"{row.id}{SEED_SUFFIX}{k}", row.method,
                       {**row.params, "model": replica_id(method_model(row.params), k)}, row.spp, robustness=False,
                       role=SEED_ROLE, seed_of=row.id, replica=k)
            for row in rows if method_model(row.params)
            for k in range(1, model_seed_count(cfg, method_model(row.params)))]


def half_budget_method_specs(cfg: dict, rows: Sequence[MethodSpec]) -> list[MethodSpec]:
    """For every row of ``rows`` that uses a trained model (seed rows included), with training.half_budget: row
    ``{row}_half`` with the model's half-budget twin ``{model}_half``, at the row's spp, not in the robustness
    scenario, role ``budget``; the half-budget row of seed row k is seed row k of the first seed's."""
    from denoisers.training.models import HALF_SUFFIX, half_budget_enabled, method_model

    if not half_budget_enabled(cfg):
        return []
    return [MethodSpec(f"{row.id}{HALF_SUFFIX}", row.method,
                       {**row.params, "model": f"{method_model(row.params)}{HALF_SUFFIX}"}, row.spp, robustness=False,
                       role=BUDGET_ROLE, seed_of=f"{row.seed_of}{HALF_SUFFIX}" if row.seed_of else None,
                       replica=row.replica, budget_of=row.id)
            for row in rows if method_model(row.params)]


def method_specs(cfg: dict) -> list[MethodSpec]:
    """The evaluation rows in table order: ``evaluation.methods`` (spp default: every evaluated spp;
    robustness default: true), then one row per trained ablation variant (:func:`ablation_method_specs`), then
    the seed rows of both (:func:`seed_method_specs`), then the half-budget rows of all of these
    (:func:`half_budget_method_specs`)."""
    configured = [MethodSpec(entry["id"], entry["method"], dict(entry.get("params") or {}),
                             _row_spp(cfg, entry.get("spp")), bool(entry.get("robustness", True)), METHOD_ROLE)
                  for entry in cfg["evaluation"]["methods"]]
    rows = configured + ablation_method_specs(cfg)
    rows += seed_method_specs(cfg, rows)
    return rows + half_budget_method_specs(cfg, rows)


def volume_method_specs(cfg: dict) -> list[MethodSpec]:
    """The rows run on the volumetric clips (``volumes.rows``, when ``volumes.enabled``), each at the values of
    ``volumes.denoise_spp`` its own ``spp`` keeps (all when absent); never in the robustness scenario."""
    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return []
    denoise_spp = [int(s) for s in volumes.get("denoise_spp", [])]
    rows = [MethodSpec(entry["id"], entry["method"], dict(entry.get("params") or {}),
                       tuple(s for s in denoise_spp if entry.get("spp") is None or s in entry["spp"]),
                       robustness=False, role=VOLUME_ROLE)
            for entry in volumes.get("rows", [])]
    rows += seed_method_specs(cfg, rows)
    return rows + half_budget_method_specs(cfg, rows)


def method_spec(cfg: dict, method_id: str) -> MethodSpec:
    """The spec of row ``method_id`` (configured, ablation or volume row); KeyError listing the ids otherwise."""
    specs = method_specs(cfg) + volume_method_specs(cfg)
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
    from scenegen.channels import RADIANCE_BUFFER, SAMPLE_BUFFERS

    render = cfg["render"]
    return {buffer: render["spp"] + (render["extra_radiance_spp"] if buffer == RADIANCE_BUFFER else 0)
            for buffer in SAMPLE_BUFFERS}


def evaluation_problems(cfg: dict, check_methods: bool = True) -> list[str]:
    """Constraints of the ``evaluation`` section the JSON schema cannot express (schema-valid cfg);
    ``check_methods`` False leaves out the registry lookup of every row's method (it imports torch)."""
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
    for entry in (cfg.get("training") or {}).get("ablations", []):
        owners = [(f"entry {entry['id']!r}", entry, "its variants"),
                  *((f"entry {entry['id']!r} variant {variant['id']!r}", variant, "it")
                    for variant in entry["variants"])]
        for where, owner, what in owners:
            own_outside = [spp for spp in owner.get("spp", []) if spp not in evaluated]
            if own_outside:
                problems.append(f"config key 'training.ablations' {where} has spp {owner['spp']!r} with values "
                                f"{own_outside} that are not in 'evaluation.spp' = {evaluated!r}; allowed: values of "
                                f"evaluation.spp, or [] to not evaluate {what}")
    if variants and outside:
        problems.append(f"config key 'evaluation.ablation_spp' = {ablation_spp!r} has values {outside} that are not in "
                        f"'evaluation.spp' = {evaluated!r}; allowed: values of evaluation.spp, or [] to not "
                        "evaluate the ablation variants")
    rows = method_specs(cfg) + volume_method_specs(cfg)
    if check_methods:
        problems += [problem for spec in rows if spec.role not in (SEED_ROLE, BUDGET_ROLE)
                     for problem in [method_name_problem(cfg, spec)] if problem]
    added = {spec.id for spec in rows if spec.role in (SEED_ROLE, BUDGET_ROLE)}
    for method_id in sorted(added & {spec.id for spec in rows if spec.role not in (SEED_ROLE, BUDGET_ROLE)}):
        problems.append(f"evaluation row id {method_id!r} is also the id of a row the config adds for a trained "
                        "model (training.seeds > 1: {row}_seed{k}; training.half_budget: {row}_half); allowed: "
                        "another row id")
    evaluated_variants = [spec.id for spec in ablation_method_specs(cfg)]
    for method_id in sorted(set(ids) & set(evaluated_variants)):
        problems.append(f"config key 'evaluation.methods' has the id {method_id!r}, which is the id of the row "
                        "added for that trained ablation variant (evaluation.ablation_spp or its ablation's spp); "
                        f"allowed: ids other than the ablation variants {evaluated_variants}, or "
                        "evaluation.ablation_spp: [] / the ablation's spp: []")
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


def _row_key(cfg: dict, spec: MethodSpec) -> str:
    """The config key that defines row ``spec`` (its method name): evaluation.methods[i], volumes.rows[i] or the
    training ablation that adds it."""
    for section, rows in (("evaluation.methods", cfg["evaluation"]["methods"]),
                          ("volumes.rows", (cfg.get("volumes") or {}).get("rows", []))):
        for index, entry in enumerate(rows):
            if entry["id"] == spec.id:
                return f"{section}[{index}].method"
    return f"training (the row of trained model {spec.id!r})"


def method_name_problem(cfg: dict, spec: MethodSpec) -> str | None:
    """Why the row's method is not registered (its config key, the closest registered name and every one), else
    None."""
    import difflib

    from denoisers import registry

    names = registry.available()
    if spec.method in names:
        return None
    close = difflib.get_close_matches(spec.method, names, n=1)
    return (f"config key '{_row_key(cfg, spec)}' (row {spec.id!r}) = {spec.method!r} is not a registered "
            f"method{f' (did you mean {close[0]!r}?)' if close else ''}; allowed: {', '.join(names)}")


def check_method_name(cfg: dict, spec: MethodSpec) -> None:
    """EvaluationError with :func:`method_name_problem` when the row's method is not registered."""
    problem = method_name_problem(cfg, spec)
    if problem:
        raise EvaluationError(problem)


def _plan(cfg: dict, specs: Sequence[MethodSpec], spps_of) -> list[Run]:
    from denoisers import registry

    available = rendered_layers(cfg)
    runs = []
    for spec in specs:
        spps = spps_of(spec)
        if not spps:
            continue
        check_method_name(cfg, spec)
        method = registry.build(spec.method, resolve_method_params(cfg, spec.params), row=spec.id)
        for spp in spps:
            layers = spp * method.samples_factor
            # An adaptive method reads every stored layer: radiance needs the budget, other buffers one layer.
            short = [buffer for buffer in method.info.inputs if available[buffer] < (
                layers if buffer == "radiance" or not method.info.adaptive else 1)]
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
