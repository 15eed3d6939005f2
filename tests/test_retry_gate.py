"""scenegen.retry_gate: a job that failed on its config or inputs refuses its retry; a new run clears that.

The command-line tools are run as the workflow runs them, stderr redirected to the job's log; the SLURM side (a
retry within one run) is tests/test_slurm.py::test_clip_jobs_go_grouped_and_retries_grow_or_are_refused."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from scenegen.retry_gate import (EXIT_NOT_RETRIED, KILLED_FOR_MEMORY, clear_markers, marker_for, record_failure,
                                 refuse_retry, simulated_memory_kill)

REPO = Path(__file__).resolve().parents[1]


def _run_tool(module: str, args: list[str], log: Path, env: dict | None = None) -> int:
    """``python -m module args > log 2>&1`` as a rule's shell runs it; returns the exit status."""
    with log.open("w") as stream:
        return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO, stdout=stream, stderr=stream,
                              env=env, timeout=300).returncode


def test_marker_refuses_the_next_attempt_and_a_new_run_clears_it(tmp_path: Path) -> None:
    log = tmp_path / "logs" / "job.log"
    log.parent.mkdir()
    log.write_text("")
    assert refuse_retry(log) is None
    marker = record_failure(ValueError("frame_0003.exr: truncated"), log)
    assert marker == marker_for(log) and "frame_0003.exr: truncated" in marker.read_text()
    assert refuse_retry(log) == EXIT_NOT_RETRIED
    assert clear_markers(tmp_path / "logs") == 1 and refuse_retry(log) is None


@pytest.mark.parametrize("module", ["denoisers", "scenegen"])
def test_a_tool_failing_on_its_config_refuses_its_retry(module: str, tmp_path: Path) -> None:
    """An unreadable config is an expected failure: the first attempt fails and marks the log, the second stops at
    once with EXIT_NOT_RETRIED and says why; with the marker cleared (a new run) it fails on the config again."""
    log = tmp_path / "job.log"
    command = (["evaluate", "--config", str(tmp_path / "missing.yaml"), "--denoised", str(tmp_path), "--render-dir",
                str(tmp_path), "--out", str(tmp_path / "o.csv")]
               if module == "denoisers" else
               ["generate", "--config", str(tmp_path / "missing.yaml"), "--scene", "test_000", "--out", str(tmp_path)])
    first = _run_tool(module, command, log)
    assert first != 0 and first != EXIT_NOT_RETRIED, log.read_text()
    assert "missing.yaml" in marker_for(log).read_text()
    assert _run_tool(module, command, log) == EXIT_NOT_RETRIED
    text = log.read_text()
    assert "not retried: the previous attempt failed deterministically" in text and "missing.yaml" in text
    clear_markers(tmp_path)
    assert _run_tool(module, command, log) == first


def test_without_a_log_file_nothing_is_marked(tmp_path: Path) -> None:
    """A tool run by hand (stderr on a pipe here, a terminal usually) has no job log: no marker, no refusal."""
    done = subprocess.run([sys.executable, "-m", "scenegen", "generate", "--config", str(tmp_path / "missing.yaml"),
                           "--scene", "test_000", "--out", str(tmp_path)], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode != 0 and not list(tmp_path.rglob("*.no-retry"))


def test_fault_injection_fakes_a_memory_kill_only_below_its_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    assert simulated_memory_kill("generate") is None          # not set: never
    monkeypatch.setenv("MCDN_FAULT_MIN_MEM_MB", "5000")
    monkeypatch.setenv("SLURM_MEM_PER_NODE", "4000")
    assert simulated_memory_kill("generate") == KILLED_FOR_MEMORY
    monkeypatch.setenv("MCDN_FAULT_COMMANDS", "render-noisy")
    assert simulated_memory_kill("generate") is None          # another command
    monkeypatch.setenv("MCDN_FAULT_COMMANDS", "generate")
    monkeypatch.setenv("SLURM_MEM_PER_NODE", "8000")
    assert simulated_memory_kill("generate") is None          # enough memory
    monkeypatch.delenv("SLURM_MEM_PER_NODE")
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    assert simulated_memory_kill("generate") is None          # not in a SLURM job
