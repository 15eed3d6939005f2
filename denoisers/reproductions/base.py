"""What a paper's reproduction module provides (see denoisers/reproductions/__init__.py).

A module defines ``REPRODUCTION = Reproduction(...)``: its claims (with decision functions), the
tables and figures it writes (names, listed at workflow parse time, so no heavy imports), and a
``write`` function that writes them and returns its REPORT.md section.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from denoisers.report.claims import Claim

if TYPE_CHECKING:
    from denoisers.report.collect import Results


def no_outputs(cfg: dict) -> list[str]:
    return []


def no_section(res: Results, tables: Path, figures: Path) -> str:
    return ""


@dataclass(frozen=True)
class Reproduction:
    """One paper: its claims, the tables ({name}.csv + {name}.md) and figures ({name}.png) it writes."""

    key: str                                   # module name, e.g. 'chaitanya2017'
    paper: str                                 # citation, e.g. 'Chaitanya et al. 2017'
    title: str
    source: str                                # file in ../shared/papers/
    order: int                                 # position in the report (the claim prefix number)
    claims: tuple[Claim, ...] = ()
    tables: Callable[[dict], list[str]] = no_outputs
    figures: Callable[[dict], list[str]] = no_outputs
    write: Callable[[Results, Path, Path], str] = field(default=no_section)
