"""Temporal-stability scenarios (config section ``stability``; scene ids ``stab_{name}``).

One minimal, seeded clip per phenomenon a denoiser may get wrong over time (registry: ``SCENARIOS``;
the scenarios: ``scenegen.scenarios.library``; their building blocks: ``builder``). A scenario is written
in the procedural manifest format, so generate_scene / render_noisy / render_reference treat it like any
other scene; ``scenegen.scenarios.masks`` (rule derive_masks) then derives from the renders where and
when each difficulty happens.
"""
from __future__ import annotations

from pathlib import Path

from scenegen.catalog import STABILITY_CONTROL_SUFFIX, stability_control_id, stability_scenario, stability_scene_ids
from scenegen.generate import SceneDraft, write_draft
from scenegen.scenarios import library  # noqa: F401 -- registers the scenarios
from scenegen.scenarios.builder import ScenarioSettings
from scenegen.scenarios.registry import MASK_KINDS, SCENARIOS, build_scenario, hold_final_frame, register_scenario
from scenegen.seeds import scene_seed

__all__ = ["MASK_KINDS", "SCENARIOS", "ScenarioSettings", "build_scenario", "draw_scenario", "generate_scenario",
           "hold_final_frame", "register_scenario", "scenario_control", "stability_control_ids"]


def scenario_control(cfg: dict, scene_id: str) -> str | None:
    """The control clip's id (stab_{name}__still) of stability scene ``scene_id``, or None when the scenario is
    not animated (nothing in it changes: its own clip is its control)."""
    return stability_control_id(scene_id) if SCENARIOS[stability_scenario(cfg, scene_id)].animated else None


def stability_control_ids(cfg: dict) -> list[str]:
    """The control clips of the configured animated scenarios, in config order (empty when stability is off)."""
    return [control for control in map(lambda scene: scenario_control(cfg, scene), stability_scene_ids(cfg))
            if control is not None]


def scenario_settings(cfg: dict, scene_id: str) -> ScenarioSettings:
    """The settings of scene ``scene_id`` (stab_{name}) under ``cfg``: its seed (global seed and scene id),
    ``stability.frames``, ``stability.width`` and ``stability.height``. A control clip stab_{name}__still is
    drawn with its scenario's settings (same content), so it has the scenario's seed."""
    scene_id = scene_id.removesuffix(STABILITY_CONTROL_SUFFIX)
    stability = cfg["stability"]
    return ScenarioSettings(scene_id=scene_id, seed=scene_seed(cfg["seed"], scene_id), frames=stability["frames"],
                            width=stability["width"], height=stability["height"])


def draw_scenario(cfg: dict, scene_id: str) -> SceneDraft:
    """The SceneDraft of stability scene ``scene_id`` (KeyError naming the config keys if it has none); a control
    id stab_{name}__still gives the scenario held at its final frame (hold_final_frame)."""
    draft = build_scenario(stability_scenario(cfg, scene_id), scenario_settings(cfg, scene_id))
    if scene_id.endswith(STABILITY_CONTROL_SUFFIX):
        if not SCENARIOS[stability_scenario(cfg, scene_id)].animated:
            raise KeyError(f"{scene_id!r}: scenario {stability_scenario(cfg, scene_id)!r} is not animated and has no "
                           "control clip (its own clip is its control)")
        return hold_final_frame(draft, scene_id)
    return draft


def generate_scenario(cfg: dict, scene_id: str, out_dir: Path) -> dict:
    """Write scene ``scene_id``'s manifest, meshes and textures to ``out_dir``; return the manifest."""
    draft = draw_scenario(cfg, scene_id)
    write_draft(draft, Path(out_dir))
    return draft.manifest
