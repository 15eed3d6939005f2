"""Camera fly-through paths inside the room and the pinhole camera model shared with Mitsuba.

Mitsuba's `look_at(origin, target, up)` builds a camera-to-world matrix whose columns are
(left, up', forward, origin): camera +z looks at the target, +y is up and +x points to the image's
*left*. The `perspective` sensor with `fov_axis='x'` maps camera point (x, y, z) to film position
    px = W/2 * (1 - x / (z tan(fov_x/2))),   py = H/2 * (1 - y / (z tan(fov_y/2)))
with tan(fov_y/2) = tan(fov_x/2) * H / W, pixels counted from the top-left corner (x right, y down).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CAMERA_PATH_TYPES = ("dolly", "orbit", "pan", "spline")

CAMERA_CLEARANCE_M = 0.5
"""No object's bounding sphere may come closer than this (metres) to any camera position or to the
segment between two consecutive camera positions of the clip."""

WALL_MARGIN_M = 0.8
"""Minimum horizontal distance (metres) between camera positions and walls."""

FOV_X_RANGE_DEG = (35.0, 75.0)


@dataclass
class CameraBox:
    """Axis-aligned box (metres) that camera positions must stay in."""
    lo: np.ndarray
    hi: np.ndarray

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> bool:
        return bool(np.all(points >= self.lo - tol) and np.all(points <= self.hi + tol))

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(self.lo, self.hi)

    def shrunk(self, margin: float) -> "CameraBox":
        centre = 0.5 * (self.lo + self.hi)
        half = np.maximum(0.5 * (self.hi - self.lo) - margin, 0.0)
        return CameraBox(centre - half, centre + half)


@dataclass
class CameraPath:
    """Per-frame camera origins (n, 3) and look-at targets (n, 3), metres; `speed` in m/frame
    (rad/frame for 'pan')."""
    kind: str
    origins: np.ndarray
    targets: np.ndarray
    speed: float


def camera_box(room_size: np.ndarray) -> CameraBox:
    """Region for camera positions in a room of size (sx, sy, sz) centred on x=z=0 with the floor at y=0."""
    sx, sy, sz = room_size
    lo = np.array([-sx / 2 + WALL_MARGIN_M, 0.6, -sz / 2 + WALL_MARGIN_M])
    hi = np.array([sx / 2 - WALL_MARGIN_M, min(sy - 0.6, 2.2), sz / 2 - WALL_MARGIN_M])
    return CameraBox(lo, hi)


def interest_box(room_size: np.ndarray) -> CameraBox:
    """Region where look-at targets and orbit centres are drawn (inner part of the room, low height)."""
    sx, sy, sz = room_size
    return CameraBox(np.array([-sx / 3, 0.3, -sz / 3]), np.array([sx / 3, min(1.5, sy - 0.5), sz / 3]))


def _direction(yaw: np.ndarray | float, pitch: np.ndarray | float) -> np.ndarray:
    """Unit view direction(s) (..., 3) from yaw about +y and pitch above the horizon (radians)."""
    yaw, pitch = np.asarray(yaw), np.asarray(pitch)
    return np.stack([np.cos(pitch) * np.cos(yaw), np.sin(pitch), np.cos(pitch) * np.sin(yaw)], axis=-1)


def catmull_rom(points: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Uniform Catmull-Rom spline through control points (K, 3) evaluated at parameters `samples` (N,) in
    [0, K-1]; the end tangents use mirrored phantom points. Returns (N, 3)."""
    padded = np.vstack([2 * points[0] - points[1], points, 2 * points[-1] - points[-2]])
    seg = np.clip(np.floor(samples).astype(np.int64), 0, len(points) - 2)
    t = (samples - seg)[:, None]
    p0, p1, p2, p3 = padded[seg], padded[seg + 1], padded[seg + 2], padded[seg + 3]
    return 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3)


def _keep_target_ahead(origins: np.ndarray, targets: np.ndarray, min_dist: float = 1.0,
                       max_abs_pitch_deg: float = 60.0) -> np.ndarray:
    """Push targets that are too close to the camera or too steeply above/below it to a safe direction."""
    view = targets - origins
    dist = np.linalg.norm(view, axis=1, keepdims=True)
    view = view / np.maximum(dist, 1e-9)
    horizontal = np.linalg.norm(view[:, [0, 2]], axis=1)
    max_sin = np.sin(np.radians(max_abs_pitch_deg))
    steep = np.abs(view[:, 1]) > max_sin
    if np.any(steep):
        # Rescale to the pitch limit; degenerate straight-up/down views fall back to +x.
        flat = np.where(horizontal[:, None] > 1e-6, view[:, [0, 2]] / np.maximum(horizontal, 1e-9)[:, None],
                        np.array([[1.0, 0.0]]))
        cos_lim = np.cos(np.radians(max_abs_pitch_deg))
        fixed = np.column_stack([flat[:, 0] * cos_lim, np.sign(view[:, 1]) * max_sin, flat[:, 1] * cos_lim])
        view = np.where(steep[:, None], fixed, view)
    return origins + view * np.maximum(dist, min_dist)


def _dolly(rng: np.random.Generator, n: int, box: CameraBox, room_size: np.ndarray) -> CameraPath:
    speed = rng.uniform(0.02, 0.12)
    for _ in range(100):
        yaw = rng.uniform(0, 2 * np.pi)
        direction = _direction(yaw, rng.uniform(-0.15, 0.15))
        start = box.sample(rng)
        origins = start + np.arange(n)[:, None] * speed * direction
        if box.contains(origins):
            break
        speed *= 0.95
    else:
        origins = np.repeat(box.sample(rng)[None], n, axis=0)
        direction = _direction(rng.uniform(0, 2 * np.pi), 0.0)
    if rng.random() < 0.5:
        # Look ahead along the motion, with a fixed sideways/vertical offset of the aim point.
        offset = np.array([rng.uniform(-1, 1), rng.uniform(-0.6, 0.1), rng.uniform(-1, 1)])
        targets = origins + 3.0 * direction + offset
    else:
        targets = np.repeat(interest_box(room_size).sample(rng)[None], n, axis=0)
    return CameraPath("dolly", origins, _keep_target_ahead(origins, targets), float(speed))


def _orbit(rng: np.random.Generator, n: int, box: CameraBox, room_size: np.ndarray) -> CameraPath:
    centre = interest_box(room_size).sample(rng)
    radius = rng.uniform(1.0, 3.0)
    speed = rng.uniform(0.03, 0.15)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    theta0 = rng.uniform(0, 2 * np.pi)
    height = np.clip(centre[1] + rng.uniform(0.2, 1.2), box.lo[1], box.hi[1])
    for attempt in range(60):
        angles = theta0 + sign * (speed / radius) * np.arange(n)
        origins = np.column_stack([centre[0] + radius * np.cos(angles), np.full(n, height),
                                   centre[2] + radius * np.sin(angles)])
        if box.contains(origins):
            break
        radius = max(radius * 0.9, 0.6)
        theta0 = rng.uniform(0, 2 * np.pi)
        if attempt >= 30:
            centre[[0, 2]] *= 0.8  # drift the orbit centre towards the room centre
    else:
        origins = np.clip(origins, box.lo, box.hi)
    targets = np.repeat(centre[None], n, axis=0)
    return CameraPath("orbit", origins, _keep_target_ahead(origins, targets), float(speed))


def _pan(rng: np.random.Generator, n: int, box: CameraBox, room_size: np.ndarray) -> CameraPath:
    origin = box.sample(rng)
    rate = np.radians(rng.uniform(0.5, 3.0)) * (1.0 if rng.random() < 0.5 else -1.0)
    yaw = rng.uniform(0, 2 * np.pi) + rate * np.arange(n)
    pitch = np.radians(rng.uniform(-20.0, 5.0)) + np.radians(rng.uniform(0, 5.0)) * np.sin(
        np.linspace(0, np.pi, n) + rng.uniform(0, np.pi))
    origins = np.repeat(origin[None], n, axis=0)
    targets = origins + 2.0 * _direction(yaw, pitch)
    return CameraPath("pan", origins, targets, float(abs(rate)))


def _spline(rng: np.random.Generator, n: int, box: CameraBox, room_size: np.ndarray) -> CameraPath:
    speed = rng.uniform(0.03, 0.12)
    n_ctrl = int(rng.integers(4, 7))
    step = speed * max(n - 1, 1) / (n_ctrl - 1)
    inner = box.shrunk(0.15)  # Catmull-Rom overshoots its control polygon slightly
    ctrl = [inner.sample(rng)]
    heading = rng.uniform(0, 2 * np.pi)
    for _ in range(n_ctrl - 1):
        heading += rng.uniform(-0.8, 0.8)
        nxt = ctrl[-1] + step * _direction(heading, rng.uniform(-0.2, 0.2))
        ctrl.append(np.clip(nxt, inner.lo, inner.hi))
    ctrl_arr = np.array(ctrl)
    params = np.linspace(0.0, n_ctrl - 1, n)
    origins = np.clip(catmull_rom(ctrl_arr, params), box.lo, box.hi)
    interest = interest_box(room_size)
    target_ctrl = np.array([interest.sample(rng) for _ in range(n_ctrl)])
    # Keep the target moving gently: shrink target control points towards their mean.
    target_ctrl = target_ctrl.mean(axis=0) + 0.4 * (target_ctrl - target_ctrl.mean(axis=0))
    targets = catmull_rom(target_ctrl, params)
    return CameraPath("spline", origins, _keep_target_ahead(origins, targets), float(speed))


def lift_low_views(origins: np.ndarray, targets: np.ndarray, min_pitch_deg: float) -> np.ndarray:
    """Targets (n, 3) whose view direction is raised to ``min_pitch_deg`` (negative: below the horizon)
    where it points lower, keeping yaw and target distance; used in open scenes so that the sky shows."""
    view = targets - origins
    dist = np.linalg.norm(view, axis=1, keepdims=True)
    view = view / np.maximum(dist, 1e-9)
    min_sin = np.sin(np.radians(min_pitch_deg))
    low = view[:, 1] < min_sin
    horizontal = np.linalg.norm(view[:, [0, 2]], axis=1, keepdims=True)
    flat = np.where(horizontal > 1e-6, view[:, [0, 2]] / np.maximum(horizontal, 1e-9), np.array([[1.0, 0.0]]))
    cos_lim = np.sqrt(1.0 - min_sin**2)
    lifted = np.column_stack([flat[:, 0] * cos_lim, np.full(len(view), min_sin), flat[:, 1] * cos_lim])
    return np.where(low[:, None], origins + lifted * dist, targets)


_PATH_BUILDERS = {"dolly": _dolly, "orbit": _orbit, "pan": _pan, "spline": _spline}


def draw_camera_path(rng: np.random.Generator, kind: str, n_frames: int, room_size: np.ndarray) -> CameraPath:
    """Draw a path of `kind` (one of CAMERA_PATH_TYPES) with `n_frames` frames inside the room."""
    if kind not in _PATH_BUILDERS:
        raise ValueError(f"unknown camera path {kind!r}; expected one of {CAMERA_PATH_TYPES}")
    return _PATH_BUILDERS[kind](rng, n_frames, camera_box(room_size), room_size)


def clearance_segments(origins: np.ndarray, cut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segments (S, 3) start / end joining consecutive camera positions, skipping the jump at a cut;
    every camera position is also included as a degenerate segment."""
    if len(origins) == 1:
        return origins.copy(), origins.copy()
    keep = ~np.asarray(cut[1:], dtype=bool)
    starts, ends = origins[:-1][keep], origins[1:][keep]
    return np.vstack([starts, origins]), np.vstack([ends, origins])


def distance_to_segments(points: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(N,) distance from each of (N, 3) points to the closest of the (S, 3) segments."""
    d = ends - starts                                   # (S, 3)
    rel = points[:, None, :] - starts[None, :, :]       # (N, S, 3)
    denom = np.maximum(np.einsum("sk,sk->s", d, d), 1e-18)
    t = np.clip(np.einsum("nsk,sk->ns", rel, d) / denom, 0.0, 1.0)
    closest = starts[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)


# ---------------------------------------------------------------------------------------------
# Pinhole model (numpy mirror of Mitsuba's perspective sensor)
# ---------------------------------------------------------------------------------------------

def look_at_matrix(origin: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world matrix following Mitsuba's `Transform4f.look_at` (+z forward, x left)."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    left /= np.linalg.norm(left)
    new_up = np.cross(forward, left)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = left, new_up, forward, origin
    return out


def camera_to_pixel_matrix(fov_x_deg: float, width: int, height: int) -> np.ndarray:
    """(3, 3) K with [u w, v w, w] = K @ (x, y, z)_camera, w = z; (u, v) pixel coords, x right, y down."""
    tan_x = np.tan(np.radians(fov_x_deg) / 2)
    tan_y = tan_x * height / width
    return np.array([[-width / (2 * tan_x), 0.0, width / 2],
                     [0.0, -height / (2 * tan_y), height / 2],
                     [0.0, 0.0, 1.0]])
