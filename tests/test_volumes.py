"""Heterogeneous media (scenegen.volumes.media): grid axes, transfer functions, shells, determinism, user fields,
and transfer-function edits of a loaded scene. Reference values are hand-computed or analytic."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
import trimesh

from scenegen.volumes.fields import load_field, noise_cloud, smoke_plume
from scenegen.volumes.mesh import shells_from_mesh
from scenegen.volumes.media import TransferFunction, medium_shape, update_medium

# extinction 0 -> 0, 0.5 -> 4, 1 -> 10; albedo red at 0 to blue at 1
TF_A = TransferFunction(extinction=[(0.0, 0.0), (0.5, 4.0), (1.0, 10.0)],
                        albedo=[(0.0, 1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 1.0)])
# extinction only defined on [0.2, 0.6] (constant beyond), constant albedo
TF_B = TransferFunction(extinction=[(0.2, 1.0), (0.6, 3.0)], albedo=[(0.0, 0.2, 0.4, 0.6)])


def _line(*values: float) -> np.ndarray:
    """A (1, 1, n) field along x."""
    return np.asarray(values, dtype=np.float32).reshape(1, 1, -1)


# ------------------------------------------------------------------------------------- transfer functions
def test_transfer_function_matches_hand_computed_values():
    sigma_t, albedo = TF_A.apply(_line(0.0, 0.25, 0.5, 0.75, 1.0))
    assert sigma_t.dtype == np.float32 and albedo.dtype == np.float32
    assert sigma_t.shape == (1, 1, 5) and albedo.shape == (1, 1, 5, 3)
    np.testing.assert_allclose(sigma_t[0, 0], [0.0, 2.0, 4.0, 7.0, 10.0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(albedo[0, 0], [[1.0, 0.0, 0.0], [0.75, 0.0, 0.25], [0.5, 0.0, 0.5],
                                              [0.25, 0.0, 0.75], [0.0, 0.0, 1.0]], rtol=0, atol=1e-6)
    sigma_b, albedo_b = TF_B.apply(_line(0.0, 0.4, 1.0))
    np.testing.assert_allclose(sigma_b[0, 0], [1.0, 2.0, 3.0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(albedo_b[0, 0], [[0.2, 0.4, 0.6]] * 3, rtol=0, atol=1e-6)


def test_transfer_function_edits():
    s = _line(0.0, 0.25, 0.5, 0.75, 1.0)
    # ramp slid right by 0.25: new(s) = old(s - 0.25); old is 0 below 0
    sigma, albedo = TF_A.shifted(0.25).apply(s)
    np.testing.assert_allclose(sigma[0, 0], [0.0, 0.0, 2.0, 4.0, 7.0], atol=1e-6)
    np.testing.assert_allclose(albedo[0, 0, 1], [0.75, 0.0, 0.25], atol=1e-6)       # colour did not move
    # slid left by 0.25: new(s) = old(s + 0.25); old is 10 above 1
    np.testing.assert_allclose(TF_A.shifted(-0.25).apply(s)[0][0, 0], [2.0, 4.0, 7.0, 10.0, 10.0], atol=1e-6)
    np.testing.assert_allclose(TF_A.shifted(0.25, albedo=True).apply(s)[1][0, 0, 2], [0.75, 0.0, 0.25], atol=1e-6)
    np.testing.assert_allclose(TF_A.scaled(2.0).apply(s)[0][0, 0], [0.0, 4.0, 8.0, 14.0, 20.0], atol=1e-6)
    # knots (1, 0, 0) -> (0.5, 0, 0) and (0, 0, 1) -> (0, 0, 1) (2 clipped to 1)
    np.testing.assert_allclose(TF_A.recoloured((0.5, 1.0, 2.0)).apply(_line(0.0, 0.5, 1.0))[1][0, 0],
                               [[0.5, 0.0, 0.0], [0.25, 0.0, 0.5], [0.0, 0.0, 1.0]], atol=1e-6)
    half_sigma, half_albedo = TF_A.interpolate(TF_B, 0.5).apply(_line(0.0, 0.4, 0.5, 1.0))
    # A(0.4) = 3.2, B(0.4) = 2; A(0.5) = 4, B(0.5) = 2.5
    np.testing.assert_allclose(half_sigma[0, 0], [0.5, 2.6, 3.25, 6.5], atol=1e-6)
    np.testing.assert_allclose(half_albedo[0, 0, 2], [0.35, 0.2, 0.55], atol=1e-6)
    assert TF_A.interpolate(TF_B, 0.0).apply(s)[0].tobytes() == TF_A.apply(s)[0].tobytes()


def test_transfer_function_manifest_round_trip_and_validation():
    text = json.dumps(TF_A.shifted(0.1).to_dict(), sort_keys=True)
    again = TransferFunction.from_dict(json.loads(text))
    assert again == TF_A.shifted(0.1)
    assert json.dumps(again.to_dict(), sort_keys=True) == text
    with pytest.raises(ValueError, match="keys"):
        TransferFunction.from_dict({**TF_A.to_dict(), "gamma": 2})
    bad = {
        "strictly increasing": dict(extinction=[(0.5, 1.0), (0.2, 2.0)], albedo=TF_A.albedo),
        r"\[0, 1\]": dict(extinction=[(0.0, 1.0), (1.5, 2.0)], albedo=TF_A.albedo),
        ">= 0": dict(extinction=[(0.0, -1.0)], albedo=TF_A.albedo),
        "colours": dict(extinction=TF_A.extinction, albedo=[(0.0, 1.2, 0.0, 0.0)]),
        "4-tuples": dict(extinction=TF_A.extinction, albedo=[(0.0, 1.0, 0.0)]),
        "finite": dict(extinction=[(0.0, float("nan"))], albedo=TF_A.albedo),
    }
    for message, kwargs in bad.items():
        with pytest.raises(ValueError, match=message):
            TransferFunction(**kwargs)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        TF_A.apply(_line(0.5, 1.5))


# ------------------------------------------------------------------------------------------ fields
def test_noise_fields_are_deterministic_and_bounded():
    cloud = noise_cloud(np.random.default_rng(7), 16)
    assert cloud.shape == (16, 16, 16) and cloud.dtype == np.float32
    assert cloud.tobytes() == noise_cloud(np.random.default_rng(7), 16).tobytes()
    assert cloud.tobytes() != noise_cloud(np.random.default_rng(8), 16).tobytes()
    assert cloud.min() == 0.0 and cloud.max() == 1.0
    # default margin 0.06: the outermost voxel layers (centres at 1/32 and 31/32) are empty on every axis
    for axis in range(3):
        assert np.take(cloud, [0, -1], axis=axis).max() == 0.0
    assert cloud[5:11, 5:11, 5:11].mean() > 0.2

    plume = smoke_plume(np.random.default_rng(7), (8, 12, 10), margin=0.05)
    assert plume.shape == (8, 12, 10) and plume.dtype == np.float32
    assert plume.tobytes() == smoke_plume(np.random.default_rng(7), (8, 12, 10), margin=0.05).tobytes()
    assert plume.tobytes() != smoke_plume(np.random.default_rng(8), (8, 12, 10), margin=0.05).tobytes()
    assert plume.min() == 0.0 and plume.max() == 1.0
    # y (up) = axis 1; first and last centres at 1/24 and 23/24 lie within the 0.05 margin: empty
    assert plume[:, 0].max() == 0.0 and plume[:, -1].max() == 0.0
    widths = (plume > 0.05).sum(axis=(0, 2))
    assert widths[8] > widths[2]                                        # the column widens as it rises
    with pytest.raises(TypeError, match="Generator"):
        noise_cloud(7, 16)
    with pytest.raises(ValueError, match="resolution"):
        noise_cloud(np.random.default_rng(0), (4, 4))


def _centred_sphere(radius: float) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    sphere.apply_translation((0.5, 0.5, 0.5))
    return sphere


def test_shells_of_a_sphere_deepen_inward():
    field = shells_from_mesh(_centred_sphere(0.4), 31, fit=False)
    assert field.shape == (31, 31, 31) and field.dtype == np.float32
    centres = (np.arange(31) + 0.5) / 31                       # voxel 15 is at 0.5, the sphere centre
    z, y, x = np.meshgrid(centres, centres, centres, indexing="ij")
    r = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2)
    assert field[r > 0.4].max() == 0.0                        # the icosphere lies inside its circumsphere
    assert field[r < 0.38].min() > 0.0                         # and contains 95 % of its radius
    assert field[15, 15, 15] == 1.0                            # deepest voxel: the centre
    line = field[15, 15, :16].astype(np.float64)               # along x from the box face to the centre
    inside = line > 0.0
    assert not inside[:3].any() and inside[3:].all()           # |x - 0.5| = 0.403 at i = 2, 0.371 at i = 3
    assert np.all(np.diff(line[3:]) > 0.0)                     # strictly deeper towards the centre
    # analytic sphere depth (0.4 - r) / 0.4, up to the facets of the icosphere (sagitta ~0.01 of 0.4)
    np.testing.assert_allclose(line[3:], (0.4 - np.abs(centres[3:16] - 0.5)) / 0.4, atol=0.04)
    np.testing.assert_allclose(field[15, 15, ::-1], field[15, 15, :], atol=1e-6)   # x -> 1 - x symmetry

    layered = shells_from_mesh(_centred_sphere(0.4), 31, layers=3, fit=False)
    np.testing.assert_allclose(np.unique(layered), [0.0, 1 / 3, 2 / 3, 1.0], atol=1e-7)
    assert layered[15, 15, 3] == np.float32(1 / 3) and layered[15, 15, 15] == 1.0   # skin outside, bone inside
    # fit=True centres the mesh and scales its extent to 1 - 2 * margin = 0.9 whatever its units
    big = trimesh.creation.icosphere(subdivisions=2, radius=7.0)
    big.apply_translation((3.0, -2.0, 10.0))
    np.testing.assert_allclose(shells_from_mesh(big, 31), shells_from_mesh(_centred_sphere(0.45), 31, fit=False),
                               atol=1e-5)


def test_shells_box_rows_through_projected_edges():
    """A fitted box spans [0.05, 0.95]^3; rows with y == z run exactly along the diagonals of its x faces."""
    field = shells_from_mesh(trimesh.creation.box((2.0, 2.0, 2.0)), 20)
    centres = (np.arange(20) + 0.5) / 20
    inside_1d = (centres > 0.05) & (centres < 0.95)
    expected = inside_1d[:, None, None] & inside_1d[None, :, None] & inside_1d[None, None, :]
    np.testing.assert_array_equal(field > 0.0, expected)


def test_shells_reject_open_meshes():
    sphere = _centred_sphere(0.4)
    open_mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    with pytest.raises(ValueError, match="watertight"):
        shells_from_mesh(open_mesh, 8, fit=False)


def test_load_field(tmp_path):
    path = tmp_path / "ct.npy"
    np.save(path, np.array([[[2.0, 4.0], [6.0, 10.0]]]))      # (1, 2, 2) [z, y, x]
    field = load_field(path)
    assert field.dtype == np.float32 and field.shape == (1, 2, 2)
    np.testing.assert_allclose(field[0], [[0.0, 0.25], [0.5, 1.0]], atol=1e-7)

    flat = tmp_path / "slice.npy"
    np.save(flat, np.ones((4, 4)))
    with pytest.raises(ValueError, match=re.escape(str(flat))):
        load_field(flat)
    holes = tmp_path / "holes.npy"
    np.save(holes, np.array([[[0.0, np.nan], [1.0, 2.0]]]))
    with pytest.raises(ValueError, match=re.escape(str(holes))):
        load_field(holes)
    missing = tmp_path / "missing.npy"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))):
        load_field(missing)


# ------------------------------------------------------------------------------------------ Mitsuba
def test_grid_axes_survive_mitsuba():
    """Voxel [z=1, y=2, x=3] of a 4x5x6 grid: flat index 1*30 + 2*6 + 3 = 45, and in a box from (0, 1, 2)
    to (6, 6, 6) (1-unit voxels) its centre is at world (0 + 3.5, 1 + 2.5, 2 + 1.5)."""
    mi = pytest.importorskip("mitsuba")
    import drjit as dr

    sigma_t = np.zeros((4, 5, 6), np.float32)
    sigma_t[1, 2, 3] = 2.0
    albedo = np.full((4, 5, 6, 3), 0.5, np.float32)
    albedo[1, 2, 3] = (0.1, 0.2, 0.3)
    shape = mi.load_dict(medium_shape(sigma_t, albedo, (0.0, 1.0, 2.0), (6.0, 6.0, 6.0)))
    params = mi.traverse(shape)
    data = np.array(params["interior_medium.sigma_t.data"])
    assert data.shape == (4, 5, 6, 1)
    assert int(np.argmax(data.ravel())) == 45 and data.ravel()[45] == 2.0
    assert np.array(params["interior_medium.albedo.data"]).reshape(-1, 3)[45].tolist() == pytest.approx([0.1, 0.2, 0.3])

    medium = shape.interior_medium()

    def coefficients(x: float, y: float, z: float) -> tuple[np.ndarray, np.ndarray]:
        mei = dr.zeros(mi.MediumInteraction3f)
        mei.p = mi.Point3f(x, y, z)
        sigma_s, _, sigma_t_rgb = medium.get_scattering_coefficients(mei, True)
        return np.array(sigma_s).ravel(), np.array(sigma_t_rgb).ravel()

    sigma_s, extinction = coefficients(3.5, 3.5, 3.5)
    np.testing.assert_allclose(extinction, [2.0, 2.0, 2.0], atol=1e-5)
    np.testing.assert_allclose(sigma_s, [0.2, 0.4, 0.6], atol=1e-5)                 # albedo x sigma_t
    np.testing.assert_allclose(coefficients(1.5, 3.5, 5.5)[1], [0.0, 0.0, 0.0], atol=1e-6)   # [z, y, x] swapped


def _volume_scene(sigma_t: np.ndarray, albedo: np.ndarray, scale: float = 1.0) -> dict:
    import mitsuba as mi

    return {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": 8},
        "sensor": {
            "type": "perspective", "fov": 45, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0.0, 0.3, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": 16},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.05, 0.06]}},
        "sun": {"type": "point", "position": [2.0, 3.0, 2.0],
                "intensity": {"type": "rgb", "value": [20.0, 19.0, 17.0]}},
        "cloud": medium_shape(sigma_t, albedo, (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), scale=scale),
    }


def test_transfer_function_edit_without_rebuilding():
    mi = pytest.importorskip("mitsuba")

    field = noise_cloud(np.random.default_rng(3), 12)
    tf = TransferFunction(extinction=[(0.0, 0.0), (0.1, 0.0), (1.0, 20.0)],
                          albedo=[(0.0, 0.9, 0.9, 0.9), (1.0, 0.6, 0.7, 0.9)])
    sigma_t, albedo = tf.apply(field)
    doubled, _ = tf.scaled(2.0).apply(field)

    scene = mi.load_dict(_volume_scene(sigma_t, albedo))
    before = np.array(mi.render(scene, seed=11))
    assert update_medium(scene, doubled, albedo) == "cloud.interior_medium"
    np.testing.assert_array_equal(np.array(mi.traverse(scene)["cloud.interior_medium.sigma_t.data"])[..., 0], doubled)
    edited = np.array(mi.render(scene, seed=11))
    fresh = np.array(mi.render(mi.load_dict(_volume_scene(doubled, albedo)), seed=11))

    assert np.all(np.isfinite(edited)) and before.tobytes() != edited.tobytes()
    assert edited.tobytes() == fresh.tobytes()                 # bit-identical to a rebuilt scene

    # The same doubling through the medium's scale (x2 is exact in float).
    update_medium(scene, sigma_t, None, scale=2.0)
    assert np.array(mi.render(scene, seed=11)).tobytes() == fresh.tobytes()

    with pytest.raises(ValueError, match="does not match"):
        update_medium(scene, sigma_t[:-1], None)
    bare = mi.load_dict({"type": "scene", "sky": {"type": "constant"}})
    with pytest.raises(KeyError, match="sigma_t"):
        update_medium(bare, sigma_t, albedo)
