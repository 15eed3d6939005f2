"""Tests of the procedural scene generator and its Mitsuba scene-dict builder (fast: small scenes, few frames)."""
from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
import trimesh

from scenegen.mitsuba_env import init_mitsuba

init_mitsuba()

import mitsuba as mi  # noqa: E402

from scenegen.camera import CAMERA_CLEARANCE_M, look_at_matrix  # noqa: E402
from scenegen.generate import MAX_ATTEMPTS, generate_scene  # noqa: E402
from scenegen.materials import MATERIAL_MIX  # noqa: E402
from scenegen.mitsuba_scene import (build_scene_dict, camera_matrices, object_to_world,  # noqa: E402
                                    project_to_pixels)

N_FRAMES = 4
# Closed rooms (open_scene_prob 0): these tests check the room shell; open scenes: tests/test_open_scenes.py.
SMALL_CFG = {"objects": [5, 8], "moving_objects_prob": 1.0, "animated_light_prob": 1.0, "camera_cut_prob": 0.5,
             "open_scene_prob": 0.0}
# A handful of seeds whose union of object materials covers every type of MATERIAL_MIX.
MIX_SEEDS = (11, 12, 13, 14)
MIX_CFG = {"objects": [12, 16], "open_scene_prob": 0.0}


def _files(root: pathlib.Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def mix_scenes(tmp_path_factory) -> list[tuple[dict, pathlib.Path]]:
    root = tmp_path_factory.mktemp("mix")
    return [(generate_scene(MIX_CFG, seed, f"mix_{seed}", root / str(seed), n_frames=N_FRAMES), root / str(seed))
            for seed in MIX_SEEDS]


@pytest.fixture(scope="module")
def animated_scenes(tmp_path_factory) -> list[tuple[dict, pathlib.Path]]:
    root = tmp_path_factory.mktemp("animated")
    return [(generate_scene(SMALL_CFG, seed, f"anim_{seed}", root / str(seed), n_frames=N_FRAMES), root / str(seed))
            for seed in range(100, 106)]


def test_same_seed_gives_identical_files_and_other_seed_differs(tmp_path):
    first = generate_scene(SMALL_CFG, 7, "train_000", tmp_path / "a", n_frames=3)
    second = generate_scene(SMALL_CFG, 7, "train_000", tmp_path / "b", n_frames=3)
    other = generate_scene(SMALL_CFG, 8, "train_000", tmp_path / "c", n_frames=3)
    files_a, files_b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert files_a.keys() == files_b.keys()
    assert any(name.startswith("meshes/") for name in files_a)
    for name in files_a:
        assert files_a[name] == files_b[name], name
    assert first == second
    assert json.loads(files_a["manifest.json"]) == first
    assert (tmp_path / "c" / "manifest.json").read_bytes() != files_a["manifest.json"]
    assert other["seed"] == 8 and other["draw_seed"] == 8


def test_manifest_structure(animated_scenes):
    for manifest, scene_dir in animated_scenes:
        assert manifest["format_version"] == 1
        assert manifest["n_frames"] == N_FRAMES and len(manifest["camera"]["frames"]) == N_FRAMES
        assert [s["index"] for s in manifest["shapes"]] == list(range(len(manifest["shapes"])))
        assert [s["name"] for s in manifest["shapes"][:6]] == ["floor", "ceiling", "wall_x_neg", "wall_x_pos",
                                                               "wall_z_neg", "wall_z_pos"]
        assert any(s["kind"] == "light" and s["emitter"] for s in manifest["shapes"])
        for shape in manifest["shapes"]:
            assert (scene_dir / shape["mesh"]).is_file()
            assert 0 <= shape["material"] < len(manifest["materials"])
            assert np.asarray(shape["to_world"]).shape == (4, 4)
            if shape["to_world_per_frame"] is not None:
                assert np.asarray(shape["to_world_per_frame"]).shape == (N_FRAMES, 4, 4)
                assert shape["index"] in manifest["animation"]["moving_shapes"]
            if shape["emitter"] is not None:
                assert manifest["materials"][shape["material"]]["emissive"]
        for material in manifest["materials"]:
            assert len(material["albedo"]) == 3 and all(0.0 <= a <= 1.0 for a in material["albedo"])
            assert 0.0 <= material["roughness"] <= 1.0
            assert material["transmissive"] == (material["type"] == "dielectric")
            if material["type"] in ("conductor", "roughconductor"):
                assert material["metallic"]
            if material["texture"] is not None:
                assert (scene_dir / material["texture"]).is_file()
        cut_frame = manifest["animation"]["camera_cut_frame"]
        assert [f["cut"] for f in manifest["camera"]["frames"]] == [t == cut_frame for t in range(N_FRAMES)]
        animated = manifest["animation"]["animated_light"]
        names = [e["name"] for e in manifest["emitters"]] + [s["name"] for s in manifest["shapes"]]
        assert animated in names  # animated_light_prob = 1
    # moving_objects_prob = 1: at least one scene must actually have a moving object.
    assert any(any(manifest["shapes"][i]["kind"] == "object" for i in manifest["animation"]["moving_shapes"])
               for manifest, _ in animated_scenes)
    assert any(m["animation"]["camera_cut_frame"] is not None for m, _ in animated_scenes)


def test_object_count_in_range_and_material_mix_covered(mix_scenes):
    seen_types = set()
    for manifest, _ in mix_scenes:
        n_objects = sum(s["kind"] == "object" for s in manifest["shapes"])
        assert MIX_CFG["objects"][0] <= n_objects <= MIX_CFG["objects"][1]
        assert manifest["stats"]["n_objects"] == n_objects
        seen_types |= {m["type"] for m in manifest["materials"]}
    assert set(MATERIAL_MIX) <= seen_types


def test_geometry_orientation_and_room_containment(mix_scenes):
    manifest, scene_dir = mix_scenes[0]
    size = np.asarray(manifest["room"]["size"])
    centre = np.array([0.0, size[1] / 2, 0.0])
    to_world = object_to_world(manifest, 0)
    for shape in manifest["shapes"]:
        mesh = trimesh.load(scene_dir / shape["mesh"], process=False)
        world = trimesh.transform_points(mesh.vertices, to_world[shape["index"]])
        if shape["kind"] == "room":
            # Walls face the room's inside.
            tri = world[mesh.faces]
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            assert np.all(np.einsum("ij,ij->i", normals, centre - tri.mean(axis=1)) > 0)
        else:
            lo = np.array([-size[0] / 2, 0.0, -size[2] / 2]) - 1e-4
            assert np.all(world >= lo) and np.all(world <= size * [0.5, 1, 0.5] + 1e-4)
        if shape["kind"] == "object":
            welded = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
            assert welded.volume > 0  # outward winding
            assert np.allclose(0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0)), 0.0, atol=1e-5)


def test_objects_keep_clear_of_camera_path(animated_scenes, mix_scenes):
    for manifest, scene_dir in animated_scenes + mix_scenes:
        origins = np.array([f["origin"] for f in manifest["camera"]["frames"]])
        cuts = [f["cut"] for f in manifest["camera"]["frames"]]
        # Dense samples of every camera segment (not across cuts), independent of the generator's geometry code.
        samples = [origins]
        for t in range(len(origins) - 1):
            if not cuts[t + 1]:
                s = np.linspace(0.0, 1.0, 33)[:, None]
                samples.append(origins[t] + s * (origins[t + 1] - origins[t]))
        samples = np.vstack(samples)
        for shape in manifest["shapes"]:
            if shape["kind"] != "object":
                continue
            vertices = np.asarray(trimesh.load(scene_dir / shape["mesh"], process=False).vertices)
            radius = np.linalg.norm(vertices, axis=1).max()
            for frame in range(manifest["n_frames"]):
                centre = object_to_world(manifest, frame)[shape["index"]][:3, 3]
                gap = np.linalg.norm(samples - centre, axis=1).min() - radius
                assert gap > CAMERA_CLEARANCE_M - 1e-3, (manifest["scene_id"], shape["name"], frame, gap)


def test_ply_has_uvs_and_normals_in_mitsuba(mix_scenes):
    manifest, scene_dir = mix_scenes[1]
    for shape in manifest["shapes"]:
        mesh = mi.load_dict({"type": "ply", "filename": str(scene_dir / shape["mesh"])})
        assert mesh.has_vertex_texcoords() and mesh.has_vertex_normals()


@pytest.mark.slow
def test_scenes_load_and_render_in_mitsuba(mix_scenes, animated_scenes):
    scenes = []
    for manifest, scene_dir in [*mix_scenes, animated_scenes[0]]:
        frame = manifest["n_frames"] - 1
        # optimize=False: Mitsuba would otherwise merge meshes whose BSDF dicts happen to be identical.
        scene = mi.load_dict(build_scene_dict(manifest, scene_dir, frame, width=32, height=32), optimize=False)
        assert len(scene.shapes()) == len(manifest["shapes"])
        scenes.append(scene)
    # Each render costs a JIT compile: render two of the scenes loaded above.
    for scene in scenes[:2]:
        image = np.asarray(mi.render(scene, spp=4))
        assert image.shape == (32, 32, 3)
        assert np.all(np.isfinite(image))
        assert image.mean() > 1e-3


def test_look_at_matches_mitsuba():
    origin, target, up = np.array([0.3, 1.2, -0.7]), np.array([-1.0, 0.4, 2.0]), np.array([0.0, 1.0, 0.0])
    ours = look_at_matrix(origin, target, up)
    theirs = np.array(mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up).matrix)
    assert np.allclose(ours, theirs, atol=1e-6)


@pytest.mark.parametrize("width,height", [(32, 32), (48, 27)])
def test_project_to_pixels_matches_mitsuba_sensor(mix_scenes, width, height):
    manifest, scene_dir = mix_scenes[2]
    rng = np.random.default_rng(0)
    for frame in (0, manifest["n_frames"] - 1):
        sensor = mi.load_dict(build_scene_dict(manifest, scene_dir, frame, width=width, height=height)["sensor"])
        film_uv = rng.uniform(0.02, 0.98, size=(16, 2))
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(film_uv[:, 0], film_uv[:, 1]), mi.Point2f(0.5, 0.5))
        o, d = np.array(ray.o).reshape(3, -1).T, np.array(ray.d).reshape(3, -1).T
        if o.shape[0] == 1:
            o = np.repeat(o, len(d), axis=0)
        for distance in (0.3, 2.5, 9.0):
            pixels, in_front = project_to_pixels(o + distance * d, manifest, frame, width, height)
            assert np.all(in_front)
            np.testing.assert_allclose(pixels, film_uv * [width, height], atol=1e-3)
        behind = project_to_pixels(o - d, manifest, frame, width, height)[1]
        assert not np.any(behind)
    matrices = camera_matrices(manifest, 0, width, height)
    assert matrices["to_world"].shape == (4, 4) and matrices["world_to_ndc"].shape == (3, 4)


def test_luminance_redraw_is_recorded(tmp_path):
    calls = []

    def reject_first(manifest: dict, scene_dir: pathlib.Path) -> float:
        calls.append(manifest["draw_seed"])
        assert (scene_dir / "manifest.json").is_file()
        return 0.0 if len(calls) == 1 else 1.0

    manifest = generate_scene(SMALL_CFG, 21, "train_001", tmp_path / "s", n_frames=2, luminance_check=reject_first)
    assert len(calls) == 2
    assert manifest["seed"] == 21 and manifest["draw_seed"] == calls[1] != 21
    assert len(manifest["redraws"]) == 1
    redraw = manifest["redraws"][0]
    assert redraw["attempt"] == 0 and redraw["seed"] == 21 and redraw["mean_luminance"] == 0.0
    assert "dark" in redraw["reason"]
    assert manifest["stats"]["preview_mean_luminance"] == 1.0
    assert json.loads((tmp_path / "s" / "manifest.json").read_text()) == manifest
    # The files on disk belong to the accepted draw (redraws replace meshes/ and textures/).
    on_disk = {p.name for p in (tmp_path / "s" / "meshes").iterdir()}
    assert on_disk == {pathlib.Path(s["mesh"]).name for s in manifest["shapes"]}


def test_luminance_all_rejected_keeps_closest_draw(tmp_path):
    values = iter([50.0, 9.0, 30.0, 70.0, 20.0, 80.0, 60.0, 40.0])

    def too_bright(manifest: dict, scene_dir: pathlib.Path) -> float:
        return next(values)

    cfg = {**SMALL_CFG, "objects": [5, 5]}
    manifest = generate_scene(cfg, 3, "test_000", tmp_path / "s", n_frames=2, luminance_check=too_bright)
    assert len(manifest["redraws"]) == MAX_ATTEMPTS
    assert manifest["draw_seed"] == manifest["redraws"][1]["seed"]
    assert manifest["stats"]["preview_mean_luminance"] == 9.0
