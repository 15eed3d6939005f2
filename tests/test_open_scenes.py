"""Open scenes of the procedural generator: which scenes are open, their shell, the sky environment map
(Mitsuba's envmap convention and its irradiance), and that the sky is seen and lights the scene."""
from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from scenegen.mitsuba_env import init_mitsuba

init_mitsuba()

import mitsuba as mi  # noqa: E402

from scenegen import lights  # noqa: E402
from scenegen.camera import lift_low_views  # noqa: E402
from scenegen.catalog import scene_ids
from scenegen.config import load_config  # noqa: E402
from scenegen.exr import read_exr, write_exr  # noqa: E402
from scenegen.generate import generate_scene, open_scene  # noqa: E402
from scenegen.mitsuba_scene import build_scene_dict, preview_mean_luminance  # noqa: E402
from scenegen.render import RenderSettings, render_gbuffer  # noqa: E402

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
OPEN_CFG = {"objects": [4, 6], "open_scene_prob": 1.0, "moving_objects_prob": 1.0, "animated_light_prob": 1.0,
            "camera_cut_prob": 0.0}
N_FRAMES = 4
SEEDS = (40, 42, 45, 49)   # two of each open kind (checked below)


@pytest.fixture(scope="module")
def open_scenes(tmp_path_factory) -> list[tuple[dict, pathlib.Path]]:
    root = tmp_path_factory.mktemp("open")
    return [(generate_scene(OPEN_CFG, seed, f"train_{seed:03d}", root / str(seed), n_frames=N_FRAMES),
             root / str(seed)) for seed in SEEDS]


def test_open_scene_rule_is_an_exact_evenly_spread_fraction() -> None:
    rng = np.random.default_rng(0)
    for prob in (0.0, 0.1, 0.25, 1 / 3, 0.5, 1.0):
        flags = [open_scene(f"train_{k:03d}", prob, rng) for k in range(60)]
        for n in (1, 7, 20, 60):
            assert sum(flags[:n]) == int(np.ceil(n * prob - 1e-9)), (prob, n)
        if prob > 0:
            assert flags[0]
    assert [k for k in range(12) if open_scene(f"test_{k:03d}", 0.25, rng)] == [0, 4, 8]
    # Ids without an index draw: about a fraction p of them.
    drawn = [open_scene("custom", 0.3, np.random.default_rng(seed)) for seed in range(400)]
    assert 0.2 < np.mean(drawn) < 0.4


@pytest.mark.parametrize("config", ["config.yaml", "smoke.yaml"])
def test_shipped_configs_have_an_open_test_scene(config: str) -> None:
    cfg = load_config(REPO_ROOT / "config" / config)
    tests = [s for s in scene_ids(cfg) if s.startswith("test_")]
    assert any(open_scene(s, cfg["scenes"]["open_scene_prob"], np.random.default_rng(0)) for s in tests)


def test_lift_low_views_keeps_yaw_distance_and_higher_views() -> None:
    origins = np.zeros((3, 3))
    targets = np.array([[2.0, -2.0 * np.sqrt(3.0), 0.0],   # 60 degrees down, 4 m away
                        [0.0, -0.1, -3.0],                   # slightly down: kept
                        [0.0, 1.0, 1.0]])                    # up: kept
    lifted = lift_low_views(origins, targets, -20.0)
    np.testing.assert_allclose(lifted[0], 4.0 * np.array([np.cos(np.radians(20)), -np.sin(np.radians(20)), 0.0]))
    assert np.array_equal(lifted[1:], targets[1:])


def test_open_scene_shell_sky_and_files(open_scenes) -> None:
    kinds = set()
    for manifest, scene_dir in open_scenes:
        kind = manifest["room"]["open"]
        kinds.add(kind)
        room = [s["name"] for s in manifest["shapes"] if s["kind"] == "room"]
        if kind == "ground":
            assert room == ["floor"]
            assert not any(s["kind"] == "light" for s in manifest["shapes"])
        else:
            walls = {"wall_x_neg", "wall_x_pos", "wall_z_neg", "wall_z_pos"}
            assert manifest["room"]["missing_wall"] in walls
            assert set(room) == {"floor", "ceiling"} | walls - {manifest["room"]["missing_wall"]}
        sky = [e for e in manifest["emitters"] if e["type"] == "envmap"]
        assert len(sky) == 1 and sky[0]["scale"] > 0
        assert not any(e["type"] == "constant" for e in manifest["emitters"])
        image = np.stack([read_exr(scene_dir / sky[0]["filename"])[0][c] for c in "RGB"], axis=-1)
        assert image.shape == (*lights.SKY_MAP_SIZE, 3) and np.all(image > 0)
        # Moving shapes index objects or light panels, whatever the number of room surfaces.
        for index in manifest["animation"]["moving_shapes"]:
            assert manifest["shapes"][index]["kind"] in ("object", "light")
            assert manifest["shapes"][index]["to_world_per_frame"] is not None
        # The floor is large enough that the camera sees the horizon over it.
        floor = next(s for s in manifest["shapes"] if s["name"] == "floor")
        assert floor["bounding_radius"] > 50.0
    assert kinds == {"ground", "opening"}


def test_open_scene_is_byte_identical_for_the_same_seed(tmp_path) -> None:
    for tag in ("a", "b"):
        generate_scene(OPEN_CFG, 45, "test_000", tmp_path / tag, n_frames=2)
    files = {p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()}
    assert pathlib.Path("textures/sky.exr") in files
    assert files == {p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file()}
    for rel in files:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel


def test_sky_map_follows_mitsuba_envmap_convention_and_has_unit_irradiance(tmp_path) -> None:
    """Mitsuba renders of the sky alone: the radiance seen along a direction is the map's value there
    (lights.latlong_directions), and a white Lambertian floor under it has radiance scale / pi
    (irradiance = scale, the normalisation of lights.draw_sky)."""
    image, params = lights.draw_sky(np.random.default_rng(5))
    write_exr(tmp_path / "sky.exr", {c: image[..., k] for k, c in enumerate("RGB")})
    sky = {"type": "envmap", "filename": str(tmp_path / "sky.exr"), "scale": 2.0}
    directions, _ = lights.latlong_directions(*image.shape[:2])
    rows, cols = [20, 50, 60, 100], [10, 70, 130, 200]
    for row, col in zip(rows, cols):
        d = directions[row, col]
        up = [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0]
        scene = mi.load_dict({"type": "scene", "sky": sky, "integrator": {"type": "path", "max_depth": 1},
                              "sensor": {"type": "perspective", "fov": 0.2,
                                         "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=d.tolist(),
                                                                                    up=up),
                                         "film": {"type": "hdrfilm", "width": 1, "height": 1,
                                                  "rfilter": {"type": "box"}}}})
        seen = np.asarray(mi.render(scene, spp=16))[0, 0, :3]
        np.testing.assert_allclose(seen, 2.0 * image[row, col], rtol=0.03)

    floor = {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(500.0),
             "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}
    scene = mi.load_dict({"type": "scene", "sky": sky, "floor": floor,
                          "integrator": {"type": "path", "max_depth": 2},
                          "sensor": {"type": "perspective", "fov": 30,
                                     "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 0], target=[0, 0, 0],
                                                                                up=[0, 0, 1]),
                                     "film": {"type": "hdrfilm", "width": 16, "height": 16,
                                              "rfilter": {"type": "box"}}}})
    radiance = np.asarray(mi.render(scene, spp=512, seed=1))[..., :3]
    luminance = float((radiance @ lights.REC709_LUMINANCE).mean())
    assert abs(luminance - 2.0 / np.pi) < 0.02 * 2.0 / np.pi, luminance
    assert 0.3 <= params["sun_share"] <= 0.75 and params["sun_direction"][1] > 0


def test_sky_is_seen_and_lights_the_scene(open_scenes) -> None:
    """Ground scenes see sky in their first and last frames and are lit mainly by it; rooms with an
    opening see sky in one of them and are brighter with the sky than without."""
    settings = RenderSettings(width=32, height=32)
    for manifest, scene_dir in open_scenes:
        sky_pixels = [float((render_gbuffer(manifest, scene_dir, frame, settings)["object"] < 0).mean())
                      for frame in (0, N_FRAMES - 1)]
        dark = json.loads(json.dumps(manifest))
        dark["emitters"] = [e for e in manifest["emitters"] if e["type"] != "envmap"]
        with_sky = preview_mean_luminance(manifest, scene_dir, frame=1)
        without_sky = preview_mean_luminance(dark, scene_dir, frame=1)
        if manifest["room"]["open"] == "ground":
            assert min(sky_pixels) > 0.02, sky_pixels
            assert without_sky < 0.75 * with_sky, (without_sky, with_sky)
        else:
            assert max(sky_pixels) > 0.02, sky_pixels
            assert without_sky < 0.95 * with_sky, (without_sky, with_sky)


def test_open_scene_loads_in_mitsuba_with_every_shape(open_scenes) -> None:
    manifest, scene_dir = open_scenes[0]
    scene = mi.load_dict(build_scene_dict(manifest, scene_dir, 0, width=16, height=16), optimize=False)
    assert len(scene.shapes()) == len(manifest["shapes"])
    assert scene.environment() is not None
