"""Job digests of the scene generator's outputs: which config settings a scene and its renders depend on.

SHA-256 of canonical JSON (scenegen.config.config_digest). The workflow passes them as params of
generate_scene, render_noisy and render_reference, so Snakemake reruns exactly the jobs whose settings
changed; denoisers.experiment combines them into the lineage digests that outputs record, and the
training job keys its data on the training scenes' render digests. Config level (no rendering), except that a
custom scene's digest covers the contents of its XML and of every file the XML references
(scenegen.custom.check.scene_files: Mitsuba's parser, no instantiation).
"""
from __future__ import annotations

from typing import Any

from scenegen.catalog import (STABILITY_CONTROL_SUFFIX, STABILITY_PREFIX, VOLUME_CUSTOM_PREFIX, VOLUME_PREFIX,
                              extra_scene, scene_frame_count, scene_frames_per_chunk, scene_reference_spp,
                              scene_render_config, stability_scenario, volume_clip_spec, volume_extra)
from scenegen.config import config_digest
from scenegen.custom.check import scene_files

#: scenes.* keys that say how many scenes exist or how frames are batched, not what a scene holds.
SCENE_LAYOUT_KEYS = frozenset({"n_train", "n_test", "frames_per_chunk"})
NOISY_ONLY_KEYS = frozenset({"spp", "extra_radiance_spp"})
#: Version of the noisy frames' channel layout (docs/data-format.md), part of every noisy render's digest so that
#: renders of an older layout are redone rather than read: 2 added gbuffer.albedo and gbuffer.roughness.
NOISY_FORMAT_VERSION = 2
#: render.* keys only the references depend on; train_reference_spp, test_reference_spp and
#: test_reference_spp_per_scene enter a reference
#: digest as the scene's effective reference_spp (scenegen.catalog.scene_reference_spp), so null or absent changes no digest.
REFERENCE_ONLY_KEYS = frozenset({"reference_spp", "reference_batch_spp", "train_reference_spp",
                                 "test_reference_spp", "test_reference_spp_per_scene", "reference_integrator"})
#: render.* keys only the noisy renders depend on, with the value that enters no digest (so configs written before
#: the key existed keep their renders): gbuffer_albedo_spp > 1 averages the G-buffer albedo over jittered rays.
NOISY_OPTIONAL_KEYS: dict[str, Any] = {"gbuffer_albedo_spp": 1}


def scene_settings(cfg: dict, scene: str) -> dict[str, Any]:
    """The config values a scene's content depends on (not the number of scenes). Render keys shared by
    the noisy and reference renders (resolution, variant, path depth) are included: the generator's
    preview render uses them."""
    if scene.startswith(STABILITY_PREFIX):
        # A scenario depends on its name, clip length and image size (speeds are set in pixels per frame).
        stability = cfg["stability"]
        shared = [f"render.{key}" for key in cfg["render"]
                  if key not in NOISY_ONLY_KEYS | REFERENCE_ONLY_KEYS | set(NOISY_OPTIONAL_KEYS) | {"width", "height"}]
        clip = {key: stability[key] for key in ("frames", "width", "height")}
        settings = {"seed": cfg["seed"], "stability": {"scenario": stability_scenario(cfg, scene), **clip},
                    "render_shared": config_digest(cfg, *shared)}
        if scene.endswith(STABILITY_CONTROL_SUFFIX):   # the scenario held at its final frame
            settings["control"] = "final frame"
        return settings
    if scene.startswith(VOLUME_PREFIX):
        # A clip depends on its scenario (its seed derives from the scene id), length, size, field and depth.
        volumes = cfg["volumes"]
        shared = [f"render.{key}" for key in ("variant", "rr_depth") if key in cfg["render"]]
        own = volume_extra(cfg, scene) if scene.startswith(VOLUME_CUSTOM_PREFIX) else None
        return {"seed": cfg["seed"], "volumes": {
                    "scenario": volume_clip_spec(cfg, scene)[1], **({"extra": own} if own else {}),
                    **{key: volumes[key] for key in ("frames", "width", "height", "resolution", "max_depth")}},
                "render_shared": config_digest(cfg, *shared)}
    if scene.startswith("custom_"):
        # The XML and every file it references, by content: an edited mesh or texture reruns the import.
        entry = extra_scene(cfg, scene)
        procedural: dict[str, Any] = {"extra_scene": entry, "files": scene_files(entry)}
    else:
        # A scene depends on its own frame count only: train_frames (null or absent changes no digest) enters
        # a train_* scene's settings as its frames, and no other scene's.
        procedural = {key: value for key, value in cfg["scenes"].items()
                      if key not in SCENE_LAYOUT_KEYS | {"train_frames"}}
        procedural["frames"] = scene_frame_count(cfg, scene)
    shared = [f"render.{key}" for key in cfg["render"]
              if key not in NOISY_ONLY_KEYS | REFERENCE_ONLY_KEYS | set(NOISY_OPTIONAL_KEYS)]
    return {"seed": cfg["seed"], "scenes": procedural, "render_shared": config_digest(cfg, *shared)}


def scene_digest(cfg: dict, scene: str) -> str:
    """Rule generate_scene."""
    return config_digest(scene_settings(cfg, scene))


def render_digest(cfg: dict, scene: str, kind: str) -> str:
    """Rules render_noisy (``kind`` 'noisy') and render_reference ('reference')."""
    if kind == "noisy":   # stability scenes: their own spp (scene_render_config)
        render = scene_render_config(cfg, scene)
        own = {key: render[key] for key in sorted(NOISY_ONLY_KEYS)}
        own["format"] = NOISY_FORMAT_VERSION
        if not scene.startswith(VOLUME_PREFIX):   # volumetric clips have their own G-buffer pass
            own.update({key: render[key] for key, neutral in NOISY_OPTIONAL_KEYS.items()
                        if render.get(key, neutral) != neutral})
    else:   # the spp this scene's references are rendered with, under the key reference_spp
        own = {"reference_batch_spp": cfg["render"]["reference_batch_spp"],
               "reference_spp": scene_reference_spp(cfg, scene),
               "reference_integrator": scene_render_config(cfg, scene)["reference_integrator"]}
    return config_digest({"scene": scene_settings(cfg, scene), "frames": scene_frame_count(cfg, scene),
                          "frames_per_chunk": scene_frames_per_chunk(cfg, scene), "render": own})


def masks_digest(cfg: dict, scene: str) -> str:
    """Rule derive_masks (a stability scene's masks and events): its noisy and reference renders' settings."""
    return config_digest({"noisy": render_digest(cfg, scene, "noisy"),
                          "reference": render_digest(cfg, scene, "reference")})
