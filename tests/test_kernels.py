"""Per-pixel kernel application (native and torch), the scale composition of Vogels et al. (Eq. 5) and
the motion-vector warp (denoisers/kernels.py, denoisers/native/kernels.cpp)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from denoisers import filters, kernels, native
from scenegen import motion as scene_motion


def direct_apply(image: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Slow explicit loop: out[c, y, x] = sum_t w[t, y, x] image[c, y + dy_t, x + dx_t], zero outside."""
    channels, height, width = image.shape
    size = int(round(weights.shape[0] ** 0.5))
    radius = size // 2
    out = torch.zeros(channels, height, width, dtype=torch.float64)
    for y in range(height):
        for x in range(width):
            for i in range(size):
                for j in range(size):
                    sy, sx = y + i - radius, x + j - radius
                    if 0 <= sy < height and 0 <= sx < width:
                        out[:, y, x] += float(weights[i * size + j, y, x]) * image[:, sy, sx].double()
    return out


def random_case(channels: int, height: int, width: int, size: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    image = torch.rand(channels, height, width, generator=generator) * 4 - 1
    weights = torch.softmax(torch.randn(size * size, height, width, generator=generator), dim=0)
    return image, weights


def native_available() -> bool:
    return native.enabled() and native.load_kernels() is not None


@pytest.mark.parametrize("size", [1, 3, 5])
def test_torch_reference_matches_direct_evaluation(size: int) -> None:
    image, weights = random_case(3, 7, 9, size)
    torch.testing.assert_close(kernels.apply_kernels_torch(image, weights).double(), direct_apply(image, weights),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("size", [3, 5, 7])
def test_native_matches_direct_evaluation(size: int) -> None:
    if not native_available():
        pytest.skip("native kernel extension unavailable (see the denoisers.native warning)")
    image, weights = random_case(3, 6, 11, size, seed=size)      # smaller than the kernel in places: all borders
    out = kernels.apply_kernels(image, weights, backend="native")
    assert out.dtype == torch.float32 and out.shape == image.shape
    torch.testing.assert_close(out.double(), direct_apply(image, weights), rtol=1e-5, atol=1e-6)
    # Unnormalised weights (the caller's business) and a batch of two.
    batch = torch.stack([image, -image]), torch.stack([weights * 3, weights - 0.01])
    torch.testing.assert_close(kernels.apply_kernels(*batch, backend="native"),
                               kernels.apply_kernels_torch(*batch), rtol=1e-5, atol=1e-5)


def test_native_results_do_not_depend_on_the_thread_count() -> None:
    if not native_available():
        pytest.skip("native kernel extension unavailable")
    image, weights = random_case(3, 64, 40, 5, seed=9)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = kernels.apply_kernels(image, weights, backend="native")
        torch.set_num_threads(2)
        two = kernels.apply_kernels(image, weights, backend="native")
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)


def test_fallback_without_native_and_gradients_use_the_torch_path(monkeypatch: pytest.MonkeyPatch) -> None:
    image, weights = random_case(2, 5, 6, 3)
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "0")
    torch.testing.assert_close(kernels.apply_kernels(image, weights), kernels.apply_kernels_torch(image, weights))
    with pytest.raises(RuntimeError, match="native kernel application unavailable"):
        kernels.apply_kernels(image, weights, backend="native")
    monkeypatch.delenv(native.ENVIRONMENT_SWITCH)
    trainable = weights.clone().requires_grad_(True)
    assert kernels.apply_kernels(image, trainable).grad_fn is not None       # auto picks the torch path


def test_backward_of_the_torch_path() -> None:
    image, weights = random_case(2, 4, 5, 3, seed=2)
    image, weights = image.double().requires_grad_(True), weights.double().requires_grad_(True)
    assert torch.autograd.gradcheck(kernels.apply_kernels_torch, (image, weights))
    # The gradient with respect to a weight is the tap value it multiplies (zero outside the image).
    out = kernels.apply_kernels_torch(image, weights)
    out[:, 0, 0].sum().backward()
    expected = torch.zeros_like(weights)
    for t in range(9):
        dy, dx = t // 3 - 1, t % 3 - 1
        if dy >= 0 and dx >= 0:
            expected[t, 0, 0] = image[:, dy, dx].sum()
    torch.testing.assert_close(weights.grad, expected)


def test_bad_shapes_are_rejected() -> None:
    image, weights = random_case(3, 4, 4, 5)
    with pytest.raises(ValueError, match="k\\*k taps with k odd"):
        kernels.apply_kernels(image, weights[:16])
    with pytest.raises(ValueError, match="differ"):
        kernels.apply_kernels(image, weights[:, :3])


# ------------------------------------------------------------------------------------------------
# Scale composition (Vogels et al. Eq. 5, Hasselgren et al. Eq. 3)
# ------------------------------------------------------------------------------------------------

def test_compose_scales_hand_computed() -> None:
    fine = torch.tensor([[[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]]])       # (1, 2, 4)
    coarse = torch.tensor([[[10.0, 20.0]]])                                    # (1, 1, 2)
    # D fine = [[3.5, 5.5]]; o = fine + 0.5 (U coarse - U D fine) = fine + 0.5 [6.5, 6.5, 14.5, 14.5].
    out = kernels.compose_scales(fine, coarse, torch.full((2, 4), 0.5))
    expected = torch.tensor([[[4.25, 5.25, 10.25, 11.25], [8.25, 9.25, 14.25, 15.25]]])
    torch.testing.assert_close(out, expected)
    # Per-pixel alpha: 0 keeps the fine pixel, 1 swaps its 2x2 block mean for the coarse value.
    alpha = torch.tensor([[0.0, 1.0, 0.0, 1.0], [1.0, 0.0, 1.0, 0.0]])
    expected = torch.tensor([[[1.0, 2.0 + 6.5, 3.0, 4.0 + 14.5], [5.0 + 6.5, 6.0, 7.0 + 14.5, 8.0]]])
    torch.testing.assert_close(kernels.compose_scales(fine, coarse, alpha), expected)
    # Alpha given at the coarse resolution is upsampled (nearest).
    torch.testing.assert_close(kernels.compose_scales(fine, coarse, torch.tensor([[0.5, 0.5]])),
                               kernels.compose_scales(fine, coarse, torch.full((2, 4), 0.5)))


def test_compose_multiscale_hand_computed_three_levels() -> None:
    full = torch.arange(16.0).view(1, 4, 4)
    half = torch.tensor([[[1.0, 2.0], [3.0, 4.0]]])
    quarter = torch.tensor([[[10.0]]])
    # Coarsest first: middle = half + 0.5 (10 - mean(half) = 7.5) = half + 3.75.
    middle = half + 3.75
    # Then full + 1.0 (U middle - U D full) with alpha 1.
    expected = full - kernels.upsample(kernels.downsample(full), (4, 4)) + kernels.upsample(middle, (4, 4))
    assert expected[0, 0, 0] == pytest.approx(0.0 - 2.5 + 4.75)        # D full at block (0, 0) = 2.5
    out = kernels.compose_multiscale([full, half, quarter], [torch.ones(4, 4), torch.full((2, 2), 0.5)])
    torch.testing.assert_close(out, expected)


def test_consistent_pyramid_composes_to_the_fine_image_whatever_alpha() -> None:
    image = torch.rand(3, 9, 7)                                # odd sizes: D averages the partial blocks
    pyramid = [image, kernels.downsample(image), kernels.downsample(kernels.downsample(image))]
    alphas = [torch.rand(9, 7), torch.rand(5, 4)]
    torch.testing.assert_close(kernels.compose_multiscale(pyramid, alphas), image)
    identity = [torch.zeros(25, *level.shape[-2:]) for level in pyramid]
    for weights in identity:
        weights[12] = 1.0                                      # the centre tap
    torch.testing.assert_close(kernels.multiscale_filter(image, identity, alphas), image)


def test_temporal_blend() -> None:
    current, history = torch.ones(3, 4, 4), torch.full((3, 4, 4), 3.0)
    identity = torch.zeros(9, 4, 4)
    identity[4] = 1.0
    out = kernels.temporal_blend(current, history, identity, torch.full((4, 4), 0.25))
    torch.testing.assert_close(out, torch.full((3, 4, 4), 1.5))


# ------------------------------------------------------------------------------------------------
# Warp of the previous output
# ------------------------------------------------------------------------------------------------

def test_warp_is_the_existing_motion_vector_warp() -> None:
    generator = torch.Generator().manual_seed(4)
    previous = torch.rand(3, 9, 12, generator=generator)
    motion = (torch.rand(2, 9, 12, generator=generator) - 0.5) * 8            # fractional, some off-screen
    warped = kernels.warp_previous(previous, motion)
    assert torch.equal(warped, filters.warp_previous(previous, motion))       # the one SVGF and RLS use
    np.testing.assert_allclose(warped.numpy(), scene_motion.warp_previous(previous.numpy(), motion.numpy()),
                               rtol=1e-5, atol=1e-5)
    batch = torch.stack([previous, 2 * previous])
    torch.testing.assert_close(kernels.warp_previous(batch, motion)[1], 2 * warped)
