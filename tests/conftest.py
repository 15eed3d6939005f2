"""Shared fixtures: a hand-built test scene independent of the scene generator."""
from __future__ import annotations

from pathlib import Path

import pytest

from scenegen.mitsuba_env import init_mitsuba

init_mitsuba()

#: Test files that start first: with one pytest-xdist worker per core and a file per worker (scripts/run-tests.sh),
#: the suite's wall time is at least its longest file's, the shared smoke-DAG run, so it must not start last.
LONGEST_FILES = ("test_pipeline.py",)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run :data:`LONGEST_FILES` first (a stable sort: every other test keeps its order)."""
    items.sort(key=lambda item: item.path.name not in LONGEST_FILES)


def _write_mesh(mesh, path: Path) -> str:
    mesh.export(str(path))
    return str(path)


def build_test_scene_dict(tmp_dir: Path, *, width: int = 32, height: int = 32, integrator: dict | None = None,
                          materials: bool = True) -> tuple[dict, dict[str, dict]]:
    """A closed room with glass, mirror, rough metal, plastic and diffuse objects, an area light and a
    point light. Returns (scene dict with PLY shapes, {shape key: material record}) -- the material
    records are what ``scenegen.mitsuba_scene.attach_face_attributes`` needs."""
    import mitsuba as mi
    import trimesh

    tmp_dir.mkdir(parents=True, exist_ok=True)
    room = trimesh.creation.box(extents=(4.0, 3.0, 4.0))
    room.invert()  # normals face inward
    room.apply_translation((0.0, 1.5, 0.0))
    panel = trimesh.creation.box(extents=(1.0, 0.02, 1.0))
    panel.apply_translation((0.0, 2.97, 0.0))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.45)
    ball.apply_translation((-0.8, 0.45, 0.3))
    metal = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    metal.apply_translation((0.8, 0.4, -0.2))
    block = trimesh.creation.box(extents=(0.6, 0.9, 0.6))
    block.apply_translation((0.1, 0.45, -0.9))
    mirror = trimesh.creation.box(extents=(1.2, 1.2, 0.05))
    mirror.apply_translation((0.0, 1.2, -1.9))

    def diffuse(rgb):
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}

    shapes = {
        "shape_000": (room, diffuse([0.6, 0.55, 0.5]), {"type": "diffuse", "roughness": 1.0}),
        "shape_001": (panel, diffuse([0.2, 0.2, 0.2]), {"type": "diffuse", "roughness": 1.0}),
        "shape_002": (ball, {"type": "dielectric", "int_ior": 1.5},
                      {"type": "dielectric", "roughness": 0.0, "transmissive": True}),
        "shape_003": (metal, {"type": "roughconductor", "material": "Au", "alpha": 0.25},
                      {"type": "roughconductor", "roughness": 0.25, "metallic": True}),
        "shape_004": (block, {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.7]},
                              "alpha": 0.2}, {"type": "roughplastic", "roughness": 0.2}),
        "shape_005": (mirror, {"type": "conductor", "material": "Ag"},
                      {"type": "conductor", "roughness": 0.0, "metallic": True}),
    }
    scene = {
        "type": "scene",
        "integrator": integrator or {"type": "path", "max_depth": 6},
        "sensor": {
            "type": "perspective", "fov": 60, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0.3, 1.4, 1.9], target=[0, 0.8, -0.5], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": 1},
        },
        "point": {"type": "point", "position": [1.2, 2.2, 1.0], "intensity": {"type": "rgb", "value": [3.0, 2.6, 2.0]}},
        "fill": {"type": "constant", "radiance": {"type": "rgb", "value": [0.02, 0.02, 0.03]}},
    }
    records = {}
    for index, (key, (mesh, bsdf, record)) in enumerate(shapes.items()):
        entry = {"type": "ply", "filename": _write_mesh(mesh, tmp_dir / f"{key}.ply"), "face_normals": True,
                 "bsdf": bsdf if materials else diffuse([0.5, 0.5, 0.5])}
        if key == "shape_001":
            entry["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [12.0, 11.0, 9.0]}}
        scene[key] = entry
        records[key] = {"index": index, **record}
    return scene, records


def load_with_attributes(scene_dict: dict, records: dict[str, dict]):
    """Load the scene dict after attaching the per-face attributes the feature integrator reads."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import attach_face_attributes

    scene_dict = dict(scene_dict)
    for key, record in records.items():
        mesh = mi.load_dict(scene_dict[key])
        attach_face_attributes(mesh, {"index": record["index"]}, record)
        scene_dict[key] = mesh
    return mi.load_dict(scene_dict)


@pytest.fixture(scope="session")
def test_scene_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("test_scene")


@pytest.fixture
def one_torch_thread():
    """One torch thread for the duration of a test: filter tests are small and the machine is shared."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
