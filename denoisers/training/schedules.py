"""Learning-rate schedules of the trainer (denoisers.training.loop): the base rate's multiplier per step."""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def lr_factor(schedule: Mapping[str, Any], step: int) -> float:
    """Multiplier of the base learning rate for optimiser step ``step`` (0-based).

    * ``{"name": "constant"}``
    * ``{"name": "ramp_inv_sqrt", "ramp_steps": R, "ramp_factor": k}`` -- Chaitanya et al. 2017 §5.3:
      "ramped up tenfold using a geometric progression during the first 10 training epochs, and then
      decreased according to 1/sqrt(t)": k^(step/R - 1) for step < R (1/k -> 1), then sqrt(R / step).
      The base rate is the peak (0.001 in the paper); R is in steps here (the paper: 10 of 500 epochs).
    * ``{"name": "cosine", "warmup_steps": W, "total_steps": S, "min_factor": m}`` -- linear warm-up,
      then cosine decay from 1 to m at step S (m afterwards); the trainer sets S to its step budget when the
      schedule leaves it out.
    * ``{"name": "step", "every": n, "gamma": g}`` -- g^(step // n). (A config may give ``every_fraction`` of
      the step budget instead; denoisers.training.models resolves it to ``every`` before the trainer sees it.)
    """
    name = schedule.get("name", "constant")
    if name == "constant":
        return 1.0
    if name == "ramp_inv_sqrt":
        ramp, factor = int(schedule.get("ramp_steps", 100)), float(schedule.get("ramp_factor", 10.0))
        if ramp < 1 or factor < 1:
            raise ValueError(f"ramp_inv_sqrt needs ramp_steps >= 1 and ramp_factor >= 1, got {dict(schedule)}")
        return factor ** (step / ramp - 1.0) if step < ramp else math.sqrt(ramp / step)
    if name == "cosine":
        warmup, total = int(schedule.get("warmup_steps", 0)), int(schedule["total_steps"])
        minimum = float(schedule.get("min_factor", 0.0))
        if step < warmup:
            return (step + 1) / warmup
        progress = min(1.0, (step - warmup) / max(1, total - warmup))
        return minimum + (1.0 - minimum) * 0.5 * (1.0 + math.cos(math.pi * progress))
    if name == "step":
        if "every" not in schedule:
            raise ValueError(f"a step schedule needs every (steps; the config may give every_fraction of "
                             f"budget.max_steps instead), got {dict(schedule)}")
        every = int(schedule["every"])
        if every < 1:
            raise ValueError(f"a step schedule needs every >= 1, got {dict(schedule)}")
        return float(schedule.get("gamma", 0.1)) ** (step // every)
    raise ValueError(f"unknown learning-rate schedule {name!r}; known: constant, ramp_inv_sqrt, cosine, step")
