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

Everything except :func:`medium_shape` and :func:`update_medium` is pure numpy; those two import mitsuba
lazily and expect a variant to be set (``scenegen.mitsuba_env.init_mitsuba()``). The generators are
deterministic: the same ``rng`` state and parameters give the same bytes.
"""
from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

Resolution = int | tuple[int, int, int]

#: Elements of one (points x triangles) work array in the mesh queries (~8 MB of float64).
_MESH_CHUNK_ELEMENTS = 1 << 20


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
# ---------------------------------------------------------------------------------------------

def _inside_mask(triangles: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """(D, H, W) bool: voxel centre inside the closed mesh of (F, 3, 3) unit-cube (x, y, z) triangles.

    Scanline parity: a ray along +x through every (y, z) row of voxel centres counts the triangles it
    crosses before each centre. Rows only meet triangles whose (y, z) bounding box covers them. A row
    through a projected edge or vertex is decided by simulation of simplicity (the row is taken at
    (y + eps, z + eps^2)), with each edge's orientation test computed once in a canonical vertex order,
    so two triangles sharing an edge never both count (or both miss) the crossing.
    """
    depth, height, width = shape
    ys, zs, xs = _centres(height), _centres(depth), _centres(width)
    ty, tz = triangles[:, :, 1], triangles[:, :, 2]
    area2 = (ty[:, 1] - ty[:, 0]) * (tz[:, 2] - tz[:, 0]) - (tz[:, 1] - tz[:, 0]) * (ty[:, 2] - ty[:, 0])
    faces = np.flatnonzero(area2 != 0.0)                 # faces parallel to x are never crossed transversally
    jlo = np.searchsorted(ys, ty[faces].min(axis=1), side="left")
    jhi = np.searchsorted(ys, ty[faces].max(axis=1), side="right")
    klo = np.searchsorted(zs, tz[faces].min(axis=1), side="left")
    khi = np.searchsorted(zs, tz[faces].max(axis=1), side="right")
    n_j, n_k = jhi - jlo, khi - klo
    n_pairs = n_j * n_k
    face = np.repeat(np.arange(len(faces)), n_pairs)
    within = np.arange(int(n_pairs.sum())) - np.repeat(np.cumsum(n_pairs) - n_pairs, n_pairs)
    row_j = jlo[face] + within // np.maximum(n_k[face], 1)
    row_k = klo[face] + within % np.maximum(n_k[face], 1)
    face = faces[face]
    py, pz = ys[row_j], zs[row_k]

    signs, weights = [], []
    for e in range(3):                                   # directed edge v_e -> v_(e+1), opposite vertex e+2
        a, b = e, (e + 1) % 3
        # Canonical order: the vertex smaller in (y, z) first, so both faces of an edge compute the same w.
        ay, az, by, bz = ty[face, a], tz[face, a], ty[face, b], tz[face, b]
        swap = (ay > by) | ((ay == by) & (az > bz))
        ay, by = np.where(swap, by, ay), np.where(swap, ay, by)
        az, bz = np.where(swap, bz, az), np.where(swap, az, bz)
        w = (by - ay) * (pz - az) - (bz - az) * (py - ay)
        tie = np.where(bz != az, -np.sign(bz - az), np.sign(by - ay))   # sign of w at (py + eps, pz + eps^2)
        sign = np.where(w != 0.0, np.sign(w), tie) * np.where(swap, -1.0, 1.0)
        signs.append(sign)
        weights.append(np.where(swap, -w, w))
    crossed = (signs[0] == signs[1]) & (signs[1] == signs[2]) & (signs[0] != 0.0)
    # Barycentric x of the crossing: the weight of vertex v is the edge function of the edge opposite it.
    tx = triangles[face[crossed], :, 0]
    w_opp = np.stack([weights[1][crossed], weights[2][crossed], weights[0][crossed]], axis=1)
    total = w_opp.sum(axis=1)
    safe = total != 0.0
    x_hit = np.where(safe, (w_opp * tx).sum(axis=1) / np.where(safe, total, 1.0), tx.mean(axis=1))
    first_after = np.searchsorted(xs, x_hit, side="right")            # first voxel whose centre is beyond the hit
    flat = (row_k[crossed] * height + row_j[crossed]) * (width + 1) + first_after
    hits = np.bincount(flat, minlength=depth * height * (width + 1)).reshape(depth, height, width + 1)
    return (np.cumsum(hits, axis=2)[..., :width] % 2) == 1


@dataclass(frozen=True)
class _Triangles:
    """Per-triangle quantities (F, ...) of the point-triangle distance."""
    a: np.ndarray          # (F, 3) first vertex
    ab: np.ndarray         # (F, 3) B - A
    ac: np.ndarray         # (F, 3) C - A
    unit_normal: np.ndarray  # (F, 3), zero for degenerate triangles
    d00: np.ndarray        # |AB|^2
    d01: np.ndarray        # AB . AC
    d11: np.ndarray        # |AC|^2
    ab_bc: np.ndarray      # AB . BC
    bc_bc: np.ndarray      # |BC|^2
    a_sq: np.ndarray       # |A|^2
    a_ab: np.ndarray       # A . AB
    a_ac: np.ndarray       # A . AC
    a_n: np.ndarray        # A . unit normal
    degenerate: np.ndarray  # (F,) bool

    @classmethod
    def build(cls, triangles: np.ndarray) -> "_Triangles":
        a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
        ab, ac, bc = b - a, c - a, c - b
        normal = np.cross(ab, ac)
        length = np.linalg.norm(normal, axis=1)
        degenerate = length <= 1e-300
        unit = normal / np.where(degenerate, 1.0, length)[:, None]

        def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            return np.einsum("fi,fi->f", u, v)

        return cls(a, ab, ac, unit, dot(ab, ab), dot(ab, ac), dot(ac, ac), dot(ab, bc), dot(bc, bc),
                   dot(a, a), dot(a, ab), dot(a, ac), dot(a, unit), degenerate)

    def subset(self, index: np.ndarray) -> "_Triangles":
        return _Triangles(**{name: getattr(self, name)[index] for name in self.__dataclass_fields__})

    def sq_distances(self, points: np.ndarray) -> np.ndarray:
        """(N, F) squared distances of (N, 3) points to the triangles.

        Everything follows from |AP|^2, AP.AB, AP.AC and AP.n (matrix products): the plane distance when the
        projection's barycentrics are inside the triangle, else the nearest of the three edge segments."""
        def segment_sq(ap_sq: np.ndarray, ap_e: np.ndarray, e_sq: np.ndarray) -> np.ndarray:
            t = np.clip(ap_e / np.where(e_sq > 0.0, e_sq, 1.0), 0.0, 1.0)
            return ap_sq - 2.0 * t * ap_e + t * t * e_sq

        pp = np.einsum("ni,ni->n", points, points)[:, None]
        ap_sq = np.maximum(pp - 2.0 * (points @ self.a.T) + self.a_sq, 0.0)      # |P - A|^2
        d20 = points @ self.ab.T - self.a_ab                                      # AP . AB
        d21 = points @ self.ac.T - self.a_ac                                      # AP . AC
        denom = np.where(self.degenerate, 1.0, self.d00 * self.d11 - self.d01 * self.d01)
        v = (self.d11 * d20 - self.d01 * d21) / denom
        w = (self.d00 * d21 - self.d01 * d20) / denom
        inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0) & ~self.degenerate
        plane_sq = (points @ self.unit_normal.T - self.a_n) ** 2
        bp_sq = np.maximum(ap_sq - 2.0 * d20 + self.d00, 0.0)                     # |P - B|^2
        bp_bc = (d21 - d20) - self.ab_bc                                          # BP . BC
        edge_sq = np.minimum(np.minimum(segment_sq(ap_sq, d20, self.d00), segment_sq(ap_sq, d21, self.d11)),
                             segment_sq(bp_sq, bp_bc, self.bc_bc))
        return np.maximum(np.where(inside, plane_sq, edge_sq), 0.0)


def _distance_to_mesh(points: np.ndarray, voxels: np.ndarray, triangles: np.ndarray, brick: int = 4) -> np.ndarray:
    """(N,) exact distance of (N, 3) points (at integer (N, 3) ``voxels`` indices) to the nearest triangle.

    Points are grouped into bricks of brick^3 voxels; with c a brick's centre, r its radius and d_c the
    distance of c to the mesh, only triangles within d_c + 2 r of c can be nearest to a point of the brick."""
    tris = _Triangles.build(triangles)
    brick_of = voxels // brick
    keys, inverse = np.unique(brick_of, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse, minlength=len(keys))
    centres = np.stack([np.bincount(inverse, points[:, axis], len(keys)) for axis in range(3)], axis=1)
    centres /= counts[:, None]
    radius = np.zeros(len(keys))
    np.maximum.at(radius, inverse, np.linalg.norm(points - centres[inverse], axis=1))
    step = max(1, _MESH_CHUNK_ELEMENTS // len(triangles))
    centre_sq = np.concatenate([tris.sq_distances(centres[s:s + step]) for s in range(0, len(keys), step)])
    centre_dist = np.sqrt(centre_sq)
    bound = centre_dist.min(axis=1) + 2.0 * radius + 1e-9
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    out = np.empty(len(points))
    for b in range(len(keys)):
        members = order[starts[b]:starts[b + 1]]
        candidates = np.flatnonzero(centre_dist[b] <= bound[b])
        out[members] = np.sqrt(tris.subset(candidates).sq_distances(points[members]).min(axis=1))
    return out


def voxel_centres(resolution: Resolution) -> np.ndarray:
    """(D, H, W, 3) unit-cube (x, y, z) coordinates of the voxel centres of a [z, y, x] grid."""
    depth, height, width = _grid_shape(resolution)
    z, y, x = np.meshgrid(_centres(depth), _centres(height), _centres(width), indexing="ij")
    return np.stack([x, y, z], axis=-1)


def shells_from_mesh(mesh: Any, resolution: Resolution = 32, layers: int | None = None, *, fit: bool = True,
                     margin: float = 0.05) -> np.ndarray:
    """(D, H, W) float32 'anatomy-like' field in [0, 1] of a closed mesh, indexed [z, y, x].

    The value at a voxel centre inside the mesh is its distance to the surface divided by the largest such
    distance (0 at the surface, 1 at the deepest voxel); outside it is exactly 0. With ``layers`` = L the
    depth is quantised into L nested shells of equal thickness with values 1/L, 2/L, ..., 1 (outermost
    'skin' 1/L, innermost 'bone' 1), so transfer-function thresholds between the plateaus separate them.

    ``mesh``: a closed (watertight) ``trimesh.Trimesh`` or anything with ``vertices`` (V, 3) and ``faces``
    (F, 3). ``fit=True`` scales it uniformly and centres it in [margin, 1 - margin]^3 (its world units are
    irrelevant); ``fit=False`` takes its (x, y, z) coordinates as unit-cube coordinates. Containment is
    scanline parity along x and depth the exact point-triangle distance with per-brick culling, both
    vectorised numpy (no rtree / embree needed).
    """
    import trimesh

    shape = _grid_shape(resolution)
    if layers is not None and (isinstance(layers, bool) or int(layers) != layers or int(layers) < 1):
        raise ValueError(f"layers must be None or a positive int, got {layers!r}")
    _check_range("margin", margin, 0.0, 0.5, hi_open=True)
    try:
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
    except AttributeError:
        raise TypeError(f"mesh must have vertices and faces (e.g. a trimesh.Trimesh), "
                        f"got {type(mesh).__name__}") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh needs vertices (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("mesh vertices must be finite")
    closed = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    if not closed.is_watertight:
        raise ValueError("mesh must be closed (watertight) to have an inside; trimesh reports it is not")
    vertices = np.asarray(closed.vertices, dtype=np.float64)
    triangles_idx = np.asarray(closed.faces, dtype=np.int64)
    if fit:
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        extent = float((hi - lo).max())
        if extent <= 0.0:
            raise ValueError("mesh has zero extent")
        vertices = (vertices - 0.5 * (lo + hi)) * ((1.0 - 2.0 * margin) / extent) + 0.5
    triangles = vertices[triangles_idx]

    inside = _inside_mask(triangles, shape).reshape(-1)
    if not inside.any():
        raise ValueError(f"no voxel centre of the {shape} grid lies inside the mesh "
                         f"(increase the resolution{' or use fit=True' if not fit else ''})")
    points = voxel_centres(shape).reshape(-1, 3)
    voxels = np.stack(np.unravel_index(np.flatnonzero(inside), shape), axis=1)   # (z, y, x): brick grouping only
    depth = np.zeros(len(points))
    depth[inside] = _distance_to_mesh(points[inside], voxels, triangles)
    depth /= depth.max()
    if layers is not None:
        depth = np.where(inside, np.maximum(np.ceil(depth * int(layers)), 1.0) / int(layers), 0.0)
    return np.clip(depth, 0.0, 1.0).astype(np.float32).reshape(shape)


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
