"""benchmarks/dag_budget.py: the work a config asks for and the rates read from sidecars and benchmark files."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from scenegen.config import validate_config

from tests.benchmark_modules import load_benchmark

REPO_ROOT = Path(__file__).resolve().parents[1]
dag_budget = load_benchmark("dag_budget")


def smoke() -> dict:
    return validate_config(yaml.safe_load((REPO_ROOT / "config" / "smoke.yaml").read_text()))


def test_render_work_counts_every_chunk_at_its_own_reference_spp_and_layers() -> None:
    cfg = smoke()
    cfg["render"]["train_reference_spp"] = 16
    work = dag_budget.render_work(cfg).set_index(["scene", "chunk"])
    render, scenes = cfg["render"], cfg["scenes"]
    pixels = render["width"] * render["height"]
    frames = scenes["frames_per_chunk"]
    # A training scene that trains (not a validation scene) takes train_reference_spp; a test scene reference_spp.
    assert work.loc[("train_000", 0), "reference_samples"] == frames * pixels * 16
    assert work.loc[("test_000", 0), "reference_samples"] == frames * pixels * render["reference_spp"]
    assert work.loc[("test_000", 0), "noisy_pixel_layers"] == frames * pixels * (render["spp"] + render["extra_radiance_spp"])
    # Stability clips at their own size and reference spp.
    stab = cfg["stability"]
    first = f"stab_{stab['scenarios'][0]}"
    assert work.loc[(first, 0), "reference_samples"] == stab["frames"] * stab["width"] * stab["height"] * stab["reference_spp"]
    # The configured reference integrator, except for the stability clips (their masks need the feature means).
    assert work.loc[("test_000", 0), "reference_integrator"] == "path"
    assert work.loc[(first, 0), "reference_integrator"] == "mcdn_features"
    # Volumetric clips: one chunk each, at the volumes section's size, spp and reference spp, with their integrators.
    vol = cfg["volumes"]
    clip = work.loc[(f"vol_test_{vol['scenarios'][0]}_000", 0)]
    assert clip["reference_samples"] == vol["frames"] * vol["width"] * vol["height"] * vol["reference_spp"]
    assert clip["noisy_pixel_layers"] == vol["frames"] * vol["width"] * vol["height"] * vol["spp"]
    assert (clip["reference_integrator"], clip["noisy_integrator"]) == ("volpath", "mcdn_volpath_features")
    assert work.loc[("test_000", 0), "noisy_integrator"] == "mcdn_features"
    n_volume = len(vol["scenarios"]) * (vol["n_test"] + vol["n_train"])
    # Every animated scenario also renders its failure-free control clip stab_{name}__still.
    controls = [f"stab_{name}__still" for name in stab["scenarios"] if name not in ("caustics", "low_light")]
    assert work.loc[(controls[0], 0), "reference_integrator"] == "mcdn_features"
    assert work.index.get_level_values("scene").nunique() == (scenes["n_train"] + scenes["n_test"]
                                                              + len(stab["scenarios"]) + len(controls) + n_volume)


def test_rates_come_from_the_sidecars_and_benchmark_folders_map_to_rules(tmp_path: Path) -> None:
    renders = tmp_path / "renders" / "train_000"
    for kind, meta in (("reference", {"samples_per_s": 2.0e6}),
                       ("noisy", {"timing_s": 4.0, "width": 10, "height": 20, "spp": 3, "extra_radiance_spp": 1})):
        chunk = renders / kind / "chunk_000"
        chunk.mkdir(parents=True)
        (chunk / "frame_0000.json").write_text(json.dumps(meta))
    volume = tmp_path / "more" / "vol_test_camera_000"
    for kind, meta in (("reference", {"samples_per_s": 5.0e5, "integrator": "volpath"}),
                       ("noisy", {"timing_s": 1.0, "width": 10, "height": 10, "spp": 2,
                                  "integrator": "mcdn_volpath_features"})):
        chunk = volume / kind / "chunk_000"
        chunk.mkdir(parents=True)
        (chunk / "frame_0000.json").write_text(json.dumps(meta))
    reference, noisy = dag_budget.sidecar_rates(tmp_path / "renders", tmp_path / "more")
    # A sidecar without the integrator key was rendered by the feature integrator (before the key existed).
    assert list(reference["mcdn_features"]) == [2.0e6] and noisy["mcdn_features"][0] == pytest.approx(4.0 / (10 * 20 * 4))
    assert list(reference["volpath"]) == [5.0e5] and noisy["mcdn_volpath_features"][0] == pytest.approx(1.0 / 200)
    with pytest.raises(SystemExit, match="volumetric reference sidecars"):
        dag_budget.reference_rates({"path": reference["mcdn_features"]}, {"volpath"}, None)
    rates = dag_budget.reference_rates(reference, {"path", "mcdn_features"}, {"median_path_rate_ratio": 1.5})
    assert list(rates["path"][0]) == [3.0e6] and list(rates["mcdn_features"][0]) == [2.0e6]
    with pytest.raises(SystemExit, match="--reference-speed"):
        dag_budget.reference_rates(reference, {"path"}, None)
    for folder, seconds in (("denoise", [3.0, 5.0, 4.0]), ("tune", [7.0])):
        (tmp_path / "run" / "benchmarks" / folder).mkdir(parents=True)
        for i, value in enumerate(seconds):
            (tmp_path / "run" / "benchmarks" / folder / f"spp{i}.tsv").write_text(f"s\tmax_rss\n{value}\t10\n")
    (tmp_path / "run" / "benchmarks" / "build_report.tsv").write_text("s\tmax_rss\n9.0\t10\n")
    assert dag_budget.per_job_seconds(tmp_path / "run") == {"denoise_row": 4.0, "tune_method": 7.0, "build_report": 9.0}
    with pytest.raises(SystemExit, match="no reference or noisy frame sidecars"):
        dag_budget.sidecar_rates(tmp_path / "empty")


def test_training_uses_a_runs_observed_seconds_per_step_first(tmp_path: Path) -> None:
    """A model trained in a finished run is estimated at that run's elapsed seconds per step (validation
    included), at the config's budget; models the run lacks fall back to the training-speed record."""
    for model, steps, seconds in (("rae", 2000, 640.0), ("ntasd", 0, 0.0)):
        (tmp_path / "models" / model).mkdir(parents=True)
        (tmp_path / "models" / model / "summary.json").write_text(json.dumps({"steps": steps, "elapsed_seconds": seconds}))
    observed = dag_budget.observed_step_seconds([tmp_path, tmp_path / "other"])
    assert observed == {"rae": pytest.approx(0.32)}          # a model without steps is not a rate
    cfg = smoke()
    first = cfg["training"]["models"][0]
    speed = {"models": [{"model": first["id"], "configured_variant": "bf16", "flops_per_step": 1.0,
                         "variants": [{"variant": "bf16", "status": "timed", "ms_per_step_median": 100.0}]}]}
    work = dag_budget.training_work(cfg, speed, {first["id"]: 0.5}).set_index("model")
    steps = first["budget"]["max_steps"]
    assert work.loc[first["id"], "how"] == "observed in --run"
    assert work.loc[first["id"], "seconds"] == pytest.approx(0.5 * steps)
    work = dag_budget.training_work(cfg, speed).set_index("model")
    assert work.loc[first["id"], "how"] == "measured"
    assert work.loc[first["id"], "seconds"] == pytest.approx(0.1 * steps)
