"""Samples per pixel of a training batch when a model trains at several spp (Isik et al. 2021 §4.3: S drawn
round robin from a set, per epoch in the paper, per batch here).

A batch carries ``data.spp`` sample layers (N, T, S, C, H, W); batch ``i`` of training uses the first
``choices[i % len(choices)]`` of them (the layers are already drawn at random from the stored ones); in eval
mode (validation) every carried layer, so validation is at ``data.spp``.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from torch import nn


def samples_for_batch(model: "nn.Module", batch: Any, choices: Sequence[int] | None) -> int:
    """Sample layers batch ``batch`` (its ``index``) uses: all carried ones without ``choices`` or in eval mode."""
    carried = int(batch["radiance"].shape[2])
    if not choices or not model.training:
        return carried
    return min(int(choices[int(getattr(batch, "index", 0)) % len(choices)]), carried)


def check_choices(method: str, choices: Sequence[int], carried: int) -> tuple[int, ...]:
    """``choices`` as a tuple; ValueError naming the method unless non-empty with each in 1..carried."""
    values = tuple(int(s) for s in choices)
    if not values or any(not 1 <= s <= carried for s in values):
        raise ValueError(f"{method}: loss.spp_choices {list(values)} must be non-empty, each in 1..data.spp = {carried}")
    return values
