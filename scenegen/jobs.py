"""The pipeline's jobs: generate one scene, render one chunk of noisy frames or references.

Every job writes into a hidden temporary sibling of its output directory and renames it into
place only when everything is written, so an interrupted job leaves nothing that looks complete.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenegen.atomic import atomic_directory
from scenegen.catalog import (CUSTOM_PREFIX, STABILITY_PREFIX, VOLUME_PREFIX, extra_scene, scene_frame_count,
                              scene_frames_per_chunk, scene_reference_spp, scene_render_config)
from scenegen.mitsuba_env import init_mitsuba
from scenegen.render import (NonFiniteCounter, RenderSettings, frame_meta, load_frame_scene, noisy_frame_seed,
                             psnr_between_halves, reference_batch_seeds,
                             render_gbuffer, render_reference_frame, render_sample_layers)
from scenegen.seeds import scene_seed

log = logging.getLogger("scenegen")


def chunk_frames(n_frames: int, frames_per_chunk: int, chunk: int) -> list[int]:
    """Global frame indices of ``chunk``; raises if the chunk does not exist."""
    n_chunks = math.ceil(n_frames / frames_per_chunk)
    if not 0 <= chunk < n_chunks:
        raise ValueError(f"chunk {chunk} out of range: the clip of {n_frames} frames has {n_chunks} chunks "
                         f"of {frames_per_chunk} frames")
    return list(range(chunk * frames_per_chunk, min(n_frames, (chunk + 1) * frames_per_chunk)))


def _load_manifest(scene_dir: Path) -> dict:
    path = Path(scene_dir) / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"scene manifest not found: {path}")
    return json.loads(path.read_text())


def run_generate(cfg: dict, scene_id: str, out_dir: Path) -> dict:
    """Draw scene ``scene_id`` and write it to ``out_dir`` (manifest, meshes, textures)."""
    from scenegen.generate import generate_scene
    from scenegen.mitsuba_scene import preview_mean_luminance

    init_mitsuba(cfg["render"]["variant"])
    if scene_id.startswith(CUSTOM_PREFIX):
        from scenegen.custom.scene import import_custom_scene

        with atomic_directory(out_dir) as tmp_dir:
            manifest = import_custom_scene(extra_scene(cfg, scene_id), scene_id, tmp_dir)
        log.info("custom scene %s from %s: %d shapes", scene_id, manifest["xml"], len(manifest["shapes"]))
        return manifest
    if scene_id.startswith(STABILITY_PREFIX):
        from scenegen.scenarios import generate_scenario

        with atomic_directory(out_dir) as tmp_dir:
            manifest = generate_scenario(cfg, scene_id, tmp_dir)
        log.info("stability scenario %s: %d shapes, %d frames", scene_id, len(manifest["shapes"]),
                 manifest["n_frames"])
        return manifest
    if scene_id.startswith(VOLUME_PREFIX):
        from scenegen.volumes.render import generate_volume_scene

        return generate_volume_scene(cfg, scene_id, out_dir)
    seed = scene_seed(cfg["seed"], scene_id)
    with atomic_directory(out_dir) as tmp_dir:
        manifest = generate_scene(cfg["scenes"], seed, scene_id, tmp_dir, n_frames=scene_frame_count(cfg, scene_id),
                                  luminance_check=preview_mean_luminance)
    log.info("scene %s: seed %d, %d shapes, %d redraws", scene_id, seed, len(manifest["shapes"]),
             len(manifest.get("redraws", [])))
    return manifest


def run_render_noisy(cfg: dict, scene_id: str, chunk: int, scene_dir: Path, out_dir: Path) -> None:
    """Render the per-sample noisy frames of one chunk, with motion vectors and G-buffers."""
    from scenegen.channels import noisy_channels, pixel_channels
    from scenegen.dataset import write_frame
    from scenegen.motion import motion_vectors

    settings = RenderSettings.from_config(scene_render_config(cfg, scene_id))
    if scene_id.startswith(VOLUME_PREFIX):
        from scenegen.volumes.render import run_render_volume_noisy

        return run_render_volume_noisy(cfg, scene_id, chunk, scene_dir, out_dir, settings)
    variant = init_mitsuba(settings.variant)
    manifest = _load_manifest(scene_dir)
    frames = chunk_frames(manifest["n_frames"], scene_frames_per_chunk(cfg, scene_id), chunk)
    n_layers = settings.spp + settings.extra_radiance_spp
    samples_per_frame = n_layers * settings.width * settings.height

    rates: list[float] = []
    gbuffer_prev = (render_gbuffer(manifest, scene_dir, frames[0] - 1, settings) if frames[0] > 0 else None)
    with atomic_directory(out_dir) as tmp_dir, \
            tqdm(total=len(frames) * n_layers, desc=f"noisy {scene_id} chunk {chunk}", unit="layer") as bar:
        for frame in frames:
            start = time.perf_counter()
            scene = load_frame_scene(manifest, scene_dir, frame, settings)
            counter = NonFiniteCounter()
            seed = noisy_frame_seed(cfg["seed"], scene_id, frame)
            samples = render_sample_layers(scene, n_layers=settings.spp, n_radiance_only=settings.extra_radiance_spp,
                                           seed=seed, counter=counter, progress=bar)
            render_seconds = time.perf_counter() - start
            gbuffer = render_gbuffer(manifest, scene_dir, frame, settings, scene=scene)
            cut = bool(manifest["camera"]["frames"][frame].get("cut", False))
            motion, valid = motion_vectors(gbuffer, gbuffer_prev, manifest, frame, settings.width,
                                           settings.height, camera_cut=cut)
            meta = frame_meta(manifest, scene_id, frame, settings, variant)
            meta.update({
                "spp": settings.spp, "extra_radiance_spp": settings.extra_radiance_spp,
                "seeds": {"layers": seed}, "nonfinite": counter.counts,
                "nonfinite_total": int(sum(counter.counts.values())),
                "valid_fraction": float(valid.mean()),
                "timing_s": render_seconds, "samples_per_s": samples_per_frame / render_seconds,
            })
            if meta["nonfinite_total"]:
                log.warning("frame %d: replaced %d non-finite sample values %s", frame,
                            meta["nonfinite_total"], counter.counts)
            channels, half = noisy_channels(samples)
            pixel, pixel_half = pixel_channels(motion, valid, gbuffer)
            channels.update(pixel)
            write_frame(tmp_dir / f"frame_{frame:04d}.exr", channels, meta, half=half | pixel_half)
            bar.set_postfix(samples_per_s=f"{meta['samples_per_s']:.3g}")
            gbuffer_prev = gbuffer
            rates.append(meta["samples_per_s"])
    log.info("noisy %s chunk %d: %d frames, mean %.3g samples/s", scene_id, chunk, len(frames), np.mean(rates))


def run_render_reference(cfg: dict, scene_id: str, chunk: int, scene_dir: Path, out_dir: Path) -> None:
    """Render the high-spp references (two independent halves) of one chunk, at the scene's reference spp
    (scenegen.catalog.scene_reference_spp); the sidecars record it. An evaluated scene's chunk stored under its render
    digest is copied from the store instead (scenegen.reference_store; store.references).
    ``render.reference_integrator``: "path" renders radiance with Mitsuba's ``path`` integrator (the buffers the
    evaluation and training use); "features" renders with the feature integrator and adds the feature means."""
    from scenegen.channels import reference_channels
    from scenegen.dataset import write_frame
    from scenegen.reference_store import install_reference_chunk

    stored = install_reference_chunk(cfg, scene_id, chunk, out_dir)
    if stored is not None:
        log.info("reference %s chunk %d: installed from the store (%s); not rendered", scene_id, chunk, stored)
        return
    settings = dataclasses.replace(RenderSettings.from_config(scene_render_config(cfg, scene_id)),
                                   reference_spp=scene_reference_spp(cfg, scene_id))
    if scene_id.startswith(VOLUME_PREFIX):
        from scenegen.volumes.render import run_render_volume_reference

        return run_render_volume_reference(cfg, scene_id, chunk, scene_dir, out_dir, settings)
    variant = init_mitsuba(settings.variant)
    manifest = _load_manifest(scene_dir)
    frames = chunk_frames(manifest["n_frames"], scene_frames_per_chunk(cfg, scene_id), chunk)
    half_spp = settings.reference_spp // 2
    features = settings.reference_integrator == "features"
    mode = "samples" if features else "path"
    rates: list[float] = []
    n_batches = math.ceil(half_spp / settings.reference_batch_spp)
    with atomic_directory(out_dir) as tmp_dir, \
            tqdm(total=len(frames) * 2 * half_spp, desc=f"reference {scene_id} chunk {chunk}", unit="spp") as bar:
        for frame in frames:
            start = time.perf_counter()
            scene = load_frame_scene(manifest, scene_dir, frame, settings, mode=mode)
            counter = NonFiniteCounter()
            seeds = tuple(reference_batch_seeds(cfg["seed"], scene_id, frame, half, n_batches) for half in (0, 1))
            reference = render_reference_frame(scene, spp=2 * half_spp, batch_spp=settings.reference_batch_spp,
                                               seeds_half=seeds, counter=counter, progress=bar,
                                               features=features)
            seconds = time.perf_counter() - start
            psnr_halves = psnr_between_halves(reference["radiance_half0"], reference["radiance_half1"])
            meta = frame_meta(manifest, scene_id, frame, settings, variant)
            meta.update({
                "spp": 2 * half_spp, "seeds": {"half0": seeds[0], "half1": seeds[1]},
                "integrator": "mcdn_features" if features else "path", "buffers": sorted(reference),
                "psnr_halves": psnr_halves,
                "psnr_reference_noise_floor": psnr_halves + 10.0 * math.log10(4.0),
                "nonfinite": counter.counts, "nonfinite_total": int(sum(counter.counts.values())),
                "timing_s": seconds,
                "samples_per_s": 2 * half_spp * settings.width * settings.height / seconds,
            })
            write_frame(tmp_dir / f"frame_{frame:04d}.exr", reference_channels(reference), meta, half=set())
            bar.set_postfix(samples_per_s=f"{meta['samples_per_s']:.3g}")
            rates.append(meta["samples_per_s"])
    log.info("reference %s chunk %d: %d frames at %d spp, mean %.3g samples/s", scene_id, chunk, len(frames),
             2 * half_spp, np.mean(rates))
