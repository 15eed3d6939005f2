"""The hand-optimised hot loops of EAW and SVGF against the generic formulation they replace.

``filter_eaw`` and ``SVGF._atrous`` write the a-trous iterations out (base-2 exponentials, per-offset
geometric terms shared between iterations, both taps of a pair in one op on ``PairWorkspace`` views);
here they are compared with the same iterations run through ``atrous_step`` and the original per-pair
callbacks (``atrous_step`` itself is checked against a direct evaluation in test_filters.py). Inputs are
random, with zero normals, depth jumps and sizes at which some tap offsets leave the image. The a-trous
comparisons run on both implementations of the hot loops: the torch one (``MCDN_NATIVE=0``) and the native
kernels of ``denoisers.native`` (skipped when they cannot be built).
"""
from __future__ import annotations

import pytest
import torch

from denoisers import native, registry
from denoisers.filters import (PairRegion, PairWorkspace, atrous_step, bilinear_footprint, bilinear_taps,
                               gather_taps, gaussian_blur_3x3, luminance)
from denoisers.methods import svgf as svgf_module
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

def reference_svgf_atrous(svgf, illumination, variance, normal, depth, gradient):
    """The SVGF a-trous passes through atrous_step with the method's per-pair callbacks."""
    depth_scales = svgf._depth_scales(depth, gradient)
    filtered, history = illumination, illumination
    for i in range(svgf.iterations):
        luminance_scale = 1.0 / (svgf.sigma_luminance * gaussian_blur_3x3(variance).clamp_min_(0).sqrt_()
                                 + svgf_module.LUMINANCE_EPSILON)

        def centre_scales(dy, dx, luminance_scale=luminance_scale):
            return [luminance_scale, *depth_scales(dy, dx)]

        filtered, variance = atrous_step(filtered, 2 ** i, {"n": normal, "z": depth, "l": luminance(filtered)},
                                         svgf._all_terms, centre_scales, variance=variance)
        if i == 0:
            history = filtered
    return filtered, history


@pytest.mark.parametrize("height, width, params", [
    (40, 56, {}),                                   # defaults: sigma_n = 128, the log1p path
    (23, 37, {"sigma_normal": 16.0}),               # cosine floor < 0.5: the log path
    (70, 9, {"iterations": 3, "sigma_luminance": 1.0, "sigma_depth": 0.3}),
    (12, 12, {"iterations": 1}),
])
def test_svgf_atrous_matches_the_generic_atrous_step(backend: str, height: int, width: int, params: dict) -> None:
    guides = random_guides(height, width, seed=height * width)
    generator = torch.Generator().manual_seed(height)
    variance = torch.rand(1, height, width, generator=generator) ** 2
    svgf = registry.build("svgf", params)
    gradient = svgf_module._depth_gradient(guides["depth"])
    expected, expected_history = reference_svgf_atrous(svgf, guides["color"], variance, guides["normal"],
                                                       guides["depth"], gradient)
    for _ in range(2):                                            # a fresh and a reused workspace
        out, history = svgf._atrous(guides["color"], variance, guides["normal"], guides["depth"], gradient)
        assert torch.allclose(out, expected, rtol=1e-4, atol=1e-6)
        assert torch.allclose(history, expected_history, rtol=1e-4, atol=1e-6)


def reference_reproject(svgf, frame: Frame, depth: torch.Tensor, normal: torch.Tensor):
    """Consistency-weighted bilinear reprojection of the history, tap by tap with gather_taps."""
    history = svgf._history
    indices, weights, inside = bilinear_taps(frame.pixel["motion"])
    state = history.state
    taps = gather_taps(state, indices)                                    # (4, 10, H, W)
    valid = frame.pixel["valid"] > 0.5
    consistent = (inside[:, None] & valid
                  & ((taps[:, 6:7] - depth).abs() <= svgf.reprojection_depth_tolerance * depth)
                  & ((taps[:, 7:10] * normal).sum(dim=1, keepdim=True) >= svgf.reprojection_normal_cos))
    tap_weights = weights[:, None] * consistent
    weight_sum = tap_weights.sum(dim=0)
    previous = (taps[:, :6] * tap_weights).sum(dim=0) / weight_sum.clamp_min(svgf_module.MIN_REPROJECTION_WEIGHT)
    return previous, weight_sum > svgf_module.MIN_REPROJECTION_WEIGHT


def test_svgf_reprojection_matches_a_direct_evaluation() -> None:
    height, width = 19, 23
    guides = random_guides(height, width, seed=5)
    generator = torch.Generator().manual_seed(6)
    svgf = registry.build("svgf")
    state = torch.cat([torch.rand(6, height, width, generator=generator) * 3, guides["depth"], guides["normal"]])
    svgf._history = svgf_module._History(state=state, index=4)
    motion = torch.randn(2, height, width, generator=generator) * 2
    valid = (torch.rand(1, height, width, generator=generator) > 0.2).float()
    depth = guides["depth"] * (1 + 0.15 * torch.rand(1, height, width, generator=generator))  # some fail the test
    frame = Frame(samples={}, pixel={"motion": motion, "valid": valid}, index=5, camera_cut=False)
    previous, success = svgf._reproject(frame, depth, guides["normal"])
    expected, expected_success = reference_reproject(svgf, frame, depth, guides["normal"])
    assert 0.2 < float(expected_success.float().mean()) < 0.95
    assert torch.equal(success.bool(), expected_success)
    assert torch.allclose(previous, expected, rtol=1e-5, atol=1e-6)


def test_svgf_depth_gradient_takes_the_smaller_one_sided_difference() -> None:
    depth = torch.tensor([[1.0, 2.0, 2.5, 10.0], [1.0, 1.5, 3.0, 3.5]])[None]
    gradient = svgf_module._depth_gradient(depth)
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
