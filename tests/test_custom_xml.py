"""Bring-your-own XML scenes are rendered as authored: hide_emitters, max_depth / rr_depth, one object id
per authored shape, and every substitution recorded (scenegen.custom.scene, scenegen.custom.parse, the integrator).

References are Mitsuba's own ``path`` integrator and analytic screen positions, never the harness's code.
"""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from scenegen.config import ConfigError, load_config, validate_config
from scenegen.custom.scene import UNBOUNDED_DEPTH, import_custom_scene, integrator_settings
from scenegen.render import RenderSettings, load_frame_scene, render_gbuffer

REPO = Path(__file__).resolve().parents[1]
SENSOR = """<sensor type="{sensor}">
    {fov}
    <transform name="to_world">{scale}<lookat origin="{origin}" target="{target}" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/>
      <rfilter type="box"/></film>
  </sensor>"""
#: Half-size (scene units) of the orthographic view: the camera's [-1, 1]^2 scaled by this.
ORTHO_HALF = 0.8


def sensor(width: int = 24, height: int = 24, fov: float = 60.0, origin: str = "0, 0, 5", target: str = "0, 0, 0",
           kind: str = "perspective") -> str:
    """A box-filtered sensor; perspective with a horizontal ``fov``, or orthographic of half-size ORTHO_HALF."""
    ortho = kind == "orthographic"
    return SENSOR.format(sensor=kind, fov="" if ortho else f'<float name="fov" value="{fov}"/>',
                         scale=f'<scale x="{ORTHO_HALF}" y="{ORTHO_HALF}"/>' if ortho else "", origin=origin,
                         target=target, width=width, height=height)


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / f"{name}.xml"
    path.write_text(text)
    return path


def entry(xml: Path, **extra) -> dict:
    return {"name": xml.stem, "xml": str(xml), "frames": 1, "camera": {"path": "pan"}, **extra}


def render_mean(scene, spp: int, seed: int = 5, integrator=None) -> np.ndarray:
    import mitsuba as mi

    kwargs = {"integrator": integrator} if integrator is not None else {}
    return np.array(mi.render(scene, spp=spp, seed=seed, **kwargs), np.float64)[..., :3]


# ------------------------------------------------------------------------------------------ substitutions
def test_every_substitution_is_recorded(tmp_path: Path) -> None:
    xml = write(tmp_path, "odd", f"""<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="thinlens">
    <float name="aperture_radius" value="0.05"/><float name="focus_distance" value="4"/>
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="stratified"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/>
      <integer name="crop_width" value="20"/><integer name="crop_height" value="10"/>
      <rfilter type="gaussian"/></film>
  </sensor>
  {sensor()}
  <shape type="sphere"/>
  <emitter type="constant"/>
</scene>""")
    manifest = import_custom_scene(entry(xml, max_depth=3), "custom_odd", tmp_path / "odd")
    rows = {row["what"]: row for row in manifest["substitutions"]}
    assert set(rows) == {"integrator", "max_depth", "pixel filter", "resolution", "sampler", "sensor", "sensors",
                         "camera"}
    assert (rows["integrator"]["authored"], rows["integrator"]["used"]) == ("direct", "mcdn_features")
    assert "not reproduced" in rows["integrator"]["why"]
    assert (rows["max_depth"]["authored"], rows["max_depth"]["used"]) == ("-1", "3")
    assert rows["pixel filter"]["authored"] == "gaussian (radius 2 px)"
    assert rows["resolution"]["authored"] == "40x30 (crop 20x10)"
    assert rows["sampler"]["authored"] == "stratified, 16 spp"
    assert (rows["sensor"]["authored"], rows["sensors"]["authored"]) == ("thinlens", "2 sensors")
    assert manifest["render"] == {"max_depth": 3, "rr_depth": 5, "hide_emitters": False, "filter": "box"}
    for row in manifest["substitutions"]:
        assert set(row) == {"what", "authored", "used", "why"} and all(row.values()), row


def test_a_box_filtered_path_scene_substitutes_only_what_it_must(tmp_path: Path) -> None:
    xml = write(tmp_path, "plain", f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  {sensor()}
  <shape type="sphere"/>
</scene>""")
    manifest = import_custom_scene(entry(xml), "custom_plain", tmp_path / "plain")
    assert [row["what"] for row in manifest["substitutions"]] == ["integrator", "resolution", "sampler", "camera"]
    assert manifest["render"]["max_depth"] == 4 and manifest["authored"]["filter"] == "box"
    no_integrator = write(tmp_path, "bare", f'<scene version="3.0.0">{sensor()}<shape type="sphere"/></scene>')
    manifest = import_custom_scene(entry(no_integrator), "custom_bare", tmp_path / "bare")
    assert manifest["substitutions"][0]["authored"] == "none" and manifest["render"]["max_depth"] == -1
    assert integrator_settings(manifest)["max_depth"] == UNBOUNDED_DEPTH


def test_extra_scene_depth_keys_are_validated() -> None:
    cfg = copy.deepcopy(load_config(REPO / "config" / "config.yaml"))     # it has an extra scene
    cfg["extra_scenes"][0]["max_depth"] = 0
    with pytest.raises(ConfigError, match=r"extra_scenes\[0\]\.max_depth' = 0 is not allowed"):
        validate_config(copy.deepcopy(cfg))
    cfg["extra_scenes"][0].update(max_depth=-1, rr_depth=0)
    with pytest.raises(ConfigError, match=r"extra_scenes\[0\]\.rr_depth"):
        validate_config(cfg)


# ------------------------------------------------------------------------------------------ hide_emitters
LIGHT_SCENE = """<scene version="3.0.0">
  <integrator type="{integrator}"><integer name="max_depth" value="5"/>
    <boolean name="hide_emitters" value="{hide}"/></integrator>
  {sensor}
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.6"/><translate x="{light_x}" z="{light_z}"/></transform>
    <emitter type="area"><rgb name="radiance" value="5"/></emitter>
  </shape>
  <shape type="sphere"><point name="center" x="0.9" y="0" z="-0.5"/><float name="radius" value="0.5"/></shape>
  <shape type="sphere"><point name="center" x="-0.8" y="0" z="-0.5"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></shape>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
</scene>"""


def light_scene(integrator: str, hide: bool, light_x: float = -1.8, light_z: float = 1.0, **view):
    import mitsuba as mi

    import scenegen.integrator  # noqa: F401 -- registers mcdn_features

    return mi.load_string(LIGHT_SCENE.format(integrator=integrator, hide=str(hide).lower(), light_x=light_x,
                                             light_z=light_z, sensor=sensor(**view)))


def test_hide_emitters_matches_mitsuba_path() -> None:
    """The area light (nothing behind it) and the environment are hidden from camera rays but still light
    the spheres: the same image as Mitsuba's path with hide_emitters=true."""
    for hide in (False, True):
        ours = render_mean(light_scene("mcdn_features", hide), spp=64)
        theirs = render_mean(light_scene("path", hide), spp=64)
        np.testing.assert_allclose(ours, theirs, atol=2e-4)
    shown = render_mean(light_scene("path", False), spp=16)
    assert shown.max() == pytest.approx(5.0) and (ours == 0).all(axis=-1).mean() > 0.5
    assert (ours.max(axis=-1) > 0.05).sum() >= 20  # the spheres (about 30 pixels) are still lit


def test_a_hidden_area_light_shows_the_surface_behind_it() -> None:
    """Looking through a hidden light at a sphere equals looking at the sphere from in front of the light
    with nothing hidden: orthographic rays, so both cameras see the same points along the same directions.
    (Mitsuba 3.9.1's own path/prb differ here: for rays continued behind a hidden area emitter they shade
    the next surface as if the emitter did not occlude the environment; the lit side below is darker.)"""
    import mitsuba as mi

    size = 16
    view = {"kind": "orthographic", "width": size, "height": size, "target": "0.9, 0, -0.5"}
    # The sphere (radius 0.5 about x = 0.9) lies wholly behind the light panel (x in [0.3, 1.5]).
    hidden = light_scene("mcdn_features", True, light_x=0.9, light_z=1.0, origin="0.9, 0, 4", **view)
    in_front = light_scene("path", False, light_x=0.9, light_z=1.0, origin="0.9, 0, 0.9", **view)
    ours, reference = render_mean(hidden, spp=512), render_mean(in_front, spp=512)
    centres = (np.arange(size) + 0.5) / size * 2 * ORTHO_HALF - ORTHO_HALF
    sphere = np.hypot(*np.meshgrid(centres, centres)) < 0.45  # pixels wholly inside the silhouette
    assert sphere.sum() > 50
    assert ours[sphere].mean() == pytest.approx(reference[sphere].mean(), rel=0.02)
    assert np.abs(ours - reference)[sphere].mean() < 0.1 * reference[sphere].mean()
    gbuffer = np.array(mi.render(hidden, spp=1, integrator=mi.load_dict({"type": "mcdn_features",
                                                                          "mode": "gbuffer"})))
    depth = gbuffer[..., 3 + 6]
    assert (depth[sphere] > 3.9).all()  # camera to sphere (4 and more), not to the light panel (3)


# ------------------------------------------------------------------------------------------ max_depth
DEPTH_SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="{depth}"/></integrator>
  {sensor}
  <bsdf type="diffuse" id="wall"><rgb name="reflectance" value="0.8"/></bsdf>
  <shape type="cube"><transform name="to_world"><scale value="2"/></transform>
    <boolean name="flip_normals" value="true"/><ref id="wall"/></shape>
  <shape type="sphere"><point name="center" x="0" y="-1.4" z="0"/><float name="radius" value="0.5"/>
    <ref id="wall"/></shape>
  <shape type="sphere"><point name="center" x="0" y="1.5" z="0"/><float name="radius" value="0.25"/>
    <emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>
</scene>"""


def test_max_depth_is_the_xml_s_unless_the_entry_sets_it(tmp_path: Path) -> None:
    import mitsuba as mi

    view = sensor(16, 16, origin="0, 0, 1.9", target="0, -1, 0")
    xml = write(tmp_path, "box", DEPTH_SCENE.format(sensor=view, depth=2))
    settings = RenderSettings(width=16, height=16, max_depth=8, rr_depth=5)  # the config's depth: not used

    def ours(manifest: dict) -> float:
        scene = load_frame_scene(manifest, tmp_path, 0, settings)
        return float(render_mean(scene, spp=256).mean())

    def mitsuba_path(depth: int) -> float:
        return float(render_mean(mi.load_string(DEPTH_SCENE.format(sensor=view, depth=depth)), spp=256).mean())

    authored = import_custom_scene(entry(xml), "custom_box", tmp_path / "a")
    assert authored["render"]["max_depth"] == 2
    assert ours(authored) == pytest.approx(mitsuba_path(2), rel=0.03)
    assert mitsuba_path(8) > 1.5 * mitsuba_path(2)  # indirect light matters here: the depth is visible
    overridden = import_custom_scene(entry(xml, max_depth=8), "custom_box", tmp_path / "b")
    assert overridden["render"]["max_depth"] == 8
    assert {"what": "max_depth", "authored": "2", "used": "8",
            "why": "set by the extra_scenes entry's max_depth"} in overridden["substitutions"]
    assert ours(overridden) == pytest.approx(mitsuba_path(8), rel=0.03)


# ------------------------------------------------------------------------------------------ object ids
IDS_SCENE = """<scene version="3.0.0">
  <integrator type="path"/>
  {sensor}
  <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.5"/></bsdf>
  <shape type="sphere"><point name="center" x="-3" y="0" z="0"/><float name="radius" value="0.4"/>
    <ref id="grey"/></shape>
  <shape type="sphere"><point name="center" x="-1.8" y="0" z="0"/><float name="radius" value="0.4"/>
    <ref id="grey"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="0.4"/><translate x="-0.6"/></transform>
    <ref id="grey"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="0.4"/><translate x="0.6"/></transform>
    <ref id="grey"/></shape>
  <shape type="merge">
    <shape type="cube"><transform name="to_world"><scale value="0.4"/><translate x="1.8"/></transform>
      <ref id="grey"/></shape>
    <shape type="cube"><transform name="to_world"><scale value="0.4"/><translate x="3"/></transform>
      <ref id="grey"/></shape>
  </shape>
  <emitter type="constant"/>
</scene>"""


def test_merged_shapes_keep_distinct_object_ids(tmp_path: Path) -> None:
    """Two analytic spheres, two rectangles sharing a material (merged by Mitsuba's default loading) and
    two cubes in a `merge` shape: six authored shapes, six ids, in authored order from left to right."""
    import mitsuba as mi

    width, height, fov = 96, 16, 90.0
    xml = write(tmp_path, "ids", IDS_SCENE.format(sensor=sensor(width, height, fov=fov)))
    assert len(mi.load_file(str(xml)).shapes()) < 6  # what Mitsuba does on its own: merged shapes
    manifest = import_custom_scene(entry(xml), "custom_ids", tmp_path / "ids")
    assert [shape["type"] for shape in manifest["shapes"]] == ["sphere", "sphere", "rectangle", "rectangle",
                                                               "cube", "cube"]
    settings = RenderSettings(width=width, height=height)
    objects = render_gbuffer(manifest, tmp_path, 0, settings)["object"][0]
    # Pinhole at z = 5 looking down -z, horizontal fov 90 degrees: x at depth 5 (z = 0) maps to column
    # (0.5 + x / (2 * 5 * tan 45)) * width; the front faces of the cubes (z = 0.4) are nearer, same centre.
    for index, x in enumerate((-3.0, -1.8, -0.6, 0.6, 1.8, 3.0)):
        depth = 5.0 - (0.4 if index >= 4 else 0.0)
        column = int((0.5 + x / (2 * depth * math.tan(math.radians(fov / 2)))) * width)
        assert objects[height // 2, column] == index, (index, objects[height // 2])
    assert set(np.unique(objects)) == {-1.0, *map(float, range(6))}


@pytest.mark.parametrize("bsdf, expected", [
    ({"type": "conductor"}, {"type": "conductor", "roughness": 0.0, "metallic": True, "transmissive": False}),
    ({"type": "roughconductor", "alpha": 0.3}, {"type": "roughconductor", "roughness": 0.3, "metallic": True}),
    ({"type": "twosided", "inner": {"type": "roughconductor", "alpha": 0.3}},
     {"type": "roughconductor", "roughness": 0.3, "metallic": True, "transmissive": False}),
    ({"type": "twosided", "inner": {"type": "conductor"}}, {"type": "conductor", "roughness": 0.0, "metallic": True}),
    ({"type": "dielectric"}, {"type": "dielectric", "roughness": 0.0, "metallic": False, "transmissive": True}),
    ({"type": "roughdielectric", "alpha": 0.2}, {"type": "roughdielectric", "roughness": 0.2, "transmissive": True}),
    ({"type": "twosided", "inner": {"type": "diffuse"}}, {"type": "diffuse", "roughness": 1.0, "metallic": False}),
])
def test_material_features_of_xml_bsdfs_follow_the_plugin(bsdf: dict, expected: dict) -> None:
    """Smooth and two-sided BSDFs are recognised (Mitsuba's class names are SmoothConductor, TwoSidedBRDF, ...)."""
    import mitsuba as mi

    from scenegen.custom.scene import _material_record
    from scenegen.mitsuba_env import init_mitsuba

    init_mitsuba("llvm_ad_rgb")
    record = _material_record(mi.load_dict(bsdf))
    for key, value in expected.items():
        assert record[key] == pytest.approx(value) if isinstance(value, float) else record[key] == value, (key, record)
