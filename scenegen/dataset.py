"""The on-disk data contract (EXR channel names) and the clip loader.

This module is the single source of truth for channel names: the renderer turns its arrays into EXR
channels with :func:`noisy_channels`, :func:`pixel_channels` and :func:`reference_channels`, and the
loader (:func:`load_frame`, :func:`load_clip`) reads them back. docs/data-format.md documents the same
tables for humans; a test checks that the two agree.

Array conventions: per-sample buffers are (S, C, H, W) per frame and (T, S, C, H, W) per clip, per-pixel
buffers (C, H, W) / (T, C, H, W), all float32 unless stated otherwise.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from scenegen.exr import read_exr, read_header, write_exr

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
    # Volumetric clips only (scenegen.volume_integrator): at the camera ray's first real collision.
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

#: EXR string attribute holding the same JSON as the sidecar ``frame_TTTT.json``.
META_ATTRIBUTE = "mcdn_meta"

_SAMPLE_CHANNEL_RE = re.compile(r"^s(\d{2})\.([A-Za-z0-9_]+)\.([A-Za-z0-9_]+)$")
_CHUNK_DIR_RE = re.compile(r"^chunk_(\d{3,})$")
_FRAME_FILE_RE = re.compile(r"^frame_(\d{4,})\.exr$")
_HALF_PIXEL_CHANNELS = frozenset(name for buffer in HALF_PIXEL_BUFFERS for name in PIXEL_BUFFERS[buffer])
_GBUFFER_KEYS = tuple(b[len(GBUFFER_PREFIX):] for b in PIXEL_BUFFERS if b.startswith(GBUFFER_PREFIX))


class DatasetError(RuntimeError):
    """Rendered data is missing, inconsistent or invalid; the message names the file."""


class MissingBufferError(DatasetError, KeyError):
    """A requested buffer was not rendered into the file (later stages catch it to name the method)."""

    def __init__(self, message: str, buffer: str, path: Path | None = None) -> None:
        super().__init__(message)
        self.buffer = buffer
        self.path = path

    def __str__(self) -> str:  # KeyError would otherwise print the message in quotes
        return str(self.args[0])


class NotEnoughSamplesError(DatasetError, ValueError):
    """More sample layers were requested than a buffer has on disk."""


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


# ---------------------------------------------------------------------------------------------------
# Paths and writing (used by the renderer)
# ---------------------------------------------------------------------------------------------------

def chunk_dir_name(chunk: int) -> str:
    return f"chunk_{chunk:03d}"


def frame_stem(frame: int) -> str:
    return f"frame_{frame:04d}"


def write_frame(exr_path: Path, channels: Mapping[str, np.ndarray], meta: Mapping, *,
                half: Iterable[str] | Callable[[str], bool] | None = None) -> None:
    """Write a frame EXR plus its sidecar JSON (same stem); the JSON is also stored as ``mcdn_meta``.

    channels: {name: (H, W)}; by default HALF/FLOAT follows :func:`is_half_channel` (reference frames,
    which are all FLOAT, pass ``half=set()``). The sidecar is written after the EXR, so a present sidecar
    implies a complete EXR.
    """
    exr_path = Path(exr_path)
    text = json.dumps(meta, indent=1, sort_keys=True)
    write_exr(exr_path, channels, half=is_half_channel if half is None else half,
              attributes={META_ATTRIBUTE: text})
    sidecar = exr_path.with_suffix(".json")
    tmp = sidecar.with_name(f".{sidecar.name}.tmp")
    tmp.write_text(text + "\n", encoding="utf-8")
    tmp.replace(sidecar)


# ---------------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------------

def _read_meta(exr_path: Path, attributes: Mapping[str, object]) -> dict:
    sidecar = exr_path.with_suffix(".json")
    try:
        if sidecar.is_file():
            return json.loads(sidecar.read_text(encoding="utf-8"))
        if META_ATTRIBUTE in attributes:
            return json.loads(str(attributes[META_ATTRIBUTE]))
    except json.JSONDecodeError as error:
        raise DatasetError(f"{exr_path}: frame metadata is not valid JSON ({error})") from error
    raise DatasetError(f"{exr_path}: no metadata: neither {sidecar.name} nor the {META_ATTRIBUTE!r} attribute exists")


def _check_finite(path: Path, planes: Mapping[str, np.ndarray]) -> None:
    for name, plane in planes.items():
        if not np.isfinite(plane).all():
            count = int(plane.size - np.count_nonzero(np.isfinite(plane)))
            raise DatasetError(f"{path}: channel {name!r} has {count} non-finite values")


def _missing_buffer(path: Path, buffer: str, available: Sequence[str], kind: str) -> MissingBufferError:
    return MissingBufferError(f"{path}: {kind} buffer {buffer!r} was not rendered into this file; "
                              f"available: {', '.join(available) or 'none'}", buffer, path)


def load_frame(path: Path, *, buffers: Sequence[str] = ALL, spp: int | None = None,
               pixel: bool = True) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """Read one noisy frame EXR (and its sidecar JSON).

    Returns (samples {buffer: (S, C, H, W) float32}, pixel {buffer: (C, H, W) float32} keyed like
    :data:`PIXEL_BUFFERS` (empty if ``pixel=False``), meta dict). ``spp=k`` keeps the first k layers of
    each buffer; ``spp=None`` keeps every stored layer, so radiance may have more layers than the rest.
    Only the requested channels are kept in memory.
    """
    path = Path(path)
    if spp is not None and spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    names, attributes = read_header(path)
    try:
        layers = sample_layers(names)
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from error

    wanted: dict[str, list[str]] = {}
    for buffer in buffers:
        if buffer not in layers:
            raise _missing_buffer(path, buffer, list(layers), "per-sample")
        count = layers[buffer] if spp is None else spp
        if count > layers[buffer]:
            raise NotEnoughSamplesError(f"{path}: requested spp={spp} for buffer {buffer!r}, "
                                        f"but only {layers[buffer]} sample layers are stored")
        wanted[buffer] = [name for s in range(count) for name in sample_channel_names(buffer, s)]
    if pixel:
        stored = set(names)
        for buffer, channel_names in PIXEL_BUFFERS.items():
            if not stored.issuperset(channel_names):
                present = [b for b, c in PIXEL_BUFFERS.items() if stored.issuperset(c)]
                raise _missing_buffer(path, buffer, present, "per-pixel")

    requested = [name for channel_names in wanted.values() for name in channel_names]
    if pixel:
        requested += [name for channel_names in PIXEL_BUFFERS.values() for name in channel_names]
    planes = read_exr(path, requested)[0] if requested else {}
    _check_finite(path, planes)

    samples = {}
    for buffer, channel_names in wanted.items():
        n_channels = len(SAMPLE_BUFFERS[buffer])
        stacked = np.stack([planes.pop(name) for name in channel_names])
        samples[buffer] = stacked.reshape(-1, n_channels, *stacked.shape[1:])
    pixel_data = {buffer: np.stack([planes[name] for name in channel_names])
                  for buffer, channel_names in PIXEL_BUFFERS.items()} if pixel else {}
    return samples, pixel_data, _read_meta(path, attributes)


#: Buffers every reference frame holds, whatever render.reference_integrator rendered it.
REQUIRED_REFERENCE_BUFFERS: tuple[str, ...] = ("radiance", "radiance_half0", "radiance_half1")


def load_reference_frame(path: Path, buffers: Sequence[str] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read one reference frame: ({buffer: (C, H, W) float32}, meta). Default: every REFERENCE_BUFFERS entry
    stored in the file (radiance and its two halves always; the feature means only when the reference was
    rendered with ``render.reference_integrator: features``)."""
    path = Path(path)
    names, attributes = read_header(path)
    stored = set(names)
    if buffers is None:
        buffers = [*REQUIRED_REFERENCE_BUFFERS,
                   *(b for b in REFERENCE_BUFFERS
                     if b not in REQUIRED_REFERENCE_BUFFERS and stored.issuperset(reference_channel_names(b)))]
    buffers = list(buffers)
    for buffer in buffers:
        if buffer not in REFERENCE_BUFFERS or not stored.issuperset(reference_channel_names(buffer)):
            present = [b for b in REFERENCE_BUFFERS if stored.issuperset(reference_channel_names(b))]
            raise _missing_buffer(path, buffer, present, "reference")
    planes, _ = read_exr(path, [name for buffer in buffers for name in reference_channel_names(buffer)])
    _check_finite(path, planes)
    data = {buffer: np.stack([planes[name] for name in reference_channel_names(buffer)]) for buffer in buffers}
    return data, _read_meta(path, attributes)


def find_frames(kind_dir: Path) -> dict[int, Path]:
    """Map global frame index -> EXR path over ``kind_dir/chunk_CCC/frame_TTTT.exr`` (hidden/tmp entries ignored)."""
    frames: dict[int, Path] = {}
    if not kind_dir.is_dir():
        return frames
    for chunk in sorted(kind_dir.iterdir()):
        if not (chunk.is_dir() and _CHUNK_DIR_RE.match(chunk.name)):
            continue
        for exr_path in sorted(chunk.iterdir()):
            match = _FRAME_FILE_RE.match(exr_path.name)
            if not match:
                continue
            frame = int(match.group(1))
            if frame in frames:
                raise DatasetError(f"frame {frame} is stored twice: {frames[frame]} and {exr_path}")
            frames[frame] = exr_path
    return frames


@dataclass
class Clip:
    """A rendered clip (or a subset of its frames) in memory."""

    scene: str
    frames: list[int]                          # global frame indices, sorted
    samples: dict[str, np.ndarray]             # buffer -> (T, S, C, H, W) float32
    motion: np.ndarray                         # (T, 2, H, W) float32, pixels
    valid: np.ndarray                          # (T, 1, H, W) bool
    gbuffer: dict[str, np.ndarray]             # 'position'/'normal'/'depth'/'object' -> (T, C, H, W) float32
    reference: dict[str, np.ndarray] | None    # buffer -> (T, C, H, W) float32
    meta: list[dict]                           # sidecar JSON per frame
    reference_meta: list[dict] | None = None   # reference sidecar JSON per frame (spp, psnr_halves, ...)

    def stack(self, buffers: Sequence[str], spp: int | None = None) -> np.ndarray:
        """(T, S, sum C, H, W) channel concatenation of per-sample buffers (first ``spp`` layers if given).

        Without ``spp`` all buffers must hold the same number of layers.
        """
        arrays = []
        for buffer in buffers:
            if buffer not in self.samples:
                raise MissingBufferError(f"buffer {buffer!r} is not loaded in clip {self.scene!r}; "
                                         f"loaded: {', '.join(self.samples)}", buffer)
            arrays.append(self.samples[buffer] if spp is None else self.samples[buffer][:, :spp])
        layer_counts = {buffer: array.shape[1] for buffer, array in zip(buffers, arrays)}
        if spp is not None and min(layer_counts.values(), default=spp) < spp:
            raise NotEnoughSamplesError(f"spp={spp} requested but clip {self.scene!r} has {layer_counts}")
        if len(set(layer_counts.values())) > 1:
            raise ValueError(f"buffers have different numbers of sample layers {layer_counts}; pass spp=")
        return np.concatenate(arrays, axis=2)

    @property
    def radiance_mean(self) -> np.ndarray:
        """(T, 3, H, W) per-pixel mean radiance over all loaded sample layers (box-filtered estimate)."""
        if RADIANCE_BUFFER not in self.samples:
            raise MissingBufferError(f"radiance is not loaded in clip {self.scene!r}", RADIANCE_BUFFER)
        return self.samples[RADIANCE_BUFFER].mean(axis=1)


def load_clip(render_dir: Path, *, buffers: Sequence[str] = ALL, spp: int | None = None,
              frames: Sequence[int] | None = None, reference: bool = True) -> Clip:
    """Load a scene's frames from ``render_dir`` = results/renders/{scene}.

    Frames are gathered across ``noisy/chunk_*`` (and ``reference/chunk_*``) and sorted by global index;
    ``frames`` selects a subset. ``buffers``/``spp`` select per-sample data as in :func:`load_frame`.
    Arrays are preallocated and filled frame by frame, so peak memory is the clip plus one frame.
    """
    render_dir = Path(render_dir)
    noisy = find_frames(render_dir / "noisy")
    if not noisy:
        raise DatasetError(f"{render_dir / 'noisy'}: no frames found (expected chunk_CCC/frame_TTTT.exr)")
    if frames is None:
        selected = sorted(noisy)
    else:
        selected = sorted(set(frames))
        absent = [t for t in selected if t not in noisy]
        if absent:
            raise DatasetError(f"{render_dir / 'noisy'}: frame(s) {absent} not rendered; "
                               f"available {min(noisy)}..{max(noisy)} ({len(noisy)} frames)")
    references = find_frames(render_dir / "reference") if reference else {}
    if reference:
        for t in selected:
            if t not in references:
                expected = render_dir / "reference" / noisy[t].parent.name / noisy[t].name
                raise DatasetError(f"{expected}: reference frame {t} is missing")

    n_frames = len(selected)
    samples: dict[str, np.ndarray] = {}
    pixels: dict[str, np.ndarray] = {}
    reference_data: dict[str, np.ndarray] = {}
    metas: list[dict] = []
    reference_metas: list[dict] = []
    for i, t in enumerate(selected):
        frame_samples, frame_pixels, meta = load_frame(noisy[t], buffers=buffers, spp=spp)
        if i == 0:
            samples = {b: np.empty((n_frames, *a.shape), np.float32) for b, a in frame_samples.items()}
            pixels = {b: np.empty((n_frames, *a.shape), np.float32) for b, a in frame_pixels.items()}
        _fill(samples, frame_samples, i, noisy[t])
        _fill(pixels, frame_pixels, i, noisy[t])
        metas.append(meta)
        if reference:
            frame_reference, reference_meta = load_reference_frame(references[t])
            reference_metas.append(reference_meta)
            if i == 0:
                reference_data = {b: np.empty((n_frames, *a.shape), np.float32) for b, a in frame_reference.items()}
            _fill(reference_data, frame_reference, i, references[t])

    noisy_shape = pixels["motion"].shape[-2:]
    for buffer, array in reference_data.items():
        if array.shape[-2:] != noisy_shape:
            raise DatasetError(f"{render_dir}: reference {buffer!r} is {array.shape[-2:]} pixels, "
                               f"noisy frames are {noisy_shape}")
    gbuffer = {b[len(GBUFFER_PREFIX):]: a for b, a in pixels.items() if b.startswith(GBUFFER_PREFIX)}
    return Clip(
        scene=str(metas[0].get("scene", render_dir.name)),
        frames=selected,
        samples=samples,
        motion=pixels["motion"],
        valid=pixels["valid"] > 0.5,
        gbuffer=gbuffer,
        reference=reference_data if reference else None,
        meta=metas,
        reference_meta=reference_metas if reference else None,
    )


def _fill(destination: dict[str, np.ndarray], frame: Mapping[str, np.ndarray], index: int, path: Path) -> None:
    """Copy one frame's arrays into slot ``index`` of preallocated clip arrays, checking shapes agree."""
    for buffer, array in frame.items():
        target = destination[buffer]
        if array.shape != target.shape[1:]:
            raise DatasetError(f"{path}: buffer {buffer!r} has shape {array.shape}, "
                               f"earlier frames have {target.shape[1:]} (different size or layer count)")
        target[index] = array
