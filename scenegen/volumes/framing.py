"""Camera framing of a volumetric clip (scenegen.volumes.scenes): which part of the box a transfer function makes
visible, and how far an orbiting camera must stand so that part fills at most ``FRAME_FILL`` of the frame.
Positions and distances in scene units, angles in radians unless a name says degrees; y is up.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from scenegen.volumes.media import TransferFunction

UP = (0.0, 1.0, 0.0)

#: A voxel counts as visible when a ray crossing the whole box at its extinction would lose this fraction.
VISIBLE_OPTICAL_DEPTH = 0.05
#: The visible part of the volume spans at most this fraction of the frame's width and height.
FRAME_FILL = 0.9


def occupied_bounds(field: np.ndarray, transfer_functions: Sequence[TransferFunction], box_min: Sequence[float],
                    box_max: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners (x, y, z; scene units) of the voxels (field (D, H, W) indexed [z, y, x]) that any
    frame's transfer function makes visible (sigma_t x longest box side >= VISIBLE_OPTICAL_DEPTH); the whole
    box when none is."""
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    threshold = VISIBLE_OPTICAL_DEPTH / float((hi - lo).max())
    visible = np.zeros(field.shape, dtype=bool)
    for tf in transfer_functions:
        visible |= tf.apply(field)[0] >= threshold
    if not visible.any():
        return lo, hi
    shape_xyz = np.asarray(field.shape[::-1], dtype=np.float64)
    span = np.array([np.flatnonzero(visible.any(axis=tuple(a for a in range(3) if a != axis)))[[0, -1]]
                     for axis in (2, 1, 0)], dtype=np.float64)           # (x, y, z) x (first, last) voxel index
    return lo + span[:, 0] / shape_xyz * (hi - lo), lo + (span[:, 1] + 1.0) / shape_xyz * (hi - lo)


def orbit_radius(distance: float, height: float) -> float:
    """Horizontal radius of a camera orbit ``height`` above the target at ``distance`` from it (at least 0.5)."""
    return math.sqrt(max(distance ** 2 - height ** 2, 0.25))


def framing_spill(lower: np.ndarray, upper: np.ndarray, fov_x_deg: float, aspect: float, height: float,
                  angles: np.ndarray, distance: float, fill: float = FRAME_FILL) -> float:
    """How far the box [lower, upper] reaches towards the frame's edge, as a multiple of ``fill`` (1: it spans
    exactly ``fill`` of the width or height; inf: the camera is inside it), worst over the orbit ``angles``
    (radians) of a camera ``distance`` from the box's centre, ``height`` above it, looking at it.
    ``aspect`` = height / width of the frame."""
    centre = 0.5 * (lower + upper)
    corners = np.array(np.meshgrid(*zip(lower, upper), indexing="ij")).reshape(3, -1).T - centre    # (8, 3)
    tan_x = math.tan(math.radians(fov_x_deg) / 2)
    limits = fill * np.array([tan_x, tan_x * aspect])
    radius = orbit_radius(distance, height)
    worst = 0.0
    for angle in angles:
        origin = np.array([radius * math.cos(angle), height, radius * math.sin(angle)])
        forward = -origin / np.linalg.norm(origin)
        right = np.cross(forward, UP)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        rel = corners - origin
        depth = rel @ forward
        if depth.min() <= 1e-6:
            return math.inf
        worst = max(worst, float(np.max(np.abs(rel @ right) / depth) / limits[0]),
                    float(np.max(np.abs(rel @ up) / depth) / limits[1]))
    return worst


def framing_distance(lower: np.ndarray, upper: np.ndarray, fov_x_deg: float, aspect: float, height: float,
                     angles: np.ndarray) -> float:
    """Smallest camera distance at which :func:`framing_spill` is at most 1 (bisection: the spill shrinks
    as the camera backs off)."""
    def spill(distance: float) -> float:
        return framing_spill(lower, upper, fov_x_deg, aspect, height, angles, distance)

    near, far = abs(height) + 1e-3, max(2.0 * abs(height), 1.0)
    while spill(far) > 1.0:
        far *= 2.0
    for _ in range(40):
        middle = 0.5 * (near + far)
        near, far = (middle, far) if spill(middle) > 1.0 else (near, middle)
    return far
