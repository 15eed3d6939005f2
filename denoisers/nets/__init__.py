"""Neural networks of the learned denoisers, rebuilt by name from a checkpoint.

Every network module sets ``NET_NAME`` and keeps its configuration dataclass in ``.config``
(with ``to_dict()`` / ``from_dict()``), so a checkpoint stores ``net_spec(model)`` and
:func:`build_net` rebuilds the same architecture before the weights are loaded.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn


def _builders() -> dict[str, Any]:
    from denoisers.nets import afn, kpcn, ntasd, rae

    return {rae.RecurrentAutoencoder.NET_NAME: rae.RecurrentAutoencoder, ntasd.NTASDNet.NET_NAME: ntasd.NTASDNet,
            afn.AFNNet.NET_NAME: afn.AFNNet, kpcn.KPCNNet.NET_NAME: kpcn.KPCNNet}


def available_nets() -> list[str]:
    """Names of the networks :func:`build_net` knows."""
    return sorted(_builders())


def build_net(name: str, config: Mapping[str, Any] | None = None) -> nn.Module:
    """A freshly initialised network ``name`` with configuration ``config`` (a ``to_dict()`` mapping)."""
    builders = _builders()
    if name not in builders:
        raise KeyError(f"unknown network {name!r}; known: {', '.join(sorted(builders))}")
    cls = builders[name]
    return cls(cls.Config.from_dict(dict(config or {})))


def net_spec(model: nn.Module) -> dict[str, Any]:
    """{'name': ..., 'config': {...}}: what :func:`build_net` needs to rebuild ``model``'s architecture."""
    return {"name": model.NET_NAME, "config": model.config.to_dict()}


def count_parameters(model: nn.Module) -> int:
    """Number of trainable scalar parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def for_inference(model: nn.Module) -> nn.Module:
    """``model`` in eval mode with channels-last weights (in place; returns it). oneDNN's convolutions then keep
    the activations channels-last from the first layer on: the NTASD U-Nets' forward ran 1.6x faster than in
    NCHW at 128 x 128 (1-2 threads, float32; the same arithmetic), and no per-call layout copy is made.
    Code that needs NCHW (the native kernels) makes its inputs contiguous itself."""
    return model.eval().to(memory_format=torch.channels_last)
