"""Deterministic failures are not retried: a job that failed on its config or its inputs fails its retries at once.

The SLURM profile retries failed jobs with more memory and wall time (``attempt``), which helps a job killed for
memory or time and wastes a slot on one that would fail the same way again (an invalid model id, a corrupt EXR,
a non-finite loss). Snakemake's retries cannot tell the two apart, so the command-line tools do:

* on an expected failure (the errors the CLIs report in one line: configuration, inputs, checkpoints, the
  store, ...) they write ``<log>.no-retry`` beside the job's log, holding the message;
* at start, a job whose log has that marker stops with exit code :data:`EXIT_NOT_RETRIED` and says why, without
  doing the work again;
* the workflow removes every marker when a run starts (``onstart``: :func:`clear_markers`), so the next
  ``snakemake`` invocation, after the config or the input was fixed, runs the job again.

The job's log is the file the tool's stderr goes to (the rules redirect ``> {log} 2>&1``); a tool run by hand, its
stderr on a terminal, has no log and no marker.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

MARKER_SUFFIX = ".no-retry"
#: Exit status of a retry refused because its previous attempt failed deterministically.
EXIT_NOT_RETRIED = 3


def job_log(stream_fd: int = 2) -> Path | None:
    """The regular file ``stream_fd`` (stderr) writes to, or None (a terminal, a pipe, no /proc)."""
    try:
        target = Path(os.readlink(f"/proc/self/fd/{stream_fd}"))
    except OSError:
        return None
    return target if target.is_file() else None


def marker_for(log: Path) -> Path:
    return log.with_name(log.name + MARKER_SUFFIX)


def refuse_retry(log: Path | None = None) -> int | None:
    """:data:`EXIT_NOT_RETRIED` after printing the earlier failure when this job's log has a marker, else None."""
    log = job_log() if log is None else log
    if log is None:
        return None
    marker = marker_for(log)
    if not marker.is_file():
        return None
    message = marker.read_text(encoding="utf-8", errors="replace").strip()
    print(f"not retried: the previous attempt failed deterministically (config or inputs), and would fail the same "
          f"way again:\n{message}\n(fix it and run snakemake again: a new run clears {marker.name})", file=sys.stderr)
    return EXIT_NOT_RETRIED


def record_failure(error: BaseException, log: Path | None = None) -> Path | None:
    """Write this job's marker with ``error``'s message; returns its path (None without a job log)."""
    log = job_log() if log is None else log
    if log is None:
        return None
    marker = marker_for(log)
    marker.write_text(f"{type(error).__name__}: {error}\n", encoding="utf-8")
    return marker


def clear_markers(root: Path) -> int:
    """Remove every marker below ``root`` (the experiment's logs); returns how many."""
    count = 0
    for marker in Path(root).rglob(f"*{MARKER_SUFFIX}"):
        marker.unlink(missing_ok=True)
        count += 1
    return count


#: Fault injection for the one-node SLURM check (tests/test_slurm.py): a job whose SLURM allocation holds less memory
#: than this many MB stops at once as if killed for memory, so only its retry, with more memory, gets through.
FAULT_MIN_MEMORY_VARIABLE = "MCDN_FAULT_MIN_MEM_MB"
#: Comma-separated subcommands (``generate``, ``denoise``, ...) the fault applies to; unset: every one.
FAULT_COMMANDS_VARIABLE = "MCDN_FAULT_COMMANDS"
#: Exit status of a process killed by SIGKILL, as the kernel's out-of-memory killer leaves it.
KILLED_FOR_MEMORY = 137


def simulated_memory_kill(command: str) -> int | None:
    """:data:`KILLED_FOR_MEMORY` when :data:`FAULT_MIN_MEMORY_VARIABLE` is set, ``command`` is among
    :data:`FAULT_COMMANDS_VARIABLE` and this SLURM job was given less memory (``SLURM_MEM_PER_NODE``, MB), else
    None. Never set outside that check."""
    limit, commands = os.environ.get(FAULT_MIN_MEMORY_VARIABLE), os.environ.get(FAULT_COMMANDS_VARIABLE)
    allocated = _slurm_job_memory_mb() if limit else None
    if not limit or allocated is None or allocated >= int(limit):
        return None
    if commands and command not in commands.split(","):
        return None
    print(f"simulated out-of-memory kill ({FAULT_MIN_MEMORY_VARIABLE}): the job has {allocated} MB, {limit} MB "
          "are needed", file=sys.stderr)
    return KILLED_FOR_MEMORY


def _slurm_job_memory_mb() -> int | None:
    """Memory (MB) of the SLURM job this process runs in: ``SLURM_MEM_PER_NODE``, or (inside a job step, whose
    environment the executor's jobstep plugin strips of it) ``scontrol show job``'s MinMemoryNode."""
    import re
    import subprocess

    if os.environ.get("SLURM_MEM_PER_NODE"):
        return int(os.environ["SLURM_MEM_PER_NODE"])
    job = os.environ.get("SLURM_JOB_ID")
    if not job:
        return None
    try:
        shown = subprocess.run(["scontrol", "show", "job", "-o", job], capture_output=True, text=True,
                               timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    found = re.search(r"MinMemoryNode=(\d+)([MG])", shown)
    return None if found is None else int(found.group(1)) * (1024 if found.group(2) == "G" else 1)
