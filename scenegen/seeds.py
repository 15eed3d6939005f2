"""Stable seed derivation: every random stream is a pure function of (global seed, names)."""
from __future__ import annotations

import zlib

import numpy as np


def _name_key(name: str) -> int:
    return zlib.crc32(name.encode("utf-8"))


def derive_seed(global_seed: int, *names: str | int) -> int:
    """A 32-bit seed determined by ``global_seed`` and the sequence ``names`` (strings or ints)."""
    keys = [int(global_seed)] + [n if isinstance(n, int) else _name_key(n) for n in names]
    return int(np.random.SeedSequence(keys).generate_state(1, dtype=np.uint32)[0])


def scene_seed(global_seed: int, scene_id: str) -> int:
    """Seed of scene ``scene_id`` (e.g. ``"train_003"``)."""
    return derive_seed(global_seed, scene_id)
