"""Object-space meshes for procedural scenes, rigid transforms, and byte-stable PLY export.

Conventions: metres, y is up. Every mesh is centred on its axis-aligned bounding box centre, has
outward-facing triangle winding, and is exported *unwelded* (three vertices per triangle) so each
triangle can carry its own planar-projection UVs and flat or crease-aware smooth normals.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import trimesh
from trimesh.visual import TextureVisuals

OBJECT_SHAPE_MIX: dict[str, float] = {
    "box": 0.14,
    "icosphere": 0.10,
    "cylinder": 0.10,
    "cone": 0.08,
    "capsule": 0.10,
    "torus": 0.10,
    "displaced_sphere": 0.14,
    "extrusion": 0.12,
    "stacked_boxes": 0.12,
}
"""Probability of each procedural object shape (sums to 1). Primitives come from trimesh.creation;
displaced_sphere is an icosphere pushed along its normals by 3D value noise, extrusion is a random
star-shaped polygon extruded along y, stacked_boxes is 2-4 boxes of decreasing size piled up."""

# Shapes whose top is flat when upright, so other objects may be stacked on them.
FLAT_TOP_SHAPES = ("box", "cylinder", "extrusion", "stacked_boxes")

SMOOTH_CREASE_DEG = 35.0
"""Edges whose dihedral angle exceeds this stay sharp when computing smooth vertex normals."""


@dataclass
class ObjectMesh:
    """A centred object-space mesh: vertices (V, 3) metres, faces (F, 3) int, smooth or flat shading."""
    kind: str
    vertices: np.ndarray
    faces: np.ndarray
    smooth: bool

    @property
    def bounding_radius(self) -> float:
        """Radius (metres) of the origin-centred sphere enclosing all vertices."""
        return float(np.linalg.norm(self.vertices, axis=1).max())

    def scaled(self, factor: float) -> "ObjectMesh":
        return ObjectMesh(self.kind, self.vertices * factor, self.faces, self.smooth)


# ---------------------------------------------------------------------------------------------
# Rigid transforms
# ---------------------------------------------------------------------------------------------

def rotation_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) right-handed rotation about `axis` (3,) by `angle_rad` radians (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    x, y, z = axis
    skew = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * skew + (1.0 - np.cos(angle_rad)) * (skew @ skew)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation drawn uniformly from SO(3) via a normalised Gaussian quaternion."""
    quat = rng.normal(size=4)
    w, x, y, z = quat / np.linalg.norm(quat)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) homogeneous transform x -> R x + t."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


# ---------------------------------------------------------------------------------------------
# Shape builders (all return y-up meshes; `size` is the rough diameter in metres)
# ---------------------------------------------------------------------------------------------

_Z_TO_Y = rotation_matrix(np.array([1.0, 0.0, 0.0]), -np.pi / 2)  # maps +z onto +y


def _from_trimesh(kind: str, mesh: trimesh.Trimesh, smooth: bool, z_up: bool = False) -> ObjectMesh:
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if z_up:
        vertices = vertices @ _Z_TO_Y.T
    faces = np.asarray(mesh.faces, dtype=np.int64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return ObjectMesh(kind, vertices - 0.5 * (lo + hi), faces, smooth)


def _value_noise_3d(rng: np.random.Generator, points: np.ndarray, frequency: float) -> np.ndarray:
    """(N,) smooth value noise in [0, 1] at (N, 3) points, on a random periodic 16^3 lattice."""
    period = 16
    lattice = rng.random((period, period, period))
    p = points * frequency
    base = np.floor(p).astype(np.int64)
    f = p - base
    f = f * f * (3.0 - 2.0 * f)
    result = np.zeros(len(points))
    for corner in range(8):
        offset = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
        idx = (base + offset) % period
        weight = np.prod(np.where(offset == 1, f, 1.0 - f), axis=1)
        result += weight * lattice[idx[:, 0], idx[:, 1], idx[:, 2]]
    return result


def _star_extrusion(rng: np.random.Generator, radius: float, height: float) -> trimesh.Trimesh:
    """Random star-shaped polygon (fan-triangulable from its centre) extruded along +z."""
    n = int(rng.integers(5, 13))
    angles = np.sort((np.arange(n) + rng.uniform(-0.35, 0.35, n)) * (2 * np.pi / n))
    radii = radius * rng.uniform(0.45, 1.0, n)
    ring = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    bottom = np.column_stack([ring, np.zeros(n)])
    top = np.column_stack([ring, np.full(n, height)])
    vertices = np.vstack([bottom, top, [[0.0, 0.0, 0.0]], [[0.0, 0.0, height]]])
    i = np.arange(n)
    j = (i + 1) % n
    cb, ct = 2 * n, 2 * n + 1
    faces = np.vstack([
        np.column_stack([np.full(n, cb), j, i]),          # bottom cap, facing -z
        np.column_stack([np.full(n, ct), n + i, n + j]),  # top cap, facing +z
        np.column_stack([i, j, n + j]),                   # sides, outward for counter-clockwise ring
        np.column_stack([i, n + j, n + i]),
    ])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _stacked_boxes(rng: np.random.Generator, size: float) -> trimesh.Trimesh:
    """2-4 boxes of decreasing footprint piled along +y with random offsets and yaw."""
    parts = []
    y = 0.0
    width = size
    for _ in range(int(rng.integers(2, 5))):
        extents = np.array([width * rng.uniform(0.6, 1.0), size * rng.uniform(0.15, 0.4),
                            width * rng.uniform(0.6, 1.0)])
        yaw = rotation_matrix(np.array([0.0, 1.0, 0.0]), rng.uniform(0, np.pi / 2))
        offset = np.array([rng.uniform(-0.15, 0.15) * width, y + extents[1] / 2, rng.uniform(-0.15, 0.15) * width])
        parts.append(trimesh.creation.box(extents=extents, transform=make_transform(yaw, offset)))
        y += extents[1]
        width *= rng.uniform(0.55, 0.85)
    return trimesh.util.concatenate(parts)


def draw_object_mesh(rng: np.random.Generator, kind: str, size: float) -> ObjectMesh:
    """Build a random mesh of the given kind whose largest dimension is about `size` metres."""
    r = size / 2
    if kind == "box":
        extents = size * rng.uniform(0.35, 1.0, 3)
        return _from_trimesh(kind, trimesh.creation.box(extents=extents), smooth=False)
    if kind == "icosphere":
        return _from_trimesh(kind, trimesh.creation.icosphere(subdivisions=3, radius=r), smooth=True)
    if kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=r * rng.uniform(0.3, 1.0), height=size * rng.uniform(0.4, 1.0),
                                         sections=40)
        return _from_trimesh(kind, mesh, smooth=True, z_up=True)
    if kind == "cone":
        mesh = trimesh.creation.cone(radius=r * rng.uniform(0.4, 1.0), height=size * rng.uniform(0.5, 1.0),
                                     sections=40)
        return _from_trimesh(kind, mesh, smooth=True, z_up=True)
    if kind == "capsule":
        radius = r * rng.uniform(0.25, 0.5)
        mesh = trimesh.creation.capsule(height=max(size - 2 * radius, 0.05), radius=radius, count=[24, 24])
        return _from_trimesh(kind, mesh, smooth=True, z_up=True)
    if kind == "torus":
        minor = r * rng.uniform(0.12, 0.35)
        mesh = trimesh.creation.torus(major_radius=r - minor, minor_radius=minor, major_sections=48,
                                      minor_sections=20)
        return _from_trimesh(kind, mesh, smooth=True, z_up=True)
    if kind == "displaced_sphere":
        sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
        unit = np.asarray(sphere.vertices)
        noise = _value_noise_3d(rng, unit + rng.uniform(0, 16, 3), frequency=rng.uniform(1.5, 4.0))
        amplitude = rng.uniform(0.1, 0.35)
        displaced = unit * (r * (1.0 - amplitude + 2.0 * amplitude * noise))[:, None]
        mesh = trimesh.Trimesh(vertices=displaced, faces=sphere.faces, process=False)
        return _from_trimesh(kind, mesh, smooth=True)
    if kind == "extrusion":
        mesh = _star_extrusion(rng, radius=r, height=size * rng.uniform(0.2, 1.0))
        return _from_trimesh(kind, mesh, smooth=False, z_up=True)
    if kind == "stacked_boxes":
        return _from_trimesh(kind, _stacked_boxes(rng, size), smooth=False)
    raise ValueError(f"unknown object kind {kind!r}")


def quad_mesh(center: np.ndarray, half_u: np.ndarray, half_v: np.ndarray, normal: np.ndarray,
              kind: str = "quad") -> ObjectMesh:
    """Two-triangle rectangle spanned by half-extent vectors `half_u`, `half_v` (3,), winding facing `normal`."""
    corners = center + np.array([-half_u - half_v, half_u - half_v, half_u + half_v, -half_u + half_v])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), normal) < 0:
        faces = faces[:, ::-1]
    return ObjectMesh(kind, corners, faces, smooth=False)


# ---------------------------------------------------------------------------------------------
# Normals, UVs and export
# ---------------------------------------------------------------------------------------------

def _face_normals_and_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(length, 1e-20)[:, None]
    return normals, 0.5 * length


def corner_normals(vertices: np.ndarray, faces: np.ndarray, smooth: bool,
                   crease_deg: float = SMOOTH_CREASE_DEG) -> np.ndarray:
    """Per-corner normals (F*3, 3): face normals if flat; else area-weighted averages over the faces around
    each vertex whose normal is within `crease_deg` of the corner's own face (keeps cylinder rims sharp)."""
    face_n, area = _face_normals_and_areas(vertices, faces)
    n_faces = len(faces)
    if not smooth:
        return np.repeat(face_n, 3, axis=0)
    # Weld coincident vertices first so adjacency is found even when the builder duplicated them.
    _, weld = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    corner_vertex = weld.reshape(-1)[faces.reshape(-1)]
    corner_face = np.repeat(np.arange(n_faces), 3)
    incidence = scipy.sparse.csr_matrix(
        (np.ones(len(corner_vertex)), (np.arange(len(corner_vertex)), corner_vertex)))
    pairs = (incidence @ incidence.T).tocoo()  # (corner, corner') sharing one welded vertex
    own, other = corner_face[pairs.row], corner_face[pairs.col]
    keep = np.einsum("ij,ij->i", face_n[own], face_n[other]) >= np.cos(np.radians(crease_deg))
    weights = area[other] * keep
    summed = np.zeros((3 * n_faces, 3))
    for axis in range(3):
        summed[:, axis] = np.bincount(pairs.row, weights=weights * face_n[other, axis], minlength=3 * n_faces)
    length = np.linalg.norm(summed, axis=1, keepdims=True)
    fallback = np.repeat(face_n, 3, axis=0)
    return np.where(length > 1e-12, summed / np.maximum(length, 1e-20), fallback)


def planar_uvs(vertices: np.ndarray, faces: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
    """Per-corner UVs (F*3, 2) in metres: each triangle is projected onto the coordinate plane most
    perpendicular to its normal (box / triplanar mapping). `offset` (3,) shifts the projection origin."""
    face_n, _ = _face_normals_and_areas(vertices, faces)
    dominant = np.argmax(np.abs(face_n), axis=1)
    # (u, v) axes per dominant axis: x-facing -> (z, y), y-facing -> (x, z), z-facing -> (x, y).
    u_axis = np.array([2, 0, 0])[dominant]
    v_axis = np.array([1, 2, 1])[dominant]
    pts = vertices[faces] + (0.0 if offset is None else offset)
    u = np.take_along_axis(pts, np.repeat(u_axis[:, None, None], 3, axis=1), axis=2)[..., 0]
    v = np.take_along_axis(pts, np.repeat(v_axis[:, None, None], 3, axis=1), axis=2)[..., 0]
    return np.stack([u, v], axis=-1).reshape(-1, 2)


def export_ply(mesh: ObjectMesh, path: pathlib.Path, uv_offset: np.ndarray | None = None) -> None:
    """Write an unwelded binary PLY (float32 positions + normals, `s`/`t` texture coordinates).

    trimesh's PLY writer is deterministic (fixed header comment, no timestamps), so identical meshes
    give identical bytes.
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    positions = mesh.vertices[faces].reshape(-1, 3)
    normals = corner_normals(mesh.vertices, faces, mesh.smooth)
    uvs = planar_uvs(mesh.vertices, faces, uv_offset)
    tm = trimesh.Trimesh(vertices=positions, faces=np.arange(len(positions)).reshape(-1, 3),
                         vertex_normals=normals, process=False, validate=False)
    tm.visual = TextureVisuals(uv=uvs)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = tm.export(file_type="ply", encoding="binary", vertex_normal=True)
    path.write_bytes(data)
