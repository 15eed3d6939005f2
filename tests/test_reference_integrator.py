"""References rendered with Mitsuba's ``path`` (render.reference_integrator: path) on a generated scene: the
scene loader gives ``path`` the same depths, and its image is the feature integrator's in expectation."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.generate import generate_scene
from scenegen.render import NonFiniteCounter, RenderSettings, load_frame_scene, render_reference_frame

SETTINGS = RenderSettings(width=32, height=32, max_depth=8, rr_depth=5)
#: Every material kind the generator draws, an open scene (sky) and several objects.
SCENE_CFG = {
    "objects": [12, 12], "camera_paths": ["orbit"], "animated_light_prob": 0.0, "moving_objects_prob": 0.0,
    "camera_cut_prob": 0.0, "luminance_range": [0.05, 5.0], "open_scene_prob": 1.0,
}
BLOCK = 4


def _blocks(radiance: np.ndarray) -> np.ndarray:
    """(3, H, W) -> (H/B * W/B,) block means of Rec. 709 luminance."""
    lum = np.tensordot(np.array([0.2126, 0.7152, 0.0722]), radiance, axes=1)
    h, w = lum.shape
    return lum.reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3)).reshape(-1)


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("reference_integrator") / "scene"
    return generate_scene(SCENE_CFG, 2027, "train_000", out, n_frames=1), out


def _estimates(manifest: dict, scene_dir: Path, mode: str, n: int, spp: int, seed0: int) -> np.ndarray:
    """(n, blocks): independent ``spp``-sample reference estimates through render_reference_frame."""
    scene = load_frame_scene(manifest, scene_dir, 0, SETTINGS, mode=mode)
    out = []
    for k in range(n):
        ref = render_reference_frame(scene, spp=spp, batch_spp=spp // 2, counter=NonFiniteCounter(),
                                     seeds_half=([seed0 + 2 * k], [seed0 + 2 * k + 1]),
                                     features=mode == "samples")
        assert set(ref) >= {"radiance", "radiance_half0", "radiance_half1"}
        assert ("albedo" in ref) == (mode == "samples")
        out.append(_blocks(ref["radiance"]))
    return np.stack(out)


def test_path_references_agree_with_the_feature_integrator(generated: tuple[dict, Path]) -> None:
    manifest, scene_dir = generated
    n = 8
    path = _estimates(manifest, scene_dir, "path", n, 64, 100)
    ours = _estimates(manifest, scene_dir, "samples", n, 64, 900)
    se = np.sqrt(path.var(axis=0, ddof=1) / n + ours.var(axis=0, ddof=1) / n)
    z = (path.mean(axis=0) - ours.mean(axis=0)) / np.maximum(se, 1e-12)
    # Same estimator in expectation: z ~ Student-t (7 dof), E[z^2] = 1.4; a wrong depth or a missing
    # light (e.g. the loader not passing max_depth to path) shifts many blocks by several errors.
    assert np.mean(z ** 2) < 2.5, f"mean z^2 = {np.mean(z ** 2):.2f}, worst block z = {np.abs(z).max():.1f}"
    assert np.abs(z).max() < 6.0
    scene = load_frame_scene(manifest, scene_dir, 0, SETTINGS, mode="path")
    integrator = str(scene.integrator())
    assert "PathIntegrator" in integrator and "max_depth = 8" in integrator and "rr_depth = 5" in integrator, integrator
