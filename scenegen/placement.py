"""Object placement of the procedural scene generator: objects inside the room (or the open scene's
site), apart from each other and clear of the camera path, and their optional rigid motion.

Split out of `scenegen.generate`; every draw comes from the Generator passed in, in a fixed order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen import camera as cam
from scenegen import geometry as geo

ROOM_MARGIN_M = 0.02

PLACEMENT_MIX: dict[str, float] = {"floor": 0.55, "stacked": 0.25, "floating": 0.20}
"""Probability of resting an object on the floor, on top of a flat-topped object, or floating in the air."""


@dataclass
class PlacedObject:
    """An object mesh with its rigid placement; `per_frame` (n_frames, 4, 4) only for moving objects."""
    mesh: geo.ObjectMesh
    rotation: np.ndarray
    translation: np.ndarray
    placement: str
    support: int | None
    per_frame: np.ndarray | None = None

    @property
    def to_world(self) -> np.ndarray:
        return geo.make_transform(self.rotation, self.translation)

    def aabb(self, matrix: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        world = geo.transform_points(self.to_world if matrix is None else matrix, self.mesh.vertices)
        return world.min(axis=0), world.max(axis=0)


def draw_from_mix(rng: np.random.Generator, mix: dict[str, float]) -> str:
    """One name of ``mix`` (name -> probability, normalised here), drawn with one ``rng.choice``."""
    names = list(mix)
    probs = np.array([mix[n] for n in names], dtype=np.float64)
    return names[int(rng.choice(len(names), p=probs / probs.sum()))]


def _aabbs_overlap(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> bool:
    return bool(np.all(lo_a < hi_b) and np.all(lo_b < hi_a))


def _orientation(rng: np.random.Generator, kind: str, placement: str) -> np.ndarray:
    """(3, 3) rotation: upright with random yaw for resting objects, uniformly random when floating."""
    if placement == "floating":
        return geo.random_rotation(rng)
    yaw = geo.rotation_matrix(np.array([0.0, 1.0, 0.0]), rng.uniform(0, 2 * np.pi))
    if kind in ("icosphere", "displaced_sphere"):
        return geo.random_rotation(rng)
    if kind == "capsule" and rng.random() < 0.5:
        return yaw @ geo.rotation_matrix(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # lying on its side
    return yaw


class Placer:
    """Places objects in the room, keeping them inside it, apart from each other and off the camera path."""

    def __init__(self, room_size: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, focus: np.ndarray):
        self.room_lo = np.array([-room_size[0] / 2, 0.0, -room_size[2] / 2]) + ROOM_MARGIN_M
        self.room_hi = np.array([room_size[0] / 2, room_size[1], room_size[2] / 2]) - ROOM_MARGIN_M
        self.room_lo[1] = 0.0
        self.seg_start, self.seg_end = seg_start, seg_end
        self.focus = focus
        self.objects: list[PlacedObject] = []
        self.boxes: list[tuple[np.ndarray, np.ndarray]] = []

    def clear_of_camera(self, centres: np.ndarray, radius: float) -> bool:
        dist = cam.distance_to_segments(np.atleast_2d(centres), self.seg_start, self.seg_end)
        return bool(np.all(dist > radius + cam.CAMERA_CLEARANCE_M))

    def inside_room(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        return bool(np.all(lo >= self.room_lo - 1e-9) and np.all(hi <= self.room_hi + 1e-9))

    def _xz(self, rng: np.random.Generator, lo_r: np.ndarray, hi_r: np.ndarray) -> np.ndarray:
        lim_lo = self.room_lo[[0, 2]] - lo_r[[0, 2]]
        lim_hi = self.room_hi[[0, 2]] - hi_r[[0, 2]]
        if rng.random() < 0.35:
            # Cluster some objects around what the camera looks at, so frames are not empty.
            xz = self.focus[[0, 2]] + rng.normal(0.0, 1.0, 2)
        else:
            xz = rng.uniform(lim_lo, np.maximum(lim_hi, lim_lo))
        return np.clip(xz, lim_lo, np.maximum(lim_hi, lim_lo))

    def place(self, rng: np.random.Generator, mesh: geo.ObjectMesh) -> PlacedObject:
        supports = [i for i, o in enumerate(self.objects)
                    if o.mesh.kind in geo.FLAT_TOP_SHAPES and o.placement != "floating"]
        for attempt in range(400):
            if attempt and attempt % 20 == 0:
                mesh = mesh.scaled(0.85)  # crowded room: shrink until it fits
            placement = draw_from_mix(rng, PLACEMENT_MIX)
            if placement == "stacked" and not supports:
                placement = "floor"
            rotation = _orientation(rng, mesh.kind, placement)
            rotated = mesh.vertices @ rotation.T
            lo_r, hi_r = rotated.min(axis=0), rotated.max(axis=0)
            support: int | None = None
            if placement == "floor":
                xz = self._xz(rng, lo_r, hi_r)
                y = -lo_r[1] + 1e-3
            elif placement == "stacked":
                support = supports[int(rng.integers(len(supports)))]
                s_lo, s_hi = self.boxes[support]
                quarter = 0.25 * (s_hi - s_lo)
                centre_xz = rng.uniform((s_lo + quarter)[[0, 2]], (s_hi - quarter)[[0, 2]])
                xz = centre_xz - 0.5 * (lo_r + hi_r)[[0, 2]]
                y = s_hi[1] - lo_r[1] + 1e-3
            else:
                xz = self._xz(rng, lo_r, hi_r)
                y = rng.uniform(0.4 - lo_r[1], max(self.room_hi[1] - 0.3 - hi_r[1], 0.4 - lo_r[1]))
            translation = np.array([xz[0], y, xz[1]])
            lo, hi = lo_r + translation, hi_r + translation
            if not self.inside_room(lo, hi):
                continue
            if not self.clear_of_camera(translation, mesh.bounding_radius):
                continue
            # After many failures allow touching/overlapping neighbours, never the camera clearance.
            if attempt < 120 and any(_aabbs_overlap(lo, hi, b_lo, b_hi)
                                     for i, (b_lo, b_hi) in enumerate(self.boxes) if i != support):
                continue
            obj = PlacedObject(mesh, rotation, translation, placement, support)
            self.objects.append(obj)
            self.boxes.append((lo, hi))
            return obj
        raise RuntimeError("could not place an object clear of the camera path")

    def animate(self, rng: np.random.Generator, index: int, n_frames: int) -> bool:
        """Try to give object `index` a rigid motion (translation + rotation per frame) that stays in the
        room, off the camera path and clear of other objects; returns whether it succeeded."""
        obj = self.objects[index]
        others = [self.boxes[i] for i in range(len(self.objects)) if i != index
                  and not _aabbs_overlap(*self.boxes[index], *self.boxes[i])]
        t = np.arange(n_frames, dtype=np.float64)
        speed = rng.uniform(0.01, 0.06)
        for _attempt in range(8):
            direction = rng.normal(size=3)
            axis = rng.normal(size=3)
            if obj.placement != "floating":
                direction[1] = 0.0  # resting objects slide and spin on their support plane
                axis = np.array([0.0, 1.0, 0.0])
            direction /= np.linalg.norm(direction)
            spin = np.radians(rng.uniform(0.5, 4.0))
            matrices = np.stack([geo.make_transform(geo.rotation_matrix(axis, spin * k) @ obj.rotation,
                                                    obj.translation + speed * k * direction) for k in t])
            centres = matrices[:, :3, 3]
            ok = self.clear_of_camera(centres, obj.mesh.bounding_radius)
            for m in matrices if ok else []:
                lo, hi = obj.aabb(m)
                if not self.inside_room(lo, hi) or any(_aabbs_overlap(lo, hi, b_lo, b_hi) for b_lo, b_hi in others):
                    ok = False
                    break
            if ok:
                obj.per_frame = matrices
                return True
            speed *= 0.6
        return False

