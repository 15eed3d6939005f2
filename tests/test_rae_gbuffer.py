"""The RAE on G-buffer features (task and method ``rae``; Chaitanya et al. 2017 §3.1-3.2 demodulate by a
rasterised G-buffer's albedo): rendered frames carry the pixel-centre albedo and roughness, the smoke config's
model trains on them, and the method denoises a rendered clip with them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from denoisers import registry
from denoisers.training.models import training_problems, training_split
from scenegen import jobs
from scenegen.config import load_config
from scenegen.dataset import load_clip

ROOT = Path(__file__).resolve().parents[1]


def _config() -> dict:
    return load_config(ROOT / "config/smoke.yaml")


def test_the_gbuffer_model_is_a_valid_training_entry() -> None:
    cfg = _config()
    assert next(m for m in cfg["training"]["models"] if m["id"] == "rae")["method"] == "rae"
    assert not [p for p in training_problems(cfg) if "rae" in p]
    bad = _config()
    next(m for m in bad["training"]["models"] if m["id"] == "rae")["net"]["features_from"] = "samples"
    assert any("rae" in p and "features_from" in p for p in training_problems(bad))


@pytest.mark.slow
def test_rae_gbuffer_trains_on_rendered_frames_and_denoises_a_clip(tmp_path: Path) -> None:
    from denoisers.training.job import train_model

    cfg = _config()
    train, validate = training_split(cfg)
    renders = tmp_path / "renders"
    for scene in [*train, *validate, "test_000"]:
        jobs.run_generate(cfg, scene, tmp_path / "scenes" / scene)
        for chunk in (0, 1):
            jobs.run_render_noisy(cfg, scene, chunk, tmp_path / "scenes" / scene,
                                  renders / scene / f"noisy/chunk_{chunk:03d}")
            jobs.run_render_reference(cfg, scene, chunk, tmp_path / "scenes" / scene,
                                      renders / scene / f"reference/chunk_{chunk:03d}")
    clip = load_clip(renders / "test_000", buffers=("radiance", "albedo", "depth"), spp=4)
    albedo = clip.gbuffer["albedo"]
    assert albedo.shape == clip.samples["albedo"][:, 0].shape and 0.0 <= albedo.min() and albedo.max() <= 1.0
    # Noise-free: where all 4 jittered samples agree (a pixel inside one surface) and took their features at the
    # primary hit (their feature depth is the G-buffer's; through a mirror or glass it is not: the per-sample
    # features follow the specular chain, the G-buffer keeps the first surface), both hold the same albedo.
    samples = clip.samples["albedo"]
    primary = (np.abs(clip.samples["depth"][:, :, 0] - clip.gbuffer["depth"][:, None, 0]) < 1e-2).all(axis=1)
    agree = (np.ptp(samples, axis=1) < 1e-3).all(axis=1) & primary               # (T, H, W)
    assert agree.mean() > 0.3
    np.testing.assert_allclose(np.moveaxis(albedo, 1, -1)[agree], np.moveaxis(samples[:, 0], 1, -1)[agree],
                               atol=2e-3)                                       # HALF storage
    summary = train_model(cfg, "rae", renders, tmp_path / "models" / "rae", threads=1, progress=False)
    assert summary["steps"] == 4
    method = registry.build("rae", {"checkpoint": str(tmp_path / "models/rae/best.pt")})
    clip = load_clip(renders / "test_000", buffers=method.info.inputs, spp=1)
    outputs = [method.denoise(frame) for frame in registry.clip_frames(clip, method.info, 1)]
    assert len(outputs) == 4 and all(out.shape == (3, 48, 48) and torch.isfinite(out).all() for out in outputs)
