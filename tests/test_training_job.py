"""Tests of the training stage's configuration (denoisers/training/models.py, tasks.py) and of one training job
(denoisers/training/job.py) on synthetic clips standing in for the rendered training scenes."""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
import torch

from denoisers.nets.rae import RAEConfig, parameter_count
from denoisers.training import data as training_data
from denoisers.training.job import train_model, whole_frame_check, work_dir_for
from denoisers.training.loop import load_checkpoint
from denoisers.training.models import (model_spec, model_specs, resolve_method_params, same_training_as,
                                       training_problems, training_split)
from scenegen.config import load_config
from tests.test_training import synthetic_clip

REPO_ROOT = Path(__file__).resolve().parents[1]


def smoke_config() -> dict:
    return load_config(REPO_ROOT / "config" / "smoke.yaml")


def tiny_training_config() -> dict:
    """The smoke config with a two-level RAE on 8x8 crops of 3-frame sequences (synthetic 16x16 clips)."""
    cfg = smoke_config()
    cfg["training"]["models"][0].update(net={"width": 0.125, "levels": 2}, data={**cfg["training"]["models"][0]["data"],
                                                                                 "crop": 8, "length": 3})
    cfg["training"]["models"][0]["budget"] = {"max_steps": 3}
    cfg["training"]["ablations"] = []
    cfg["training"]["validate_every"] = 2
    return cfg


@pytest.fixture
def synthetic_renders(monkeypatch: pytest.MonkeyPatch):
    """load_clip returns a synthetic clip named after the render directory (seeded by the scene)."""

    def fake_load_clip(render_dir, **kwargs):
        name = Path(render_dir).name
        return synthetic_clip(frames=6, layers=4, seed=sum(map(ord, name)), scene=name)

    monkeypatch.setattr(training_data, "load_clip", fake_load_clip)
    training_data.clear_clip_cache()
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)
    training_data.clear_clip_cache()


# ------------------------------------------------------------------------------------- config level
def test_ablation_variants_inherit_the_base_model_and_share_the_ablation_budget() -> None:
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    specs = {spec.id: spec for spec in model_specs(cfg)}
    base = specs["rae"]
    raw = next(entry for entry in cfg["training"]["models"] if entry["id"] == "rae")
    assert base.net == {"width": 0.5, "feature_init": "zero"} and base.budget["max_steps"] == raw["budget"]["max_steps"] == 4000
    color = specs["rae_inputs_color"]
    assert color.net == {"width": 0.5, "feature_init": "zero", "demodulate": False, "features": []}
    assert color.loss == base.loss and color.data == base.data and color.optimizer == base.optimizer
    inputs = next(entry for entry in cfg["training"]["ablations"] if entry["id"] == "rae_inputs")
    assert "budget" not in inputs and color.seed == base.seed and color.budget == base.budget
    assert specs["rae_loss_spatial"].loss == {"spatial": 1.0, "gradient": 0.0, "temporal": 0.0}
    assert (color.ablation, color.variant) == ("rae_inputs", "color")
    # The default has the Fig. 3 input sets that add demodulation, normals, then depth and roughness; the cluster
    # config has all six. Both losses of §4.4 are configured.
    assert {s.variant for s in specs.values() if s.ablation == "rae_inputs"} == {
        "color", "untextured", "normal", "all"}
    cluster = {spec.id: spec for spec in model_specs(load_config(REPO_ROOT / "config" / "cluster.yaml"))}
    assert {s.variant for s in cluster.values() if s.ablation == "rae_inputs"} == {
        "color", "untextured", "depth", "normal", "normal_depth", "all"}
    assert {s.variant for s in specs.values() if s.ablation == "rae_loss"} == {"spatial", "combined"}


def test_a_variant_identical_to_its_base_is_the_same_training() -> None:
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    same = {spec.id: same_training_as(cfg, spec.id) for spec in model_specs(cfg)}
    assert same["rae_inputs_all"] == "rae" and same["rae_loss_combined"] == "rae"
    assert {model for model, source in same.items() if source} == {"rae_inputs_all", "rae_loss_combined"}
    # A budget of its own makes it a different training.
    shorter = copy.deepcopy(cfg)
    next(a for a in shorter["training"]["ablations"] if a["id"] == "rae_inputs")["budget"] = {"max_steps": 2000}
    assert same_training_as(shorter, "rae_inputs_all") is None


def test_missing_keys_take_the_schema_defaults() -> None:
    cfg = smoke_config()
    cfg["training"]["models"] = [{"id": "plain", "method": "rae"}]
    cfg["training"]["ablations"] = []
    spec = model_spec(cfg, "plain")
    assert spec.data == {"length": 7, "crop": 64, "spp": 1, "rotate": True, "flip": True, "color_range": [0.0, 2.0],
                         "backward_prob": 0.5, "stop_prob": 0.1, "layers": "random", "crops": "uniform",
                         "importance_floor": 0.2}
    assert spec.optimizer["batch_size"] == 4 and spec.optimizer["schedule"]["name"] == "ramp_inv_sqrt"
    assert spec.budget == {"max_steps": 1000, "max_seconds": None}


def test_the_last_training_scenes_are_held_out_for_validation() -> None:
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    train, validation = training_split(cfg)
    assert train == [f"train_{i:03d}" for i in range(24)] and validation == ["train_024", "train_025"]


def _model(cfg: dict, model_id: str) -> dict:
    return next(entry for entry in cfg["training"]["models"] if entry["id"] == model_id)


@pytest.mark.parametrize("break_config, message", [
    (lambda c: c["training"]["ablations"][0].update(model="raee"), "names model 'raee'"),
    (lambda c: c["training"]["models"].append(dict(c["training"]["models"][0], id="rae_loss_spatial")),
     "model id 'rae_loss_spatial' more than once"),
    (lambda c: c["evaluation"]["methods"].append({"id": "x", "method": "rae", "params": {"model": "nope"}}),
     "uses model 'nope'"),
    (lambda c: c["training"]["models"][0]["data"].update(crop=64), "data.crop = 64 exceeds the frame size 48"),
    (lambda c: c["training"]["models"][0]["data"].update(length=9), "data.length = 9 exceeds scenes.frames = 4"),
    (lambda c: c["scenes"].update(n_train=1), "at least one training and one validation scene"),
    (lambda c: c["training"]["models"][0]["net"].update(widht=0.5), "unknown configuration keys ['widht']"),
    (lambda c: c["training"]["models"][0]["loss"].update(perceptual=1.0), "unknown loss terms ['perceptual']"),
    (lambda c: c["training"]["models"][0].update(method="eaw"), "method 'eaw' cannot be trained"),
    # The task builds, but its sequences carry motion vectors, which backward playback would misread.
    (lambda c: _model(c, "afn_single").update(data={**_model(c, "afn_single")["data"], "backward_prob": 0.5}),
     "backward playback needs forward motion vectors"),
])
def test_training_problems_name_the_key(break_config, message: str) -> None:
    cfg = smoke_config()
    assert training_problems(cfg) == []
    broken = copy.deepcopy(cfg)
    break_config(broken)
    problems = training_problems(broken)
    assert any(message in problem for problem in problems), problems


def test_an_evaluation_row_names_its_model_and_gets_the_checkpoint_path() -> None:
    cfg = smoke_config()
    params = resolve_method_params(cfg, {"model": "rae", "reset_state_every_frame": True}, "some/results")
    assert params == {"checkpoint": "some/results/models/rae/best.pt", "reset_state_every_frame": True}
    assert resolve_method_params(cfg, {"factor": 2}) == {"factor": 2}
    with pytest.raises(KeyError, match="no trained model with id 'missing'"):
        resolve_method_params(cfg, {"model": "missing"})


def test_the_work_directory_ignores_the_budget_but_not_the_settings(tmp_path: Path) -> None:
    cfg = smoke_config()
    spec = model_spec(cfg, "rae")
    longer = copy.deepcopy(cfg)
    longer["training"]["models"][0]["budget"] = {"max_steps": 400}
    wider = copy.deepcopy(cfg)
    wider["training"]["models"][0]["net"]["width"] = 0.5
    assert work_dir_for(tmp_path, cfg, spec) == work_dir_for(tmp_path, longer, model_spec(longer, "rae"))
    assert work_dir_for(tmp_path, cfg, spec) != work_dir_for(tmp_path, wider, model_spec(wider, "rae"))


def _with_schedule(cfg: dict, schedule: dict, max_steps: int) -> dict:
    cfg = copy.deepcopy(cfg)
    cfg["training"]["models"][0]["optimizer"] = {**cfg["training"]["models"][0].get("optimizer", {}),
                                                 "schedule": schedule}
    cfg["training"]["models"][0]["budget"] = {"max_steps": max_steps}
    return cfg


def test_a_step_schedule_given_as_a_fraction_of_the_budget_is_the_absolute_schedule(tmp_path: Path) -> None:
    """every_fraction f at B steps is every = round(f B): the same spec, digests and work directory as the
    absolute form; a longer budget moves the drops, so it is another training (a new work directory), while an
    absolute schedule keeps its work directory and continues."""
    cfg = smoke_config()
    fraction = _with_schedule(cfg, {"name": "step", "every_fraction": 0.35, "gamma": 0.5625}, 4000)
    absolute = _with_schedule(cfg, {"name": "step", "every": 1400, "gamma": 0.5625}, 4000)
    spec_f, spec_a = model_spec(fraction, "rae"), model_spec(absolute, "rae")
    assert spec_f.optimizer["schedule"] == {"name": "step", "every": 1400, "gamma": 0.5625}
    assert spec_f.settings() == spec_a.settings()
    assert work_dir_for(tmp_path, fraction, spec_f) == work_dir_for(tmp_path, absolute, spec_a)

    longer_f = _with_schedule(cfg, {"name": "step", "every_fraction": 0.35, "gamma": 0.5625}, 8000)
    longer_a = _with_schedule(cfg, {"name": "step", "every": 1400, "gamma": 0.5625}, 8000)
    assert model_spec(longer_f, "rae").optimizer["schedule"]["every"] == 2800
    assert work_dir_for(tmp_path, longer_f, model_spec(longer_f, "rae")) != work_dir_for(tmp_path, fraction, spec_f)
    assert work_dir_for(tmp_path, longer_a, model_spec(longer_a, "rae")) == work_dir_for(tmp_path, absolute, spec_a)
    # A cosine without total_steps decays over the budget in the same way.
    cosine = _with_schedule(cfg, {"name": "cosine", "warmup_steps": 10}, 300)
    longer_cosine = _with_schedule(cfg, {"name": "cosine", "warmup_steps": 10}, 600)
    assert model_spec(cosine, "rae").optimizer["schedule"]["total_steps"] == 300
    assert work_dir_for(tmp_path, cosine, model_spec(cosine, "rae")) != \
        work_dir_for(tmp_path, longer_cosine, model_spec(longer_cosine, "rae"))
    # A tiny budget still drops at most once per step.
    assert model_spec(_with_schedule(cfg, {"name": "step", "every_fraction": 0.01}, 10), "rae") \
        .optimizer["schedule"]["every"] == 1


def test_an_ablation_with_its_own_budget_resolves_the_fraction_against_it() -> None:
    cfg = _with_schedule(smoke_config(), {"name": "step", "every_fraction": 0.5, "gamma": 0.5}, 100)
    cfg["training"]["ablations"] = [{"id": "abl", "model": "rae", "budget": {"max_steps": 300},
                                     "variants": [{"id": "a"}]},
                                    {"id": "same", "model": "rae", "variants": [{"id": "b"}]}]
    assert model_spec(cfg, "rae").optimizer["schedule"]["every"] == 50
    assert model_spec(cfg, "abl_a").optimizer["schedule"]["every"] == 150
    assert model_spec(cfg, "same_b").optimizer["schedule"]["every"] == 50


@pytest.mark.parametrize("schedule, message", [
    ({"name": "step", "gamma": 0.5}, r"schedule' = .* needs exactly one of every, every_fraction; given: none"),
    ({"name": "step", "every": 10, "every_fraction": 0.5}, "given: every, every_fraction"),
    ({"name": "step", "every_fraction": 1.5}, "every_fraction"),
    ({"name": "step", "every_fraction": 0.0}, "every_fraction"),
    ({"name": "step", "every": 0}, "every"),
])
def test_a_step_schedule_needs_exactly_one_valid_interval(tmp_path: Path, schedule: dict, message: str) -> None:
    from scenegen.config import ConfigError

    cfg = _with_schedule(smoke_config(), schedule, 100)
    path = tmp_path / "bad.yaml"
    path.write_text(json.dumps(cfg))
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_the_trainer_names_a_step_schedule_without_an_interval() -> None:
    from denoisers.training.schedules import lr_factor

    with pytest.raises(ValueError, match="needs every"):
        lr_factor({"name": "step", "every_fraction": 0.5}, 3)
    with pytest.raises(ValueError, match="every >= 1"):
        lr_factor({"name": "step", "every": 0}, 3)


def test_the_training_thread_count_is_part_of_every_models_settings(tmp_path: Path) -> None:
    """The weights depend on torch's thread count, so training.threads is a setting: every model (ablation
    variants included) carries it, and changing it changes the digests, the work directory and retrains."""
    from denoisers.experiment import Lineage

    cfg = smoke_config()
    two = copy.deepcopy(cfg)
    two["training"]["threads"] = 2
    assert {spec.threads for spec in model_specs(cfg)} == {1} and {spec.threads for spec in model_specs(two)} == {2}
    for spec in model_specs(cfg):
        assert Lineage(cfg).model(spec.id) != Lineage(two).model(spec.id), spec.id
    assert work_dir_for(tmp_path, cfg, model_spec(cfg, "rae")) != work_dir_for(tmp_path, two, model_spec(two, "rae"))
    # A variant equal to its base at one thread count is equal at the other too.
    assert {s.id: same_training_as(cfg, s.id) for s in model_specs(cfg)} == \
        {s.id: same_training_as(two, s.id) for s in model_specs(two)}


def test_a_training_job_refuses_another_thread_count_than_the_configs(tmp_path: Path) -> None:
    cfg = tiny_training_config()
    with pytest.raises(ValueError, match="training.threads = 1"):
        train_model(cfg, "rae", tmp_path / "renders", tmp_path / "models" / "rae", threads=2, progress=False)
    assert not (tmp_path / "models").exists()


# ---------------------------------------------------------------------------------------- the job
def test_a_training_job_publishes_the_model_and_is_deterministic(tmp_path: Path, synthetic_renders) -> None:
    cfg = tiny_training_config()
    summary = train_model(cfg, "rae", tmp_path / "renders", tmp_path / "a" / "models" / "rae", threads=1,
                          progress=False)
    out = tmp_path / "a" / "models" / "rae"
    assert {p.name for p in out.iterdir()} == {"best.pt", "curves.csv", "curves.png", "summary.json",
                                                "validation.csv", "settings.json"}
    assert summary["steps"] == 3 and summary["stopped_by"] == "max_steps"
    assert summary["provenance"]["threads"] == {"training": 1} and "torch" in summary["provenance"]["packages"]
    assert summary["train_scenes"] == ["train_000"] and summary["validation_scenes"] == ["train_001"]
    assert summary["parameters_full_width"] == parameter_count(RAEConfig(levels=2))      # width 1, same design
    assert summary["parameters"] == parameter_count(RAEConfig(width=0.125, levels=2))
    assert json.loads((out / "settings.json").read_text())["net"] == {"width": 0.125, "levels": 2}
    validation = (out / "validation.csv").read_text().strip().splitlines()
    assert len(validation) == 1 + cfg["training"]["validation_sequences"]
    # Trained on 8-pixel crops of 16-pixel frames: best.pt is checked on whole validation frames.
    check = summary["crop_check"]
    assert check["crop"] == 8 and set(check["scenes"]) == {"train_001"} and math.isfinite(check["gap_db"])
    assert check["gap_db"] == check["scenes"]["train_001"]["gap_db"]
    # The same config and seed from scratch give the same weights.
    train_model(cfg, "rae", tmp_path / "renders", tmp_path / "b" / "models" / "rae", threads=1, progress=False)
    a, b = (load_checkpoint(tmp_path / run / "models" / "rae" / "best.pt")["model_state"] for run in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_longer_budget_continues_the_previous_run(tmp_path: Path, synthetic_renders) -> None:
    cfg = tiny_training_config()
    out = tmp_path / "models" / "rae"
    first = train_model(cfg, "rae", tmp_path / "renders", out, threads=1, progress=False)
    assert first["resumed_from"] is None
    cfg["training"]["models"][0]["budget"] = {"max_steps": 5}
    longer = train_model(cfg, "rae", tmp_path / "renders", out, threads=1, progress=False)
    assert longer["resumed_from"] == 3 and longer["steps"] == 5
    # A shorter budget than the checkpoint's steps trains from scratch instead of pretending.
    cfg["training"]["models"][0]["budget"] = {"max_steps": 2}
    shorter = train_model(cfg, "rae", tmp_path / "renders", out, threads=1, progress=False)
    assert shorter["resumed_from"] is None and shorter["steps"] == 2


def test_an_identical_variant_publishes_the_base_weights_under_its_own_id(tmp_path: Path, synthetic_renders) -> None:
    from denoisers.experiment import Lineage
    from denoisers.training.job import publish_same_training

    cfg = tiny_training_config()
    cfg["training"]["ablations"] = [{"id": "abl", "model": "rae", "variants": [{"id": "same"}]}]
    models = tmp_path / "models"
    with pytest.raises(FileNotFoundError, match="'rae'"):
        train_model(cfg, "abl_same", tmp_path / "renders", models / "abl_same", threads=1, progress=False)
    train_model(cfg, "rae", tmp_path / "renders", models / "rae", threads=1, progress=False)
    summary = train_model(cfg, "abl_same", tmp_path / "renders", models / "abl_same", threads=1, progress=False)
    assert summary["same_training_as"] == "rae" and summary["model_id"] == "abl_same"
    assert summary["settings_digest"] == Lineage(cfg).model("abl_same") != Lineage(cfg).model("rae")
    assert (models / "abl_same" / "best.pt").read_bytes() == (models / "rae" / "best.pt").read_bytes()
    assert json.loads((models / "abl_same" / "settings.json").read_text())["variant"] == "same"
    # Independent of the shortcut: a model trained for real with the base's settings and seed under another id
    # has the same weights, so reusing them is what training the variant would give.
    twin = copy.deepcopy(cfg)
    twin["training"]["ablations"] = []
    twin["training"]["models"].append({**copy.deepcopy(twin["training"]["models"][0]), "id": "twin",
                                       "seed": model_spec(cfg, "rae").seed})
    train_model(twin, "twin", tmp_path / "renders", tmp_path / "twin" / "models" / "twin", threads=1, progress=False)
    a, b = (load_checkpoint(path)["model_state"] for path in (models / "rae" / "best.pt",
                                                             tmp_path / "twin" / "models" / "twin" / "best.pt"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    # A base trained with other settings is not reused.
    stale = copy.deepcopy(cfg)
    stale["training"]["models"][0]["net"]["width"] = 0.25
    with pytest.raises(ValueError, match="other settings"):
        publish_same_training(stale, "abl_same", models / "rae", tmp_path / "stale" / "abl_same")


@pytest.mark.parametrize("config_name", ["config.yaml", "cluster.yaml", "smoke.yaml"])
def test_the_hasselgren_variants_share_data_seed_and_budget(config_name: str) -> None:
    """Issue 12: the five NTASD variants are compared as trained with the same data, seed and budget."""
    cfg = load_config(REPO_ROOT / "config" / config_name)
    methods = {"ntasd", "ntasd_uniform", "ntasd_kpn", "ntasd_direct", "dasr"}
    specs = [spec for spec in model_specs(cfg) if spec.method in methods and spec.ablation is None]
    assert {spec.method for spec in specs} == methods
    assert len({spec.seed for spec in specs}) == 1

    def common(data: dict) -> dict:     # direct prediction adds the paper's colour augmentation (Sec. 2.2)
        return {k: v for k, v in data.items() if k not in ("permute_channels", "grayscale_prob")}

    assert all(common(spec.data) == common(specs[0].data) and spec.budget == specs[0].budget for spec in specs)
    direct = next(spec for spec in specs if spec.method == "ntasd_direct")
    assert direct.data["permute_channels"] is True and direct.data["grayscale_prob"] > 0
    assert not any(spec.data.get("permute_channels") for spec in specs if spec is not direct)


def test_model_specs_are_rebuilt_when_the_training_section_changes_and_never_shared() -> None:
    cfg = load_config(Path(__file__).resolve().parents[1] / "config/config.yaml")
    first = model_specs(cfg)
    first[0].net["width"] = 99.0                       # a caller mutating its copy
    again = model_specs(cfg)
    assert again[0].net["width"] != 99.0 and [s.id for s in again] == [s.id for s in first]
    changed = copy.deepcopy(cfg)
    changed["training"]["models"][0]["net"]["width"] = 0.25
    assert model_specs(changed)[0].net["width"] == 0.25
    reseeded = dict(cfg, seed=cfg["seed"] + 1)
    assert model_specs(reseeded)[0].seed != model_specs(cfg)[0].seed


def test_the_whole_frame_check_is_skipped_with_a_reason(tmp_path: Path) -> None:
    cfg = smoke_config()
    rae, ntasd = model_spec(cfg, "rae"), model_spec(cfg, "ntasd")
    # Neither branch reads a checkpoint or a clip.
    missing = tmp_path / "no_model.pt"
    assert whole_frame_check(rae, None, 1, [tmp_path], missing) == {"skipped": "trained on whole frames"}
    assert "adaptive" in whole_frame_check(ntasd, 32, 4, [tmp_path], missing)["skipped"]
