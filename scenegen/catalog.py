"""The scenes a config holds and their per-scene settings.

Scene ids: ``train_NNN`` and ``test_NNN`` (procedural), ``custom_{name}`` (bring-your-own XML, config
``extra_scenes``), ``stab_{scenario}`` with their controls ``stab_{scenario}__still`` (the stability suite) and
``vol_{split}_{scenario}_{index}`` / ``vol_custom_{name}`` (volumetric clips); which of them train and which are
held out for validation; and, per scene, its render settings, reference spp, frame count and render chunks.
Loading and validating the config itself is :mod:`scenegen.config`.
"""
from __future__ import annotations

import math
from typing import Any

SCENE_SPLITS = ("train", "test")
CUSTOM_PREFIX = "custom_"
#: Scene ids of the stability scenarios (config section ``stability``, scenegen.scenarios): stab_{scenario}.
#: They are rendered and masked (target ``stability``), never trained on or evaluated by the evaluation rows.
STABILITY_PREFIX = "stab_"
#: Suffix of a scenario's failure-free control clip, stab_{name}__still (scenegen.scenarios.hold_final_frame):
#: rendered and denoised like its scenario, scored only as the steady state of the scenario's lag metric.
STABILITY_CONTROL_SUFFIX = "__still"
#: Scene ids of the volumetric clips (config section ``volumes``, scenegen.volumes.scenes):
#: vol_{split}_{scenario}_{index:03d}, split "test" or "train". Rendered with the volumetric integrators only.
VOLUME_PREFIX = "vol_"
VOLUME_SPLITS = ("test", "train")
#: Bring-your-own volumes (``volumes.extra``): vol_custom_{name}, evaluated like the vol_test_* clips.
VOLUME_CUSTOM_PREFIX = f"{VOLUME_PREFIX}custom_"
#: Scenes whose references render.train_reference_spp applies to (the training and validation scenes).
TRAIN_PREFIX = "train_"
TEST_PREFIX = "test_"
#: Scenes every method is scored on (render.test_reference_spp applies to them): seeded and external.
EVALUATED_PREFIXES = (TEST_PREFIX, CUSTOM_PREFIX)


def extra_scene(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """Return the extra_scenes entry of a custom_{name} scene id; KeyError if there is none."""
    if not scene_id.startswith(CUSTOM_PREFIX):
        raise KeyError(f"{scene_id!r} is not a custom scene id")
    name = scene_id[len(CUSTOM_PREFIX) :]
    for entry in cfg.get("extra_scenes", []):
        if entry["name"] == name:
            return entry
    raise KeyError(f"no extra_scenes entry named {name!r} (scene id {scene_id!r})")


def scene_ids(cfg: dict[str, Any]) -> list[str]:
    """All scene ids: train_000.., test_000.., then custom_{name} for every extra scene."""
    ids = [f"{split}_{index:03d}" for split in SCENE_SPLITS for index in range(cfg["scenes"][f"n_{split}"])]
    ids += [f"{CUSTOM_PREFIX}{entry['name']}" for entry in cfg.get("extra_scenes", [])]
    return ids


def stability_scene_ids(cfg: dict[str, Any]) -> list[str]:
    """Scene ids of the stability scenarios, stab_{name} for every ``stability.scenarios`` entry in config
    order; empty when ``stability.enabled`` is false. Not part of scene_ids (never trained on or evaluated)."""
    stability = cfg.get("stability") or {}
    if not stability.get("enabled", False):
        return []
    return [f"{STABILITY_PREFIX}{name}" for name in stability.get("scenarios", [])]


def stability_control_id(scene_id: str) -> str:
    """The failure-free control clip's id of stability scene ``scene_id``: stab_{name}__still."""
    return f"{scene_id}{STABILITY_CONTROL_SUFFIX}"


def stability_scenario(cfg: dict[str, Any], scene_id: str) -> str:
    """Scenario name of a stab_{name} scene id or of its control stab_{name}__still; KeyError if the config
    does not have the scenario."""
    scene_id = scene_id.removesuffix(STABILITY_CONTROL_SUFFIX)
    if scene_id not in stability_scene_ids(cfg):
        raise KeyError(f"{scene_id!r} is not a stability scene of this config (stability.enabled, "
                       f"stability.scenarios: {', '.join(stability_scene_ids(cfg)) or 'none'})")
    return scene_id[len(STABILITY_PREFIX):]


def volume_scene_ids(cfg: dict[str, Any]) -> list[str]:
    """Scene ids of the volumetric clips: for each split (test, then train) and each ``volumes.scenarios``
    kind in config order, vol_{split}_{scenario}_{index:03d}; empty when ``volumes.enabled`` is false. Not
    part of scene_ids (the surface scenes' split, training and evaluation never see them)."""
    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return []
    return [f"{VOLUME_PREFIX}{split}_{scenario}_{index:03d}" for split in VOLUME_SPLITS
            for scenario in volumes.get("scenarios", []) for index in range(int(volumes.get(f"n_{split}", 0)))] + [
        f"{VOLUME_CUSTOM_PREFIX}{entry['name']}" for entry in volumes.get("extra", [])]


def volume_extra(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """The ``volumes.extra`` entry of a vol_custom_{name} scene id; KeyError otherwise."""
    name = scene_id[len(VOLUME_CUSTOM_PREFIX):]
    for entry in (cfg.get("volumes") or {}).get("extra", []):
        if entry["name"] == name:
            return entry
    raise KeyError(f"no volumes.extra entry named {name!r} (scene id {scene_id!r})")


def volume_clip_spec(cfg: dict[str, Any], scene_id: str) -> tuple[str, str, int]:
    """(split, scenario, index) of a vol_* scene id (a vol_custom_* clip: ('custom', its scenario, 0)); KeyError if
    the config does not have it."""
    if scene_id not in volume_scene_ids(cfg):
        raise KeyError(f"{scene_id!r} is not a volumetric clip of this config (volumes.enabled, volumes.scenarios, "
                       f"volumes.n_test, volumes.n_train, volumes.extra: {', '.join(volume_scene_ids(cfg)) or 'none'})")
    if scene_id.startswith(VOLUME_CUSTOM_PREFIX):
        return "custom", volume_extra(cfg, scene_id).get("scenario", "camera"), 0
    split, rest = scene_id[len(VOLUME_PREFIX):].split("_", 1)
    scenario, index = rest.rsplit("_", 1)
    return split, scenario, int(index)


def volume_training_split(cfg: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(clips that train, validation clips) of the volumetric training clips: vol_train_* ordered index-major
    (index 0 of every scenario, then index 1, ...), the last ``training.validation_scenes`` (default 2) held out,
    so the held-out clips cover the scenarios."""
    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return [], []
    ids = [f"{VOLUME_PREFIX}train_{scenario}_{index:03d}" for index in range(int(volumes.get("n_train", 0)))
           for scenario in volumes.get("scenarios", [])]
    held_out = min(int((cfg.get("training") or {}).get("validation_scenes", 2)), len(ids))
    return ids[:len(ids) - held_out], ids[len(ids) - held_out:]


def scene_render_config(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """The ``render`` settings a scene is rendered with: ``render`` itself, except for the stability scenes,
    whose width, height, spp and reference_spp come from the ``stability`` section (spp null = render.spp),
    and whose references always hold the feature means (their texture masks read the reference albedo), and
    the volumetric clips, whose size, spp, reference spp and path depth come from the ``volumes`` section (no
    radiance-only layers; references with Mitsuba's volpath, radiance only)."""
    if scene_id.startswith(VOLUME_PREFIX):
        volumes = cfg["volumes"]
        spp = volumes["spp"] if volumes.get("spp") is not None else cfg["render"]["spp"]
        return {**cfg["render"], "width": volumes["width"], "height": volumes["height"], "spp": spp,
                "extra_radiance_spp": 0, "reference_spp": volumes["reference_spp"], "train_reference_spp": None,
                "test_reference_spp": None,
                "reference_integrator": "path", "max_depth": volumes["max_depth"]}
    if not scene_id.startswith(STABILITY_PREFIX):
        return cfg["render"]
    stability = cfg["stability"]
    spp = stability["spp"] if stability.get("spp") is not None else cfg["render"]["spp"]
    return {**cfg["render"], "width": stability["width"], "height": stability["height"], "spp": spp,
            "reference_spp": stability["reference_spp"], "train_reference_spp": None, "test_reference_spp": None,
            "reference_integrator": "features"}


def training_scene_split(cfg: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(scenes that train, validation scenes): the train_* ids with the last ``training.validation_scenes``
    (default 2) held out for validation."""
    train = [scene for scene in scene_ids(cfg) if scene.startswith(TRAIN_PREFIX)]
    held_out = min(int((cfg.get("training") or {}).get("validation_scenes", 2)), len(train))
    return train[:len(train) - held_out], train[len(train) - held_out:]


def scene_reference_spp(cfg: dict[str, Any], scene_id: str) -> int:
    """Reference spp of a scene: ``render.train_reference_spp`` for the train_* scenes that train and
    ``render.test_reference_spp_per_scene[scene]``, else ``render.test_reference_spp``, for the evaluated test_*
    and custom_* scenes, each when set (not null), else
    ``render.reference_spp`` (always for the held-out validation scenes, whose references select every model)."""
    if scene_id.startswith((STABILITY_PREFIX, VOLUME_PREFIX)):
        return int(scene_render_config(cfg, scene_id)["reference_spp"])
    render = cfg["render"]
    train_spp = render.get("train_reference_spp")
    if train_spp is not None and scene_id in training_scene_split(cfg)[0]:
        return int(train_spp)
    if scene_id.startswith(EVALUATED_PREFIXES):
        per_scene = render.get("test_reference_spp_per_scene") or {}
        return int(per_scene[scene_id]) if scene_id in per_scene else evaluated_reference_spp(cfg)
    return int(render["reference_spp"])


def evaluated_reference_spp(cfg: dict[str, Any]) -> int:
    """Reference spp of the evaluated test_* and custom_* scenes: ``render.test_reference_spp``, else
    ``render.reference_spp``."""
    test_spp = cfg["render"].get("test_reference_spp")
    return int(test_spp if test_spp is not None else cfg["render"]["reference_spp"])


def reference_spp_exceptions(cfg: dict[str, Any]) -> dict[str, int]:
    """The evaluated scenes of ``cfg`` whose references have their own spp (render.test_reference_spp_per_scene,
    names the config has no scene of left out): {scene id: spp}, sorted by id."""
    per_scene = cfg["render"].get("test_reference_spp_per_scene") or {}
    if not per_scene:
        return {}
    present = set(scene_ids(cfg))
    return {scene: int(spp) for scene, spp in sorted(per_scene.items()) if scene in present}


def evaluated_reference_text(cfg: dict[str, Any]) -> str:
    """'3072 spp' or '3072 spp (test_001: 6144)': the evaluated scenes' reference spp for reports."""
    exceptions = reference_spp_exceptions(cfg)
    extra = ", ".join(f"{scene}: {spp}" for scene, spp in exceptions.items())
    return f"{evaluated_reference_spp(cfg)} spp" + (f" ({extra})" if extra else "")


def scene_frame_count(cfg: dict[str, Any], scene_id: str) -> int:
    """Frames in the clip of a scene (the extra scene's own count for custom scenes; ``scenes.train_frames``,
    when set, for the train_* scenes)."""
    if scene_id.startswith(CUSTOM_PREFIX):
        return int(extra_scene(cfg, scene_id)["frames"])
    if scene_id.startswith(STABILITY_PREFIX):
        return int(cfg["stability"]["frames"])
    if scene_id.startswith(VOLUME_PREFIX):
        return int(cfg["volumes"]["frames"])
    if scene_id.startswith(TRAIN_PREFIX) and cfg["scenes"].get("train_frames") is not None:
        return int(cfg["scenes"]["train_frames"])
    return int(cfg["scenes"]["frames"])


def scene_frames_per_chunk(cfg: dict[str, Any], scene_id: str) -> int:
    """Frames per render job of a scene: ``scenes.frames_per_chunk``; a stability or volumetric clip is one chunk."""
    if scene_id.startswith((STABILITY_PREFIX, VOLUME_PREFIX)):
        return scene_frame_count(cfg, scene_id)
    return int(cfg["scenes"]["frames_per_chunk"])


def chunk_count(cfg: dict[str, Any], scene_id: str) -> int:
    """Number of render chunks of a scene: ceil(frames / frames_per_chunk)."""
    return math.ceil(scene_frame_count(cfg, scene_id) / scene_frames_per_chunk(cfg, scene_id))


def chunk_frames(cfg: dict[str, Any], scene_id: str, chunk: int) -> range:
    """Frame indices rendered by one chunk (the last chunk may be shorter)."""
    if not 0 <= chunk < chunk_count(cfg, scene_id):
        raise ValueError(f"scene {scene_id!r} has no chunk {chunk} (it has {chunk_count(cfg, scene_id)})")
    per_chunk = scene_frames_per_chunk(cfg, scene_id)
    return range(chunk * per_chunk, min((chunk + 1) * per_chunk, scene_frame_count(cfg, scene_id)))
