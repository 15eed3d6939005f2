"""The Mitsuba scene features published scenes use, in a bring-your-own scene: each renders as Mitsuba's own
``path`` integrator renders the unmodified XML (mean radiance within the noise of both), with sane per-sample
buffers and one object id per authored shape; or it is refused by name at config time.

Scene folders (meshes, textures, an environment map) are written here by the tests; the reference is
``mi.load_file`` + Mitsuba's ``path``, never the harness's code.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scenegen.mitsuba_env import init_mitsuba

init_mitsuba()

import mitsuba as mi  # noqa: E402

from scenegen.custom.scene import import_custom_scene  # noqa: E402
from scenegen.custom.check import check_scene, custom_scene_problems  # noqa: E402
from scenegen.render import (NonFiniteCounter, RenderSettings, load_frame_scene, render_gbuffer,  # noqa: E402
                             render_sample_layers)

SIZE = 20
SENSOR = f"""<sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 1.6, 4.2" target="0, 0.4, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{SIZE}"/><integer name="height" value="{SIZE}"/>
      <rfilter type="box"/></film></sensor>"""
FLOOR = """<shape type="rectangle" id="floor"><transform name="to_world"><scale value="3"/>
    <rotate x="1" angle="-90"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"""
LAMP = """<shape type="sphere" id="lamp"><point name="center" x="1.5" y="3" z="1.5"/><float name="radius" value="0.4"/>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>"""


def scene_xml(body: str, lights: str = LAMP) -> str:
    return f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="6"/></integrator>
  {SENSOR}
  {FLOOR}
  {lights}
  {body}
</scene>"""


def write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(np.ascontiguousarray(rgb.astype(np.uint8))).write(str(path))


def write_exr(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(np.ascontiguousarray(rgb.astype(np.float32))).write(str(path))


def write_assets(folder: Path) -> None:
    """Textures (checker, normal map, bump height, alpha mask, emission), an environment map and an OBJ."""
    ij = np.add.outer(np.arange(32), np.arange(32))
    checker = np.where((ij // 4 % 2)[..., None] == 0, [230, 200, 40], [30, 70, 170])
    write_png(folder / "textures" / "checker.png", checker)
    tilt = np.stack([np.full((32, 32), 0.35), np.zeros((32, 32)), np.full((32, 32), 0.94)], -1)
    write_png(folder / "textures" / "normal.png", np.round((tilt * 0.5 + 0.5) * 255))
    write_png(folder / "textures" / "height.png", np.repeat((np.sin(ij / 3.0) * 0.5 + 0.5)[..., None] * 255, 3, -1))
    write_png(folder / "textures" / "mask.png", np.repeat(np.where(ij // 6 % 2 == 0, 255, 0)[..., None], 3, -1))
    sky = np.ones((16, 32, 3)) * np.linspace(0.2, 1.0, 16)[:, None, None] * np.array([0.6, 0.8, 1.0])
    write_exr(folder / "textures" / "sky.exr", sky)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "meshes" / "quad.obj").write_text(
        "v -0.5 0 -0.5\nv 0.5 0 -0.5\nv 0.5 0 0.5\nv -0.5 0 0.5\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 1 0\nf 1/1/1 4/4/1 3/3/1 2/2/1\n")


def cube(bsdf: str, x: float = 0.0, y: float = 0.45, scale: float = 0.45, ident: str = "") -> str:
    name = f' id="{ident}"' if ident else ""
    return (f'<shape type="cube"{name}><transform name="to_world"><scale value="{scale}"/>'
            f'<translate x="{x}" y="{y}"/></transform>{bsdf}</shape>')


CHECKER = '<texture type="bitmap" name="{name}"><string name="filename" value="textures/checker.png"/></texture>'
FEATURES: dict[str, tuple[str, str]] = {
    # name: (body, lights)
    "twosided": (cube('<bsdf type="twosided"><bsdf type="roughplastic"><rgb name="diffuse_reflectance" '
                      'value="0.2, 0.5, 0.7"/></bsdf></bsdf>'), LAMP),
    "bumpmap": (cube('<bsdf type="bumpmap"><texture type="bitmap"><string name="filename" '
                     'value="textures/height.png"/><boolean name="raw" value="true"/></texture>'
                     '<float name="scale" value="2"/><bsdf type="diffuse"/></bsdf>'), LAMP),
    "normalmap": (cube('<bsdf type="normalmap"><texture type="bitmap" name="normalmap"><string name="filename" '
                       'value="textures/normal.png"/><boolean name="raw" value="true"/></texture>'
                       '<bsdf type="roughconductor"><float name="alpha" value="0.3"/></bsdf></bsdf>'), LAMP),
    "mask": (cube('<bsdf type="mask"><texture type="bitmap" name="opacity"><string name="filename" '
                  'value="textures/mask.png"/></texture><bsdf type="diffuse"><rgb name="reflectance" '
                  'value="0.8, 0.3, 0.2"/></bsdf></bsdf>'), LAMP),
    "blendbsdf": (cube('<bsdf type="blendbsdf"><float name="weight" value="0.4"/><bsdf type="diffuse"/>'
                       '<bsdf type="conductor"/></bsdf>'), LAMP),
    "principled": (cube('<bsdf type="principled">' + CHECKER.format(name="base_color")
                        + '<float name="metallic" value="0.3"/><float name="roughness" value="0.4"/></bsdf>'), LAMP),
    "textured_mesh": ('<shape type="obj" id="panel"><string name="filename" value="meshes/quad.obj"/>'
                      '<transform name="to_world"><scale value="1.5"/><translate y="0.01"/></transform>'
                      '<bsdf type="diffuse">' + CHECKER.format(name="reflectance") + '</bsdf></shape>', LAMP),
    "point": (cube('<bsdf type="diffuse"/>'), '<emitter type="point"><point name="position" x="1" y="2.5" z="1.5"/>'
                                               '<rgb name="intensity" value="15"/></emitter>'),
    "spot": (cube('<bsdf type="diffuse"/>'), '<emitter type="spot"><transform name="to_world"><lookat '
                                              'origin="0.5, 3, 1" target="0, 0, 0"/></transform><float '
                                              'name="cutoff_angle" value="35"/><rgb name="intensity" value="25"/>'
                                              '</emitter>'),
    "directional": (cube('<bsdf type="diffuse"/>'), '<emitter type="directional"><vector name="direction" x="-0.4" '
                                                     'y="-1" z="-0.3"/><rgb name="irradiance" value="2"/></emitter>'),
    "envmap": (cube('<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf>'),
               '<emitter type="envmap"><string name="filename" value="textures/sky.exr"/></emitter>'),
    "textured_area": (cube('<bsdf type="diffuse"/>'),
                      '<shape type="rectangle" id="panel_light"><transform name="to_world"><scale value="0.6"/>'
                      '<rotate x="1" angle="90"/><translate y="2.5"/></transform><emitter type="area">'
                      + CHECKER.format(name="radiance") + '</emitter></shape>'),
}


INSTANCES = ('<shape type="shapegroup" id="group">' + cube('<bsdf type="diffuse"/>', scale=0.25, y=0.0) + '</shape>'
             + ''.join(f'<shape type="instance"><ref id="group"/><transform name="to_world"><translate x="{x}" '
                       f'y="0.25"/></transform></shape>' for x in (-0.8, 0.8)))
MEDIUM = ('<shape type="cube"><transform name="to_world"><scale value="0.4"/><translate y="0.5"/></transform>'
          '<bsdf type="null"/><medium type="homogeneous" name="interior"><rgb name="albedo" value="0.8"/>'
          '<float name="sigma_t" value="2"/></medium></shape>')
#: Features refused at config time: (body, words the message must contain).
REFUSED: dict[str, tuple[str, tuple[str, ...]]] = {
    "instancing": (INSTANCES, ("shapegroup", "not supported", "instanc")),
    "medium": (MEDIUM, ("medium 'homogeneous'", "not supported", "participating media")),
}


def import_feature(tmp_path: Path, name: str) -> tuple[dict, Path, Path]:
    folder = tmp_path / name
    write_assets(folder)
    body, lights = FEATURES[name] if name in FEATURES else (REFUSED[name][0], LAMP)
    xml = folder / "scene.xml"
    xml.write_text(scene_xml(body, lights))
    entry = {"name": name, "xml": str(xml), "frames": 1, "camera": {"path": "pan"}}
    return import_custom_scene(entry, f"custom_{name}", folder / "out"), folder, xml


def group_means(images: np.ndarray, groups: int) -> np.ndarray:
    """(N, ...) per-sample images -> (groups,) means of equal groups of them."""
    return images.reshape(groups, -1).mean(axis=1)


@pytest.mark.parametrize("name", sorted(FEATURES))
def test_feature_renders_as_mitsuba_path(tmp_path: Path, name: str) -> None:
    manifest, folder, xml = import_feature(tmp_path, name)
    settings = RenderSettings(width=SIZE, height=SIZE, max_depth=6)
    scene = load_frame_scene(manifest, folder / "out", 0, settings)
    counter = NonFiniteCounter()
    layers = render_sample_layers(scene, n_layers=256, n_radiance_only=0, seed=11, counter=counter)
    assert sum(counter.counts.values()) == 0
    albedo, normal = layers["albedo"], layers["normal"]
    assert albedo.min() >= 0.0 and albedo.max() <= 1.0
    length = np.linalg.norm(normal, axis=1)
    assert np.all((np.abs(length - 1) < 1e-3) | (length == 0))
    reference = mi.load_file(str(xml))
    theirs = np.stack([np.array(mi.render(reference, spp=32, seed=seed), np.float64)[..., :3].mean()
                       for seed in range(8)])
    ours = group_means(layers["radiance"].astype(np.float64), 8)
    error = math.sqrt(ours.var(ddof=1) / 8 + theirs.var(ddof=1) / 8)
    assert abs(ours.mean() - theirs.mean()) < 4 * error + 1e-6, (ours.mean(), theirs.mean(), error)
    # The manifest records the lights: area emitters per shape, the others in "emitters".
    lights = {"point": "point", "spot": "spot", "directional": "directional", "envmap": "envmap"}
    assert [emitter["type"] for emitter in manifest["emitters"]] == ([lights[name]] if name in lights else [])
    area = [shape["emitter"] for shape in manifest["shapes"] if shape["emitter"] is not None]
    if name == "textured_area":
        assert area == [{"type": "area", "radiance_texture": "bitmap"}]
    elif name not in lights:
        assert area == [{"type": "area", "radiance": [8.0, 8.0, 8.0]}]
    objects = render_gbuffer(manifest, folder / "out", 0, settings)["object"][0]
    seen = set(np.unique(objects)) - {-1.0}
    assert seen <= set(float(shape["index"]) for shape in manifest["shapes"])
    assert len(seen) >= 2   # the floor and the feature's shape


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_refused_feature_is_named_at_config_time(tmp_path: Path, name: str) -> None:
    """Instances and participating media would render wrongly without a word: the config check names the
    feature, the scene id, the file and the line, and the import refuses it too."""
    folder = tmp_path / name
    folder.mkdir()
    xml = folder / "scene.xml"
    xml.write_text(scene_xml(REFUSED[name][0]))
    problems = custom_scene_problems({"extra_scenes": [{"name": name, "xml": str(xml), "frames": 1,
                                                         "camera": {"path": "pan"}}]})
    assert problems and all(f"(scene custom_{name})" in problem for problem in problems)
    assert any(f"{xml} (line " in problem for problem in problems)
    for words in REFUSED[name][1]:
        assert any(words in problem for problem in problems), (words, problems)
    assert check_scene(xml).problems
    with pytest.raises(ValueError, match="not supported"):
        import_feature(tmp_path / "again", name)
