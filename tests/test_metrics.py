"""Metrics against skimage / flip_evaluator and against hand-computed tiny cases."""
from __future__ import annotations

import itertools
import math

import flip_evaluator
import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from denoisers import metrics as M


def tau(x: float) -> float:
    """Eq. 15 written out for scalars, independent of the module."""
    x = max(x, 0.0)
    return (x / (1.0 + x)) ** (1.0 / 2.4)


def hdr_pair(seed: int, shape=(3, 48, 40), noise: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A smooth-ish HDR reference with a bright region, and a multiplicatively noisy prediction."""
    rng = np.random.default_rng(seed)
    ref = rng.gamma(2.0, 0.5, shape)
    ref[..., : shape[-2] // 3, :] *= 8.0
    pred = ref * np.exp(noise * rng.standard_normal(shape))
    return pred.astype(np.float32), ref.astype(np.float32)


def skimage_ssim(pred: np.ndarray, ref: np.ndarray) -> float:
    return structural_similarity(tau_array(ref), tau_array(pred), gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1, channel_axis=0)


def tau_array(x: np.ndarray) -> np.ndarray:
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    return (x / (1.0 + x)) ** (1.0 / 2.4)


# ------------------------------------------------------------------------------------------ tonemap
def test_tonemap_values_and_types():
    x = np.array([-2.0, 0.0, 1.0, 3.0, np.inf])
    expected = [0.0, 0.0, 0.5 ** (1 / 2.4), 0.75 ** (1 / 2.4), 1.0]
    np.testing.assert_allclose(M.tonemap(x), expected, rtol=1e-12)
    t = M.tonemap(torch.tensor([1.0, 3.0, float("inf")]))
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
    np.testing.assert_allclose(t.numpy(), expected[2:], rtol=1e-6)
    assert M.tonemap(np.ones(2, dtype=np.float32)).dtype == np.float32
    assert np.isnan(M.tonemap(np.array([np.nan])))[0]


# ---------------------------------------------------------------------------------- PSNR and SSIM
@pytest.mark.parametrize("seed", [0, 1])
def test_psnr_matches_skimage(seed):
    pred, ref = hdr_pair(seed)
    expected = peak_signal_noise_ratio(tau_array(ref), tau_array(pred), data_range=1)
    assert M.psnr(pred, ref) == pytest.approx(expected, abs=1e-6)


def test_psnr_of_a_sequence_pools_the_mse_over_frames():
    ref = np.zeros((2, 3, 4, 4))
    pred = np.zeros((2, 3, 4, 4))
    pred[0] = 1.0  # tau(1) = 0.5^(1/2.4) everywhere in frame 0, frame 1 exact
    mse = 0.5 * tau(1.0) ** 2
    assert M.psnr(pred, ref) == pytest.approx(-10 * math.log10(mse), abs=1e-9)
    assert M.rmse(pred, ref) == pytest.approx(math.sqrt(mse), abs=1e-12)


@pytest.mark.parametrize("seed,noise", [(0, 0.3), (1, 1.0), (2, 0.05)])
def test_ssim_matches_skimage(seed, noise):
    pred, ref = hdr_pair(seed, noise=noise)
    assert abs(M.ssim(pred, ref) - skimage_ssim(pred, ref)) < 1e-4


def test_ssim_of_a_sequence_is_the_mean_of_frames_and_accepts_torch():
    pairs = [hdr_pair(seed, shape=(3, 24, 30)) for seed in (3, 4)]
    pred = torch.from_numpy(np.stack([p for p, _ in pairs]))
    ref = torch.from_numpy(np.stack([r for _, r in pairs]))
    expected = np.mean([skimage_ssim(p, r) for p, r in pairs])
    assert abs(M.ssim(pred, ref) - expected) < 1e-4


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="11x11"):
        M.ssim(np.ones((3, 8, 32)), np.ones((3, 8, 32)))


# --------------------------------------------------------------------- hand-computed pixel metrics
def test_rmse_hand_computed():
    pred = np.full((3, 2, 2), 3.0)
    ref = np.full((3, 2, 2), 1.0)
    assert M.rmse(pred, ref) == pytest.approx(tau(3.0) - tau(1.0), abs=1e-12)


def test_relmse_hand_computed_per_channel():
    # (C=3, H=1, W=2); each channel relative to its own reference value.
    pred = np.array([[[2.0, 0.0]], [[1.0, 0.1]], [[0.0, 4.0]]])
    ref = np.array([[[1.0, 0.0]], [[1.0, 0.0]], [[2.0, 4.0]]])
    terms = [1 / 1.01, 0.0, 0.0, 0.01 / 0.01, 4 / 4.01, 0.0]
    assert M.relmse(pred, ref) == pytest.approx(sum(terms) / 6, abs=1e-12)


def test_smape_hand_computed_per_channel():
    pred = np.array([[[3.0, 0.0]], [[-1.0, 2.0]], [[0.5, 0.0]]])
    ref = np.array([[[1.0, 0.0]], [[1.0, 2.0]], [[0.0, 1.0]]])
    terms = [2 / 4.01, 0.0, 2 / 2.01, 0.0, 0.5 / 0.51, 1 / 1.01]
    assert M.smape(pred, ref) == pytest.approx(sum(terms) / 6, abs=1e-12)


# ----------------------------------------------------------------------------------------- FLIP
def test_flip_identical_is_zero_and_matches_direct_call():
    pred, ref = hdr_pair(5, shape=(3, 40, 40))
    assert M.flip(ref, ref) == 0.0
    direct = flip_evaluator.evaluate(tau_array(ref).transpose(1, 2, 0).astype(np.float32).copy(),
                                     tau_array(pred).transpose(1, 2, 0).astype(np.float32).copy(),
                                     "LDR", applyMagma=False)[1]
    assert M.flip(pred, ref) == pytest.approx(direct, abs=1e-6)
    assert 0.0 < direct < 1.0


def test_flip_black_versus_white_is_large():
    white = np.full((3, 32, 32), 1e6)
    assert M.flip(np.zeros_like(white), white) > 0.9


# ----------------------------------------------------------------------- perfect scores, monotone
def test_identical_inputs_give_perfect_frame_scores():
    _, ref = hdr_pair(6)
    scores = M.frame_metrics(ref, ref)
    assert set(scores) == set(M.FRAME_METRICS)
    assert scores["psnr"] == math.inf
    assert scores["ssim"] == pytest.approx(1.0, abs=1e-12)
    for name in ("rmse", "relmse", "smape", "flip"):
        assert scores[name] == 0.0


def test_more_noise_is_worse_for_every_metric():
    levels = [0.05, 0.3, 1.0]
    rng = np.random.default_rng(7)
    _, ref = hdr_pair(7, shape=(4, 3, 32, 32))
    white = rng.standard_normal(ref.shape)
    results = [M.frame_metrics(ref * np.exp(s * white), ref) for s in levels]
    temporal = [M.temporal_metrics(ref * np.exp(s * white), ref, warmup=0) for s in levels]
    for name, info in M.METRICS.items():
        if info.temporal:
            values = [np.nanmean(t[name]) for t in temporal]
        else:
            values = [r[name] for r in results]
        sign = -1 if info.higher_is_better else 1
        assert all(sign * a < sign * b for a, b in itertools.pairwise(values)), (name, values)


def test_spikes_give_finite_scores():
    pred, ref = hdr_pair(8)
    pred[:, 5, 7] = 500.0 * ref.mean()
    assert all(math.isfinite(v) for v in M.frame_metrics(pred, ref).values())


# --------------------------------------------------------------------------------- temporal metrics
def test_static_sequence_equal_to_reference_is_perfect():
    _, frame = hdr_pair(9, shape=(3, 16, 16))
    seq = np.repeat(frame[None], 4, axis=0)
    result = M.temporal_metrics(seq, seq, warmup=1)
    assert np.isnan(result["tpsnr"][0]) and np.isnan(result["trmae"][0])
    assert np.all(result["tpsnr"][1:] == np.inf)
    assert np.all(result["trmae"][1:] == 0.0)


def test_trmae_hand_computed():
    # (T=3, C=3, H=1, W=1); linear differences, per channel.
    pred = np.array([[1.0, 1.0, 1.0], [2.0, 1.0, 0.5], [2.0, 3.0, 0.5]]).reshape(3, 3, 1, 1)
    ref = np.array([[1.0, 1.0, 1.0], [1.0, 2.0, 1.0], [1.0, 2.0, 1.0]]).reshape(3, 3, 1, 1)
    # t=1: dp = (1, 0, -0.5), dr = (0, 1, 0); t=2: dp = (0, 2, 0), dr = (0, 0, 0)
    expected_t1 = (1 / 0.01 + 1 / 1.01 + 0.5 / 0.01) / 3
    expected_t2 = (0 + 2 / 0.01 + 0) / 3
    np.testing.assert_allclose(M.trmae(pred, ref), [np.nan, expected_t1, expected_t2], rtol=1e-12)


def test_tpsnr_hand_computed():
    # Reference static at 1; prediction goes 1 -> 3 -> 3 (uniform frames, C=3, 2x2).
    ref = np.ones((3, 3, 2, 2))
    pred = np.ones((3, 3, 2, 2))
    pred[1:] = 3.0
    jump = tau(3.0) - tau(1.0)
    np.testing.assert_allclose(M.tpsnr(pred, ref), [np.nan, -10 * math.log10(jump**2), np.inf])


def test_warmup_sets_early_frames_to_nan():
    pred, ref = hdr_pair(10, shape=(5, 3, 12, 12))
    full = M.temporal_metrics(pred, ref, warmup=0)
    warm = M.temporal_metrics(pred, ref, warmup=3)
    for name in M.TEMPORAL_METRICS:
        assert full[name].shape == (5,)
        assert np.isnan(full[name][0]) and np.all(np.isfinite(full[name][1:]))
        assert np.all(np.isnan(warm[name][:3]))
        np.testing.assert_array_equal(warm[name][3:], full[name][3:])
    assert np.all(np.isnan(M.trmae(pred, ref, warmup=9)))
    with pytest.raises(ValueError, match="warmup"):
        M.temporal_metrics(pred, ref, warmup=-1)
    single = M.temporal_metrics(pred[:1], ref[:1], warmup=0)
    assert np.isnan(single["tpsnr"]).all() and single["trmae"].shape == (1,)


# ------------------------------------------------------------------------------------- validation
def test_mismatched_shapes_name_both_shapes():
    with pytest.raises(ValueError, match=r"\(3, 8, 8\).*\(3, 8, 9\)"):
        M.psnr(np.zeros((3, 8, 8)), np.zeros((3, 8, 9)))
    with pytest.raises(ValueError, match=r"\(4, 3, 8, 8\).*\(5, 3, 8, 8\)"):
        M.temporal_metrics(np.zeros((4, 3, 8, 8)), np.zeros((5, 3, 8, 8)), warmup=0)
    with pytest.raises(ValueError, match=r"\(T, C, H, W\)"):
        M.trmae(np.zeros((3, 8, 8)), np.zeros((3, 8, 8)))
    with pytest.raises(ValueError, match="got shape"):
        M.smape(np.zeros((8, 8)), np.zeros((8, 8)))


@pytest.mark.parametrize("name", ["psnr", "ssim", "rmse", "relmse", "smape", "flip", "frame_metrics"])
def test_non_finite_input_is_counted_in_the_error(name):
    pred, ref = hdr_pair(11, shape=(3, 16, 16))
    pred[0, 0, :2] = np.nan
    pred[1, 3, 3] = np.inf
    with pytest.raises(M.NonFiniteError, match=rf"{name}: pred has 3 non-finite values \(2 NaN, 1 Inf\)") as err:
        getattr(M, name)(pred, ref)
    assert err.value.count == 3 and isinstance(err.value, ValueError)
    assert M.count_nonfinite(pred) == 3


def test_non_finite_reference_in_temporal_metrics():
    seq = np.ones((3, 3, 4, 4))
    bad = seq.copy()
    bad[2, 1, 0, 0] = -np.inf
    with pytest.raises(M.NonFiniteError, match="temporal_metrics: ref has 1"):
        M.temporal_metrics(seq, bad, warmup=0)


def test_registry_describes_every_metric():
    assert set(M.METRICS) == set(M.FRAME_METRICS) | set(M.TEMPORAL_METRICS)
    assert {n for n, i in M.METRICS.items() if i.higher_is_better} == {"psnr", "ssim", "tpsnr"}
    assert {n for n, i in M.METRICS.items() if i.temporal} == set(M.TEMPORAL_METRICS)
    for name, info in M.METRICS.items():
        assert info.name == name and info.formula and info.description
