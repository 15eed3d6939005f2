"""One folder per experiment (config key output_dir), settings digests that refuse mixing, the clean command,
and targets that cannot exist for a config rejected while the DAG is built.

Snakemake runs happen in temporary copies of the workflow (tests/test_workflow.py's helpers); the clean tests
build small experiment folders under tmp_path. Nothing here touches the repository's results/.
"""
from __future__ import annotations

import copy
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from denoisers import evaluate
from denoisers.jobs import denoise, scoring
from denoisers.clean import CleanError, clean_experiment
from denoisers.experiment import DIGEST_KEY, Lineage, SettingsMismatchError
from denoisers.report.collect import collect
from denoisers.training.job import train_model, work_dir_for
from denoisers.training.models import model_spec
from scenegen.catalog import scene_ids
from scenegen.config import ConfigError, OUTPUT_ENTRIES, load_config, validate_config
from tests.test_evaluate import write_synthetic_scene
from tests.test_evaluate import smoke_config as evaluation_config
from tests.test_report import report_config, write_results
from tests.test_training_job import synthetic_renders, tiny_training_config  # noqa: F401 (fixture)
from tests.test_workflow import REPO_ROOT, copy_workflow, dry_run, run_snakemake, stub_workflow  # noqa: F401

SMOKE = "config/smoke.yaml"


def smoke_with(**changes) -> dict:
    """The smoke config with top-level keys replaced, validated (defaults filled)."""
    cfg = yaml.safe_load((REPO_ROOT / SMOKE).read_text())
    cfg.update(copy.deepcopy(changes))
    return validate_config(cfg)


# ------------------------------------------------------------------------------------------ output_dir
def test_shipped_configs_have_separate_folders() -> None:
    default, smoke = load_config(REPO_ROOT / "config/config.yaml"), load_config(REPO_ROOT / SMOKE)
    assert default["output_dir"] == "results" and smoke["output_dir"] == "results/smoke"
    gitignored = (REPO_ROOT / ".gitignore").read_text().splitlines()
    assert "results/" in gitignored   # covers both


@pytest.mark.parametrize("value, fragment", [(".", "a folder of its own"), ("..", "no '..'"),
                                             ("results/../x", "no '..'"), ("/", "a folder of its own"),
                                             ("results/metrics", "component 'metrics'"),
                                             ("exp/.config", "component '.config'")])
def test_output_dirs_that_would_mix_or_escape_are_rejected(value: str, fragment: str) -> None:
    with pytest.raises(ConfigError, match="output_dir") as error:
        smoke_with(output_dir=value)
    assert fragment in str(error.value)


def test_rule_files_write_nothing_outside_the_output_dir() -> None:
    """No rule file or the Snakefile spells a results path: every path goes through results_path / OUT."""
    for path in [REPO_ROOT / "Snakefile", *sorted((REPO_ROOT / "workflow/rules").glob("*.smk"))]:
        code = [line.split("#", 1)[0] for line in path.read_text().splitlines()]
        offending = [line for line in code if re.search(r"[\"']results", line)]
        assert not offending, (path.name, offending)


@pytest.mark.slow
def test_two_configs_dry_runs_have_disjoint_outputs(workflow_copy: Path) -> None:
    """Every output, log and benchmark of the default and the smoke DAG lies in its config's folder, and the
    folders share no path (the smoke folder is nested in results/, but in none of the default's outputs)."""
    paths = {}
    for config, out in (("config/config.yaml", "results"), (SMOKE, "results/smoke")):
        text = run_snakemake("-n", "-p", "--forceall", "--configfile", config, cwd=workflow_copy).stdout
        # The job listing: "    output: a, b" and "    log: c" lines (the printed shell commands are not indented).
        written = {p for line in text.splitlines() if re.match(r"^\s+(output|log): ", line)
                   for p in line.split(": ", 1)[1].split(", ")}
        assert len(written) > 100 and all(p.startswith(f"{out}/") for p in written), config
        paths[out] = written
        assert f"--render-root {out}/renders " in text and f"--results {out} " in text
        assert all(p.startswith(f"{out}/") for p in re.findall(r"--(?:config|out) (\S+)", text))
    default, smoke = paths["results"], paths["results/smoke"]
    assert not default & smoke
    assert not [p for p in default if any(q.startswith(p + "/") for q in smoke)]


@pytest.fixture(scope="module")
def workflow_copy(tmp_path_factory) -> Path:
    return copy_workflow(tmp_path_factory.mktemp("workflow"))


# ---------------------------------------------------------------------------------- impossible targets
IMPOSSIBLE = [
    ("renders/test_000/noisy/chunk_005", "render_noisy", "has 2 chunk(s)"),
    ("renders/test_003/reference/chunk_000", "render_reference", "scene test_003 is not in this config"),
    ("scenes/test_007", "generate_scene", "scenes: train_000, train_001, test_000"),
    ("robustness/rae_inputs_color", "robustness_row", "not in the robustness scenario"),
    ("denoised/nope", "denoise_row", "no evaluation row nope"),
    ("metrics/nope", "evaluate_row", "no evaluation row nope"),
    ("models/nope", "train_denoiser", "no model nope"),
    ("tuning/svgf.json", "tune_method", "tuned methods: eaw, rls, wrls"),
]


@pytest.mark.slow
@pytest.mark.parametrize("target, rule, allowed", IMPOSSIBLE)
def test_impossible_targets_fail_when_the_dag_is_built(workflow_copy: Path, target: str, rule: str,
                                                       allowed: str) -> None:
    path = f"results/smoke/{target}"
    result = run_snakemake("-n", path, "--configfile", SMOKE, cwd=workflow_copy, check=False)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert f"impossible target {path} (rule {rule})" in output and allowed in output, output[-2000:]


@pytest.mark.slow
def test_possible_path_targets_still_build(workflow_copy: Path) -> None:
    counts = dry_run("results/smoke/metrics/eaw", "results/smoke/renders/test_000/noisy/chunk_001",
                     "--configfile", SMOKE, cwd=workflow_copy)
    assert counts["evaluate_row"] == 1 and counts["denoise_row"] == 1 and counts["tune_method"] == 1


# -------------------------------------------------------------------------------------------- digests
def test_lineage_digests_follow_the_settings_they_depend_on() -> None:
    cfg = smoke_with()
    row = evaluate.method_spec(cfg, "noisy")
    base = Lineage(cfg)
    # The seed changes every output; how many test scenes or which other rows exist changes none.
    seed7 = Lineage(smoke_with(seed=7))
    assert base.metrics(row, "test_000", 1) != seed7.metrics(row, "test_000", 1)
    assert base.model("rae") != seed7.model("rae") and base.tuning("eaw") != seed7.tuning("eaw")
    more = copy.deepcopy(cfg)
    more["scenes"]["n_test"] = 3
    more["evaluation"]["methods"] = more["evaluation"]["methods"][:1]
    assert Lineage(more).metrics(row, "test_000", 1) == base.metrics(row, "test_000", 1)
    # A trained model depends on its training renders, not on how many test or external scenes exist.
    more["extra_scenes"] = []
    assert Lineage(more).model("rae") == base.model("rae")
    spp = copy.deepcopy(cfg)
    spp["render"]["reference_spp"] = 32
    assert Lineage(spp).model("rae") != base.model("rae")
    # warmup_frames: the metrics, not the denoised clip; reference_spp: the metrics, not the clip.
    for section, key, value in (("evaluation", "warmup_frames", 2), ("render", "reference_spp", 32)):
        changed = copy.deepcopy(cfg)
        changed[section][key] = value
        assert Lineage(changed).denoised(row, "test_000", 1) == base.denoised(row, "test_000", 1), key
        assert Lineage(changed).metrics(row, "test_000", 1) != base.metrics(row, "test_000", 1), key
    # A tuned row's clip depends on its tuning grid; an untuned row's does not.
    grid = copy.deepcopy(cfg)
    grid["tuning"]["methods"][0]["grid"] = {"sigma_color": [4.0]}
    tuned = evaluate.method_spec(cfg, "eaw")
    assert Lineage(grid).denoised(tuned, "test_000", 1) != base.denoised(tuned, "test_000", 1)
    assert Lineage(grid).denoised(row, "test_000", 1) == base.denoised(row, "test_000", 1)


def test_denoise_and_evaluate_record_digests_and_refuse_a_clip_of_other_settings(tmp_path: Path) -> None:
    cfg = evaluation_config(methods=[{"id": "noisy", "method": "noisy"}])
    render_dir = tmp_path / "renders" / "test_000"
    write_synthetic_scene(render_dir)
    denoised = evaluate.denoised_dir(tmp_path, "noisy", "test_000", 1)
    csv = evaluate.metrics_csv(tmp_path, "noisy", "test_000", 1)
    record = denoise.denoise_clip(cfg, "noisy", "test_000", 1, render_dir, denoised)
    scoring.evaluate_clip(cfg, denoised, render_dir, csv)
    row, lineage = evaluate.method_spec(cfg, "noisy"), Lineage(cfg)
    assert record[DIGEST_KEY] == lineage.denoised(row, "test_000", 1)
    sidecar = json.loads(evaluate.metrics_sidecar(csv).read_text())
    assert sidecar == {"method_id": "noisy", "scene": "test_000", "spp": 1,
                       DIGEST_KEY: lineage.metrics(row, "test_000", 1)}
    # The clip was denoised with seed 2026; scoring it for a seed-7 config is refused, naming the file.
    seed7 = copy.deepcopy(cfg) | {"seed": 7}
    with pytest.raises(SettingsMismatchError, match=re.escape(str(denoised / evaluate.TIMING_FILE))):
        scoring.evaluate_clip(seed7, denoised, render_dir, tmp_path / "other.csv")
    assert not (tmp_path / "other.csv").exists()


def test_a_trained_model_records_its_digest(tmp_path: Path, synthetic_renders) -> None:  # noqa: F811
    cfg = tiny_training_config()
    summary = train_model(cfg, "rae", tmp_path / "renders", tmp_path / "models" / "rae", threads=1, progress=False)
    assert summary[DIGEST_KEY] == Lineage(cfg).model("rae")
    assert json.loads((tmp_path / "models" / "rae" / "summary.json").read_text())[DIGEST_KEY] == summary[DIGEST_KEY]


def _record_digests(root: Path, cfg: dict, digest_cfg: dict) -> None:
    """Give the hand-made results tree (tests/test_report.py) the digests of ``digest_cfg``."""
    lineage = Lineage(digest_cfg)
    for run in (run for run in evaluate.plan_runs(cfg) if run.runnable):
        for scene in evaluate.evaluated_scene_ids(cfg):
            csv = evaluate.metrics_csv(root, run.spec.id, scene, run.spp)
            evaluate.metrics_sidecar(csv).write_text(json.dumps({DIGEST_KEY: lineage.metrics(run.spec, scene, run.spp)}))
            timing_path = evaluate.denoised_dir(root, run.spec.id, scene, run.spp) / evaluate.TIMING_FILE
            timing = json.loads(timing_path.read_text())
            timing_path.write_text(json.dumps(timing | {DIGEST_KEY: lineage.denoised(run.spec, scene, run.spp)}))


def test_the_report_refuses_outputs_whose_digests_disagree(tmp_path: Path) -> None:
    cfg = report_config()
    write_results(tmp_path, cfg)
    unchecked = collect(cfg, tmp_path).digests       # hand-made outputs record no digest: unchecked, not refused
    assert unchecked.matched == 0 and unchecked.unrecorded and not unchecked.mismatched
    _record_digests(tmp_path, cfg, cfg)
    ledger = collect(cfg, tmp_path).digests
    clips = sum(run.runnable for run in evaluate.plan_runs(cfg)) * len(evaluate.evaluated_scene_ids(cfg))
    assert ledger.matched == 2 * clips and not ledger.mismatched   # every metrics sidecar and timing.json
    assert len(ledger.unrecorded) == len(unchecked.unrecorded) - 2 * clips   # the robustness outputs
    # One metrics file of a seed-7 run among the seed-2026 ones: refused, naming the file and both digests.
    seed7 = copy.deepcopy(cfg) | {"seed": 7}
    row = evaluate.method_spec(cfg, "svgf")
    stale = evaluate.metrics_sidecar(evaluate.metrics_csv(tmp_path, "svgf", "test_001", 2))
    stale.write_text(json.dumps({DIGEST_KEY: Lineage(seed7).metrics(row, "test_001", 2)}))
    with pytest.raises(SettingsMismatchError) as error:
        collect(cfg, tmp_path)
    message = str(error.value)
    assert str(stale) in message and "1 output(s)" in message
    assert Lineage(seed7).metrics(row, "test_001", 2) in message and Lineage(cfg).metrics(row, "test_001", 2) in message
    # A model trained for other settings is refused too.
    stale.write_text(json.dumps({DIGEST_KEY: Lineage(cfg).metrics(row, "test_001", 2)}))
    model = tmp_path / "models" / "rae"
    model.mkdir(parents=True)
    (model / "summary.json").write_text(json.dumps({DIGEST_KEY: Lineage(seed7).model("rae"), "steps": 4}))
    for name in ("curves.csv", "validation.csv"):
        (model / name).write_text("step,train_loss\n1,0.5\n")
    with pytest.raises(SettingsMismatchError, match=re.escape(str(model / "summary.json"))):
        collect(cfg, tmp_path)


# ---------------------------------------------------------------------------------------------- clean
def _experiment(root: Path, cfg: dict) -> dict[str, Path]:
    """A small experiment folder of ``cfg`` under the working directory ``root``: outputs, a current and a
    stale training work directory, an interrupted job's temporary, an unknown file and a nested experiment."""
    out = root / cfg["output_dir"]
    files = {"config": out / ".config" / "abc.yaml", "scene": out / "scenes" / "test_000" / "manifest.json",
             "report": out / "REPORT.md", "log": out / "logs" / "build_report.log",
             "current": work_dir_for(out / "models", cfg, model_spec(cfg, "rae")) / "checkpoint.pt",
             "stale": out / "models" / ".work" / "rae-0123456789ab" / "checkpoint.pt",
             "temporary": out / "renders" / "test_000" / "noisy" / ".chunk_000.tmp-4242" / "frame_0000.exr",
             "notes": out / "notes.txt", "nested": out / "smoke" / ".config" / "def.yaml"}
    for path in files.values():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x" * 1000)
    return files


def test_clean_stale_removes_only_unused_work_dirs_and_temporaries(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    cfg = smoke_with(output_dir="results")
    files = _experiment(tmp_path, cfg)
    listed = clean_experiment(cfg, stale_only=True, dry_run=True)
    assert {path for path, _ in listed} == {files["stale"].parent, files["temporary"].parent}
    assert all(path.exists() for path in files.values())
    clean_experiment(cfg, stale_only=True)
    gone = {name for name, path in files.items() if not path.exists()}
    assert gone == {"stale", "temporary"}


def test_clean_removes_the_experiment_but_not_a_nested_one_or_unknown_files(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    cfg = smoke_with(output_dir="results")
    files = _experiment(tmp_path, cfg)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "keep.txt").write_text("keep")
    (tmp_path / "results" / "figures").symlink_to(outside)          # a link is removed, never followed
    removed = clean_experiment(cfg)
    assert {path.name for path, _ in removed} <= set(OUTPUT_ENTRIES) and len(removed) == 7
    assert {name for name, path in files.items() if path.exists()} == {"notes", "nested"}
    assert (outside / "keep.txt").read_text() == "keep"
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == ["notes.txt", "smoke"]
    # The nested experiment is cleaned with its own config; its folder goes once empty.
    smoke = smoke_with(output_dir="results/smoke")
    clean_experiment(smoke)
    assert not (tmp_path / "results" / "smoke").exists()


def test_clean_refuses_folders_it_must_not_touch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    with pytest.raises(CleanError, match="is or contains"):
        clean_experiment(smoke_with(output_dir=str(tmp_path)))            # contains the working directory
    (tmp_path / "data" / "scenes").mkdir(parents=True)
    with pytest.raises(CleanError, match="no .config"):                  # no workflow run wrote it
        clean_experiment(smoke_with(output_dir=str(tmp_path / "data")))
    assert (tmp_path / "data" / "scenes").is_dir()
    assert clean_experiment(smoke_with(output_dir="never_ran")) == []


@pytest.mark.slow
def test_two_configs_run_one_after_the_other_leave_two_complete_folders(stub_workflow: Path) -> None:  # noqa: F811 (the imported fixture)
    """The stub `renders` run of the smoke config, then a seed-7 config with its own output_dir: both folders
    hold every scene and chunk, the first is untouched; `clean` of the second leaves the first intact."""
    work = stub_workflow
    smoke = load_config(work / SMOKE)
    first = work / smoke["output_dir"]
    before = {p: p.stat().st_mtime_ns for p in first.rglob("*") if p.is_file()}
    seed7 = yaml.safe_load((work / SMOKE).read_text()) | {"seed": 7, "output_dir": "results/seed7"}
    (work / "seed7.yaml").write_text(yaml.safe_dump(seed7))
    run_snakemake("renders", "--cores", "2", "--configfile", "seed7.yaml", cwd=work)
    assert {p: p.stat().st_mtime_ns for p in first.rglob("*") if p.is_file()} == before
    for folder in (first, work / "results/seed7"):
        for scene in scene_ids(smoke):
            assert (folder / "scenes" / scene).is_dir()
            for kind in ("noisy", "reference"):
                assert (folder / "renders" / scene / kind / "chunk_001" / "stub.txt").is_file(), (folder, scene)
    assert dry_run("renders", "--configfile", SMOKE, cwd=work) == {}
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    command = [sys.executable, "-m", "denoisers", "clean", "--config", "seed7.yaml"]
    listed = subprocess.run([*command, "--dry-run"], cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert listed.returncode == 0 and "would remove" in listed.stdout and (work / "results/seed7").is_dir()
    done = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert not (work / "results/seed7").exists()
    assert {p: p.stat().st_mtime_ns for p in first.rglob("*") if p.is_file()} == before
