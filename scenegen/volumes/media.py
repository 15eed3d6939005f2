"""Heterogeneous media: scalar fields, transfer functions and the Mitsuba scene-dict entry of a medium box.

Conventions (Iglesias-Guitian et al. 2022 volumetric scenes):

- A *scalar field* is a float32 array (D, H, W) with values in [0, 1], indexed [z, y, x] on the unit
  cube: voxel [k, j, i] has its centre at ((i + 0.5) / W, (j + 0.5) / H, (k + 0.5) / D) in (x, y, z).
  This is the layout of Mitsuba's ``gridvolume`` (last array axis = world x, first = world z).
- A :class:`TransferFunction` maps the scalar to extinction sigma_t (1 / scene unit, before the medium's
  ``scale``) and to the single-scattering albedo (linear RGB in [0, 1]) by piecewise-linear ramps.
- :func:`medium_shape` is the Mitsuba dict of a ``cube`` with a ``null`` BSDF whose ``interior`` is a
  ``heterogeneous`` medium, the grids mapped from the unit cube onto a world box; :func:`update_medium`
  edits an already-loaded scene through ``mi.traverse`` (transfer-function animation without rebuilding).
  A volumetric scene needs the ``volpath`` integrator: ``path`` silently ignores media.

Scalar fields: scenegen.volumes.fields (procedural, .npy) and scenegen.volumes.mesh (shells of a mesh).
:class:`TransferFunction` is pure numpy; :func:`medium_shape` and :func:`update_medium` import mitsuba
lazily and expect a variant to be set (``scenegen.mitsuba_env.init_mitsuba()``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from scenegen.volumes.fields import _check_range

# ---------------------------------------------------------------------------------------------
# Transfer functions
# ---------------------------------------------------------------------------------------------

def _points(name: str, points: Any, width: int) -> tuple[tuple[float, ...], ...]:
    """Validated control points as a tuple of float tuples (scalar, value...) with strictly increasing
    scalars in [0, 1]."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != width or len(array) == 0:
        raise ValueError(f"{name} control points must be a non-empty list of {width}-tuples "
                         f"(scalar, {'value' if width == 2 else 'r, g, b'}), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} control points must be finite, got {array.tolist()}")
    scalars = array[:, 0]
    if np.any(scalars < 0.0) or np.any(scalars > 1.0):
        raise ValueError(f"{name} control-point scalars must lie in [0, 1], got {scalars.tolist()}")
    if np.any(np.diff(scalars) <= 0.0):
        raise ValueError(f"{name} control-point scalars must be strictly increasing, got {scalars.tolist()}")
    return tuple(tuple(float(v) for v in row) for row in array)


def _resample(points: tuple[tuple[float, ...], ...], knots: np.ndarray) -> np.ndarray:
    """(K, C) values of the piecewise-linear function ``points`` (constant beyond its ends) at ``knots``."""
    array = np.asarray(points, dtype=np.float64)
    return np.stack([np.interp(knots, array[:, 0], array[:, c]) for c in range(1, array.shape[1])], axis=1)


def _shift_points(points: tuple[tuple[float, ...], ...], offset: float) -> list[list[float]]:
    """Control points of s -> f(s - offset) on [0, 1]: moved knots inside [0, 1] plus the ends 0 and 1."""
    scalars = np.asarray(points, dtype=np.float64)[:, 0] + offset
    knots = np.unique(np.concatenate([[0.0, 1.0], scalars[(scalars > 0.0) & (scalars < 1.0)]]))
    values = _resample(points, knots - offset)
    return [[float(k), *map(float, v)] for k, v in zip(knots, values)]


@dataclass(frozen=True)
class TransferFunction:
    """Piecewise-linear maps from a scalar in [0, 1] to extinction and to RGB albedo.

    ``extinction``: control points (scalar, sigma_t) with sigma_t >= 0 in 1 / scene unit (multiplied by the
    medium's ``scale``); ``albedo``: control points (scalar, r, g, b) with r, g, b in [0, 1] (single-scattering
    albedo, linear RGB). Scalars strictly increasing in [0, 1]; values are constant beyond the first and last
    control point (``np.interp``). Lists are accepted and stored as tuples of floats.
    """
    extinction: tuple[tuple[float, float], ...]
    albedo: tuple[tuple[float, float, float, float], ...]

    def __post_init__(self) -> None:
        extinction = _points("extinction", self.extinction, 2)
        albedo = _points("albedo", self.albedo, 4)
        if any(value < 0.0 for _, value in extinction):
            raise ValueError(f"extinction values must be >= 0, got {[v for _, v in extinction]}")
        if any(not 0.0 <= c <= 1.0 for row in albedo for c in row[1:]):
            raise ValueError(f"albedo colours must lie in [0, 1], got {[list(row[1:]) for row in albedo]}")
        object.__setattr__(self, "extinction", extinction)
        object.__setattr__(self, "albedo", albedo)

    # -- evaluation --------------------------------------------------------------------------------
    def apply(self, field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(D, H, W) scalar field in [0, 1] -> (sigma_t (D, H, W) float32, albedo (D, H, W, 3) float32)."""
        values = np.asarray(field)
        if values.ndim != 3:
            raise ValueError(f"field must be a 3-D (D, H, W) array, got shape {values.shape}")
        if values.dtype.kind not in "fiu":
            raise ValueError(f"field must hold real numbers, got dtype {values.dtype}")
        values = values.astype(np.float64)
        if not np.all(np.isfinite(values)):
            raise ValueError("field has non-finite values")
        if values.size and (values.min() < 0.0 or values.max() > 1.0):
            raise ValueError(f"field values must lie in [0, 1], got [{values.min()}, {values.max()}]")
        ext = np.asarray(self.extinction)
        alb = np.asarray(self.albedo)
        sigma_t = np.interp(values, ext[:, 0], ext[:, 1]).astype(np.float32)
        albedo = np.stack([np.interp(values, alb[:, 0], alb[:, c]) for c in (1, 2, 3)], axis=-1).astype(np.float32)
        return sigma_t, albedo

    @property
    def max_extinction(self) -> float:
        """Largest sigma_t the function can produce (1 / scene unit, before the medium's scale)."""
        return max(value for _, value in self.extinction)

    # -- manifest ----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, list[list[float]]]:
        """JSON-ready {'extinction': [[s, sigma_t], ...], 'albedo': [[s, r, g, b], ...]}."""
        return {"extinction": [list(row) for row in self.extinction], "albedo": [list(row) for row in self.albedo]}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TransferFunction":
        """Inverse of :meth:`to_dict` (validated; unknown or missing keys are errors)."""
        if not isinstance(data, dict):
            raise TypeError(f"transfer function must be a dict, got {type(data).__name__}")
        keys = set(data)
        if keys != {"extinction", "albedo"}:
            raise ValueError(f"transfer function needs exactly the keys 'extinction' and 'albedo', "
                             f"got {sorted(keys)}")
        return cls(extinction=data["extinction"], albedo=data["albedo"])

    # -- edits over time ---------------------------------------------------------------------------
    def shifted(self, offset: float, *, albedo: bool = False) -> "TransferFunction":
        """The opacity ramp slid along the scalar axis by ``offset`` (new sigma_t(s) = sigma_t(s - offset),
        constant beyond the old ends); with ``albedo=True`` the colour ramp slides too."""
        offset = _check_range("offset", offset, -1.0, 1.0)
        return TransferFunction(_shift_points(self.extinction, offset),
                                _shift_points(self.albedo, offset) if albedo else self.albedo)

    def scaled(self, factor: float) -> "TransferFunction":
        """Extinction multiplied by ``factor`` >= 0 (a denser or thinner medium, same colours)."""
        factor = float(factor)
        if not (math.isfinite(factor) and factor >= 0.0):
            raise ValueError(f"extinction factor must be finite and >= 0, got {factor}")
        return TransferFunction([(s, v * factor) for s, v in self.extinction], self.albedo)

    def recoloured(self, rgb_scale: Sequence[float]) -> "TransferFunction":
        """Albedo multiplied per channel by ``rgb_scale`` (3,) >= 0, clipped to [0, 1]."""
        scale = np.asarray(rgb_scale, dtype=np.float64)
        if scale.shape != (3,) or not np.all(np.isfinite(scale) & (scale >= 0.0)):
            raise ValueError(f"rgb_scale must be three finite values >= 0, got {rgb_scale!r}")
        albedo = [(row[0], *np.clip(np.asarray(row[1:]) * scale, 0.0, 1.0)) for row in self.albedo]
        return TransferFunction(self.extinction, albedo)

    def interpolate(self, other: "TransferFunction", t: float) -> "TransferFunction":
        """(1 - t) * self + t * other, exactly (control points at the union of both functions' scalars)."""
        t = _check_range("t", t, 0.0, 1.0)

        def lerp(a: tuple, b: tuple) -> list[list[float]]:
            knots = np.unique(np.concatenate([np.asarray(a)[:, 0], np.asarray(b)[:, 0]]))
            values = (1.0 - t) * _resample(a, knots) + t * _resample(b, knots)
            return [[float(k), *map(float, v)] for k, v in zip(knots, values)]

        if not isinstance(other, TransferFunction):
            raise TypeError(f"other must be a TransferFunction, got {type(other).__name__}")
        return TransferFunction(lerp(self.extinction, other.extinction), lerp(self.albedo, other.albedo))


# ---------------------------------------------------------------------------------------------
# Mitsuba
# ---------------------------------------------------------------------------------------------

def _check_grids(sigma_t: np.ndarray | None, albedo: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """float32 copies; sigma_t (D, H, W) finite >= 0, albedo (D, H, W, 3) in [0, 1], same (D, H, W)."""
    out_sigma = out_albedo = None
    if sigma_t is not None:
        out_sigma = np.ascontiguousarray(sigma_t, dtype=np.float32)
        if out_sigma.ndim != 3 or out_sigma.size == 0:
            raise ValueError(f"sigma_t must be a non-empty (D, H, W) grid, got shape {out_sigma.shape}")
        if not np.all(np.isfinite(out_sigma)) or out_sigma.min() < 0.0:
            raise ValueError("sigma_t must be finite and >= 0")
    if albedo is not None:
        out_albedo = np.ascontiguousarray(albedo, dtype=np.float32)
        if out_albedo.ndim != 4 or out_albedo.shape[-1] != 3 or out_albedo.size == 0:
            raise ValueError(f"albedo must be a (D, H, W, 3) grid, got shape {out_albedo.shape}")
        if not np.all(np.isfinite(out_albedo)) or out_albedo.min() < 0.0 or out_albedo.max() > 1.0:
            raise ValueError("albedo must be finite and in [0, 1]")
    if out_sigma is not None and out_albedo is not None and out_sigma.shape != out_albedo.shape[:3]:
        raise ValueError(f"sigma_t {out_sigma.shape} and albedo {out_albedo.shape} grids differ in (D, H, W)")
    return out_sigma, out_albedo


def _check_scale(scale: float) -> float:
    scale = float(scale)
    if not (math.isfinite(scale) and scale >= 0.0):
        raise ValueError(f"medium scale must be finite and >= 0, got {scale}")
    return scale


def medium_shape(sigma_t: np.ndarray, albedo: np.ndarray, bbox_min: Sequence[float], bbox_max: Sequence[float],
                 scale: float = 1.0) -> dict[str, Any]:
    """Mitsuba dict of a ``cube`` with a ``null`` BSDF whose ``interior`` is a ``heterogeneous`` medium.

    ``sigma_t`` (D, H, W) >= 0 (1 / scene unit; grey extinction, see Mitsuba issue #1387) and ``albedo``
    (D, H, W, 3) in [0, 1] are [z, y, x] grids on the unit cube, mapped onto the world box
    [bbox_min, bbox_max] (x, y, z), like the cube itself. ``scale`` multiplies sigma_t. Isotropic phase.
    Render with ``volpath``; edit later with :func:`update_medium`.
    """
    import mitsuba as mi

    sigma, alb = _check_grids(sigma_t, albedo)
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)) or np.any(hi <= lo):
        raise ValueError(f"bbox_min {bbox_min!r} must be below bbox_max {bbox_max!r} on every axis (x, y, z)")
    extent = hi - lo
    unit_to_box = mi.ScalarTransform4f().translate(lo.tolist()).scale(extent.tolist())      # [0, 1]^3 -> box
    cube_to_box = mi.ScalarTransform4f().translate((0.5 * (lo + hi)).tolist()).scale((0.5 * extent).tolist())
    return {
        "type": "cube",
        "to_world": cube_to_box,                                                             # [-1, 1]^3 -> box
        "bsdf": {"type": "null"},
        "interior": {
            "type": "heterogeneous",
            "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(sigma[..., None]), "to_world": unit_to_box},
            "albedo": {"type": "gridvolume", "grid": mi.VolumeGrid(alb), "to_world": unit_to_box},
            "scale": _check_scale(scale),
            "phase": {"type": "isotropic"},
        },
    }


MEDIUM_KEY_SUFFIXES = (".sigma_t.data", ".albedo.data", ".scale")
"""``mi.traverse`` keys of a medium built by :func:`medium_shape`: ``<shape>.interior_medium`` + these."""


def medium_keys(params: Any) -> dict[str, dict[str, str]]:
    """{medium prefix: {'sigma_t' | 'albedo' | 'scale': full key}} of the grid media found in ``mi.traverse``
    parameters (a prefix is the key before ``.sigma_t.data``, e.g. ``'cloud.interior_medium'``)."""
    keys = list(params.keys())
    media: dict[str, dict[str, str]] = {}
    for key in keys:
        if key.endswith(".sigma_t.data"):
            prefix = key[: -len(".sigma_t.data")]
            found = {"sigma_t": key}
            for name, suffix in (("albedo", ".albedo.data"), ("scale", ".scale")):
                if prefix + suffix in keys:
                    found[name] = prefix + suffix
            media[prefix] = found
    return media


def update_medium(scene: Any, sigma_t: np.ndarray | None, albedo: np.ndarray | None, scale: float | None = None,
                  *, medium: str | None = None) -> str:
    """Replace the grids (and optionally the scale) of a loaded scene's heterogeneous medium in place.

    Uses ``mi.traverse(scene)`` + ``params.update()`` (Mitsuba refreshes the majorant), so a transfer-function
    edit needs no rebuild. ``sigma_t`` (D, H, W) / ``albedo`` (D, H, W, 3) must match the existing grid
    resolution; None leaves that grid unchanged. ``medium``: the key prefix (see :func:`medium_keys`) when the
    scene holds several media. Returns the prefix of the medium that was updated.
    """
    import mitsuba as mi

    sigma, alb = _check_grids(sigma_t, albedo)
    params = mi.traverse(scene)
    media = medium_keys(params)
    if medium is not None:
        if medium not in media:
            raise KeyError(f"no grid medium {medium!r} in the scene; found {sorted(media)}")
        prefix = medium
    elif len(media) == 1:
        prefix = next(iter(media))
    else:
        related = sorted(k for k in params.keys() if any(k.endswith(s) for s in MEDIUM_KEY_SUFFIXES)
                         or "medium" in k)
        if not media:
            raise KeyError(f"no heterogeneous medium with a grid sigma_t (key ending in '.sigma_t.data') in the "
                           f"scene; medium-related keys found: {related}")
        raise KeyError(f"the scene holds {len(media)} grid media {sorted(media)}; pass medium=<prefix>")
    keys = media[prefix]
    for name, grid, channels in (("sigma_t", sigma, 1), ("albedo", alb, 3)):
        if grid is None:
            continue
        if name not in keys:
            raise KeyError(f"medium {prefix!r} has no grid {name} (keys: {sorted(keys.values())})")
        current = tuple(params[keys[name]].shape)
        wanted = tuple(grid.shape[:3]) + (channels,)
        if current != wanted:
            raise ValueError(f"{name} grid {grid.shape} does not match the scene's {keys[name]} of shape {current}")
        params[keys[name]] = mi.TensorXf(grid.reshape(wanted))
    if scale is not None:
        if "scale" not in keys:
            raise KeyError(f"medium {prefix!r} exposes no scale (keys: {sorted(keys.values())})")
        params[keys["scale"]] = _check_scale(scale)
    params.update()
    return prefix
