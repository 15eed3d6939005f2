"""Per-sample albedo of every material kind against values computed from the material parameters.

Convention (OIDN's albedo input, see ``scenegen.integrator``): diffuse-type BSDFs give their base
colour, conductors ``specular_reflectance`` x Fresnel reflectance at normal incidence, dielectrics
their transmission tint; values in [0, 1] and independent of the view angle. The references below
are computed here from the parameters (Fresnel formula, 8-bit sRGB decoding), not by the renderer.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scenegen.geometry import export_ply, make_transform, quad_mesh, rotation_matrix
from scenegen.materials import METAL_IOR, draw_material
from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_sample_layers

COSINES = (1.0, 0.6, 0.3)  # cosine between the quad's normal and the view direction, per column
CELL_PX = 6  # pixels per grid cell (each cell is 2 x 2 m)
N_LAYERS = 2
DISTANCE = 100.0  # a far camera with a narrow field of view: nearly parallel rays


def _fresnel0(eta, k) -> np.ndarray:
    eta, k = np.asarray(eta, np.float64), np.asarray(k, np.float64)
    return ((eta - 1.0) ** 2 + k**2) / ((eta + 1.0) ** 2 + k**2)


def _srgb8_to_linear(value: np.ndarray) -> np.ndarray:
    c = np.asarray(value, np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _record(name: str, mat_type: str, params: dict, roughness: float, *, metallic: bool = False,
            transmissive: bool = False) -> dict:
    return {"name": name, "type": mat_type, "params": params, "roughness": roughness, "metallic": metallic,
            "transmissive": transmissive, "emissive": False, "texture": None}


def _material_cases(scene_dir: Path) -> list[tuple[dict, np.ndarray | None]]:
    """(manifest material record, expected albedo (3,) or None for the checker texture)."""
    rng = np.random.default_rng(7)
    cases: list[tuple[dict, np.ndarray | None]] = []

    entry, _ = draw_material(rng, "diffuse", "diffuse", "textures/unused.png", 0.0)
    cases.append((entry, np.array(entry["params"]["reflectance"]["value"])))

    # A textured diffuse material as the generator writes it, with a uniform texture (known colour).
    entry, _ = draw_material(rng, "diffuse_tex", "diffuse", "textures/uniform.png", 1.0)
    uniform = np.array([200, 90, 30], np.uint8)
    Image.fromarray(np.tile(uniform, (16, 16, 1))).save(scene_dir / "textures" / "uniform.png")
    cases.append((entry, _srgb8_to_linear(uniform)))

    entry, _ = draw_material(rng, "plastic", "roughplastic", "textures/unused.png", 0.0)
    entry["params"]["alpha"] = entry["roughness"] = 0.3
    cases.append((entry, np.array(entry["params"]["diffuse_reflectance"]["value"])))

    for metallic in (0.0, 1.0):
        entry, _ = draw_material(rng, f"principled_{metallic:g}", "principled", "textures/unused.png", 0.0)
        entry["params"]["metallic"] = metallic
        entry["metallic"] = metallic > 0.5
        cases.append((entry, np.array(entry["params"]["base_color"]["value"])))

    # Principled metal with a two-colour checker texture (nearest filtering): every sample is one colour.
    entry, _ = draw_material(rng, "principled_tex", "principled", "textures/checker.png", 1.0)
    entry["params"]["metallic"], entry["metallic"] = 1.0, True
    entry["params"]["base_color"]["filter_type"] = "nearest"
    checker = np.where((np.add.outer(np.arange(16), np.arange(16)) // 4 % 2)[..., None] == 0,
                       np.array([250, 220, 40], np.uint8), np.array([20, 60, 160], np.uint8)).astype(np.uint8)
    Image.fromarray(checker).save(scene_dir / "textures" / "checker.png")
    cases.append((entry, None))

    # A rough conductor exactly as the generator draws it (random metal), then one per table metal.
    entry, _ = draw_material(rng, "drawn_metal", "roughconductor", "textures/unused.png", 0.0)
    entry["params"]["alpha"] = entry["roughness"] = 0.3
    cases.append((entry, _fresnel0(entry["params"]["eta"]["value"], entry["params"]["k"]["value"])))
    for metal in ("gold", "silver", "copper", "aluminium", "chromium", "iron"):
        eta, k = METAL_IOR[metal]
        alpha = 0.15 if metal == "silver" else 0.5
        params = {"type": "roughconductor", "eta": _rgb(eta), "k": _rgb(k), "alpha": alpha,
                  "distribution": "ggx"}
        cases.append((_record(metal, "roughconductor", params, alpha, metallic=True), _fresnel0(eta, k)))
    tint = np.array([0.9, 0.5, 0.7])
    eta, k = METAL_IOR["copper"]
    params = {"type": "roughconductor", "eta": _rgb(eta), "k": _rgb(k), "alpha": 0.3,
              "specular_reflectance": _rgb(tint)}
    cases.append((_record("tinted_copper", "roughconductor", params, 0.3, metallic=True),
                  tint * _fresnel0(eta, k)))

    for name, tint in (("rough_glass", np.ones(3)), ("rough_tinted_glass", np.array([0.95, 0.7, 0.4]))):
        params = {"type": "roughdielectric", "int_ior": 1.5, "ext_ior": 1.000277, "alpha": 0.3,
                  "specular_transmittance": _rgb(tint)}
        cases.append((_record(name, "roughdielectric", params, 0.3, transmissive=True), tint))
    return cases


def _grid_manifest(scene_dir: Path, materials: list[dict]) -> dict:
    """One row of quads per material, one column per view cosine; camera on +z looking down -z."""
    rows, cols = len(materials), len(COSINES)
    shapes = []
    for row in range(rows):
        for col, cosine in enumerate(COSINES):
            # Width 2 / cos: every quad projects onto its 2 x 2 m cell.
            mesh = quad_mesh(np.zeros(3), np.array([1.0 / cosine, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]),
                             np.array([0.0, 0.0, 1.0]))
            path = f"meshes/quad_{row:02d}_{col}.ply"
            export_ply(mesh, scene_dir / path)
            rotation = rotation_matrix(np.array([0.0, 1.0, 0.0]), float(np.arccos(cosine)))
            centre = np.array([2.0 * col - (cols - 1), (rows - 1) - 2.0 * row, 0.0])
            shapes.append({"index": len(shapes), "name": path, "mesh": path, "material": row, "emitter": None,
                           "to_world": make_transform(rotation, centre).tolist(), "to_world_per_frame": None})
    fov_x = float(np.degrees(2.0 * np.arctan(cols / DISTANCE)))
    camera = {"origin": [0.0, 0.0, DISTANCE], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0]}
    return {"kind": "procedural", "shapes": shapes, "materials": materials,
            "camera": {"fov_x_deg": fov_x, "frames": [camera]},
            "emitters": [{"name": "sky", "type": "constant", "radiance": [1.0, 1.0, 1.0]}]}


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """Rendered sample layers of the material grid, its material cases and the grid shape."""
    scene_dir = tmp_path_factory.mktemp("albedo_grid")
    (scene_dir / "textures").mkdir()
    cases = _material_cases(scene_dir)
    manifest = _grid_manifest(scene_dir, [record for record, _ in cases])
    settings = RenderSettings(width=CELL_PX * len(COSINES), height=CELL_PX * len(cases), max_depth=4)
    scene = load_frame_scene(manifest, scene_dir, 0, settings)
    layers = render_sample_layers(scene, n_layers=N_LAYERS, n_radiance_only=0, seed=3,
                                  counter=NonFiniteCounter())
    return layers, cases


def _cell_samples(layers: dict, n_rows: int) -> dict[tuple[int, int], np.ndarray]:
    """{(row, col): (N, 3) albedo of the samples whose first hit lies inside that cell's quad}."""
    albedo = np.moveaxis(layers["albedo"], 1, -1).reshape(-1, 3)
    position = np.moveaxis(layers["position"], 1, -1).reshape(-1, 3)
    hit = layers["depth"].reshape(-1) > 0
    col_f = position[:, 0] + (len(COSINES) - 1) / 2.0 * 2.0
    row_f = (n_rows - 1) - position[:, 1]
    col, row = np.round(col_f / 2.0).astype(int), np.round(row_f / 2.0).astype(int)
    interior = hit & (np.abs(col_f - 2.0 * col) < 0.8) & (np.abs(row_f - 2.0 * row) < 0.8)
    return {(r, c): albedo[interior & (row == r) & (col == c)]
            for r in range(n_rows) for c in range(len(COSINES))}


def test_albedo_matches_material_table_at_every_view_angle(grid):
    layers, cases = grid
    low, high = float(layers["albedo"].min()), float(layers["albedo"].max())
    assert low >= 0.0 and high <= 1.0, f"albedo outside [0, 1]: [{low}, {high}]"
    cells = _cell_samples(layers, len(cases))
    for row, (record, expected) in enumerate(cases):
        for col, cosine in enumerate(COSINES):
            samples = cells[(row, col)]
            where = f"{record['name']} ({record['type']}) at view cosine {cosine}"
            assert len(samples) >= N_LAYERS * 4, f"{where}: only {len(samples)} samples hit the quad"
            if expected is None:
                continue
            np.testing.assert_allclose(samples, np.broadcast_to(expected, samples.shape), atol=2e-3,
                                       err_msg=where)


def test_texture_variation_is_kept(grid):
    """Checker-textured principled metal: each sample is one of the two texel colours, both appear."""
    layers, cases = grid
    row = next(i for i, (record, _) in enumerate(cases) if record["name"] == "principled_tex")
    colours = _srgb8_to_linear(np.array([[250, 220, 40], [20, 60, 160]]))
    for col, cosine in enumerate(COSINES):
        samples = _cell_samples(layers, len(cases))[(row, col)]
        distance = np.abs(samples[:, None, :] - colours[None]).max(axis=-1)  # (N, 2)
        assert np.all(distance.min(axis=1) < 2e-3), f"view cosine {cosine}: samples off both texel colours"
        nearest = distance.argmin(axis=1)
        assert (nearest == 0).any() and (nearest == 1).any(), f"view cosine {cosine}: one texel colour only"


def test_smooth_conductor_and_dielectric_pass_through(tmp_path):
    """Mirror and glass are specular: their samples take the albedo of the diffuse surface seen
    through or in them, not their own colour."""
    colour = np.array([0.25, 0.5, 0.125])
    eta, k = METAL_IOR["gold"]
    (tmp_path / "meshes").mkdir()
    materials = [
        _record("wall", "diffuse", {"type": "diffuse", "reflectance": _rgb(colour)}, 1.0),
        _record("mirror", "conductor", {"type": "conductor", "eta": _rgb(eta), "k": _rgb(k)}, 0.0,
                metallic=True),
        _record("glass", "dielectric", {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.000277,
                                        "specular_transmittance": _rgb([0.9, 0.9, 0.6])}, 0.0,
                transmissive=True),
    ]
    # Quads tilted 45 degrees about x: the mirror sends camera rays up to the ceiling, the glass
    # refracts them down onto the back wall and reflects them to the ceiling; both are ``colour``.
    tilt = rotation_matrix(np.array([1.0, 0.0, 0.0]), -np.pi / 4)

    def quad(center, half_u, half_v, normal):
        return quad_mesh(*(np.asarray(v, np.float64) for v in (center, half_u, half_v, normal)))

    small = quad([0, 0, 0], [1, 0, 0], [0, 1.5, 0], [0, 0, 1])
    layout = [("wall", quad([0, 0, -10], [40, 0, 0], [0, 40, 0], [0, 0, 1]), 0, np.eye(4)),
              ("ceiling", quad([0, 10, 0], [40, 0, 0], [0, 0, 40], [0, -1, 0]), 0, np.eye(4)),
              ("mirror", small, 1, make_transform(tilt, np.array([-1.0, 0.0, 0.0]))),
              ("glass", small, 2, make_transform(tilt, np.array([1.0, 0.0, 0.0])))]
    shapes = []
    for index, (name, mesh, material, to_world) in enumerate(layout):
        export_ply(mesh, tmp_path / "meshes" / f"{name}.ply")
        shapes.append({"index": index, "name": name, "mesh": f"meshes/{name}.ply", "material": material,
                       "emitter": None, "to_world": to_world.tolist(), "to_world_per_frame": None})
    manifest = {"kind": "procedural", "shapes": shapes, "materials": materials,
                "camera": {"fov_x_deg": float(np.degrees(2.0 * np.arctan(2.0 / DISTANCE))),
                           "frames": [{"origin": [0.0, 0.0, DISTANCE], "target": [0.0, 0.0, 0.0],
                                       "up": [0.0, 1.0, 0.0]}]},
                "emitters": [{"name": "sky", "type": "constant", "radiance": [1.0, 1.0, 1.0]}]}
    scene = load_frame_scene(manifest, tmp_path, 0, RenderSettings(width=16, height=8, max_depth=6))
    layers = render_sample_layers(scene, n_layers=4, n_radiance_only=0, seed=5, counter=NonFiniteCounter())
    specular = layers["flags"][:, 3] > 0.5  # (S, H, W): the camera ray's first hit was the mirror or glass
    assert specular[..., :8].sum() > 20 and specular[..., 8:].sum() > 20
    albedo = np.moveaxis(layers["albedo"], 1, -1)[specular]
    np.testing.assert_allclose(albedo, np.broadcast_to(colour, albedo.shape), atol=1e-4)


XML = """<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="{fov}"/>
    <transform name="to_world"><lookat origin="0, 0, {distance}" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <shape type="sphere"><point name="center" x="-3" y="1" z="0"/><float name="radius" value="0.9"/>
    <bsdf type="roughconductor"><float name="alpha" value="0.3"/>
      <rgb name="eta" value="{eta}"/><rgb name="k" value="{k}"/></bsdf></shape>
  <shape type="sphere"><point name="center" x="-1" y="1" z="0"/><float name="radius" value="0.9"/>
    <bsdf type="roughdielectric"><float name="alpha" value="0.3"/>
      <rgb name="specular_transmittance" value="0.9, 0.6, 0.3"/></bsdf></shape>
  <shape type="sphere"><point name="center" x="1" y="1" z="0"/><float name="radius" value="0.9"/>
    <bsdf type="principled"><rgb name="base_color" value="0.7, 0.3, 0.1"/><float name="metallic" value="1"/>
    </bsdf></shape>
  <shape type="sphere"><point name="center" x="3" y="1" z="0"/><float name="radius" value="0.9"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf></shape>
  <shape type="cube"><transform name="to_world"><scale value="0.6"/><rotate y="1" angle="30"/>
      <rotate x="1" angle="20"/><translate x="-3" y="-1"/></transform>
    <bsdf type="roughconductor"><float name="alpha" value="0.3"/>
      <rgb name="eta" value="{eta}"/><rgb name="k" value="{k}"/></bsdf></shape>
  <shape type="cube"><transform name="to_world"><scale value="0.6"/><rotate y="1" angle="30"/>
      <rotate x="1" angle="20"/><translate x="-1" y="-1"/></transform>
    <bsdf type="twosided"><bsdf type="roughconductor"><float name="alpha" value="0.3"/>
      <rgb name="eta" value="{eta}"/><rgb name="k" value="{k}"/></bsdf></bsdf></shape>
  <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
</scene>
"""


def _albedo_near(layers: dict, centres: list[tuple[float, float]], radius: float = 0.8) -> list[np.ndarray]:
    """Per centre (x, y): (N, 3) albedo of the samples whose first hit lies within ``radius`` in x-y."""
    albedo = np.moveaxis(layers["albedo"], 1, -1).reshape(-1, 3)
    position = np.moveaxis(layers["position"], 1, -1).reshape(-1, 3)
    hit = layers["depth"].reshape(-1) > 0
    low, high = float(albedo.min()), float(albedo.max())
    assert low >= 0.0 and high <= 1.0, f"albedo outside [0, 1]: [{low}, {high}]"
    return [albedo[hit & (np.hypot(position[:, 0] - cx, position[:, 1] - cy) < radius)] for cx, cy in centres]


def _check_shapes(layers: dict, expectations: list[tuple[tuple[float, float], np.ndarray, float]]) -> None:
    """Every shape's samples equal ``expected`` within ``atol`` and are constant over the view angles."""
    centres = [centre for centre, _, _ in expectations]
    for samples, (centre, expected, atol) in zip(_albedo_near(layers, centres), expectations):
        assert len(samples) > 20, f"shape at {centre}: only {len(samples)} samples"
        np.testing.assert_allclose(samples, np.broadcast_to(expected, samples.shape), atol=atol,
                                   err_msg=f"shape at {centre}")
        assert np.ptp(samples, axis=0).max() < 1e-4, f"albedo of the shape at {centre} varies with the view"


def test_xml_scene_shapes(tmp_path):
    """Bring-your-own XML scene through scenegen.custom.scene: analytic spheres and meshes get their albedo
    from their BSDF's parameters; a conductor wrapped in ``twosided`` (parameters not read) falls back
    to its directional albedo at normal incidence, F0 up to the masking loss (< 0.1 % at alpha 0.3)
    and the quadrature error."""
    from scenegen.custom.scene import import_custom_scene, load_custom_frame_scene

    eta, k = METAL_IOR["gold"]
    xml = tmp_path / "scene.xml"
    xml.write_text(XML.format(fov=np.degrees(2.0 * np.arctan(4.0 / DISTANCE)), distance=DISTANCE,
                              eta=", ".join(map(str, eta)), k=", ".join(map(str, k))))
    entry = {"name": "albedo", "xml": str(xml), "frames": 1, "camera": {"path": "dolly"}}
    manifest = import_custom_scene(entry, "custom_albedo", tmp_path / "scene")
    scene = load_custom_frame_scene(manifest, 0, width=64, height=32,
                                    integrator={"type": "mcdn_features", "max_depth": 4})
    layers = render_sample_layers(scene, n_layers=2, n_radiance_only=0, seed=9, counter=NonFiniteCounter())
    gold = _fresnel0(eta, k)
    _check_shapes(layers, [((-3, 1), gold, 2e-3), ((-1, 1), np.array([0.9, 0.6, 0.3]), 2e-3),
                           ((1, 1), np.array([0.7, 0.3, 0.1]), 2e-3), ((3, 1), np.array([0.2, 0.4, 0.6]), 2e-3),
                           ((-3, -1), gold, 2e-3), ((-1, -1), gold, 0.02)])


def test_fallback_without_attributes(tmp_path):
    """Shapes without face attributes (analytic shapes outside scenegen's loaders, shapegroup
    instances): diffuse-type BSDFs give their base colour, others their directional albedo at normal
    incidence; a blend BSDF mesh is told (albedo source 2) to use that too. References from the
    parameters: rough gold ~ F0; rough glass R + (1 - R) x tint (R of Mitsuba's default BK7 1.5046 /
    air 1.000277 interface); a 50/50 blend of diffuse and rough gold 0.5 x reflectance + 0.5 x F0.
    The quadrature picks lobes at 64 fixed points, so lobe mixtures are within about 1/64 of the
    weights."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import attach_face_attributes

    eta, k = METAL_IOR["gold"]
    gold = _fresnel0(eta, k)
    tint, base, diffuse = np.array([0.9, 0.6, 0.3]), np.array([0.7, 0.3, 0.1]), np.array([0.2, 0.4, 0.6])
    conductor = {"eta": _rgb(eta), "k": _rgb(k)}
    bsdfs = [
        {"type": "roughconductor", "alpha": 0.3, **conductor},
        {"type": "roughdielectric", "alpha": 0.3, "specular_transmittance": _rgb(tint)},
        {"type": "principled", "base_color": _rgb(base), "metallic": 1.0, "roughness": 0.5},
        {"type": "diffuse", "reflectance": _rgb(diffuse)},
    ]
    scene_dict = {
        "type": "scene", "integrator": {"type": "mcdn_features", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 9], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 48, "height": 32, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant"},
    }
    for i, bsdf in enumerate(bsdfs):
        scene_dict[f"sphere_{i}"] = {"type": "sphere", "center": [2.0 * i - 3.0, 1.0, 0.0], "radius": 0.9,
                                     "bsdf": bsdf}
    blend = mi.load_dict({"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([-1.0, -1.2, 0.0]),
                          "bsdf": {"type": "blendbsdf", "weight": 0.5,
                                   "bsdf_0": {"type": "diffuse", "reflectance": _rgb(diffuse)},
                                   "bsdf_1": {"type": "roughconductor", "alpha": 0.3, **conductor}}})
    attach_face_attributes(blend, {"index": 4}, None)
    scene_dict["blend"] = blend
    layers = render_sample_layers(mi.load_dict(scene_dict), n_layers=2, n_radiance_only=0, seed=4,
                                  counter=NonFiniteCounter())
    reflectance = ((1.5046 / 1.000277 - 1.0) / (1.5046 / 1.000277 + 1.0)) ** 2
    _check_shapes(layers, [((-3, 1), gold, 0.02), ((-1, 1), reflectance + (1.0 - reflectance) * tint, 0.015),
                           ((1, 1), base, 2e-3), ((3, 1), diffuse, 2e-3),
                           ((-1, -1.2), 0.5 * diffuse + 0.5 * gold, 0.02)])
