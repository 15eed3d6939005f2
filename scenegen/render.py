"""Render per-sample noisy frames, pixel-centre G-buffers and high-spp references with Mitsuba 3.

All light transport goes through the ``mcdn_features`` integrator (``scenegen.integrator``) via
``mi.render``: one call per 1-spp sample layer with a box reconstruction filter, so every pixel of
a layer holds exactly one independent sample. The only Python loops are over sample layers and
reference batches; pixels and paths run in Mitsuba's vectorised wavefront.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenegen.mitsuba_env import init_mitsuba
from scenegen.seeds import derive_seed

# Buffer name -> channel count of the per-sample arrays this module returns.
SAMPLE_BUFFER_SIZES: dict[str, int] = {
    "radiance": 3, "diffuse": 3, "specular": 3, "albedo": 3, "normal": 3,
    "depth": 1, "roughness": 1, "flags": 4, "position": 3,
}


@dataclass
class RenderSettings:
    """Render parameters shared by every pass (from the ``render`` config section)."""

    width: int = 128
    height: int = 128
    spp: int = 8
    extra_radiance_spp: int = 0
    reference_spp: int = 1024
    reference_batch_spp: int = 32
    reference_integrator: str = "path"   # "path": radiance only; "features": also the feature means
    gbuffer_albedo_spp: int = 1           # 1: pixel-centre G-buffer albedo; K > 1: mean over K jittered rays
    max_depth: int = 8
    rr_depth: int = 5
    variant: str = "llvm_ad_rgb"

    @classmethod
    def from_config(cls, render_cfg: dict) -> "RenderSettings":
        known = {k: render_cfg[k] for k in cls.__dataclass_fields__ if k in render_cfg}
        return cls(**known)


@dataclass
class NonFiniteCounter:
    """Counts non-finite values replaced by zero, per buffer."""

    counts: dict[str, int] = field(default_factory=dict)

    def sanitise(self, name: str, array: np.ndarray) -> np.ndarray:
        bad = ~np.isfinite(array)
        n_bad = int(bad.sum())
        self.counts[name] = self.counts.get(name, 0) + n_bad
        if n_bad:
            array = np.where(bad, 0.0, array).astype(array.dtype)
        return array


#: render.reference_integrator values: Mitsuba's ``path`` (radiance only, about 1.4x the rate of the
#: feature integrator on generated scenes) or the feature integrator (radiance plus feature means).
REFERENCE_INTEGRATORS: tuple[str, ...] = ("path", "features")


def load_frame_scene(manifest: dict, scene_dir: Path, frame: int, settings: RenderSettings,
                     *, mode: str = "samples"):
    """Load the Mitsuba scene of ``frame`` with per-face attributes and the feature integrator in ``mode``
    ("samples", "gbuffer"), or with Mitsuba's ``path`` integrator for ``mode="path"`` (same depths)."""
    init_mitsuba(settings.variant)
    import mitsuba as mi

    import scenegen.integrator  # noqa: F401 -- registers "mcdn_features"
    from scenegen.mitsuba_scene import attach_face_attributes, build_scene_dict

    integrator: dict = {"type": "path", "max_depth": settings.max_depth, "rr_depth": settings.rr_depth}
    if mode != "path":
        integrator.update(type="mcdn_features", mode=mode)
    if manifest.get("kind") == "custom":
        from scenegen.custom.scene import load_custom_frame_scene

        return load_custom_frame_scene(manifest, frame, width=settings.width, height=settings.height,
                                       integrator=integrator)
    scene_dict = build_scene_dict(manifest, Path(scene_dir), frame, width=settings.width,
                                  height=settings.height, integrator=integrator)
    for shape in manifest["shapes"]:
        key = f"shape_{shape['index']:03d}"
        mesh = mi.load_dict(scene_dict[key])
        material = manifest["materials"][shape["material"]] if shape.get("material") is not None else None
        attach_face_attributes(mesh, shape, material)
        scene_dict[key] = mesh
    return mi.load_dict(scene_dict)


def _gbuffer_sensor(manifest: dict, frame: int, settings: RenderSettings):
    """The frame's sensor with a non-jittered 1-spp stratified sampler: rays through pixel centres."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import sensor_dict

    sampler = {"type": "stratified", "sample_count": 1, "jitter": False}
    return mi.load_dict(sensor_dict(manifest, frame, width=settings.width, height=settings.height,
                                    sampler=sampler))


def split_channels(image: np.ndarray, sizes: list[tuple[str, int]]) -> dict[str, np.ndarray]:
    """(H, W, C) -> {name: (c, H, W)} following ``sizes`` in order."""
    out, start = {}, 0
    for name, size in sizes:
        out[name] = np.ascontiguousarray(np.moveaxis(image[..., start:start + size], -1, 0))
        start += size
    if start != image.shape[-1]:
        raise RuntimeError(f"renderer returned {image.shape[-1]} channels, expected {start}")
    return out


def render_spp(scene, *, spp: int, seed: int, sensor=None) -> np.ndarray:
    import mitsuba as mi

    image = mi.render(scene, spp=spp, seed=seed, sensor=sensor if sensor is not None else 0)
    return np.array(image, dtype=np.float32)


def render_gbuffer(manifest: dict, scene_dir: Path, frame: int, settings: RenderSettings,
                   scene=None) -> dict[str, np.ndarray]:
    """Primary-hit G-buffer through pixel centres: position (3,H,W), normal (3,H,W), depth (1,H,W), object (1,H,W)."""
    init_mitsuba(settings.variant)
    import mitsuba as mi

    from scenegen.integrator import GBUFFER_AOVS

    if scene is None:
        scene = load_frame_scene(manifest, scene_dir, frame, settings)
    sensor = _gbuffer_sensor(manifest, frame, settings)
    integrator = mi.load_dict({"type": "mcdn_features", "mode": "gbuffer"})
    image = np.array(mi.render(scene, spp=1, seed=0, sensor=sensor, integrator=integrator), np.float32)
    buffers = split_channels(image, [("rgb", 3), *GBUFFER_AOVS])
    if settings.gbuffer_albedo_spp > 1:
        buffers["albedo"] = gbuffer_albedo_mean(scene, integrator, spp=settings.gbuffer_albedo_spp, seed=frame + 1)
    return buffers


def gbuffer_albedo_mean(scene, integrator, *, spp: int, seed: int) -> np.ndarray:
    """(3, H, W) mean G-buffer albedo (each ray's primary hit's own, 0 on a miss) over ``spp`` jittered camera rays
    per pixel of ``scene``'s own sensor (box-filtered film: the pixel footprint); ``integrator`` is a
    ``mcdn_features`` integrator in ``gbuffer`` mode."""
    import mitsuba as mi

    from scenegen.integrator import GBUFFER_AOVS

    image = np.array(mi.render(scene, spp=spp, seed=seed, integrator=integrator), np.float32)
    return split_channels(image, [("rgb", 3), *GBUFFER_AOVS])["albedo"]


def sample_wavefront(scene, *, n_layers: int, seed: int) -> np.ndarray:
    """Trace ``n_layers`` independent 1-spp samples of every pixel in one wavefront.

    Direct call of the integrator's ``sample`` (JIT variants only): rays are generated like
    Mitsuba's film loop at 1 spp (uniform jitter in the pixel, box filter), lanes ordered
    layer-major; rays start in the sensor's medium. Returns (S, H, W, 3 + n_aov) float32: radiance then the AOVs.
    """
    import drjit as dr
    import mitsuba as mi

    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    n_pixels = width * height
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(1)
    sampler.seed(seed, n_layers * n_pixels)
    index = dr.arange(mi.UInt32, n_layers * n_pixels)
    pixel = index % n_pixels
    film_position = mi.Vector2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    ray, _ = sensor.sample_ray_differential(0.0, sampler.next_1d(),
                                            film_position / mi.ScalarVector2f(width, height), aperture)
    # The camera's medium (None unless the sensor sits inside one): volumetric integrators start there.
    radiance, _, aovs = scene.integrator().sample(scene, sampler, ray, sensor.get_medium(), mi.Bool(True))
    outputs = [radiance.x, radiance.y, radiance.z, *aovs]
    dr.eval(*outputs)
    stacked = np.stack([np.asarray(value, dtype=np.float32) for value in outputs], axis=-1)
    return stacked.reshape(n_layers, height, width, len(outputs))


def render_sample_layers(scene, *, n_layers: int, n_radiance_only: int, seed: int,
                         counter: NonFiniteCounter, progress=None) -> dict[str, np.ndarray]:
    """Render ``n_layers`` full-feature 1-spp layers plus ``n_radiance_only`` radiance-only layers.

    Returns {buffer: (S, C, H, W) float32}; ``radiance`` has S = n_layers + n_radiance_only layers,
    every other buffer n_layers. Non-finite values are replaced by 0 and counted in ``counter``.
    JIT variants trace all layers in one wavefront; the scalar fallback renders one layer per
    ``mi.render`` call (seeds derived from ``seed``).
    """
    from scenegen.integrator import SAMPLE_AOVS
    from scenegen.mitsuba_env import is_jit_variant

    layout = [("radiance", 3), *SAMPLE_AOVS]
    total = n_layers + n_radiance_only
    if is_jit_variant():
        images = sample_wavefront(scene, n_layers=total, seed=seed)
    else:
        images = np.stack([render_spp(scene, spp=1, seed=derive_seed(seed, layer)) for layer in range(total)])
    parts = {name: np.stack([split_channels(image, layout)[name] for image in images])
             for name, _ in layout}
    out = {"radiance": counter.sanitise("radiance", parts["radiance"])}
    diffuse = counter.sanitise("diffuse", parts["diffuse"][:n_layers])
    out["diffuse"] = diffuse
    out["specular"] = out["radiance"][:n_layers] - diffuse
    for name in ("albedo", "normal", "depth", "roughness", "flags", "position"):
        out[name] = counter.sanitise(name, parts[name][:n_layers])
    if progress is not None:
        progress.update(total)
    return out


def frame_meta(manifest: dict, scene_id: str, frame: int, settings: RenderSettings, variant: str) -> dict:
    """Sidecar fields every rendered frame shares: scene, frame, size, variant, path depths, the camera of the frame
    and of the previous frame (scenegen.mitsuba_scene.camera_matrices as lists), camera_cut."""
    from scenegen.mitsuba_scene import camera_matrices

    depths = {"max_depth": settings.max_depth, "rr_depth": settings.rr_depth}
    if manifest.get("kind") == "custom":      # rendered with the XML's (or its entry's) depths
        from scenegen.custom.scene import integrator_settings

        authored = integrator_settings(manifest)
        depths.update({key: authored[key] for key in depths if key in authored})
    meta = {
        "scene": scene_id, "frame": frame, "width": settings.width, "height": settings.height,
        "variant": variant, **depths,
        "camera": _plain(camera_matrices(manifest, frame, settings.width, settings.height)),
        "prev_camera": (_plain(camera_matrices(manifest, frame - 1, settings.width, settings.height))
                        if frame > 0 else None),
        "camera_cut": bool(manifest["camera"]["frames"][frame].get("cut", False)),
        "gbuffer_albedo_spp": settings.gbuffer_albedo_spp,
    }
    return meta


def _plain(value):
    """numpy arrays and scalars -> Python lists and numbers (no rounding: sidecar cameras are exact)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def noisy_frame_seed(global_seed: int, scene_id: str, frame: int) -> int:
    """Seed of the noisy sample layers of one frame."""
    return derive_seed(global_seed, scene_id, "noisy", frame)


def reference_batch_seeds(global_seed: int, scene_id: str, frame: int, half: int, n: int) -> list[int]:
    """Seeds of the reference batches of one half; disjoint from the noisy seeds by construction."""
    return [derive_seed(global_seed, scene_id, "reference", frame, half, batch) for batch in range(n)]


def render_reference_frame(scene, *, spp: int, batch_spp: int, seeds_half: tuple[list[int], list[int]],
                           counter: NonFiniteCounter, progress=None, features: bool = True) -> dict[str, np.ndarray]:
    """Two independent halves of ``spp/2`` samples each; returns {buffer: (C, H, W)} with
    ``radiance`` (their mean), ``radiance_half0``, ``radiance_half1``, and, with ``features`` (a scene
    loaded with the feature integrator), the mean of diffuse, specular, albedo, normal and depth over all
    samples. ``features=False`` expects a radiance-only integrator (Mitsuba's ``path``)."""
    from scenegen.integrator import SAMPLE_AOVS

    layout = [("radiance", 3), *SAMPLE_AOVS] if features else [("radiance", 3)]
    half_spp = spp // 2
    n_batches = math.ceil(half_spp / batch_spp)
    sums: dict[str, np.ndarray] = {}
    half_radiance = []
    for half in range(2):
        acc = None
        remaining = half_spp
        for batch in range(n_batches):
            batch_count = min(batch_spp, remaining)
            remaining -= batch_count
            parts = split_channels(render_spp(scene, spp=batch_count, seed=seeds_half[half][batch]), layout)
            for name in ("radiance", "diffuse", "albedo", "normal", "depth") if features else ("radiance",):
                value = counter.sanitise(name, parts[name]).astype(np.float64) * batch_count
                sums[name] = sums.get(name, 0.0) + value
                if name == "radiance":
                    acc = value if acc is None else acc + value
            if progress is not None:
                progress.update(batch_count)
        half_radiance.append(acc / half_spp)
    total = 2 * half_spp
    out = {name: (value / total).astype(np.float32) for name, value in sums.items()}
    if features:
        out["specular"] = out["radiance"] - out["diffuse"]
    out["radiance_half0"] = half_radiance[0].astype(np.float32)
    out["radiance_half1"] = half_radiance[1].astype(np.float32)
    return out


def psnr_between_halves(half0: np.ndarray, half1: np.ndarray) -> float:
    """PSNR (dB) between the two reference halves on tonemapped radiance, x -> (x/(1+x))^(1/2.4).

    The halves are independent, so E|h0 - h1|^2 = 2 var(half) and the averaged reference has
    variance var(half)/2 = E|h0 - h1|^2 / 4: its own noise floor is about this value + 6.02 dB
    (to first order in the tonemapper).
    """
    from denoisers.metrics import psnr

    return psnr(half0, half1)
