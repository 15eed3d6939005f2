"""Bring-your-own Mitsuba XML scenes go through the same render jobs and loader."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from scenegen.config import load_config
from scenegen.custom.scene import CustomSceneError, import_custom_scene
from scenegen.dataset import load_clip
from scenegen.jobs import run_generate, run_render_noisy, run_render_reference

REPO = Path(__file__).resolve().parents[1]
XML = """<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 1.2, 4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
  </sensor>
  <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.6"/></bsdf>
  <shape type="rectangle">
    <transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/></transform>
    <ref id="grey"/>
  </shape>
  <shape type="sphere"><point name="center" x="-0.6" y="0.5" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.3"/></bsdf></shape>
  <shape type="cube"><transform name="to_world"><scale value="0.35"/><translate x="0.8" y="0.35"/></transform>
    <bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.5, 0.8"/></bsdf></shape>
  <emitter type="point"><point name="position" x="1" y="3" z="2"/><rgb name="intensity" value="20"/></emitter>
  <emitter type="constant"><rgb name="radiance" value="0.2"/></emitter>
</scene>
"""


@pytest.fixture(scope="module")
def custom_cfg(tmp_path_factory):
    root = tmp_path_factory.mktemp("custom")
    xml = root / "my_scene.xml"
    xml.write_text(XML)
    cfg = copy.deepcopy(load_config(REPO / "config" / "smoke.yaml"))
    cfg["render"].update(width=32, height=32, spp=4, reference_spp=64, reference_batch_spp=32)
    cfg["scenes"]["frames_per_chunk"] = 2
    cfg["extra_scenes"] = [{"name": "mine", "xml": str(xml), "frames": 2, "camera": {"path": "orbit"}}]
    return cfg, root


def test_custom_scene_renders_and_loads(custom_cfg):
    import mitsuba as mi

    cfg, root = custom_cfg
    scene_dir = root / "scenes" / "custom_mine"
    manifest = run_generate(cfg, "custom_mine", scene_dir)
    assert manifest["kind"] == "custom" and len(manifest["camera"]["frames"]) == 2
    # The XML's own sensor is the first frame's camera.
    np.testing.assert_allclose(manifest["camera"]["frames"][0]["origin"], [0, 1.2, 4], atol=1e-5)
    render_dir = root / "renders" / "custom_mine"
    run_render_noisy(cfg, "custom_mine", 0, scene_dir, render_dir / "noisy" / "chunk_000")
    run_render_reference(cfg, "custom_mine", 0, scene_dir, render_dir / "reference" / "chunk_000")
    clip = load_clip(render_dir)
    # An evaluated scene: 4 full layers plus the config's radiance-only layers for adaptive sampling.
    extra = cfg["render"]["extra_radiance_spp"]
    assert extra > 0 and clip.samples["radiance"].shape == (2, 4 + extra, 3, 32, 32)
    assert clip.samples["albedo"].shape == (2, 4, 3, 32, 32)
    assert np.isfinite(clip.samples["radiance"]).all()
    # Every shape carries material features: the meshes as mesh attributes (the rough plastic cube), the
    # analytic rough-conductor sphere as texture attributes. The orbit keeps most pixels reprojectable.
    assert (np.abs(clip.samples["roughness"] - 0.1) < 1e-3).any()  # roughplastic's default alpha
    assert (np.abs(clip.samples["roughness"] - 0.3) < 1e-3).any()  # the sphere's alpha
    assert (np.abs(clip.samples["roughness"] - 1.0) < 1e-3).any()  # the diffuse floor
    assert (clip.samples["flags"][:, :, 1] > 0.5).any()            # metallic: the conductor sphere
    assert all(shape["material_features"] for shape in manifest["shapes"])
    assert manifest["shapes_without_material_features"] == []
    assert [shape["type"] for shape in manifest["shapes"]] == ["rectangle", "sphere", "cube"]
    hit = clip.gbuffer["object"][1, 0] >= 0  # background (environment) pixels have no history
    assert hit.mean() > 0.3 and clip.valid[1, 0][hit].mean() > 0.7
    assert set(np.unique(clip.gbuffer["object"][0, 0])) == {-1.0, 0.0, 1.0, 2.0}

    # As authored: `<integrator type="path"/>` means path's defaults (no depth limit), not render.max_depth.
    assert manifest["render"] == {"max_depth": -1, "rr_depth": 5, "hide_emitters": False, "filter": "box"}
    assert {row["what"] for row in manifest["substitutions"]} == {
        "integrator", "pixel filter", "resolution", "sampler", "camera"}
    film_filter = next(row for row in manifest["substitutions"] if row["what"] == "pixel filter")
    assert film_filter["authored"] == "gaussian (radius 2 px, the film's default)"

    # Frame 0 matches Mitsuba's own path tracer on the unmodified XML.
    original = mi.load_file(str(root / "my_scene.xml"))
    expected = np.array(mi.render(original, spp=512, seed=3))[..., :3].mean()
    ours = clip.reference["radiance"][0].mean()
    assert abs(ours - expected) < 0.05 * expected, (ours, expected)


def test_missing_xml_names_file(tmp_path):
    entry = {"name": "gone", "xml": str(tmp_path / "nope.xml"), "frames": 1, "camera": {"path": "pan"}}
    with pytest.raises(CustomSceneError, match="nope.xml"):
        import_custom_scene(entry, "custom_gone", tmp_path / "out")
