"""The native affinity kernel (denoisers/native/affinity.cpp) against the torch reference of
denoisers/affinity.py: random inputs over sizes, dilations and borders, the bandwidth-0 box filter, and
independence of the thread count; the same for the native backward (affinity_sums_backward, which
_AffinitySums.backward uses in float32) against the torch backward (_backward_torch)."""
from __future__ import annotations

import pytest
import torch

from denoisers import affinity, native


def require_native() -> None:
    if native.load_affinity() is None:
        pytest.skip("native affinity extension unavailable (see the denoisers.native warning, or MCDN_NATIVE=0)")


def random_case(dims: int, with_center: bool, seed: int, batch: int = 2, channels: int = 3, height: int = 17,
                width: int = 23):
    generator = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, channels, height, width, generator=generator) * 4 - 1
    features = torch.randn(batch, dims, height, width, generator=generator)
    neighbours = features + 0.3 * torch.randn(batch, dims, height, width, generator=generator)
    bandwidth = torch.rand(batch, 1, height, width, generator=generator) * 2
    center = torch.rand(batch, 1, height, width, generator=generator) if with_center else None
    return image, features, neighbours, bandwidth, center


@pytest.mark.parametrize("with_center", [False, True])
# (d, C) with C = 3 and d in {1, 2, 4, 8} take the fused per-tap loop, the others the unfused passes.
@pytest.mark.parametrize("dims, channels", [(1, 3), (8, 3), (3, 3), (8, 1)])
@pytest.mark.parametrize("dilation", [1, 2, 4])
@pytest.mark.parametrize("size", [1, 3, 5, 13])
def test_native_matches_torch_reference(size: int, dilation: int, dims: int, channels: int, with_center: bool) -> None:
    require_native()
    image, features, neighbours, bandwidth, center = random_case(dims, with_center, seed=size * 100 + dilation,
                                                                 channels=channels)
    # 13 x 4 reaches 24 pixels out: every tap of the largest kernels is outside for part of the 17 x 23 image.
    num, den = affinity.affinity_sums(image, features, bandwidth, center, size, dilation, neighbours=neighbours,
                                      backend="native")
    num_ref, den_ref = affinity._sums_torch(image, features, neighbours, bandwidth, center, size, dilation)
    assert num.shape == image.shape and den.shape == (2, 1, 17, 23)
    assert num.dtype == den.dtype == torch.float32
    torch.testing.assert_close(num, num_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(den, den_ref, rtol=1e-5, atol=1e-6)
    # The spatial kernel (neighbours = features) through the public default, against the torch backend.
    num, den = affinity.affinity_sums(image, features, bandwidth, center, size, dilation, backend="native")
    num_ref, den_ref = affinity.affinity_sums(image, features, bandwidth, center, size, dilation, backend="torch")
    torch.testing.assert_close(num, num_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(den, den_ref, rtol=1e-5, atol=1e-6)


def inside_taps(height: int, width: int, size: int, dilation: int) -> torch.Tensor:
    """(H, W): how many of the dilated k x k taps of each pixel fall inside the image (analytic: rows x columns)."""
    offsets = [(i - size // 2) * dilation for i in range(size)]
    rows = torch.tensor([sum(0 <= y + o < height for o in offsets) for y in range(height)], dtype=torch.float32)
    cols = torch.tensor([sum(0 <= x + o < width for o in offsets) for x in range(width)], dtype=torch.float32)
    return rows[:, None] * cols[None, :]


@pytest.mark.parametrize("size, dilation", [(3, 1), (5, 2), (13, 1), (7, 4)])
def test_zero_bandwidth_is_a_box_filter_over_the_inside_taps(size: int, dilation: int) -> None:
    require_native()
    height, width = 9, 14
    image, features, _, _, _ = random_case(4, False, seed=7, batch=1, height=height, width=width)
    bandwidth = torch.zeros(1, 1, height, width)
    num, den = affinity.affinity_sums(image, features, bandwidth, None, size, dilation, backend="native")
    count = inside_taps(height, width, size, dilation)
    assert torch.equal(den[0, 0], count)                 # sums of exact ones: exact
    # num is the plain sum of the inside taps: zero-padded box sum.
    padded = torch.nn.functional.pad(image.double(), [(size // 2) * dilation] * 4)
    box = torch.nn.functional.conv2d(padded, torch.ones(3, 1, size, size, dtype=torch.float64), groups=3,
                                     dilation=dilation)
    tolerance = 2e-5 * size * size                        # float sums of up to k*k values in [-1, 3]
    torch.testing.assert_close(num.double(), box, rtol=1e-5, atol=tolerance)
    # A unit centre weight leaves the box unchanged; centre weight 0 drops the centre tap from both sums.
    num_one, den_one = affinity.affinity_sums(image, features, bandwidth, torch.ones_like(bandwidth), size,
                                              dilation, backend="native")
    assert torch.equal(den_one, den) and torch.equal(num_one, num)
    num_zero, den_zero = affinity.affinity_sums(image, features, bandwidth, torch.zeros_like(bandwidth), size,
                                                dilation, backend="native")
    assert torch.equal(den_zero[0, 0], count - 1)
    torch.testing.assert_close(num_zero, num - image, rtol=1e-5, atol=tolerance)


def test_native_results_do_not_depend_on_the_thread_count() -> None:
    require_native()
    image, features, neighbours, bandwidth, center = random_case(8, True, seed=3, height=61, width=37)
    threads = torch.get_num_threads()
    results = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            for c in (center, None):
                results.append(affinity.affinity_sums(image, features, bandwidth, c, 5, 2, neighbours=neighbours,
                                                      backend="native"))
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(results[:2], results[2:]):
        assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_native_rejects_bad_shapes() -> None:
    require_native()
    module = native.load_affinity()
    image, features, neighbours, bandwidth, center = random_case(2, True, seed=1)
    with pytest.raises(RuntimeError, match="neighbours"):
        module.affinity_sums(image, features, neighbours[:, :1].contiguous(), bandwidth, center, 3, 1)
    with pytest.raises(RuntimeError, match="center"):
        module.affinity_sums(image, features, neighbours, bandwidth, center[..., :5].contiguous(), 3, 1)
    with pytest.raises(RuntimeError, match="odd"):
        module.affinity_sums(image, features, neighbours, bandwidth, center, 4, 1)
    with pytest.raises(RuntimeError, match="float32"):
        module.affinity_sums(image.double(), features, neighbours, bandwidth, None, 3, 1)


def backward_case(dims: int, with_center: bool, seed: int, height: int = 11, width: int = 14):
    """random_case inputs of odd size plus random output gradients (grad_num, grad_den)."""
    image, features, neighbours, bandwidth, center = random_case(dims, with_center, seed, height=height, width=width)
    generator = torch.Generator().manual_seed(seed + 1)
    grad_num = torch.randn(image.shape, generator=generator)
    grad_den = torch.randn(bandwidth.shape, generator=generator)
    return image, features, neighbours, bandwidth, center, grad_num, grad_den


def autograd_gradients(inputs, grad_num, grad_den, size: int, dilation: int, shared: bool):
    """d/d inputs of sum(num * grad_num) + sum(den * grad_den) through affinity_sums (backend "auto": the native
    kernels when available). With ``shared`` the neighbours are the features tensor itself, whose gradient
    autograd sums over both uses; its slot holds None then."""
    image, features, neighbours, bandwidth, center = (t.clone().requires_grad_() if t is not None else None
                                                      for t in inputs)
    neighbours = None if shared else neighbours
    num, den = affinity.affinity_sums(image, features, bandwidth, center, size, dilation, neighbours=neighbours)
    leaves = (image, features, neighbours, bandwidth, center)
    grads = iter(torch.autograd.grad((num * grad_num).sum() + (den * grad_den).sum(),
                                     [t for t in leaves if t is not None]))
    return [next(grads) if t is not None else None for t in leaves]


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("with_center", [False, True])
@pytest.mark.parametrize("dims", [1, 8])
@pytest.mark.parametrize("dilation", [1, 2, 4])
@pytest.mark.parametrize("size", [1, 3, 5, 13])
def test_native_backward_matches_torch_backward(size: int, dilation: int, dims: int, with_center: bool,
                                                shared: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    require_native()
    *inputs, grad_num, grad_den = backward_case(dims, with_center, seed=size * 100 + dilation * 10 + dims)
    # 13 x 4 reaches 24 pixels out of the 11 x 14 image: all but the centre tap are partly or wholly outside.
    got = autograd_gradients(inputs, grad_num, grad_den, size, dilation, shared)
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "0")       # load_affinity() None: torch forward and backward
    expected = autograd_gradients(inputs, grad_num, grad_den, size, dilation, shared)
    for name, a, b in zip(("image", "features", "neighbours", "bandwidth", "center"), got, expected):
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == torch.float32 and a.shape == b.shape, name
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=lambda m, name=name: f"{name}: {m}")


def test_native_backward_returns_only_the_needed_gradients() -> None:
    require_native()
    module = native.load_affinity()
    image, features, neighbours, bandwidth, center, grad_num, grad_den = backward_case(3, True, seed=5)
    args = (image, features, neighbours, bandwidth, center, grad_num, grad_den, 5, 2)
    full = module.affinity_sums_backward(*args, [True] * 5)
    reference = affinity._backward_torch(*args, (True,) * 5)
    for got, expected in zip(full, reference):
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5)
    for index in range(5):                         # each gradient alone: the same values, None elsewhere
        needs = [i == index for i in range(5)]
        alone = module.affinity_sums_backward(*args, needs)
        assert all((t is None) == (not need) for t, need in zip(alone, needs))
        assert torch.equal(alone[index], full[index])
    no_center = module.affinity_sums_backward(*args[:4], None, *args[5:], [True] * 5)
    assert no_center[4] is None and all(t is not None for t in no_center[:4])
    # Through autograd, only the inputs that require a gradient get one (here the bandwidth).
    bandwidth = bandwidth.clone().requires_grad_()
    num, den = affinity.affinity_sums(image, features, bandwidth, center, 5, 2, neighbours=neighbours)
    ((num * grad_num).sum() + (den * grad_den).sum()).backward()
    assert torch.equal(bandwidth.grad, full[3])


def test_native_backward_does_not_depend_on_the_thread_count() -> None:
    require_native()
    module = native.load_affinity()
    image, features, neighbours, bandwidth, center, grad_num, grad_den = backward_case(8, True, seed=3, height=61,
                                                                                        width=37)
    threads = torch.get_num_threads()
    results = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            for c in (center, None):
                results.append(module.affinity_sums_backward(image, features, neighbours, bandwidth, c, grad_num,
                                                             grad_den, 5, 2, [True] * 5))
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(results[:2], results[2:]):
        for a, b in zip(one, two):
            assert (a is None and b is None) or torch.equal(a, b)


def test_native_backward_rejects_bad_gradients() -> None:
    require_native()
    module = native.load_affinity()
    image, features, neighbours, bandwidth, center, grad_num, grad_den = backward_case(2, True, seed=1)
    with pytest.raises(RuntimeError, match="grad_num"):
        module.affinity_sums_backward(image, features, neighbours, bandwidth, center, grad_num[:, :2].contiguous(),
                                      grad_den, 3, 1, [True] * 5)
    with pytest.raises(RuntimeError, match="grad_den"):
        module.affinity_sums_backward(image, features, neighbours, bandwidth, center, grad_num, grad_den.double(),
                                      3, 1, [True] * 5)
    with pytest.raises(RuntimeError, match="5 flags"):
        module.affinity_sums_backward(image, features, neighbours, bandwidth, center, grad_num, grad_den, 3, 1,
                                      [True] * 4)


@pytest.mark.parametrize("dims", [1, 2, 4, 8])
@pytest.mark.parametrize("size, dilation", [(3, 1), (13, 2)])
def test_fused_backward_is_bit_identical_to_the_unfused_passes(dims: int, size: int, dilation: int) -> None:
    # Three colour channels take the fused backward loops; a fourth channel of zeros (zero image, zero grad_num)
    # sends the same problem through the unfused passes (only C = 3 is fused) and adds only exact +0 terms, so
    # every gradient must agree bit for bit.
    require_native()
    module = native.load_affinity()
    image, features, neighbours, bandwidth, center, grad_num, grad_den = backward_case(dims, True, seed=11 + dims,
                                                                                        height=19, width=29)
    pad = lambda t: torch.cat([t, torch.zeros_like(t[:, :1])], dim=1).contiguous()  # noqa: E731
    for c in (center, None):
        fused = module.affinity_sums_backward(image, features, neighbours, bandwidth, c, grad_num, grad_den,
                                              size, dilation, [True] * 5)
        unfused = module.affinity_sums_backward(pad(image), features, neighbours, bandwidth, c, pad(grad_num),
                                                grad_den, size, dilation, [True] * 5)
        assert torch.equal(fused[0], unfused[0][:, :3])
        for a, b in zip(fused[1:], unfused[1:]):
            assert (a is None and b is None) or torch.equal(a, b)
