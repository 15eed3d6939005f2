"""Tests for the Snakemake workflow: lint, dry-run DAG shape, config errors, rerun triggers, profiles.

None of these runs the real renderer or a denoiser: dry runs only, plus one real run of the `renders`
target in a temporary copy of the workflow where `python -m scenegen` is a stub that just creates the
output directories. Every snakemake call runs in a temporary copy of Snakefile, workflow/ and config/:
a run writes <output_dir>/.config/, and the repository's own results/ and .snakemake/ stay untouched.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from denoisers.evaluate import ABLATION_ROLE, EvaluationError, method_specs, plan_runs, robustness_runs
from denoisers.jobs.rows import row_clips
# Aliased: pytest would collect a module-level name starting with `test_` as a test.
from denoisers.evaluate import evaluated_scene_ids
from denoisers.device import resolve_config_device
from denoisers.training.models import (method_model, model_specs, same_training_as, trained_model_specs,
                                       training_split, trains_on_volumes)
from scenegen.catalog import chunk_count, scene_ids, stability_scene_ids, volume_scene_ids, volume_training_split
from scenegen.config import config_digest, load_config

REPO_ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
JOB_RULES = ("generate_scene", "render_noisy", "render_reference", "denoise_row", "evaluate_row",
             "robustness_row", "build_report", "train_denoiser", "tune_method", "time_methods", "time_training",
             "derive_masks", "denoise_scenario_row", "score_scenario_row", "build_atlas", "denoise_volume_row",
             "evaluate_volume_row", "robustness_volume_row", "verify_stored_model")
STAGE_TARGETS = ("scenes", "renders", "train", "denoise", "evaluate", "baselines", "report", "stability", "volumes",
                 "verify")
# examples/: the configs' extra_scenes XML (an input of its generate_scene job).
WORKFLOW_FILES = ("Snakefile", "workflow", "config", "examples")
# The smoke config's experiment folder (config key output_dir): every path of its DAG is below it.
SMOKE_OUT = load_config(REPO_ROOT / "config/smoke.yaml")["output_dir"]


def run_snakemake(*args: str, cwd: Path, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run the venv's snakemake in ``cwd`` with `python` (used by the rules) resolving to this interpreter."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    result = subprocess.run(
        [str(SNAKEMAKE), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    if check:
        assert result.returncode == 0, f"snakemake {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}"
    return result


def job_counts(output: str) -> dict[str, int]:
    """Parse the first 'Job stats' table of a snakemake run into {rule: job count}."""
    from denoisers.dag_counts import parse_job_stats

    return parse_job_stats(output)


def dry_run(*args: str, cwd: Path) -> dict[str, int]:
    result = run_snakemake("-n", *args, cwd=cwd)
    return job_counts(result.stdout + result.stderr)


def copy_workflow(destination: Path) -> Path:
    """Copy Snakefile, workflow/, config/ and examples/ to ``destination``; the rules' CLIs stay the installed
    ones."""
    for name in WORKFLOW_FILES:
        source = REPO_ROOT / name
        if source.is_dir():
            shutil.copytree(source, destination / name)
        else:
            shutil.copy(source, destination / name)
    return destination


@pytest.fixture(scope="module")
def workflow_copy(tmp_path_factory) -> Path:
    """A fresh copy of the workflow without results, for dry runs."""
    return copy_workflow(tmp_path_factory.mktemp("workflow"))


def expected_jobs(cfg: dict, target: str = "all") -> dict[str, int]:
    """{rule: job count} of a --forceall dry run of ``target``, derived from the config.

    Renders cover every scene; the evaluation only the evaluated scenes (test and custom), with one
    denoise and one evaluate job per row with a runnable (row, spp) pair (each job does the row's clips: every
    evaluated scene at each of its spp) and one robustness job per runnable row with robustness at
    evaluation.robustness.spp. The rows are
    evaluation.methods (each at its own spp) plus one per trained ablation variant (at evaluation.ablation_spp). Which pairs are planned and
    runnable (those needing no more sample layers than were rendered) is decided by the workflow's own
    planning, denoisers.evaluate.plan_runs / robustness_runs.
    """
    scenes, test_scenes = scene_ids(cfg), evaluated_scene_ids(cfg)
    def rows(runs) -> int:
        return len({run.spec.id for run in runs if run.runnable}) if test_scenes else 0

    evaluated, robustness = rows(plan_runs(cfg)), rows(robustness_runs(cfg))
    # Training reads every train_* scene (the held-out validation scenes too); the evaluation needs only the
    # models its rows name, the report and the default target every configured model.
    train_scenes = sum(training_split(cfg), [])
    all_models = len(trained_model_specs(cfg))      # seed replicas and half-budget twins included

    # The models the evaluated rows name (the configured rows' and the ablation rows', one per variant), plus
    # the base of a variant whose training is its base's (same_training_as): its job copies the base's weights.
    def needed(models: set) -> int:
        models = models - {None}
        return len(models | {same_training_as(cfg, m) for m in models} - {None})

    used_models = needed({method_model(spec.params) for spec in method_specs(cfg)})
    # One tuning job per method that an evaluated row takes tuned parameters from; it reads the training scenes.
    tuned = len({run.spec.method for run in plan_runs(cfg) if run.runnable and run.spec.params.get("tuned")})

    def renders(noisy: list[str], reference: list[str]) -> dict[str, int]:
        ids = set(noisy) | set(reference)
        return {"generate_scene": len(ids), "render_noisy": sum(chunk_count(cfg, s) for s in set(noisy)),
                "render_reference": sum(chunk_count(cfg, s) for s in set(reference))}

    training_inputs = train_scenes if all_models or tuned else []
    baseline_runs = [run for run in plan_runs(cfg) if run.runnable and method_model(run.spec.params) is None]
    baseline_jobs = rows(baseline_runs)
    baseline_tuned = len({run.spec.method for run in baseline_runs if run.spec.params.get("tuned")})
    baseline_inputs = train_scenes if baseline_tuned else []
    used_inputs = train_scenes if used_models or tuned else []
    # The timing job (rule time_methods): one, if any configured row is runnable; its inputs (the timing
    # scene's noisy renders, the rows' models and tuning results) are needed by the evaluation anyway.
    from denoisers.jobs.timing import timed_runs

    timed = 1 if test_scenes and timed_runs(cfg) else 0
    evaluation = {"denoise_row": evaluated, "evaluate_row": evaluated, "robustness_row": robustness,
                  "time_methods": timed}
    # The training-speed job (rule time_training): one, if training.speed times a model; no inputs; the report
    # (and so the default target) reads it, the evaluation does not.
    from denoisers.training.speed import speed_models

    speed = {"time_training": 1 if speed_models(cfg) else 0}
    # The stability scenarios (target `stability`, also part of `report` and `all`): per stab_* scene its scene,
    # its chunks (one per clip) and one derive_masks job; every configured row with a runnable stability.denoise_spp
    # denoises and scores all its clips in one job each (denoise_scenario_row, score_scenario_row), with the models
    # and tuning results those rows need (and so the training scenes' renders), and one build_atlas job.
    from denoisers.jobs.stability import stability_runs

    from scenegen.scenarios import stability_control_ids

    # Each animated scenario's failure-free control clip (stab_{name}__still) is rendered and denoised by every
    # run (the lag metric's steady state), but has no masks and no scores of its own.
    stab, stab_controls = stability_scene_ids(cfg), stability_control_ids(cfg)
    stab_runs = [run for run in stability_runs(cfg) if run.runnable]
    stab_models = needed({method_model(run.spec.params) for run in stab_runs})
    stab_tuned = {run.spec.method for run in stab_runs if run.spec.params.get("tuned")}
    stab_train = train_scenes if stab_models or stab_tuned else []
    stab_clips = stab + stab_controls
    stab_rows = len({run.spec.id for run in stab_runs})
    stability = {**renders(stab_clips + stab_train, stab_clips + stab_train), "derive_masks": len(stab),
                 "denoise_scenario_row": stab_rows, "score_scenario_row": stab_rows,
                 "build_atlas": 1 if stab else 0, "train_denoiser": stab_models, "tune_method": len(stab_tuned)}
    # The volumetric clips (target `volumes`, also part of `report` and `all`): their scenes and chunks (one per
    # clip), and every volume row with a runnable spp denoised and scored on every vol_test_* clip, one job per row.
    from denoisers.jobs.volumes import volume_robustness_runs, volume_runs, volume_test_scene_ids

    vol, vol_test = volume_scene_ids(cfg), volume_test_scene_ids(cfg)
    runnable_volume = [run for run in volume_runs(cfg) if run.runnable] if vol_test else []
    vol_models = needed({method_model(run.spec.params) for run in runnable_volume})
    volume_rows = len({run.spec.id for run in runnable_volume})
    volume_robustness_rows = len({run.spec.id for run in volume_robustness_runs(cfg)}) if vol_test else 0
    volumes = {**renders(vol, vol), "denoise_volume_row": volume_rows, "evaluate_volume_row": volume_rows,
               "train_denoiser": vol_models, "robustness_volume_row": volume_robustness_rows}
    # Models with data.scenes volumes train on the vol_train_* clips (their renders join the `train` target's).
    vol_train = sum(volume_training_split(cfg), []) if any(trains_on_volumes(m) for m in model_specs(cfg)) else []
    jobs = {
        "scenes": {"generate_scene": len(scenes)},
        # `verify` retrains the stored models (the copy of the workflow has no store/): nothing to plan.
        "verify": {},
        "volumes": volumes,
        "stability": stability,
        "renders": renders(scenes, scenes),
        "train": {**renders(trained := (train_scenes if all_models else []) + vol_train, trained),
                  "train_denoiser": all_models},
        "denoise": {**renders(test_scenes + used_inputs, used_inputs), "denoise_row": evaluated,
                    "train_denoiser": used_models, "tune_method": tuned},
        "evaluate": {**renders(test_scenes + used_inputs, test_scenes + used_inputs), **evaluation,
                     "train_denoiser": used_models, "tune_method": tuned},
        # `baselines`: the rows without a trained model, denoised and scored; no training job. The copy has no
        # store, so the tuned rows' tuning jobs (and the training renders they read) are planned.
        "baselines": {**renders(test_scenes + baseline_inputs, test_scenes + baseline_inputs),
                      "denoise_row": baseline_jobs, "evaluate_row": baseline_jobs, "tune_method": baseline_tuned},
        "report": {**renders(test_scenes + training_inputs, test_scenes + training_inputs), **evaluation, **speed,
                   "build_report": 1, "train_denoiser": all_models, "tune_method": tuned},
        "all": {**renders(scenes, scenes), **evaluation, **speed, "build_report": 1, "train_denoiser": all_models,
                "tune_method": tuned},
    }[target]
    if target in ("all", "report"):
        # The stability jobs share the scenes, renders, models and tuning jobs with the rest of the DAG.
        base = scenes if target == "all" else test_scenes + training_inputs
        evaluated_tuned = {run.spec.method for run in plan_runs(cfg) if run.runnable and run.spec.params.get("tuned")}
        jobs = {**{rule: jobs.get(rule, 0) + stability.get(rule, 0) for rule in {**jobs, **stability}},
                **renders(list({*base, *stab_clips, *stab_train}), list({*base, *stab_clips, *stab_train})),
                "train_denoiser": max(jobs.get("train_denoiser", 0), stab_models),
                "tune_method": len(evaluated_tuned | stab_tuned)}
        # The volume jobs: their own scenes; their models (if any) are among every configured model already.
        jobs = {rule: jobs.get(rule, 0) + volumes.get(rule, 0) for rule in {**jobs, **volumes}}
        jobs["train_denoiser"] = all_models
    return {rule: count for rule, count in {**jobs, target: 1}.items() if count}


@pytest.mark.slow
def test_lint_is_clean(workflow_copy: Path) -> None:
    result = run_snakemake("--lint", cwd=workflow_copy)
    assert "Lints for" not in result.stdout + result.stderr


@pytest.mark.slow
def test_cluster_config_passes_dry_run_and_lint(workflow_copy: Path) -> None:
    """config/cluster.yaml (issue 11 §5: larger budgets for a SLURM cluster) builds its whole DAG and lints clean."""
    cluster = load_config(workflow_copy / "config/cluster.yaml")
    result = run_snakemake("-n", "--forceall", "--configfile", "config/cluster.yaml", cwd=workflow_copy, timeout=900)
    assert job_counts(result.stdout + result.stderr) == expected_jobs(cluster)
    assert_documented("config/cluster.yaml", job_counts(result.stdout + result.stderr))
    lint = run_snakemake("--lint", "--configfile", "config/cluster.yaml", cwd=workflow_copy, timeout=900)
    assert "Lints for" not in lint.stdout + lint.stderr
    # Larger than the default config on every axis that costs compute.
    default = load_config(workflow_copy / "config/config.yaml")
    assert cluster["output_dir"] != default["output_dir"]
    for section, key in (("scenes", "n_train"), ("scenes", "n_test"), ("scenes", "frames"), ("render", "width"),
                         ("render", "reference_spp"), ("training", "validation_scenes")):
        assert cluster[section][key] > default[section][key], (section, key)
    steps = {m["id"]: m["budget"]["max_steps"] for m in cluster["training"]["models"]}
    assert all(steps[m["id"]] > m["budget"]["max_steps"] for m in default["training"]["models"])


#: Rules that compute on compute.device (Mitsuba or torch) and so ask for a GPU under cuda.
GPU_RULES = frozenset({"generate_scene", "render_noisy", "render_reference", "derive_masks", "train_denoiser",
                       "verify_stored_model", "denoise_row", "robustness_row", "denoise_scenario_row",
                       "denoise_volume_row", "robustness_volume_row", "time_methods"})


@pytest.mark.slow
def test_gpu_cluster_overlay_asks_for_a_gpu_where_the_device_computes(workflow_copy: Path) -> None:
    """config/overlays/cluster-gpu.yaml over config/cluster.yaml (issue 50 §2): the same DAG, planned here without a
    GPU (compute.device cuda is taken as configured), every job of a rule that computes on the device asks for one
    GPU and every other job for none."""
    result = run_snakemake("-n", "--forceall", "--configfile", "config/cluster.yaml",
                           "config/overlays/cluster-gpu.yaml", cwd=workflow_copy, timeout=900)
    text = result.stdout + result.stderr
    assert result.returncode == 0, text[-3000:]
    cluster = load_config(workflow_copy / "config/cluster.yaml")
    assert job_counts(text) == expected_jobs(cluster)
    asks: dict[str, set[bool]] = {}
    for rule, body in re.findall(r"^rule (\w+):\n(.*?)(?=^\S|\Z)", text, flags=re.M | re.S):
        resources = re.search(r"resources: (.*)", body)
        if resources:
            asks.setdefault(rule, set()).add("gpu=1" in resources.group(1))
    assert asks and all(asks[rule] == {rule in GPU_RULES} for rule in asks), asks
    assert GPU_RULES & set(asks) >= {"render_noisy", "train_denoiser", "denoise_row"}, sorted(asks)


@pytest.mark.slow
def test_isik2021_config_passes_dry_run_and_lint(workflow_copy: Path) -> None:
    """config/isik2021.yaml (issue 13: every AFN variant of Tables 2-5 and KPCN, a long run) builds its whole DAG
    with the jobs its config implies, lints clean, and trains every AFN variant and KPCN."""
    from denoisers.training.models import training_problems
    from denoisers.training.schedules import lr_factor

    isik = load_config(workflow_copy / "config/isik2021.yaml")
    assert training_problems(isik) == []
    methods = {spec.method for spec in model_specs(isik)}
    assert {"afn", "kpcn"} <= methods, methods
    # The paper's 128 crops, here whole frames: on smaller crops AFN runs learned the crop borders
    # (docs/findings.md, "AFN: 64-pixel training crops and whole frames").
    frame = min(isik["render"]["width"], isik["render"]["height"])
    assert all(spec.data["crop"] >= frame for spec in model_specs(isik)), [s.data["crop"] for s in model_specs(isik)]
    # The learning rate is constant over the convergence window (the last window_fraction of the steps) and half
    # a window before it, so the under-trained check compares validations at the final rate and does not count
    # a drop's one-off gain (docs/findings.md, "AFN and KPCN: the paper's learning rate at our budget").
    window = {"window_fraction": 0.2, **isik["training"].get("convergence", {})}["window_fraction"]
    for spec in model_specs(isik):
        steps = spec.budget["max_steps"]
        settled = range(int(steps * (1 - 1.5 * window)), steps)
        factors = {lr_factor(spec.optimizer["schedule"], step) for step in settled}
        assert len(factors) == 1, (spec.id, spec.optimizer["schedule"], sorted(factors))
    result = run_snakemake("-n", "--forceall", "--configfile", "config/isik2021.yaml", cwd=workflow_copy, timeout=900)
    assert job_counts(result.stdout + result.stderr) == expected_jobs(isik)
    lint = run_snakemake("--lint", "--configfile", "config/isik2021.yaml", cwd=workflow_copy, timeout=900)
    assert "Lints for" not in lint.stdout + lint.stderr


@pytest.mark.slow
def test_smoke_dry_run_has_the_expected_jobs(workflow_copy: Path) -> None:
    # --forceall: list every job even if outputs exist.
    counts = dry_run("--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    assert counts == expected_jobs(load_config(workflow_copy / "config/smoke.yaml"))
    # A dry run writes nothing below the experiment folder, not even the resolved config (.config/<digest>.yaml).
    assert not (workflow_copy / SMOKE_OUT).exists()
    assert set(counts) == {*JOB_RULES, "all"} - {"verify_stored_model"}      # `verify` is not part of `all`


@pytest.mark.slow
def assert_documented(config: str, counts: dict[str, int]) -> None:
    """The manual's generated job counts of ``config`` (dag-jobs blocks, denoisers.dag_counts) equal this dry run's."""
    from denoisers.dag_counts import BLOCK, dag_block

    pages = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
    blocks = [m["body"] for page in pages for m in BLOCK.finditer(page.read_text()) if m["config"] == config]
    assert blocks, f"no dag-jobs block of {config} in README.md or docs/"
    assert all(body == dag_block(config, counts) for body in blocks), (
        f"the manual's job counts of {config} are out of date: run `python -m denoisers job-counts`")


def test_default_dry_run_has_the_expected_jobs(workflow_copy: Path) -> None:
    counts = dry_run("--forceall", cwd=workflow_copy)
    assert counts == expected_jobs(load_config(workflow_copy / "config/config.yaml"))
    assert set(counts) == {*JOB_RULES, "all"} - {"verify_stored_model"}      # `verify` is not part of `all`
    assert_documented("config/config.yaml", counts)


@pytest.mark.slow
def test_runs_needing_more_sample_layers_than_rendered_are_left_out(workflow_copy: Path) -> None:
    cfg = yaml.safe_load((workflow_copy / "config/smoke.yaml").read_text())
    cfg["scenes"]["n_test"] = 2
    cfg["render"].update(spp=4, extra_radiance_spp=0)
    # Without extra layers the NTASD models (8 radiance layers) cannot train; only the RAE's models stay.
    cfg["training"]["models"] = [m for m in cfg["training"]["models"] if m["method"] in ("rae", "rae_color")]
    # ablation_spp []: only the rows below (the ablation rows: test_ablation_variants_are_evaluated_...).
    cfg["evaluation"].update(spp=[1, 2, 4], ablation_spp=[], methods=[
        {"id": "noisy", "method": "noisy"},
        {"id": "path_x2", "method": "path_tracing", "params": {"factor": 2}},
        {"id": "path_x4", "method": "path_tracing", "params": {"factor": 4}},
    ])
    cfg["stability"]["rows"] = None    # the smoke config's stability rows are not among these
    cfg["evaluation"]["robustness"].update(enabled=True, spp=2)
    (workflow_copy / "layers.yaml").write_text(yaml.safe_dump(cfg))
    counts = dry_run("--forceall", "--configfile", "layers.yaml", cwd=workflow_copy)
    # Hand count with 4 rendered layers: noisy runs at 1, 2, 4 spp; path_x2 needs 2, 4, 8 layers (runs
    # at 1, 2); path_x4 needs 4, 8, 16 (runs at 1): 3 row jobs, 6 (row, spp) pairs x 2 evaluated (test) scenes
    # as their clips. Robustness at 2 spp: noisy and path_x2 (4 layers), not path_x4 (8 layers): 2 row jobs.
    assert {rule: counts.get(rule) for rule in ("denoise_row", "evaluate_row", "robustness_row")} == {
        "denoise_row": 3, "evaluate_row": 3, "robustness_row": 2}
    layers = load_config(workflow_copy / "layers.yaml")
    assert counts == expected_jobs(layers)
    scenes = ["test_000", "test_001"]
    assert {row: row_clips(layers, row) for row in ("noisy", "path_x2", "path_x4")} == {
        "noisy": [(scene, spp) for spp in (1, 2, 4) for scene in scenes],
        "path_x2": [(scene, spp) for spp in (1, 2) for scene in scenes], "path_x4": [(scene, 1) for scene in scenes]}
    assert row_clips(layers, "path_x2", "robustness") == [(scene, 2) for scene in scenes]
    with pytest.raises(EvaluationError, match="not in the robustness scenario"):
        row_clips(layers, "path_x4", "robustness")


def dry_run_jobs(*args: str, cwd: Path) -> list[tuple[str, dict[str, str]]]:
    """(rule, {'input': ..., 'output': ..., ...}) of every job a dry run lists."""
    result = run_snakemake("-n", *args, cwd=cwd)
    jobs: list[tuple[str, dict[str, str]]] = []
    for line in (result.stdout + result.stderr).splitlines():
        rule = re.match(r"^(?:local)?rule (\w+):$", line.strip())
        if rule:
            jobs.append((rule.group(1), {}))
        elif jobs and re.match(r"^\s+\w+: ", line):
            key, value = line.strip().split(": ", 1)
            jobs[-1][1][key] = value
    return jobs


@pytest.mark.slow
def test_ablation_variants_are_evaluated_at_ablation_spp_only(workflow_copy: Path) -> None:
    cfg = load_config(workflow_copy / "config/smoke.yaml")
    variants = [spec.id for spec in model_specs(cfg) if spec.ablation]
    ablation_spp = cfg["evaluation"]["ablation_spp"]
    assert len(variants) == 7 and ablation_spp == [1] and cfg["evaluation"]["spp"] == [1, 2, 4]   # rae_capacity: 2
    # The rows come after the configured ones, at ablation_spp only, and not in the robustness scenario.
    specs = method_specs(cfg)
    assert [spec.id for spec in specs] == [entry["id"] for entry in cfg["evaluation"]["methods"]] + variants
    assert {(run.spec.id, run.spp) for run in plan_runs(cfg) if run.spec.role == ABLATION_ROLE} == \
        {(variant, spp) for variant in variants for spp in ablation_spp}
    assert not {run.spec.id for run in robustness_runs(cfg)} & set(variants)

    jobs = dry_run_jobs("evaluate", "--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    test_scenes = evaluated_scene_ids(cfg)
    for variant in variants:
        denoise = {job["output"]: job["input"].split(", ") for rule, job in jobs if rule == "denoise_row"
                   and job["output"] == f"{SMOKE_OUT}/denoised/{variant}"}
        assert len(denoise) == 1 and f"{SMOKE_OUT}/models/{variant}" in next(iter(denoise.values()))
        assert row_clips(cfg, variant) == [(scene, spp) for spp in ablation_spp for scene in test_scenes]
        assert not [job for rule, job in jobs if rule == "robustness_row" and job["output"].endswith(f"/{variant}")]
    trained = {job["output"] for rule, job in jobs if rule == "train_denoiser"}
    assert {f"{SMOKE_OUT}/models/{variant}" for variant in variants} <= trained


@pytest.mark.slow
def test_custom_scenes_are_denoised_evaluated_and_reported(workflow_copy: Path) -> None:
    """An extra scene (the default config's, added to the smoke config) is an evaluated scene: every runnable
    (row, spp) denoises and scores it, every robustness row runs on it, and the report reads its manifest; it
    is rendered but never trained on."""
    smoke = yaml.safe_load((workflow_copy / "config/smoke.yaml").read_text())
    default = yaml.safe_load((workflow_copy / "config/config.yaml").read_text())
    extra = [dict(entry, frames=smoke["scenes"]["frames"]) for entry in default["extra_scenes"]]
    (workflow_copy / "smoke-external.yaml").write_text(yaml.safe_dump(smoke | {"extra_scenes": extra}))
    cfg = load_config(workflow_copy / "smoke-external.yaml")
    custom = [f"custom_{entry['name']}" for entry in cfg["extra_scenes"]]
    assert custom == ["custom_spheres_room"] and evaluated_scene_ids(cfg) == ["test_000", *custom]
    jobs = dry_run_jobs("report", "--forceall", "--configfile", "smoke-external.yaml", cwd=workflow_copy)
    outputs = {rule: {path for r, job in jobs if r == rule for path in job["output"].split(", ")} for rule in
               ("denoise_row", "evaluate_row", "robustness_row", "generate_scene")}
    runs = [run for run in plan_runs(cfg) if run.runnable]
    assert {f"{SMOKE_OUT}/denoised/{run.spec.id}" for run in runs} == outputs["denoise_row"]
    assert {f"{SMOKE_OUT}/metrics/{run.spec.id}" for run in runs} == outputs["evaluate_row"]
    # Every row job reads the external scene's renders and does its clips.
    custom_noisy = f"{SMOKE_OUT}/renders/{custom[0]}/noisy/chunk_000"
    assert all(custom_noisy in job["input"].split(", ") for rule, job in jobs if rule == "denoise_row")
    assert all((custom[0], run.spp) in row_clips(cfg, run.spec.id) for run in runs)
    robust = [run for run in robustness_runs(cfg) if run.runnable]
    assert robust and {f"{SMOKE_OUT}/robustness/{run.spec.id}" for run in robust} == outputs["robustness_row"]
    assert all((custom[0], run.spp) in row_clips(cfg, run.spec.id, "robustness") for run in robust)
    assert f"{SMOKE_OUT}/scenes/{custom[0]}" in outputs["generate_scene"]
    report = next(job for rule, job in jobs if rule == "build_report")
    assert f"{SMOKE_OUT}/scenes/{custom[0]}" in report["input"].split(", ")
    training = [job for rule, job in jobs if rule == "train_denoiser"]
    assert training and not any(custom[0] in job["input"] for job in training)


@pytest.mark.slow
def test_row_spp_robustness_and_ablation_spp_select_the_jobs(workflow_copy: Path) -> None:
    cfg = yaml.safe_load((workflow_copy / "config/smoke.yaml").read_text())
    cfg["evaluation"].update(spp=[1, 2], ablation_spp=[2], methods=[
        {"id": "noisy", "method": "noisy"},
        {"id": "eaw", "method": "eaw", "spp": [2], "robustness": False},
        {"id": "path_x2", "method": "path_tracing", "params": {"factor": 2}, "spp": []},
    ])
    cfg["stability"]["rows"] = None    # the smoke config's stability rows are not among these
    (workflow_copy / "rows.yaml").write_text(yaml.safe_dump(cfg))
    counts = dry_run("denoise", "--forceall", "--configfile", "rows.yaml", cwd=workflow_copy)
    # Hand count on the one evaluated (test) scene: noisy at 1 and 2 spp, eaw at 2, path_x2 at none, the 7
    # ablation variants at 2: 9 row jobs (path_x2 has none) doing 10 clips, which need the 7 variant models and
    # the base model rae (no row uses it, but rae_loss_combined is its training and reuses its weights).
    assert counts["denoise_row"] == 9 and counts["train_denoiser"] == 8
    rows = load_config(workflow_copy / "rows.yaml")
    clips = {spec.id: row_clips(rows, spec.id) for spec in method_specs(rows) if spec.id != "path_x2"}
    assert sum(map(len, clips.values())) == 10 and clips["noisy"] == [("test_000", 1), ("test_000", 2)]
    with pytest.raises(EvaluationError, match="not evaluated at any spp"):
        row_clips(rows, "path_x2")
    counts = dry_run("evaluate", "--forceall", "--configfile", "rows.yaml", cwd=workflow_copy)
    # Robustness: noisy and path_x2 (its evaluated spp do not matter), not eaw or the variants.
    assert {rule: counts[rule] for rule in ("denoise_row", "evaluate_row", "robustness_row")} == {
        "denoise_row": 9, "evaluate_row": 9, "robustness_row": 2}
    assert counts == expected_jobs(rows, "evaluate")

    cfg["evaluation"]["ablation_spp"] = []
    (workflow_copy / "no_ablation.yaml").write_text(yaml.safe_dump(cfg))
    counts = dry_run("denoise", "--forceall", "--configfile", "no_ablation.yaml", cwd=workflow_copy)
    assert counts["denoise_row"] == 2 and "train_denoiser" not in counts


#: Which clips each row rule's job does (denoisers.jobs.rows.CLIP_KINDS).
ROW_RULE_KINDS = {"denoise_row": "evaluation", "evaluate_row": "evaluation", "robustness_row": "robustness",
                  "denoise_scenario_row": "stability", "score_scenario_row": "stability",
                  "denoise_volume_row": "volumes", "evaluate_volume_row": "volumes",
                  "robustness_volume_row": "volume_robustness"}


@pytest.mark.slow
def test_row_jobs_wall_time_counts_their_own_clips(workflow_copy: Path) -> None:
    """A row job's wall-time limit (SLURM) is 10 minutes plus one per clip it does (row_clips of its kind): the
    spike scenario's rows count their spike clips, not the row's evaluated clips."""
    cfg = load_config(workflow_copy / "config/smoke.yaml")
    jobs = dry_run_jobs("all", "--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    seen = set()
    for rule, job in jobs:
        if rule not in ROW_RULE_KINDS:
            continue
        row = job["wildcards"].removeprefix("method=")
        resources = dict(item.split("=", 1) for item in job["resources"].split(", "))
        assert int(resources["runtime"]) == 10 + len(row_clips(cfg, row, ROW_RULE_KINDS[rule])), (rule, row)
        seen.add(rule)
    assert seen == set(ROW_RULE_KINDS) == set(ROW_RULES)


@pytest.mark.slow
def test_timing_target_runs_one_training_speed_job(workflow_copy: Path) -> None:
    """Stage target `timing`: the timing job and one time_training job writing <out>/timing/training.json with
    the training threads; with training.speed.enabled false the report neither runs nor needs it."""
    result = run_snakemake("-n", "-p", "timing", "--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    output = result.stdout + result.stderr
    counts = job_counts(output)
    assert counts["time_training"] == 1 and counts["time_methods"] == 1 and "build_report" not in counts
    assert f"output: {SMOKE_OUT}/timing/training.json" in output
    commands = [line for line in result.stdout.splitlines() if "python -m denoisers time-training" in line]
    threads = load_config(workflow_copy / "config/smoke.yaml")["training"]["threads"]
    assert len(commands) == 1 and f"--threads {threads} " in commands[0]
    cfg = yaml.safe_load((workflow_copy / "config/smoke.yaml").read_text())
    cfg["training"]["speed"]["enabled"] = False
    (workflow_copy / "no_speed.yaml").write_text(yaml.safe_dump(cfg))
    counts = dry_run("report", "--forceall", "--configfile", "no_speed.yaml", cwd=workflow_copy)
    assert "time_training" not in counts and counts == expected_jobs(load_config(workflow_copy / "no_speed.yaml"),
                                                                     "report")


def failing_dry_run(workflow_copy: Path, tmp_path: Path, cfg: dict) -> str:
    """Dry-run the workflow with ``cfg`` written to a file; assert it fails and return its output."""
    bad_config = tmp_path / "bad_config.yaml"
    bad_config.write_text(yaml.safe_dump(cfg))
    result = run_snakemake("-n", "--configfile", str(bad_config), cwd=workflow_copy, check=False)
    assert result.returncode != 0
    assert not (workflow_copy / cfg["output_dir"]).exists(), "a failed config check wrote into the output folder"
    return result.stdout + result.stderr


def test_problems_of_several_config_sections_come_in_one_message(workflow_copy: Path, tmp_path: Path) -> None:
    """A cross-key problem (scenes.objects min above max), a misspelt row method (evaluation) and a tuning entry for an
    unknown method (tuning): one failed dry run names all three (the section checks used to wait until the cross-key
    checks passed)."""
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    index = next(i for i, entry in enumerate(cfg["evaluation"]["methods"]) if entry["method"] == "svgf")
    cfg["evaluation"]["methods"][index]["method"] = "svfg"
    cfg.setdefault("tuning", {})["methods"] = [{"method": "eawx", "grid": {"sigma_color": [1.0]}}]
    cfg["scenes"]["objects"] = [5, 2]
    output = failing_dry_run(workflow_copy, tmp_path, cfg)
    assert "scenes.objects" in output
    assert "did you mean 'svgf'?" in output
    assert "config key 'tuning.methods': unknown method 'eawx'" in output


def test_ablation_spp_outside_the_evaluated_spp_fails_the_dry_run(workflow_copy: Path, tmp_path: Path) -> None:
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    cfg["evaluation"]["ablation_spp"] = [8]  # smoke evaluates [1, 2, 4]
    cfg["evaluation"]["methods"][2]["spp"] = [2, 3]
    output = failing_dry_run(workflow_copy, tmp_path, cfg)
    assert "evaluation.ablation_spp" in output and "[8]" in output
    assert "evaluation.methods[2].spp" in output and "[3]" in output


@pytest.mark.slow
@pytest.mark.parametrize("target", STAGE_TARGETS)
def test_stage_targets_select_their_jobs(workflow_copy: Path, target: str) -> None:
    counts = dry_run(target, "--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    assert counts == expected_jobs(load_config(workflow_copy / "config/smoke.yaml"), target)


@pytest.mark.slow
def test_dry_run_passes_the_resolved_config_to_the_cli(workflow_copy: Path) -> None:
    result = run_snakemake("-n", "-p", "--forceall", "--configfile", "config/smoke.yaml", cwd=workflow_copy)
    cfg = load_config(workflow_copy / "config/smoke.yaml")
    jobs = expected_jobs(cfg)
    lines = result.stdout.splitlines()
    scenegen = [line for line in lines if "python -m scenegen" in line]
    denoisers = [line for line in lines if "python -m denoisers" in line]
    assert len(scenegen) == (jobs["generate_scene"] + jobs["render_noisy"] + jobs["render_reference"]
                             + jobs["derive_masks"])
    assert len(denoisers) == sum(jobs.get(rule, 0) for rule in JOB_RULES[3:] if rule != "derive_masks")
    scenario = [line for line in denoisers if "python -m denoisers denoise-row --kind stability " in line]
    assert len(scenario) == jobs["denoise_scenario_row"]
    config_files = {re.search(r"--config (\S+)", command).group(1) for command in scenegen + denoisers}
    assert len(config_files) == 1
    # A dry run does not write the resolved config; its name is the digest of the validated config with its
    # compute.device resolved (denoisers.device: auto -> cpu or cuda, where the DAG is planned).
    resolved_path = workflow_copy / config_files.pop()
    assert not resolved_path.exists()
    assert resolved_path.name == f"{config_digest(resolve_config_device(cfg))[:16]}.yaml"
    assert any("render-noisy" in command and "--chunk 1 " in command for command in scenegen)

    volume = [line for line in denoisers if "python -m denoisers denoise-row --kind volumes " in line]
    assert len(volume) == jobs["denoise_volume_row"]
    assert all(re.search(r"--out \S+/volumes/denoised/[a-z0-9_]+ ", command) for command in volume)
    denoise = [line for line in denoisers if "python -m denoisers denoise-row " in line and "--kind" not in line]
    planned = {run.spec.id for run in plan_runs(cfg) if run.runnable}
    ran = {re.search(r"--method-id (\S+)", c).group(1) for c in denoise}
    assert ran == planned and len(denoise) == len(planned)
    assert all(f"--threads {cfg['evaluation']['threads']} " in command for command in denoise)
    # The row jobs denoise the evaluated scenes of the config (denoisers.jobs.rows.row_clips), never a training scene.
    assert all(not scene.startswith("train_") for row in planned for scene, _ in row_clips(cfg, row)), \
        "a training scene is evaluated"


def test_invalid_config_fails_the_dry_run_naming_the_key(workflow_copy: Path, tmp_path: Path) -> None:
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    cfg["render"]["varient"] = cfg["render"].pop("variant")
    cfg["scenes"]["camera_paths"] = ["orbit", "crane"]
    output = failing_dry_run(workflow_copy, tmp_path, cfg)
    assert "render.varient" in output and "did you mean 'variant'" in output
    assert "scenes.camera_paths[1]" in output and "dolly, orbit, pan, spline" in output


def test_evaluated_spp_above_the_rendered_layers_fails_the_dry_run(workflow_copy: Path, tmp_path: Path) -> None:
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    cfg["evaluation"]["spp"] = [1, 2, 16]  # smoke renders 4 layers (8 of radiance)
    output = failing_dry_run(workflow_copy, tmp_path, cfg)
    assert "evaluation.spp" in output and "[16]" in output


STUB_CLI = """\
\"\"\"Stand-in for the real CLI: validates the resolved config and creates the output directory.\"\"\"
import argparse
import pathlib

from scenegen.config import load_config

parser = argparse.ArgumentParser()
parser.add_argument("command", choices=["generate", "render-noisy", "render-reference"])
for option in ("--config", "--scene", "--scene-dir", "--out"):
    parser.add_argument(option)
parser.add_argument("--chunk", type=int)
parser.add_argument("--threads", type=int)
args = parser.parse_args()
load_config(args.config)
out = pathlib.Path(args.out)
out.mkdir(parents=True)
(out / "stub.txt").write_text(f"{args.command} {args.scene} {args.chunk}\\n")
"""
# The stub package shadows the real `scenegen` in the workflow copy (Snakemake and `python -m` put the
# working directory first on sys.path): its __main__ replaces the CLI, every other module (the
# Snakefile imports scenegen.config and, through denoisers, scenegen.atomic) comes from the real package.
STUB_INIT = f"__path__.append({str(REPO_ROOT / 'scenegen')!r})\n"


@pytest.fixture
def stub_workflow(tmp_path: Path) -> Path:
    """A copy of the workflow whose `python -m scenegen` is a fast stub, with the `renders` target of the
    smoke config run once (a stub render cannot be denoised, so the evaluation stage is left out)."""
    copy_workflow(tmp_path)
    package = tmp_path / "scenegen"
    package.mkdir()
    (package / "__init__.py").write_text(STUB_INIT)
    (package / "__main__.py").write_text(STUB_CLI)
    run_snakemake("renders", "--cores", "2", "--configfile", "config/smoke.yaml", cwd=tmp_path)
    return tmp_path


def smoke_variant(workdir: Path, section: str, key: str, value: object) -> str:
    cfg = yaml.safe_load((workdir / "config/smoke.yaml").read_text())
    cfg[section][key] = value
    if section == "render" and key == "spp":    # tuning.spp must stay within the rendered layers
        cfg["tuning"]["spp"] = [s for s in cfg["tuning"]["spp"] if s <= value]
    path = workdir / f"{section}_{key}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path.name


@pytest.mark.slow
def test_config_changes_rerun_only_the_affected_jobs(stub_workflow: Path) -> None:
    work = stub_workflow
    assert (work / SMOKE_OUT / "renders/test_000/reference/chunk_001/stub.txt").is_file()
    assert dry_run("renders", "--configfile", "config/smoke.yaml", cwd=work) == {}

    # The smoke config: 3 procedural scenes, 2 chunks each.
    # (8, not fewer: the NTASD models train on render.spp + extra_radiance_spp = 8 radiance layers)
    noisy_only = dry_run("renders", "--configfile", smoke_variant(work, "render", "spp", 8), cwd=work)
    assert noisy_only == {"render_noisy": 6, "renders": 1}

    reference_only = dry_run("renders", "--configfile", smoke_variant(work, "render", "reference_spp", 32), cwd=work)
    assert reference_only == {"render_reference": 6, "renders": 1}
    # render.train_reference_spp: only the references of the scene that trains (train_000; train_001 validates
    # and keeps reference_spp); null or the reference_spp itself: nothing.
    train_only = dry_run("renders", "--configfile", smoke_variant(work, "render", "train_reference_spp", 16), cwd=work)
    assert train_only == {"render_reference": 2, "renders": 1}
    for same in (None, 64):
        assert dry_run("renders", "--configfile", smoke_variant(work, "render", "train_reference_spp", same),
                       cwd=work) == {}

    one_more_scene = dry_run("renders", "--configfile", smoke_variant(work, "scenes", "n_train", 3), cwd=work)
    assert one_more_scene == {"generate_scene": 1, "render_noisy": 2, "render_reference": 2, "renders": 1}

    # Every procedural scene; adding an external scene renders only it.
    everything = dry_run("renders", "--configfile", smoke_variant(work, "scenes", "objects", [3, 7]), cwd=work)
    assert everything == {"generate_scene": 3, "render_noisy": 6, "render_reference": 6, "renders": 1}
    custom = yaml.safe_load((work / "config/smoke.yaml").read_text())
    custom["extra_scenes"] = [{"name": "spheres_room", "xml": "examples/scenes/spheres_room/scene.xml", "frames": 4,
                               "camera": {"path": "dolly"}, "max_depth": 3}]
    (work / "custom_depth.yaml").write_text(yaml.safe_dump(custom))
    assert dry_run("renders", "--configfile", "custom_depth.yaml", cwd=work) == {
        "generate_scene": 1, "render_noisy": 2, "render_reference": 2, "renders": 1}


STUB_TRAIN_CLI = """\
\"\"\"Stand-in for `python -m denoisers train`: validates the resolved config and creates the model directory.\"\"\"
import argparse
import pathlib

from scenegen.config import load_config

parser = argparse.ArgumentParser()
parser.add_argument("command", choices=["train"])
for option in ("--config", "--model-id", "--render-root", "--out", "--threads"):
    parser.add_argument(option)
args = parser.parse_args()
load_config(args.config)
out = pathlib.Path(args.out)
out.mkdir(parents=True)
(out / "stub.txt").write_text(args.model_id + "\\n")
"""
STUB_DENOISERS_INIT = f"__path__.append({str(REPO_ROOT / 'denoisers')!r})\n"


@pytest.mark.slow
def test_training_reruns_only_when_its_settings_or_data_change(stub_workflow: Path) -> None:
    work = stub_workflow
    package = work / "denoisers"
    package.mkdir()
    (package / "__init__.py").write_text(STUB_DENOISERS_INIT)
    (package / "__main__.py").write_text(STUB_TRAIN_CLI)
    run_snakemake("train", "--cores", "2", "--configfile", "config/smoke.yaml", cwd=work)
    assert (work / SMOKE_OUT / "models/rae_loss_spatial/stub.txt").is_file()
    assert dry_run("train", "--configfile", "config/smoke.yaml", cwd=work) == {}

    def variant(name: str, change) -> str:
        cfg = yaml.safe_load((work / "config/smoke.yaml").read_text())
        change(cfg)
        (work / name).write_text(yaml.safe_dump(cfg))
        return name

    # An ablation's budget: only its variants. The base model's network: the base and every variant that does
    # not set the changed key itself (the capacity size width0125 keeps its own width: 8 models - 1).
    ablation = dry_run("train", "--configfile", variant("a.yaml", lambda c: c["training"]["ablations"][0].update(
        budget={"max_steps": 3})), cwd=work)
    assert ablation == {"train_denoiser": 3, "train": 1}
    base = dry_run("train", "--configfile", variant("b.yaml", lambda c: c["training"]["models"][0]["net"].update(
        width=0.5)), cwd=work)
    assert base == {"train_denoiser": 7, "train": 1}
    # Evaluation settings do not touch the models; the training data's render settings retrain all.
    evaluation = dry_run("train", "--configfile", variant("c.yaml", lambda c: c["evaluation"].update(threads=2)),
                         cwd=work)
    assert evaluation == {}
    data = dry_run("train", "--configfile", variant("d.yaml", lambda c: c["render"].update(max_depth=6)), cwd=work)
    smoke = model_specs(load_config(work / "config/smoke.yaml"))
    surface_models = [spec.id for spec in smoke if not trains_on_volumes(spec)]
    assert len(surface_models) >= 13            # rae, 7 ablation variants, NTASD and Isik rows
    assert data["train_denoiser"] == len(surface_models)   # the surface data's settings retrain every surface model
    # The volumetric clips' settings retrain only the models that train on them (rae_volume).
    volume = dry_run("train", "--configfile", variant("e.yaml", lambda c: c["volumes"].update(reference_spp=32)),
                     cwd=work)
    assert volume["train_denoiser"] == len(smoke) - len(surface_models) == 1
    # The training thread count is a setting of every model (the weights depend on it): all retrain.
    threads = dry_run("train", "--configfile", variant("f.yaml", lambda c: c["training"].update(threads=2)), cwd=work)
    assert threads["train_denoiser"] == len(smoke)


def rule_names() -> set[str]:
    names = set()
    for rule_file in (REPO_ROOT / "workflow/rules").glob("*.smk"):
        names |= set(re.findall(r"^rule (\w+):", rule_file.read_text(), flags=re.MULTILINE))
    return names


def config_threaded_rules() -> set[str]:
    """Rules whose ``threads:`` is a config key."""
    names = set()
    for rule_file in (REPO_ROOT / "workflow/rules").glob("*.smk"):
        for rule, body in re.findall(r"^rule (\w+):(.*?)(?=^rule |\Z)", rule_file.read_text(), flags=re.M | re.S):
            if re.search(r"^\s+threads: config\[", body, flags=re.M):
                names.add(rule)
    return names


def rule_priorities() -> dict[str, int]:
    """``priority:`` of every rule that sets one."""
    found = {}
    for rule_file in (REPO_ROOT / "workflow/rules").glob("*.smk"):
        for rule, body in re.findall(r"^rule (\w+):(.*?)(?=^rule |\Z)", rule_file.read_text(), flags=re.M | re.S):
            match = re.search(r"^\s+priority: (\d+)", body, flags=re.M)
            if match:
                found[rule] = int(match.group(1))
    return found


def test_scenes_and_renders_then_trainings_come_first() -> None:
    """On two cores a 2-thread render waits until no 1-thread job runs; scenes and renders therefore outrank
    every other rule (a late render stalled the training that needed it), and trainings the short jobs."""
    priorities = rule_priorities()
    first = {"generate_scene", "render_noisy", "render_reference"}
    others = rule_names() - first - {"train_denoiser"}
    assert {priorities[rule] for rule in first} == {priorities["render_noisy"]}
    assert priorities["render_noisy"] > priorities["train_denoiser"]
    assert priorities["train_denoiser"] > max((priorities.get(rule, 0) for rule in others), default=0)


def test_training_runtime_follows_the_budget() -> None:
    from denoisers.training.models import (DEFAULT_TRAINING_RUNTIME_MIN, TRAINING_RUNTIME_MARGIN_MIN,
                                           training_runtime_minutes)

    cfg = load_config(REPO_ROOT / "config/config.yaml")
    rae = next(m for m in cfg["training"]["models"] if m["id"] == "rae")
    assert training_runtime_minutes(cfg, "rae") == -(-rae["budget"]["max_seconds"] * 11 // 600) + TRAINING_RUNTIME_MARGIN_MIN
    rae["budget"]["max_seconds"] = None
    assert training_runtime_minutes(cfg, "rae") == DEFAULT_TRAINING_RUNTIME_MIN


#: The evaluation's rules, one job per row (denoisers.jobs.rows): their wall-time limit grows with the row's clips
#: and the attempt (the rules set it).
ROW_RULES = ("denoise_row", "evaluate_row", "robustness_row", "denoise_scenario_row", "score_scenario_row",
             "denoise_volume_row", "evaluate_volume_row", "robustness_volume_row")


def test_slurm_profile_sets_resources_for_every_rule() -> None:
    profile = yaml.safe_load((REPO_ROOT / "workflow/profiles/slurm/config.yaml").read_text())
    assert profile["executor"] == "slurm"
    assert {"slurm_partition", "slurm_account"} <= set(profile["default-resources"])
    assert set(profile["set-resources"]) == rule_names() == set(JOB_RULES)
    config_threads = config_threaded_rules()
    assert config_threads == {"denoise_row", "denoise_scenario_row", "denoise_volume_row", "robustness_row",
                              "robustness_volume_row", "train_denoiser", "tune_method", "verify_stored_model"}
    for rule, resources in profile["set-resources"].items():
        assert "mem_mb" in resources, rule
        # train_denoiser's (and verify_stored_model's) runtime comes from the model's budget (the rule), a row job's
        # from its clip count (the rule), every other rule's from here.
        assert ("runtime" in resources) == (rule not in ("train_denoiser", "verify_stored_model", *ROW_RULES)), rule
        # Rules threaded by a config key get as many CPUs as their threads (the executor's fallback);
        # a fixed cpus_per_task would oversubscribe them when a config raises the key.
        assert ("cpus_per_task" in resources) == (rule not in config_threads), rule
        assert rule not in profile.get("set-threads", {}) or rule not in config_threads, rule
    # A job never gets more threads than the CPUs SLURM allocates to it.
    for rule, threads in profile.get("set-threads", {}).items():
        assert rule in rule_names() and threads <= profile["set-resources"][rule]["cpus_per_task"], rule
    # Issue 50 §2: a retry gets more memory and time; failures do not stop the run; the short per-clip jobs go in
    # batches (the evaluated scenes' clips are batched per row by the rules themselves); the timing jobs have their
    # node to themselves.
    assert profile["keep-going"] is True and profile["retries"] >= 1
    for rule, resources in profile["set-resources"].items():
        for key in ("mem_mb", "runtime"):
            assert key not in resources or "* attempt" in str(resources[key]), (rule, key)
    # No group jobs: every evaluation rule is one job per row already.
    assert "groups" not in profile and "group-components" not in profile
    assert set(ROW_RULES) <= rule_names()
    assert all("--exclusive" in profile["set-resources"][rule]["slurm_extra"] for rule in ("time_methods",
                                                                                          "time_training"))


def test_local_profile_runs_on_two_cores() -> None:
    profile = yaml.safe_load((REPO_ROOT / "workflow/profiles/local/config.yaml").read_text())
    assert profile["cores"] == 2 and profile["keep-going"] is True and profile["rerun-incomplete"] is True


def test_local_profile_finishes_independent_jobs_after_a_failure_and_exits_nonzero(tmp_path: Path) -> None:
    # A toy workflow: `broken` fails at once, `slow` (independent of it) starts beside it and ends later,
    # `downstream` needs both. The long run must keep `slow`'s output and must not build `downstream`.
    (tmp_path / "Snakefile").write_text(
        'rule all:\n    input: "downstream.txt"\n'
        'rule broken:\n    output: "broken.txt"\n    shell: "exit 3"\n'
        'rule slow:\n    output: "slow.txt"\n    shell: "sleep 2 && echo ok > {output}"\n'
        'rule after_slow:\n    input: "slow.txt"\n    output: "after_slow.txt"\n    shell: "cp {input} {output}"\n'
        'rule downstream:\n    input: "broken.txt", "after_slow.txt"\n    output: "downstream.txt"\n'
        '    shell: "cat {input} > {output}"\n'
    )
    result = run_snakemake("--profile", str(REPO_ROOT / "workflow/profiles/local"), cwd=tmp_path, check=False)
    assert result.returncode != 0, result.stderr
    assert (tmp_path / "after_slow.txt").read_text() == "ok\n"
    assert not (tmp_path / "broken.txt").exists() and not (tmp_path / "downstream.txt").exists()


def test_conda_env_mirrors_the_project_dependencies() -> None:
    env = yaml.safe_load((REPO_ROOT / "workflow/envs/harness.yaml").read_text())
    pip_section = next(item["pip"] for item in env["dependencies"] if isinstance(item, dict))
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    assert sorted(pip_section) == sorted(project["dependencies"])


def test_an_unknown_method_name_fails_the_dry_run_naming_the_row(workflow_copy: Path, tmp_path: Path) -> None:
    """A misspelt method of a row is named with its config key, its row and the closest registered name."""
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    index = next(i for i, entry in enumerate(cfg["evaluation"]["methods"]) if entry["method"] == "svgf")
    cfg["evaluation"]["methods"][index]["method"] = "svfg"
    output = failing_dry_run(workflow_copy, tmp_path, cfg)
    assert f"config key 'evaluation.methods[{index}].method' (row 'svgf') = 'svfg'" in output
    assert "did you mean 'svgf'?" in output
