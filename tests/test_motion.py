"""Motion vectors: warping the previous reference reproduces the current one; disocclusions are invalid."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from scenegen.generate import generate_scene
from scenegen.motion import motion_vectors, warp_previous
from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_gbuffer, render_reference_frame

SIZE = 64
SETTINGS = RenderSettings(width=SIZE, height=SIZE, max_depth=4, rr_depth=4)
SCENE_CFG = {
    "objects": [10, 10], "camera_paths": ["dolly"], "animated_light_prob": 0.0, "moving_objects_prob": 0.0,
    "camera_cut_prob": 0.0, "luminance_range": [0.05, 5.0], "open_scene_prob": 0.0,
}


def _diffuse_only(manifest: dict) -> dict:
    """Every material becomes a diffuse checkerboard (25 cm squares in the meshes' metre-scale UVs):
    shading is view-independent and every surface has structure to track."""
    manifest = copy.deepcopy(manifest)
    for material in manifest["materials"]:
        albedo = np.clip(np.asarray(material["albedo"], np.float64), 0.05, 0.95)
        checker = {"type": "checkerboard", "color0": {"type": "rgb", "value": list(albedo)},
                   "color1": {"type": "rgb", "value": list(0.3 * albedo)},
                   "to_uv": [[4.0, 0, 0, 0], [0, 4.0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
        material.update(type="diffuse", params={"type": "diffuse", "reflectance": checker},
                        roughness=1.0, metallic=False, transmissive=False)
    return manifest


def _reference(manifest: dict, scene_dir: Path, frame: int) -> np.ndarray:
    scene = load_frame_scene(manifest, scene_dir, frame, SETTINGS)
    ref = render_reference_frame(scene, spp=512, batch_spp=256, seeds_half=([11 + frame], [97 + frame]),
                                 counter=NonFiniteCounter())
    return ref["radiance"]


def _tonemap(x: np.ndarray) -> np.ndarray:
    return np.power(np.clip(x, 0, None) / (1 + np.clip(x, 0, None)), 1 / 2.4)


def _visible_from_previous(manifest: dict, scene_dir: Path, gbuffer: dict, frame: int) -> np.ndarray:
    """Ground truth: is each pixel's primary-hit point (static scene) unoccluded from camera ``frame - 1``?"""
    import mitsuba as mi

    scene = load_frame_scene(manifest, scene_dir, frame - 1, SETTINGS)
    origin = np.asarray(manifest["camera"]["frames"][frame - 1]["origin"], np.float64)
    points = gbuffer["position"].reshape(3, -1).T.astype(np.float64)
    to_point = points - origin
    distance = np.linalg.norm(to_point, axis=1)
    direction = to_point / np.maximum(distance, 1e-9)[:, None]
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(len(points), v, np.float32)) for v in origin]),
                   mi.Vector3f(*[mi.Float(direction[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    hit_distance = np.asarray(si.t, np.float64)
    return (np.abs(hit_distance - distance) < 1e-3 * distance + 1e-3).reshape(SIZE, SIZE)


@pytest.fixture(scope="module")
def base_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("motion") / "scene"
    manifest = generate_scene(SCENE_CFG, 4242, "motion_test", out, n_frames=2)
    return _diffuse_only(manifest), out


def test_camera_motion_warp_and_disocclusion(base_scene):
    manifest, scene_dir = base_scene
    manifest = copy.deepcopy(manifest)
    frames = manifest["camera"]["frames"]
    # A sideways step of 0.4 m makes parallax and disocclusions around every object.
    forward = np.subtract(frames[0]["target"], frames[0]["origin"])
    side = np.cross(forward, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    frames[1] = dict(frames[0], origin=list(np.add(frames[0]["origin"], 0.4 * side)),
                     target=list(np.add(frames[0]["target"], 0.4 * side)))

    gbuf0 = render_gbuffer(manifest, scene_dir, 0, SETTINGS)
    gbuf1 = render_gbuffer(manifest, scene_dir, 1, SETTINGS)
    motion, valid = motion_vectors(gbuf1, gbuf0, manifest, 1, SIZE, SIZE)
    valid = valid[0]
    assert np.abs(motion).max() > 2.0, "the step should move pixels by several pixels"

    ref0, ref1 = _reference(manifest, scene_dir, 0), _reference(manifest, scene_dir, 1)
    warped = warp_previous(ref0, motion)
    err_warped = np.abs(_tonemap(warped) - _tonemap(ref1)).mean(axis=0)
    err_static = np.abs(_tonemap(ref0) - _tonemap(ref1)).mean(axis=0)
    assert valid.mean() > 0.5
    assert err_warped[valid].mean() < 0.03, err_warped[valid].mean()
    assert err_warped[valid].mean() < 0.35 * err_static[valid].mean()

    visible = _visible_from_previous(manifest, scene_dir, gbuf1, 1)
    hit = gbuf1["object"][0] >= 0
    prev_pixel = np.stack(np.meshgrid(np.arange(SIZE), np.arange(SIZE), indexing="xy")) + 0.5 + motion
    on_screen = np.all((prev_pixel >= 0) & (prev_pixel < SIZE), axis=0)
    newly_visible = hit & on_screen & ~visible
    assert newly_visible.sum() >= 5, "the camera step should disocclude some surface"
    # Newly visible regions are flagged invalid; what was visible and on screen mostly stays valid.
    from scipy.ndimage import binary_erosion

    interior = binary_erosion(newly_visible)
    # Visibility is decided at the exact point but tested at the pixel grid, so pixels on the rim
    # of a disoccluded region can go either way; inside the region none may pass.
    assert interior.sum() >= 5 and not valid[interior].any()
    assert valid[newly_visible].mean() < 0.1
    assert valid[hit & on_screen & visible].mean() > 0.85
    assert not valid[~on_screen].any()


def test_moving_object_warp(base_scene):
    manifest, scene_dir = base_scene
    manifest = copy.deepcopy(manifest)
    manifest["camera"]["frames"][1] = dict(manifest["camera"]["frames"][0])
    gbuf0 = render_gbuffer(manifest, scene_dir, 0, SETTINGS)
    # Move the object covering most pixels 0.12 m sideways (and a little rotation about y).
    objects = {s["index"] for s in manifest["shapes"] if s["kind"] == "object"}
    ids, counts = np.unique(np.rint(gbuf0["object"]).astype(int), return_counts=True)
    on_screen = [(c, i) for i, c in zip(ids, counts) if i in objects]
    mover = max(on_screen)[1]
    shape = manifest["shapes"][mover]
    start = np.asarray(shape["to_world"], np.float64)
    angle = 0.1
    rotation = np.array([[np.cos(angle), 0, np.sin(angle), 0], [0, 1, 0, 0],
                         [-np.sin(angle), 0, np.cos(angle), 0], [0, 0, 0, 1]])
    moved = rotation @ start
    moved[:3, 3] = start[:3, 3] + np.array([0.12, 0.0, 0.05])
    shape["to_world_per_frame"] = [start.tolist(), moved.tolist()]
    manifest["animation"]["moving_shapes"] = [mover]

    gbuf1 = render_gbuffer(manifest, scene_dir, 1, SETTINGS)
    motion, valid = motion_vectors(gbuf1, gbuf0, manifest, 1, SIZE, SIZE)
    valid = valid[0]
    on_mover = np.rint(gbuf1["object"][0]).astype(int) == mover
    assert on_mover.sum() > 20
    assert np.abs(motion[:, on_mover]).max() > 1.0
    still = ~on_mover & (gbuf1["object"][0] >= 0)
    np.testing.assert_allclose(motion[:, still], 0.0, atol=1e-3)

    ref0, ref1 = _reference(manifest, scene_dir, 0), _reference(manifest, scene_dir, 1)
    warped = warp_previous(ref0, motion)
    err_warped = np.abs(_tonemap(warped) - _tonemap(ref1)).mean(axis=0)
    err_static = np.abs(_tonemap(ref0) - _tonemap(ref1)).mean(axis=0)
    mover_valid = on_mover & valid
    assert mover_valid.sum() > 10
    # Shading of the moved object changes slightly with its orientation; geometry must line up.
    assert err_warped[mover_valid].mean() < 0.05, err_warped[mover_valid].mean()
    assert err_warped[mover_valid].mean() < 0.5 * err_static[mover_valid].mean()
    # Background pixels that the object uncovered were hidden in frame 0: invalid.
    uncovered = ~on_mover & (np.rint(gbuf0["object"][0]).astype(int) == mover)
    assert uncovered.sum() > 0 and not valid[uncovered].any()


def test_first_frame_and_cut_have_no_history(base_scene):
    manifest, scene_dir = base_scene
    gbuf0 = render_gbuffer(manifest, scene_dir, 0, SETTINGS)
    motion, valid = motion_vectors(gbuf0, None, manifest, 0, SIZE, SIZE)
    assert not valid.any() and not motion.any()
    gbuf1 = render_gbuffer(manifest, scene_dir, 1, SETTINGS)
    _, valid_cut = motion_vectors(gbuf1, gbuf0, manifest, 1, SIZE, SIZE, camera_cut=True)
    assert not valid_cut.any()
