"""scenes.train_frames: shorter clips for the train_* scenes only (issue 11 §2, the data-scale choice).

Absent or null changes no digest of any scene; a value changes exactly the train_* scenes' scene and render
digests and chunk counts; the scene generator is asked for that many frames; a model whose sequences are
longer than the training clips is a config error naming the key.
"""
from __future__ import annotations

import copy
from pathlib import Path

import pytest

from scenegen import jobs
from scenegen.catalog import chunk_count, scene_frame_count, scene_ids
from scenegen.config import ConfigError, load_config, validate_config
from scenegen.digests import render_digest, scene_digest

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {"default": REPO_ROOT / "config" / "config.yaml", "smoke": REPO_ROOT / "config" / "smoke.yaml"}


def _config(name: str, train_frames: int | None) -> dict:
    cfg = load_config(CONFIGS[name])
    cfg["scenes"]["train_frames"] = train_frames
    return validate_config(cfg)


def _digests(cfg: dict) -> dict[tuple[str, str], str]:
    out = {}
    for scene in scene_ids(cfg):
        out[(scene, "scene")] = scene_digest(cfg, scene)
        for kind in ("noisy", "reference"):
            out[(scene, kind)] = render_digest(cfg, scene, kind)
    return out


@pytest.mark.parametrize("name", CONFIGS)
def test_absent_or_null_changes_no_digest(name: str) -> None:
    null = _config(name, None)
    absent = copy.deepcopy(null)
    del absent["scenes"]["train_frames"]
    equal = _config(name, null["scenes"]["frames"])
    assert _digests(null) == _digests(absent)
    # The value equal to scenes.frames is the same clip: the same scenes and renders.
    assert _digests(equal) == _digests(null)


@pytest.mark.parametrize("name", CONFIGS)
def test_a_value_changes_only_the_train_scenes(name: str) -> None:
    base = _config(name, None)
    frames = base["scenes"]["frames_per_chunk"] if base["scenes"]["frames"] > base["scenes"]["frames_per_chunk"] \
        else base["scenes"]["frames"] - 1
    short = _config(name, frames)
    before, after = _digests(base), _digests(short)
    changed = {key for key in before if before[key] != after[key]}
    trains = {scene for scene in scene_ids(base) if scene.startswith("train_")}
    assert changed == {(scene, what) for scene in trains for what in ("scene", "noisy", "reference")}
    for scene in scene_ids(base):
        expected = frames if scene in trains else base["scenes"]["frames"] if scene.startswith("test_") \
            else scene_frame_count(base, scene)
        assert scene_frame_count(short, scene) == expected, scene
    train, test = sorted(trains)[0], "test_000"
    assert chunk_count(short, train) == -(-frames // short["scenes"]["frames_per_chunk"])
    assert chunk_count(short, test) == chunk_count(base, test)


def test_the_generator_is_asked_for_the_train_frames(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    cfg = _config("smoke", 3)
    asked: dict[str, int] = {}

    def fake_generate(scene_cfg, seed, scene_id, out_dir, n_frames, luminance_check=None):
        asked[scene_id] = n_frames
        return {"shapes": [], "n_frames": n_frames}

    import scenegen.generate

    monkeypatch.setattr(scenegen.generate, "generate_scene", fake_generate)   # run_generate imports it at call time
    jobs.run_generate(cfg, "train_000", tmp_path / "train_000")
    jobs.run_generate(cfg, "test_000", tmp_path / "test_000")
    assert asked == {"train_000": 3, "test_000": cfg["scenes"]["frames"]}


def test_sequences_longer_than_the_training_clips_are_a_config_error() -> None:
    """Checked with the other training problems (denoisers.training.models.training_problems, the workflow's
    config check) and, for the value itself, by the schema."""
    from denoisers.training.models import training_problems

    cfg = load_config(CONFIGS["smoke"])
    length = max(model["data"]["length"] for model in cfg["training"]["models"])
    cfg["scenes"]["train_frames"] = length - 1
    problems = training_problems(validate_config(cfg))
    assert f"training model 'rae': data.length = {length} exceeds scenes.train_frames = {length - 1}" in problems
    cfg["scenes"]["train_frames"] = 0
    with pytest.raises(ConfigError, match="scenes.train_frames"):
        validate_config(cfg)
