"""EXR channel names of the rendered data: the tables (per-sample, per-pixel and reference buffers, which are
stored as HALF) and the conversion between planar arrays and named channels.

The single source of truth for channel names: the renderer turns its arrays into EXR channels with
:func:`noisy_channels`, :func:`pixel_channels` and :func:`reference_channels`; the loader (scenegen.dataset)
reads them back. docs/data-format.md documents the same tables for humans; a test checks that the two agree.

Array conventions: per-sample buffers are (S, C, H, W) per frame, per-pixel buffers (C, H, W), float32 unless
stated otherwise; a channel is one (H, W) plane.
"""

from __future__ import annotations

import re
from typing import Mapping, Sequence

import numpy as np

# ---------------------------------------------------------------------------------------------------
# Channel tables
# ---------------------------------------------------------------------------------------------------

#: Per-sample buffers: buffer -> channel suffixes; EXR channel ``sNN.<buffer>.<suffix>`` for layer NN.
SAMPLE_BUFFERS: dict[str, tuple[str, ...]] = {
    "radiance": ("R", "G", "B"),
    "diffuse": ("R", "G", "B"),
    "specular": ("R", "G", "B"),
    "albedo": ("R", "G", "B"),
    "normal": ("X", "Y", "Z"),
    "depth": ("Z",),
    "roughness": ("Y",),
    "flags": ("emissive", "metallic", "transmissive", "specular_bounce"),
    "position": ("X", "Y", "Z"),
    # Volumetric clips only (scenegen.volumes.integrator): at the camera ray's first real collision.
    "sigma_t": ("Y",),
    "medium": ("Y",),
    "transmittance": ("Y",),
}
#: Per-sample buffers stored as HALF; every other channel of a noisy frame is FLOAT.
HALF_BUFFERS: frozenset[str] = frozenset({"albedo", "normal", "roughness", "flags", "medium", "transmittance"})
#: The only buffer that may have more layers than the others (radiance-only "sample layers").
RADIANCE_BUFFER = "radiance"
#: Sample layers are named s00..s31.
MAX_SAMPLE_LAYERS = 32
#: Per-sample buffers of a volumetric clip's noisy frame (radiance, albedo, position and depth have the
#: surface names; albedo is the single-scattering albedo at a medium event, see docs/data-format.md).
VOLUME_BUFFERS: tuple[str, ...] = ("radiance", "albedo", "position", "depth", "sigma_t", "medium", "transmittance")
#: Per-pixel buffers a volumetric clip stores only as zeros (no surfaces: no normal, no roughness).
VOLUME_ZERO_PIXEL_BUFFERS: tuple[str, ...] = ("gbuffer.normal", "gbuffer.roughness")
#: Default for ``buffers=``: every per-sample buffer of a surface scene's noisy frame.
ALL: tuple[str, ...] = tuple(name for name in SAMPLE_BUFFERS if name not in {"sigma_t", "medium", "transmittance"})

#: Per-pixel buffers of a noisy frame (pixel-centre G-buffer pass): buffer -> full EXR channel names.
PIXEL_BUFFERS: dict[str, tuple[str, ...]] = {
    "motion": ("motion.X", "motion.Y"),
    "valid": ("motion.valid",),
    "gbuffer.position": ("gbuffer.position.X", "gbuffer.position.Y", "gbuffer.position.Z"),
    "gbuffer.normal": ("gbuffer.normal.X", "gbuffer.normal.Y", "gbuffer.normal.Z"),
    "gbuffer.depth": ("gbuffer.depth.Z",),
    "gbuffer.object": ("gbuffer.object.Y",),
    "gbuffer.albedo": ("gbuffer.albedo.R", "gbuffer.albedo.G", "gbuffer.albedo.B"),
    "gbuffer.roughness": ("gbuffer.roughness.Y",),
}
#: Per-pixel buffers stored as HALF.
HALF_PIXEL_BUFFERS: frozenset[str] = frozenset({"valid", "gbuffer.normal", "gbuffer.albedo", "gbuffer.roughness"})
GBUFFER_PREFIX = "gbuffer."

#: Reference frame buffers (all FLOAT): buffer -> channel suffixes; EXR channel ``<buffer>.<suffix>``.
REFERENCE_BUFFERS: dict[str, tuple[str, ...]] = {
    "radiance": ("R", "G", "B"),
    "radiance_half0": ("R", "G", "B"),
    "radiance_half1": ("R", "G", "B"),
    "diffuse": ("R", "G", "B"),
    "specular": ("R", "G", "B"),
    "albedo": ("R", "G", "B"),
    "normal": ("X", "Y", "Z"),
    "depth": ("Z",),
}

_SAMPLE_CHANNEL_RE = re.compile(r"^s(\d{2})\.([A-Za-z0-9_]+)\.([A-Za-z0-9_]+)$")
_HALF_PIXEL_CHANNELS = frozenset(name for buffer in HALF_PIXEL_BUFFERS for name in PIXEL_BUFFERS[buffer])
_GBUFFER_KEYS = tuple(b[len(GBUFFER_PREFIX):] for b in PIXEL_BUFFERS if b.startswith(GBUFFER_PREFIX))



# ---------------------------------------------------------------------------------------------------
# Names and array <-> channel conversion
# ---------------------------------------------------------------------------------------------------

def layer_name(s: int) -> str:
    """Two-digit sample layer prefix, e.g. 3 -> 's03'."""
    if not 0 <= s < MAX_SAMPLE_LAYERS:
        raise ValueError(f"sample layer {s} outside 0..{MAX_SAMPLE_LAYERS - 1}")
    return f"s{s:02d}"


def sample_channel_names(buffer: str, s: int) -> list[str]:
    """EXR channel names of ``buffer`` in sample layer ``s``, e.g. ['s00.radiance.R', ...]."""
    if buffer not in SAMPLE_BUFFERS:
        raise KeyError(f"unknown per-sample buffer {buffer!r}; known: {', '.join(SAMPLE_BUFFERS)}")
    return [f"{layer_name(s)}.{buffer}.{suffix}" for suffix in SAMPLE_BUFFERS[buffer]]


def reference_channel_names(buffer: str) -> list[str]:
    """EXR channel names of a reference buffer, e.g. ['radiance_half0.R', ...]."""
    if buffer not in REFERENCE_BUFFERS:
        raise KeyError(f"unknown reference buffer {buffer!r}; known: {', '.join(REFERENCE_BUFFERS)}")
    return [f"{buffer}.{suffix}" for suffix in REFERENCE_BUFFERS[buffer]]


def noisy_channel_names(spp: int, extra_radiance_spp: int = 0, buffers: Sequence[str] | None = None) -> list[str]:
    """Every channel of a noisy frame with ``spp`` full layers of ``buffers`` (default: a surface scene's,
    :data:`ALL`; a volumetric clip's: :data:`VOLUME_BUFFERS`) plus radiance-only extra layers."""
    if spp < 1 or spp + extra_radiance_spp > MAX_SAMPLE_LAYERS or extra_radiance_spp < 0:
        raise ValueError(f"need 1 <= spp and spp + extra_radiance_spp <= {MAX_SAMPLE_LAYERS}, "
                         f"got spp={spp}, extra_radiance_spp={extra_radiance_spp}")
    buffers = ALL if buffers is None else tuple(buffers)
    names = [name for s in range(spp) for buffer in buffers for name in sample_channel_names(buffer, s)]
    names += [name for s in range(spp, spp + extra_radiance_spp)
              for name in sample_channel_names(RADIANCE_BUFFER, s)]
    names += [name for channel_names in PIXEL_BUFFERS.values() for name in channel_names]
    return names


def is_half_channel(name: str) -> bool:
    """Whether a noisy-frame channel is stored as HALF (usable as ``write_exr(..., half=is_half_channel)``)."""
    match = _SAMPLE_CHANNEL_RE.match(name)
    if match:
        return match.group(2) in HALF_BUFFERS
    return name in _HALF_PIXEL_CHANNELS


def _check_planar(name: str, array: np.ndarray, ndim: int, channels: int) -> None:
    if array.ndim != ndim or array.shape[-3] != channels:
        layout = "(S, C, H, W)" if ndim == 4 else "(C, H, W)"
        raise ValueError(f"buffer {name!r} must be {layout} with C={channels}, got shape {array.shape}")


def noisy_channels(buffers: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], set[str]]:
    """Per-sample buffers {buffer: (S, C, H, W)} -> (EXR channels {'sNN.buffer.C': (H, W)}, names to store as HALF).

    All buffers except radiance must have the same S; radiance may have more layers (radiance-only
    extra layers) but not fewer, and at most 32. Usage: ``write_exr(path, channels, half=half)``.
    """
    buffers = {buffer: np.asarray(array) for buffer, array in buffers.items()}
    full_layers: int | None = None
    for buffer, array in buffers.items():
        if buffer not in SAMPLE_BUFFERS:
            raise KeyError(f"unknown per-sample buffer {buffer!r}; known: {', '.join(SAMPLE_BUFFERS)}")
        _check_planar(buffer, array, 4, len(SAMPLE_BUFFERS[buffer]))
        if buffer != RADIANCE_BUFFER:
            if full_layers is not None and array.shape[0] != full_layers:
                raise ValueError(f"all non-radiance buffers need the same number of layers; "
                                 f"{buffer!r} has {array.shape[0]}, others {full_layers}")
            full_layers = array.shape[0]
    radiance = buffers.get(RADIANCE_BUFFER)
    if radiance is not None and full_layers is not None and radiance.shape[0] < full_layers:
        raise ValueError(f"radiance has {radiance.shape[0]} layers, fewer than the other buffers ({full_layers})")

    channels: dict[str, np.ndarray] = {}
    half: set[str] = set()
    for buffer, array in buffers.items():
        for s in range(array.shape[0]):
            names = sample_channel_names(buffer, s)
            channels.update(zip(names, array[s]))
            if buffer in HALF_BUFFERS:
                half.update(names)
    return channels, half


def noisy_buffers(channels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Inverse of :func:`noisy_channels`: {'sNN.buffer.C': (H, W)} -> {buffer: (S, C, H, W) float32}.

    Channels that are not per-sample (motion, gbuffer, ...) are ignored. Raises ValueError if a buffer's
    layers are not s00..s(S-1) with every channel present.
    """
    layers = sample_layers(channels)
    return {buffer: np.stack([np.stack([np.asarray(channels[name], dtype=np.float32)
                                        for name in sample_channel_names(buffer, s)]) for s in range(count)])
            for buffer, count in layers.items()}


def sample_layers(channel_names: Sequence[str] | Mapping[str, object]) -> dict[str, int]:
    """Number of stored sample layers per buffer, from a list of EXR channel names.

    Layers must be contiguous from s00 and complete (all channels of the buffer); otherwise ValueError.
    Unknown buffers are ignored.
    """
    found: dict[str, set[tuple[int, str]]] = {}
    for name in channel_names:
        match = _SAMPLE_CHANNEL_RE.match(name)
        if match and match.group(2) in SAMPLE_BUFFERS:
            found.setdefault(match.group(2), set()).add((int(match.group(1)), match.group(3)))
    counts: dict[str, int] = {}
    for buffer, entries in found.items():
        count = max(s for s, _ in entries) + 1
        expected = {(s, suffix) for s in range(count) for suffix in SAMPLE_BUFFERS[buffer]}
        absent = sorted(expected - entries)
        if absent:
            s, suffix = absent[0]
            raise ValueError(f"buffer {buffer!r} has layers up to {layer_name(count - 1)} but channel "
                             f"{layer_name(s)}.{buffer}.{suffix} is missing")
        counts[buffer] = count
    return counts


def pixel_channels(motion: np.ndarray, valid: np.ndarray,
                   gbuffer: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], set[str]]:
    """Per-pixel data -> (EXR channels {'motion.X': (H, W), ...}, names to store as HALF).

    motion: (2, H, W) pixels; valid: (1, H, W) bool or 0/1; gbuffer: {'position': (3, H, W),
    'normal': (3, H, W), 'depth': (1, H, W), 'object': (1, H, W), 'albedo': (3, H, W), 'roughness':
    (1, H, W)}. Other G-buffer keys (e.g. the integrator's 'rgb') are not part of the format and are dropped.
    """
    buffers = {"motion": np.asarray(motion), "valid": np.asarray(valid, dtype=np.float32)}
    for buffer in PIXEL_BUFFERS:
        if buffer.startswith(GBUFFER_PREFIX):
            key = buffer[len(GBUFFER_PREFIX):]
            if key not in gbuffer:
                raise KeyError(f"G-buffer {key!r} is missing; expected {', '.join(_GBUFFER_KEYS)}")
            buffers[buffer] = np.asarray(gbuffer[key])
    channels: dict[str, np.ndarray] = {}
    for buffer, array in buffers.items():
        _check_planar(buffer, array, 3, len(PIXEL_BUFFERS[buffer]))
        channels.update(zip(PIXEL_BUFFERS[buffer], array))
    return channels, set(_HALF_PIXEL_CHANNELS)


def reference_channels(buffers: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Reference buffers {buffer: (C, H, W)} -> EXR channels {'buffer.C': (H, W)}."""
    channels: dict[str, np.ndarray] = {}
    for buffer, array in buffers.items():
        names = reference_channel_names(buffer)
        array = np.asarray(array)
        _check_planar(buffer, array, 3, len(names))
        channels.update(zip(names, array))
    return channels
