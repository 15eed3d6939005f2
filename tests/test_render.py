"""The feature integrator against Mitsuba's own ``path`` integrator, and per-sample buffer sanity."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import scenegen.integrator  # noqa: F401 -- registers mcdn_features
from scenegen.render import NonFiniteCounter, render_sample_layers
from tests.conftest import build_test_scene_dict, load_with_attributes

MAX_DEPTH = 6
BLOCK = 4


def _luminance_blocks(image: np.ndarray) -> np.ndarray:
    """(H, W, >=3) -> (H/B * W/B,) block means of Rec. 709 luminance."""
    lum = image[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    h, w = lum.shape
    return lum.reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3)).reshape(-1)


def _batches(scene, integrator, *, n_batches: int, spp: int, seed0: int) -> np.ndarray:
    """(n_batches, blocks) luminance block means of independent ``spp``-sample estimates; with
    ``integrator=None`` the estimate is the mean of the project's per-sample layers."""
    import mitsuba as mi

    def estimate(seed: int) -> np.ndarray:
        if integrator is None:
            layers = render_sample_layers(scene, n_layers=spp, n_radiance_only=0, seed=seed,
                                          counter=NonFiniteCounter())
            return np.moveaxis(layers["radiance"].mean(axis=0), 0, -1)
        return np.array(mi.render(scene, spp=spp, seed=seed, integrator=integrator))

    return np.stack([_luminance_blocks(estimate(seed0 + k)) for k in range(n_batches)])


@pytest.fixture(scope="module")
def scene(test_scene_dir):
    scene_dict, records = build_test_scene_dict(test_scene_dir / "unbiased",
                                                integrator={"type": "mcdn_features", "max_depth": MAX_DEPTH})
    return load_with_attributes(scene_dict, records)


@pytest.mark.slow
def test_mean_converges_to_mitsuba_path(scene):
    """Block means of the per-sample layers agree with ``path`` within their joint standard error,
    and the error against a high-spp ``path`` image falls as the sample count grows."""
    import mitsuba as mi

    ours_integrator = None  # the per-sample layers rendered by render_sample_layers
    path_integrator = mi.load_dict({"type": "path", "max_depth": MAX_DEPTH})
    n_batches = 8
    ours = _batches(scene, ours_integrator, n_batches=n_batches, spp=128, seed0=1000)
    ref = _batches(scene, path_integrator, n_batches=n_batches, spp=512, seed0=5000)
    se = np.sqrt(ours.var(axis=0, ddof=1) / n_batches + ref.var(axis=0, ddof=1) / n_batches)
    z = (ours.mean(axis=0) - ref.mean(axis=0)) / np.maximum(se, 1e-12)
    # Under unbiasedness z is ~Student-t with 7 dof per block: E[z^2] = 1.4; a bias of a few standard
    # errors in any region pushes the mean far above that.
    assert np.mean(z ** 2) < 2.5, f"mean z^2 = {np.mean(z ** 2):.2f}, worst block z = {np.abs(z).max():.1f}"
    assert np.abs(z).max() < 6.0

    reference = ref.mean(axis=0)
    rmse = []
    for spp in (4, 16, 64):
        mean_spp = _batches(scene, ours_integrator, n_batches=1, spp=spp, seed0=9000 + spp)[0]
        rmse.append(float(np.sqrt(np.mean((mean_spp - reference) ** 2))))
    # Monte Carlo error falls as 1/sqrt(N): a factor 2 per 4x samples; demand at least 1.4 per step.
    assert rmse[0] > 1.4 * rmse[1] > 1.4 ** 2 * rmse[2], rmse


def test_sample_layers_buffers(scene):
    counter = NonFiniteCounter()
    layers = render_sample_layers(scene, n_layers=4, n_radiance_only=2, seed=100,
                                  counter=counter)
    assert layers["radiance"].shape == (6, 3, 32, 32)
    for name, channels in (("diffuse", 3), ("specular", 3), ("albedo", 3), ("normal", 3), ("depth", 1),
                           ("roughness", 1), ("flags", 4), ("position", 3)):
        assert layers[name].shape == (4, channels, 32, 32), name
    np.testing.assert_allclose(layers["diffuse"] + layers["specular"], layers["radiance"][:4], atol=1e-5)
    flags = layers["flags"]
    assert set(np.unique(flags)) <= {0.0, 1.0}
    # The scene has a conductor (metallic), glass (transmissive) and a visible emitter panel.
    assert flags[:, 1].any() and flags[:, 2].any()
    normal_length = np.linalg.norm(layers["normal"], axis=1)
    hit = layers["depth"][:, 0] > 0
    np.testing.assert_allclose(normal_length[hit], 1.0, atol=2e-3)
    assert np.all(layers["depth"] >= 0) and np.all(layers["roughness"] >= 0)
    assert sum(counter.counts.values()) == 0


def _ratio_of_sums(numerator: np.ndarray, denominator: np.ndarray) -> tuple[float, float]:
    """sum(numerator) / sum(denominator) over pixels and its delta-method standard error, treating the
    pixels as independent: SE = sqrt(sum (a - r b)^2) / sum b."""
    ratio = float(numerator.sum() / denominator.sum())
    return ratio, float(np.sqrt(((numerator - ratio * denominator) ** 2).sum()) / denominator.sum())


def test_radiance_layers_are_deterministic_and_independent(scene):
    """Same seed, same layers; and the layers of a frame behave as independent samples of each pixel:
    adjacent layers are uncorrelated, the variance of the mean of k layers falls as 1/k, and the means of
    two renders with neighbouring seeds differ by exactly their own noise (nothing shared between them)."""
    n_layers = 64

    def render(seed: int) -> dict[str, np.ndarray]:
        return render_sample_layers(scene, n_layers=n_layers, n_radiance_only=0, seed=seed,
                                    counter=NonFiniteCounter())

    a, b, other = render(7), render(7), render(8)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    rec709 = np.array([0.2126, 0.7152, 0.0722])
    x = np.einsum("c,kcp->kp", rec709, a["radiance"].reshape(n_layers, 3, -1))       # (layers, pixels)
    y = np.einsum("c,kcp->kp", rec709, other["radiance"].reshape(n_layers, 3, -1))
    var = x.var(axis=0, ddof=1)
    noisy = var > 0
    n_pixels = int(noisy.sum())
    assert n_pixels > 0.9 * x.shape[1]

    # 1. Adjacent layers are uncorrelated. Per pixel, z_k = (x_k - mean) / std over the layers; for
    #    independent (exchangeable) layers E[z_i z_j] = -1/K exactly (sum_k z_k = 0, sum_k z_k^2 = K - 1),
    #    and mean_p z_i z_j has standard deviation about 1/sqrt(N) (|z_i z_j| ~ 1). A layer repeated or
    #    leaking into the next gives mean_p z_i z_j near its correlation instead.
    z = (x[:, noisy] - x[:, noisy].mean(axis=0)) / np.sqrt(var[noisy])
    adjacent = (z[:-1] * z[1:]).mean(axis=1) + 1.0 / n_layers
    worst = int(np.abs(adjacent).argmax())
    assert abs(adjacent[worst]) < 4.0 / np.sqrt(n_pixels), \
        f"layers {worst}, {worst + 1}: r + 1/K = {adjacent[worst]:.3f}"

    # 2. The variance of the mean of k layers is var / k: k x (variance across the K/k block means)
    #    against the per-pixel variance of single layers, pooled over pixels, within 4 standard errors.
    for k in (2, 4, 8):
        block_var = x.reshape(n_layers // k, k, -1).mean(axis=1).var(axis=0, ddof=1)
        ratio, se = _ratio_of_sums(k * block_var, var)
        assert abs(ratio - 1.0) < 4.0 * se, f"k = {k}: k Var(mean of k) / Var(layer) = {ratio:.3f} +- {se:.3f}"

    # 3. Layers of another seed share nothing with these: E (mean_a - mean_b)^2 = (var_a + var_b) / K.
    #    A component common to all layers of a frame, or seeds whose layer streams overlap (seed s, layer k
    #    = seed s + 1, layer k - 1), would show up here, not within one frame.
    ratio, se = _ratio_of_sums((x.mean(axis=0) - y.mean(axis=0)) ** 2, (var + y.var(axis=0, ddof=1)) / n_layers)
    assert abs(ratio - 1.0) < 4.0 * se, f"(mean_7 - mean_8)^2 / ((var_7 + var_8) / K) = {ratio:.3f} +- {se:.3f}"


def test_nonfinite_samples_are_replaced_and_counted():
    counter = NonFiniteCounter()
    values = np.array([[1.0, np.nan], [np.inf, -np.inf]], np.float32)
    clean = counter.sanitise("radiance", values)
    assert np.isfinite(clean).all() and clean[0, 0] == 1.0
    assert counter.counts["radiance"] == 3


def test_mis_weight_is_zero_where_the_power_heuristic_is_not_finite() -> None:
    """A light-sample pdf that overflows at grazing angles gives inf / inf; Mitsuba's ``path`` drops such a
    weight (NaN radiance would otherwise reach the references as zeroed pixels)."""
    import drjit as dr
    import mitsuba as mi

    from scenegen.integrator import _mis_weight

    pdf_a = mi.Float([float("inf"), 2.0, 0.0, 1e30])
    pdf_b = mi.Float([float("inf"), 2.0, 1.0, 1e30])
    weight = np.asarray(_mis_weight(pdf_a, pdf_b))
    assert np.all(np.isfinite(weight))
    assert weight[0] == 0.0 and weight[1] == pytest.approx(0.5) and weight[2] == 0.0
    assert not dr.any(dr.isnan(_mis_weight(pdf_a, pdf_b)))


def test_one_render_thread_does_not_hang_exr_io(tmp_path: Path) -> None:
    """Mitsuba 3.9.1 / drjit 1.5.0 never return from EXR I/O with a one-thread Dr.Jit pool; the render jobs'
    thread setting (scenegen.mitsuba_env.set_render_threads) keeps the pool at >= 2, so asking for 1 thread
    writes and reads an EXR (in a subprocess with a timeout, since the failure is a hang)."""
    import subprocess
    import sys

    code = ("from scenegen.mitsuba_env import init_mitsuba, set_render_threads\n"
            "init_mitsuba('llvm_ad_rgb')\nimport mitsuba as mi, numpy as np\n"
            "print(set_render_threads(1))\n"
            f"mi.Bitmap(np.ones((4, 4, 3), dtype=np.float32)).write({str(tmp_path / 'x.exr')!r})\n"
            f"print(float(np.asarray(mi.Bitmap({str(tmp_path / 'x.exr')!r})).mean()))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["2", "1.0"]


def test_gbuffer_albedo_and_roughness_are_the_primary_hits_material(scene) -> None:
    """The G-buffer pass returns, per pixel, the albedo and roughness of the surface its ray hits first, as a
    rasterised G-buffer holds them: on the diffuse room the scene's reflectance (0.6, 0.55, 0.5), on the rough
    plastic block its diffuse reflectance (0.2, 0.4, 0.7) and roughness 0.2 (values from the scene dict, not
    from the integrator), 0 on a miss; the glass ball's pixels keep the glass itself, not what lies behind."""
    import mitsuba as mi

    from scenegen.integrator import GBUFFER_AOVS
    from scenegen.render import split_channels

    integrator = mi.load_dict({"type": "mcdn_features", "mode": "gbuffer"})
    image = np.array(mi.render(scene, spp=1, seed=0, integrator=integrator), np.float32)
    g = split_channels(image, [("rgb", 3), *GBUFFER_AOVS])
    shape = np.rint(g["object"][0]).astype(int)
    room, block, ball = shape == 0, shape == 4, shape == 2
    assert room.sum() > 100 and block.sum() > 10 and ball.sum() > 10
    np.testing.assert_allclose(g["albedo"][:, room].T, np.broadcast_to([0.6, 0.55, 0.5], (room.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(g["roughness"][0, room], 1.0)
    np.testing.assert_allclose(g["albedo"][:, block].T, np.broadcast_to([0.2, 0.4, 0.7], (block.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(g["roughness"][0, block], 0.2, atol=1e-6)
    np.testing.assert_allclose(g["roughness"][0, ball], 0.0)
    # Behind the ball lies the room: the per-sample albedo would follow the glass; the G-buffer does not.
    assert not np.allclose(g["albedo"][:, ball].T, [0.6, 0.55, 0.5], atol=1e-3)
    assert not g["albedo"][:, shape < 0].any()
