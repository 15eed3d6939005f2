"""The registry of stability scenarios: ``@register_scenario`` adds a scenario function by name.

A scenario function takes a ``ScenarioBuilder`` (its ``rng`` is seeded from the global seed and the
scene id, its ``settings`` hold the clip length and image size) and adds what its phenomenon needs;
``build_scenario`` calls it and returns the SceneDraft (procedural manifest format plus a ``stability``
record naming the scenario's focus masks, subject shapes and events).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable

import numpy as np

from scenegen.generate import SceneDraft
from scenegen.scenarios.builder import ScenarioBuilder, ScenarioSettings

#: Mask kinds scenegen.scenarios.masks derives for every scenario (a scenario's focus is a subset).
MASK_KINDS = ("disocclusion", "shadow", "specular", "transmission", "firefly", "indirect_only", "fast_motion",
              "texture", "subject")


@dataclass(frozen=True)
class Scenario:
    """A registered scenario: its builder function, the masks that locate its difficulty, a description."""

    name: str
    function: Callable[[ScenarioBuilder], None]
    focus: tuple[str, ...]
    description: str
    animated: bool = True


SCENARIOS: dict[str, Scenario] = {}


def register_scenario(name: str, *, focus: tuple[str, ...] = (), animated: bool = True) -> Callable:
    """Decorator: register ``function(builder) -> None`` as scenario ``name`` (scene id stab_{name}); ``focus``
    names the masks (MASK_KINDS) where its difficulty is; ``animated=False`` declares that nothing in its clip
    moves or changes (its own clip is then its failure-free control); the docstring's first line describes it."""
    unknown = set(focus) - set(MASK_KINDS)
    if unknown:
        raise ValueError(f"scenario {name!r}: unknown focus masks {sorted(unknown)}; allowed: {MASK_KINDS}")

    def decorate(function: Callable[[ScenarioBuilder], None]) -> Callable[[ScenarioBuilder], None]:
        if name in SCENARIOS:
            raise ValueError(f"scenario {name!r} registered twice")
        description = (function.__doc__ or name).strip().splitlines()[0]
        SCENARIOS[name] = Scenario(name, function, tuple(focus), description, bool(animated))
        return function

    return decorate


def build_scenario(name: str, settings: ScenarioSettings) -> SceneDraft:
    """Draw scenario ``name`` for ``settings`` (no files written); same settings give the same draft."""
    if name not in SCENARIOS:
        raise KeyError(f"unknown stability scenario {name!r}; registered: {', '.join(SCENARIOS)}")
    scenario = SCENARIOS[name]
    builder = ScenarioBuilder(settings, np.random.default_rng(settings.seed))
    scenario.function(builder)
    return builder.finish(name, scenario.focus, scenario.description)


def hold_final_frame(draft: SceneDraft, scene_id: str) -> SceneDraft:
    """The failure-free control of a scenario draft, as scene ``scene_id``: every animated thing (shape
    transforms, light positions and intensities, camera pose) held at its final-frame state in every frame, no
    camera cut, no events. The control's frames all show the scenario's last frame, so a method's error on them
    is its steady state on what the scenario ends with (issue 15 §2's lag metric). Meshes and textures are
    shared with the scenario; the manifest is a new dict (the draft's is not modified)."""
    manifest = copy.deepcopy(draft.manifest)
    n = int(manifest["n_frames"])
    for entry in manifest["shapes"] + manifest["emitters"]:
        for key in [k for k in entry if k.endswith("_per_frame") and entry[k] is not None]:
            entry[key] = [copy.deepcopy(entry[key][-1]) for _ in range(n)]
        if entry.get("to_world_per_frame") is not None:
            entry["to_world"] = copy.deepcopy(entry["to_world_per_frame"][-1])
    last = manifest["camera"]["frames"][-1]
    manifest["camera"]["frames"] = [{**copy.deepcopy(last), "cut": False} for _ in range(n)]
    manifest["camera"].update(path="static", speed=None, path_after_cut=None, speed_after_cut=None)
    manifest["animation"] = {"animated_light": None, "moving_shapes": [], "camera_cut_frame": None}
    manifest["scene_id"] = scene_id
    manifest["stability"] = {**manifest["stability"], "events": [], "control_of": manifest["stability"]["scenario"]}
    return SceneDraft(manifest=manifest, meshes=list(draft.meshes), textures=list(draft.textures))
