"""RLS / wRLS (Iglesias-Guitian et al. 2022): the batched RLS math against a direct weighted least-squares
solve, the whole filter against an independent NumPy recomputation of Eq. 12-14, and the filter's
behaviour (constant images, convergence, spikes, non-finite inputs, resets, reprojection)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from denoisers.methods.rls import RLS, WeightedRLS, clip_to_neighbourhood, rls_update
from denoisers.registry import Frame, build, clip_frames, get
from scenegen.dataset import Clip

METHODS = ("rls", "wrls")


def _frame(radiance: np.ndarray, index: int, motion: np.ndarray | None = None, valid: float | np.ndarray = 1.0,
           camera_cut: bool = False) -> Frame:
    """Frame from samples (S, 3, H, W); valid is forced to 0 on frame 0 as in the data format."""
    height, width = radiance.shape[-2:]
    motion = np.zeros((2, height, width), np.float32) if motion is None else motion
    valid_map = np.broadcast_to(np.asarray(valid, np.float32), (1, height, width)) * (index > 0)
    return Frame(samples={"radiance": torch.from_numpy(np.ascontiguousarray(radiance, dtype=np.float32))},
                 pixel={"motion": torch.from_numpy(np.ascontiguousarray(motion, dtype=np.float32)),
                        "valid": torch.from_numpy(np.ascontiguousarray(valid_map, dtype=np.float32))},
                 index=index, camera_cut=camera_cut)


def _smooth_image(height: int, width: int) -> np.ndarray:
    """(3, H, W) smooth positive test image."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([1.0 + 0.5 * np.sin(x / 7.0), 0.8 + 0.4 * np.cos(y / 9.0),
                     0.6 + 0.3 * np.sin((x + y) / 11.0)]).astype(np.float32)


def _noisy_samples(truth: np.ndarray, spp: int, rng: np.random.Generator) -> np.ndarray:
    """(spp, 3, H, W) unbiased noisy samples: truth times a mean-1 gamma variable (relative std 0.7)."""
    return (truth[None] * rng.gamma(2.0, 0.5, (spp,) + truth.shape)).astype(np.float32)


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


# -- the RLS update against a direct least-squares solve ----------------------------------------------

def _direct_weighted_ls(features: np.ndarray, targets: np.ndarray, weights: np.ndarray, forgetting: float,
                        beta_init: np.ndarray, cov_init: np.ndarray) -> np.ndarray:
    """argmin_beta sum_s lambda^(T-s) w_s (y_s - [1, z_s] beta)^2 + lambda^T (beta - b0)^T P0^-1 (beta - b0)
    for one scalar model, by stacking sqrt-weighted rows and calling numpy.linalg.lstsq."""
    steps = len(features)
    rows = [np.sqrt(forgetting ** (steps - 1 - s) * weights[s]) * np.array([1.0, features[s]])
            for s in range(steps)]
    rhs = [np.sqrt(forgetting ** (steps - 1 - s) * weights[s]) * targets[s] for s in range(steps)]
    # Prior rows: L^T (beta - b0) with L L^T = lambda^T P0^-1.
    prior_root = np.linalg.cholesky(forgetting ** steps * np.linalg.inv(cov_init))
    design = np.vstack([np.array(rows), prior_root.T])
    target = np.concatenate([np.array(rhs), prior_root.T @ beta_init])
    return np.linalg.lstsq(design, target, rcond=None)[0]


@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
def test_batched_update_equals_direct_weighted_least_squares(dtype: torch.dtype, tolerance: float) -> None:
    rng = np.random.default_rng(7)
    steps, pixels, forgetting = 7, 3, 0.9          # strong forgetting so that the weighting matters
    features = rng.uniform(0.2, 3.0, (steps, pixels))
    targets = 0.3 + 1.7 * features + rng.normal(0.0, 0.4, (steps, pixels))
    weights = rng.uniform(0.05, 1.0, (steps, pixels))
    weights[3, 1] = 0.0                             # a fully rejected sample
    cov_init = np.array([[[2.0, 0.3], [0.3, 0.5]], [[1.0, 0.0], [0.0, 1.0]], [[0.5, -0.2], [-0.2, 4.0]]])
    beta_init = np.array([[0.0, 1.0], [0.5, 0.5], [-1.0, 2.0]])

    beta = torch.tensor(beta_init.T, dtype=dtype)                              # (2, pixels)
    cov = torch.tensor(np.stack([cov_init[:, 0, 0], cov_init[:, 0, 1], cov_init[:, 1, 1]]), dtype=dtype)
    for s in range(steps):
        beta, cov = rls_update(beta, cov, torch.tensor(features[s], dtype=dtype),
                               torch.tensor(targets[s], dtype=dtype), torch.tensor(weights[s], dtype=dtype),
                               forgetting)
    for j in range(pixels):
        expected = _direct_weighted_ls(features[:, j], targets[:, j], weights[:, j], forgetting,
                                       beta_init[j], cov_init[j])
        np.testing.assert_allclose(beta[:, j].double().numpy(), expected, rtol=tolerance, atol=tolerance)
        # P is the inverse of the forgetting-weighted information matrix.
        information = forgetting ** steps * np.linalg.inv(cov_init[j]) + sum(
            forgetting ** (steps - 1 - s) * weights[s, j] * np.outer([1, features[s, j]], [1, features[s, j]])
            for s in range(steps))
        expected_cov = np.linalg.inv(information)
        got_cov = cov[:, j].double().numpy()
        np.testing.assert_allclose(got_cov, [expected_cov[0, 0], expected_cov[0, 1], expected_cov[1, 1]],
                                   rtol=50 * tolerance, atol=tolerance)


@pytest.mark.parametrize("method", METHODS)
def test_filter_matches_independent_recomputation_of_eq_12_to_14(method: str) -> None:
    """Pixel (2, 2) of a 5x5 image whose other pixels alternate 0 / 100 (so the 3x3 clipping box never
    binds): its feature is the plain exponential history of Eq. 12, and with blending off the output is
    [1, z_T] beta_T of the weighted least-squares fit, recomputed here in NumPy."""
    rng = np.random.default_rng(3)
    steps, alpha, forgetting, bandwidth, epsilon = 9, 0.75, 0.998, 0.75, 1e-4
    prior_intercept, prior_slope, floor_factor = 1.0, 0.01, 0.01
    values = rng.uniform(0.5, 2.5, (steps, 3))
    values[4] *= 6.0                                # an outlier frame, so that weights differ from 1
    params = dict(blend_radius=0, prior_intercept=prior_intercept, prior_slope=prior_slope,
                  magnitude_floor=floor_factor, epsilon=epsilon)
    if method == "wrls":
        params["bandwidth"] = bandwidth
    denoiser = build(method, params)
    background = np.where((np.add.outer(np.arange(5), np.arange(5)) % 2) == 0, 0.0, 100.0)
    outputs = []
    for t in range(steps):
        image = np.repeat(background[None], 3, axis=0)
        image[:, 2, 2] = values[t]
        outputs.append(denoiser.denoise(_frame(image[None], t)).numpy()[:, 2, 2])

    features = np.zeros_like(values)
    features[0] = values[0]
    for t in range(1, steps):
        features[t] = alpha * features[t - 1] + (1 - alpha) * values[t]
    if method == "wrls":
        distance = (np.linalg.norm(values - features, axis=1)
                    / (np.minimum(np.linalg.norm(values, axis=1), np.linalg.norm(features, axis=1)) + epsilon))
        weights = np.exp(-distance ** 2 / bandwidth ** 2)
        assert weights.min() < 0.5 < weights.max()
    else:
        weights = np.ones(steps)
    frame0 = np.repeat(background[None], 3, axis=0)
    frame0[:, 2, 2] = values[0]
    floor = floor_factor * float(np.abs(frame0).mean()) + 1e-12
    slopes = []
    for t in range(1, steps):
        for c in range(3):
            cov_init = np.diag([prior_intercept, prior_slope / (features[0, c] ** 2 + floor ** 2)])
            beta = _direct_weighted_ls(features[:t + 1, c], values[:t + 1, c], weights[:t + 1], forgetting,
                                       np.array([0.0, 1.0]), cov_init)
            slopes.append(beta[1])
            expected = max(beta[0] + beta[1] * features[t, c], 0.0)
            assert outputs[t][c] == pytest.approx(expected, rel=1e-4), (t, c)
    assert np.ptp(slopes) > 0.01                   # the check exercises the slope, not only the intercept


# -- behaviour --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
def test_constant_input_stays_constant(method: str) -> None:
    colour = np.array([0.5, 1.0, 2.0], np.float32)
    image = np.broadcast_to(colour[:, None, None], (3, 24, 24))
    motion = np.stack([np.full((24, 24), 0.4), np.full((24, 24), -1.3)]).astype(np.float32)
    denoiser = build(method)
    for t in range(6):
        out = denoiser.denoise(_frame(np.stack([image, image]), t, motion)).numpy()
        np.testing.assert_allclose(out, image, rtol=1e-5)


@pytest.mark.parametrize("method", METHODS)
def test_static_noisy_sequence_converges_towards_the_mean(method: str) -> None:
    rng = np.random.default_rng(1)
    truth = _smooth_image(32, 32)
    denoiser = build(method)
    errors = [_rmse(denoiser.denoise(_frame(_noisy_samples(truth, 1, rng), t)).numpy(), truth) for t in range(24)]
    noisy_error = _rmse(_noisy_samples(truth, 1, rng).mean(0), truth)
    assert errors[0] == pytest.approx(noisy_error, rel=0.15)        # no history yet
    assert np.mean(errors[-6:]) < 0.5 * errors[0]
    assert np.mean(errors[-6:]) < np.mean(errors[4:10])              # still improving after the feature settles


def _spike_run(method: str, seed: int = 5) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-frame RMSE (whole image, spike pixels) of a static noisy sequence with spikes of 500x the image
    mean in 1% of the pixels of one sample layer at one frame (Isik et al. 2021, Fig. 3)."""
    rng = np.random.default_rng(seed)
    truth = _smooth_image(48, 48)
    spike_frame = 12
    spike_pixels = np.random.default_rng(99).random((48, 48)) < 0.01
    denoiser = build(method)
    errors, spike_errors = [], []
    for t in range(spike_frame + 12):
        samples = _noisy_samples(truth, 2, rng)
        if t == spike_frame:
            samples[0][:, spike_pixels] = 500.0 * truth.mean()
        out = denoiser.denoise(_frame(samples, t)).numpy()
        errors.append(_rmse(out, truth))
        spike_errors.append(_rmse(out[:, spike_pixels], truth[:, spike_pixels]))
    return np.array(errors), np.array(spike_errors), spike_frame


def test_wrls_suppresses_a_spike_better_than_rls() -> None:
    rls_errors, rls_spike_errors, spike_frame = _spike_run("rls")
    wrls_errors, wrls_spike_errors, _ = _spike_run("wrls")
    before, after = slice(spike_frame - 4, spike_frame), slice(spike_frame + 1, None)
    # At the spike frame both outputs carry the spike through the feature (Eq. 12), but RLS also refits
    # its models to it.
    assert wrls_errors[spike_frame] < 0.5 * rls_errors[spike_frame]
    # Afterwards the clipped feature has dropped the spike; RLS's refitted models still amplify noise at
    # the spike pixels while wRLS's models were barely touched (weights ~ 0).
    assert np.mean(wrls_spike_errors[after]) < 0.85 * np.mean(rls_spike_errors[after])
    assert np.mean(wrls_errors[after]) < np.mean(rls_errors[after])
    # The clipped feature keeps a trace of the spike for a few frames (it decays by alpha = 0.75 per
    # frame from the top of the neighbourhood box); wRLS is back to its pre-spike error after that.
    assert np.mean(wrls_spike_errors[spike_frame + 4:]) < 1.3 * np.mean(wrls_spike_errors[before])


@pytest.mark.parametrize("method", METHODS)
def test_non_finite_and_huge_inputs_give_finite_output(method: str) -> None:
    rng = np.random.default_rng(2)
    truth = _smooth_image(20, 20)
    denoiser = build(method)
    for t in range(5):
        samples = _noisy_samples(truth, 2, rng)
        samples[0, 0, 3, 4] = np.nan
        samples[1, 1, 5, 6] = np.inf
        samples[0, 2, 7, 8] = -np.inf
        samples[1, :, 9, 9] = 3e38
        samples[0, :, 0, 0] = 1e12
        motion = rng.normal(0.0, 0.7, (2, 20, 20)).astype(np.float32)
        motion[0, 2, 2] = np.nan
        out = denoiser.denoise(_frame(samples, t, motion))
        assert out.shape == (3, 20, 20) and out.dtype == torch.float32
        assert bool(torch.isfinite(out).all())
        assert bool((out >= 0).all())


@pytest.mark.parametrize("method", METHODS)
def test_camera_cut_and_invalid_history_reset_the_models(method: str) -> None:
    rng = np.random.default_rng(4)
    scene_a, scene_b = _smooth_image(16, 16), 3.0 * _smooth_image(16, 16)[::-1].copy()
    frames_b = [_noisy_samples(scene_b, 2, rng) for _ in range(3)]

    fresh = build(method)
    expected = [fresh.denoise(_frame(samples, t + 1, valid=1.0 if t else 0.0)).numpy()
                for t, samples in enumerate(frames_b)]
    for cut in ("camera_cut", "valid"):
        denoiser = build(method)
        for t in range(6):
            denoiser.denoise(_frame(_noisy_samples(scene_a, 2, rng), t))
        first = _frame(frames_b[0], 6, valid=1.0 if cut == "camera_cut" else 0.0, camera_cut=cut == "camera_cut")
        got = [denoiser.denoise(first).numpy()]
        got += [denoiser.denoise(_frame(samples, 7 + t)).numpy() for t, samples in enumerate(frames_b[1:])]
        for a, b in zip(got, expected):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)

    # Where only part of the frame is invalid, those pixels restart from the identity model: with
    # blending off, their output is exactly the noisy input.
    denoiser = build(method, {"blend_radius": 0})
    for t in range(5):
        denoiser.denoise(_frame(_noisy_samples(scene_a, 2, rng), t))
    valid = np.ones((16, 16), np.float32)
    valid[4:9, 2:7] = 0.0
    samples = _noisy_samples(scene_a, 2, rng)
    out = denoiser.denoise(_frame(samples, 5, valid=valid)).numpy()
    np.testing.assert_allclose(out[:, 4:9, 2:7], samples.mean(0)[:, 4:9, 2:7], rtol=1e-6)
    assert not np.allclose(out[:, 10:, 10:], samples.mean(0)[:, 10:, 10:])


def test_reprojection_follows_the_motion_vectors() -> None:
    """A textured image moving 1.5 px/frame to the left: with the true backward motion (+1.5 px) the
    filter converges; with the motion zeroed its history lags the content and the error is higher."""
    rng = np.random.default_rng(6)
    height, width, steps, speed = 32, 32, 14, 1.5
    y, x = np.mgrid[0:height, 0:width + int(speed * steps) + 2].astype(np.float64)
    texture = np.stack([1.0 + 0.8 * np.sin(x / 2.5), 1.0 + 0.8 * np.cos(x / 3.0 + y / 4.0),
                        1.0 + 0.5 * np.sin(y / 3.0)]).astype(np.float32)
    errors = {}
    for label, motion_scale in (("true", 1.0), ("zero", 0.0)):
        denoiser = build("wrls")
        frame_errors = []
        for t in range(steps):
            shift = speed * t
            xs = np.arange(width) + shift
            x0 = np.floor(xs).astype(int)
            frac = (xs - x0).astype(np.float32)
            truth = texture[:, :, x0] * (1 - frac) + texture[:, :, x0 + 1] * frac
            motion = np.zeros((2, height, width), np.float32)
            motion[0] = motion_scale * speed
            out = denoiser.denoise(_frame(_noisy_samples(truth, 2, rng), t, motion)).numpy()
            # The 2 rightmost columns come from outside the previous frame (border-clamped lookups).
            frame_errors.append(_rmse(out[:, :, :-2], truth[:, :, :-2]))
        errors[label] = np.mean(frame_errors[-6:])
        noisy = _rmse(_noisy_samples(truth, 2, rng).mean(0), truth)
        if label == "true":
            assert errors[label] < 0.6 * noisy
    assert errors["true"] < 0.8 * errors["zero"]


def test_clip_moves_history_into_the_neighbourhood_box_along_the_line_to_its_centre() -> None:
    current = torch.zeros(3, 3, 3)
    current[:, 0, 0] = torch.tensor([1.0, 2.0, 4.0])          # box [0, 1] x [0, 2] x [0, 4], centre (0.5, 1, 2)
    history = torch.zeros(3, 3, 3)
    history[:, 1, 1] = torch.tensor([3.0, 1.0, 2.0])          # 2.5 half-extents out along red
    history[:, 0, 0] = torch.tensor([0.2, 1.5, 3.0])          # inside: unchanged
    clipped = clip_to_neighbourhood(history, current)
    expected = torch.tensor([0.5, 1.0, 2.0]) + (torch.tensor([3.0, 1.0, 2.0]) - torch.tensor([0.5, 1.0, 2.0])) / 5.0
    torch.testing.assert_close(clipped[:, 1, 1], expected)
    torch.testing.assert_close(clipped[:, 0, 0], history[:, 0, 0])
    # Pixel (2, 2)'s window excludes (0, 0): its box is the single colour 0.
    torch.testing.assert_close(clipped[:, 2, 2], torch.zeros(3))


def test_registry_declarations_and_clip_frames() -> None:
    for name, cls in (("rls", RLS), ("wrls", WeightedRLS)):
        assert get(name) is cls
        assert cls.info.temporal and not cls.info.trainable
        assert cls.info.inputs == ("radiance",) and set(cls.info.pixel_inputs) == {"motion", "valid"}
    with pytest.raises(ValueError, match="did you mean 'blend_bandwidth'"):
        build("rls", {"bandwidth": 0.5})                     # RLS has no weights
    rng = np.random.default_rng(8)
    frames, height, width = 4, 12, 10
    truth = _smooth_image(height, width)
    clip = Clip(scene="synthetic", frames=list(range(frames)),
                samples={"radiance": np.stack([_noisy_samples(truth, 2, rng) for _ in range(frames)])},
                motion=np.zeros((frames, 2, height, width), np.float32),
                valid=np.arange(frames)[:, None, None, None] > np.zeros((1, 1, height, width)),
                gbuffer={}, reference=None, meta=[{"camera_cut": False}] * frames)
    denoiser = build("wrls")
    outputs = [denoiser.denoise(frame) for frame in clip_frames(clip, denoiser.info, spp=2)]
    assert len(outputs) == frames and all(o.shape == (3, height, width) for o in outputs)


def test_resolution_change_without_reset_is_an_error() -> None:
    rng = np.random.default_rng(9)
    denoiser = build("wrls")
    denoiser.denoise(_frame(_noisy_samples(_smooth_image(8, 8), 1, rng), 0))
    with pytest.raises(ValueError, match="8x8"):
        denoiser.denoise(_frame(_noisy_samples(_smooth_image(8, 12), 1, rng), 1))
    denoiser.reset()
    assert denoiser.denoise(_frame(_noisy_samples(_smooth_image(8, 12), 1, rng), 0)).shape == (3, 8, 12)


def test_optional_gaussian_prefilter_is_the_3x3_binomial() -> None:
    """prefilter=True (the paper's Gaussian pixel reconstruction filter): on frame 0 with blending off the
    output is the filtered input, here a single bright pixel spread as [1, 2, 1]^2 / 16."""
    image = np.zeros((3, 5, 5), np.float32)
    image[:, 2, 2] = 16.0
    out = build("wrls", {"prefilter": True, "blend_radius": 0}).denoise(_frame(image[None], 0)).numpy()
    expected = np.zeros((5, 5), np.float32)
    expected[1:4, 1:4] = np.outer([1, 2, 1], [1, 2, 1])
    np.testing.assert_allclose(out, np.broadcast_to(expected, (3, 5, 5)), rtol=1e-6)
