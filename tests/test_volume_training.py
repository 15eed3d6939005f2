"""The colour-only RAE on the volumetric clips (Iglesias-Guitian et al. 2022 retrain the RAE on colour alone for
volumes): a model with ``data.scenes: volumes`` trains on the vol_train_* clips with its own split, digests and
checks, and method ``rae_color`` runs it on a volumetric clip."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

from denoisers import registry
from denoisers.experiment import train_digest
from denoisers.training.models import model_spec, training_problems, training_split
from scenegen import jobs
from scenegen.catalog import volume_scene_ids, volume_training_split
from scenegen.config import load_config
from scenegen.dataset import load_clip

ROOT = Path(__file__).resolve().parents[1]


def _config() -> dict:
    cfg = load_config(ROOT / "config/smoke.yaml")
    cfg["volumes"].update(enabled=True, scenarios=["camera", "light"], n_test=1, n_train=2, frames=3, width=24,
                          height=24, spp=2, reference_spp=16, resolution=12)
    return cfg


def test_volume_models_split_the_volumetric_training_clips_index_major() -> None:
    cfg = _config()
    cfg["training"]["validation_scenes"] = 2
    assert volume_training_split(cfg) == (["vol_train_camera_000", "vol_train_light_000"],
                                          ["vol_train_camera_001", "vol_train_light_001"])
    spec = model_spec(cfg, "rae_volume")
    assert training_split(cfg, spec) == volume_training_split(cfg)
    surface = training_split(cfg, model_spec(cfg, "rae"))                       # surface models unchanged
    assert surface == training_split(cfg) and all(s.startswith("train_") for s in sum(surface, []))
    # The volume model's digest follows the volumetric clips' renders, not the surface scenes'.
    changed = copy.deepcopy(cfg)
    changed["volumes"]["reference_spp"] = 32
    assert train_digest(cfg, "rae_volume") != train_digest(changed, "rae_volume")
    assert train_digest(cfg, "rae") == train_digest(changed, "rae")


def test_volume_model_problems_are_named() -> None:
    cfg = _config()
    cfg["volumes"]["n_train"] = 0
    assert any("rae_volume" in p and "vol_train_* clips" in p for p in training_problems(cfg))
    cfg = _config()
    model = next(m for m in cfg["training"]["models"] if m["id"] == "rae_volume")
    model["net"]["demodulate"] = True
    assert any("rae_volume" in p and "colour-only RAE needs" in p for p in training_problems(cfg))
    cfg = _config()
    model = next(m for m in cfg["training"]["models"] if m["id"] == "rae_volume")
    model["method"] = "rae"
    assert any("rae_volume" in p and "which volumetric clips do not have" in p for p in training_problems(cfg))


@pytest.mark.slow
def test_rae_color_trains_on_volumetric_clips_and_denoises_one(tmp_path) -> None:
    from denoisers.training.job import train_model

    cfg = _config()
    cfg["training"]["validation_scenes"] = 1
    renders = tmp_path / "renders"
    for scene in volume_scene_ids(cfg):
        if scene.startswith("vol_train_camera") or scene == "vol_test_camera_000":
            jobs.run_generate(cfg, scene, tmp_path / "scenes" / scene)
            jobs.run_render_noisy(cfg, scene, 0, tmp_path / "scenes" / scene, renders / scene / "noisy/chunk_000")
            jobs.run_render_reference(cfg, scene, 0, tmp_path / "scenes" / scene,
                                      renders / scene / "reference/chunk_000")
    cfg["volumes"]["scenarios"] = ["camera"]          # the clips rendered above: 1 trains, 1 validates
    summary = train_model(cfg, "rae_volume", renders, tmp_path / "models" / "rae_volume", threads=1, progress=False)
    assert summary["steps"] == 4
    method = registry.build("rae_color", {"checkpoint": str(tmp_path / "models/rae_volume/best.pt")})
    clip = load_clip(renders / "vol_test_camera_000", buffers=method.info.inputs, spp=2)
    outputs = [method.denoise(frame) for frame in registry.clip_frames(clip, method.info, 2)]
    assert len(outputs) == 3 and all(out.shape == (3, 24, 24) and torch.isfinite(out).all() for out in outputs)
    # The sample-feature RAE reads buffers the clips do not have: the loader refuses them by name.
    with pytest.raises(Exception, match="normal|albedo"):
        load_clip(renders / "vol_test_camera_000", buffers=registry.get("rae_samples").info.inputs, spp=2)
