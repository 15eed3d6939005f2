"""The hand-optimised hot loops of EAW and SVGF against references that do not share their code.

``filter_eaw`` writes the a-trous iterations out (base-2 exponentials, per-offset geometric terms shared
between iterations, both taps of a pair in one op on ``PairWorkspace`` views); it is compared with the
same iterations run through ``atrous_step`` (itself checked against a direct evaluation in
test_filters.py). SVGF's a-trous passes, depth gradient and reprojection are compared with a float64
numpy evaluation of the documented formulas written in this file, which uses none of the helpers of
denoisers/filters.py or of the method. Inputs are random, with zero normals, depth jumps and sizes at
which some tap offsets leave the image. The a-trous comparisons run on both implementations of the hot
loops: the torch one (``MCDN_NATIVE=0``) and the native kernels of ``denoisers.native`` (skipped when
they cannot be built).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from denoisers import native, registry
from denoisers.filters import PairRegion, PairWorkspace, atrous_step, bilinear_footprint, bilinear_taps
from denoisers.methods import svgf_terms
from denoisers.methods.eaw import eaw_workspace, filter_eaw
from denoisers.registry import Frame


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(params=["torch", "native"])
def backend(request, monkeypatch) -> str:
    """Runs a test with the torch hot loops and with the native kernels."""
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "1" if request.param == "native" else "0")
    if request.param == "native" and native.load() is None:
        pytest.skip("native kernels unavailable")
    return request.param


def random_guides(height: int, width: int, seed: int) -> dict[str, torch.Tensor]:
    """Random colour (3), unit normals with a zero-normal hole (3), depth with a jump (1), all (C, H, W)."""
    generator = torch.Generator().manual_seed(seed)
    color = torch.rand(3, height, width, generator=generator) ** 3 * 4
    normal = torch.randn(3, height, width, generator=generator) * 0.3 + torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    normal = normal / normal.norm(dim=0, keepdim=True)
    normal[:, : height // 4, : width // 4] = 0.0                  # no surface there
    depth = 2.0 + torch.rand(1, height, width, generator=generator) * 0.05
    depth[:, :, width // 2:] += 1.5                               # an object edge
    return {"color": color, "normal": normal, "depth": depth}


# -------------------------------------------------------------------------------------------------
# PairWorkspace and bilinear_footprint
# -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dy, dx", [(0, 1), (1, -2), (2, 2), (3, 0), (1, 5)])
def test_pair_workspace_views_are_the_region_slices(dy: int, dx: int) -> None:
    height, width = 7, 9
    workspace = PairWorkspace(height, width, images={"image": 2}, doubled={"both": 3})
    workspace["image"].copy_(torch.arange(2 * height * width, dtype=torch.float32).view(2, height, width))
    workspace["both"].copy_(torch.randn(2, 3, height, width, generator=torch.Generator().manual_seed(dy * 7 + dx)))
    region = PairRegion(height, width, dy, dx)
    image, both = workspace["image"], workspace["both"]
    pair = workspace.pair("image", region)
    assert torch.equal(pair[0], region.at_first(image)) and torch.equal(pair[1], region.at_second(image))
    straight, crossed = workspace.straight("both", region), workspace.crossed("both", region)
    assert torch.equal(straight[0], region.at_first(both[0])) and torch.equal(straight[1], region.at_second(both[1]))
    assert torch.equal(crossed[0], region.at_second(both[0])) and torch.equal(crossed[1], region.at_first(both[1]))
    assert workspace.pair("image", region) is pair                      # cached
    # A write through the straight view lands in the two copies' regions and nowhere else.
    expected = both.clone()
    region.at_first(expected[0]).add_(1.0)
    region.at_second(expected[1]).add_(1.0)
    straight.add_(1.0)
    assert torch.equal(both, expected)
    with pytest.raises(ValueError):
        workspace.straight("image", region)


def test_bilinear_footprint_is_bilinear_taps_with_a_float_mask() -> None:
    generator = torch.Generator().manual_seed(4)
    motion = torch.randn(2, 11, 13, generator=generator) * 4
    motion[0, 1, 2] = float("nan")
    indices, weights, inside = bilinear_footprint(motion)
    expected_indices, expected_weights, expected_inside = bilinear_taps(motion)
    assert torch.equal(indices, expected_indices) and torch.equal(weights, expected_weights)
    assert inside.dtype == torch.float32 and torch.equal(inside.bool(), expected_inside)
    assert set(inside.unique().tolist()) <= {0.0, 1.0}


# -------------------------------------------------------------------------------------------------
# EAW
# -------------------------------------------------------------------------------------------------

def reference_eaw(color: torch.Tensor, geometry: torch.Tensor, sigma: float, iterations: int,
                  decay: float) -> torch.Tensor:
    """The EAW iterations through atrous_step: w = exp(-|f_p - f_q|^2), f = [c / sigma_i, geometry]."""

    def pair_terms(at_p, at_q):
        return -(at_p["f"] - at_q["f"]).square().sum(dim=0, keepdim=True), ()

    for i in range(iterations):
        features = torch.cat([color / (sigma * decay ** i), geometry])
        color, _ = atrous_step(color, 2 ** i, {"f": features}, pair_terms)
    return color


@pytest.mark.parametrize("height, width, iterations", [(40, 56, 5), (23, 17, 5), (9, 70, 3), (33, 33, 1)])
def test_filter_eaw_matches_the_generic_atrous_step(backend: str, height: int, width: int, iterations: int) -> None:
    guides = random_guides(height, width, seed=height + width)
    geometry = torch.cat([guides["normal"] / 0.5, guides["depth"].expand(3, height, width) / 0.25])
    sigma = 0.7
    expected = reference_eaw(guides["color"], geometry, sigma, iterations, 0.5)
    workspace = None
    for _ in range(2):                                            # a fresh and a reused workspace
        out = filter_eaw(guides["color"], geometry, sigma, iterations, 0.5, workspace)
        assert torch.allclose(out, expected, rtol=1e-4, atol=1e-6)
        workspace = eaw_workspace(height, width, 3, geometry.shape[0])


# -------------------------------------------------------------------------------------------------
# SVGF
# -------------------------------------------------------------------------------------------------

# The SVGF reference below is written from the documented formula (Schied et al. 2017 as the SVGF class
# docstring states it) in float64 numpy, with its own luminance, 3x3 blur, depth gradient, edge-stopping
# terms and bilinear taps: it shares no helper with denoisers/filters.py or denoisers/methods/svgf.py,
# so a bug in a helper both implementations use cannot cancel out.
SVGF_DEFAULTS = {"sigma_luminance": 4.0, "sigma_normal": 128.0, "sigma_depth": 1.0, "iterations": 5}
REC709 = np.array([0.2126, 0.7152, 0.0722])
B3 = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0


def shifted(image: np.ndarray, dy: int, dx: int) -> tuple[np.ndarray, np.ndarray]:
    """(image at q = p + (dy, dx) for every pixel p (0 where q is outside), (H, W) bool: q inside)."""
    height, width = image.shape[-2:]
    out = np.zeros_like(image)
    inside = np.zeros((height, width), bool)
    ys, xs = slice(max(0, -dy), min(height, height - dy)), slice(max(0, -dx), min(width, width - dx))
    if ys.stop <= ys.start or xs.stop <= xs.start:
        return out, inside
    qs, qx = slice(ys.start + dy, ys.stop + dy), slice(xs.start + dx, xs.stop + dx)
    out[..., ys, xs] = image[..., qs, qx]
    inside[ys, xs] = True
    return out, inside


def blur_3x3_float64(image: np.ndarray) -> np.ndarray:
    """[1, 2, 1] x [1, 2, 1] weighted mean over the neighbours inside the image."""
    total, norm = np.zeros_like(image), np.zeros(image.shape[-2:])
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            value, inside = shifted(image, dy, dx)
            weight = (2 - abs(dy)) * (2 - abs(dx))
            total += weight * value
            norm += weight * inside
    return total / norm


def depth_gradient_float64(depth: np.ndarray) -> np.ndarray:
    """(1, H, W) -> (2, H, W) [dz/dx, dz/dy]: of the forward and backward differences the smaller in
    magnitude (the only one at the image border)."""
    out = []
    for axis in (2, 1):
        d = np.diff(depth, axis=axis)
        forward = np.concatenate([d, np.take(d, [-1], axis=axis)], axis=axis)
        backward = np.concatenate([np.take(d, [0], axis=axis), d], axis=axis)
        out.append(np.where(np.abs(forward) <= np.abs(backward), forward, backward)[0])
    return np.stack(out)


def independent_svgf_atrous(illumination, variance, normal, depth, gradient, params: dict):
    """The variance-guided a-trous passes: for taps q = p + 2^i (a, b), a, b in -2..2, inside the image,
    w(p, q) = exp(max(sigma_n log max(0, n_p . n_q) - |z_p - z_q| / (sigma_z |grad z(p) . (q - p)| + eps_z(p))
                  - |l_p - l_q| / (sigma_l sqrt(g3x3(Var)(p)) + 1e-10), -60)),  w(p, p) = 1,
    eps_z(p) = 1e-3 z_p + 1e-6, weights h = B3(a) B3(b); out = sum h w c(q) / sum h w and
    Var_out = sum h^2 w^2 Var(q) / (sum h w)^2. Returns (output of the last pass, output of the first)."""
    p = {**SVGF_DEFAULTS, **params}
    c, var = illumination.astype(np.float64), variance.astype(np.float64)
    n, z, g = normal.astype(np.float64), depth.astype(np.float64), gradient.astype(np.float64)
    history = None
    for i in range(p["iterations"]):
        step = 2 ** i
        lum = np.tensordot(REC709, c, axes=1)[None]
        luminance_scale = 1.0 / (p["sigma_luminance"] * np.sqrt(np.maximum(blur_3x3_float64(var), 0)) + 1e-10)
        depth_eps = 1e-3 * z + 1e-6
        total, weight_sum, var_total = np.zeros_like(c), np.zeros_like(z), np.zeros_like(var)
        for a in range(-2, 3):
            for b in range(-2, 3):
                dy, dx = a * step, b * step
                c_q, inside = shifted(c, dy, dx)
                if not inside.any():
                    continue
                n_q, z_q, l_q, var_q = (shifted(x, dy, dx)[0] for x in (n, z, lum, var))
                if (a, b) == (0, 0):
                    w = np.ones_like(z)
                else:
                    with np.errstate(divide="ignore"):
                        log_w = p["sigma_normal"] * np.log(np.maximum((n * n_q).sum(0, keepdims=True), 0.0))
                    log_w -= np.abs(z - z_q) / (p["sigma_depth"] * np.abs(g[0:1] * dx + g[1:2] * dy) + depth_eps)
                    log_w -= np.abs(lum - l_q) * luminance_scale
                    w = np.exp(np.maximum(log_w, -60.0)) * inside
                hw = B3[a + 2] * B3[b + 2] * w
                total += hw * c_q
                weight_sum += hw
                var_total += hw ** 2 * var_q
        c, var = total / weight_sum, var_total / weight_sum ** 2
        if i == 0:
            history = c
    return c, history


@pytest.mark.parametrize("height, width, params", [
    (40, 56, {}),                                   # defaults: sigma_n = 128, the log1p path
    (23, 37, {"sigma_normal": 16.0}),               # cosine floor < 0.5: the log path
    (70, 9, {"iterations": 3, "sigma_luminance": 1.0, "sigma_depth": 0.3}),
    (12, 12, {"iterations": 1}),
])
def test_svgf_atrous_matches_an_independent_float64_evaluation(backend: str, height: int, width: int,
                                                                params: dict) -> None:
    guides = random_guides(height, width, seed=height * width)
    generator = torch.Generator().manual_seed(height)
    variance = torch.rand(1, height, width, generator=generator) ** 2
    svgf = registry.build("svgf", params)
    gradient = depth_gradient_float64(guides["depth"].double().numpy())
    expected, expected_history = independent_svgf_atrous(guides["color"].numpy(), variance.numpy(),
                                                         guides["normal"].numpy(), guides["depth"].numpy(),
                                                         gradient, params)
    # The edge-stopping terms are active: the output is far from the plain B3 blur of the same taps.
    plain, _ = independent_svgf_atrous(guides["color"].numpy(), variance.numpy() * 1e12,
                                       np.tile([[[0.0]], [[0.0]], [[1.0]]], (1, height, width)),
                                       np.full((1, height, width), 2.0), np.zeros((2, height, width)), params)
    assert np.abs(plain - expected).max() > 0.1
    for _ in range(2):                                            # a fresh and a reused workspace
        out, history = svgf._atrous(guides["color"], variance, guides["normal"], guides["depth"],
                                    torch.from_numpy(gradient).float())
        np.testing.assert_allclose(out.numpy(), expected, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(history.numpy(), expected_history, rtol=1e-4, atol=1e-6)


def test_svgf_depth_gradient_matches_an_independent_float64_evaluation() -> None:
    depth = random_guides(23, 31, seed=3)["depth"]
    np.testing.assert_allclose(svgf_terms.depth_gradient(depth).numpy(),
                               depth_gradient_float64(depth.double().numpy()), rtol=1e-5, atol=1e-6)


def independent_reproject(state: np.ndarray, motion: np.ndarray, valid: np.ndarray, depth: np.ndarray,
                          normal: np.ndarray, depth_tolerance: float, normal_cos: float):
    """Per pixel p: the previous position p + motion, its four bilinear taps (floor and floor + 1 per axis)
    with weights (1 - f)/f per axis; a tap counts if it lies in the image, the pixel is valid, and the tap's
    stored depth and normal pass |z_tap - z_p| <= tol z_p and n_tap . n_p >= cos. Returns (sum of the
    counted taps' weights x state[:6] / their weight sum, their weight sum)."""
    state, depth, normal = state.astype(np.float64), depth.astype(np.float64), normal.astype(np.float64)
    _, height, width = state.shape
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = xs + motion[0], ys + motion[1]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    previous, weight_sum = np.zeros((6, height, width)), np.zeros((1, height, width))
    for ty, wy in ((y0, 1 - fy), (y0 + 1, fy)):
        for tx, wx in ((x0, 1 - fx), (x0 + 1, fx)):
            inside = (tx >= 0) & (tx < width) & (ty >= 0) & (ty < height)
            tap = state[:, np.clip(ty, 0, height - 1).astype(int), np.clip(tx, 0, width - 1).astype(int)]
            consistent = (inside & (valid[0] > 0.5) & (np.abs(tap[6] - depth[0]) <= depth_tolerance * depth[0])
                          & ((tap[7:10] * normal).sum(0) >= normal_cos))
            weight = wy * wx * consistent
            previous += weight * tap[:6]
            weight_sum += weight
    return previous / np.where(weight_sum > 0, weight_sum, 1.0), weight_sum


def test_svgf_reprojection_matches_an_independent_float64_evaluation() -> None:
    height, width = 19, 23
    guides = random_guides(height, width, seed=5)
    generator = torch.Generator().manual_seed(6)
    svgf = registry.build("svgf")
    state = torch.cat([torch.rand(6, height, width, generator=generator) * 3, guides["depth"], guides["normal"]])
    svgf._history = svgf_terms.History(state=state, index=4)
    motion = torch.randn(2, height, width, generator=generator) * 2
    valid = (torch.rand(1, height, width, generator=generator) > 0.2).float()
    depth = guides["depth"] * (1 + 0.15 * torch.rand(1, height, width, generator=generator))  # some fail the test
    frame = Frame(samples={}, pixel={"motion": motion, "valid": valid}, index=5, camera_cut=False)
    previous, success = svgf._reproject(frame, depth, guides["normal"])
    # The documented thresholds: relative depth difference <= 0.1, n . n >= 0.9; success: weight > 0.01.
    expected, weight_sum = independent_reproject(state.numpy(), motion.numpy(), valid.numpy(), depth.numpy(),
                                                 guides["normal"].numpy(), 0.1, 0.9)
    expected_success = weight_sum > 0.01
    assert 0.2 < float(expected_success.mean()) < 0.95
    # Weight sums within float32 rounding of the 0.01 threshold could go either way.
    decided = np.abs(weight_sum - 0.01) > 1e-5
    np.testing.assert_array_equal(success.bool().numpy()[decided], expected_success[decided])
    where = np.broadcast_to(expected_success & decided, expected.shape)
    np.testing.assert_allclose(previous.numpy()[where], expected[where], rtol=1e-5, atol=1e-6)


def test_svgf_depth_gradient_takes_the_smaller_one_sided_difference() -> None:
    depth = torch.tensor([[1.0, 2.0, 2.5, 10.0], [1.0, 1.5, 3.0, 3.5]])[None]
    gradient = svgf_terms.depth_gradient(depth)
    # Row 0: forward differences 1, 0.5, 7.5; backward at x = 1 is 1, forward 0.5 -> 0.5; at x = 2 backward 0.5.
    assert torch.equal(gradient[0, 0], torch.tensor([1.0, 0.5, 0.5, 7.5]))
    assert torch.equal(gradient[1, :, 0], torch.zeros(2))
    assert torch.equal(gradient[1, :, 2], torch.tensor([0.5, 0.5]))


def test_svgf_workspace_follows_the_image_size() -> None:
    """Frames of another size in between give the same output as a fresh filter (buffers rebuilt)."""
    def frame(height, width, index, seed):
        guides = random_guides(height, width, seed)
        spp = 2
        noise = 1 + 0.3 * torch.rand(spp, 1, height, width)
        samples = {"radiance": guides["color"][None].repeat(spp, 1, 1, 1) * noise,
                   "albedo": torch.full((spp, 3, height, width), 0.5),
                   "normal": guides["normal"][None].repeat(spp, 1, 1, 1),
                   "depth": guides["depth"][None].repeat(spp, 1, 1, 1)}
        pixel = {"motion": torch.zeros(2, height, width), "valid": torch.ones(1, height, width),
                 "gbuffer.depth": guides["depth"], "gbuffer.normal": guides["normal"]}
        return Frame(samples=samples, pixel=pixel, index=index, camera_cut=True)

    torch.manual_seed(0)
    big, small = frame(24, 30, 0, 1), frame(11, 13, 0, 2)
    svgf = registry.build("svgf")
    first = svgf.denoise(big)
    svgf.denoise(small)
    assert torch.equal(svgf.denoise(big), first)
    assert torch.equal(registry.build("svgf").denoise(small), svgf.denoise(small))
