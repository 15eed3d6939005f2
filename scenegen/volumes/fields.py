"""Scalar fields of heterogeneous media (Iglesias-Guitian et al. 2022 volumetric scenes): procedural noise
clouds and smoke plumes, and users' ``.npy`` volumes. A field is a float32 array (D, H, W) with values in
[0, 1], indexed [z, y, x] on the unit cube: voxel [k, j, i] has its centre at ((i + 0.5) / W, (j + 0.5) / H,
(k + 0.5) / D) in (x, y, z), the layout of Mitsuba's ``gridvolume``. Pure numpy and deterministic: the same
``rng`` state and parameters give the same bytes. Fields from meshes: scenegen.volumes.mesh; transfer
functions and the Mitsuba medium: scenegen.volumes.media.
"""
from __future__ import annotations

import math
import pathlib
from collections.abc import Sequence
from typing import Any

import numpy as np

Resolution = int | tuple[int, int, int]


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------

def _grid_shape(resolution: Resolution) -> tuple[int, int, int]:
    """(D, H, W) from an int (cubic grid) or a (D, H, W) triple of ints; each at least 1."""
    def is_int(n: Any) -> bool:
        return isinstance(n, (int, np.integer)) and not isinstance(n, bool)

    if is_int(resolution):
        shape = (int(resolution),) * 3
    elif isinstance(resolution, (tuple, list)) and len(resolution) == 3 and all(is_int(n) for n in resolution):
        shape = tuple(int(n) for n in resolution)
    else:
        raise ValueError(f"resolution must be an int or a (D, H, W) triple of ints, got {resolution!r}")
    if min(shape) < 1:
        raise ValueError(f"resolution must be at least 1 voxel per axis, got {shape}")
    return shape  # type: ignore[return-value]


def _check_rng(rng: Any) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator (see scenegen.seeds), got {type(rng).__name__}")
    return rng


def _check_range(name: str, value: float, lo: float, hi: float, *, lo_open: bool = False,
                 hi_open: bool = False) -> float:
    value = float(value)
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        interval = f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
        raise ValueError(f"{name} must be in {interval}, got {value}")
    return value


def _centres(n: int) -> np.ndarray:
    """(n,) voxel-centre coordinates (i + 0.5) / n on [0, 1]."""
    return (np.arange(n, dtype=np.float64) + 0.5) / n


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite 0 -> 1 ramp between edge0 and edge1 (a step at edge0 when they coincide)."""
    if edge1 <= edge0:
        return (x >= edge0).astype(np.float64)
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _face_falloff(shape: tuple[int, int, int], margin: float, softness: float) -> np.ndarray:
    """(D, H, W) in [0, 1]: 0 within ``margin`` of any box face, rising smoothly to 1 over ``softness``."""
    z, y, x = (_centres(n) for n in shape)
    per_axis = [_smoothstep(margin, margin + softness, np.minimum(c, 1.0 - c)) for c in (z, y, x)]
    return per_axis[0][:, None, None] * per_axis[1][None, :, None] * per_axis[2][None, None, :]


def _interp_axis(values: np.ndarray, axis: int, n: int, frequency: int, offset: float) -> np.ndarray:
    """Resample lattice ``values`` along ``axis`` at the n voxel centres: lattice coordinate
    u = centre * frequency + offset, smoothstep-weighted linear interpolation between floor(u) and floor(u) + 1."""
    u = _centres(n) * frequency + offset
    i0 = np.floor(u).astype(np.int64)
    t = u - i0
    t = t * t * (3.0 - 2.0 * t)
    shape = [1] * values.ndim
    shape[axis] = n
    t = t.reshape(shape)
    return np.take(values, i0, axis=axis) * (1.0 - t) + np.take(values, i0 + 1, axis=axis) * t


def _lattice_noise(rng: np.random.Generator, shape: tuple[int, int, int],
                   frequency: tuple[int, int, int]) -> np.ndarray:
    """(D, H, W) float64 value noise in [0, 1]: a random lattice with ``frequency`` (fz, fy, fx) cells across
    the unit cube, randomly offset by up to a cell, interpolated separably (x, then y, then z)."""
    offsets = rng.random(3)
    lattice = rng.random(tuple(f + 2 for f in frequency))
    out = lattice
    for axis in (2, 1, 0):
        out = _interp_axis(out, axis, shape[axis], frequency[axis], float(offsets[axis]))
    return out


def _fbm(rng: np.random.Generator, shape: tuple[int, int, int], octaves: int, base_frequency: int,
         persistence: float, stretch: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """(D, H, W) float64 fractal sum of ``octaves`` value-noise layers in [0, 1]; octave k has frequency
    base_frequency * 2^k (times ``stretch`` per (z, y, x) axis, at least 1) and weight persistence^k."""
    total = np.zeros(shape)
    weight_sum = 0.0
    for k in range(octaves):
        f = base_frequency * 2 ** k
        frequency = tuple(max(1, int(round(f * s))) for s in stretch)
        weight = persistence ** k
        total += weight * _lattice_noise(rng, shape, frequency)  # type: ignore[arg-type]
        weight_sum += weight
    return total / weight_sum


def _normalise_max(field: np.ndarray) -> np.ndarray:
    """float32 field / its maximum (all zeros stays zeros), clipped to [0, 1]."""
    peak = float(field.max()) if field.size else 0.0
    if peak > 0.0:
        field = field / peak
    return np.clip(field, 0.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Procedural scalar fields
# ---------------------------------------------------------------------------------------------

def noise_cloud(rng: np.random.Generator, resolution: Resolution = 32, octaves: int = 4, *,
                base_frequency: int = 3, persistence: float = 0.5, turbulence: float = 0.9,
                radii: Sequence[float] | None = None, margin: float = 0.06, softness: float = 0.12) -> np.ndarray:
    """(D, H, W) float32 cloud in [0, 1] (maximum 1), indexed [z, y, x] on the unit cube.

    An ellipsoidal body (1 at the centre, 0 at the ellipsoid ``radii`` (x, y, z), default 0.5 - margin
    each) is eroded and grown by fractal value noise: density = clip(body + turbulence * (noise - 0.5)),
    then multiplied by a falloff that is exactly 0 within ``margin`` of the box faces and reaches 1 after
    a further ``softness``, so the cloud never touches the box. Normalised to a maximum of 1.
    """
    _check_rng(rng)
    shape = _grid_shape(resolution)
    if int(octaves) < 1 or int(base_frequency) < 1:
        raise ValueError(f"octaves and base_frequency must be >= 1, got {octaves}, {base_frequency}")
    _check_range("persistence", persistence, 0.0, 1.0, lo_open=True)
    _check_range("turbulence", turbulence, 0.0, 2.0)
    _check_range("margin", margin, 0.0, 0.5, hi_open=True)
    _check_range("softness", softness, 0.0, 0.5)
    radii_xyz = np.full(3, 0.5 - margin) if radii is None else np.asarray(radii, dtype=np.float64)
    if radii_xyz.shape != (3,) or not np.all(np.isfinite(radii_xyz) & (radii_xyz > 0.0)):
        raise ValueError(f"radii must be three positive (x, y, z) radii, got {radii!r}")

    z, y, x = (_centres(n) for n in shape)
    r2 = (((x - 0.5) / radii_xyz[0]) ** 2)[None, None, :] + (((y - 0.5) / radii_xyz[1]) ** 2)[None, :, None] \
        + (((z - 0.5) / radii_xyz[2]) ** 2)[:, None, None]
    body = 1.0 - _smoothstep(0.0, 1.0, np.sqrt(r2))
    noise = _fbm(rng, shape, int(octaves), int(base_frequency), float(persistence))
    density = np.clip(body + float(turbulence) * (noise - 0.5), 0.0, 1.0)
    return _normalise_max(density * _face_falloff(shape, margin, softness))


def smoke_plume(rng: np.random.Generator, resolution: Resolution = 32, *, octaves: int = 4,
                base_frequency: int = 3, persistence: float = 0.55, base_radius: float = 0.05,
                top_radius: float = 0.25, sway: float = 0.12, turbulence: float = 0.7, margin: float = 0.04,
                softness: float = 0.08) -> np.ndarray:
    """(D, H, W) float32 smoke column in [0, 1] (maximum 1), indexed [z, y, x]; rises along +y (axis 1).

    A Gaussian column whose radius grows linearly from ``base_radius`` at the source (y = margin) to
    ``top_radius`` at the top; its axis wanders in x and z by up to ``sway`` (1-D value noise that grows
    with height); density is modulated by vertically stretched fractal noise (``turbulence`` = depth of
    modulation), fades in at the source, thins with height and fades out at the top, and is 0 within
    ``margin`` of the box faces. Normalised to a maximum of 1.
    """
    _check_rng(rng)
    shape = _grid_shape(resolution)
    if int(octaves) < 1 or int(base_frequency) < 1:
        raise ValueError(f"octaves and base_frequency must be >= 1, got {octaves}, {base_frequency}")
    _check_range("persistence", persistence, 0.0, 1.0, lo_open=True)
    _check_range("base_radius", base_radius, 0.0, 0.5, lo_open=True)
    _check_range("top_radius", top_radius, 0.0, 0.5, lo_open=True)
    _check_range("sway", sway, 0.0, 0.5)
    _check_range("turbulence", turbulence, 0.0, 1.0)
    _check_range("margin", margin, 0.0, 0.5, hi_open=True)
    _check_range("softness", softness, 0.0, 0.5)

    height = shape[1]
    z, y, x = (_centres(n) for n in shape)
    t = np.clip((y - margin) / (1.0 - 2.0 * margin), 0.0, 1.0)                     # (H,) height along the column
    wander = rng.random((2, 5))                                                     # 1-D lattices for x and z drift
    drift = np.stack([_interp_axis(w, 0, height, 4, 0.0) for w in wander])         # (2, H) in [0, 1]
    cx = 0.5 + 2.0 * sway * t * (drift[0] - 0.5)
    cz = 0.5 + 2.0 * sway * t * (drift[1] - 0.5)
    radius = base_radius + (top_radius - base_radius) * t                           # (H,)
    d2 = (x[None, None, :] - cx[None, :, None]) ** 2 + (z[:, None, None] - cz[None, :, None]) ** 2
    column = np.exp(-2.0 * d2 / radius[None, :, None] ** 2)
    vertical = _smoothstep(0.0, 0.08, t) * (1.0 - 0.5 * t) * (1.0 - _smoothstep(0.75, 1.0, t))
    noise = _fbm(rng, shape, int(octaves), int(base_frequency), float(persistence), stretch=(1.0, 0.5, 1.0))
    density = column * vertical[None, :, None] * (1.0 - turbulence + turbulence * noise)
    return _normalise_max(density * _face_falloff(shape, margin, softness))


# ---------------------------------------------------------------------------------------------
# Anatomy-like fields from closed meshes
def voxel_centres(resolution: Resolution) -> np.ndarray:
    """(D, H, W, 3) unit-cube (x, y, z) coordinates of the voxel centres of a [z, y, x] grid."""
    depth, height, width = _grid_shape(resolution)
    z, y, x = np.meshgrid(_centres(depth), _centres(height), _centres(width), indexing="ij")
    return np.stack([x, y, z], axis=-1)



# ---------------------------------------------------------------------------------------------
# User volumes
# ---------------------------------------------------------------------------------------------

def load_field(path: str | pathlib.Path) -> np.ndarray:
    """(D, H, W) float32 scalar field in [0, 1] from a user's ``.npy`` file, indexed [z, y, x] as stored.

    The array must be 3-D, real (float or integer, e.g. uint8 / uint16 CT data), finite and not constant;
    it is normalised by its min / max. Errors name the file.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"volume field {str(path)!r} does not exist")
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 -- any unreadable file is the same user error
        raise ValueError(f"volume field {str(path)!r} is not a readable .npy array: {exc}") from exc
    if not isinstance(array, np.ndarray):
        raise ValueError(f"volume field {str(path)!r} holds {type(array).__name__}, not a single .npy array")
    if array.ndim != 3:
        raise ValueError(f"volume field {str(path)!r} must be a 3-D (D, H, W) array indexed [z, y, x], "
                         f"got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise ValueError(f"volume field {str(path)!r} must hold real numbers, got dtype {array.dtype}")
    if array.size == 0:
        raise ValueError(f"volume field {str(path)!r} is empty (shape {array.shape})")
    values = array.astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"volume field {str(path)!r} has {int((~np.isfinite(values)).sum())} non-finite values")
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        raise ValueError(f"volume field {str(path)!r} is constant ({lo}); cannot normalise it to [0, 1]")
    return np.clip((values - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)
