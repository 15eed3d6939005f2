"""Temporal-stability scenarios (config section ``stability``; scene ids ``stab_{name}``).

One minimal, seeded clip per phenomenon a denoiser may get wrong over time (registry: ``SCENARIOS``;
the scenarios: ``scenegen.scenarios.library``; their building blocks: ``builder``). A scenario is written
in the procedural manifest format, so generate_scene / render_noisy / render_reference treat it like any
other scene; ``scenegen.scenarios.masks`` (rule derive_masks) then derives from the renders where and
when each difficulty happens.
"""
from __future__ import annotations

from pathlib import Path

from scenegen.config import stability_scenario
from scenegen.generate import SceneDraft, write_draft
from scenegen.scenarios import library  # noqa: F401 -- registers the scenarios
from scenegen.scenarios.builder import ScenarioSettings
from scenegen.scenarios.registry import MASK_KINDS, SCENARIOS, build_scenario, register_scenario
from scenegen.seeds import scene_seed

__all__ = ["MASK_KINDS", "SCENARIOS", "ScenarioSettings", "build_scenario", "draw_scenario", "generate_scenario",
           "register_scenario"]


def scenario_settings(cfg: dict, scene_id: str) -> ScenarioSettings:
    """The settings of scene ``scene_id`` (stab_{name}) under ``cfg``: its seed (global seed and scene id),
    ``stability.frames``, ``stability.width`` and ``stability.height``."""
    stability = cfg["stability"]
    return ScenarioSettings(scene_id=scene_id, seed=scene_seed(cfg["seed"], scene_id), frames=stability["frames"],
                            width=stability["width"], height=stability["height"])


def draw_scenario(cfg: dict, scene_id: str) -> SceneDraft:
    """The SceneDraft of stability scene ``scene_id`` (KeyError naming the config keys if it has none)."""
    return build_scenario(stability_scenario(cfg, scene_id), scenario_settings(cfg, scene_id))


def generate_scenario(cfg: dict, scene_id: str, out_dir: Path) -> dict:
    """Write scene ``scene_id``'s manifest, meshes and textures to ``out_dir``; return the manifest."""
    draft = draw_scenario(cfg, scene_id)
    write_draft(draft, Path(out_dir))
    return draft.manifest
