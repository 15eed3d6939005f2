"""Screen-space motion vectors and their validity mask, from pixel-centre G-buffers.

For pixel centre c = (i + 0.5, j + 0.5) of frame t with primary-hit world position p on shape k,
the previous position is p' = M_k(t-1) M_k(t)^-1 p (rigid shape transforms), projected with the
camera of frame t-1 to q; the motion vector is q - c, so ``prev_pixel = centre + motion``.

A vector is valid (Isik et al. 2021, Sec. 4.1: "test whether the normal and world position in the
current and previous frame agree after warping") when q lands on screen and in front of the
previous camera, and at each of the four previous-frame pixels a bilinear lookup at q reads, the
G-buffer shows the same shape, a normal within ``NORMAL_COS_MIN`` of the warped normal and a
position on the warped point's tangent plane (distance along the normal below
``PLANE_TOLERANCE`` times the depth). Newly visible
(disoccluded) surfaces fail one of these tests. Frame 0 and the frame after a camera cut have no
valid history.
"""
from __future__ import annotations

import numpy as np

NORMAL_COS_MIN = 0.9
PLANE_TOLERANCE = 0.02  # relative to depth; a 128 px frame at 60 deg fov has ~0.008*depth pixels


def _apply(matrices: np.ndarray, points: np.ndarray, *, w: float) -> np.ndarray:
    """Apply per-point 4x4 matrices (N,4,4) to (N,3) points (w=1) or directions (w=0)."""
    homogeneous = np.concatenate([points, np.full((points.shape[0], 1), w)], axis=1)
    return np.einsum("nij,nj->ni", matrices, homogeneous)[:, :3]


def motion_vectors(gbuffer: dict[str, np.ndarray], gbuffer_prev: dict[str, np.ndarray] | None,
                   manifest: dict, frame: int, width: int, height: int, *,
                   camera_cut: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Motion vectors (2, H, W) in pixels and validity mask (1, H, W) bool for ``frame``.

    ``gbuffer`` / ``gbuffer_prev``: {"position": (3,H,W), "normal": (3,H,W), "depth": (1,H,W),
    "object": (1,H,W)} of frames ``frame`` and ``frame - 1`` (``None`` for frame 0).
    """
    from scenegen.mitsuba_scene import object_to_world, project_to_pixels

    motion = np.zeros((2, height, width), np.float32)
    valid = np.zeros((1, height, width), bool)
    if gbuffer_prev is None or frame == 0:
        return motion, valid

    position = gbuffer["position"].reshape(3, -1).T.astype(np.float64)
    normal = gbuffer["normal"].reshape(3, -1).T.astype(np.float64)
    shape_index = np.rint(gbuffer["object"].reshape(-1)).astype(np.int64)
    hit = shape_index >= 0

    to_world_now = object_to_world(manifest, frame)
    to_world_prev = object_to_world(manifest, frame - 1)
    # Per-shape rigid motion from frame t to t-1: M(t-1) M(t)^-1.
    shape_motion = np.einsum("kij,kjl->kil", to_world_prev, np.linalg.inv(to_world_now))
    per_pixel = shape_motion[np.where(hit, shape_index, 0)]
    per_pixel[~hit] = np.eye(4)
    position_prev = _apply(per_pixel, position, w=1.0)
    normal_prev = _apply(per_pixel, normal, w=0.0)

    pixel_prev, in_front = project_to_pixels(position_prev, manifest, frame - 1, width, height)
    jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    centre = np.stack([ii.reshape(-1) + 0.5, jj.reshape(-1) + 0.5], axis=1)
    flow = pixel_prev - centre
    motion = np.where(hit[:, None] & in_front[:, None], flow, 0.0).T.reshape(2, height, width)
    motion = motion.astype(np.float32)
    if camera_cut:
        return motion, valid

    on_screen = (in_front & np.all(np.isfinite(pixel_prev), axis=1)
                 & (pixel_prev[:, 0] >= 0) & (pixel_prev[:, 0] < width)
                 & (pixel_prev[:, 1] >= 0) & (pixel_prev[:, 1] < height))
    # Test every tap the bilinear warp reads (the 2x2 pixel centres around q): a vector is only
    # valid when all of them show the warped surface, so no occluder's colour leaks in.
    ok = hit & on_screen
    base_x = np.floor(np.nan_to_num(pixel_prev[:, 0]) - 0.5).astype(np.int64)
    base_y = np.floor(np.nan_to_num(pixel_prev[:, 1]) - 0.5).astype(np.int64)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        xi = np.clip(base_x + dx, 0, width - 1)
        yi = np.clip(base_y + dy, 0, height - 1)
        prev_object = np.rint(gbuffer_prev["object"][0, yi, xi]).astype(np.int64)
        prev_position = gbuffer_prev["position"][:, yi, xi].T.astype(np.float64)
        prev_normal = gbuffer_prev["normal"][:, yi, xi].T.astype(np.float64)
        prev_depth = gbuffer_prev["depth"][0, yi, xi].astype(np.float64)
        same_shape = prev_object == shape_index
        normal_agrees = np.sum(prev_normal * normal_prev, axis=1) >= NORMAL_COS_MIN
        plane_distance = np.abs(np.sum((prev_position - position_prev) * normal_prev, axis=1))
        on_plane = plane_distance <= PLANE_TOLERANCE * np.maximum(prev_depth, 1e-6)
        ok &= same_shape & normal_agrees & on_plane
    valid = ok.reshape(1, height, width)
    return motion, valid


def warp_previous(previous: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Bilinearly sample ``previous`` (C, H, W) at ``centre + motion`` (motion (2, H, W), pixels).

    Out-of-range lookups clamp to the border; combine with the validity mask.
    """
    channels, height, width = previous.shape
    jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    # Continuous coordinates relative to pixel centres of the previous frame.
    x = np.clip(ii + motion[0], 0, width - 1)
    y = np.clip(jj + motion[1], 0, height - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    fx = (x - x0)[None]
    fy = (y - y0)[None]
    top = previous[:, y0, x0] * (1 - fx) + previous[:, y0, x1] * fx
    bottom = previous[:, y1, x0] * (1 - fx) + previous[:, y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(previous.dtype)
