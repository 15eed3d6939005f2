"""The resolved description of one trained model (:class:`ModelSpec`), shared by ``models`` (which
builds specs from the config) and ``tasks`` (which turns a spec into a training task).

Its own module so that ``tasks`` does not import ``models`` (``models`` checks specs with ``tasks``).
Plain dataclass, no torch: the Snakefile imports it while parsing.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class ModelSpec:
    """One trained model: its id, method and fully resolved settings."""

    id: str
    method: str
    seed: int
    net: dict[str, Any] = field(hash=False, compare=False)
    loss: dict[str, Any] = field(hash=False, compare=False)
    data: dict[str, Any] = field(hash=False, compare=False)
    optimizer: dict[str, Any] = field(hash=False, compare=False)
    budget: dict[str, Any] = field(hash=False, compare=False)
    ablation: str | None = None
    variant: str | None = None
    #: Step arithmetic as configured (precision auto / bf16 / fp32, channels_last; denoisers.training.precision).
    compute: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    #: Torch threads of the training step (``training.threads``). Part of the settings: the trained weights
    #: depend on it (oneDNN splits its reductions by thread, so 1 and 2 threads differ after a few steps).
    threads: int = 1

    def settings(self) -> dict[str, Any]:
        """Everything that determines the trained weights (with the data), for digests and settings.json."""
        return {"id": self.id, "method": self.method, "seed": self.seed, "net": self.net, "loss": self.loss,
                "data": self.data, "optimizer": self.optimizer, "budget": self.budget,
                "ablation": self.ablation, "variant": self.variant, "compute": self.compute, "threads": self.threads}
