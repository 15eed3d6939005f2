"""Frame files on disk: writing a frame EXR with its sidecar JSON, and the loader (:func:`load_frame`,
:func:`load_clip`) that reads noisy and reference frames back, checked (missing buffers, too few sample layers,
non-finite values and missing metadata raise :class:`DatasetError` naming the file). Channel names and the
array <-> channel conversion: scenegen.channels.

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

from scenegen.channels import (ALL, GBUFFER_PREFIX, PIXEL_BUFFERS, RADIANCE_BUFFER, REFERENCE_BUFFERS, SAMPLE_BUFFERS,
                               is_half_channel, reference_channel_names, sample_channel_names, sample_layers)
from scenegen.exr import read_exr, read_header, write_exr

#: EXR string attribute holding the same JSON as the sidecar ``frame_TTTT.json``.
META_ATTRIBUTE = "mcdn_meta"

_CHUNK_DIR_RE = re.compile(r"^chunk_(\d{3,})$")
_FRAME_FILE_RE = re.compile(r"^frame_(\d{4,})\.exr$")


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
