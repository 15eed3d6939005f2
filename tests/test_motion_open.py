"""Motion vectors on open scenes and fine geometry: environment pixels reproject by direction, a detailed
mesh keeps its history, occluders still invalidate it, and SVGF accumulates the environment's history.

Every scene is built by hand (no scene generator); references are analytic camera moves, Mitsuba ray
casts from the previous camera and Mitsuba renders of the previous frame.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.ndimage import binary_dilation, binary_erosion

from scenegen import geometry as geo
from scenegen.exr import write_exr
from scenegen.motion import motion_vectors, pixel_ray_directions, warp_previous
from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_gbuffer, render_reference_frame

WIDTH, HEIGHT = 64, 48
SETTINGS = RenderSettings(width=WIDTH, height=HEIGHT, max_depth=3, rr_depth=3)
FOV_X = 40.0


def _material(rgb: list[float]) -> dict:
    return {"name": "m", "type": "diffuse", "albedo": rgb, "roughness": 1.0, "metallic": False,
            "transmissive": False, "params": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}}


def _manifest(shapes: list[dict], frames: list[dict], emitter: dict) -> dict:
    """A hand-built manifest: ``shapes`` [{mesh, to_world[, to_world_per_frame]}] (diffuse grey), one emitter."""
    records = [{"index": i, "name": f"shape_{i}", "kind": "object", "material": 0, "emitter": None,
                "to_world_per_frame": None, **shape} for i, shape in enumerate(shapes)]
    return {"shapes": records, "materials": [_material([0.5, 0.5, 0.5])], "emitters": [emitter],
            "camera": {"fov_x_deg": FOV_X, "frames": frames}, "n_frames": len(frames)}


def _camera(origin, target) -> dict:
    return {"origin": [float(v) for v in origin], "target": [float(v) for v in target], "up": [0.0, 1.0, 0.0]}


def _write(mesh: geo.ObjectMesh, scene_dir: Path, name: str) -> str:
    geo.export_ply(mesh, scene_dir / "meshes" / f"{name}.ply")
    return f"meshes/{name}.ply"


def _sphere(scene_dir: Path, radius: float = 0.5) -> str:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return _write(geo.ObjectMesh("ball", np.asarray(sphere.vertices), np.asarray(sphere.faces), True), scene_dir, "ball")


def _bumpy_sphere_mesh() -> geo.ObjectMesh:
    """A finely tessellated sphere (81920 faces, radius 0.8 m) with 1 cm bumps every ~10 cm: smooth at the
    pixel scale in position, but its normals turn by up to ~30 degrees from one pixel to the next."""
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    unit = np.asarray(sphere.vertices)
    k = 2 * np.pi / 0.1
    bumps = np.sin(k * 0.8 * unit[:, 0]) * np.sin(k * 0.8 * unit[:, 1] + 1.0) * np.sin(k * 0.8 * unit[:, 2] + 2.0)
    vertices = unit * (0.8 + 0.01 * bumps)[:, None]
    return geo.ObjectMesh("bumpy", vertices, np.asarray(sphere.faces), True)


def _bumpy_sphere(scene_dir: Path) -> str:
    return _write(_bumpy_sphere_mesh(), scene_dir, "bumpy")


PLATE_AT = np.array([0.15, 0.1, 1.2])


def _plate_mesh() -> geo.ObjectMesh:
    plate = trimesh.creation.box(extents=(0.5, 0.8, 0.02))
    return geo.ObjectMesh("plate", np.asarray(plate.vertices), np.asarray(plate.faces), False)


def _bumpy_sphere_and_plate(scene_dir: Path) -> str:
    """The bumpy sphere and the plate at PLATE_AT in one mesh: an occluder of the same shape."""
    sphere, plate = _bumpy_sphere_mesh(), _plate_mesh()
    vertices = np.vstack([sphere.vertices, plate.vertices + PLATE_AT])
    faces = np.vstack([sphere.faces, plate.faces + len(sphere.vertices)])
    return _write(geo.ObjectMesh("bumpy_plate", vertices, faces, True), scene_dir, "bumpy_plate")


def _checker_sky(scene_dir: Path) -> dict:
    """An envmap emitter: a latitude-longitude checkerboard of 10-degree cells (two colours)."""
    height, width = 90, 180
    rows, cols = np.meshgrid(np.arange(height) // 5, np.arange(width) // 5, indexing="ij")
    light = ((rows + cols) % 2 == 0)[..., None]
    image = np.where(light, [1.0, 0.9, 0.7], [0.1, 0.2, 0.4]).astype(np.float32)
    write_exr(scene_dir / "sky.exr", {c: image[..., k] for k, c in enumerate("RGB")})
    return {"name": "sky", "type": "envmap", "filename": "sky.exr", "scale": 1.0}


def _translate(x: float, y: float, z: float) -> list[list[float]]:
    return geo.make_transform(np.eye(3), np.array([x, y, z])).tolist()


def _first_hit_distance(manifest: dict, scene_dir: Path, frame: int, origin: np.ndarray,
                        directions: np.ndarray) -> np.ndarray:
    """(N,) distance along (N, 3) unit rays from ``origin`` to the first surface of ``frame``'s scene (inf: none)."""
    import mitsuba as mi

    scene = load_frame_scene(manifest, scene_dir, frame, SETTINGS)
    n = len(directions)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(n, v, np.float32)) for v in origin]),
                   mi.Vector3f(*[mi.Float(directions[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    return np.where(np.asarray(si.is_valid()), np.asarray(si.t, np.float64), np.inf)


def _visible_from_previous(manifest: dict, scene_dir: Path, gbuffer: dict, frame: int) -> np.ndarray:
    """(H, W) bool: the pixel's primary-hit point is unoccluded from camera ``frame - 1`` (environment
    pixels: their ray direction is unblocked from the previous camera position)."""
    origin = np.asarray(manifest["camera"]["frames"][frame - 1]["origin"], np.float64)
    points = gbuffer["position"].reshape(3, -1).T.astype(np.float64)
    hit = gbuffer["object"].reshape(-1) >= 0
    distance = np.linalg.norm(points - origin, axis=1)
    directions = np.where(hit[:, None], (points - origin) / np.maximum(distance, 1e-9)[:, None],
                          pixel_ray_directions(manifest, frame, WIDTH, HEIGHT))
    first = _first_hit_distance(manifest, scene_dir, frame - 1, origin, directions)
    visible = np.where(hit, np.abs(first - distance) < 1e-3 * distance + 1e-3, np.isinf(first))
    return visible.reshape(HEIGHT, WIDTH)


def _motion(manifest: dict, scene_dir: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    gbuf0 = render_gbuffer(manifest, scene_dir, 0, SETTINGS)
    gbuf1 = render_gbuffer(manifest, scene_dir, 1, SETTINGS)
    motion, valid = motion_vectors(gbuf1, gbuf0, manifest, 1, WIDTH, HEIGHT)
    return motion, valid[0], gbuf1


def _on_screen(motion: np.ndarray, margin: float = 0.0) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5, indexing="xy")
    x, y = xs + motion[0], ys + motion[1]
    return (x >= margin) & (x < WIDTH - margin) & (y >= margin) & (y < HEIGHT - margin)


# -------------------------------------------------------------------------------------------------
# Environment pixels
# -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sky_scene(tmp_path_factory) -> tuple[Path, list[dict], dict]:
    """A 0.5 m ball under the checker sky, a level camera 3 m away: (scene dir, shapes, emitter)."""
    scene_dir = tmp_path_factory.mktemp("sky")
    return scene_dir, [{"mesh": _sphere(scene_dir), "to_world": _translate(0.4, 0.0, 0.0)}], _checker_sky(scene_dir)


def test_environment_motion_under_pure_rotation_is_analytic(sky_scene) -> None:
    """The camera turns 4 degrees to the right about +y: an environment pixel at angle g right of the axis
    came from angle g + 4 degrees, i.e. x' = W/2 + f tan(g + a), y' - H/2 = (y - H/2) / (cos a - tan g sin a)."""
    scene_dir, shapes, sky = sky_scene
    angle = np.radians(4.0)
    origin = np.array([0.0, 0.0, 3.0])
    frames = [_camera(origin, origin + [0.0, 0.0, -1.0]),
              _camera(origin, origin + [np.sin(angle), 0.0, -np.cos(angle)])]
    manifest = _manifest(shapes, frames, sky)
    motion, valid, gbuf1 = _motion(manifest, scene_dir)
    environment = gbuf1["object"][0] < 0
    assert 0.3 < environment.mean() < 0.95

    f = WIDTH / (2 * np.tan(np.radians(FOV_X) / 2))
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5, indexing="xy")
    gamma = np.arctan((xs - WIDTH / 2) / f)
    expected_x = WIDTH / 2 + f * np.tan(gamma + angle) - xs
    expected_y = (ys - HEIGHT / 2) * (1 / (np.cos(angle) - np.tan(gamma) * np.sin(angle)) - 1)
    np.testing.assert_allclose(motion[0][environment], expected_x[environment], atol=2e-3)
    np.testing.assert_allclose(motion[1][environment], expected_y[environment], atol=2e-3)
    assert motion[0][environment].min() > 2.5   # f tan(4 deg) = 6.1 px at the centre

    # No parallax: every environment pixel 2 px away from the ball whose lookup stays inside the image is valid.
    clear = environment & ~binary_dilation(~environment, iterations=2) & _on_screen(motion, margin=0.5)
    assert clear.sum() > 500 and valid[clear].all()
    assert not valid[environment & ~_on_screen(motion)].any()


def test_environment_does_not_move_under_translation_and_disocclusions_are_invalid(sky_scene) -> None:
    """A pure camera translation leaves points at infinity where they were (motion 0); sky newly revealed
    behind the ball (its direction was blocked from the previous camera) has no history."""
    scene_dir, shapes, sky = sky_scene
    origin, step = np.array([0.0, 0.0, 3.0]), np.array([0.45, 0.1, -0.3])
    frames = [_camera(origin, origin + [0.0, 0.0, -1.0]), _camera(origin + step, origin + step + [0.0, 0.0, -1.0])]
    manifest = _manifest(shapes, frames, sky)
    motion, valid, gbuf1 = _motion(manifest, scene_dir)
    environment = gbuf1["object"][0] < 0
    np.testing.assert_allclose(motion[:, environment], 0.0, atol=1e-3)

    visible = _visible_from_previous(manifest, scene_dir, gbuf1, 1)
    revealed = environment & ~visible
    assert revealed.sum() >= 20, "the step should uncover sky behind the ball"
    assert not valid[binary_erosion(revealed)].any()
    assert valid[revealed].mean() < 0.1
    unblocked = environment & visible & ~binary_dilation(~(environment & visible), iterations=2)
    assert unblocked.sum() > 500 and valid[unblocked].all()


def test_environment_warp_reproduces_the_rendered_sky(sky_scene) -> None:
    """Rotation and translation together: warping Mitsuba's render of the previous frame with the motion
    vectors reproduces the current render on the valid environment pixels."""
    scene_dir, shapes, sky = sky_scene
    origin = np.array([0.0, 0.0, 3.0])
    frames = [_camera(origin, origin + [0.0, 0.05, -1.0]),
              _camera(origin + [0.3, 0.05, 0.2], origin + [0.3, 0.05, 0.2] + [0.06, -0.02, -1.0])]
    manifest = _manifest(shapes, frames, sky)
    motion, valid, gbuf1 = _motion(manifest, scene_dir)
    environment = gbuf1["object"][0] < 0
    renders = []
    for frame in (0, 1):
        scene = load_frame_scene(manifest, scene_dir, frame, SETTINGS)
        renders.append(render_reference_frame(scene, spp=256, batch_spp=128, seeds_half=([3 + frame], [9 + frame]),
                                              counter=NonFiniteCounter())["radiance"])
    warped = warp_previous(renders[0], motion)
    err_warped = np.abs(warped - renders[1]).mean(axis=0)
    err_static = np.abs(renders[0] - renders[1]).mean(axis=0)
    sky_valid = environment & valid
    assert sky_valid.mean() > 0.3 and np.abs(motion[:, sky_valid]).max() > 2.0
    assert err_warped[sky_valid].mean() < 0.2 * err_static[sky_valid].mean(), (
        err_warped[sky_valid].mean(), err_static[sky_valid].mean())
    assert err_warped[sky_valid].mean() < 0.03


def test_environment_has_no_history_on_frame_zero_and_after_a_cut(sky_scene) -> None:
    scene_dir, shapes, sky = sky_scene
    origin = np.array([0.0, 0.0, 3.0])
    frames = [_camera(origin, origin + [0.0, 0.0, -1.0]), _camera(origin, origin + [0.02, 0.0, -1.0])]
    manifest = _manifest(shapes, frames, sky)
    gbuf0 = render_gbuffer(manifest, scene_dir, 0, SETTINGS)
    gbuf1 = render_gbuffer(manifest, scene_dir, 1, SETTINGS)
    assert not motion_vectors(gbuf0, None, manifest, 0, WIDTH, HEIGHT)[1].any()
    assert not motion_vectors(gbuf1, gbuf0, manifest, 1, WIDTH, HEIGHT, camera_cut=True)[1].any()
    assert motion_vectors(gbuf1, gbuf0, manifest, 1, WIDTH, HEIGHT)[1][0][gbuf1["object"][0] < 0].mean() > 0.5


# -------------------------------------------------------------------------------------------------
# Fine geometry
# -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bumpy_scene(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    scene_dir = tmp_path_factory.mktemp("bumpy")
    return scene_dir, {"bumpy": _bumpy_sphere(scene_dir), "plate": _write(_plate_mesh(), scene_dir, "plate"),
                       "bumpy_plate": _bumpy_sphere_and_plate(scene_dir)}


UNIFORM_SKY = {"name": "sky", "type": "constant", "radiance": [1.0, 1.0, 1.0]}


@pytest.mark.parametrize("move", ["orbit", "side_step"])
def test_detailed_mesh_keeps_its_history(bumpy_scene, move: str) -> None:
    """Small camera moves around a bumpy, finely tessellated sphere: every interior sphere pixel stays
    visible from the previous camera (ray cast), and at least 90 % of them keep their history (the
    nearest-normal test of the earlier version kept about 75 %)."""
    scene_dir, meshes = bumpy_scene
    origin = np.array([0.0, 0.3, 3.2])
    if move == "orbit":
        a = np.radians(1.0)
        second = _camera([3.2 * np.sin(a), 0.3, 3.2 * np.cos(a)], [0.0, 0.0, 0.0])
    else:
        second = _camera(origin + [0.05, 0.0, 0.0], [0.05, 0.0, 0.0])
    manifest = _manifest([{"mesh": meshes["bumpy"], "to_world": np.eye(4).tolist()}], [_camera(origin, [0, 0, 0]), second],
                         UNIFORM_SKY)
    motion, valid, gbuf1 = _motion(manifest, scene_dir)
    sphere = gbuf1["object"][0] == 0
    interior = binary_erosion(sphere, iterations=2) & _on_screen(motion, margin=1.0)
    visible = _visible_from_previous(manifest, scene_dir, gbuf1, 1)
    assert interior.sum() > 800 and np.abs(motion[:, interior]).max() > 0.5
    assert visible[interior].mean() > 0.99
    assert valid[interior & visible].mean() > 0.9, valid[interior & visible].mean()


@pytest.mark.parametrize("mover, occluder", [("camera", "own shape"), ("camera", "same shape"),
                                             ("occluder", "own shape")])
def test_occluder_in_front_of_a_detailed_mesh_still_invalidates(bumpy_scene, mover: str, occluder: str) -> None:
    """A thin plate 1.2 m in front of the bumpy sphere: sphere pixels the plate hid in the previous frame
    (ray cast from the previous camera) have no history, whether the camera or the plate moved, and also
    when the plate is part of the sphere's mesh (only the position test can tell them apart then)."""
    scene_dir, meshes = bumpy_scene
    origin = np.array([0.0, 0.3, 3.2])
    if occluder == "same shape":
        shapes = [{"mesh": meshes["bumpy_plate"], "to_world": np.eye(4).tolist()}]
    else:
        shapes = [{"mesh": meshes["bumpy"], "to_world": np.eye(4).tolist()},
                  {"mesh": meshes["plate"], "to_world": _translate(*PLATE_AT)}]
    if mover == "camera":
        frames = [_camera(origin, [0, 0, 0]), _camera(origin + [0.25, 0.0, 0.0], [0.25, 0.0, 0.0])]
    else:
        frames = [_camera(origin, [0, 0, 0])] * 2
        shapes[1]["to_world_per_frame"] = [_translate(*PLATE_AT), _translate(*(PLATE_AT + [-0.15, 0.0, 0.0]))]
    manifest = _manifest(shapes, frames, UNIFORM_SKY)
    motion, valid, gbuf1 = _motion(manifest, scene_dir)
    visible = _visible_from_previous(manifest, scene_dir, gbuf1, 1)
    # Sphere pixels (the plate lies at z = 1.2, the sphere within |z| < 0.81).
    position = gbuf1["position"]
    sphere = (gbuf1["object"][0] == 0) & (position[2] < PLATE_AT[2] - 0.05)
    newly_visible = sphere & ~visible & _on_screen(motion)
    assert newly_visible.sum() >= 20, newly_visible.sum()
    assert binary_erosion(newly_visible).sum() >= 5 and not valid[binary_erosion(newly_visible)].any()
    assert valid[newly_visible].mean() < 0.1
    still_visible = binary_erosion(sphere & visible, iterations=2) & _on_screen(motion, margin=1.0)
    assert valid[still_visible].mean() > 0.9


# -------------------------------------------------------------------------------------------------
# SVGF accumulates the environment's history
# -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("native", ["1", "0"])
def test_svgf_accumulates_environment_history(monkeypatch, native: str) -> None:
    """Sky in the top rows (G-buffer miss: depth 0, normal 0), a wall below, everything valid: the sky's
    history grows like the wall's; a sky pixel whose taps land on the wall, or a wall pixel whose taps land
    on the sky, restarts."""
    from denoisers import registry
    from denoisers.registry import Frame

    monkeypatch.setenv("MCDN_NATIVE", native)
    height, width, sky_rows = 16, 20, 6
    depth = torch.full((1, height, width), 2.0)
    depth[:, :sky_rows] = 0.0
    normal = torch.zeros(3, height, width)
    normal[2, sky_rows:] = 1.0
    radiance = torch.full((1, 3, height, width), 0.5)
    samples = {"radiance": radiance, "albedo": torch.ones(1, 3, height, width), "normal": normal[None].clone(),
               "depth": depth[None].clone(), "position": torch.zeros(1, 3, height, width),
               "flags": torch.zeros(1, 4, height, width)}
    svgf = registry.build("svgf")
    for index in range(4):
        motion = torch.zeros(2, height, width)
        if index == 3:
            motion[1, sky_rows - 1, :5] = 2.0      # sky pixels looking up their history on the wall
            motion[1, sky_rows + 1, 5:10] = -3.0   # wall pixels looking up their history in the sky
        pixel = {"motion": motion, "valid": torch.full((1, height, width), float(index > 0)),
                 "gbuffer.depth": depth, "gbuffer.normal": normal}
        svgf.denoise(Frame(samples=samples, pixel=pixel, index=index, camera_cut=False))
    length = svgf._history.length[0]
    assert torch.all(length[:sky_rows - 1] == 4) and torch.all(length[sky_rows + 2:] == 4)
    assert torch.all(length[sky_rows - 1, :5] == 1) and torch.all(length[sky_rows - 1, 5:] == 4)
    assert torch.all(length[sky_rows + 1, 5:10] == 1)
