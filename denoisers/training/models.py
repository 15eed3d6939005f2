"""Which models the config trains, with what settings, on which scenes (config level: no torch).

``training.models`` lists trained models; every entry of ``training.ablations`` adds one model per
variant, id ``{ablation}_{variant}``, whose settings are the base model's with the variant's ``net`` /
``loss`` / ``data`` keys overriding and the ablation's ``budget`` replacing the base budget (so all
variants of a comparison share data and budget) and the base model's ``compute`` (step arithmetic).
An ablation of ``kind: capacity`` is a size sweep of the base network: its variants may override only
``net`` (e.g. ``width``, ``levels``), so every size trains on the same data with the same seed and budget
(:func:`training_problems` enforces it); denoisers.report.capacity reports it.
Missing data / optimizer / budget / compute keys take the defaults of the config schema
(workflow/schemas/config.schema.yaml, ``$defs``).

Scene split: the ``train_*`` scenes minus the last ``training.validation_scenes`` of them train;
those last ones validate. Test scenes are never read by training.

Evaluation rows use a model through ``params: {model: <id>}``; :func:`resolve_method_params` turns
that into the method's ``checkpoint`` (``<output_dir>/models/<id>/best.pt``).
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import sequence_problems, task_builder, task_problems
from scenegen.catalog import SCENE_SPLITS, training_scene_split, volume_training_split
from scenegen.config import output_root
from scenegen.channels import VOLUME_ZERO_PIXEL_BUFFERS

TRAIN_PREFIX = f"{SCENE_SPLITS[0]}_"
#: Files a finished model directory holds (the rule's output directory).
MODEL_FILE = "best.pt"
MODEL_FILES: tuple[str, ...] = (MODEL_FILE, "curves.csv", "curves.png", "summary.json", "validation.csv",
                                "settings.json")
#: Ablation ids the report knows how to read (Chaitanya et al. 2017 Fig. 3 and §4.4).
INPUT_ABLATION, LOSS_ABLATION = "rae_inputs", "rae_loss"
#: ``training.ablations[*].kind``: a comparison of variants (a paper's ablation) or a capacity sweep of the
#: base network's size (variants override only ``net``; the report picks the smallest adequate size).
COMPARISON_KIND, CAPACITY_KIND = "comparison", "capacity"


def _schema_defaults(definition: str, value: Mapping[str, Any] | None) -> dict[str, Any]:
    """``value`` with the defaults of ``$defs/<definition>`` of the config schema filled in."""
    from scenegen.config import fill_definition_defaults

    return fill_definition_defaults(definition, copy.deepcopy(dict(value or {})))


def _derived_seed(cfg: dict, model_id: str) -> int:
    digest = hashlib.sha256(f"{cfg['seed']}/train/{model_id}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def _base_spec(cfg: dict, entry: Mapping[str, Any]) -> ModelSpec:
    return ModelSpec(
        id=entry["id"], method=entry["method"],
        seed=int(entry["seed"]) if entry.get("seed") is not None else _derived_seed(cfg, entry["id"]),
        net=copy.deepcopy(dict(entry.get("net") or {})), loss=copy.deepcopy(dict(entry.get("loss") or {})),
        data=_schema_defaults("training_data", entry.get("data")),
        optimizer=_schema_defaults("training_optimizer", entry.get("optimizer")),
        budget=_schema_defaults("training_budget", entry.get("budget")),
        compute=_schema_defaults("training_compute", entry.get("compute")),
        threads=int((cfg.get("training") or {}).get("threads") or 1))


def resolve_schedule(optimizer: Mapping[str, Any], budget: Mapping[str, Any]) -> dict[str, Any]:
    """``optimizer`` with its schedule in steps: a step schedule's ``every_fraction`` (of ``budget.max_steps``)
    becomes ``every`` = round(fraction x max_steps) (at least 1), a cosine without ``total_steps`` gets
    max_steps. Specs, digests and the trainer see only the absolute form, so ``every_fraction: 0.35`` at 4000
    steps is the same model as ``every: 1400``, and raising the budget moves the drops with it: a new schedule,
    so a new work directory and a training from scratch, not a continued one that would fail its checkpoint's
    fingerprint."""
    resolved = copy.deepcopy(dict(optimizer))
    schedule = dict(resolved.get("schedule") or {})
    max_steps = int(budget["max_steps"])
    if schedule.get("name") == "step" and "every_fraction" in schedule and "every" not in schedule:
        schedule["every"] = max(1, round(float(schedule.pop("every_fraction")) * max_steps))
    elif schedule.get("name") == "cosine" and schedule.get("total_steps") is None:
        schedule["total_steps"] = max_steps
    resolved["schedule"] = schedule
    return resolved


def model_specs(cfg: dict) -> list[ModelSpec]:
    """Every model the config trains: ``training.models`` in order, then every ablation variant.

    The specs depend on ``seed`` and ``training`` alone; they are built once per distinct pair (a Snakefile asks
    for them for every job) and each call returns its own deep copy, so callers may mutate what they get."""
    key = json.dumps([cfg.get("seed"), cfg.get("training")], sort_keys=True, default=repr)
    specs = _SPECS_CACHE.pop(key, None)
    if specs is None:
        specs = _build_model_specs(cfg)
    _SPECS_CACHE[key] = specs                   # most recently used last
    while len(_SPECS_CACHE) > _SPECS_CACHE_SIZE:
        _SPECS_CACHE.pop(next(iter(_SPECS_CACHE)))
    return pickle.loads(pickle.dumps(specs))    # a deep copy, several times faster than copy.deepcopy


_SPECS_CACHE: dict[str, list[ModelSpec]] = {}
_SPECS_CACHE_SIZE = 16


def _build_model_specs(cfg: dict) -> list[ModelSpec]:
    training = cfg.get("training") or {}
    # Bases keep the configured schedule, so an ablation with its own budget resolves every_fraction against it.
    bases = {entry["id"]: _base_spec(cfg, entry) for entry in training.get("models", [])}
    specs = [ModelSpec(**{**base.__dict__, "optimizer": resolve_schedule(base.optimizer, base.budget)})
             for base in bases.values()]
    for ablation in training.get("ablations", []):
        base = bases.get(ablation["model"])
        if base is None:
            continue  # reported by training_problems
        budget = _schema_defaults("training_budget", ablation["budget"]) if ablation.get("budget") else base.budget
        for variant in ablation["variants"]:
            model_id = variant_model_id(ablation, variant)
            specs.append(ModelSpec(
                id=model_id, method=base.method, seed=base.seed,
                net={**base.net, **copy.deepcopy(variant.get("net") or {})},
                loss={**base.loss, **copy.deepcopy(variant.get("loss") or {})},
                data=_schema_defaults("training_data", {**base.data, **(variant.get("data") or {})}),
                optimizer=resolve_schedule(base.optimizer, budget), budget=copy.deepcopy(budget),
                ablation=ablation["id"], variant=variant["id"], compute=copy.deepcopy(base.compute),
                threads=base.threads))
    return specs


def variant_model_id(ablation: Mapping[str, Any], variant: Mapping[str, Any]) -> str:
    """The model id of one variant of a ``training.ablations`` entry: ``{ablation id}_{variant id}``."""
    return f"{ablation['id']}_{variant['id']}"


#: Id suffix of a seed replica: model ``{id}`` trains again as ``{id}_seed{k}``, k = 1 .. training.seeds - 1.
SEED_SUFFIX = "_seed"


def seed_count(cfg: dict) -> int:
    """``training.seeds``: how many times every model trains (1: once, no replicas)."""
    return int((cfg.get("training") or {}).get("seeds") or 1)


def model_seed_count(cfg: dict, model_id: str) -> int:
    """How many times model ``model_id`` trains: its own ``seeds`` (a ``training.models`` entry or an ablation
    variant), else its ablation's where that is set (e.g. 1 for a capacity sweep, which feeds measurements), else
    :func:`seed_count`."""
    training = cfg.get("training") or {}
    for entry in training.get("models", []):
        if entry["id"] == model_id and entry.get("seeds"):
            return int(entry["seeds"])
    for ablation in training.get("ablations", []):
        for variant in ablation.get("variants", []):
            if variant_model_id(ablation, variant) == model_id:
                return int(variant.get("seeds") or ablation.get("seeds") or seed_count(cfg))
    return seed_count(cfg)


def replica_id(model_id: str, k: int) -> str:
    """The id of seed replica ``k`` of ``model_id`` (k = 0: the model itself)."""
    return model_id if k == 0 else f"{model_id}{SEED_SUFFIX}{k}"


def replica_seed(seed: int, k: int) -> int:
    """The training seed of replica ``k`` of a model trained with ``seed`` (k = 0: ``seed``). A function of the
    model's seed alone, so variants of one ablation, which share the base model's seed, share every replica's."""
    if k == 0:
        return int(seed)
    digest = hashlib.sha256(f"{int(seed)}/replica/{k}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def seed_replicas(cfg: dict) -> list[ModelSpec]:
    """The extra trainings of ``training.seeds``: for every model of :func:`model_specs` and k = 1 .. its seeds - 1
    (:func:`model_seed_count`),
    its spec with id ``{id}_seed{k}`` and seed :func:`replica_seed` (every other setting, ablation labels
    included, unchanged). Empty with one seed."""
    return [ModelSpec(**{**spec.__dict__, "id": replica_id(spec.id, k), "seed": replica_seed(spec.seed, k)})
            for spec in model_specs(cfg) for k in range(1, model_seed_count(cfg, spec.id))]


#: Id suffix of a half-budget model: ``{id}_half`` is model ``{id}`` (a seed replica included) stopped at half its
#: ``budget.max_steps`` (training.half_budget).
HALF_SUFFIX = "_half"


def half_budget_enabled(cfg: dict) -> bool:
    """``training.half_budget``: every model also trains (is evaluated) at half its budget."""
    return bool((cfg.get("training") or {}).get("half_budget"))


def half_steps(max_steps: int) -> int:
    """The step a half-budget model stops at: max_steps // 2 (at least 1)."""
    return max(1, int(max_steps) // 2)


def half_budget_spec(spec: ModelSpec) -> ModelSpec:
    """The half-budget twin of ``spec``: id ``{id}_half``, ``budget.max_steps`` halved, every other setting the
    full model's, the learning-rate schedule included (already resolved against the full budget): its weights are
    the full run's at its middle step (the training job stops the full run there; denoisers.training.job)."""
    return ModelSpec(**{**spec.__dict__, "id": f"{spec.id}{HALF_SUFFIX}",
                        "budget": {**spec.budget, "max_steps": half_steps(spec.budget["max_steps"])}})


def half_budget_specs(cfg: dict) -> list[ModelSpec]:
    """The half-budget twin of every model and seed replica (empty unless training.half_budget)."""
    if not half_budget_enabled(cfg):
        return []
    return [half_budget_spec(spec) for spec in model_specs(cfg) + seed_replicas(cfg)]


def half_of(cfg: dict, model_id: str) -> str | None:
    """The full model (a seed replica included) whose half-budget twin ``model_id`` is, else None."""
    if not half_budget_enabled(cfg) or not model_id.endswith(HALF_SUFFIX):
        return None
    full = model_id[:-len(HALF_SUFFIX)]
    return full if full in {spec.id for spec in model_specs(cfg) + seed_replicas(cfg)} else None


def trained_model_specs(cfg: dict) -> list[ModelSpec]:
    """Every training the config runs: :func:`model_specs`, the seed replicas (:func:`seed_replicas`), then the
    half-budget twins (:func:`half_budget_specs`)."""
    return model_specs(cfg) + seed_replicas(cfg) + half_budget_specs(cfg)


def replica_ids(cfg: dict, model_id: str) -> list[str]:
    """``model_id`` and the ids of its seed replicas, seed order."""
    return [replica_id(model_id, k) for k in range(model_seed_count(cfg, model_id))]


def replica_of(cfg: dict, model_id: str) -> tuple[str, int] | None:
    """(model id, k) when ``model_id`` is seed replica k >= 1 of a configured model, else None."""
    for spec in model_specs(cfg):
        for k in range(1, model_seed_count(cfg, spec.id)):
            if replica_id(spec.id, k) == model_id:
                return spec.id, k
    return None


def model_spec(cfg: dict, model_id: str) -> ModelSpec:
    """The spec of model ``model_id`` (a seed replica included); KeyError listing the configured ids otherwise."""
    specs = trained_model_specs(cfg)
    for spec in specs:
        if spec.id == model_id:
            return spec
    known = ", ".join(spec.id for spec in specs) or "none"
    raise KeyError(f"no trained model with id {model_id!r}; configured models: {known}")


#: What determines a model's weights besides its id and ablation labels (ModelSpec.settings() minus those).
_TRAINING_KEYS = ("method", "seed", "net", "loss", "data", "optimizer", "budget", "compute", "threads")


def same_training_as(cfg: dict, model_id: str) -> str | None:
    """The base model an ablation variant is identical to (same method, seed, net, loss, data, optimizer,
    budget and compute: e.g. Fig. 3's "all inputs" or the combined loss at the base's budget), else None.

    Such a variant is not trained again: its job publishes the base's weights under its own id
    (``denoisers.training.job``), so the comparison still has its row and the DAG pays for one training."""
    full = half_of(cfg, model_id)
    if full is not None:      # the half of a model that reuses another's weights is that one's half
        same = same_training_as(cfg, full)
        return f"{same}{HALF_SUFFIX}" if same else None
    replica = replica_of(cfg, model_id)
    if replica is not None:   # replica k of a variant equal to its base is the base's replica k
        same = same_training_as(cfg, replica[0])
        return replica_id(same, replica[1]) if same else None
    spec = model_spec(cfg, model_id)
    if spec.ablation is None:
        return None
    ablation = next(a for a in (cfg.get("training") or {}).get("ablations", []) if a["id"] == spec.ablation)
    base = model_spec(cfg, ablation["model"])
    same = all(spec.settings()[key] == base.settings()[key] for key in _TRAINING_KEYS)
    return base.id if same else None


def ablation_variants(cfg: dict, ablation_id: str) -> dict[str, ModelSpec]:
    """variant id -> spec of one ablation (empty if the config has no such ablation)."""
    return {spec.variant: spec for spec in model_specs(cfg) if spec.ablation == ablation_id}


def ablation_kind(ablation: Mapping[str, Any]) -> str:
    """An ablation entry's ``kind`` (default ``comparison``)."""
    return ablation.get("kind") or COMPARISON_KIND


def capacity_ablations(cfg: dict) -> list[dict[str, Any]]:
    """The ``training.ablations`` entries of kind ``capacity`` whose base model is configured, in config order."""
    training = cfg.get("training") or {}
    bases = {entry["id"] for entry in training.get("models", [])}
    return [ablation for ablation in training.get("ablations", [])
            if ablation_kind(ablation) == CAPACITY_KIND and ablation["model"] in bases]


def capacity_model_ids(cfg: dict) -> set[str]:
    """Model ids of the variants of every capacity ablation (their network sizes differ from the base's)."""
    kinds = {ablation["id"] for ablation in capacity_ablations(cfg)}
    return {spec.id for spec in model_specs(cfg) if spec.ablation in kinds}


#: ``data.scenes`` values: what a model trains on (absent = surfaces).
SURFACE_DATA, VOLUME_DATA = "surfaces", "volumes"


def trains_on_volumes(spec: ModelSpec | None) -> bool:
    return spec is not None and spec.data.get("scenes", SURFACE_DATA) == VOLUME_DATA


def training_split(cfg: dict, spec: ModelSpec | None = None) -> tuple[list[str], list[str]]:
    """(training scenes, validation scenes) of model ``spec`` (None: the surface models'): the train_* ids with
    the last ``validation_scenes`` held out, or, for a model with ``data.scenes: volumes``, the vol_train_* clips
    (scenegen.catalog.volume_training_split)."""
    if trains_on_volumes(spec):
        return volume_training_split(cfg)
    return training_scene_split(cfg)


def model_dir(results: Path | str, model_id: str) -> Path:
    return Path(results) / "models" / model_id


def model_checkpoint(results: Path | str, model_id: str) -> Path:
    return model_dir(results, model_id) / MODEL_FILE


def settings_digest(spec: ModelSpec, extra: Mapping[str, Any] | None = None) -> str:
    """SHA-256 of a model's settings (and ``extra``, e.g. the scene split)."""
    payload = json.dumps({"model": spec.settings(), "extra": dict(extra or {})}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()


def resolve_method_params(cfg: dict, params: Mapping[str, Any], results: Path | str | None = None, *,
                          method: str | None = None) -> dict[str, Any]:
    """Constructor parameters of an evaluation row: ``model: <id>`` becomes ``checkpoint: <model dir>/best.pt``;
    ``tuned: true`` adds ``method``'s parameters from <results>/tuning/{method}.json (the row's own params
    win). ``results`` defaults to the config's output_dir. With ``method`` None (planning, before any tuning
    ran) ``tuned`` is dropped without reading."""
    from denoisers.jobs.tuning import TUNED_KEY, tuned_params

    results = output_root(cfg) if results is None else results
    resolved = dict(params)
    if resolved.pop(TUNED_KEY, False) and method is not None:
        resolved = {**tuned_params(results, method), **resolved}
    if "model" in resolved:
        model_id = resolved.pop("model")
        model_spec(cfg, model_id)  # KeyError naming the configured models
        resolved["checkpoint"] = str(model_checkpoint(results, model_id))
    return resolved


#: Scheduler wall time of a training job without a ``max_seconds`` cap (minutes).
DEFAULT_TRAINING_RUNTIME_MIN = 120
#: Added to the ``max_seconds`` cap: loading the clips, the final per-sequence validation, copying outputs.
TRAINING_RUNTIME_MARGIN_MIN = 20


def training_runtime_minutes(cfg: dict, model_id: str) -> int:
    """Wall time (minutes) a scheduler should allow the training job of ``model_id``: its ``budget.max_seconds``
    cap (the trainer stops there) plus 10 % and :data:`TRAINING_RUNTIME_MARGIN_MIN`; without a cap
    :data:`DEFAULT_TRAINING_RUNTIME_MIN`. The rule's ``runtime`` resource (SLURM ``--time``)."""
    cap = model_spec(cfg, model_id).budget.get("max_seconds")
    if cap is None:
        return DEFAULT_TRAINING_RUNTIME_MIN
    return int(math.ceil(round(float(cap) * 1.1 / 60.0, 6))) + TRAINING_RUNTIME_MARGIN_MIN  # round: 3600 s -> 66, not 67


def method_model(params: Mapping[str, Any]) -> str | None:
    """The trained model an evaluation row uses (its ``model`` param), if any."""
    return params.get("model")


def _sample_buffers(spec: ModelSpec) -> tuple[str, ...]:
    try:
        return task_builder(spec.method).sample_buffers
    except KeyError:
        return ()           # reported by task_problems


def _pixel_buffers(spec: ModelSpec) -> tuple[str, ...]:
    try:
        return task_builder(spec.method).pixel_buffers
    except KeyError:
        return ()           # reported by task_problems


def training_problems(cfg: dict, build_tasks: bool = True) -> list[str]:
    """Constraints of the ``training`` section the JSON schema cannot express (schema-valid cfg).

    ``build_tasks`` False skips building each model's network and loss (the net / loss keys' check), which
    imports torch: for jobs that never touch a model, once the workflow has checked the whole config."""
    training = cfg.get("training") or {}
    problems: list[str] = []
    base_ids = [entry["id"] for entry in training.get("models", [])]
    for ablation in training.get("ablations", []):
        if ablation["model"] not in base_ids:
            problems.append(f"config key 'training.ablations' entry {ablation['id']!r} names model "
                            f"{ablation['model']!r}, which is not in training.models; allowed: {base_ids}")
        if ablation_kind(ablation) == CAPACITY_KIND:
            for variant in ablation["variants"]:
                other = sorted(key for key in variant if key not in ("id", "net", "seeds", "spp") and variant[key])
                if other:
                    problems.append(f"config key 'training.ablations' entry {ablation['id']!r} (kind capacity) variant "
                                    f"{variant['id']!r} overrides {', '.join(other)}; allowed: only net, and seeds "
                                    "and spp (a capacity ablation trains every size with the base model's data, seed "
                                    "and budget)")
        variant_ids = [v["id"] for v in ablation["variants"]]
        for dup in sorted({v for v in variant_ids if variant_ids.count(v) > 1}):
            problems.append(f"config key 'training.ablations' entry {ablation['id']!r} has variant {dup!r} twice")
    specs = model_specs(cfg)
    ids = [spec.id for spec in specs]
    every = [spec.id for spec in trained_model_specs(cfg)]
    for dup in sorted({i for i in every if every.count(i) > 1}):
        problems.append(f"config key 'training' defines the model id {dup!r} more than once (models, "
                        f"ablation variants {{ablation}}_{{variant}} and seed replicas {{id}}{SEED_SUFFIX}{{k}} "
                        "share one namespace)")
    for entry in cfg["evaluation"]["methods"]:
        model = method_model(entry.get("params") or {})
        if model is not None and model not in ids:
            problems.append(f"config key 'evaluation.methods' row {entry['id']!r} uses model {model!r}, which "
                            f"training does not define; allowed: {ids or 'none (training.models is empty)'}")
    if not specs:
        return problems
    if any(not trains_on_volumes(spec) for spec in specs):
        train, validation = training_split(cfg)
        if not train or not validation:
            problems.append(f"training needs at least one training and one validation scene: scenes.n_train = "
                            f"{cfg['scenes']['n_train']}, training.validation_scenes = "
                            f"{training['validation_scenes']}; allowed: n_train > validation_scenes")
    for spec in specs:
        where = f"training model {spec.id!r}"
        if trains_on_volumes(spec):
            problems += [f"{where}: {problem}" for problem in _volume_data_problems(cfg, spec)]
            problems += [f"{where}: {problem}" for problem in _build_problems(spec)] if build_tasks else []
            continue
        size = min(cfg["render"]["width"], cfg["render"]["height"])
        if spec.data["crop"] > size:
            problems.append(f"{where}: data.crop = {spec.data['crop']} exceeds the frame size {size}")
        frames = cfg["scenes"].get("train_frames") or cfg["scenes"]["frames"]
        if spec.data["length"] > frames:
            key = "scenes.train_frames" if cfg["scenes"].get("train_frames") else "scenes.frames"
            problems.append(f"{where}: data.length = {spec.data['length']} exceeds {key} = {frames}")
        # Radiance has render.spp + extra_radiance_spp layers, every other per-sample buffer render.spp.
        radiance_only = _sample_buffers(spec) == ("radiance",)
        stored = cfg["render"]["spp"] + (cfg["render"].get("extra_radiance_spp") or 0 if radiance_only else 0)
        if spec.data["spp"] > stored:
            what = "render.spp + render.extra_radiance_spp" if radiance_only else "render.spp"
            problems.append(f"{where}: data.spp = {spec.data['spp']} exceeds {what} = {stored}")
        problems += [f"{where}: {problem}" for problem in _build_problems(spec)] if build_tasks else []
    return problems


def _build_problems(spec: ModelSpec) -> list[str]:
    """Why ``spec``'s task (net and loss keys) or its sequences (data keys against the task's buffers) cannot be
    built; the task first, since its sequences need a known method."""
    return task_problems(spec) or sequence_problems(spec)


def _volume_data_problems(cfg: dict, spec: ModelSpec) -> list[str]:
    """Why a model with ``data.scenes: volumes`` cannot train on this config's volumetric training clips."""
    volumes = cfg.get("volumes") or {}
    train, validation = volume_training_split(cfg)
    if not train or not validation:
        return [f"data.scenes = volumes needs volumetric training and validation clips: volumes.enabled = "
                f"{volumes.get('enabled', False)}, volumes.n_train = {volumes.get('n_train', 0)} per scenario, "
                f"training.validation_scenes = {cfg['training'].get('validation_scenes', 2)}; allowed: more "
                "vol_train_* clips than validation_scenes"]
    problems = []
    size = min(volumes["width"], volumes["height"])
    if spec.data["crop"] > size:
        problems.append(f"data.crop = {spec.data['crop']} exceeds the volumetric clips' frame size {size}")
    if spec.data["length"] > volumes["frames"]:
        problems.append(f"data.length = {spec.data['length']} exceeds volumes.frames = {volumes['frames']}")
    stored = volumes["spp"] if volumes.get("spp") is not None else cfg["render"]["spp"]
    if spec.data["spp"] > stored:
        problems.append(f"data.spp = {spec.data['spp']} exceeds volumes.spp = {stored}")
    from scenegen.channels import VOLUME_BUFFERS

    missing = [buffer for buffer in _sample_buffers(spec) if buffer not in VOLUME_BUFFERS]
    missing += [buffer for buffer in _pixel_buffers(spec) if buffer in VOLUME_ZERO_PIXEL_BUFFERS]
    if missing:
        problems.append(f"method {spec.method!r} reads {', '.join(missing)}, which volumetric clips do not have "
                        f"(they hold {', '.join(VOLUME_BUFFERS)}); e.g. method rae_color trains on volumes")
    return problems
