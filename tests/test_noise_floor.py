"""The reference noise floor against cases whose answer is known independently of the code.

Every reference frame stores ``psnr_halves``, the PSNR between its two independent half-sample
renders, and ``psnr_reference_noise_floor`` = psnr_halves + 10 log10(4) (scenegen.jobs), the PSNR of
the averaged reference against the true image: with independent halves of variance v each,
E|h0 - h1|^2 = 2v while the mean of the halves has error variance v/2, a factor 4 (to first order in
the tonemapper tau). Here the halves are Gaussian noise of known variance around a known image, so
both numbers follow from the variance alone; the expectations are computed by Gauss-Hermite
quadrature of tau in float64 (no linearisation), with tau written out in this file.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from scenegen import jobs
from scenegen import render as render_module
from scenegen.channels import REFERENCE_BUFFERS
from scenegen.dataset import MissingBufferError, load_reference_frame
from scenegen.integrator import SAMPLE_AOVS
from scenegen.render import psnr_between_halves

DB = 10.0 / math.log(10.0)        # d(10 log10 m) / d(ln m): a relative error e of an MSE is DB * e decibels


def tau(x: np.ndarray) -> np.ndarray:
    """Isik 2021 Eq. 15: (max(x, 0) / (1 + max(x, 0)))^(1/2.4), in float64."""
    x = np.maximum(np.asarray(x, np.float64), 0.0)
    return (x / (1.0 + x)) ** (1.0 / 2.4)


def tau_inverse(t: np.ndarray) -> np.ndarray:
    """The radiance x >= 0 with tau(x) = t, t in [0, 1)."""
    r = np.asarray(t, np.float64) ** 2.4
    return r / (1.0 - r)


def gaussian_expectation(f, mean: np.ndarray, std: float, nodes: int = 40) -> np.ndarray:
    """E[f(mean + std Z)], Z ~ N(0, 1), per element, by Gauss-Hermite quadrature (exact for smooth f)."""
    z, w = np.polynomial.hermite_e.hermegauss(nodes)
    w = w / w.sum()
    return sum(wk * f(mean + std * zk) for zk, wk in zip(z, w))


def tau_variance(mean: np.ndarray, std: float) -> np.ndarray:
    """Var tau(mean + std Z) per element."""
    first = gaussian_expectation(tau, mean, std)
    return gaussian_expectation(lambda x: tau(x) ** 2, mean, std) - first ** 2


def expected_psnr(per_value_mse: np.ndarray) -> tuple[float, float]:
    """(-10 log10 of the mean expected squared error, standard error of the PSNR estimate in dB) for
    independent Gaussian errors with the given expected squares: Var(e^2) = 2 (E e^2)^2."""
    mse = float(per_value_mse.mean())
    relative_se = math.sqrt(2.0 * float((per_value_mse ** 2).sum())) / float(per_value_mse.sum())
    return -10.0 * math.log10(mse), DB * relative_se


# -------------------------------------------------------------------------------------------------
# psnr_between_halves on halves built in tonemapped space
# -------------------------------------------------------------------------------------------------

def test_psnr_between_halves_of_known_gaussian_noise() -> None:
    """Halves tau^-1(T + n_k) with T known and n_k ~ N(0, s^2) independent: the PSNR between them is
    -10 log10 mean((n0 - n1)^2) for the drawn noise, and -10 log10(2 s^2) in expectation."""
    rng = np.random.default_rng(11)
    shape, s = (3, 48, 64), 0.02
    truth = rng.uniform(0.3, 0.7, shape)
    n0, n1 = rng.normal(0.0, s, shape), rng.normal(0.0, s, shape)
    half0, half1 = tau_inverse(truth + n0).astype(np.float32), tau_inverse(truth + n1).astype(np.float32)
    measured = psnr_between_halves(half0, half1)
    # The realised value (float32 halves: relative MSE error ~1e-4, far below 0.01 dB).
    assert measured == pytest.approx(-10.0 * math.log10(np.mean((n0 - n1) ** 2)), abs=0.01)
    expected, se = expected_psnr(np.full(shape, 2.0 * s * s))
    assert abs(measured - expected) < 4.0 * se, (measured, expected, se)
    # The reference built from these halves sits 6.02 dB above them: exactly so in expectation here,
    # where the noise is added in tonemapped space.
    floor = -10.0 * math.log10(np.mean((tau(0.5 * (half0.astype(np.float64) + half1)) - truth) ** 2))
    assert abs(floor - (measured + 10.0 * math.log10(4.0))) < 4.0 * math.sqrt(2.0) * se


# -------------------------------------------------------------------------------------------------
# The reference job end to end on a synthetic renderer with known per-sample variance
# -------------------------------------------------------------------------------------------------

HEIGHT, WIDTH = 48, 64
SAMPLE_STD = 0.125                 # standard deviation of one path sample, every pixel and channel
REFERENCE_SPP, BATCH_SPP = 256, 48  # halves of 128 samples in batches of 48, 48 and 32
AOV_CHANNELS = sum(size for _, size in SAMPLE_AOVS)


def true_image() -> np.ndarray:
    """(3, H, W) smooth radiance in [0.25, 2]: tau' varies several-fold across the image."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH] / np.array([HEIGHT, WIDTH])[:, None, None]
    base = 0.25 + 1.75 * (0.5 + 0.5 * np.sin(2 * np.pi * (x + 0.5 * y)))
    return np.stack([base, 0.8 * base + 0.05, 0.6 * base + 0.1])


def fake_render(scene, *, spp: int, seed: int, sensor=None, aov_channels: int = AOV_CHANNELS) -> np.ndarray:
    """Stands in for mi.render of the feature integrator (or of ``path`` with ``aov_channels=0``): an
    (H, W, 3 + AOVs) image whose radiance is the mean of ``spp`` samples true_image() + N(0, SAMPLE_STD^2),
    drawn from ``seed``; AOVs zero."""
    noise = np.random.default_rng(seed).normal(0.0, SAMPLE_STD / math.sqrt(spp), (3, HEIGHT, WIDTH))
    image = np.zeros((HEIGHT, WIDTH, 3 + aov_channels), np.float32)
    image[..., :3] = np.moveaxis(true_image() + noise, 0, -1)
    return image


@pytest.fixture(scope="module", params=["path", "features"])
def reference_chunk(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Run scenegen.jobs.run_render_reference on two frames with fake_render as the renderer, for both
    render.reference_integrator values (the scene loader is asked for the matching integrator)."""
    integrator = request.param
    root = tmp_path_factory.mktemp(f"noise_floor_{integrator}")
    scene_dir, out_dir = root / "scene", root / "reference" / "chunk_000"
    scene_dir.mkdir()
    (scene_dir / "manifest.json").write_text(json.dumps({"n_frames": 2}))
    cfg = {"seed": 3, "scenes": {"frames_per_chunk": 2},
           "render": {"width": WIDTH, "height": HEIGHT, "reference_spp": REFERENCE_SPP,
                      "reference_batch_spp": BATCH_SPP, "reference_integrator": integrator}}
    modes: list[str] = []
    aov_channels = AOV_CHANNELS if integrator == "features" else 0

    def fake_load(*args, mode: str = "samples", **kwargs):
        modes.append(mode)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(render_module, "render_spp", lambda scene, **kw: fake_render(scene, **kw, aov_channels=aov_channels))
        patch.setattr(jobs, "load_frame_scene", fake_load)
        patch.setattr(jobs, "frame_meta", lambda manifest, scene_id, frame, settings, variant:
                      {"scene": scene_id, "frame": frame, "camera_cut": False})
        jobs.run_render_reference(cfg, "test_000", 0, scene_dir, out_dir)
    assert modes == (["samples"] * 2 if integrator == "features" else ["path"] * 2)
    return out_dir


def test_reference_buffers_follow_the_reference_integrator(reference_chunk: Path) -> None:
    """path stores radiance and its halves only; features adds the feature means; the default read
    returns what is stored, and asking for an absent feature mean names the buffer."""
    meta = json.loads((reference_chunk / "frame_0000.json").read_text())
    data, _ = load_reference_frame(reference_chunk / "frame_0000.exr")
    required = {"radiance", "radiance_half0", "radiance_half1"}
    if meta["integrator"] == "path":
        assert set(data) == required == set(meta["buffers"])
        with pytest.raises(MissingBufferError, match="'albedo'"):
            load_reference_frame(reference_chunk / "frame_0000.exr", ["albedo"])
    else:
        assert meta["integrator"] == "mcdn_features"
        assert set(data) == set(REFERENCE_BUFFERS) == set(meta["buffers"])
    np.testing.assert_allclose(data["radiance"], 0.5 * (data["radiance_half0"] + data["radiance_half1"]),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("frame", [0, 1])
def test_reference_noise_floor_of_a_render_with_known_variance(reference_chunk: Path, frame: int) -> None:
    meta = json.loads((reference_chunk / f"frame_{frame:04d}.json").read_text())
    truth = true_image()
    half_std = SAMPLE_STD / math.sqrt(REFERENCE_SPP // 2)
    # psnr_halves: E (tau(h0) - tau(h1))^2 = 2 Var tau(h) per value, h = truth + N(0, half_std^2).
    halves_expected, halves_se = expected_psnr(2.0 * tau_variance(truth, half_std))
    assert abs(meta["psnr_halves"] - halves_expected) < 4.0 * halves_se, (meta["psnr_halves"], halves_expected)
    # The noise floor: E (tau(mean of halves) - tau(truth))^2, the mean having std half_std / sqrt(2).
    floor_mse = gaussian_expectation(lambda x: (tau(x) - tau(truth)) ** 2, truth, half_std / math.sqrt(2.0))
    floor_expected, floor_se = expected_psnr(floor_mse)
    # The stored floor is psnr_halves + 6.02 dB, so it carries the halves' estimation error; the
    # first-order approximation behind the 6.02 dB is far below that error at this noise level.
    assert abs(floor_expected - (halves_expected + 10.0 * math.log10(4.0))) < 0.1 * halves_se
    assert abs(meta["psnr_reference_noise_floor"] - floor_expected) < 4.0 * halves_se, meta
    # The reference actually stored is that far from the truth: h0 - h1 and h0 + h1 are independent
    # for Gaussian halves, so the two estimates differ by their independent errors only.
    stored, _ = load_reference_frame(reference_chunk / f"frame_{frame:04d}.exr", ["radiance"])
    achieved = -10.0 * math.log10(np.mean((tau(stored["radiance"]) - tau(truth)) ** 2))
    assert abs(achieved - meta["psnr_reference_noise_floor"]) < 4.0 * math.hypot(halves_se, floor_se), \
        (achieved, meta["psnr_reference_noise_floor"])
    assert meta["spp"] == REFERENCE_SPP
