"""Kernel-prediction building blocks (issue 12; Hasselgren et al. 2020 Sec. 2.1, Vogels et al. 2018).

* :func:`apply_kernels` -- per-pixel k x k kernels (the inference hot loop): native C++ kernel
  (denoisers/native/kernels.cpp) for inference, torch ``unfold`` reference with autograd for training.
* :func:`downsample`, :func:`upsample`, :func:`compose_scales`, :func:`compose_multiscale` -- the scale
  composition of Vogels et al. (their Eq. 5, Eq. 3 of Hasselgren et al.):
  ``o = i_f - alpha * U(D(i_f)) + alpha * U(i_c)``, applied recursively from the coarsest scale.
* :func:`multiscale_filter` -- filter an image at full, 1/2 and 1/4 resolution with per-level kernels
  and compose; :func:`temporal_blend` -- the filtered warped history blended with weight alpha'.
* :func:`warp_previous` -- the motion-vector warp of the previous output (Eq. 1 of Hasselgren et al.);
  the same function SVGF and RLS reproject with (denoisers.filters.warp_previous).

Kernel layout and borders: ``weights[t]`` with ``t = i * k + j`` is the weight of the tap at offset
(dy, dx) = (i - k // 2, j - k // 2) (row-major, top-left tap first), so
``out[c, y, x] = sum_t weights[t, y, x] * image[c, y + dy_t, x + dx_t]``. Taps outside the image read 0
(zero padding) and the weights are used as given, not renormalised over the taps inside: the caller
normalises or softmaxes them (a network learns to give border taps no weight). Images are linear
radiance (or any float channels), (C, H, W) or batched (N, C, H, W) with weights (N, k*k, H, W).

Networks: denoisers.nets.ntasd; training and the frame step: denoisers.nets.ntasd_task.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from denoisers import filters, native

DEFAULT_KERNEL_SIZE = 5
BACKENDS = ("auto", "native", "torch")


def _kernel_size(weights: torch.Tensor) -> int:
    taps = weights.shape[-3]
    size = int(round(taps ** 0.5))
    if size * size != taps or size % 2 == 0:
        raise ValueError(f"weights must have k*k taps with k odd along dim -3, got {taps} (shape "
                         f"{tuple(weights.shape)})")
    return size


def _check(image: torch.Tensor, weights: torch.Tensor) -> int:
    if image.dim() not in (3, 4) or weights.dim() != image.dim():
        raise ValueError(f"image (C, H, W) or (N, C, H, W) and weights (k*k, H, W) or (N, k*k, H, W) expected, "
                         f"got {tuple(image.shape)} and {tuple(weights.shape)}")
    if image.shape[-2:] != weights.shape[-2:] or (image.dim() == 4 and image.shape[0] != weights.shape[0]):
        raise ValueError(f"image {tuple(image.shape)} and weights {tuple(weights.shape)} differ in batch or H, W")
    return _kernel_size(weights)


def apply_kernels_torch(image: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Reference: per-pixel kernels by ``unfold`` (zero padding), differentiable in image and weights.

    image (C, H, W) or (N, C, H, W); weights (k*k, H, W) or (N, k*k, H, W). Returns image's shape.
    Memory: a (N, C, k*k, H, W) temporary.
    """
    size = _check(image, weights)
    batched = image.dim() == 4
    images, kernels = (image, weights) if batched else (image[None], weights[None])
    n, channels, height, width = images.shape
    patches = F.unfold(images, size, padding=size // 2).view(n, channels, size * size, height, width)
    out = (patches * kernels.unsqueeze(1)).sum(dim=2)
    return out if batched else out[0]


def apply_kernels(image: torch.Tensor, weights: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Per-pixel k x k kernels applied to ``image`` (layout and borders: module docstring).

    image (C, H, W) or (N, C, H, W) float; weights (k*k, H, W) or (N, k*k, H, W), k odd (5 by default in
    the networks). backend "auto": the native kernel when it is built and no gradient is needed (float32
    CPU tensors, grad mode off or no input requiring grad), else the torch reference; "native" raises if
    the native kernel is unavailable; "torch" forces the reference. The native kernel is inference only.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    size = _check(image, weights)
    needs_grad = torch.is_grad_enabled() and (image.requires_grad or weights.requires_grad)
    module = None
    if backend != "torch" and not needs_grad and image.device.type == "cpu" and weights.device.type == "cpu":
        module = native.load_kernels()
    if backend == "native" and module is None:
        raise RuntimeError("native kernel application unavailable (see the denoisers.native warning, or "
                           f"{native.ENVIRONMENT_SWITCH}=0), or a gradient is needed, or tensors are not on the CPU")
    if module is None:
        return apply_kernels_torch(image, weights)
    dtype = image.dtype
    images = image.detach().float().contiguous()
    kernels = weights.detach().float().contiguous()
    if image.dim() == 3:
        return module.apply_kernels(images, kernels, size).to(dtype)
    return torch.stack([module.apply_kernels(i, k, size) for i, k in zip(images, kernels)]).to(dtype)


def downsample(image: torch.Tensor) -> torch.Tensor:
    """D: 2 x 2 box average, (..., C, H, W) -> (..., C, ceil(H/2), ceil(W/2)); a last odd row or column
    averages the pixels it has."""
    shape = image.shape
    flat = image.reshape(-1, *shape[-3:])
    out = F.avg_pool2d(flat, 2, stride=2, ceil_mode=True, count_include_pad=False)
    return out.reshape(*shape[:-2], *out.shape[-2:])


def upsample(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """U: nearest-neighbour 2x upsampling, (..., C, h, w) -> (..., C, H, W) with h = ceil(H/2), w = ceil(W/2)
    (pixel (y, x) takes coarse pixel (y // 2, x // 2); cropped for odd H or W)."""
    height, width = size
    if image.shape[-2] != -(-height // 2) or image.shape[-1] != -(-width // 2):
        raise ValueError(f"upsample: coarse size {tuple(image.shape[-2:])} does not match the fine size "
                         f"{height}x{width} (expected {-(-height // 2)}x{-(-width // 2)})")
    return image.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)[..., :height, :width]


def _fine_alpha(alpha: torch.Tensor, fine: torch.Tensor) -> torch.Tensor:
    """Blend weight at the fine resolution, (..., 1, H, W): given there, or at the coarse one (upsampled)."""
    height, width = fine.shape[-2:]
    if alpha.dim() == fine.dim() - 1:
        alpha = alpha.unsqueeze(-3)
    if alpha.shape[-2:] == (height, width):
        return alpha
    return upsample(alpha, (height, width))


def compose_scales(fine: torch.Tensor, coarse: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Vogels et al. Eq. 5 (Hasselgren et al. Eq. 3): ``o = i_f - alpha U D i_f + alpha U i_c``.

    fine i_f (..., C, H, W); coarse i_c (..., C, ceil(H/2), ceil(W/2)); alpha: per-pixel blend weight,
    (..., 1, H, W) or (..., H, W) at the fine resolution, or at the coarse one (then upsampled by U).
    alpha = 0 keeps the fine image, alpha = 1 replaces its low frequencies by the coarse image's.
    """
    size = tuple(fine.shape[-2:])
    weight = _fine_alpha(alpha, fine)
    return fine - weight * upsample(downsample(fine), size) + weight * upsample(coarse, size)


def compose_multiscale(images: Sequence[torch.Tensor], alphas: Sequence[torch.Tensor]) -> torch.Tensor:
    """Recursive composition from the coarsest scale: images[0] is full resolution, images[l] is 2^-l;
    alphas[l] blends images[l] with the composition of the coarser levels (len(alphas) = len(images) - 1)."""
    if len(alphas) != len(images) - 1 or not images:
        raise ValueError(f"{len(images)} images need {max(len(images) - 1, 0)} blend weights, got {len(alphas)}")
    out = images[-1]
    for level in range(len(images) - 2, -1, -1):
        out = compose_scales(images[level], out, alphas[level])
    return out


def multiscale_filter(image: torch.Tensor, weights: Sequence[torch.Tensor], alphas: Sequence[torch.Tensor],
                      backend: str = "auto") -> torch.Tensor:
    """Hasselgren et al.'s spatial path: ``image`` (..., C, H, W) and its 2x, 4x, ... box-downsampled
    versions are each filtered with their per-pixel kernels ``weights[l]`` (..., k*k, H_l, W_l), then
    composed with :func:`compose_multiscale` (``alphas[l]`` as there). Three levels in the paper."""
    pyramid = [image]
    for _ in range(len(weights) - 1):
        pyramid.append(downsample(pyramid[-1]))
    filtered = [apply_kernels(level, w, backend) for level, w in zip(pyramid, weights)]
    return compose_multiscale(filtered, alphas)


def temporal_blend(current: torch.Tensor, warped_history: torch.Tensor, history_weights: torch.Tensor,
                   alpha: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """``(1 - alpha') current + alpha' K(warped_history)``: the finest-scale temporal kernel of Hasselgren
    et al. applied to the warped previous output and blended per pixel. alpha' (..., 1, H, W) or (..., H, W)."""
    weight = alpha.unsqueeze(-3) if alpha.dim() == current.dim() - 1 else alpha
    return (1 - weight) * current + weight * apply_kernels(warped_history, history_weights, backend)


def warp_previous(previous: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Eq. 1 of Hasselgren et al.: ``c_warped(x, y) = c_history(x + m_x, y + m_y)``, bilinear, border-clamped.

    previous (C, H, W) or (N, C, H, W); motion (2, H, W) backward motion in pixels (scenegen convention),
    or (N, 2, H, W) per image.
    This is denoisers.filters.warp_previous (grid_sample, as the paper), shared with SVGF and RLS;
    combine with ``motion.valid`` where reprojection fails (the paper's networks see the raw warp).
    """
    return filters.warp_previous(previous, motion)
