"""The volumetric feature integrator (``mcdn_volpath_features``) against Mitsuba's own ``volpath``, and
its per-sample AOVs against analytic values.

Statistics as in ``tests/test_render.py``: per-block means of independent renders (distinct seeds) of
both integrators, z = (mean_ours - mean_ref) / sqrt(var_ours / n + var_ref / n) per block, and
mean z^2 < 2.5, max |z| < 6. Here the blocks are per RGB channel (the albedo is coloured) and there
are 16 passes per integrator (z ~ Student-t with 15 dof, E[z^2] = 1.15), which keeps the false-alarm
rate of the max |z| bound low over 3 x 36 blocks; the bounds themselves are the project's.
"""
from __future__ import annotations

import numpy as np
import pytest

import scenegen.volumes.integrator  # noqa: F401 -- registers mcdn_volpath_features
from scenegen.volumes.integrator import VOLUME_AOVS

SIZE = 24
BLOCK = 4
N_PASSES = 16
CAMERA = (0.0, 1.2, 3.0)
#: Mitsuba's perspective rays start on the near-clip plane: the centre ray at this distance from the camera.
NEAR_CLIP = 0.01
FOG_SIGMA_T = 0.15
SLAB_SIGMA_T = 2.0
SLAB_THICKNESS = 0.5


def _blob(n: int = 8) -> np.ndarray:
    """(n, n, n, 1) float32 Gaussian density blob, indexed [z, y, x] like Mitsuba's grids."""
    c = (np.arange(n) + 0.5) / n
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    r2 = (x - 0.5) ** 2 + (y - 0.45) ** 2 + (z - 0.55) ** 2
    return np.exp(-r2 / (2 * 0.18 ** 2)).astype(np.float32)[..., None]


def _sensor(target, medium=None) -> dict:
    import mitsuba as mi

    sensor = {"type": "perspective", "fov": 45, "near_clip": NEAR_CLIP,
              "to_world": mi.ScalarTransform4f().look_at(origin=list(CAMERA), target=list(target), up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"},
                       "pixel_format": "rgb"},
              "sampler": {"type": "independent"}}
    if medium is not None:
        sensor["medium"] = medium
    return sensor


def cloud_scene(*, max_depth: int = 8, fog: bool = False, target=(0.0, 0.5, 0.0)):
    """A heterogeneous blob (8^3 grid, grey extinction, coloured albedo, isotropic phase) in a null-BSDF
    cube over a diffuse floor, lit by a point light and a constant environment. ``fog``: everything,
    camera included, sits in a homogeneous fog box with coloured albedo."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    fog_medium = mi.load_dict({"type": "homogeneous", "sigma_t": FOG_SIGMA_T,
                               "albedo": {"type": "rgb", "value": [0.6, 0.75, 0.9]},
                               "phase": {"type": "isotropic"}}) if fog else None
    cloud = {"type": "cube", "to_world": T().translate([0, 0.6, 0]).scale(0.5), "bsdf": {"type": "null"},
             "interior": {"type": "heterogeneous", "scale": 6.0,
                          "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(_blob()),
                                      "to_world": T().translate([-0.5, 0.1, -0.5])},
                          "albedo": {"type": "rgb", "value": [0.9, 0.6, 0.3]},
                          "phase": {"type": "isotropic"}}}
    scene = {"type": "scene",
             "integrator": {"type": "mcdn_volpath_features", "max_depth": max_depth},
             "sensor": _sensor(target, fog_medium),
             "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
             "cloud": cloud,
             "light": {"type": "point", "position": [1.0, 2.5, 1.0], "intensity": {"type": "rgb", "value": [6, 6, 6]}},
             "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.2, 0.2, 0.25]}}}
    if fog:
        cloud["exterior"] = fog_medium
        scene["fog"] = {"type": "cube", "to_world": T().translate([0, 1, 0]).scale(4), "bsdf": {"type": "null"},
                        "interior": fog_medium}
    return mi.load_dict(scene)


def slab_scene(medium: dict):
    """Camera looking down -z through a 0.5-thick null-BSDF slab (z in [-0.25, 0.25]) filled with
    ``medium`` at a diffuse wall at z = -1."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "mcdn_volpath_features", "max_depth": 8},
        "sensor": {**_sensor((0.0, 0.0, 0.0)),
                   "to_world": T().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0])},
        "slab": {"type": "cube", "to_world": T().scale([2, 2, SLAB_THICKNESS / 2]), "bsdf": {"type": "null"},
                 "interior": medium},
        "wall": {"type": "rectangle", "to_world": T().translate([0, 0, -1]).scale(3),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.4, 0.5]}}},
        "env": {"type": "constant", "radiance": 1.0},
    })


def _blocks(image: np.ndarray) -> np.ndarray:
    """(H, W, >=3) -> (3 * H/B * W/B,) per-channel RGB block means."""
    rgb = image[..., :3]
    h, w, _ = rgb.shape
    return rgb.reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK, 3).mean(axis=(1, 3)).reshape(-1)


def _passes(scene, integrator, *, spp: int, seed0: int, n: int = N_PASSES) -> np.ndarray:
    """(n, blocks): block means of ``n`` independent ``spp``-sample renders (integrator None: the scene's)."""
    import mitsuba as mi

    kwargs = {} if integrator is None else {"integrator": integrator}
    return np.stack([_blocks(np.array(mi.render(scene, spp=spp, seed=seed0 + k, **kwargs)))
                     for k in range(n)])


def _z(ours: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-block z of the difference of means. Blocks that see only the constant environment are noise
    free (variance 0 up to float rounding) and differ between the integrators by float32 rounding
    (0.20000003 vs 0.2000002): the standard error has a floor of 1e-5 x the block mean, far below the
    Monte Carlo error of every noisy block (~1e-3 relative)."""
    ours, ref = ours.astype(np.float64), ref.astype(np.float64)
    se = np.sqrt(ours.var(axis=0, ddof=1) / len(ours) + ref.var(axis=0, ddof=1) / len(ref))
    floor = 1e-5 * np.maximum(np.abs(ref.mean(axis=0)), 1e-7)
    return (ours.mean(axis=0) - ref.mean(axis=0)) / np.maximum(se, floor)


def _assert_agree(z: np.ndarray) -> None:
    # Under unbiasedness z ~ Student-t (15 dof) per block: E[z^2] = 1.15; a bias of a few standard
    # errors in any region pushes the mean far above 2.5.
    assert np.mean(z ** 2) < 2.5, f"mean z^2 = {np.mean(z ** 2):.2f}, worst block z = {np.abs(z).max():.1f}"
    assert np.abs(z).max() < 6.0, f"worst block z = {np.abs(z).max():.1f}"


def _volpath(max_depth: int = 8):
    import mitsuba as mi

    return mi.load_dict({"type": "volpath", "max_depth": max_depth})


@pytest.fixture(scope="module")
def cloud():
    return cloud_scene()


@pytest.fixture(scope="module")
def volpath_passes(cloud) -> np.ndarray:
    return _passes(cloud, _volpath(8), spp=256, seed0=5000)


def test_heterogeneous_cloud_mean_matches_volpath(cloud, volpath_passes) -> None:
    ours = _passes(cloud, None, spp=256, seed0=1000)
    z = _z(ours, volpath_passes)
    print(f"cloud: mean z^2 = {np.mean(z ** 2):.2f}, max |z| = {np.abs(z).max():.2f}")
    _assert_agree(z)


def test_comparison_rejects_a_truncated_path(cloud, volpath_passes) -> None:
    """The same test has power: direct visibility only (max_depth 1), single scattering plus direct
    surface light (max_depth 2) and paths cut at 4 vertices all differ from volpath at max_depth 8 by
    many standard errors (measured mean z^2: ~2e5, ~700, ~20; an unbiased comparison gives ~1)."""
    for max_depth, bound in ((1, 100.0), (2, 10.0), (4, 5.0)):
        ours = _passes(cloud_scene(max_depth=max_depth), None, spp=128, seed0=2000)
        z = _z(ours, volpath_passes)
        print(f"max_depth {max_depth} vs 8: mean z^2 = {np.mean(z ** 2):.1f}, max |z| = {np.abs(z).max():.1f}")
        assert np.mean(z ** 2) > bound


@pytest.mark.slow
def test_camera_inside_fog_matches_volpath() -> None:
    """Camera, cloud, floor and light inside a homogeneous fog box (sensor medium): the integrator starts
    in the sensor's medium and crosses fog/cloud/fog boundaries as volpath does."""
    scene = cloud_scene(fog=True)
    ours = _passes(scene, None, spp=128, seed0=3000)
    ref = _passes(scene, _volpath(8), spp=128, seed0=7000)
    z = _z(ours, ref)
    print(f"fog: mean z^2 = {np.mean(z ** 2):.2f}, max |z| = {np.abs(z).max():.2f}")
    _assert_agree(z)


# ----------------------------------------------------------------------------------- per-sample AOVs
def _per_sample(scene, n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` samples of the centre ray (film position (0.5, 0.5), no jitter) through the scene's integrator,
    started in the sensor's medium. Returns {"radiance": (n, 3), aov name: (n, channels)}."""
    import drjit as dr
    import mitsuba as mi

    sensor = scene.sensors()[0]
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    centre = mi.Point2f(dr.full(mi.Float, 0.5, n), dr.full(mi.Float, 0.5, n))
    ray, _ = sensor.sample_ray(0.0, 0.5, centre, mi.Point2f(0.5))
    L, _, aovs = scene.integrator().sample(scene, sampler, ray, sensor.get_medium(), mi.Bool(True))
    dr.eval(L, aovs)
    values = np.stack([np.asarray(v, dtype=np.float64) for v in aovs], axis=-1)
    out, start = {"radiance": np.asarray(L, dtype=np.float64).T}, 0
    for name, size in VOLUME_AOVS:
        out[name] = values[:, start:start + size]
        start += size
    return out


def _assert_mean_close(values: np.ndarray, expected: float, what: str) -> None:
    se = values.std(ddof=1) / np.sqrt(len(values))
    assert abs(values.mean() - expected) < 4.0 * se + 1e-6, \
        f"{what}: {values.mean():.4f} vs {expected:.4f} (se {se:.4f})"


def test_aovs_on_a_ray_into_the_cloud(cloud) -> None:
    s = _per_sample(cloud, 8192, seed=11)
    flag, tr = s["medium"][:, 0], s["transmittance"][:, 0]
    assert set(np.unique(flag)) <= {0.0, 1.0}
    assert flag.mean() > 0.5
    medium_event = flag == 1.0
    assert np.all(s["sigma_t"][medium_event, 0] > 0) and np.all(s["sigma_t"][~medium_event, 0] == 0)
    np.testing.assert_allclose(s["albedo"][medium_event], np.tile([0.9, 0.6, 0.3], (medium_event.sum(), 1)),
                               rtol=1e-5)
    # Medium events lie inside the cloud's box, at the distance of their position from the camera.
    pos = s["position"][medium_event]
    assert np.all(np.abs(pos[:, [0, 2]]) <= 0.5 + 1e-4)
    assert np.all((pos[:, 1] >= 0.1 - 1e-4) & (pos[:, 1] <= 1.1 + 1e-4))
    # depth is measured from the ray origin on the near-clip plane (as the surface integrator's depth).
    np.testing.assert_allclose(s["depth"][medium_event, 0] + NEAR_CLIP, np.linalg.norm(pos - CAMERA, axis=1),
                               rtol=1e-5)
    # Ratio-tracked camera transmittance: in [0, 1], mean = P(no real collision) = 1 - E[flag] (paired).
    assert np.all((tr >= 0.0) & (tr <= 1.0))
    _assert_mean_close(flag - (1.0 - tr), 0.0, "flag - (1 - transmittance)")
    assert tr.std() < flag.std()  # ratio tracking is the lower-variance estimate of the same quantity
    assert np.all(np.isfinite(s["radiance"]))


@pytest.mark.parametrize("fog", [False, True], ids=["clear", "fog"])
def test_aovs_on_a_ray_that_sees_only_the_floor(fog: bool) -> None:
    target = np.array([1.2, 0.0, 1.5])  # the centre ray misses the cloud's box
    distance = float(np.linalg.norm(target - CAMERA)) - NEAR_CLIP  # from the ray origin on the near plane
    s = _per_sample(cloud_scene(fog=fog, target=tuple(target)), 4096, seed=12)
    flag, tr = s["medium"][:, 0], s["transmittance"][:, 0]
    floor = flag == 0.0
    np.testing.assert_allclose(s["depth"][floor, 0], distance, rtol=1e-4)
    np.testing.assert_allclose(s["position"][floor], np.tile(target, (floor.sum(), 1)), atol=1e-4)
    np.testing.assert_allclose(s["albedo"][floor], 0.5, rtol=1e-5)
    assert np.all(s["sigma_t"][floor] == 0)
    if not fog:
        assert floor.all() and np.all(tr == 1.0)
    else:
        # Homogeneous fog from the camera (sensor medium) to the floor: analytic transmittance, and the
        # fog events happen before the floor with probability 1 - T.
        expected = np.exp(-FOG_SIGMA_T * distance)
        np.testing.assert_allclose(tr, expected, rtol=1e-3)
        _assert_mean_close(flag, 1.0 - expected, "fog event rate")
        assert np.all(s["depth"][~floor, 0] < distance) and np.allclose(s["sigma_t"][~floor], FOG_SIGMA_T)


def test_transmittance_aov_through_slabs() -> None:
    """Analytic slab transmittance exp(-sigma_t * thickness): exact for a homogeneous slab (analytic
    tracking), in the mean for a heterogeneous one (ratio tracking with majorant 2 sigma_t)."""
    import mitsuba as mi

    expected = np.exp(-SLAB_SIGMA_T * SLAB_THICKNESS)
    homogeneous = {"type": "homogeneous", "sigma_t": SLAB_SIGMA_T, "albedo": 0.8}
    s = _per_sample(slab_scene(homogeneous), 2048, seed=13)
    np.testing.assert_allclose(s["transmittance"][:, 0], expected, rtol=1e-3)
    _assert_mean_close(s["medium"][:, 0], 1.0 - expected, "homogeneous slab event rate")

    # Density 0.5 everywhere except one corner voxel of 1: the majorant is twice the extinction the centre
    # ray sees, so ratio tracking multiplies 1/2 per tentative collision.
    grid = np.full((8, 8, 8, 1), 0.5, np.float32)
    grid[0, 0, 0, 0] = 1.0
    box = mi.ScalarTransform4f().translate([-2, -2, -SLAB_THICKNESS / 2]).scale([4, 4, SLAB_THICKNESS])
    heterogeneous = {"type": "heterogeneous", "scale": 2 * SLAB_SIGMA_T, "albedo": 0.8,
                     "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(grid), "to_world": box}}
    s = _per_sample(slab_scene(heterogeneous), 8192, seed=14)
    tr, flag = s["transmittance"][:, 0], s["medium"][:, 0]
    assert len(np.unique(tr)) > 2  # genuine ratio tracking, not a 0/1 estimate
    assert np.all((tr >= 0.0) & (tr <= 1.0))
    _assert_mean_close(tr, expected, "heterogeneous slab transmittance")
    _assert_mean_close(flag, 1.0 - expected, "heterogeneous slab event rate")
    np.testing.assert_allclose(s["sigma_t"][flag == 1.0], SLAB_SIGMA_T, rtol=1e-4)


def test_same_seed_gives_the_same_image(cloud) -> None:
    import mitsuba as mi

    a = np.array(mi.render(cloud, spp=8, seed=42))
    b = np.array(mi.render(cloud, spp=8, seed=42))
    c = np.array(mi.render(cloud, spp=8, seed=43))
    assert a.shape == (SIZE, SIZE, 3 + sum(size for _, size in VOLUME_AOVS))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[..., :3], c[..., :3])
