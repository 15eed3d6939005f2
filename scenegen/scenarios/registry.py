"""The registry of stability scenarios: ``@register_scenario`` adds a scenario function by name.

A scenario function takes a ``ScenarioBuilder`` (its ``rng`` is seeded from the global seed and the
scene id, its ``settings`` hold the clip length and image size) and adds what its phenomenon needs;
``build_scenario`` calls it and returns the SceneDraft (procedural manifest format plus a ``stability``
record naming the scenario's focus masks, subject shapes and events).
"""
from __future__ import annotations

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


SCENARIOS: dict[str, Scenario] = {}


def register_scenario(name: str, *, focus: tuple[str, ...] = ()) -> Callable:
    """Decorator: register ``function(builder) -> None`` as scenario ``name`` (scene id stab_{name}); ``focus``
    names the masks (MASK_KINDS) where its difficulty is; the docstring's first line describes it."""
    unknown = set(focus) - set(MASK_KINDS)
    if unknown:
        raise ValueError(f"scenario {name!r}: unknown focus masks {sorted(unknown)}; allowed: {MASK_KINDS}")

    def decorate(function: Callable[[ScenarioBuilder], None]) -> Callable[[ScenarioBuilder], None]:
        if name in SCENARIOS:
            raise ValueError(f"scenario {name!r} registered twice")
        description = (function.__doc__ or name).strip().splitlines()[0]
        SCENARIOS[name] = Scenario(name, function, tuple(focus), description)
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
