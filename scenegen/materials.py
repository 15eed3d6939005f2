"""Random materials for procedural scenes, stored as Mitsuba-dict-ready, JSON-serialisable params.

A texture inside `params` is written as
`{"type": "bitmap", "filename": "textures/tex_000.png", "to_uv": [[4x4]]}` with the filename relative
to the scene directory and `to_uv` as a plain 4x4 list; `mitsuba_scene.build_scene_dict` turns these
into absolute paths and `mi.ScalarTransform4f`. Mesh UVs are in metres (planar projection), so the
`to_uv` scale is the number of texture repeats per metre.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from scenegen.textures import draw_texture, linear_to_srgb, mean_linear_albedo, srgb_to_linear

MATERIAL_MIX: dict[str, float] = {
    "diffuse": 0.30,
    "roughplastic": 0.20,
    "roughconductor": 0.15,
    "conductor": 0.08,
    "dielectric": 0.10,
    "principled": 0.17,
}
"""Probability of each Mitsuba BSDF type for an object's material (sums to 1).

diffuse: Lambertian; roughplastic: diffuse base under a rough GGX/Beckmann dielectric coating;
roughconductor: rough metal (GGX); conductor: smooth mirror-like metal; dielectric: smooth glass;
principled: Disney-style principled BSDF with random metallic / roughness / clearcoat.
diffuse, roughplastic and principled get a procedural texture with probability TEXTURE_PROB.
"""

WALL_MATERIAL_MIX: dict[str, float] = {
    "diffuse": 0.60,
    "roughplastic": 0.25,
    "principled": 0.15,
}
"""Probability of each BSDF type for the room's floor, ceiling and walls (non-metallic, opaque)."""

TEXTURE_PROB = 0.5
"""Probability that a texture-capable object material uses a procedural bitmap albedo."""

WALL_TEXTURE_PROB = 0.6
"""Probability that a wall / floor / ceiling material uses a procedural bitmap albedo."""

TEXTURED_TYPES = ("diffuse", "roughplastic", "principled")

# Approximate RGB complex indices of refraction (eta, k) of common metals, for conductor BSDFs.
METAL_IOR: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "gold": ((0.18, 0.42, 1.37), (3.42, 2.35, 1.77)),
    "silver": ((0.16, 0.14, 0.13), (4.00, 3.00, 2.30)),
    "copper": ((0.27, 0.68, 1.32), (3.61, 2.62, 2.29)),
    "aluminium": ((1.35, 0.97, 0.62), (7.47, 6.40, 5.30)),
    "chromium": ((3.10, 3.20, 2.30), (3.30, 3.30, 3.10)),
    "iron": ((2.90, 2.90, 2.60), (3.10, 2.90, 2.80)),
}


def _rgb(value: np.ndarray) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(v) for v in value]}


def draw_color(rng: np.random.Generator, value_range: tuple[float, float] = (0.15, 0.85),
               max_saturation: float = 0.8) -> np.ndarray:
    """Random colour via HSV in sRGB space; returns linear RGB (3,) in [0, 1]."""
    hue = rng.random()
    sat = rng.uniform(0.0, max_saturation)
    val = rng.uniform(*value_range)
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    srgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return srgb_to_linear(srgb)


def fresnel_conductor_normal(eta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Normal-incidence reflectance (3,) of a conductor with complex IOR eta + i k (each (3,))."""
    eta, k = np.asarray(eta), np.asarray(k)
    return ((eta - 1.0) ** 2 + k**2) / ((eta + 1.0) ** 2 + k**2)


def _uv_scale_matrix(scale: float) -> list[list[float]]:
    return [[scale, 0.0, 0.0, 0.0], [0.0, scale, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def draw_material(rng: np.random.Generator, name: str, mat_type: str, texture_path: str,
                  texture_prob: float, *, allow_metallic: bool = True,
                  value_range: tuple[float, float] = (0.15, 0.85)) -> tuple[dict, np.ndarray | None]:
    """Draw the params of one material.

    `texture_path` is the relative path the texture will be written to if one is drawn.
    Returns (manifest material entry, (256, 256, 3) uint8 texture image or None).
    """
    image: np.ndarray | None = None
    albedo_source: dict[str, Any]
    albedo: np.ndarray
    if mat_type in TEXTURED_TYPES:
        color_a = draw_color(rng, value_range)
        if rng.random() < texture_prob:
            color_b = draw_color(rng, value_range)
            image, _ = draw_texture(rng, color_a, color_b)
            scale = float(np.exp(rng.uniform(np.log(0.25), np.log(1.5))))
            albedo_source = {"type": "bitmap", "filename": texture_path, "to_uv": _uv_scale_matrix(round(scale, 6))}
            albedo = mean_linear_albedo(image)
        else:
            # Quantise through 8-bit sRGB so the recorded albedo is what a PNG of it would give too.
            albedo = srgb_to_linear(np.round(linear_to_srgb(color_a) * 255.0) / 255.0)
            albedo_source = _rgb(np.round(albedo, 6))

    roughness: float
    metallic = False
    transmissive = False
    if mat_type == "diffuse":
        params = {"type": "diffuse", "reflectance": albedo_source}
        roughness = 1.0
    elif mat_type == "roughplastic":
        alpha = float(np.exp(rng.uniform(np.log(0.03), np.log(0.5))))
        params = {"type": "roughplastic", "diffuse_reflectance": albedo_source, "alpha": alpha,
                  "int_ior": float(rng.uniform(1.4, 1.7)), "ext_ior": 1.000277,
                  "distribution": "ggx" if rng.random() < 0.7 else "beckmann"}
        roughness = alpha
    elif mat_type == "principled":
        metallic_value = float(rng.uniform(0.0, 1.0)) if (allow_metallic and rng.random() < 0.4) else 0.0
        perceptual_roughness = float(rng.uniform(0.1, 0.9))
        params = {"type": "principled", "base_color": albedo_source, "metallic": metallic_value,
                  "roughness": perceptual_roughness, "specular": float(rng.uniform(0.3, 0.7))}
        if rng.random() < 0.3:
            params["clearcoat"] = float(rng.uniform(0.2, 1.0))
            params["clearcoat_gloss"] = float(rng.uniform(0.3, 1.0))
        # Mitsuba's principled BSDF squares the perceptual roughness to get the microfacet alpha.
        roughness = perceptual_roughness**2
        metallic = metallic_value > 0.5
    elif mat_type in ("roughconductor", "conductor"):
        metal_names = list(METAL_IOR)
        metal = metal_names[int(rng.integers(len(metal_names)))]
        eta, k = (np.array(v) for v in METAL_IOR[metal])
        albedo = fresnel_conductor_normal(eta, k)
        params = {"type": mat_type, "eta": _rgb(eta), "k": _rgb(k)}
        if mat_type == "roughconductor":
            alpha = float(np.exp(rng.uniform(np.log(0.05), np.log(0.6))))
            params.update({"alpha": alpha, "distribution": "ggx"})
            roughness = alpha
        else:
            roughness = 0.0
        metallic = True
    elif mat_type == "dielectric":
        if rng.random() < 0.5:
            tint = np.ones(3)
        else:
            tint = draw_color(rng, (0.85, 1.0), max_saturation=0.25)
        params = {"type": "dielectric", "int_ior": float(rng.uniform(1.33, 1.8)), "ext_ior": 1.000277,
                  "specular_transmittance": _rgb(np.round(tint, 6))}
        albedo = tint
        roughness = 0.0
        transmissive = True
    else:
        raise ValueError(f"unknown material type {mat_type!r}")

    entry = {
        "name": name,
        "type": mat_type,
        "params": params,
        "albedo": [float(v) for v in albedo],
        "roughness": float(roughness),
        "metallic": bool(metallic),
        "transmissive": bool(transmissive),
        "emissive": False,
        "texture": texture_path if image is not None else None,
    }
    return entry, image


def emissive_material(name: str, albedo: np.ndarray) -> dict:
    """Diffuse material entry for a shape that carries an area emitter."""
    return {
        "name": name,
        "type": "diffuse",
        "params": {"type": "diffuse", "reflectance": _rgb(np.round(albedo, 6))},
        "albedo": [float(v) for v in albedo],
        "roughness": 1.0,
        "metallic": False,
        "transmissive": False,
        "emissive": True,
        "texture": None,
    }
