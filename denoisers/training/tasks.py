"""Training tasks of the trainable methods: how a method's ``net`` / ``loss`` settings become a
:class:`denoisers.training.loop.TrainingTask`, and which buffers its batches need.

Adding a learned method = its registry module (denoisers/methods/), its network (denoisers/nets/) and
one ``@register_task(<method name>)`` builder here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from denoisers.training.spec import ModelSpec


@dataclass(frozen=True)
class TaskBuilder:
    """build(spec) -> task; sample_buffers: per-sample buffers the batches carry (``data.spp`` layers each);
    pixel_buffers: per-pixel buffers (denoisers.training.data.PIXEL_KEYS); mean_buffers: per-sample buffers
    carried as their mean over every stored layer (``mean.{buffer}``); optional_reference_buffers: reference
    buffers besides radiance (``reference.{buffer}``) carried when every training and validation clip's
    references hold them (e.g. diffuse / specular: render.reference_integrator features), else left out --
    the task must handle both (denoisers.training.job.reference_buffers)."""

    build: Callable[[ModelSpec], Any]
    sample_buffers: tuple[str, ...]
    pixel_buffers: tuple[str, ...] = ()
    mean_buffers: tuple[str, ...] = ()
    optional_reference_buffers: tuple[str, ...] = ()


_TASKS: dict[str, TaskBuilder] = {}


def register_task(method: str, sample_buffers: tuple[str, ...], pixel_buffers: tuple[str, ...] = (),
                  mean_buffers: tuple[str, ...] = (), optional_reference_buffers: tuple[str, ...] = ()
                  ) -> Callable[[Callable[[ModelSpec], Any]], Callable[[ModelSpec], Any]]:
    """Decorator: ``build(spec)`` makes the training task of registry method ``method``."""

    def decorate(build: Callable[[ModelSpec], Any]) -> Callable[[ModelSpec], Any]:
        _TASKS[method] = TaskBuilder(build, tuple(sample_buffers), tuple(pixel_buffers), tuple(mean_buffers),
                                     tuple(optional_reference_buffers))
        return build

    return decorate


def task_builder(method: str) -> TaskBuilder:
    """The builder of ``method``; KeyError naming the trainable methods otherwise."""
    if method not in _TASKS:
        raise KeyError(f"method {method!r} cannot be trained; trainable methods: {', '.join(sorted(_TASKS))}")
    return _TASKS[method]


def build_task(spec: ModelSpec) -> Any:
    return task_builder(spec.method).build(spec)


def task_problems(spec: ModelSpec) -> list[str]:
    """Why ``spec`` cannot be built (unknown method, unknown net / loss keys, bad values); empty if it can."""
    try:
        build_task(spec)
    except (KeyError, TypeError, ValueError) as error:
        return [str(error.args[0]) if error.args else str(error)]
    return []


def sequence_problems(spec: ModelSpec) -> list[str]:
    """Why ``spec``'s data keys (schema-filled) cannot cut the sequences its task's buffers need, e.g. backward
    playback of sequences that carry motion vectors; empty if they can (or if the method is unknown, which
    :func:`task_problems` reports)."""
    if spec.method not in _TASKS:
        return []
    try:
        task_sequence_config(_TASKS[spec.method], spec, [])
    except (TypeError, ValueError) as error:
        return [str(error.args[0]) if error.args else str(error)]
    return []


def sequence_config(spec: ModelSpec, sample_buffers: tuple[str, ...], pixel_buffers: tuple[str, ...] = (),
                    mean_buffers: tuple[str, ...] = (), reference_buffers: tuple[str, ...] = ("radiance",)) -> Any:
    """The SequenceConfig of ``spec``'s data keys carrying these buffers (ValueError if they disagree)."""
    from denoisers.training.data import SequenceConfig

    data = spec.data
    return SequenceConfig(length=data["length"], crop=data["crop"], spp=data["spp"], rotate=data["rotate"],
                          flip=data["flip"], color_range=data["color_range"], backward_prob=data["backward_prob"],
                          stop_prob=data["stop_prob"], sample_buffers=sample_buffers, layers=data["layers"],
                          crops=data["crops"], importance_floor=data["importance_floor"],
                          permute_channels=bool(data.get("permute_channels", False)),
                          grayscale_prob=float(data.get("grayscale_prob", 0.0)),
                          pixel_buffers=pixel_buffers, mean_buffers=mean_buffers,
                          reference_buffers=reference_buffers)


def reference_buffers(builder: Any, clips: Any) -> tuple[str, ...]:
    """Reference buffers a task's batches carry: radiance, plus each of the builder's
    ``optional_reference_buffers`` that every clip's references hold (all clips or none, so that every batch,
    training and validation, has the same keys)."""
    optional = tuple(getattr(builder, "optional_reference_buffers", ()))
    held = [b for b in optional if all(c.reference is not None and b in c.reference for c in clips)]
    return ("radiance", *held)


def clip_buffers(builder: Any) -> tuple[str, ...]:
    """Buffers to load from the renders for a task: its per-sample buffers, then its per-pixel means."""
    return tuple(dict.fromkeys(builder.sample_buffers + builder.mean_buffers))


def task_sequence_config(builder: Any, spec: ModelSpec, clips: Any) -> Any:
    """The SequenceConfig a task's batches need (sample, pixel, mean and reference buffers) for ``spec``'s data
    keys; ``clips`` decide the optional reference buffers (:func:`reference_buffers`)."""
    return sequence_config(spec, builder.sample_buffers, builder.pixel_buffers, builder.mean_buffers,
                           reference_buffers(builder, clips))


# ------------------------------------------------------------------------------------------- RAE
RAE_BUFFERS = ("radiance", "albedo", "normal", "depth", "roughness")


@register_task("rae_samples", sample_buffers=RAE_BUFFERS)
def _rae_task(spec: ModelSpec) -> Any:
    """RAE (Chaitanya et al. 2017) on features averaged over the samples: net keys of RAEConfig, loss weights
    spatial / gradient / temporal."""
    from denoisers.losses import RAE_LOSS_WEIGHTS
    from denoisers.nets.rae import RAEConfig
    from denoisers.nets.rae_task import RAETask

    unknown = set(spec.loss) - set(RAE_LOSS_WEIGHTS)
    if unknown:
        raise KeyError(f"rae: unknown loss terms {sorted(unknown)}; known: {sorted(RAE_LOSS_WEIGHTS)}")
    weights = {**RAE_LOSS_WEIGHTS, **{k: float(v) for k, v in spec.loss.items()}}
    if any(w < 0 for w in weights.values()) or not any(w > 0 for w in weights.values()):
        raise ValueError(f"rae: loss weights must be >= 0 with at least one > 0, got {weights}")
    return RAETask(config=RAEConfig.from_dict(spec.net), loss_weights=weights)


@register_task("rae_color", sample_buffers=("radiance",))
def _rae_color_task(spec: ModelSpec) -> Any:
    """The colour-only RAE (Iglesias-Guitian et al. 2022 retrain the RAE on colour alone for volumes): the RAE's
    keys, with net demodulate false and features [] required."""
    from denoisers.nets.rae_task import COLOR_INPUT_BUFFERS, RAETask

    task = _rae_task(spec)
    return RAETask(config=task.config, loss_weights=task.loss_weights, name="rae_color", buffers=COLOR_INPUT_BUFFERS)


@register_task("rae", sample_buffers=("radiance",),
               pixel_buffers=("gbuffer.albedo", "gbuffer.normal", "gbuffer.depth", "gbuffer.roughness"))
def _rae_gbuffer_task(spec: ModelSpec) -> Any:
    """RAE (Chaitanya et al. 2017) reading its albedo and auxiliary features from the pixel-centre G-buffer, as
    the paper's rasterised G-buffer (§3.1-3.2): the keys of ``rae_samples``; net features_from is set to gbuffer."""
    import dataclasses

    from denoisers.nets.rae_task import COLOR_INPUT_BUFFERS, RAETask

    if spec.net.get("features_from", "gbuffer") != "gbuffer":
        raise ValueError(f"rae: net features_from must be gbuffer (or left out), got {spec.net['features_from']!r}")
    task = _rae_task(spec)
    config = dataclasses.replace(task.config, features_from="gbuffer")
    return RAETask(config=config, loss_weights=task.loss_weights, name="rae", buffers=COLOR_INPUT_BUFFERS)


# ------------------------------------------------------------------------------------------- NTASD
#: Registry method -> (net.variant, net.sampling) of the Hasselgren et al. 2020 rows (Fig. 7, Table 1).
NTASD_VARIANTS: dict[str, tuple[str, str]] = {
    "ntasd": ("temporal", "adaptive"), "ntasd_uniform": ("temporal", "uniform"), "ntasd_kpn": ("kpn", "uniform"),
    "ntasd_direct": ("direct", "uniform"), "dasr": ("kpn", "dasr")}
NTASD_LOSS_KEYS = ("budget",)


def _ntasd_task(spec: ModelSpec) -> Any:
    """NTASD variants: net keys of NTASDConfig except variant/sampling (fixed by the method), ``max_samples``
    from ``data.spp`` (the radiance layers a batch carries); loss key ``budget`` (average training spp, 4)."""
    from denoisers.nets.ntasd import NTASDConfig
    from denoisers.nets.ntasd_task import DEFAULT_TRAIN_BUDGET, NTASDTask

    variant, sampling = NTASD_VARIANTS[spec.method]
    fixed = {"variant", "sampling", "max_samples"} & set(spec.net)
    if fixed:
        raise KeyError(f"{spec.method}: net keys {sorted(fixed)} are fixed by the method (variant, sampling) or "
                       "by data.spp (max_samples)")
    unknown = set(spec.loss) - set(NTASD_LOSS_KEYS)
    if unknown:
        raise KeyError(f"{spec.method}: unknown loss keys {sorted(unknown)}; known: {list(NTASD_LOSS_KEYS)}")
    budget = float(spec.loss.get("budget", DEFAULT_TRAIN_BUDGET))
    available = int(spec.data["spp"])
    if not 0 < budget <= available or (sampling == "dasr" and budget < 1):
        raise ValueError(f"{spec.method}: loss.budget = {budget} must lie in (0, data.spp = {available}] "
                         "(and >= 1 for dasr's initial pass)")
    if spec.data.get("backward_prob", 0) and variant == "temporal":
        raise ValueError(f"{spec.method}: data.backward_prob must be 0 (backward playback has no motion vectors)")
    config = NTASDConfig(**{**spec.net, "variant": variant, "sampling": sampling, "max_samples": available})
    return NTASDTask(config=config, budget=budget, name=spec.method)


for _method in NTASD_VARIANTS:
    register_task(_method, sample_buffers=("radiance",), pixel_buffers=("motion", "valid", "gbuffer.normal",
                                                                        "gbuffer.depth"),
                  mean_buffers=("albedo",))(_ntasd_task)


# ------------------------------------------------------------------------------------------- AFN
def _afn_task(spec: ModelSpec) -> Any:
    """AFN (Isik et al. 2021): net keys of AFNConfig; loss keys ``temporal`` (0.25), ``regularizer`` (1e-5) and
    ``spp_choices`` (the training round-robin over samples per pixel, [1, 2, 4]; each <= data.spp)."""
    from denoisers.nets.afn import AFNConfig
    from denoisers.nets.afn_task import LOSS_DEFAULTS, AFNTask
    from denoisers.training.spp_schedule import check_choices

    unknown = set(spec.loss) - set(LOSS_DEFAULTS)
    if unknown:
        raise KeyError(f"afn: unknown loss keys {sorted(unknown)}; known: {sorted(LOSS_DEFAULTS)}")
    loss = {**LOSS_DEFAULTS, **spec.loss}
    choices = check_choices("afn", loss["spp_choices"], int(spec.data["spp"]))
    if float(loss["temporal"]) < 0 or float(loss["regularizer"]) < 0:
        raise ValueError(f"afn: loss weights must be >= 0, got temporal {loss['temporal']}, regularizer "
                         f"{loss['regularizer']}")
    config = AFNConfig.from_dict(spec.net)
    if config.temporal and spec.data.get("backward_prob", 0):
        raise ValueError("afn: data.backward_prob must be 0 for a temporal model (backward playback has no "
                         "motion vectors)")
    return AFNTask(config=config, temporal_weight=float(loss["temporal"]), regularizer=float(loss["regularizer"]),
                   spp_choices=choices)


register_task("afn", sample_buffers=("radiance", "diffuse", "specular", "normal", "depth", "roughness", "albedo",
                                     "flags"), pixel_buffers=("motion", "valid"))(_afn_task)


# ------------------------------------------------------------------------------------------- KPCN
def _kpcn_task(spec: ModelSpec) -> Any:
    """KPCN (Bako et al. 2017): net keys of KPCNConfig; loss key ``spp_choices`` (the training round robin over
    samples per pixel, as AFN's; default: every carried layer). The loss itself has no settings (per-branch L1
    when the references hold diffuse / specular, else L1 on log radiance: denoisers.nets.kpcn_task)."""
    from denoisers.nets.kpcn import KPCNConfig
    from denoisers.nets.kpcn_task import KPCNTask
    from denoisers.training.spp_schedule import check_choices

    unknown = set(spec.loss) - {"spp_choices"}
    if unknown:
        raise KeyError(f"kpcn: unknown loss keys {sorted(unknown)}; known: ['spp_choices']")
    choices = spec.loss.get("spp_choices")
    return KPCNTask(config=KPCNConfig.from_dict(spec.net),
                    spp_choices=check_choices("kpcn", choices, int(spec.data["spp"])) if choices else None)


register_task("kpcn", sample_buffers=("radiance", "diffuse", "specular", "albedo", "normal", "depth"),
              optional_reference_buffers=("diffuse", "specular"))(_kpcn_task)
