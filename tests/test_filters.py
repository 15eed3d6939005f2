"""Tests for the shared filter helpers (denoisers/filters.py) and the EAW, SVGF and OIDN methods.

Every scene here is synthetic and built in memory: a "two planes" image whose left half is a wall facing
the camera and whose right half is a floor, so colour edges coincide with geometry edges, as in a render.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from denoisers import filters, registry
from denoisers.filters import (atrous_step, b3_kernel_2d, bilinear_taps, gather_taps, gaussian_blur_3x3,
                               luminance, sanitize, warp_previous)
from denoisers.registry import Frame, MissingInputError
from scenegen.dataset import Clip
from scenegen.motion import warp_previous as warp_previous_numpy

H, W = 32, 40


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# -------------------------------------------------------------------------------------------------
# Synthetic scenes
# -------------------------------------------------------------------------------------------------

def two_planes(height: int = H, width: int = W, split: int | None = None, textured: bool = True,
               ramp: float = 0.01) -> dict[str, torch.Tensor]:
    """Noise-free buffers (C, H, W): a grey wall (left, normal +z, 2 m away) and an orange floor (right,
    normal +y, 3-4 m away), each with a horizontal colour ramp (1 + ramp * x); albedo is a checkerboard
    (or 1)."""
    split = width // 2 if split is None else split
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    left = (xs < split)[None]
    ramp = 1.0 + ramp * xs[None]
    radiance = torch.where(left, torch.tensor([0.3, 0.3, 0.3]).view(3, 1, 1),
                           torch.tensor([1.0, 0.6, 0.2]).view(3, 1, 1)) * ramp
    normal = torch.where(left, torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1), torch.tensor([0.0, 1.0, 0.0]).view(3, 1, 1))
    wall = torch.stack([xs * 0.02, -ys * 0.02, torch.full_like(xs, -2.0)])
    floor = torch.stack([xs * 0.02, torch.full_like(xs, -1.0), -3.0 - ys * 0.03])
    position = torch.where(left, wall, floor)
    depth = position.norm(dim=0, keepdim=True)
    checker = ((xs // 4 + ys // 4) % 2)[None]
    albedo = (0.3 + 0.5 * checker if textured else torch.ones_like(checker)).expand(3, height, width).clone()
    return {"radiance": radiance * albedo, "albedo": albedo, "normal": normal, "position": position, "depth": depth}


def make_frame(scene: dict[str, torch.Tensor], index: int = 0, spp: int = 1, noise: float = 0.0,
               seed: int = 0, motion: torch.Tensor | None = None, valid: bool | torch.Tensor = True,
               camera_cut: bool = False) -> Frame:
    """A Frame with ``spp`` samples: radiance = scene radiance * (1 + noise * N(0, 1)), other buffers exact."""
    generator = torch.Generator().manual_seed(seed)
    _, height, width = scene["radiance"].shape
    radiance = scene["radiance"][None].repeat(spp, 1, 1, 1)
    if noise:
        radiance = radiance * (1 + noise * torch.randn(radiance.shape, generator=generator)).clamp_min(0)
    samples = {"radiance": radiance}
    for buffer in ("albedo", "normal", "position", "depth"):
        samples[buffer] = scene[buffer][None].repeat(spp, 1, 1, 1)
    # flags: (emissive, metallic, transmissive, specular bounce); all surfaces unless the scene says so
    flags = scene.get("flags", torch.zeros(4, height, width))
    samples["flags"] = flags[None].repeat(spp, 1, 1, 1)
    if isinstance(valid, bool):
        valid = torch.full((1, height, width), float(valid and index > 0))
    pixel = {"motion": torch.zeros(2, height, width) if motion is None else motion, "valid": valid,
             "gbuffer.depth": scene["depth"], "gbuffer.normal": scene["normal"]}
    return Frame(samples=samples, pixel=pixel, index=index, camera_cut=camera_cut)


def psnr(a: torch.Tensor, b: torch.Tensor, peak: float) -> float:
    return 10 * math.log10(peak ** 2 / float(((a - b) ** 2).mean()))


def run(method: registry.Denoiser, frames: list[Frame]) -> list[torch.Tensor]:
    method.reset()
    return [method.denoise(frame) for frame in frames]


# -------------------------------------------------------------------------------------------------
# filters.py helpers
# -------------------------------------------------------------------------------------------------

def test_luminance_rec709_and_sanitize() -> None:
    rgb = torch.eye(3).view(3, 3, 1, 1).expand(3, 3, 2, 2)                 # pure R, G, B images
    assert torch.allclose(luminance(rgb)[:, 0, 0, 0], torch.tensor([0.2126, 0.7152, 0.0722]))
    x = torch.tensor([1.0, float("nan"), float("inf"), -float("inf"), 3e30, -2.0])
    assert sanitize(x).tolist() == [1.0, 0.0, 0.0, 0.0, filters.SANITIZE_LIMIT, -2.0]
    assert filters.count_nonfinite(x) == 3


def test_b3_kernel_and_gaussian_blur() -> None:
    kernel = b3_kernel_2d()
    assert kernel.shape == (5, 5) and abs(float(kernel.sum()) - 1) < 1e-6
    assert kernel[2, 2] == pytest.approx((3 / 8) ** 2) and kernel[0, 0] == pytest.approx(1 / 256)
    x = torch.rand(2, 7, 9, generator=torch.Generator().manual_seed(1))
    h = torch.tensor([0.25, 0.5, 0.25])
    weights = torch.outer(h, h).expand(2, 1, 3, 3)
    expected = F.conv2d(x[None], weights, padding=1, groups=2)[0] / F.conv2d(torch.ones(1, 1, 7, 9), weights[:1],
                                                                               padding=1)[0]
    assert torch.allclose(gaussian_blur_3x3(x), expected, atol=1e-6)


def test_warp_previous_integer_shift_by_hand() -> None:
    prev = torch.arange(12, dtype=torch.float32).view(1, 3, 4)              # rows [0..3], [4..7], [8..11]
    motion = torch.zeros(2, 3, 4)
    motion[0] = 1.0                                                        # previous position one pixel right
    expected = torch.tensor([[1, 2, 3, 3], [5, 6, 7, 7], [9, 10, 11, 11]], dtype=torch.float32)[None]
    assert torch.equal(warp_previous(prev, motion), expected)
    motion = torch.zeros(2, 3, 4)
    motion[1] = -1.0                                                       # one row up, clamped at the top
    assert torch.equal(warp_previous(prev, motion), torch.cat([prev[:, :1], prev[:, :2]], dim=1))
    motion = torch.full((2, 3, 4), 0.5)                                    # mean of a 2x2 block
    assert warp_previous(prev, motion)[0, 0, 0] == pytest.approx((0 + 1 + 4 + 5) / 4)


def test_warp_previous_matches_numpy_reference_and_batches() -> None:
    generator = torch.Generator().manual_seed(2)
    prev = torch.rand(2, 3, 9, 11, generator=generator)
    motion = torch.randn(2, 9, 11, generator=generator) * 3
    warped = warp_previous(prev, motion)
    for n in range(2):
        expected = warp_previous_numpy(prev[n].numpy(), motion.numpy())
        assert np.allclose(warped[n].numpy(), expected, atol=1e-5)
        assert torch.allclose(warp_previous(prev[n], motion), warped[n])
    with pytest.raises(ValueError, match="motion"):
        warp_previous(prev, torch.zeros(2, 3, 3))


def test_bilinear_taps_reproduce_warp_inside_the_image() -> None:
    generator = torch.Generator().manual_seed(3)
    image = torch.rand(2, 10, 12, generator=generator)
    motion = torch.rand(2, 10, 12, generator=generator) * 2 - 1
    indices, weights, inside = bilinear_taps(motion)
    assert torch.allclose(weights.sum(dim=0), torch.ones(10, 12))
    interpolated = (gather_taps(image, indices) * weights[:, None]).sum(dim=0)
    fully_inside = inside.all(dim=0)
    assert fully_inside.float().mean() > 0.5
    assert torch.allclose(interpolated[:, fully_inside], warp_previous(image, motion)[:, fully_inside], atol=1e-5)


def _atrous_reference(values, step, log_weight, variance):
    """Direct evaluation of the a-trous sum: every tap, zero padding, weights from ``log_weight(p, q, o)``."""
    _, height, width = values.shape
    kernel = b3_kernel_2d()
    numerator = torch.zeros_like(values)
    weight_sum, variance_sum = torch.zeros(1, height, width), torch.zeros(1, height, width)
    for i in range(-2, 3):
        for j in range(-2, 3):
            dy, dx = i * step, j * step
            ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
            qy, qx = ys + dy, xs + dx
            inside = ((qy >= 0) & (qy < height) & (qx >= 0) & (qx < width))[None].float()
            qy, qx = qy.clamp(0, height - 1), qx.clamp(0, width - 1)
            weight = (torch.ones(1, height, width) if (i, j) == (0, 0)
                      else torch.exp(log_weight(ys, xs, qy, qx, dy, dx))) * kernel[i + 2, j + 2] * inside
            numerator += values[:, qy, qx] * weight
            weight_sum += weight
            variance_sum += variance[:, qy, qx] * weight ** 2
    return numerator / weight_sum, variance_sum / weight_sum ** 2


@pytest.mark.parametrize("step", [1, 2, 8, 32])
def test_atrous_step_matches_direct_evaluation(step: int) -> None:
    generator = torch.Generator().manual_seed(step)
    values = torch.rand(3, 13, 17, generator=generator)
    guide = torch.rand(2, 13, 17, generator=generator)
    scale = torch.rand(1, 13, 17, generator=generator) * 3
    variance = torch.rand(1, 13, 17, generator=generator)

    def pair_terms(at_p, at_q):  # S = -|g_p - g_q|^2 / 2, U = |g_p - g_q|_1
        difference = at_p["g"] - at_q["g"]
        return -difference.square().sum(0, keepdim=True) / 2, [difference.abs().sum(0, keepdim=True)]

    def centre_scales(dy, dx):
        return [scale * (1 + abs(dy) + abs(dx))]

    def log_weight(ys, xs, qy, qx, dy, dx):
        difference = guide[:, ys, xs] - guide[:, qy, qx]
        return (-difference.square().sum(0, keepdim=True) / 2
                - scale * (1 + abs(dy) + abs(dx)) * difference.abs().sum(0, keepdim=True))

    filtered, filtered_variance = atrous_step(values, step, {"g": guide}, pair_terms, centre_scales, variance)
    expected, expected_variance = _atrous_reference(values, step, log_weight, variance)
    assert torch.allclose(filtered, expected, atol=1e-5)
    assert torch.allclose(filtered_variance, expected_variance, atol=1e-5)


# -------------------------------------------------------------------------------------------------
# EAW
# -------------------------------------------------------------------------------------------------

def test_eaw_keeps_a_constant_image_constant() -> None:
    scene = two_planes()
    scene["radiance"] = torch.full((3, H, W), 0.7)
    out = registry.build("eaw").denoise(make_frame(scene, spp=2))
    assert torch.allclose(out, torch.full_like(out, 0.7), rtol=1e-5)


def test_eaw_passes_noise_free_input_nearly_unchanged() -> None:
    # Geometric edges are kept by the normal and position terms (a ramp, however, would be flattened by
    # the 125-pixel footprint, which is one-sided near the plane boundary) ...
    scene = two_planes(textured=False, ramp=0.0)
    out = registry.build("eaw").denoise(make_frame(scene, spp=2))
    assert psnr(out, scene["radiance"], peak=1.0) > 40
    # ... texture edges only by the colour term, which the default sigma (tuned for 1-4 spp) leaves wide.
    scene = two_planes(textured=True, ramp=0.0)
    out = registry.build("eaw", {"sigma_color": 0.1}).denoise(make_frame(scene, spp=2))
    assert psnr(out, scene["radiance"], peak=1.0) > 40


def test_eaw_denoises_and_keeps_the_edge() -> None:
    scene = two_planes()
    scene["radiance"] = torch.where(torch.arange(W) < W // 2, 0.2, 1.0).expand(3, H, W).clone()
    frame = make_frame(scene, spp=1, noise=0.5, seed=4)
    noisy = frame.mean("radiance")
    out = registry.build("eaw").denoise(frame)
    clean = scene["radiance"]
    assert float((out - clean).abs().mean()) < 0.25 * float((noisy - clean).abs().mean())
    # The edge between columns W/2 - 1 and W/2 keeps at least 90 % of its contrast.
    step = float(out[:, :, W // 2].mean() - out[:, :, W // 2 - 1].mean())
    assert step > 0.9 * 0.8


def test_eaw_colour_scale_ignores_a_bright_environment() -> None:
    # 80 % of the frame sees a bright environment (emissive flag set, radiance 100); the surface strip
    # (radiance 0.5, noisy) must still be denoised: a colour sigma scaled by the whole frame's mean
    # luminance (about 80) would be wide enough to blur the environment into the surface.
    scene = two_planes(textured=False, ramp=0.0)
    environment = torch.arange(W) < (4 * W) // 5
    scene["radiance"] = torch.where(environment, 100.0, 0.5).expand(3, H, W).clone()
    scene["flags"] = torch.zeros(4, H, W)
    scene["flags"][0] = environment.float().expand(H, W)
    frame = make_frame(scene, spp=1, noise=0.5, seed=6)
    surface = ~environment.expand(H, W)
    out = registry.build("eaw").denoise(frame)
    noisy_error = float((frame.mean("radiance") - scene["radiance"]).abs()[:, surface].mean())
    eaw_error = float((out - scene["radiance"]).abs()[:, surface].mean())
    assert eaw_error < 0.5 * noisy_error, (eaw_error, noisy_error)


def test_eaw_output_scales_with_exposure() -> None:
    frame = make_frame(two_planes(), spp=2, noise=0.5, seed=5)
    bright = make_frame(two_planes(), spp=2, noise=0.5, seed=5)
    bright.samples["radiance"] = frame.samples["radiance"] * 20
    eaw = registry.build("eaw")
    assert torch.allclose(eaw.denoise(bright), 20 * eaw.denoise(frame), rtol=1e-4, atol=1e-5)


# -------------------------------------------------------------------------------------------------
# SVGF
# -------------------------------------------------------------------------------------------------

def test_svgf_keeps_a_constant_illumination_constant_over_frames() -> None:
    scene = two_planes()
    scene["radiance"] = 0.5 * scene["albedo"]              # textured, but constant illumination
    outputs = run(registry.build("svgf"), [make_frame(scene, index=t, spp=2) for t in range(5)])
    for out in outputs:
        assert torch.allclose(out, scene["radiance"], rtol=1e-5, atol=1e-6)


def test_svgf_passes_noise_free_input_nearly_unchanged() -> None:
    scene = two_planes()
    outputs = run(registry.build("svgf"), [make_frame(scene, index=t, spp=2) for t in range(3)])
    for out in outputs:
        assert psnr(out, scene["radiance"], peak=1.0) > 40


def test_svgf_converges_towards_the_mean_on_a_static_sequence() -> None:
    scene = two_planes()
    frames = [make_frame(scene, index=t, spp=1, noise=0.5, seed=10 + t) for t in range(10)]
    errors = [float((out - scene["radiance"]).abs().mean()) for out in run(registry.build("svgf"), frames)]
    noisy_error = float((frames[0].mean("radiance") - scene["radiance"]).abs().mean())
    assert errors[0] < 0.5 * noisy_error
    # The variance estimate (from per-sample moments) does not shrink with the history, so the spatial
    # blur -- and its bias -- stays; the gain over frames is the temporal averaging on top.
    assert np.mean(errors[-3:]) < 0.7 * errors[0], errors
    assert errors[-1] < errors[1] < errors[0]


def test_svgf_uses_motion_vectors() -> None:
    """A pattern scrolling one pixel per frame: correct motion vectors beat zero motion."""
    base = two_planes(H, W + 12)
    ramp = (0.5 + 0.5 * torch.sin(torch.arange(W + 12, dtype=torch.float32) / 2.0)).view(1, 1, -1)
    base["radiance"] = base["albedo"] * ramp                 # illumination varies along x
    errors = {}
    for name, dx in (("correct", 1.0), ("zero", 0.0)):
        frames, truths = [], []
        for t in range(8):
            scene = {k: v[:, :, t:t + W] for k, v in base.items()}
            # Geometry stays put (a scrolling texture on a static scene): every pixel is consistent.
            scene.update({k: base[k][:, :, :W] for k in ("normal", "position", "depth")})
            motion = torch.zeros(2, H, W)
            motion[0] = dx                                   # the content was one pixel to the right
            frames.append(make_frame(scene, index=t, spp=1, noise=0.4, seed=30 + t, motion=motion))
            truths.append(scene["radiance"])
        outputs = run(registry.build("svgf"), frames)
        errors[name] = np.mean([float((o - r).abs()[:, :, 2:].mean()) for o, r in zip(outputs[4:], truths[4:])])
    assert errors["correct"] < 0.5 * errors["zero"], errors


def test_svgf_restarts_history_on_camera_cut_gap_and_invalid_pixels() -> None:
    scene = two_planes()
    frames = [make_frame(scene, index=t, spp=1, noise=0.5, seed=50 + t) for t in range(5)]
    svgf = registry.build("svgf")
    run(svgf, frames[:4])
    fresh = registry.build("svgf")
    cut = make_frame(scene, index=4, spp=1, noise=0.5, seed=54, camera_cut=True)
    assert torch.equal(svgf.denoise(cut), fresh.denoise(cut))            # camera cut = no history
    run(svgf, frames[:4])
    gap = make_frame(scene, index=9, spp=1, noise=0.5, seed=54)          # frame 5..8 missing
    assert torch.equal(svgf.denoise(gap), registry.build("svgf").denoise(gap))
    run(svgf, frames[:4])
    svgf.reset()
    assert torch.equal(svgf.denoise(frames[4]), registry.build("svgf").denoise(frames[4]))

    run(svgf, frames[:4])
    valid = torch.ones(1, H, W)
    valid[:, :8, :8] = 0
    svgf.denoise(make_frame(scene, index=4, spp=1, noise=0.5, seed=54, valid=valid))
    length = svgf._history.length
    assert torch.all(length[:, :8, :8] == 1) and torch.all(length[:, 8:, 8:] == 5)


def test_svgf_history_reprojection_rejects_inconsistent_depth() -> None:
    scene = two_planes()
    svgf = registry.build("svgf")
    run(svgf, [make_frame(scene, index=t, spp=1) for t in range(3)])
    moved = dict(scene)
    moved["depth"] = scene["depth"] * torch.where(torch.arange(W) < 10, 2.0, 1.0)   # left columns jumped
    svgf.denoise(make_frame(moved, index=3, spp=1))
    assert torch.all(svgf._history.length[:, :, :9] == 1) and torch.all(svgf._history.length[:, :, 11:] == 4)


def test_svgf_sparse_and_dense_spatial_variance_agree(monkeypatch) -> None:
    from denoisers.methods import svgf as svgf_module
    from denoisers.methods import svgf_terms

    generator = torch.Generator().manual_seed(7)
    scene = two_planes()
    moments = torch.rand(2, H, W, generator=generator)
    where = torch.rand(1, H, W, generator=generator) < 0.1
    svgf = registry.build("svgf")
    gradient = svgf_terms.depth_gradient(scene["depth"])
    monkeypatch.setattr(svgf_module, "SPARSE_VARIANCE_FRACTION", 1.0)
    sparse = svgf._spatial_moments(moments, scene["normal"], scene["depth"], gradient, where)
    monkeypatch.setattr(svgf_module, "SPARSE_VARIANCE_FRACTION", 0.0)
    dense = svgf._spatial_moments(moments, scene["normal"], scene["depth"], gradient, where)
    assert torch.allclose(sparse[:, where[0]], dense[:, where[0]], atol=1e-5)


def test_svgf_output_scales_with_exposure() -> None:
    scene = two_planes()
    frames = [make_frame(scene, index=t, spp=2, noise=0.5, seed=60 + t) for t in range(3)]
    bright = [make_frame(scene, index=t, spp=2, noise=0.5, seed=60 + t) for t in range(3)]
    for frame in bright:
        frame.samples["radiance"] = frame.samples["radiance"] * 20
    for dim, bright_out in zip(run(registry.build("svgf"), frames), run(registry.build("svgf"), bright)):
        assert torch.allclose(bright_out, 20 * dim, rtol=1e-3, atol=1e-4)


# -------------------------------------------------------------------------------------------------
# OIDN
# -------------------------------------------------------------------------------------------------

def test_oidn_keeps_a_constant_image_nearly_constant() -> None:
    pytest.importorskip("pyoidn")
    scene = two_planes()
    scene["radiance"] = torch.full((3, H, W), 0.7)
    scene["albedo"] = torch.full((3, H, W), 0.7)
    oidn = registry.build("oidn")
    out = oidn.denoise(make_frame(scene, spp=2))
    assert out.shape == (3, H, W)
    error = (out - 0.7).abs()
    # OIDN leaves a few percent of wobble at the image corners; the bulk is flat.
    assert float(error.mean()) < 0.01 * 0.7 and float(error.quantile(0.95)) < 0.02 * 0.7
    # Another size rebuilds the filter.
    small = {k: v[:, :16, :20] for k, v in scene.items()}
    assert oidn.denoise(make_frame(small, spp=1)).shape == (3, 16, 20)


def _oidn_direct(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """OIDN's RT filter called straight through pyoidn (one thread, HDR, quality high), (3, H, W) images."""
    import pyoidn

    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    device.set_int("numThreads", 1)
    device.commit()
    oidn_filter = pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT)
    images = {name: np.ascontiguousarray(image.transpose(1, 2, 0), dtype=np.float32)
              for name, image in (("color", color), ("albedo", albedo), ("normal", normal))}
    images["output"] = np.zeros_like(images["color"])
    for name, image in images.items():
        oidn_filter.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
    oidn_filter.set_bool("hdr", True)
    oidn_filter.set_int("quality", pyoidn.OIDN_QUALITY_HIGH)
    oidn_filter.commit()
    oidn_filter.execute()
    assert device.get_error() is None
    output = images["output"].transpose(2, 0, 1).copy()
    oidn_filter.release()
    device.release()
    return output


def test_oidn_gets_albedo_and_normal_in_their_own_slots() -> None:
    """A scene whose edges OIDN can only find in the auxiliary images: a checker texture that exists in
    the albedo (and in the very noisy colour), and a fold between two planes that exists in the normal.
    The wrapper must equal OIDN called directly with the mean albedo as albedo and the mean normal as
    normal, and beat the same call with albedo and normal swapped or with the albedo scaled out of
    range (summed over the samples instead of averaged: OIDN clips it to 1 and the texture is lost)."""
    pytest.importorskip("pyoidn")
    height, width, spp = 48, 64, 4
    ys, xs = np.mgrid[0:height, 0:width]
    checker = ((xs // 8 + ys // 8) % 2).astype(np.float64)
    left = (xs < width // 2)[None]
    albedo = np.stack([0.15 + 0.7 * checker, 0.15 + 0.6 * checker, 0.1 + 0.5 * checker])
    normal = np.where(left, np.array([0.0, 0.0, 1.0])[:, None, None], np.array([0.0, 1.0, 0.0])[:, None, None])
    clean = albedo * np.where(left, 1.0, 0.5)
    rng = np.random.default_rng(0)
    radiance = clean[None] * rng.exponential(1.0, (spp, 1, height, width))       # heavy per-sample noise
    frame = Frame(samples={"radiance": torch.from_numpy(radiance.astype(np.float32)),
                           "albedo": torch.from_numpy(np.repeat(albedo[None], spp, 0).astype(np.float32)),
                           "normal": torch.from_numpy(np.repeat(normal[None], spp, 0).astype(np.float32))})
    out = registry.build("oidn").denoise(frame).numpy()

    color = radiance.astype(np.float32).mean(axis=0)
    expected = _oidn_direct(color, albedo, normal)
    wrong = {"swapped": _oidn_direct(color, normal, albedo), "summed albedo": _oidn_direct(color, spp * albedo, normal)}

    def rmse(image: np.ndarray) -> float:
        return float(np.sqrt(np.mean((image - clean) ** 2)))

    # The auxiliary images decide the result here: the wrong ones are far from the right call (1000x the
    # tolerance below) and have at least 1.5x its error against the noise-free image.
    for name, image in wrong.items():
        assert np.abs(image - expected).max() > 0.1, name
        assert 1.5 * rmse(expected) < rmse(image), (name, rmse(expected), rmse(image))
    np.testing.assert_allclose(out, expected, atol=1e-4)     # the inputs differ by float32 rounding only
    assert 1.5 * rmse(out) < min(rmse(image) for image in wrong.values()) and rmse(out) < 0.25 * rmse(color)


# -------------------------------------------------------------------------------------------------
# Robustness and the registry
# -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["eaw", "svgf", "oidn"])
def test_outputs_stay_finite_with_spikes_nan_and_inf(name: str) -> None:
    if name == "oidn":
        pytest.importorskip("pyoidn")
    scene = two_planes()
    method = registry.build(name)
    method.reset()
    generator = torch.Generator().manual_seed(8)
    for t in range(4):
        frame = make_frame(scene, index=t, spp=2, noise=0.5, seed=70 + t)
        radiance = frame.samples["radiance"]
        spikes = torch.rand(radiance.shape[0], 1, H, W, generator=generator) < 0.01
        radiance = torch.where(spikes, 500 * float(radiance.mean()), radiance)
        radiance[0, 0, 3, 4] = float("nan")
        radiance[1, 1, 5, 6] = float("inf")
        radiance[0, 2, 7, 8] = -float("inf")
        frame.samples["radiance"] = radiance
        frame.samples["normal"][0, :, 9, 9] = float("nan")
        frame.pixel["motion"][:, 2, 2] = float("inf")
        out = method.denoise(frame)
        assert out.shape == (3, H, W) and bool(torch.isfinite(out).all()), name


def _clip(omit_sample: tuple[str, ...] = (), omit_gbuffer: tuple[str, ...] = (), frames: int = 3) -> Clip:
    """A static in-memory clip of the two-planes scene, 2 sample layers, 16x20 pixels."""
    scene = two_planes(16, 20)

    def over_time(image: torch.Tensor) -> np.ndarray:  # (C, H, W) -> (T, C, H, W)
        return np.stack([image.numpy()] * frames)

    samples = {b: np.repeat(over_time(scene[b])[:, None], 2, axis=1)
               for b in ("radiance", "albedo", "normal", "position", "depth") if b not in omit_sample}
    if "flags" not in omit_sample:
        samples["flags"] = np.zeros((frames, 2, 4, 16, 20), np.float32)
    gbuffer = {key: over_time(scene[key]) for key in ("depth", "normal", "position") if key not in omit_gbuffer}
    gbuffer["object"] = np.zeros((frames, 1, 16, 20), np.float32)
    valid = np.ones((frames, 1, 16, 20), bool)
    valid[0] = False
    return Clip(scene="synthetic", frames=list(range(frames)), samples=samples,
                motion=np.zeros((frames, 2, 16, 20), np.float32), valid=valid, gbuffer=gbuffer, reference=None,
                meta=[{"camera_cut": False}] * frames)


@pytest.mark.parametrize("name", ["eaw", "svgf", "oidn"])
def test_methods_run_on_a_clip_through_the_registry(name: str) -> None:
    if name == "oidn":
        pytest.importorskip("pyoidn")
    method = registry.build(name)
    method.reset()
    outputs = [method.denoise(frame) for frame in registry.clip_frames(_clip(), method.info, spp=2)]
    assert len(outputs) == 3 and all(o.shape == (3, 16, 20) and torch.isfinite(o).all() for o in outputs)
    assert registry.get(name).info.temporal == (name == "svgf")


@pytest.mark.parametrize("name, omit_sample, omit_gbuffer, missing", [
    ("eaw", ("position",), (), "position"),
    ("svgf", ("albedo",), (), "albedo"),
    ("svgf", (), ("normal",), "gbuffer.normal"),
    ("oidn", ("normal",), (), "normal"),
])
def test_missing_buffer_names_buffer_and_method(name, omit_sample, omit_gbuffer, missing) -> None:
    info = registry.get(name).info
    with pytest.raises(MissingInputError) as error:
        list(registry.clip_frames(_clip(omit_sample, omit_gbuffer), info, spp=1))
    assert error.value.buffer == missing and error.value.method == name
    assert repr(missing) in str(error.value) and repr(name) in str(error.value)


@pytest.mark.parametrize("name", ["eaw", "svgf", "oidn"])
def test_mismatched_buffer_resolutions_give_a_clear_error(name: str) -> None:
    if name == "oidn":
        pytest.importorskip("pyoidn")
    frame = make_frame(two_planes(), spp=1)
    frame.samples["normal"] = frame.samples["normal"][..., :-1]
    with pytest.raises(ValueError, match=rf"{name}.*normal 32x39"):
        registry.build(name).denoise(frame)


def test_invalid_parameters_are_rejected() -> None:
    with pytest.raises(ValueError, match="sigma_color"):
        registry.build("eaw", {"sigma_color": 0})
    with pytest.raises(ValueError, match="alpha_color"):
        registry.build("svgf", {"alpha_color": 1.5})
    with pytest.raises(ValueError, match="method 'svgf': unknown parameter\\(s\\) 'sigma_x'"):
        registry.build("svgf", {"sigma_x": 1.0})
