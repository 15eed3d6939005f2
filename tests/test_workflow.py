"""Tests for the Snakemake workflow: lint, dry-run DAG shape, config errors, rerun triggers, profiles.

None of these runs the real renderer: dry runs only, plus one real run in a temporary copy of the
workflow where `python -m scenegen` is a stub that just creates the output directories.
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

from scenegen.config import chunk_count, load_config, scene_ids

REPO_ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
JOB_RULES = ("generate_scene", "render_noisy", "render_reference")
JOB_STATS_LINE = re.compile(r"^(\w+)\s+(\d+)$")


def run_snakemake(*args: str, cwd: Path = REPO_ROOT, check: bool = True) -> subprocess.CompletedProcess:
    """Run the venv's snakemake with `python` (used by the rules) resolving to this interpreter."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    result = subprocess.run(
        [str(SNAKEMAKE), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )
    if check:
        assert result.returncode == 0, f"snakemake {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}"
    return result


def job_counts(output: str) -> dict[str, int]:
    """Parse the first 'Job stats' table of a snakemake run into {rule: job count}."""
    counts: dict[str, int] = {}
    in_table = False
    for line in output.splitlines():
        if line.startswith("Job stats:"):
            if counts:
                break
            in_table = True
            continue
        match = JOB_STATS_LINE.match(line.strip())
        if in_table and match:
            if match.group(1) == "total":
                break
            counts[match.group(1)] = int(match.group(2))
    return counts


def dry_run(*args: str, cwd: Path = REPO_ROOT) -> dict[str, int]:
    result = run_snakemake("-n", *args, cwd=cwd)
    return job_counts(result.stdout + result.stderr)


def expected_counts(config_path: Path) -> dict[str, int]:
    cfg = load_config(config_path)
    chunks = sum(chunk_count(cfg, scene) for scene in scene_ids(cfg))
    return {"generate_scene": len(scene_ids(cfg)), "render_noisy": chunks, "render_reference": chunks}


def test_lint_is_clean() -> None:
    result = run_snakemake("--lint")
    assert "Lints for" not in result.stdout + result.stderr


def test_smoke_dry_run_has_the_expected_jobs() -> None:
    # --forceall: list every job even if an earlier real run already produced some outputs.
    counts = dry_run("--forceall", "--configfile", "config/smoke.yaml")
    assert counts == {"generate_scene": 2, "render_noisy": 4, "render_reference": 4, "all": 1}
    assert {rule: counts[rule] for rule in JOB_RULES} == expected_counts(REPO_ROOT / "config/smoke.yaml")


def test_default_dry_run_has_the_expected_jobs() -> None:
    counts = dry_run("--forceall")
    assert counts == {"generate_scene": 12, "render_noisy": 24, "render_reference": 24, "all": 1}
    assert {rule: counts[rule] for rule in JOB_RULES} == expected_counts(REPO_ROOT / "config/config.yaml")


def test_stage_targets_select_their_jobs() -> None:
    counts = dry_run("scenes", "--forceall", "--configfile", "config/smoke.yaml")
    assert counts == {"generate_scene": 2, "scenes": 1}
    counts = dry_run("renders", "--forceall", "--configfile", "config/smoke.yaml")
    assert counts == {"generate_scene": 2, "render_noisy": 4, "render_reference": 4, "renders": 1}


def test_dry_run_passes_the_resolved_config_to_the_cli() -> None:
    result = run_snakemake("-n", "-p", "--forceall", "--configfile", "config/smoke.yaml")
    commands = [line for line in result.stdout.splitlines() if "python -m scenegen" in line]
    assert len(commands) == 10
    config_files = {re.search(r"--config (\S+)", command).group(1) for command in commands}
    assert len(config_files) == 1
    resolved = load_config(REPO_ROOT / config_files.pop())
    assert resolved["render"]["width"] == 48 and resolved["scenes"]["n_train"] == 1
    assert any("render-noisy" in command and "--chunk 1 " in command for command in commands)


def test_invalid_config_fails_the_dry_run_naming_the_key(tmp_path: Path) -> None:
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    cfg["render"]["varient"] = cfg["render"].pop("variant")
    cfg["scenes"]["camera_paths"] = ["orbit", "crane"]
    bad_config = tmp_path / "bad.yaml"
    bad_config.write_text(yaml.safe_dump(cfg))
    result = run_snakemake("-n", "--configfile", str(bad_config), check=False)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert "render.varient" in output and "did you mean 'variant'" in output
    assert "scenes.camera_paths[1]" in output and "dolly, orbit, pan, spline" in output


STUB_CLI = '''\
"""Stand-in for the real CLI: validates the resolved config and creates the output directory."""
import argparse
import pathlib

from scenegen.config import load_config

parser = argparse.ArgumentParser()
parser.add_argument("command", choices=["generate", "render-noisy", "render-reference"])
for option in ("--config", "--scene", "--scene-dir", "--out"):
    parser.add_argument(option)
parser.add_argument("--chunk", type=int)
args = parser.parse_args()
load_config(args.config)
out = pathlib.Path(args.out)
out.mkdir(parents=True)
(out / "stub.txt").write_text(f"{args.command} {args.scene} {args.chunk}\\n")
'''


@pytest.fixture
def stub_workflow(tmp_path: Path) -> Path:
    """A copy of the workflow whose `python -m scenegen` is a fast stub, run once on the smoke config."""
    for name in ("Snakefile", "workflow", "config"):
        source = REPO_ROOT / name
        if source.is_dir():
            shutil.copytree(source, tmp_path / name)
        else:
            shutil.copy(source, tmp_path / name)
    package = tmp_path / "scenegen"
    package.mkdir()
    (package / "__init__.py").write_text("")
    shutil.copy(REPO_ROOT / "scenegen" / "config.py", package / "config.py")
    (package / "__main__.py").write_text(STUB_CLI)
    run_snakemake("--cores", "2", "--configfile", "config/smoke.yaml", cwd=tmp_path)
    return tmp_path


def smoke_variant(workdir: Path, section: str, key: str, value: object) -> str:
    cfg = yaml.safe_load((workdir / "config/smoke.yaml").read_text())
    cfg[section][key] = value
    path = workdir / f"{section}_{key}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path.name


def test_config_changes_rerun_only_the_affected_jobs(stub_workflow: Path) -> None:
    work = stub_workflow
    assert (work / "results/renders/test_000/reference/chunk_001/stub.txt").is_file()
    assert dry_run("--configfile", "config/smoke.yaml", cwd=work) == {}

    noisy_only = dry_run("--configfile", smoke_variant(work, "render", "spp", 2), cwd=work)
    assert noisy_only == {"render_noisy": 4, "all": 1}

    reference_only = dry_run("--configfile", smoke_variant(work, "render", "reference_spp", 32), cwd=work)
    assert reference_only == {"render_reference": 4, "all": 1}

    one_more_scene = dry_run("--configfile", smoke_variant(work, "scenes", "n_train", 2), cwd=work)
    assert one_more_scene == {"generate_scene": 1, "render_noisy": 2, "render_reference": 2, "all": 1}

    everything = dry_run("--configfile", smoke_variant(work, "scenes", "objects", [3, 7]), cwd=work)
    assert everything == {"generate_scene": 2, "render_noisy": 4, "render_reference": 4, "all": 1}


def rule_names() -> set[str]:
    names = set()
    for rule_file in (REPO_ROOT / "workflow/rules").glob("*.smk"):
        names |= set(re.findall(r"^rule (\w+):", rule_file.read_text(), flags=re.MULTILINE))
    return names


def test_slurm_profile_sets_resources_for_every_rule() -> None:
    profile = yaml.safe_load((REPO_ROOT / "workflow/profiles/slurm/config.yaml").read_text())
    assert profile["executor"] == "slurm"
    assert {"slurm_partition", "slurm_account"} <= set(profile["default-resources"])
    assert set(profile["set-resources"]) == rule_names() == set(JOB_RULES)
    for rule, resources in profile["set-resources"].items():
        assert {"mem_mb", "runtime", "cpus_per_task"} <= set(resources), rule


def test_local_profile_runs_on_two_cores() -> None:
    profile = yaml.safe_load((REPO_ROOT / "workflow/profiles/local/config.yaml").read_text())
    assert profile["cores"] == 2 and profile["keep-going"] is False and profile["rerun-incomplete"] is True


def test_conda_env_mirrors_the_project_dependencies() -> None:
    env = yaml.safe_load((REPO_ROOT / "workflow/envs/harness.yaml").read_text())
    pip_section = next(item["pip"] for item in env["dependencies"] if isinstance(item, dict))
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    assert sorted(pip_section) == sorted(project["dependencies"])
