"""Jobs of the volumetric clips (scene ids vol_*): generate a clip, render its noisy per-sample frames and its
references, into the same on-disk layout as the surface scenes (docs/data-format.md, "Volumetric clips").

* generate: :func:`scenegen.volumes.scenes.generate_volume_clip` from the scene's seed (the config's seed and
  the scene id), the scenario named by the id and the ``volumes`` section; writes ``manifest.json`` (the
  complete description; the field is regenerated from it, same bytes).
* noisy: ``spp`` independent 1-spp layers per frame from ``mcdn_volpath_features`` in one wavefront
  (scenegen.render.sample_wavefront): radiance, albedo, position, depth, sigma_t, medium, transmittance;
  the per-pixel closest-collision G-buffer and motion vectors of scenegen.volumes.motion.
* reference: two independent halves with Mitsuba's ``volpath`` (same depths), radiance only.

The scene of frame 0 is loaded once and edited per frame (scenegen.volumes.scenes.frame_updates): a
transfer-function edit rewrites the medium grids in place, camera and light edits one transform.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from scenegen.atomic import atomic_directory, write_text_atomic
from scenegen.catalog import volume_clip_spec, volume_extra
from scenegen.mitsuba_env import init_mitsuba, is_jit_variant
from scenegen.render import (NonFiniteCounter, RenderSettings, frame_meta, noisy_frame_seed, psnr_between_halves,
                             reference_batch_seeds, render_reference_frame, render_spp, sample_wavefront,
                             split_channels)
from scenegen.seeds import scene_seed

log = logging.getLogger(__name__)

#: Per-sample buffers the volumetric integrator returns after radiance, in its AOV order.
NOISY_LAYOUT: tuple[tuple[str, int], ...] = (("radiance", 3), ("position", 3), ("depth", 1), ("sigma_t", 1),
                                             ("albedo", 3), ("medium", 1), ("transmittance", 1))


def generate_volume_scene(cfg: dict, scene_id: str, out_dir: Path) -> dict:
    """Draw the clip of ``scene_id`` and write its ``manifest.json`` to ``out_dir`` (atomically)."""
    from scenegen.volumes.scenes import generate_volume_clip

    volumes = cfg["volumes"]
    split, scenario, _ = volume_clip_spec(cfg, scene_id)
    own = volume_extra(cfg, scene_id) if split == "custom" else {}
    clip = generate_volume_clip(scene_seed(cfg["seed"], scene_id), scenario, int(volumes["frames"]),
                                resolution=int(volumes["resolution"]), field_npy=own.get("npy"),
                                transfer_function=own.get("transfer_function"),
                                frame_aspect=int(volumes["height"]) / int(volumes["width"]))
    clip = dataclasses.replace(clip, max_depth=int(volumes["max_depth"]))
    manifest = {**clip.manifest(), "scene": scene_id, "n_frames": clip.frames}
    with atomic_directory(out_dir) as tmp_dir:
        write_text_atomic(tmp_dir / "manifest.json", json.dumps(manifest, indent=1, sort_keys=True))
    log.info("volumetric clip %s: %s scenario, %s field, %s setting, %d frames", scene_id, scenario,
             manifest["field"]["kind"], manifest["setting"], clip.frames)
    return manifest


def _load_clip(scene_dir: Path) -> tuple[dict, Any]:
    from scenegen.volumes.scenes import VolumeClip

    path = Path(scene_dir) / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"scene manifest not found: {path}")
    manifest = json.loads(path.read_text())
    if manifest.get("kind") != "volume_clip":
        raise ValueError(f"{path} is not a volumetric clip's manifest (kind {manifest.get('kind')!r})")
    return manifest, VolumeClip.from_manifest(manifest)


def _open_clip(scene_id: str, chunk: int, scene_dir: Path, settings: RenderSettings,
               integrator: str) -> tuple[str, dict, Any, Any]:
    """(Mitsuba variant, manifest, VolumeClip, frame 0's scene with ``integrator``) of a clip's only chunk."""
    if chunk != 0:
        raise ValueError(f"volumetric clip {scene_id} is rendered as one chunk (chunk 0), got chunk {chunk}")
    variant = init_mitsuba(settings.variant)
    manifest, clip = _load_clip(scene_dir)
    return variant, manifest, clip, _load_scene(clip, settings, integrator)


def _load_scene(clip: Any, settings: RenderSettings, integrator: str):
    """Frame 0's Mitsuba scene with ``integrator`` ('features': mcdn_volpath_features, 'volpath')."""
    import mitsuba as mi

    import scenegen.volumes.integrator  # noqa: F401 -- registers mcdn_volpath_features

    scene = clip.scene_dict(0, width=settings.width, height=settings.height, spp=1)
    kind = "mcdn_volpath_features" if integrator == "features" else "volpath"
    scene["integrator"] = {"type": kind, "max_depth": settings.max_depth, "rr_depth": settings.rr_depth}
    return mi.load_dict(scene)


def _sample_layers(scene, n_layers: int, seed: int, counter: NonFiniteCounter) -> dict[str, np.ndarray]:
    """{buffer: (S, C, H, W) float32} of ``n_layers`` independent 1-spp layers (non-finite values -> 0, counted)."""
    from scenegen.seeds import derive_seed

    if is_jit_variant():
        images = sample_wavefront(scene, n_layers=n_layers, seed=seed)
    else:
        images = np.stack([render_spp(scene, spp=1, seed=derive_seed(seed, layer)) for layer in range(n_layers)])
    parts = [split_channels(image, list(NOISY_LAYOUT)) for image in images]
    return {name: counter.sanitise(name, np.stack([part[name] for part in parts])) for name, _ in NOISY_LAYOUT}


def run_render_volume_noisy(cfg: dict, scene_id: str, chunk: int, scene_dir: Path, out_dir: Path,
                            settings: RenderSettings) -> None:
    """Render the noisy frames of a volumetric clip (one chunk: the whole clip)."""
    from scenegen.channels import noisy_channels, pixel_channels
    from scenegen.dataset import write_frame
    from scenegen.volumes.motion import closest_collision_gbuffer, volume_motion_vectors
    from scenegen.volumes.scenes import frame_updates

    variant, manifest, clip, scene = _open_clip(scene_id, chunk, scene_dir, settings, "features")
    samples_per_frame = settings.spp * settings.width * settings.height
    gbuffer_prev = None
    with atomic_directory(out_dir) as tmp_dir, \
            tqdm(total=clip.frames * settings.spp, desc=f"noisy {scene_id}", unit="layer") as bar:
        for frame in range(clip.frames):
            start = time.perf_counter()
            frame_updates(scene, clip, frame)
            counter = NonFiniteCounter()
            seed = noisy_frame_seed(cfg["seed"], scene_id, frame)
            samples = _sample_layers(scene, settings.spp, seed, counter)
            seconds = time.perf_counter() - start
            bar.update(settings.spp)
            gbuffer = closest_collision_gbuffer(samples)
            motion, valid = volume_motion_vectors(gbuffer, gbuffer_prev, manifest, frame, settings.width,
                                                  settings.height)
            meta = frame_meta(manifest, scene_id, frame, settings, variant)
            meta.update({
                "spp": settings.spp, "extra_radiance_spp": 0, "seeds": {"layers": seed},
                "integrator": "mcdn_volpath_features", "volume": {"scenario": clip.scenario},
                "nonfinite": counter.counts, "nonfinite_total": int(sum(counter.counts.values())),
                "valid_fraction": float(valid.mean()), "timing_s": seconds,
                "samples_per_s": samples_per_frame / seconds,
            })
            if meta["nonfinite_total"]:
                log.warning("frame %d: replaced %d non-finite sample values %s", frame, meta["nonfinite_total"],
                            counter.counts)
            channels, half = noisy_channels(samples)
            pixel, pixel_half = pixel_channels(motion, valid, gbuffer)
            channels.update(pixel)
            write_frame(tmp_dir / f"frame_{frame:04d}.exr", channels, meta, half=half | pixel_half)
            gbuffer_prev = gbuffer
    log.info("noisy %s: %d frames", scene_id, clip.frames)


def run_render_volume_reference(cfg: dict, scene_id: str, chunk: int, scene_dir: Path, out_dir: Path,
                                settings: RenderSettings) -> None:
    """Render the references of a volumetric clip with Mitsuba's volpath: two independent halves per frame."""
    from scenegen.channels import reference_channels
    from scenegen.dataset import write_frame
    from scenegen.volumes.scenes import frame_updates

    variant, manifest, clip, scene = _open_clip(scene_id, chunk, scene_dir, settings, "volpath")
    half_spp = settings.reference_spp // 2
    n_batches = math.ceil(half_spp / settings.reference_batch_spp)
    with atomic_directory(out_dir) as tmp_dir, \
            tqdm(total=clip.frames * 2 * half_spp, desc=f"reference {scene_id}", unit="spp") as bar:
        for frame in range(clip.frames):
            start = time.perf_counter()
            frame_updates(scene, clip, frame)
            counter = NonFiniteCounter()
            seeds = tuple(reference_batch_seeds(cfg["seed"], scene_id, frame, half, n_batches) for half in (0, 1))
            reference = render_reference_frame(scene, spp=2 * half_spp, batch_spp=settings.reference_batch_spp,
                                               seeds_half=seeds, counter=counter, progress=bar, features=False)
            seconds = time.perf_counter() - start
            psnr_halves = psnr_between_halves(reference["radiance_half0"], reference["radiance_half1"])
            meta = frame_meta(manifest, scene_id, frame, settings, variant)
            meta.update({
                "spp": 2 * half_spp, "seeds": {"half0": seeds[0], "half1": seeds[1]}, "integrator": "volpath",
                "buffers": sorted(reference), "psnr_halves": psnr_halves,
                "psnr_reference_noise_floor": psnr_halves + 10.0 * math.log10(4.0),
                "nonfinite": counter.counts, "nonfinite_total": int(sum(counter.counts.values())),
                "timing_s": seconds, "samples_per_s": 2 * half_spp * settings.width * settings.height / seconds,
            })
            write_frame(tmp_dir / f"frame_{frame:04d}.exr", reference_channels(reference), meta, half=set())
    log.info("reference %s: %d frames at %d spp", scene_id, clip.frames, 2 * half_spp)
