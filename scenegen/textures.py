"""Procedural, seamlessly tiling albedo textures drawn with numpy and written as 8-bit sRGB PNG.

All images are (H, W, 3) arrays. Every pattern is periodic over the image so that Mitsuba's
`bitmap` texture with the default `repeat` wrap mode shows no seams.
"""
from __future__ import annotations

import pathlib

import numpy as np
from PIL import Image

TEXTURE_SIZE = 256

TEXTURE_KIND_MIX: dict[str, float] = {
    "checker": 0.35,
    "stripes": 0.30,
    "value_noise": 0.35,
}
"""Probability of each procedural pattern when a material gets a texture (sums to 1)."""


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values in [0, 1] (IEC 61966-2-1 transfer curve)."""
    srgb = np.asarray(srgb, dtype=np.float64)
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear values in [0, 1] -> sRGB-encoded values in [0, 1]."""
    linear = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(linear <= 0.0031308, linear * 12.92, 1.055 * linear ** (1.0 / 2.4) - 0.055)


def _checker_mask(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size) float mask in {0, 1}; an even number of cells per tile keeps it periodic."""
    cells = 2 * int(rng.integers(1, 9))
    idx = (np.arange(size) * cells) // size
    return ((idx[:, None] + idx[None, :]) % 2).astype(np.float64)


def _stripes_mask(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size) float mask in [0, 1]; integer wave numbers along x and y keep it periodic."""
    kx, ky = 0, 0
    while kx == 0 and ky == 0:
        kx, ky = (int(k) for k in rng.integers(-6, 7, size=2))
    duty = rng.uniform(0.3, 0.7)
    softness = rng.uniform(0.0, 0.08)
    coords = np.arange(size) / size
    phase = (kx * coords[None, :] + ky * coords[:, None]) % 1.0
    if softness <= 1e-3:
        return (phase < duty).astype(np.float64)
    # Smooth ramp of width `softness` on both stripe edges (distance to the nearest edge, in phase units).
    dist_in = np.minimum(phase, duty - phase)
    dist_out = np.minimum(phase - duty, 1.0 - phase)
    signed = np.where(phase < duty, dist_in, -dist_out)
    return np.clip(0.5 + signed / softness, 0.0, 1.0)


def _periodic_value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """(size, size) smooth value noise in [0, 1] on a periodic lattice of `cells` x `cells` values."""
    lattice = rng.random((cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(np.int64)
    f = t - i0
    f = f * f * (3.0 - 2.0 * f)  # smoothstep fade avoids visible lattice creases
    i1 = (i0 + 1) % cells
    i0 = i0 % cells
    # Rows index y, columns index x.
    v00 = lattice[i0[:, None], i0[None, :]]
    v01 = lattice[i0[:, None], i1[None, :]]
    v10 = lattice[i1[:, None], i0[None, :]]
    v11 = lattice[i1[:, None], i1[None, :]]
    fx = f[None, :]
    fy = f[:, None]
    top = v00 + (v01 - v00) * fx
    bottom = v10 + (v11 - v10) * fx
    return top + (bottom - top) * fy


def _value_noise_mask(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size) fractal value noise (3-4 octaves) rescaled to [0, 1]."""
    base_cells = int(rng.choice([2, 4, 8]))
    octaves = int(rng.integers(3, 5))
    total = np.zeros((size, size))
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        total += amplitude * _periodic_value_noise(rng, size, base_cells * 2**octave)
        norm += amplitude
        amplitude *= 0.5
    total /= norm
    lo, hi = total.min(), total.max()
    return (total - lo) / max(hi - lo, 1e-9)


def draw_texture(rng: np.random.Generator, color_a: np.ndarray, color_b: np.ndarray,
                 size: int = TEXTURE_SIZE) -> tuple[np.ndarray, str]:
    """Blend two linear-RGB colours (3,) with a random pattern.

    Returns ((size, size, 3) uint8 sRGB image, pattern kind).
    """
    kinds = list(TEXTURE_KIND_MIX)
    probs = np.array([TEXTURE_KIND_MIX[k] for k in kinds])
    kind = kinds[int(rng.choice(len(kinds), p=probs / probs.sum()))]
    if kind == "checker":
        mask = _checker_mask(rng, size)
    elif kind == "stripes":
        mask = _stripes_mask(rng, size)
    else:
        mask = _value_noise_mask(rng, size)
    linear = color_a[None, None, :] * (1.0 - mask[..., None]) + color_b[None, None, :] * mask[..., None]
    srgb8 = np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)
    return srgb8, kind


def mean_linear_albedo(srgb8: np.ndarray) -> np.ndarray:
    """Mean linear RGB (3,) of an (H, W, 3) uint8 sRGB image, as Mitsuba's bitmap texture decodes it."""
    return srgb_to_linear(srgb8.astype(np.float64) / 255.0).reshape(-1, 3).mean(axis=0)


def write_png(image: np.ndarray, path: pathlib.Path) -> None:
    """Write an (H, W, 3) uint8 image as PNG with no metadata (byte-stable for identical input)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image)).save(path, format="PNG", optimize=False, compress_level=6)
