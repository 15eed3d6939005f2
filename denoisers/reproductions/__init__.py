"""One module per reproduced paper; the report assembles whatever modules exist.

Adding a paper = adding one module here that defines ``REPRODUCTION`` (denoisers.reproductions.base).
Modules are discovered by name and ordered by ``Reproduction.order``.
"""
from __future__ import annotations

import importlib
import pkgutil
from functools import cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from denoisers.reproductions.base import Reproduction

_NOT_PAPERS = frozenset({"base"})


@cache
def all_reproductions() -> tuple[Reproduction, ...]:
    """Every paper module's REPRODUCTION, in report order."""
    found = []
    for module in pkgutil.iter_modules(__path__):
        if module.name in _NOT_PAPERS or module.name.startswith("_"):
            continue
        reproduction = getattr(importlib.import_module(f"{__name__}.{module.name}"), "REPRODUCTION", None)
        if reproduction is None:
            raise ImportError(f"{__name__}.{module.name} defines no REPRODUCTION")
        found.append(reproduction)
    return tuple(sorted(found, key=lambda r: (r.order, r.key)))


def all_claims() -> list:
    return [claim for reproduction in all_reproductions() for claim in reproduction.claims]
