"""render.train_reference_spp / test_reference_spp: lower-spp references for the train_* scenes only (issue 11
§2), higher-spp ones for the evaluated test_* and custom_* scenes only (issue 46 §3).

Config validation, the settings digests (absent or null changes no digest of any scene; a value changes
only the train_* scenes' reference digests and what depends on them) and one tiny real render (16x16
pixels, 2 frames) whose sidecars record the spp actually used.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest

from denoisers import evaluate
from denoisers.experiment import Lineage
from denoisers.training.models import training_split
from scenegen.catalog import extra_scene, scene_frame_count, scene_ids, scene_reference_spp
from scenegen.config import ConfigError, config_digest, load_config, validate_config
from scenegen.custom.check import scene_files
from scenegen.digests import NOISY_FORMAT_VERSION, render_digest, scene_digest
from scenegen.exr import read_exr

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {"default": REPO_ROOT / "config" / "config.yaml", "smoke": REPO_ROOT / "config" / "smoke.yaml"}
KINDS = ("noisy", "reference")


def _config(name: str, **render: Any) -> dict:
    """A shipped config with render.train_reference_spp and test_reference_spp null (and no per-scene spp) unless
    given, other
    ``render`` keys set and scenes.train_frames null (validated, defaults filled): the keys under test start
    from their schema defaults."""
    cfg = load_config(CONFIGS[name])
    cfg["render"].update({"train_reference_spp": None, "test_reference_spp": None, "test_reference_spp_per_scene": {},
                          **render})
    cfg["scenes"]["train_frames"] = None   # every clip scenes.frames long, as before either key existed
    return validate_config(cfg)


def _without_key(cfg: dict) -> dict:
    """``cfg`` as a config validated before the keys existed: render.train_reference_spp and
    test_reference_spp absent."""
    old = copy.deepcopy(cfg)
    del old["render"]["train_reference_spp"]
    del old["render"]["test_reference_spp"]
    old["render"].pop("test_reference_spp_per_scene", None)
    return old


# ------------------------------------------------------------------------------------------ validation
def _error(cfg: dict) -> str:
    with pytest.raises(ConfigError) as excinfo:
        validate_config(cfg)
    return str(excinfo.value)


@pytest.mark.parametrize(("value", "expected"), [
    (63, "config key 'render.train_reference_spp' = 63 must be a multiple of 2"),
    (0, "config key 'render.train_reference_spp' = 0 is out of range; allowed range: 2..1048576"),
    ("256", "config key 'render.train_reference_spp' = '256' has the wrong type; allowed type: integer or null"),
])
def test_invalid_values_are_rejected_naming_the_key(value: Any, expected: str) -> None:
    cfg = load_config(CONFIGS["smoke"])
    cfg["render"]["train_reference_spp"] = value
    assert expected in _error(cfg)


def test_default_is_null_and_means_reference_spp() -> None:
    cfg = load_config(CONFIGS["smoke"])
    assert cfg["render"]["train_reference_spp"] is None
    assert {scene_reference_spp(cfg, scene) for scene in scene_ids(cfg)} == {cfg["render"]["reference_spp"]}
    # A config file without the key gets the null default filled in.
    raw = load_config(CONFIGS["smoke"])
    del raw["render"]["train_reference_spp"]
    assert validate_config(raw)["render"]["train_reference_spp"] is None


def test_only_scenes_that_train_use_the_train_value() -> None:
    cfg = _config("default", train_reference_spp=256)
    assert [s for s in scene_ids(cfg) if s.startswith("custom_")], "the default config has an external scene"
    trains, validates = training_split(cfg)
    assert len(validates) >= 2 and set(validates) <= set(scene_ids(cfg))
    for scene in scene_ids(cfg):
        # Validation scenes score every model and decide convergence: they keep the high-spp reference.
        expected = 256 if scene in trains else cfg["render"]["reference_spp"]
        assert scene_reference_spp(cfg, scene) == expected, scene


def test_command_line_overrides_parse_the_value() -> None:
    """--config 'render={train_reference_spp: 256}' (or null) arrives as a string leaf."""
    from scenegen.config import load_schema
    from scenegen.overrides import coerce_override_strings

    for text, value in (("256", 256), ("null", None)):
        cfg = load_config(CONFIGS["smoke"])
        cfg["render"]["train_reference_spp"] = text
        coerce_override_strings(cfg, load_schema())
        assert validate_config(cfg)["render"]["train_reference_spp"] == value


def test_report_states_every_reference_spp() -> None:
    from denoisers.report.writer import _reference_spp_text

    def text(**render: Any) -> str:
        return _reference_spp_text({"render": render})

    assert text(reference_spp=1024, train_reference_spp=None) == "1024 spp"
    assert text(reference_spp=1024, train_reference_spp=1024, test_reference_spp=1024) == "1024 spp"
    assert text(reference_spp=1024) == "1024 spp"
    # The validation scenes keep reference_spp: the text must not put them with the training scenes.
    assert text(reference_spp=1024, train_reference_spp=256) == (
        "1024 spp for the evaluated scenes; the validation scenes 1024 spp (render.reference_spp), the training "
        "scenes 256 spp (render.train_reference_spp)")
    assert text(reference_spp=1024, train_reference_spp=256, test_reference_spp=3072).startswith(
        "3072 spp for the evaluated scenes; the validation scenes 1024 spp")
    assert "Mitsuba's path" in text(reference_spp=64, reference_integrator="path")
    cfg = _config("default", reference_spp=1024, train_reference_spp=256, test_reference_spp=3072,
                  test_reference_spp_per_scene={"test_001": 6144, "test_099": 8192})
    assert _reference_spp_text(cfg).startswith(
        "3072 spp (Mitsuba's path integrator) for the evaluated scenes (test_001: 6144 spp); the validation")


# --------------------------------------------------------------------------------------------- digests
def _legacy_render_digest(cfg: dict, scene: str, kind: str) -> str:
    """render_digest as it was before render.train_reference_spp existed (for a config without the key)."""
    noisy, reference = {"spp", "extra_radiance_spp"}, {"reference_spp", "reference_batch_spp", "reference_integrator"}
    if scene.startswith("custom_"):
        # Since added: the referenced files' contents (an edited mesh reruns the import; not this key's doing).
        entry = extra_scene(cfg, scene)
        procedural: dict[str, Any] = {"extra_scene": entry, "files": scene_files(entry)}
    else:
        procedural = {k: v for k, v in cfg["scenes"].items()
                      if k not in {"n_train", "n_test", "frames_per_chunk", "train_frames"}}
    later = {"gbuffer_albedo_spp"}         # keys added since, whose default enters no digest
    shared = [f"render.{key}" for key in cfg["render"] if key not in noisy | reference | later]
    settings = {"seed": cfg["seed"], "scenes": procedural, "render_shared": config_digest(cfg, *shared)}
    own = noisy if kind == "noisy" else reference
    render = {key: cfg["render"][key] for key in sorted(own)}
    if kind == "noisy":            # the channel layout's version, bumped with the layout since
        render["format"] = NOISY_FORMAT_VERSION
    return config_digest({"scene": settings, "frames": scene_frame_count(cfg, scene),
                          "frames_per_chunk": cfg["scenes"]["frames_per_chunk"], "render": render})


@pytest.mark.parametrize("name", CONFIGS)
def test_absent_or_null_changes_no_digest(name: str) -> None:
    with_null = _config(name, train_reference_spp=None)
    absent = _without_key(with_null)
    equal_spp = _config(name, train_reference_spp=with_null["render"]["reference_spp"])
    for scene in scene_ids(with_null):
        assert scene_digest(with_null, scene) == scene_digest(absent, scene) == scene_digest(equal_spp, scene)
        for kind in KINDS:
            digests = {render_digest(cfg, scene, kind) for cfg in (with_null, absent, equal_spp)}
            # ... and equal to the digest the code computed before the key existed: no rerun of old results.
            assert digests == {_legacy_render_digest(absent, scene, kind)}, (scene, kind)


@pytest.mark.parametrize("name", CONFIGS)
def test_a_value_changes_only_the_train_scenes_reference_digests(name: str) -> None:
    base = _config(name)
    lower = _config(name, train_reference_spp=256)
    changed = {(scene, kind) for scene in scene_ids(base) for kind in KINDS
               if render_digest(base, scene, kind) != render_digest(lower, scene, kind)}
    trains, validates = training_split(base)
    assert validates and changed == {(scene, "reference") for scene in trains}   # validation scenes keep reference_spp
    assert all(scene_digest(base, scene) == scene_digest(lower, scene) for scene in scene_ids(base))
    # Another value gives other train digests (the digest follows the effective spp).
    other = _config(name, train_reference_spp=128)
    assert render_digest(other, "train_000", "reference") != render_digest(lower, "train_000", "reference")


@pytest.mark.parametrize("name", CONFIGS)
def test_a_test_value_changes_only_the_evaluated_scenes_reference_digests(name: str) -> None:
    """render.test_reference_spp: the test_* and custom_* scenes' references, nothing else (not the
    validation scenes, whose references select every model: no model is re-keyed)."""
    base = _config(name)
    higher = _config(name, test_reference_spp=4 * base["render"]["reference_spp"])
    evaluated = [scene for scene in scene_ids(base) if scene.startswith(("test_", "custom_"))]
    assert evaluated and any(scene.startswith("custom_") for scene in evaluated) == (name == "default")
    changed = {(scene, kind) for scene in scene_ids(base) for kind in KINDS
               if render_digest(base, scene, kind) != render_digest(higher, scene, kind)}
    assert changed == {(scene, "reference") for scene in evaluated}
    assert {scene_reference_spp(higher, scene) for scene in evaluated} == {4 * base["render"]["reference_spp"]}
    assert all(scene_reference_spp(higher, scene) == scene_reference_spp(base, scene)
               for scene in scene_ids(base) if scene not in evaluated)
    assert Lineage(higher).model("rae") == Lineage(base).model("rae")
    assert Lineage(higher).tuning("eaw") == Lineage(base).tuning("eaw")
    row = evaluate.method_spec(base, "noisy")
    assert Lineage(higher).metrics(row, "test_000", 1) != Lineage(base).metrics(row, "test_000", 1)
    # The value equal to reference_spp is the same renders as null.
    same = _config(name, test_reference_spp=base["render"]["reference_spp"])
    assert all(render_digest(same, scene, "reference") == render_digest(base, scene, "reference")
               for scene in evaluated)


def test_a_clip_with_no_frame_after_the_warmup_is_refused() -> None:
    cfg = load_config(CONFIGS["smoke"])
    cfg["scenes"]["frames"] = cfg["evaluation"]["warmup_frames"]
    assert (f"config key 'scenes.frames' = {cfg['scenes']['frames']} leaves no frame after the "
            f"evaluation.warmup_frames") in _error(cfg)


def test_models_follow_the_train_references_and_evaluated_metrics_do_not() -> None:
    base, lower = _config("smoke"), _config("smoke", train_reference_spp=16)
    row = evaluate.method_spec(base, "noisy")
    assert Lineage(lower).model("rae") != Lineage(base).model("rae")
    assert Lineage(lower).tuning("eaw") != Lineage(base).tuning("eaw")       # tuned against train references
    assert Lineage(_without_key(base)).model("rae") == Lineage(base).model("rae")
    assert Lineage(lower).metrics(row, "test_000", 1) == Lineage(base).metrics(row, "test_000", 1)


# ------------------------------------------------------------------------------------------ real render
def test_train_references_render_at_the_train_spp(tmp_path: Path) -> None:
    """One tiny generated scene, its references rendered under a train and a test scene id (the spp is
    chosen by scene id): the sidecars and EXR metadata record the spp used, 4 and 12 (test_reference_spp)."""
    from scenegen import jobs

    cfg = load_config(CONFIGS["smoke"])
    cfg["render"].update(width=16, height=16, spp=1, reference_spp=8, train_reference_spp=4, test_reference_spp=12,
                         reference_batch_spp=2)
    cfg["scenes"].update(frames=2, frames_per_chunk=2)
    cfg = validate_config(cfg)
    scene_dir = tmp_path / "scenes" / "train_000"
    jobs.run_generate(cfg, "train_000", scene_dir)
    for scene, spp in (("train_000", 4), ("test_000", 12)):
        out = tmp_path / "renders" / scene / "reference" / "chunk_000"
        jobs.run_render_reference(cfg, scene, 0, scene_dir, out)
        for frame in (0, 1):
            meta = json.loads((out / f"frame_{frame:04d}.json").read_text())
            assert meta["scene"] == scene and meta["spp"] == spp
            # One seed per batch of reference_batch_spp samples in each half of spp/2.
            assert len(meta["seeds"]["half0"]) == len(meta["seeds"]["half1"]) == spp // 2 // 2
            channels, attributes = read_exr(out / f"frame_{frame:04d}.exr", ["radiance.R"])
            assert json.loads(attributes["mcdn_meta"])["spp"] == spp
            assert channels["radiance.R"].shape == (16, 16)
