"""Per-pixel reprojection data of a volumetric clip, from its per-sample first real collisions.

A ray through a medium has no single hit point, so the pixel-centre G-buffer of surfaces does not exist.
Iglesias-Guitian et al. 2022 (Sec. 6, "Optical flow estimation") compute the image velocity from "the
closest world coordinate from the view position of the first real collision according to delta
tracking": per pixel, of the frame's samples that collided (a medium event or a surface; the integrator's
``depth`` > 0), the one nearest the camera. :func:`closest_collision_gbuffer` builds that per-pixel
G-buffer (stored under the surface G-buffer's names, see docs/data-format.md):

* ``position`` (3, H, W): world position of the closest first real collision (0 where no sample collided);
* ``depth`` (1, H, W): its distance along the camera ray (0 where none);
* ``normal`` (3, H, W): 0 (a medium event has none);
* ``object`` (1, H, W): -1 where no sample collided (environment), 0 where the closest collision is on a
  surface, 1 where it is a medium event.

Motion (:func:`volume_motion_vectors`): the medium, room and ground never move (only the camera, a light or
the transfer function is animated), so the previous position of a collision is the point itself, projected
with the previous camera; pixels without a collision see the environment, projected as points at
infinity. When the camera did not move, every vector is 0 and valid (light and transfer-function edits
change shading, not geometry: reprojection is the identity, as in the paper). Under camera motion a vector
is valid when its target is on screen and in front of the previous camera and every bilinear tap of the
lookup shows the same kind of thing: both environment, or both a collision whose position lies within
``DEPTH_TOLERANCE`` x the point's distance from the previous camera (plus two pixel footprints) of the
warped point. The closest of S stochastic collisions moves between frames inside thin media, so the
tolerance is relative; it is a heuristic, like the paper's, fixed here and not tuned on any clip.
"""
from __future__ import annotations

import numpy as np

from scenegen.motion import MIN_TAP_WEIGHT, PLANE_FOOTPRINTS, bilinear_taps, reproject

DEPTH_TOLERANCE = 0.1
#: gbuffer ``object`` codes of a volumetric clip.
OBJECT_ENVIRONMENT, OBJECT_SURFACE, OBJECT_MEDIUM = -1.0, 0.0, 1.0


def closest_collision_gbuffer(samples: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-pixel G-buffer {position (3,H,W), normal (3,H,W), depth (1,H,W), object (1,H,W), albedo (3,H,W),
    roughness (1,H,W)} from per-sample ``depth`` (S,1,H,W), ``position`` (S,3,H,W), ``medium`` (S,1,H,W) and
    ``albedo`` (S,3,H,W) of the volumetric integrator: the nearest collision's values (its albedo a medium's
    single-scattering albedo or a surface's); normal and roughness are 0, as the clips have neither."""
    depth, position, medium = samples["depth"], samples["position"], samples["medium"]
    collided = depth[:, 0] > 0.0                                             # (S, H, W)
    nearest = np.argmin(np.where(collided, depth[:, 0], np.inf), axis=0)     # (H, W)
    any_hit = collided.any(axis=0)

    def pick(array: np.ndarray) -> np.ndarray:
        chosen = np.take_along_axis(array, nearest[None, None], axis=0)[0]
        return np.where(any_hit[None], chosen, 0.0).astype(np.float32)

    is_medium = pick(medium) > 0.5
    object_code = np.where(any_hit[None], np.where(is_medium, OBJECT_MEDIUM, OBJECT_SURFACE), OBJECT_ENVIRONMENT)
    return {"position": pick(position), "normal": np.zeros_like(position[0], dtype=np.float32),
            "depth": pick(depth), "object": object_code.astype(np.float32), "albedo": pick(samples["albedo"]),
            "roughness": np.zeros_like(depth[0], dtype=np.float32)}


def camera_moved(manifest: dict, frame: int) -> bool:
    """Whether the camera of ``frame`` differs from that of ``frame - 1`` (position, orientation or fov)."""
    now, prev = manifest["camera"]["frames"][frame], manifest["camera"]["frames"][frame - 1]
    return any(not np.allclose(np.asarray(now[key], dtype=np.float64), np.asarray(prev[key], dtype=np.float64),
                               rtol=0.0, atol=1e-9) for key in ("origin", "target", "up", "fov_x_deg"))


def volume_motion_vectors(gbuffer: dict[str, np.ndarray], gbuffer_prev: dict[str, np.ndarray] | None,
                          manifest: dict, frame: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Motion vectors (2, H, W) in pixels (previous position = pixel centre + motion) and validity (1, H, W) bool
    of ``frame`` of a volumetric clip, from the closest-collision G-buffers of ``frame`` and ``frame - 1``."""
    from scenegen.mitsuba_scene import camera_matrices

    motion = np.zeros((2, height, width), np.float32)
    if gbuffer_prev is None or frame == 0:
        return motion, np.zeros((1, height, width), bool)
    if not camera_moved(manifest, frame):
        return motion, np.ones((1, height, width), bool)

    # The scene is static: a collision's previous position is the point itself.
    position = gbuffer["position"].reshape(3, -1).T.astype(np.float64)
    hit = gbuffer["object"].reshape(-1) > OBJECT_ENVIRONMENT
    pixel_prev, motion, ok = reproject(position, hit, manifest, frame, width, height)
    camera_prev = camera_matrices(manifest, frame - 1, width, height)
    distance = np.linalg.norm(position - camera_prev["origin"], axis=1)
    tolerance = DEPTH_TOLERANCE * distance + PLANE_FOOTPRINTS * distance / abs(camera_prev["intrinsics"][0, 0])
    prev_hit_map = gbuffer_prev["object"][0] > OBJECT_ENVIRONMENT
    for xi, yi, weight in bilinear_taps(pixel_prev, width, height):
        prev_hit = prev_hit_map[yi, xi]
        prev_position = gbuffer_prev["position"][:, yi, xi].T.astype(np.float64)
        near = np.linalg.norm(prev_position - position, axis=1) <= tolerance
        agrees = np.where(hit, prev_hit & near, ~prev_hit)
        ok &= agrees | (weight <= MIN_TAP_WEIGHT)
    return motion, ok.reshape(1, height, width)
