"""Kernels from pairwise feature affinity (Isik et al. 2021, Sec. 3.4-3.5, Eq. 4-8).

One primitive, :func:`affinity_sums`, gives for every pixel p the numerator and denominator of a dilated
k x k affinity kernel applied to an image:

    w_t(p) = c(p)                                      for the centre tap when ``center`` is given,
    w_t(p) = exp(-a(p) * ||f(p) - g(p + o_t)||^2)      otherwise,
    num(p) = sum_t w_t(p) L(p + o_t),   den(p) = sum_t w_t(p),

with tap offsets o_t = dilation * (i - k // 2, j - k // 2), i, j = 0..k-1 (row-major, top-left first). Taps
outside the image get weight 0 (they are left out of both sums). The spatial kernels of Eq. 4/6 use
``g = f`` and the centre weight c; the temporal kernel of Eq. 7 uses g = the warped previous features and no
special centre. :func:`spatial_filter` is Eq. 6, :func:`joint_filter` Eq. 8 (the last spatial kernel
normalised jointly with the temporal one). ``EPS`` is the paper's epsilon = 1e-10.

:func:`gather_sums` is the same sum with weights predicted per tap (softmax of the network's k*k outputs, the
kernels of Bako et al. 2017 that Isik et al. Table 5 compares with), dilated the same way.

Gradients: :class:`_AffinitySums` computes the backward pass analytically, one tap at a time, from the saved
inputs, so training stores no (k*k, H, W) temporaries (memory of a few images, whatever k). The torch
implementation (:func:`_sums_torch`, :func:`_backward_torch`) is the reference; the native kernels
(denoisers/native/affinity.cpp, ``backend``) compute the same forward sums and gradients in passes over the
taps (the backward as two gathers, so without atomics and deterministic). Shapes: image (N, C, H, W), features / neighbours (N, d, H, W),
bandwidth a and centre c (N, 1, H, W); float32 (autocast is switched off inside).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from denoisers import native

EPS = 1e-10
BACKENDS = ("auto", "native", "torch")


def tap_offsets(size: int, dilation: int = 1) -> list[tuple[int, int]]:
    """(dy, dx) of the k x k taps, row-major from the top-left, scaled by ``dilation``."""
    if size < 1 or size % 2 == 0 or dilation < 1:
        raise ValueError(f"kernel size must be odd >= 1 and dilation >= 1, got size {size}, dilation {dilation}")
    radius = size // 2
    return [((i - radius) * dilation, (j - radius) * dilation) for i in range(size) for j in range(size)]


def _check(image: torch.Tensor, features: torch.Tensor, neighbours: torch.Tensor, bandwidth: torch.Tensor,
           center: torch.Tensor | None) -> None:
    n, _, height, width = image.shape
    expected = {"features": (features, None), "neighbours": (neighbours, features.shape[1]),
                "bandwidth": (bandwidth, 1), "center": (center, 1)}
    if image.dim() != 4:
        raise ValueError(f"affinity: image must be (N, C, H, W), got {tuple(image.shape)}")
    for name, (tensor, channels) in expected.items():
        if tensor is None:
            continue
        if tensor.dim() != 4 or tensor.shape[0] != n or tensor.shape[-2:] != (height, width) or (
                channels is not None and tensor.shape[1] != channels):
            raise ValueError(f"affinity: {name} {tuple(tensor.shape)} does not match image {tuple(image.shape)}"
                             + (f" with {channels} channel(s)" if channels is not None else ""))


def _window(padded: torch.Tensor, radius: int, dy: int, dx: int, height: int, width: int) -> torch.Tensor:
    """The (.., H, W) view of a tensor zero-padded by ``radius`` shifted by (dy, dx): value at p + (dy, dx)."""
    return padded[..., radius + dy:radius + dy + height, radius + dx:radius + dx + width]


def _sums_torch(image: torch.Tensor, features: torch.Tensor, neighbours: torch.Tensor, bandwidth: torch.Tensor,
                center: torch.Tensor | None, size: int, dilation: int) -> tuple[torch.Tensor, torch.Tensor]:
    n, channels, height, width = image.shape
    radius = (size // 2) * dilation
    pad = (radius, radius, radius, radius)
    image_p, neighbours_p = F.pad(image, pad), F.pad(neighbours, pad)
    inside_p = F.pad(torch.ones(1, 1, height, width, dtype=image.dtype, device=image.device), pad)
    num = torch.zeros_like(image)
    den = torch.zeros(n, 1, height, width, dtype=image.dtype, device=image.device)
    for dy, dx in tap_offsets(size, dilation):
        if center is not None and dy == 0 and dx == 0:
            weight = center
        else:
            distance = (features - _window(neighbours_p, radius, dy, dx, height, width)).square().sum(1, keepdim=True)
            weight = torch.exp(-bandwidth * distance) * _window(inside_p, radius, dy, dx, height, width)
        num += weight * _window(image_p, radius, dy, dx, height, width)
        den += weight
    return num, den


def _backward_torch(image: torch.Tensor, features: torch.Tensor, neighbours: torch.Tensor, bandwidth: torch.Tensor,
                    center: torch.Tensor | None, grad_num: torch.Tensor, grad_den: torch.Tensor, size: int,
                    dilation: int, need: tuple[bool, ...]) -> tuple[torch.Tensor | None, ...]:
    """Gradients (image, features, neighbours, bandwidth, center) of _sums_torch's (num, den) given grad_num and
    grad_den, tap by tap (the reference of the native affinity_sums_backward); None where ``need`` is False."""
    height, width = image.shape[-2:]
    radius = (size // 2) * dilation
    pad = (radius, radius, radius, radius)
    image_p, neighbours_p = F.pad(image, pad), F.pad(neighbours, pad)
    inside_p = F.pad(torch.ones(1, 1, height, width, dtype=image.dtype, device=image.device), pad)
    g_image_p = torch.zeros_like(image_p) if need[0] else None
    g_neighbours_p = torch.zeros_like(neighbours_p) if need[2] else None
    g_features = torch.zeros_like(features) if need[1] else None
    g_bandwidth = torch.zeros_like(bandwidth) if need[3] else None
    g_center = None
    for dy, dx in tap_offsets(size, dilation):
        shifted = _window(image_p, radius, dy, dx, height, width)
        # d loss / d w_t(p) = sum_c grad_num_c(p) L_c(p + o) + grad_den(p)
        g_weight = (grad_num * shifted).sum(1, keepdim=True) + grad_den
        if center is not None and dy == 0 and dx == 0:
            weight = center
            if need[4]:
                g_center = g_weight
        else:
            difference = features - _window(neighbours_p, radius, dy, dx, height, width)
            distance = difference.square().sum(1, keepdim=True)
            weight = torch.exp(-bandwidth * distance) * _window(inside_p, radius, dy, dx, height, width)
            if g_bandwidth is not None:
                g_bandwidth -= g_weight * weight * distance
            scale = -2.0 * g_weight * weight * bandwidth      # d loss / d f(p) = scale * (f(p) - g(p + o))
            if g_features is not None:
                g_features += scale * difference
            if g_neighbours_p is not None:
                _window(g_neighbours_p, radius, dy, dx, height, width).sub_(scale * difference)
        if g_image_p is not None:
            _window(g_image_p, radius, dy, dx, height, width).add_(weight * grad_num)
    crop = (slice(None), slice(None), slice(radius, radius + height), slice(radius, radius + width))
    return (g_image_p[crop] if g_image_p is not None else None, g_features,
            g_neighbours_p[crop] if g_neighbours_p is not None else None, g_bandwidth, g_center)


class _AffinitySums(torch.autograd.Function):
    """(num, den) of :func:`affinity_sums` with an analytic, tap-by-tap backward (module docstring)."""

    @staticmethod
    def forward(ctx, image, features, neighbours, bandwidth, center, size, dilation, backend):  # type: ignore[override]
        ctx.size, ctx.dilation, ctx.backend = size, dilation, backend
        ctx.save_for_backward(image, features, neighbours, bandwidth, center)
        on_cpu = image.device.type == "cpu"     # the native kernels read CPU memory; other devices use torch
        module = native.load_affinity() if backend != "torch" and on_cpu else None
        if backend == "native" and module is None:
            raise RuntimeError("native affinity kernel unavailable (see the denoisers.native warning, or "
                               f"{native.ENVIRONMENT_SWITCH}=0), or the tensors are not on the CPU")
        if module is not None:
            return tuple(module.affinity_sums(image.contiguous(), features.contiguous(), neighbours.contiguous(),
                                              bandwidth.contiguous(),
                                              center.contiguous() if center is not None else None, size, dilation))
        return _sums_torch(image, features, neighbours, bandwidth, center, size, dilation)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_num, grad_den):  # type: ignore[override]
        image, features, neighbours, bandwidth, center = ctx.saved_tensors
        n, _, height, width = image.shape
        grad_num = torch.zeros_like(image) if grad_num is None else grad_num.contiguous()
        grad_den = torch.zeros(n, 1, height, width, dtype=image.dtype, device=image.device) if grad_den is None \
            else grad_den.contiguous()
        need = tuple(bool(flag) for flag in ctx.needs_input_grad[:5])
        # The native backward (affinity.cpp) in float32 on the CPU; otherwise (float64 gradcheck, no build, another
        # device) the torch reference.
        module = native.load_affinity() if ctx.backend != "torch" and image.device.type == "cpu" else None
        tensors = (image, features, neighbours, bandwidth, center, grad_num, grad_den)
        if module is not None and hasattr(module, "affinity_sums_backward") and all(
                t is None or t.dtype == torch.float32 for t in tensors):
            grads = module.affinity_sums_backward(*(t.contiguous() if t is not None else None for t in tensors),
                                                  ctx.size, ctx.dilation, need)
        else:
            grads = _backward_torch(*tensors, ctx.size, ctx.dilation, need)
        return (*grads, None, None, None)


def affinity_sums(image: torch.Tensor, features: torch.Tensor, bandwidth: torch.Tensor, center: torch.Tensor | None,
                  size: int, dilation: int = 1, neighbours: torch.Tensor | None = None,
                  backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """(num (N, C, H, W), den (N, 1, H, W)) of a dilated affinity kernel (module docstring).

    ``neighbours`` defaults to ``features`` (a spatial kernel); ``center`` None makes the centre tap an
    affinity weight like the others (the temporal kernel). backend "auto": the native forward and backward
    when built (float32), "torch" the reference in both directions, "native" raises without the build.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    neighbours = features if neighbours is None else neighbours
    _check(image, features, neighbours, bandwidth, center)
    tensors = [t.float() if t is not None else None for t in (image, features, neighbours, bandwidth, center)]
    with torch.autocast("cpu", enabled=False):
        return _AffinitySums.apply(*tensors, int(size), int(dilation), backend)


def spatial_filter(image: torch.Tensor, features: torch.Tensor, bandwidth: torch.Tensor, center: torch.Tensor,
                   size: int, dilation: int = 1, backend: str = "auto") -> torch.Tensor:
    """Eq. 6: sum_t w_t L(p + o_t) / (EPS + sum_t w_t) with Eq. 4's weights; (N, C, H, W)."""
    num, den = affinity_sums(image, features, bandwidth, center, size, dilation, backend=backend)
    return num / (EPS + den)


def joint_filter(image: torch.Tensor, features: torch.Tensor, bandwidth: torch.Tensor, center: torch.Tensor,
                 size: int, dilation: int, history: torch.Tensor | None, history_features: torch.Tensor | None,
                 history_bandwidth: torch.Tensor | None, history_size: int,
                 backend: str = "auto", history_valid: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 8: the last spatial kernel on ``image`` and the temporal kernel (Eq. 7, dilation 1, no special centre)
    on the warped previous output ``history`` (features: the warped previous last-kernel features), normalised
    together. ``history`` None (a shot's first frame, omega = 0) reduces it to Eq. 6, and so does
    ``history_valid`` (N, 1, H, W) = 0 at a pixel whose reprojection failed (its temporal taps are dropped)."""
    num, den = affinity_sums(image, features, bandwidth, center, size, dilation, backend=backend)
    if history is not None:
        if history_features is None or history_bandwidth is None:
            raise ValueError("affinity: the temporal kernel needs the warped previous features and its bandwidth")
        num_t, den_t = affinity_sums(history, features, history_bandwidth, None, history_size, 1,
                                     neighbours=history_features, backend=backend)
        if history_valid is not None:
            num_t, den_t = num_t * history_valid, den_t * history_valid
        num, den = num + num_t, den + den_t
    return num / (EPS + den)


def gather_sums(image: torch.Tensor, logits: torch.Tensor, size: int, dilation: int = 1
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """(num, den) of a gather kernel: weights softmax(logits) over the k*k taps (N, k*k, H, W), dilated;
    taps outside the image read 0 and keep their weight in den (as in Bako et al.'s zero padding)."""
    if logits.shape[1] != size * size:
        raise ValueError(f"gather kernel of size {size} needs {size * size} logits per pixel, got {logits.shape[1]}")
    weights = torch.softmax(logits.float(), dim=1)
    n, channels, height, width = image.shape
    patches = F.unfold(image.float(), size, dilation=dilation, padding=(size // 2) * dilation)
    patches = patches.view(n, channels, size * size, height, width)
    num = (patches * weights.unsqueeze(1)).sum(2)
    return num, weights.sum(1, keepdim=True)


def accumulate(current: torch.Tensor, warped_previous: torch.Tensor | None, weight: torch.Tensor) -> torch.Tensor:
    """Eq. 3 / Eq. 5: (1 - lambda) x_t + lambda W x_{t-1}; the current value alone at a shot's first frame."""
    if warped_previous is None:
        return current
    return (1.0 - weight) * current + weight * warped_previous
