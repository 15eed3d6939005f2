"""OpenEXR reading and writing on top of the OpenEXR >= 3.3 Python bindings (``OpenEXR.File``).

Every image handled here is a single-part scanline EXR whose channels are independent (H, W) planes.
Channel naming for the renderer's outputs lives in :mod:`scenegen.channels`; this module only moves
named float planes to and from disk.

Binding quirks this module works around (observed with OpenEXR 3.5):
- ``OpenEXR.File(header, channels)`` replaces the values of the ``channels`` dict it is given with
  ``Channel`` objects, so we always pass a freshly built dict.
- Pixel arrays are written ignoring numpy strides, so every plane is made C-contiguous first.
- Reading a damaged file either raises ``RuntimeError`` (bad header) or constructs a File whose
  ``channels()`` raises ``ValueError``; both are turned into :class:`EXRError`.
- Python ``float`` header attributes are stored as 32-bit EXR ``float`` attributes; put values that need
  full precision into a JSON string attribute instead.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable, Mapping

import numpy as np
import OpenEXR

__all__ = ["EXRError", "COMPRESSIONS", "write_exr", "read_exr", "read_header", "list_channels"]


class EXRError(RuntimeError):
    """An EXR file could not be written or read; the message always names the file path."""


def _lossless_compressions() -> dict[str, object]:
    # Lossy codecs (pxr24, b44, dwa*) are deliberately absent: FLOAT channels must round-trip bit-exactly.
    names = {
        "none": "NO_COMPRESSION",
        "rle": "RLE_COMPRESSION",
        "zips": "ZIPS_COMPRESSION",
        "zip": "ZIP_COMPRESSION",
        "piz": "PIZ_COMPRESSION",
        "zstd": "ZSTD_COMPRESSION",  # OpenEXR >= 3.4 only; older viewers cannot open it
    }
    return {key: getattr(OpenEXR, attr) for key, attr in names.items() if hasattr(OpenEXR, attr)}


COMPRESSIONS: dict[str, object] = _lossless_compressions()

# Header attributes that OpenEXR manages itself and that callers must not override.
_RESERVED_ATTRIBUTES = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "name", "tiles", "version", "chunkCount",
})
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


def _half_predicate(half: Iterable[str] | Callable[[str], bool]) -> Callable[[str], bool]:
    if callable(half):
        return half
    half_names = frozenset(half)
    return half_names.__contains__


def _check_attributes(path: Path, attributes: Mapping[str, str | int | float]) -> dict[str, object]:
    checked: dict[str, object] = {}
    for key, value in attributes.items():
        if not isinstance(key, str) or not key:
            raise EXRError(f"{path}: attribute names must be non-empty strings, got {key!r}")
        if key in _RESERVED_ATTRIBUTES:
            raise EXRError(f"{path}: attribute {key!r} is reserved by OpenEXR")
        if isinstance(value, bool):
            value = int(value)
        if isinstance(value, (int, np.integer)):
            if not _INT32_MIN <= int(value) <= _INT32_MAX:
                raise EXRError(f"{path}: int attribute {key!r}={value} does not fit in 32 bits")
            checked[key] = int(value)
        elif isinstance(value, (float, np.floating)):
            checked[key] = float(value)
        elif isinstance(value, str):
            checked[key] = value
        else:
            raise EXRError(f"{path}: attribute {key!r} has unsupported type {type(value).__name__} "
                           "(use str, int or float)")
    return checked


def _prepare_planes(path: Path, channels: Mapping[str, np.ndarray],
                    is_half: Callable[[str], bool]) -> dict[str, OpenEXR.Channel]:
    """Validate (H, W) planes and convert them to contiguous float16 / float32 ``OpenEXR.Channel``s."""
    if not channels:
        raise EXRError(f"{path}: no channels to write")
    shape: tuple[int, ...] | None = None
    first_name = ""
    planes: dict[str, OpenEXR.Channel] = {}
    for name, array in channels.items():
        if not isinstance(name, str) or not name:
            raise EXRError(f"{path}: channel names must be non-empty strings, got {name!r}")
        array = np.asarray(array)
        if array.ndim != 2:
            raise EXRError(f"{path}: channel {name!r} must be a 2-D (H, W) array, got shape {array.shape}")
        if shape is None:
            shape, first_name = array.shape, name
        elif array.shape != shape:
            raise EXRError(f"{path}: channel {name!r} has shape {array.shape}, "
                           f"but {first_name!r} has shape {shape}")
        if not np.issubdtype(array.dtype, np.number) and array.dtype != np.bool_:
            raise EXRError(f"{path}: channel {name!r} has non-numeric dtype {array.dtype}")
        if is_half(name):
            with np.errstate(over="ignore"):
                as_half = np.ascontiguousarray(array, dtype=np.float16)
            # A finite value that turned into inf exceeded HALF's range (65504): data would be lost silently.
            if not np.isfinite(as_half).all() and (np.isfinite(as_half) != np.isfinite(array)).any():
                raise EXRError(f"{path}: channel {name!r} has values outside the HALF range (|x| > 65504)")
            planes[name] = OpenEXR.Channel(as_half)
        else:
            planes[name] = OpenEXR.Channel(np.ascontiguousarray(array, dtype=np.float32))
    return planes


def write_exr(path: Path, channels: Mapping[str, np.ndarray], *,
              half: Iterable[str] | Callable[[str], bool] = (),
              attributes: Mapping[str, str | int | float] | None = None,
              compression: str = "zip") -> None:
    """Write a single-part scanline EXR atomically.

    channels: name -> (H, W) numeric array; all arrays must share one shape. Names in ``half`` (a set of
    names or a predicate on the name) are stored as HALF (float16), all others as FLOAT (float32).
    The EXR format stores channels sorted by name whatever the insertion order.
    attributes: extra header attributes (str, int32, or float stored as 32-bit float).
    compression: one of :data:`COMPRESSIONS` (lossless only).
    The file is written to ``.<name>.tmp-<pid>`` next to ``path`` and renamed over ``path`` at the end, so
    readers never see a partial file. Non-finite values are written as they are (the renderer sanitises).
    """
    path = Path(path)
    if compression not in COMPRESSIONS:
        raise EXRError(f"{path}: unsupported compression {compression!r}; choose from {sorted(COMPRESSIONS)}")
    planes = _prepare_planes(path, channels, _half_predicate(half))
    header: dict[str, object] = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    header.update(_check_attributes(path, attributes or {}))

    tmp_path = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        OpenEXR.File(header, planes).write(str(tmp_path))
        os.replace(tmp_path, path)
    except Exception as error:
        tmp_path.unlink(missing_ok=True)
        raise EXRError(f"{path}: writing failed ({type(error).__name__}: {error})") from error


def _describe_available(names: Iterable[str], limit: int = 8) -> str:
    names = sorted(names)
    shown = ", ".join(names[:limit])
    more = f", ... ({len(names)} in total)" if len(names) > limit else ""
    return f"{shown}{more}" if names else "no channels"


def _open(path: Path, *, header_only: bool) -> OpenEXR.File:
    if not path.is_file():
        raise EXRError(f"{path}: no such EXR file")
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as error:
        raise EXRError(f"{path}: cannot open EXR, the file is corrupt or truncated "
                       f"({type(error).__name__}: {error})") from error


def _attributes(header: Mapping[str, object]) -> dict:
    return {key: value for key, value in header.items() if key != "channels"}


def read_header(path: Path) -> tuple[list[str], dict]:
    """Return (sorted channel names, header attributes) without decoding any pixels."""
    path = Path(path)
    exr = _open(path, header_only=True)
    try:
        header = exr.header()
        names = sorted(channel.name for channel in header["channels"])
    except Exception as error:
        raise EXRError(f"{path}: cannot parse EXR header ({type(error).__name__}: {error})") from error
    return names, _attributes(header)


def list_channels(path: Path) -> list[str]:
    """Sorted channel names of an EXR file (reads only the header)."""
    return read_header(path)[0]


def read_exr(path: Path, channels: Iterable[str] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read an EXR file.

    Returns ({name: (H, W) float32}, header attributes). With ``channels`` given, only those are returned
    (in the requested order); by default all channels are. The OpenEXR bindings decode the whole file, so
    peak memory is one full frame, but only the requested planes are kept.
    Raises :class:`EXRError` naming the file if it is missing, corrupt or truncated, or lacks a channel.
    """
    path = Path(path)
    exr = _open(path, header_only=False)
    try:
        stored = exr.channels()
        header = exr.header()
    except Exception as error:
        raise EXRError(f"{path}: cannot decode EXR pixels, the file is corrupt or truncated "
                       f"({type(error).__name__}: {error})") from error

    wanted = list(stored) if channels is None else list(channels)
    missing = [name for name in wanted if name not in stored]
    if missing:
        shown = ", ".join(repr(name) for name in missing[:3])
        if len(missing) > 3:
            shown += f" and {len(missing) - 3} more"
        raise EXRError(f"{path}: channel {shown} not found; available: {_describe_available(stored)}")
    # Decoded arrays own their memory, so float32 planes need no copy and the rest of the frame is freed.
    planes = {name: np.asarray(stored[name].pixels, dtype=np.float32) for name in wanted}
    return planes, _attributes(header)
