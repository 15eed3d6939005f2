"""Bring-your-own scene folders load as Mitsuba loads them (relative meshes, textures, environment maps,
includes, ``$param`` defaults), are checked when the config is read, and their digest covers every file.

References: ``mi.load_file`` + Mitsuba's ``path`` on the unmodified folder, and hand-written expectations of
which file and line an error names.
"""
from __future__ import annotations

import copy
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml

from scenegen.mitsuba_env import init_mitsuba

init_mitsuba()

import mitsuba as mi  # noqa: E402

from scenegen.config import load_config  # noqa: E402
from scenegen.custom.scene import CustomSceneError, import_custom_scene  # noqa: E402
from scenegen.custom.check import custom_scene_problems, scene_files  # noqa: E402
from scenegen.digests import render_digest, scene_digest  # noqa: E402
from scenegen.render import (NonFiniteCounter, RenderSettings, load_frame_scene, render_gbuffer,  # noqa: E402
                             render_sample_layers)
from tests.test_custom_features import SIZE, write_assets  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SENSOR = f"""<sensor type="perspective"><float name="fov" value="55"/>
    <transform name="to_world"><lookat origin="0, 1.8, 4" target="0, 0.3, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{SIZE}"/><integer name="height" value="{SIZE}"/>
      <rfilter type="box"/></film></sensor>"""
#: A downloaded-style folder: meshes of three formats in meshes/, a bitmap texture, an EXR environment map,
#: the lights in an include, and a $param default for the floor's reflectance.
FOLDER_XML = f"""<scene version="3.0.0">
  <default name="floor_reflectance" value="0.3"/>
  <integrator type="path"><integer name="max_depth" value="5"/></integrator>
  {SENSOR}
  <shape type="rectangle" id="floor"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
    </transform><bsdf type="diffuse"><rgb name="reflectance" value="$floor_reflectance"/></bsdf></shape>
  <shape type="obj" id="obj_panel"><string name="filename" value="meshes/quad.obj"/>
    <transform name="to_world"><translate x="-1" y="0.02"/></transform>
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
      <string name="filename" value="textures/checker.png"/></texture></bsdf></shape>
  <shape type="ply" id="ply_triangle"><string name="filename" value="meshes/tri.ply"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.3"/></bsdf></shape>
  <shape type="serialized" id="serialized_triangle"><string name="filename" value="meshes/tri.serialized"/>
    <transform name="to_world"><translate x="1"/></transform>
    <bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.6, 0.3"/></bsdf></shape>
  <include filename="parts/lights.xml"/>
</scene>"""
LIGHTS_XML = """<scene version="3.0.0">
  <emitter type="envmap"><string name="filename" value="textures/sky.exr"/></emitter>
  <shape type="sphere" id="lamp"><point name="center" x="1" y="2.5" z="1"/><float name="radius" value="0.3"/>
    <emitter type="area"><rgb name="radiance" value="6"/></emitter></shape>
</scene>"""
TRIANGLE = np.array([[-0.4, 0.0, 0.3], [0.4, 0.0, 0.3], [0.0, 0.9, 0.3]], np.float32)


def write_serialized(path: Path, positions: np.ndarray, faces: np.ndarray) -> None:
    """Mitsuba's ``serialized`` format (version 4, one single-precision mesh, no normals or UVs)."""
    body = struct.pack("<I", 0x1000) + b"triangle\x00" + struct.pack("<QQ", len(positions), len(faces))
    body += positions.astype("<f4").tobytes() + faces.astype("<u4").tobytes()
    path.write_bytes(struct.pack("<HH", 0x041C, 4) + zlib.compress(body) + struct.pack("<QI", 0, 1))


def write_folder(root: Path) -> Path:
    """The scene folder of FOLDER_XML under ``root``; returns the XML's path."""
    write_assets(root)
    faces = np.array([[0, 1, 2]], np.uint32)
    mesh = mi.Mesh("tri", 3, 1)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(TRIANGLE.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    mesh.write_ply(str(root / "meshes" / "tri.ply"))
    write_serialized(root / "meshes" / "tri.serialized", TRIANGLE, faces)
    (root / "parts").mkdir()
    (root / "parts" / "lights.xml").write_text(LIGHTS_XML)
    xml = root / "scene.xml"
    xml.write_text(FOLDER_XML)
    return xml


def mean_radiance(scene, groups: int = 8, spp: int = 32) -> np.ndarray:
    return np.stack([np.array(mi.render(scene, spp=spp, seed=seed), np.float64)[..., :3].mean()
                     for seed in range(groups)])


@pytest.fixture()
def folder(tmp_path: Path, monkeypatch) -> Path:
    """The scene folder, with the working directory elsewhere (relative paths must not lean on it)."""
    xml = write_folder(tmp_path / "downloaded_scene")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    return xml


def test_a_scene_folder_with_relative_paths_renders_as_mitsuba_loads_it(folder: Path, tmp_path: Path) -> None:
    entry = {"name": "downloaded", "xml": str(folder), "frames": 1, "camera": {"path": "pan"}}
    manifest = import_custom_scene(entry, "custom_downloaded", tmp_path / "out")
    assert set(manifest["files"]) == {"scene.xml", "parts/lights.xml", "meshes/quad.obj", "meshes/tri.ply",
                                      "meshes/tri.serialized", "textures/checker.png", "textures/sky.exr"}
    names = [shape["name"] for shape in manifest["shapes"]]
    assert names == ["floor", "obj_panel", "ply_triangle", "serialized_triangle", "lamp"]
    # The manifest records each shape's material and emitter.
    materials = [manifest["materials"][shape["material"]]["type"] for shape in manifest["shapes"]]
    assert materials == ["diffuse", "diffuse", "roughconductor", "roughplastic", "diffuse"]
    assert [shape["emitter"] for shape in manifest["shapes"]][:4] == [None] * 4
    assert manifest["shapes"][4]["emitter"] == {"type": "area", "radiance": [6.0, 6.0, 6.0]}
    assert [emitter["type"] for emitter in manifest["emitters"]] == ["envmap"]

    settings = RenderSettings(width=SIZE, height=SIZE)
    scene = load_frame_scene(manifest, tmp_path / "out", 0, settings)
    layers = render_sample_layers(scene, n_layers=256, n_radiance_only=0, seed=3, counter=NonFiniteCounter())
    ours = layers["radiance"].astype(np.float64).reshape(8, -1).mean(axis=1)
    theirs = mean_radiance(mi.load_file(str(folder)))
    error = math.sqrt(ours.var(ddof=1) / 8 + theirs.var(ddof=1) / 8)
    assert abs(ours.mean() - theirs.mean()) < 4 * error, (ours.mean(), theirs.mean(), error)
    objects = render_gbuffer(manifest, tmp_path / "out", 0, settings)["object"][0]
    assert {0.0, 1.0, 2.0, 3.0} <= set(np.unique(objects))   # the floor and the three meshes, one id each


def test_params_take_their_defaults_unless_the_entry_sets_them(folder: Path, tmp_path: Path) -> None:
    entry = {"name": "downloaded", "xml": str(folder), "frames": 1, "camera": {"path": "pan"}}
    settings = RenderSettings(width=SIZE, height=SIZE)

    def floor_albedo(manifest: dict, out: Path) -> float:
        albedo = render_gbuffer(manifest, out, 0, settings)
        floor = albedo["object"][0] == 0
        return float(albedo["albedo"][0][floor].mean())

    default = import_custom_scene(entry, "custom_downloaded", tmp_path / "default")
    bright = import_custom_scene({**entry, "params": {"floor_reflectance": 0.8}}, "custom_downloaded",
                                 tmp_path / "bright")
    assert default["params"] == {} and bright["params"] == {"floor_reflectance": 0.8}
    assert floor_albedo(default, tmp_path / "default") == pytest.approx(0.3, abs=1e-3)
    assert floor_albedo(bright, tmp_path / "bright") == pytest.approx(0.8, abs=1e-3)
    cfg = {"extra_scenes": [{**entry, "params": {"floor_reflectanse": 0.8}}]}
    problems = custom_scene_problems(cfg)
    assert len(problems) == 1 and "custom_downloaded" in problems[0] and "floor_reflectanse" in problems[0]


# ------------------------------------------------------------------------------------- config-time checks
def entry_for(xml: Path) -> dict:
    return {"name": "mine", "xml": str(xml), "frames": 1, "camera": {"path": "pan"}}


def line_of(text: str, needle: str) -> int:
    """1-based number of the first line of ``text`` holding ``needle``."""
    return next(number for number, line in enumerate(text.splitlines(), 1) if needle in line)


PLY_LINE = line_of(FOLDER_XML, 'type="ply"')
CONDUCTOR_LINE = line_of(FOLDER_XML, 'type="roughconductor"')
SERIALIZED_LINE = line_of(FOLDER_XML, 'type="serialized"')


@pytest.mark.parametrize("case, edit, words", [
    ("missing mesh", lambda s: s.replace("meshes/tri.ply", "meshes/gone.ply"),
     ["(scene custom_mine)", f"scene.xml (line {PLY_LINE}", "'meshes/gone.ply' not found"]),
    ("unknown plugin", lambda s: s.replace('type="roughconductor"', 'type="roughconductr"'),
     ["(scene custom_mine)", f"scene.xml (line {CONDUCTOR_LINE}", "unknown plugin 'roughconductr'"]),
    # The ply shape's closing </bsdf> removed: the parser stops at the mismatched </shape>.
    ("malformed", lambda s: s.replace('<float name="alpha" value="0.3"/></bsdf></shape>',
                                      '<float name="alpha" value="0.3"/></shape>'),
     ["(scene custom_mine)", "scene.xml", f"(line {CONDUCTOR_LINE}", "mismatch"]),
    ("missing in an include", lambda s: s,
     ["(scene custom_mine)", f"lights.xml (line {line_of(LIGHTS_XML, 'envmap')}", "'textures/sky.exr' not found"]),
])
def test_config_check_names_the_scene_file_and_line(folder: Path, case: str, edit, words: list[str]) -> None:
    folder.write_text(edit(folder.read_text()))
    if case == "missing in an include":
        (folder.parent / "textures" / "sky.exr").unlink()
    problems = custom_scene_problems({"extra_scenes": [entry_for(folder)]})
    assert problems, case
    text = "\n".join(problems)
    for word in words:
        assert word in text, (case, word, text)


def test_a_missing_xml_is_named(tmp_path: Path) -> None:
    problems = custom_scene_problems({"extra_scenes": [entry_for(tmp_path / "nowhere" / "scene.xml")]})
    assert problems == [f"extra_scenes[0] (scene custom_mine): XML file not found: {tmp_path / 'nowhere' / 'scene.xml'}"]


def test_the_digest_covers_every_referenced_file(folder: Path, tmp_path: Path) -> None:
    cfg = copy.deepcopy(load_config(REPO / "config" / "smoke.yaml"))
    cfg["extra_scenes"] = [entry_for(folder)]
    before = scene_digest(cfg, "custom_mine"), render_digest(cfg, "custom_mine", "noisy")
    manifest = import_custom_scene(entry_for(folder), "custom_mine", tmp_path / "out")
    mesh = folder.parent / "meshes" / "tri.ply"
    mesh.write_bytes(mesh.read_bytes())   # rewritten with the same content: the digest is by content
    os.utime(mesh, (1, 1))
    assert (scene_digest(cfg, "custom_mine"), render_digest(cfg, "custom_mine", "noisy")) == before
    serialized = folder.parent / "meshes" / "tri.serialized"
    write_serialized(serialized, TRIANGLE * 1.5, np.array([[0, 1, 2]], np.uint32))
    after = scene_digest(cfg, "custom_mine"), render_digest(cfg, "custom_mine", "noisy")
    assert after[0] != before[0] and after[1] != before[1]
    # A scene imported before the edit refuses to render rather than mix old and new files.
    with pytest.raises(CustomSceneError, match="meshes/tri.serialized.*re-run generate_scene"):
        load_frame_scene(manifest, tmp_path / "out", 0, RenderSettings(width=SIZE, height=SIZE))
    (folder.parent / "textures" / "checker.png").unlink()
    with pytest.raises(CustomSceneError, match="textures/checker.png' not found"):
        scene_digest(cfg, "custom_mine")
    with pytest.raises(CustomSceneError, match="textures/checker.png' not found"):
        scene_files(entry_for(folder))


# ------------------------------------------------------------------------------------- at DAG build
def test_a_bad_custom_scene_fails_the_dry_run_before_anything_is_written(tmp_path: Path) -> None:
    """The DAG is not built: the error names the scene id, the file and the line, and no resolved config
    (<output_dir>/.config/) or any other output is left behind."""
    from tests.test_workflow import copy_workflow, run_snakemake

    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")
    xml = write_folder(tmp_path / "scene")
    xml.write_text(xml.read_text().replace('type="roughconductor"', 'type="roughconductr"'))
    cfg = yaml.safe_load((REPO / "config" / "smoke.yaml").read_text())
    cfg["output_dir"] = str(tmp_path / "out")
    cfg["extra_scenes"] = [entry_for(xml)]
    (workdir / "bad.yaml").write_text(yaml.safe_dump(cfg))
    result = run_snakemake("-n", "--configfile", "bad.yaml", cwd=workdir, check=False)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert "(scene custom_mine)" in output and f"{xml} (line {CONDUCTOR_LINE}" in output and "roughconductr" in output
    assert not (tmp_path / "out").exists()
