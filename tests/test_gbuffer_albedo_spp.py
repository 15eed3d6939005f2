"""render.gbuffer_albedo_spp: the G-buffer albedo as the mean over K jittered primary rays (an antialiased albedo)
instead of the pixel-centre hit's; it changes only the noisy renders' digests, and its default none."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

import scenegen.integrator  # noqa: F401 -- registers mcdn_features
from scenegen.catalog import scene_ids
from scenegen.config import load_config, validate_config
from scenegen.digests import render_digest, scene_digest
from scenegen.render import RenderSettings, gbuffer_albedo_mean, split_channels

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {"default": REPO_ROOT / "config" / "config.yaml", "smoke": REPO_ROOT / "config" / "smoke.yaml"}
DARK, BRIGHT = 0.1, 0.9


def _checker_scene(sampler: dict):
    """An 8 x 8 pixel view filled by a diffuse square whose checkerboard (DARK / BRIGHT) has 16 x 16 checks per
    pixel: every pixel's footprint holds both in equal parts, so its mean albedo is (DARK + BRIGHT) / 2."""
    import mitsuba as mi

    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "mcdn_features", "mode": "gbuffer"},
        "sensor": {"type": "perspective", "fov": 20.0, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": sampler},
        "square": {"type": "rectangle",
                   "bsdf": {"type": "diffuse", "reflectance": {
                       "type": "checkerboard", "color0": DARK, "color1": BRIGHT,
                       "to_uv": mi.ScalarTransform4f().scale([91.0, 91.0, 1.0])}}},
    })


def test_the_mean_over_jittered_rays_is_the_footprint_albedo_the_centre_is_one_check() -> None:
    import mitsuba as mi

    from scenegen.integrator import GBUFFER_AOVS

    integrator = mi.load_dict({"type": "mcdn_features", "mode": "gbuffer"})
    centre_scene = _checker_scene({"type": "stratified", "sample_count": 1, "jitter": False})
    image = np.array(mi.render(centre_scene, spp=1, seed=0, integrator=integrator), np.float32)
    centre = split_channels(image, [("rgb", 3), *GBUFFER_AOVS])["albedo"]
    assert np.all(np.isclose(centre, DARK, atol=1e-6) | np.isclose(centre, BRIGHT, atol=1e-6))

    mean = gbuffer_albedo_mean(_checker_scene({"type": "independent", "sample_count": 1}), integrator,
                               spp=1024, seed=3)
    assert mean.shape == (3, 8, 8)
    # 1024 rays on a 50/50 footprint: binomial s.d. of the mean 0.8 * 0.016 = 0.0125 (plus the footprint's
    # own imbalance of at most one check row): 0.05 is four standard deviations.
    np.testing.assert_allclose(mean, (DARK + BRIGHT) / 2, atol=0.05)
    again = gbuffer_albedo_mean(_checker_scene({"type": "independent", "sample_count": 1}), integrator,
                                spp=1024, seed=3)
    np.testing.assert_array_equal(mean, again)            # deterministic for a seed


def test_render_settings_read_the_key() -> None:
    assert RenderSettings.from_config({}).gbuffer_albedo_spp == 1
    assert RenderSettings.from_config({"gbuffer_albedo_spp": 16}).gbuffer_albedo_spp == 16


def _digests(cfg: dict) -> dict[tuple[str, str], str]:
    out = {}
    for scene in scene_ids(cfg):
        out[(scene, "scene")] = scene_digest(cfg, scene)
        for kind in ("noisy", "reference"):
            out[(scene, kind)] = render_digest(cfg, scene, kind)
    return out


@pytest.mark.parametrize("name", CONFIGS)
def test_the_default_changes_no_digest_and_a_value_only_the_noisy_renders(name: str) -> None:
    default = load_config(CONFIGS[name])
    assert default["render"]["gbuffer_albedo_spp"] == 1
    absent = copy.deepcopy(default)
    del absent["render"]["gbuffer_albedo_spp"]
    assert _digests(absent) == _digests(default)
    antialiased = copy.deepcopy(default)
    antialiased["render"]["gbuffer_albedo_spp"] = 16
    antialiased = validate_config(antialiased)
    before, after = _digests(default), _digests(antialiased)
    changed = {key for key in before if before[key] != after[key]}
    surfaces = {scene for scene in scene_ids(default) if not scene.startswith("vol_")}
    assert changed == {(scene, "noisy") for scene in surfaces}
