"""Screen-space motion vectors and their validity mask, from pixel-centre G-buffers.

Surfaces: for pixel centre c = (i + 0.5, j + 0.5) of frame t with primary-hit world position p on
shape k, the previous position is p' = M_k(t-1) M_k(t)^-1 p (rigid shape transforms), projected
with the camera of frame t-1 to q; the motion vector is q - c, so ``prev_pixel = centre + motion``.

Environment (G-buffer miss, ``object`` = -1): the pixel sees a point at infinity along its world
ray direction d, so q is d projected with the previous camera's rotation only (camera translation
does not move points at infinity).

A vector is valid (Isik et al. 2021, Sec. 4.1: "test whether the normal and world position in the
current and previous frame agree after warping") when q lands on screen and in front of the
previous camera and every previous-frame pixel the bilinear lookup at q reads (the 2x2 pixel
centres around q with a weight above ``MIN_TAP_WEIGHT``) shows the same thing:

* environment pixels: the tap is environment too;
* surface pixels: the tap shows the same shape, its normal is within ``NORMAL_COS_MIN`` of the
  warped normal, and the two points lie on each other's tangent planes (both distances along the
  normals at most ``PLANE_FOOTPRINTS`` pixel footprints at q's distance from the previous camera).

The plane test is symmetric and scaled by the pixel footprint, so detailed meshes whose normals
change from pixel to pixel keep their history while an occluder, which lies a gap in front of q
rather than within a footprint of its surface, still fails it; the loose normal test only separates
surfaces that the position cannot (the two sides of a thin shell, creases sharper than 60 degrees).
Newly visible (disoccluded) surfaces fail one of these tests. Frame 0 and the frame after a camera
cut have no valid history.
"""
from __future__ import annotations

import numpy as np

NORMAL_COS_MIN = 0.5
PLANE_FOOTPRINTS = 2.0
MIN_TAP_WEIGHT = 1e-3  # taps with less bilinear weight contribute < 0.1 % of the warp: not tested


def _apply(matrices: np.ndarray, points: np.ndarray, *, w: float) -> np.ndarray:
    """Apply per-point 4x4 matrices (N,4,4) to (N,3) points (w=1) or directions (w=0)."""
    homogeneous = np.concatenate([points, np.full((points.shape[0], 1), w)], axis=1)
    return np.einsum("nij,nj->ni", matrices, homogeneous)[:, :3]


def pixel_ray_directions(manifest: dict, frame: int, width: int, height: int) -> np.ndarray:
    """(H*W, 3) unit world-space directions of the camera rays through the pixel centres of ``frame``
    (row-major, x fastest)."""
    from scenegen.mitsuba_scene import camera_matrices

    camera = camera_matrices(manifest, frame, width, height)
    jj, ii = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    pixels = np.stack([ii.reshape(-1), jj.reshape(-1), np.ones(width * height)], axis=1)
    local = pixels @ np.linalg.inv(camera["intrinsics"]).T           # camera space, z = 1
    world = local @ camera["to_world"][:3, :3].T
    return world / np.linalg.norm(world, axis=1, keepdims=True)


def project_directions(directions: np.ndarray, manifest: dict, frame: int, width: int,
                        height: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixel coordinates in ``frame`` of the points at infinity along (N, 3) world directions,
    and (N,) bool: in front of that camera."""
    from scenegen.mitsuba_scene import camera_matrices

    rotation = camera_matrices(manifest, frame, width, height)["world_to_pixel"][:, :3]
    homogeneous = directions @ rotation.T
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = homogeneous[:, :2] / homogeneous[:, 2:3]
    return pixels, homogeneous[:, 2] > 0.0


def bilinear_taps(pixel_prev: np.ndarray, width: int,
                   height: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The four taps (x index (N,), y index (N,), bilinear weight (N,)) of a lookup at (N, 2) continuous
    pixel coordinates; indices are clamped to the image (out-of-image lookups are rejected elsewhere)."""
    x = np.nan_to_num(pixel_prev[:, 0]) - 0.5
    y = np.nan_to_num(pixel_prev[:, 1]) - 0.5
    base_x, base_y = np.floor(x), np.floor(y)
    fx, fy = x - base_x, y - base_y
    taps = []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        weight = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy)
        xi = np.clip(base_x.astype(np.int64) + dx, 0, width - 1)
        yi = np.clip(base_y.astype(np.int64) + dy, 0, height - 1)
        taps.append((xi, yi, weight))
    return taps


def reproject(points_prev: np.ndarray, hit: np.ndarray, manifest: dict, frame: int, width: int,
              height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the pixels of ``frame`` were in frame - 1: (N, 2) previous pixel coordinates, motion (2, H, W) in pixels
    (0 where the target is behind the previous camera) and (N,) bool on screen and in front. ``points_prev`` (N, 3):
    each pixel's world point at frame - 1 (row-major, N = H W); pixels with ``hit`` false see the environment and
    are projected as points at infinity along their ray."""
    from scenegen.mitsuba_scene import project_to_pixels

    surface_prev, surface_in_front = project_to_pixels(points_prev, manifest, frame - 1, width, height)
    sky_prev, sky_in_front = project_directions(pixel_ray_directions(manifest, frame, width, height),
                                                manifest, frame - 1, width, height)
    pixel_prev = np.where(hit[:, None], surface_prev, sky_prev)
    in_front = np.where(hit, surface_in_front, sky_in_front)
    jj, ii = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    centre = np.stack([ii.reshape(-1) + 0.5, jj.reshape(-1) + 0.5], axis=1)
    motion = np.where(in_front[:, None], pixel_prev - centre, 0.0).T.reshape(2, height, width).astype(np.float32)
    on_screen = (in_front & np.all(np.isfinite(pixel_prev), axis=1)
                 & (pixel_prev[:, 0] >= 0) & (pixel_prev[:, 0] < width)
                 & (pixel_prev[:, 1] >= 0) & (pixel_prev[:, 1] < height))
    return pixel_prev, motion, on_screen


def motion_vectors(gbuffer: dict[str, np.ndarray], gbuffer_prev: dict[str, np.ndarray] | None,
                   manifest: dict, frame: int, width: int, height: int, *,
                   camera_cut: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Motion vectors (2, H, W) in pixels and validity mask (1, H, W) bool for ``frame``.

    ``gbuffer`` / ``gbuffer_prev``: {"position": (3,H,W), "normal": (3,H,W), "depth": (1,H,W),
    "object": (1,H,W)} of frames ``frame`` and ``frame - 1`` (``None`` for frame 0).
    """
    from scenegen.mitsuba_scene import camera_matrices, object_to_world

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
    per_pixel = np.tile(np.eye(4), (len(shape_index), 1, 1))
    per_pixel[hit] = shape_motion[shape_index[hit]]
    position_prev = _apply(per_pixel, position, w=1.0)
    normal_prev = _apply(per_pixel, normal, w=0.0)

    pixel_prev, motion, on_screen = reproject(position_prev, hit, manifest, frame, width, height)
    if camera_cut:
        return motion, valid

    camera_prev = camera_matrices(manifest, frame - 1, width, height)
    # Pixel footprint (metres) at q's distance from the previous camera (image-centre pixel size).
    footprint = (np.linalg.norm(position_prev - camera_prev["origin"], axis=1)
                 / abs(camera_prev["intrinsics"][0, 0]))
    tolerance = PLANE_FOOTPRINTS * footprint
    # Test every tap the bilinear warp reads: a vector is only valid when all of them show the warped
    # surface (or the environment), so no occluder's colour leaks in.
    ok = on_screen.copy()
    for xi, yi, weight in bilinear_taps(pixel_prev, width, height):
        prev_object = np.rint(gbuffer_prev["object"][0, yi, xi]).astype(np.int64)
        prev_position = gbuffer_prev["position"][:, yi, xi].T.astype(np.float64)
        prev_normal = gbuffer_prev["normal"][:, yi, xi].T.astype(np.float64)
        offset = prev_position - position_prev
        on_planes = ((np.abs(np.sum(offset * normal_prev, axis=1)) <= tolerance)
                     & (np.abs(np.sum(offset * prev_normal, axis=1)) <= tolerance))
        normal_agrees = np.sum(prev_normal * normal_prev, axis=1) >= NORMAL_COS_MIN
        same_surface = (prev_object == shape_index) & normal_agrees & on_planes
        both_environment = ~hit & (prev_object < 0)
        ok &= np.where(hit, same_surface, both_environment) | (weight <= MIN_TAP_WEIGHT)
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
