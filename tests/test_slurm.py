"""workflow/profiles/slurm on a real (one-node) SLURM: scripts/slurm-local.sh brings it up on this machine.

One scene and one noisy render chunk of the smoke config go through `--profile workflow/profiles/slurm` in a
temporary copy of the workflow. That the jobs really went through sbatch, and with the CPUs the profile
sets, is checked against SLURM's own records (squeue --states=all), not against Snakemake's output.
Skips, naming the reason, where SLURM cannot be installed or started (no apt-get, not root, a foreign
slurm.conf) or the executor plugin is not installed (`pip install -e '.[slurm]'`).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from denoisers.jobs.rows import row_clips
from scenegen.config import load_config
from tests.test_workflow import copy_workflow

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPT = REPO_ROOT / "scripts" / "slurm-local.sh"
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
# "Job 2 has been submitted with SLURM jobid 7 (log: .../slurm_logs/rule_render_noisy/test_000_000/7.log)."
SUBMITTED = re.compile(r"has been submitted with SLURM jobid (\d+) \(log: \S*/slurm_logs/rule_(\w+?)/")


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=timeout)


def _slurm_answers() -> bool:
    return shutil.which("sinfo") is not None and _run("sinfo", "-h").returncode == 0


@pytest.fixture(scope="module")
def slurm() -> Iterator[list[str]]:
    """A running one-node SLURM; yields the command-line options that point the profile at it. Stops the
    daemons afterwards only if this fixture started them."""
    if sys.platform != "linux":
        pytest.skip("SLURM test needs Linux")
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        pytest.skip("snakemake-executor-plugin-slurm is not installed: pip install -e '.[slurm]'")
    if shutil.which("slurmctld") is None and (shutil.which("apt-get") is None or os.geteuid() != 0):
        pytest.skip("SLURM is not installed and cannot be: needs apt-get and root (scripts/slurm-local.sh)")
    was_running = _slurm_answers()
    started = _run("bash", str(SCRIPT), "start", timeout=900)
    if started.returncode != 0:
        pytest.skip(f"scripts/slurm-local.sh start failed: {started.stderr.strip()[-600:]}")
    overrides = _run("bash", str(SCRIPT), "overrides")
    assert overrides.returncode == 0, overrides.stderr
    yield overrides.stdout.split()
    if not was_running:
        stopped = _run("bash", str(SCRIPT), "stop")
        assert stopped.returncode == 0, stopped.stderr


def test_smoke_scene_and_render_chunk_run_through_sbatch(slurm: list[str], tmp_path: Path) -> None:
    copy_workflow(tmp_path)
    config = yaml.safe_load((tmp_path / "config/smoke.yaml").read_text())
    out = Path(config.get("output_dir", "results"))
    chunk = out / "renders/test_000/noisy/chunk_000"
    env = dict(os.environ, PATH=f"{SNAKEMAKE.parent}{os.pathsep}{os.environ.get('PATH', '')}")
    result = subprocess.run(
        [str(SNAKEMAKE), chunk.as_posix(), "--configfile", "config/smoke.yaml",
         "--profile", "workflow/profiles/slurm", *slurm],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-4000:]

    submitted = {int(job): rule for job, rule in SUBMITTED.findall(log)}
    assert sorted(submitted.values()) == ["generate_scene", "render_noisy"], log[-4000:]
    run_id = re.search(r"SLURM run ID: (\S+)", log)
    assert run_id is not None, log[-4000:]

    # SLURM's own record of those jobs: MinJobAge keeps finished jobs in squeue.
    ids = ",".join(str(job) for job in submitted)
    queue = _run("squeue", "--states=all", "--noheader", "--format=%i|%T|%j|%C", "--jobs", ids)
    assert queue.returncode == 0, queue.stderr
    records = {int(job): (state, name, int(cpus))
               for job, state, name, cpus in (line.split("|") for line in queue.stdout.split())}
    assert set(records) == set(submitted), queue.stdout
    profile = yaml.safe_load((tmp_path / "workflow/profiles/slurm/config.yaml").read_text())
    for job, rule in submitted.items():
        state, name, cpus = records[job]
        assert state == "COMPLETED" and name == run_id.group(1), (rule, records[job])
        assert cpus == profile["set-resources"][rule]["cpus_per_task"], (rule, records[job])

    frames = sorted((tmp_path / chunk).glob("frame_*.exr"))
    assert len(frames) == config["scenes"]["frames_per_chunk"] and all(f.stat().st_size > 0 for f in frames)
    assert (tmp_path / out / "scenes/test_000").is_dir()


def _slurm_records(ids: list[int]) -> dict[int, tuple[str, int, int]]:
    """SLURM's record of jobs: id -> (state, CPUs, memory in MB)."""
    queue = _run("squeue", "--states=all", "--noheader", "--format=%i|%T|%C|%m", "--jobs", ",".join(map(str, ids)))
    assert queue.returncode == 0, queue.stderr
    records = {}
    for line in queue.stdout.split():
        job, state, cpus, memory = line.split("|")
        records[int(job)] = (state, int(cpus), int(memory.rstrip("M")) if memory.endswith("M")
                             else int(float(memory.rstrip("G")) * 1024))
    return records


def test_row_jobs_batch_clips_and_retries_grow_or_are_refused(slurm: list[str], tmp_path: Path) -> None:
    """Issue 50 §2 on one node: (1) the denoise and evaluate work of a row's clips goes to SLURM as one job per row
    (denoise_row, evaluate_row: fewer sbatch calls than clips, each job every clip of its row); (2) a job killed for
    memory (fault injection: MCDN_FAULT_MIN_MEM_MB) is retried with twice the memory and succeeds; (3) a job failing
    on a corrupt input is not run again: its retry stops at once, saying so."""
    copy_workflow(tmp_path)
    config = yaml.safe_load((tmp_path / "config/smoke.yaml").read_text())
    out = Path(config.get("output_dir", "results"))
    rows = ("noisy", "path_x2")
    targets = [(out / f"metrics/{row}").as_posix() for row in rows]
    # generate_scene asks for 4000 MB x attempt (the profile): killed at 4000 MB, through at 8000 MB
    env = dict(os.environ, PATH=f"{SNAKEMAKE.parent}{os.pathsep}{os.environ.get('PATH', '')}",
               MCDN_FAULT_MIN_MEM_MB="5000", MCDN_FAULT_COMMANDS="generate")
    command = [str(SNAKEMAKE), *targets, "--configfile", "config/smoke.yaml", "--profile", "workflow/profiles/slurm",
               *slurm]
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1200)
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-4000:]

    rules = {int(job): rule for job, rule in SUBMITTED.findall(log)}
    records = _slurm_records(sorted(rules))
    # (2) generate_scene: the first attempt (4000 MB) killed, the retry (8000 MB) completed
    generate = sorted(job for job, rule in rules.items() if rule == "generate_scene")
    assert [records[job][0] for job in generate] == ["FAILED", "COMPLETED"], (generate, records)
    assert [records[job][2] for job in generate] == [4000, 8000], records
    # (1) one denoise_row and one evaluate_row job per row, each writing every clip of its row
    smoke = load_config(tmp_path / "config/smoke.yaml")
    clips = {row: row_clips(smoke, row) for row in rows}
    assert sorted(rule for rule in rules.values() if rule.endswith("_row")) == ["denoise_row"] * 2 + \
        ["evaluate_row"] * 2, rules
    assert sum(map(len, clips.values())) > len(rows), clips
    assert all(records[job][0] == "COMPLETED" for job, rule in rules.items() if rule.endswith("_row")), records
    for row, target in zip(rows, targets):
        written = {p.relative_to(tmp_path / target).as_posix() for p in (tmp_path / target).glob("*/spp*")}
        assert written == {f"{scene}/spp{spp}.{kind}" for scene, spp in clips[row] for kind in ("csv", "json")}, row

    # (3) a truncated noisy frame: the denoise job fails on it, and its retry is refused without redoing the work
    frame = sorted((tmp_path / out / "renders/test_000/noisy/chunk_000").glob("frame_*.exr"))[0]
    frame.write_bytes(frame.read_bytes()[:200])
    failing = (out / "metrics/svgf").as_posix()
    result = subprocess.run([*command[:1], failing, *command[len(targets) + 1:]], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=900)
    assert result.returncode != 0
    denoise_log = (tmp_path / out / "logs/denoise/svgf.log").read_text()
    assert "not retried: the previous attempt failed deterministically" in denoise_log, denoise_log
    assert frame.name in denoise_log, denoise_log
