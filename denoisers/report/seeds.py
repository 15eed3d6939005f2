"""Seed rows in the results (``training.seeds`` > 1): a learned row's values as the mean over its training seeds.

A row that evaluates a trained model has one seed row per extra training seed (``{row}_seed{k}``,
denoisers.evaluate.seed_method_specs). :class:`SeedAveraged` gives the results classes (surface rows,
volume rows) per-scene values averaged over a row's seeds and each seed's own values, so that every table and
claim built on ``scene_values`` sees seed means and the claims can check each seed alone.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pandas as pd

    from denoisers.evaluate import MethodSpec


def seed_mean(per_seed: list[pd.Series]) -> pd.Series:
    """Per-index mean of per-seed Series on the index every one has (the first one's order); the Series itself
    for one seed."""
    if len(per_seed) == 1:
        return per_seed[0]
    import pandas as pd

    joined = pd.concat(per_seed, axis=1, join="inner")
    return joined.astype(float).mean(axis=1).rename(per_seed[0].name)


class SeedAveraged:
    """Mixin of a results class with ``specs`` (MethodSpec rows), ``per_scene`` (method_id, spp, scene, ...) and
    ``ran(row, spp)``."""

    specs: list[MethodSpec]
    per_scene: pd.DataFrame

    def ran(self, method_id: str | None, spp: int) -> bool:  # pragma: no cover - provided by the class
        raise NotImplementedError

    def seed_rows(self, method_id: str, spp: int) -> list[str]:
        """``method_id`` and its seed rows that ran at ``spp``, seed order; ``[method_id]`` for a row without
        seed rows (a hand-set method, or one seed)."""
        return [method_id] + [spec.id for spec in self.specs if spec.seed_of == method_id and self.ran(spec.id, spp)]

    def half_row(self, method_id: str, spp: int) -> str | None:
        """The row to compare at half the training budget: a learned row's half-budget row (``{row}_half``) when
        it ran at ``spp``, else None; any other row itself."""
        if not self.learned(method_id):
            return method_id
        half = next((spec.id for spec in self.specs if spec.budget_of == method_id), None)
        return half if half is not None and self.ran(half, spp) else None

    def learned(self, method_id: str) -> bool:
        """Whether the row denoises with a trained model (params.model)."""
        return any(spec.id == method_id and spec.params.get("model") for spec in self.specs)

    def own_scene_values(self, method_id: str, spp: int, column: str) -> pd.Series:
        """Per-scene values of one column of this row alone (no seed averaging), indexed by scene."""
        rows = self.per_scene[(self.per_scene.method_id == method_id) & (self.per_scene.spp == spp)]
        return rows.set_index("scene")[column]

    def scene_values(self, method_id: str, spp: int, column: str) -> pd.Series:
        """Per-scene values of one column, indexed by scene; for a row with seed rows the mean over its seeds
        (:meth:`seed_rows`) on the scenes every seed has."""
        return seed_mean(self.scene_values_per_seed(method_id, spp, column))

    def scene_values_per_seed(self, method_id: str, spp: int, column: str) -> list[pd.Series]:
        """:meth:`own_scene_values` of each seed of the row (one Series for a row without seed rows)."""
        return [self.own_scene_values(row, spp, column) for row in self.seed_rows(method_id, spp)]
