"""Training that outlives the machine: train models until a deadline, then keep everything in the store.

The machines here live about 3 hours and only what is committed survives, so a long training (the Isik run,
issue 48; the seed replicas, issue 46) is a series of sessions. ``python -m denoisers train-session`` is one of
them:

1. it runs the workflow for the given models (``scripts/run-main.sh results/models/<id> ...``, so a stored model is
   installed and a stored part-way checkpoint continued, denoisers.training.job) in its own process group; without
   model ids, for every model the config trains (the stage target ``train``: seed replicas and half-budget twins
   included, the stored ones installed), so a session need not know what earlier ones finished; the runs that
   continue a stored checkpoint go first (Snakemake's ``--prioritize``, unless the arguments prioritize already);
2. at ``--minutes`` it stops that run (SIGTERM to the group; the trainers checkpoint every 300 s and every
   ``training.validate_every`` steps, so at most that much work is lost);
3. it publishes every model that finished in this session (``store publish``) and the part-way state of every one
   that did not (``store checkpoint``: the next machine continues from it), using the resolved config the run wrote.

Commit ``store/`` afterwards; the next session runs the same command and goes on.

A run continues only on a machine that resolves the same step arithmetic (precision ``auto`` is bf16 where the CPU
has native bfloat16, else fp32; denoisers.training.precision): elsewhere its stored checkpoint would be ignored and
the run would start afresh, and its keeps would be refused while the stored checkpoint holds more steps. So a
session skips the models whose stored checkpoint has another arithmetic than this machine's, and says which;
``--restart-other-arithmetic`` trains them afresh here instead and lets the keeps replace that checkpoint.

A machine can also go before the deadline (2026-12-06: one was shut down an hour into its session and took the
session's training with it). ``--keep-every MINUTES`` pauses the run that often (SIGSTOP to its group), keeps what it
has reached as in step 3 and lets it go on; with ``--commit`` each keep is committed (the store only, built in a
separate index), so a lost machine loses at most that interval.

Each commit stays within the session's submission budget (denoisers.store.submission): a stop whose commits pass
the workplace's limits lands none of them, and keeps that replace a checkpoint every interval add up (on 2026-12-07
a session's six keeps of a 27 MB KPCN checkpoint did, and all its training was lost). What would pass the budget
(``--submission-budget``, 192 MiB of the 256 MiB diff limit by default) stays on disk, finished models go in
before checkpoints, and the command names what it left uncommitted.
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from denoisers.store.code import REPO_ROOT
from denoisers.store.submission import DEFAULT_BUDGET_MIB, SubmissionBudget, entry_of, fit_staged, session_base

#: Seconds between checks of the run.
POLL_SECONDS = 10.0
#: Seconds the stopped run gets to exit after SIGTERM before SIGKILL.
STOP_GRACE_SECONDS = 60.0


@dataclass
class SessionResult:
    """What one session did: the run's exit status (None: stopped at the deadline), and per model what was kept."""

    returncode: int | None
    stopped_at_deadline: bool
    published: list[str] = field(default_factory=list)
    checkpointed: list[str] = field(default_factory=list)
    untouched: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    already_stored: list[str] = field(default_factory=list)   # untouched because the store held them already
    uncommitted: list[str] = field(default_factory=list)      # store entries left on disk, not committed


def group_pids(pgid: int) -> list[int]:
    """Pids of the live processes of process group ``pgid`` (read from /proc)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue                       # the process went meanwhile
        if int(fields[2]) == pgid and fields[0] != "Z":
            pids.append(int(stat.parent.name))
    return pids


def paused_group(pgid: int, call: Callable[[], object]) -> None:
    """Stop process group ``pgid`` (SIGSTOP), run ``call`` and continue the processes this stopped; one that was
    stopped already (a trainer paused by hand with ``kill -STOP`` while the tests run) stays stopped."""
    already = {pid for pid in group_pids(pgid) if _state(pid) == "T"}
    os.killpg(pgid, signal.SIGSTOP)
    try:
        _wait_stopped(pgid)
        call()
    finally:
        for pid in group_pids(pgid):
            if pid not in already:
                try:
                    os.kill(pid, signal.SIGCONT)
                except ProcessLookupError:
                    pass


#: States of /proc/<pid>/stat that count as no longer running: stopped, traced, zombie, dead (or gone: "?").
_NOT_RUNNING = frozenset("TtZX?")


def _wait_stopped(pgid: int, timeout_s: float = 10.0) -> None:
    """Wait until every process of group ``pgid`` has stopped: SIGSTOP is delivered asynchronously, and a process
    still running when the keep copies its checkpoint could be writing it."""
    end = time.monotonic() + timeout_s
    while running := [pid for pid in group_pids(pgid) if _state(pid) not in _NOT_RUNNING]:
        if time.monotonic() > end:
            raise TimeoutError(f"process group {pgid}: processes {running} still run {timeout_s:g} s after SIGSTOP")
        time.sleep(0.01)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return "?"


def run_until(command: Sequence[str], deadline_s: float, cwd: Path = REPO_ROOT, log: Path | None = None,
              every_s: float | None = None, on_interval: Callable[[], object] | None = None) -> tuple[int | None, bool]:
    """Run ``command`` in a new process group until it exits or ``deadline_s`` seconds have passed; then SIGTERM
    the group (SIGKILL after :data:`STOP_GRACE_SECONDS`). Every ``every_s`` seconds the group is paused while
    ``on_interval()`` runs (:func:`paused_group`; the pause counts towards the deadline). Returns (exit status or
    None, stopped at the deadline)."""
    stream = open(log, "ab") if log is not None else None  # noqa: SIM115 -- closed below
    try:
        process = subprocess.Popen(list(command), cwd=cwd, stdout=stream, stderr=subprocess.STDOUT if stream else None,
                                   start_new_session=True)
        end = time.monotonic() + deadline_s
        next_keep = time.monotonic() + every_s if every_s and on_interval is not None else float("inf")
        while process.poll() is None and time.monotonic() < end:
            time.sleep(min(POLL_SECONDS, max(0.0, min(end, next_keep) - time.monotonic())))
            if process.poll() is None and end > time.monotonic() >= next_keep:
                try:
                    paused_group(process.pid, on_interval)
                except Exception as error:   # noqa: BLE001 -- the run must still be stopped at its deadline
                    print(f"train-session: the interval keep failed ({error!r}); the run goes on", file=sys.stderr)
                next_keep = time.monotonic() + every_s
        if process.poll() is not None:
            return process.returncode, False
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=STOP_GRACE_SECONDS)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        return None, True
    finally:
        if stream is not None:
            stream.close()


def resolved_config(output_dir: Path, since: float) -> Path:
    """The resolved config the run wrote (``<output_dir>/.config/<digest>.yaml``, the newest since ``since``; the
    newest of all when the run found it already written)."""
    files = sorted((output_dir / ".config").glob("*.yaml"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise FileNotFoundError(f"{output_dir / '.config'}: no resolved config; did the run start?")
    recent = [p for p in files if p.stat().st_mtime >= since]
    return (recent or files)[-1]


def stored_finished(config_file: Path) -> Callable[[str], bool]:
    """``is_stored(model_id)``: whether the store holds ``model_id`` finished under the resolved config's key."""
    import yaml

    from denoisers.store.entries import ModelStore

    cfg = yaml.safe_load(Path(config_file).read_text())
    store = ModelStore.of(cfg)
    return lambda model_id: store.model_entry(cfg, model_id) is not None


def keep(output_dir: Path, model_ids: Sequence[str], since: float, store_command: Callable[[list[str]], int],
         is_stored: Callable[[str], bool] | None = None,
         replace_other_arithmetic: Sequence[str] = ()) -> tuple[list[str], list[str], list[str]]:
    """Publish the models of ``model_ids`` that finished since ``since`` and checkpoint the runs that moved since then
    but did not finish; ``store_command(args)`` runs ``python -m denoisers store <args>``. Returns (published,
    checkpointed, untouched) ids. A half-budget twin's run is its full model's (``{id}_half`` -> ``{id}``); a run
    whose full model the store holds (``is_stored``, default :func:`stored_finished`) is not checkpointed: the
    store refuses it, since nothing would continue it (the twin then counts as untouched). The checkpoints of the
    runs in ``replace_other_arithmetic`` replace a stored one of another step arithmetic."""
    from denoisers.training.models import HALF_SUFFIX

    config = resolved_config(output_dir, since)
    if is_stored is None:
        is_stored = stored_finished(config)
    models = output_dir / "models"
    published, checkpointed, untouched = [], [], []
    for model_id in model_ids:
        summary = models / model_id / "summary.json"
        if summary.is_file() and summary.stat().st_mtime >= since and "installed_from_store" not in summary.read_text():
            if store_command(["publish", "--config", str(config), "--model-id", model_id]) == 0:
                published.append(model_id)
                continue
        run_id = model_id[:-len(HALF_SUFFIX)] if model_id.endswith(HALF_SUFFIX) else model_id
        moved = [p for p in models.glob(f".work/{run_id}-*/checkpoint.pt") if p.stat().st_mtime >= since]
        finished = (models / run_id / "summary.json").is_file() or (bool(moved) and is_stored(run_id))
        if moved and not finished and run_id not in checkpointed:
            replace = ["--replace-other-arithmetic"] if run_id in replace_other_arithmetic else []
            if store_command(["checkpoint", "--config", str(config), "--model-id", run_id, *replace]) == 0:
                checkpointed.append(run_id)
                continue
        if model_id not in published and run_id not in checkpointed:
            untouched.append(model_id)
    return published, checkpointed, untouched


def store_command(args: list[str]) -> int:
    """Run ``python -m denoisers store <args>``; its exit status. Its stderr is passed on through a pipe: with the
    session's own stderr (a log file), the retry gate (scenegen.retry_gate) would take that file for a job log, and one
    refused store command (e.g. a checkpoint the store refuses) would mark it and refuse every later one."""
    result = subprocess.run([sys.executable, "-m", "denoisers", "store", *args], cwd=REPO_ROOT,
                            stderr=subprocess.PIPE, text=True)
    sys.stderr.write(result.stderr)
    return result.returncode


def configured_trainings(config_file: Path) -> list[str]:
    """Ids of every training of a resolved config file (:func:`configured_trainings_of`)."""
    import yaml

    return configured_trainings_of(yaml.safe_load(Path(config_file).read_text()))


def configured_trainings_of(cfg: dict) -> list[str]:
    """Ids of every training of ``cfg`` (``trained_model_specs``: seed replicas and half-budget twins included),
    without the variants that publish another model's weights (``same_training_as``)."""
    from denoisers.training.models import same_training_as, trained_model_specs

    return [spec.id for spec in trained_model_specs(cfg) if same_training_as(cfg, spec.id) is None]


def half_of_run(cfg: dict, model_id: str) -> str:
    """The run ``model_id`` trains in: a half-budget twin's is its full model's."""
    from denoisers.training.models import half_of

    return half_of(cfg, model_id) or model_id


def kept_ids(model_ids: Sequence[str], configured: Sequence[str]) -> list[str]:
    """What a session keeps: every training of the config (``configured``) when no ids were given, else the ids
    with the half-budget twin of each that the config trains (a model's target trains its twin too)."""
    from denoisers.training.models import HALF_SUFFIX

    if not model_ids:
        return list(configured)
    twins = [f"{m}{HALF_SUFFIX}" for m in model_ids if f"{m}{HALF_SUFFIX}" in configured]
    return list(dict.fromkeys([*model_ids, *twins]))


def commit_store(store_root: Path, message: str, cwd: Path = REPO_ROOT,
                 budget: SubmissionBudget | None = None, reserve_for_end: bool = False) -> bool:
    """Commit the store directory as it is on disk, and nothing else: the commit is built in a separate index from
    HEAD and the store's files, so what else is staged stays staged. With ``budget``, only the store entries that
    keep the session's submission within it are committed (:func:`denoisers.store.submission.fit_staged`); the
    others stay on disk, uncommitted, and are named on stderr and in the message; ``reserve_for_end`` (an interval
    keep) leaves room for the last keep to replace the session's checkpoints once more. Returns whether a commit was made
    (False: nothing changed, nothing fitted, or git refused, e.g. another git command holds HEAD; the next keep
    tries again)."""
    store_root = Path(store_root)
    relative = store_root.relative_to(cwd).as_posix() if store_root.is_absolute() else store_root.as_posix()
    index = Path(cwd, subprocess.run(["git", "rev-parse", "--git-path", "index.train-session"], cwd=cwd,
                                     capture_output=True, text=True).stdout.strip())
    env = {**os.environ, "GIT_INDEX_FILE": str(index)}

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=cwd, env=env, capture_output=True, text=True)

    try:
        if git("read-tree", "HEAD").returncode != 0 or git("add", "-A", "--", relative).returncode != 0:
            return False
        if git("diff", "--cached", "--quiet", "--", relative).returncode == 0:
            return False
        if budget is not None:
            kept, held = fit_staged(budget, relative, cwd, env=env, reserve_for_end=reserve_for_end)
            if held:
                print(f"train-session: not committed, left on disk: {', '.join(held)} (committing it would pass "
                      f"the session's submission budget; {budget.describe()})", file=sys.stderr)
                message += f" (left on disk for the submission budget: {', '.join(held)})"
            if not kept:
                return False
        result = git("commit", "-q", "-m", message)
        if result.returncode != 0:
            print(f"train-session: git commit of {relative} failed: {result.stderr.strip()}", file=sys.stderr)
            return False
    finally:
        index.unlink(missing_ok=True)
    # The checkout's own index: the store's paths as committed (the ones held back show as unstaged changes).
    subprocess.run(["git", "reset", "-q", "--", relative], cwd=cwd, capture_output=True)
    return True


def _part_way_runs(cfg: dict, model_ids: Sequence[str]) -> Iterator[tuple[str, str, dict, dict]]:
    """(model id, its run, the stored checkpoint's meta, the arithmetic this machine resolves for the run) for each
    id of ``model_ids`` whose run (a twin's is its full model's) is a training of ``cfg`` part-way in the store."""
    from denoisers.store.entries import ModelStore
    from denoisers.training.models import model_spec
    from denoisers.training.precision import resolve_compute

    store = ModelStore.of(cfg)
    trained = set(configured_trainings_of(cfg))
    for model_id in model_ids:
        run_id = half_of_run(cfg, model_id)
        if run_id not in trained:
            continue                       # not a training of this config: the run reports it
        entry = store.checkpoint_entry(cfg, run_id)
        if entry is None or store.model_entry(cfg, run_id) is not None:
            continue
        yield model_id, run_id, entry.summary(), resolve_compute(model_spec(cfg, run_id).compute).fingerprint()


def other_arithmetic(cfg: dict, model_ids: Sequence[str]) -> dict[str, str]:
    """The ids of ``model_ids`` whose run (a twin's is its full model's) is part-way in the store with another step
    arithmetic than this machine resolves for it, each with a line that says which. Such a run cannot continue here
    (denoisers.training.job keys a run's work by the arithmetic it resolves to): it would start afresh."""
    from denoisers.store.entries import arithmetic_text

    found = {}
    for model_id, run_id, meta, here in _part_way_runs(cfg, model_ids):
        if meta.get("compute") != here:
            found[model_id] = (f"{model_id}: the stored checkpoint of {run_id} (step {meta.get('step')}) was trained "
                               f"with {arithmetic_text(meta.get('compute'))}, this machine resolves "
                               f"{arithmetic_text(here)}")
    return found


def continued_here(cfg: dict, model_ids: Sequence[str]) -> list[str]:
    """The runs of ``model_ids`` (a twin's is its full model's, each once) that continue a stored checkpoint of
    this machine's arithmetic."""
    runs = [run_id for _, run_id, meta, here in _part_way_runs(cfg, model_ids) if meta.get("compute") == here]
    return list(dict.fromkeys(runs))


def priority_args(cfg: dict, model_ids: Sequence[str], output_dir: Path, snakemake_args: Sequence[str]) -> list[str]:
    """Snakemake arguments that run the runs continued here (:func:`continued_here`) before the others, so a run
    most of the way done is finished and published first (``--prioritize <output_dir>/models/<run>``); none when
    ``snakemake_args`` prioritize already or no run continues."""
    if any(arg in ("--prioritize", "-P") or arg.startswith("--prioritize=") for arg in snakemake_args):
        return []
    runs = continued_here(cfg, model_ids)
    if not runs:
        return []
    root = output_dir.relative_to(REPO_ROOT).as_posix() if output_dir.is_relative_to(REPO_ROOT) else str(output_dir)
    return ["--prioritize", *(f"{root}/models/{run}" for run in runs)]


def store_root_of(config_file: Path) -> Path:
    """The store directory a resolved config names (absolute)."""
    import yaml

    from denoisers.store.entries import ModelStore

    root = ModelStore.of(yaml.safe_load(Path(config_file).read_text())).root
    return root if root.is_absolute() else REPO_ROOT / root


def session_config(snakemake_args: Sequence[str]) -> dict:
    """The validated config a run with ``snakemake_args`` reads: the last ``--configfile`` (default
    config/config.yaml) with the ``--config KEY=VALUE ...`` overrides merged as Snakemake merges them (its own
    parser), their string leaves parsed where the schema wants another type (scenegen.overrides), as the workflow
    does before it validates."""
    from snakemake.cli import parse_config
    from snakemake.utils import update_config

    from scenegen.config import ConfigError, load_schema, read_config_file, validate_config
    from scenegen.overrides import coerce_override_strings

    args = list(snakemake_args)
    config_files = [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--configfile"]
    path = Path(config_files[-1] if config_files else REPO_ROOT / "config" / "config.yaml")
    overrides: list[str] = []
    for i, arg in enumerate(args):
        if arg in ("--config", "-C"):
            overrides += list(itertools.takewhile(lambda a: not a.startswith("-"), args[i + 1:]))
    cfg = read_config_file(path)
    if overrides:
        try:
            update_config(cfg, parse_config(overrides))
        except ValueError as err:
            raise ConfigError(f"--config {' '.join(overrides)}: {err}") from None
        coerce_override_strings(cfg, load_schema())
    try:
        return validate_config(cfg)
    except ConfigError as err:
        raise ConfigError(f"{path}{' with --config ' + ' '.join(overrides) if overrides else ''}: {err}") from None


def train_session(model_ids: Sequence[str], minutes: float, snakemake_args: Sequence[str] = (),
                  output_dir: Path | None = None, log: Path | None = None,
                  run_command: Sequence[str] | None = None, keep_every_minutes: float | None = None,
                  commit: bool = False, restart_other_arithmetic: bool = False,
                  is_stored: Callable[[str], bool] | None = None,
                  submission_budget_mib: float | None = DEFAULT_BUDGET_MIB,
                  submission_base: str | None = None) -> SessionResult:
    """One session (module docstring); no ``model_ids``: every training of the config (:func:`configured_trainings`
    of the resolved config the run wrote). Every ``keep_every_minutes`` the run is paused and what it reached is
    kept; ``commit``: each keep, and the last, is committed (:func:`commit_store`), as far as the commits after
    ``submission_base`` (default: where this checkout's branch began, :func:`denoisers.store.submission.session_base`)
    stay within ``submission_budget_mib`` of diffs (None: no budget); what does not fit stays on disk and is listed
    in the result's ``uncommitted``. Models whose stored checkpoint
    has another step arithmetic than this machine's (:func:`other_arithmetic`, on :func:`session_config`) are
    skipped, or with ``restart_other_arithmetic`` trained afresh and their checkpoints replaced. ``run_command``
    replaces ``scripts/run-main.sh <targets> <args>`` (tests). Of the models the session left alone, those the
    store already held (``is_stored``, default :func:`stored_finished`) are reported apart from the untouched."""
    from scenegen.config import output_root

    cfg = session_config(snakemake_args)
    if output_dir is None:
        output_dir = output_root(cfg)
    requested = list(model_ids) or configured_trainings_of(cfg)
    other = other_arithmetic(cfg, requested)
    for line in other.values():
        print(f"train-session: {line}: " + ("training it afresh here (--restart-other-arithmetic)"
                                            if restart_other_arithmetic else
                                            "skipped (continue it on such a machine, or --restart-other-arithmetic)"),
              file=sys.stderr)
    skipped = [] if restart_other_arithmetic else [m for m in requested if m in other]
    if skipped:
        model_ids = [m for m in requested if m not in other]
        if not model_ids:
            return SessionResult(None, False, skipped=skipped)
    replace = sorted({half_of_run(cfg, m) for m in other}) if restart_other_arithmetic else []
    output_dir = Path(output_dir)
    if not output_dir.is_absolute():
        output_dir = REPO_ROOT / output_dir
    if run_command is None:
        targets = [f"{output_dir.relative_to(REPO_ROOT).as_posix()}/models/{m}" for m in model_ids] or ["train"]
        ahead = priority_args(cfg, list(model_ids) or configured_trainings_of(cfg), output_dir, snakemake_args)
        if ahead:
            print(f"train-session: runs continued here go first ({' '.join(ahead[1:])})", file=sys.stderr)
        run_command = ["bash", str(REPO_ROOT / "scripts" / "run-main.sh"), *targets, *snakemake_args, *ahead]
    command = list(run_command)
    since = time.time() - 1.0
    base = (submission_base or session_base(REPO_ROOT)) if commit and submission_budget_mib is not None else None
    if base:
        so_far = SubmissionBudget.measure(REPO_ROOT, base, submission_budget_mib)
        print(f"train-session: submission so far, {so_far.describe()}", file=sys.stderr)

    done: list[str] = []           # published by an interval keep: not published again

    def keep_now(final: bool) -> tuple[list[str], list[str], list[str]]:
        try:
            config = resolved_config(output_dir, since)
        except FileNotFoundError:
            if final:
                raise
            return [], [], []      # the run has not started its workflow yet
        ids = [m for m in kept_ids(model_ids, configured_trainings(config)) if m not in done]
        published, checkpointed, untouched = keep(output_dir, ids, since, store_command,
                                                  replace_other_arithmetic=replace)
        done.extend(published)
        if commit:                 # also when nothing is new: what an earlier keep left on disk may fit now
            what = "; ".join(part for part in (f"published {', '.join(published)}" if published else "",
                                                f"checkpoints of {', '.join(checkpointed)}" if checkpointed else "")
                             if part) or "what earlier keeps left on disk"
            budget = SubmissionBudget.measure(REPO_ROOT, base, submission_budget_mib) if base else None
            commit_store(store_root_of(config), f"train-session ({'end' if final else 'interval'} keep): {what}",
                         budget=budget, reserve_for_end=not final)
        return published, checkpointed, untouched

    every_s = keep_every_minutes * 60.0 if keep_every_minutes else None
    returncode, stopped = run_until(command, minutes * 60.0, log=log, every_s=every_s,
                                    on_interval=lambda: keep_now(final=False))
    _, checkpointed, untouched = keep_now(final=True)
    if is_stored is None:
        is_stored = stored_finished(resolved_config(output_dir, since))
    already = [m for m in untouched if is_stored(m)]
    uncommitted = uncommitted_entries(store_root_of(resolved_config(output_dir, since))) if commit else []
    return SessionResult(returncode, stopped, list(done), checkpointed, [m for m in untouched if m not in already],
                         skipped, already, uncommitted)


def uncommitted_entries(store_root: Path, cwd: Path = REPO_ROOT) -> list[str]:
    """The store entries (``<store>/<kind>/<id>``) with changes on disk that no commit holds."""
    store_root = Path(store_root)
    relative = store_root.relative_to(cwd).as_posix() if store_root.is_absolute() else store_root.as_posix()
    out = subprocess.run(["git", "status", "--porcelain", "-z", "--no-renames", "--untracked-files=all", "--",
                          relative], cwd=cwd,
                         capture_output=True, text=True).stdout
    return sorted({entry_of(item[3:], relative) for item in out.split("\0") if len(item) > 3})
