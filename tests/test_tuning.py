"""Tuning apart from testing (denoisers/jobs/tuning.py, rule tune_method).

Baseline parameters are chosen by a grid search that sees training scenes only; the grid search finds
a known optimum on synthetic clips; evaluation rows with ``tuned: true`` read its result; no shipped
config's test scenes share a seed with any shipped config's training (= tuning) scenes.
"""
from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import yaml

from denoisers import registry
from denoisers.registry import Denoiser, Frame
from denoisers.training.models import resolve_method_params
from denoisers.jobs.tuning import (TuningError, check_training_scenes, grid_combinations, tune_method,
                              tuned_params, tuning_problems)
from scenegen.catalog import scene_ids
from scenegen.config import load_config, validate_config
from scenegen.seeds import scene_seed
from tests.test_evaluate import write_synthetic_scene

REPO_ROOT = Path(__file__).resolve().parents[1]
SHIPPED_CONFIGS = sorted((REPO_ROOT / "config").glob("*.yaml"))


class Gain(Denoiser):
    """Test only: ``gain`` x the sample mean. The synthetic clips' noise is unbiased, so gain 1 is best."""

    def __init__(self, gain: float = 1.0) -> None:
        super().__init__()
        self.gain = float(gain)

    def denoise(self, frame: Frame) -> torch.Tensor:
        return self.gain * frame.samples["radiance"].mean(0)


@pytest.fixture
def gain_method() -> Iterator[str]:
    registry.register("test_gain", inputs=("radiance",), description="test only: scaled sample mean")(Gain)
    yield "test_gain"
    registry._REGISTRY.pop("test_gain", None)


def tuning_config(method: str, grid: dict) -> dict:
    cfg = yaml.safe_load((REPO_ROOT / "config" / "smoke.yaml").read_text())
    cfg["render"]["spp"] = 4
    cfg["tuning"] = {"spp": [1, 4], "max_frames": 3, "methods": [{"method": method, "grid": grid}]}
    return validate_config(cfg)


def test_grid_combinations_cover_the_grid_in_a_fixed_order() -> None:
    combos = grid_combinations({"b": [1, 2], "a": ["x", "y", "z"]})
    assert len(combos) == 6 and combos[0] == {"a": "x", "b": 1} and combos[-1] == {"a": "z", "b": 2}
    with pytest.raises(TuningError, match="non-empty list"):
        grid_combinations({"a": []})


@pytest.mark.parametrize("scenes", [["train_000", "test_000"], ["custom_room"], []])
def test_tuning_refuses_anything_but_training_scenes(scenes: list[str]) -> None:
    with pytest.raises(TuningError):
        check_training_scenes(scenes)


def test_grid_search_finds_the_known_optimum_on_training_clips(tmp_path: Path, gain_method: str) -> None:
    render_dirs = {}
    for k, scene in enumerate(("train_000", "train_001")):
        render_dirs[scene] = tmp_path / scene
        write_synthetic_scene(render_dirs[scene], scene=scene, seed=k)
    cfg = tuning_config(gain_method, {"gain": [0.25, 1.0, 4.0]})
    result = tune_method(cfg, gain_method, render_dirs)
    assert result["best_params"] == {"gain": 1.0}
    assert result["scenes"] == ["train_000", "train_001"] and result["spp"] == [1, 4]
    scores = {row["params"]["gain"]: row["score_db"] for row in result["results"]}
    assert scores[1.0] > scores[0.25] and scores[1.0] > scores[4.0]
    # Each score is the mean over (scene, spp) of the per-clip frame-mean PSNR.
    for row in result["results"]:
        per = torch.tensor(row["per_scene_spp_db"])
        assert per.shape == (2, 2) and abs(float(per.mean()) - row["score_db"]) < 1e-3


def test_tune_command_refuses_a_test_scene(tmp_path: Path) -> None:
    write_synthetic_scene(tmp_path / "test_000")
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(validate_config(yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text()))))
    result = subprocess.run([sys.executable, "-m", "denoisers", "tune", "--config", str(config), "--method", "eaw",
                             "--render-dirs", str(tmp_path / "test_000"), "--out", str(tmp_path / "eaw.json")],
                            cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1 and "training scenes" in result.stderr and "test_000" in result.stderr
    assert not (tmp_path / "eaw.json").exists()


def test_tuned_rows_read_the_tuning_result_and_their_own_params_win(tmp_path: Path) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    with pytest.raises(TuningError, match="eaw.json"):
        resolve_method_params(cfg, {"tuned": True}, tmp_path, method="eaw")
    (tmp_path / "tuning").mkdir()
    (tmp_path / "tuning" / "eaw.json").write_text(json.dumps({"best_params": {"sigma_color": 4.0,
                                                                              "sigma_position": 0.5}}))
    assert tuned_params(tmp_path, "eaw") == {"sigma_color": 4.0, "sigma_position": 0.5}
    resolved = resolve_method_params(cfg, {"tuned": True, "sigma_position": 1.0}, tmp_path, method="eaw")
    assert resolved == {"sigma_color": 4.0, "sigma_position": 1.0}
    # Planning (method None) drops the flag without reading any file.
    assert resolve_method_params(cfg, {"tuned": True}, tmp_path / "missing") == {}


@pytest.mark.parametrize("edit, message", [
    (lambda c: c["tuning"]["methods"].append({"method": "no_such", "grid": {"a": [1]}}), "unknown method"),
    (lambda c: c["tuning"]["methods"][0]["grid"].update(sigma_colour=[1.0]), "'sigma_colour' is not a parameter"),
    (lambda c: c["tuning"].update(methods=[m for m in c["tuning"]["methods"] if m["method"] != "eaw"]),
     "has no entry in config key 'tuning.methods'"),
    (lambda c: c["tuning"].update(spp=[64]), "render.spp"),
])
def test_tuning_problems_name_the_key(edit, message: str) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    assert tuning_problems(cfg) == []
    edit(cfg)
    problems = tuning_problems(cfg)
    assert any(message in problem for problem in problems), problems


def test_no_shipped_test_scene_shares_a_seed_with_any_shipped_training_scene() -> None:
    train_seeds, test_seeds = {}, {}
    for path in SHIPPED_CONFIGS:
        cfg = load_config(path)
        for scene in scene_ids(cfg):
            target = train_seeds if scene.startswith("train_") else test_seeds if scene.startswith("test_") else None
            if target is not None:
                target[scene_seed(cfg["seed"], scene)] = f"{path.name}:{scene}"
    assert len(SHIPPED_CONFIGS) >= 2 and test_seeds and train_seeds
    shared = set(train_seeds) & set(test_seeds)
    assert not shared, [(train_seeds[s], test_seeds[s]) for s in shared]


def test_report_tuning_table_states_the_chosen_parameters(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from denoisers.evaluate import method_specs
    from denoisers.report.tables import tuning_table

    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    (tmp_path / "tuning").mkdir()
    record = {"best_params": {"sigma_color": 4.0}, "best_score_db": 25.1234, "scenes": ["train_000", "train_001"],
              "spp": [1, 4], "frames_per_scene": 4,
              "results": [{"params": {"sigma_color": 4.0}, "score_db": 25.1234},
                          {"params": {"sigma_color": 8.0}, "score_db": 24.9}]}
    (tmp_path / "tuning" / "eaw.json").write_text(json.dumps(record))
    res = SimpleNamespace(cfg=cfg, specs=method_specs(cfg), results_dir=tmp_path)
    table = tuning_table(res).set_index("method")
    assert table.loc["eaw", "status"] == "ran" and table.loc["eaw", "rows"] == "eaw"
    assert json.loads(table.loc["eaw", "chosen"]) == {"sigma_color": 4.0}
    assert table.loc["eaw", "margin_db"] == pytest.approx(0.223, abs=1e-3) and table.loc["eaw", "grid_points"] == 2
    assert table.loc["wrls", "status"] == "not run"
