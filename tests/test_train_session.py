"""denoisers.store.session: a training run stopped at its deadline, then what finished published and what moved
checkpointed (the store calls are recorded here; tests/test_store.py covers publish and checkpoint themselves)."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from denoisers.store.session import keep, resolved_config, run_until, store_command


def test_a_run_past_its_deadline_is_stopped_and_one_before_it_is_not(tmp_path: Path) -> None:
    started = time.monotonic()
    code, stopped = run_until([sys.executable, "-c", "import time; time.sleep(120)"], 1.0, cwd=tmp_path)
    assert (code, stopped) == (None, True) and time.monotonic() - started < 30
    # A child of the run (a training job) goes with it: the whole process group is stopped.
    marker = tmp_path / "child.pid"
    script = (f"import subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', 'import time; "
              f"time.sleep(120)']); open({str(marker)!r}, 'w').write(str(p.pid)); time.sleep(120)")
    code, stopped = run_until([sys.executable, "-c", script], 3.0, cwd=tmp_path)
    assert stopped
    child = int(marker.read_text())
    time.sleep(0.5)
    assert not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text().split()[2]
    assert run_until([sys.executable, "-c", "raise SystemExit(3)"], 30.0, cwd=tmp_path) == (3, False)


def _touch(path: Path, text: str = "{}", age_s: float = 0.0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    if age_s:
        old = time.time() - age_s
        os.utime(path, (old, old))
    return path


def test_finished_models_are_published_and_moved_runs_checkpointed(tmp_path: Path) -> None:
    out = tmp_path / "results"
    since = time.time() - 100
    _touch(out / ".config" / "old.yaml", age_s=1000)
    config = _touch(out / ".config" / "abc.yaml")
    _touch(out / "models" / "done" / "summary.json")                                   # finished this session
    _touch(out / "models" / "installed" / "summary.json", '{"installed_from_store": true}')
    _touch(out / "models" / ".work" / "partway-0123" / "checkpoint.pt")                 # moved, not finished
    _touch(out / "models" / ".work" / "idle-0123" / "checkpoint.pt", age_s=1000)       # from an earlier session
    _touch(out / "models" / ".work" / "full-0123" / "checkpoint.pt")                   # the twin's run, going on
    _touch(out / "models" / "full_half" / "summary.json")                              # ...whose twin finished
    # A twin that trained in the run of a full model the store holds: no checkpoint of that run is attempted.
    _touch(out / "models" / ".work" / "stored-0123" / "checkpoint.pt")
    calls: list[list[str]] = []

    def store(args: list[str]) -> int:
        calls.append(args)
        return 0

    assert resolved_config(out, since) == config
    published, checkpointed, untouched = keep(out, ["done", "installed", "partway", "idle", "full_half", "full",
                                                    "stored_half"], since, store, is_stored={"stored"}.__contains__)
    assert published == ["done", "full_half"] and checkpointed == ["partway", "full"]
    assert untouched == ["installed", "idle", "stored_half"]
    assert not any("stored" in call for call in calls)
    assert calls[0] == ["publish", "--config", str(config), "--model-id", "done"]
    assert ["checkpoint", "--config", str(config), "--model-id", "partway"] in calls


def test_without_model_ids_a_session_keeps_every_training_of_the_config(tmp_path: Path) -> None:
    """No ids: the run targets the stage ``train`` and the session looks at every training the resolved config
    has (seed replicas and twins included, variants that reuse another model's weights left out)."""
    import yaml

    from denoisers.store.session import configured_trainings, train_session
    from denoisers.training.models import same_training_as, trained_model_specs
    from scenegen.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "smoke.yaml")
    cfg["training"].update(seeds=2, half_budget=True)
    every = [spec.id for spec in trained_model_specs(cfg)]
    reused = [model_id for model_id in every if same_training_as(cfg, model_id)]
    assert reused and "rae_seed1" in every and "rae_seed1_half" in every     # the case is not empty

    out = tmp_path / "results"
    config_text = yaml.safe_dump(cfg, sort_keys=False)
    # The stand-in run writes the resolved config, as the workflow's onstart does, and trains nothing.
    script = (f"import pathlib; p = pathlib.Path({str(out / '.config' / 'abc.yaml')!r}); "
              f"p.parent.mkdir(parents=True); p.write_text({config_text!r})")
    result = train_session([], 1.0, output_dir=out, run_command=[sys.executable, "-c", script])
    assert result.returncode == 0 and not result.stopped_at_deadline
    assert configured_trainings(out / ".config" / "abc.yaml") == [m for m in every if m not in reused]
    assert result.untouched == [m for m in every if m not in reused]
    assert result.published == [] and result.checkpointed == []


def test_models_the_store_held_before_are_reported_apart_from_the_untouched(tmp_path: Path) -> None:
    """The 2026-12-07 session listed ``afn_nar_half``, stored a session earlier, among the untouched."""
    from denoisers.store.session import train_session

    out = tmp_path / "results"
    script = (f"import pathlib; p = pathlib.Path({str(out / '.config' / 'abc.yaml')!r}); "
              "p.parent.mkdir(parents=True); p.write_text('output_dir: x')")
    result = train_session(["idle", "stored"], 1.0, output_dir=out, run_command=[sys.executable, "-c", script],
                           is_stored={"stored"}.__contains__)
    assert result.returncode == 0
    assert result.untouched == ["idle"] and result.already_stored == ["stored"]


def test_given_ids_are_kept_with_their_half_budget_twins() -> None:
    """A model's target trains its twin too (the 2026-12-06 Isik sessions trained twins they did not publish)."""
    from denoisers.store.session import kept_ids

    configured = ["rae", "rae_half", "rae_seed1", "rae_seed1_half", "kpcn"]
    assert kept_ids([], configured) == configured
    assert kept_ids(["rae_seed1"], configured) == ["rae_seed1", "rae_seed1_half"]
    assert kept_ids(["rae_seed1", "rae_seed1_half", "kpcn"], configured) == ["rae_seed1", "rae_seed1_half", "kpcn"]
    assert kept_ids(["kpcn", "other"], configured) == ["kpcn", "other"]


def test_a_refused_store_command_does_not_refuse_the_next_ones(tmp_path: Path, capsys) -> None:
    """The session's store commands write to the session's log through a pipe: a failed one leaves no retry-gate
    marker beside that log (scenegen.retry_gate), so the next store command still runs (2026-12-06: one refused
    checkpoint made the session publish nothing)."""
    from scenegen.retry_gate import EXIT_NOT_RETRIED, marker_for

    log = tmp_path / "session.out"
    args = ["checkpoint", "--config", str(tmp_path / "missing.yaml"), "--model-id", "rae"]
    saved = os.dup(2)
    try:
        with log.open("w") as stream:
            os.dup2(stream.fileno(), 2)
            codes = [store_command(args), store_command(args)]
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    assert codes[0] != 0 and codes[1] == codes[0] != EXIT_NOT_RETRIED, codes
    assert not marker_for(log).exists()
    assert "missing.yaml" in capsys.readouterr().err      # its message is passed on (to the session's log)


def test_stored_finished_asks_the_configs_store(tmp_path: Path) -> None:
    """The default of keep()'s ``is_stored``: the store named by the resolved config, under its key."""
    import yaml

    from denoisers.store.session import stored_finished
    from scenegen.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "config.yaml")
    config = tmp_path / "resolved.yaml"
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert stored_finished(config)("rae")                     # committed in store/ (docs/model-store.md)
    cfg["store"]["path"] = str(tmp_path / "empty_store")
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert not stored_finished(config)("rae")


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_a_paused_group_goes_on_and_a_process_paused_by_hand_stays_paused(tmp_path: Path) -> None:
    """The interval keep stops the run's group while it copies checkpoints, then continues only what it stopped: a
    trainer paused with ``kill -STOP`` for the test suite is not woken by it."""
    import signal
    import subprocess

    from denoisers.store.session import group_pids, paused_group

    marker = tmp_path / "children"
    script = (f"import subprocess, sys, time; ps = [subprocess.Popen([sys.executable, '-c', 'import time; "
              f"time.sleep(60)']) for _ in range(2)]; open({str(marker)!r}, 'w').write(' '.join(str(p.pid) for p in ps));"
              f" time.sleep(60)")
    run = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    try:
        for _ in range(100):
            if marker.exists() and marker.read_text():
                break
            time.sleep(0.1)
        awake, by_hand = (int(pid) for pid in marker.read_text().split())
        assert set(group_pids(run.pid)) == {run.pid, awake, by_hand}
        os.kill(by_hand, signal.SIGSTOP)
        time.sleep(0.2)
        seen: dict[int, str] = {}
        paused_group(run.pid, lambda: seen.update({pid: _state(pid) for pid in (run.pid, awake, by_hand)}))
        assert seen == {run.pid: "T", awake: "T", by_hand: "T"}
        time.sleep(0.2)
        assert _state(run.pid) != "T" and _state(awake) != "T" and _state(by_hand) == "T"
    finally:
        os.killpg(run.pid, signal.SIGKILL)
        run.wait()


def test_commit_store_commits_the_store_and_nothing_else(tmp_path: Path, monkeypatch) -> None:
    import subprocess

    from denoisers.store.session import commit_store

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True, text=True).stdout

    git("init", "-q")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "start")
    _touch(tmp_path / "code.py", "staged, not the store's")
    git("add", "code.py")
    _touch(tmp_path / "store" / "models" / "rae" / "summary.json")
    _touch(tmp_path / "store" / "checkpoints" / "afn" / "meta.json")
    for role in ("AUTHOR", "COMMITTER"):
        monkeypatch.setenv(f"GIT_{role}_NAME", "t")
        monkeypatch.setenv(f"GIT_{role}_EMAIL", "t@t")
    assert commit_store(tmp_path / "store", "keep: rae", cwd=tmp_path)
    assert git("show", "--name-only", "--format=%s", "HEAD").split() == \
        ["keep:", "rae", "store/checkpoints/afn/meta.json", "store/models/rae/summary.json"]
    assert git("diff", "--cached", "--name-only").split() == ["code.py"]        # still staged, not committed
    assert not commit_store(tmp_path / "store", "nothing new", cwd=tmp_path)
    # A checkpoint replaced by the finished model: the removal is committed too.
    import shutil

    shutil.rmtree(tmp_path / "store" / "checkpoints")
    assert commit_store(tmp_path / "store", "keep: afn finished", cwd=tmp_path)
    assert "store/checkpoints/afn/meta.json" not in git("ls-files")


def test_interval_keeps_run_while_the_run_goes_on_and_each_is_committed(tmp_path: Path, monkeypatch) -> None:
    """``--keep-every``: the session keeps (publishes / checkpoints) during the run, not only at its end, commits
    each keep with ``--commit``, and publishes a model once."""
    import yaml

    import denoisers.store.session as session
    from scenegen.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "smoke.yaml")
    out = tmp_path / "results"
    config_text = yaml.safe_dump(cfg, sort_keys=False)
    run_start = tmp_path / "run_start"
    script = (f"import pathlib, time; pathlib.Path({str(run_start)!r}).write_text(repr(time.time())); "
              f"p = pathlib.Path({str(out / '.config' / 'abc.yaml')!r}); "
              f"p.parent.mkdir(parents=True); p.write_text({config_text!r}); time.sleep(4)")
    keeps: list[tuple[float, list[str]]] = []
    commits: list[str] = []

    def fake_keep(output_dir, model_ids, since, store_command, **_):
        keeps.append((time.time(), list(model_ids)))
        return (["rae"] if "rae" in model_ids else []), ["afn"], []

    monkeypatch.setattr(session, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(session, "keep", fake_keep)
    budgets: list = []

    reserves: list[bool] = []

    def fake_commit(root, message, cwd=None, budget=None, reserve_for_end=False):
        budgets.append(budget)
        reserves.append(reserve_for_end)
        return commits.append(message) or True

    monkeypatch.setattr(session, "commit_store", fake_commit)
    monkeypatch.setattr(session, "uncommitted_entries", lambda root: [])
    result = session.train_session(["rae", "afn"], 1.0, output_dir=out, keep_every_minutes=1.0 / 60,
                                   commit=True, run_command=[sys.executable, "-c", script], submission_base="HEAD")
    assert result.returncode == 0 and not result.stopped_at_deadline
    started = float(run_start.read_text())
    assert len(keeps) >= 3 and keeps[0][0] - started < 3.5           # at least one keep while the run went on
    assert keeps[0][1] == ["rae", "afn"] and all(ids == ["afn"] for _, ids in keeps[1:])
    assert result.published == ["rae"] and result.checkpointed == ["afn"]
    assert len(commits) == len(keeps) and "published rae" in commits[0] and "(end keep)" in commits[-1]
    assert all("interval keep" in message for message in commits[:-1])
    # Every keep is committed within the session's submission budget, measured from the given base afresh.
    assert all(b is not None and b.commits == 0 and b.limit_bytes == 192 * 1024 * 1024 for b in budgets)
    # Interval keeps leave room for the end keep; the end keep spends it.
    assert reserves == [True] * (len(commits) - 1) + [False]


def _checkpoint_of_another_arithmetic(tmp_path: Path) -> tuple[dict, Path]:
    """The tiny store config (tests/test_store.py) with 2 seeds and twins, written to a YAML file, and a stored
    part-way checkpoint of its ``rae_seed1`` run whose recorded arithmetic this machine does not resolve."""
    import json

    import yaml

    from denoisers.store import ModelStore, checkpoint_key
    from denoisers.store.keys import short
    from tests.test_store import store_config

    cfg = store_config(tmp_path, steps=4)
    cfg["training"]["models"] = cfg["training"]["models"][:1]
    cfg["training"].update(seeds=2, half_budget=True)
    folder = ModelStore.of(cfg).root / "checkpoints" / "rae_seed1" / short(checkpoint_key(cfg, "rae_seed1"))
    folder.mkdir(parents=True)
    (folder / "meta.json").write_text(json.dumps({"step": 3, "compute": {"precision": "bf16-elsewhere",
                                                                         "channels_last": True}}))
    config_file = tmp_path / "config.yaml"
    config_file.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return cfg, config_file


def test_a_run_part_way_in_another_arithmetic_is_skipped_or_restarted_on_purpose(tmp_path: Path,
                                                                                   monkeypatch) -> None:
    """A run whose stored checkpoint this machine cannot continue (another precision or layout) would start afresh
    and have its keeps refused: the session skips it and its twin, saying so, or with
    ``restart_other_arithmetic`` trains it and lets its checkpoint replace the stored one."""
    import denoisers.store.session as session
    from denoisers.store.session import other_arithmetic

    cfg, config_file = _checkpoint_of_another_arithmetic(tmp_path)
    found = other_arithmetic(cfg, ["rae", "rae_half", "rae_seed1", "rae_seed1_half", "not_a_model"])
    assert sorted(found) == ["rae_seed1", "rae_seed1_half"]
    assert "step 3" in found["rae_seed1"] and "bf16-elsewhere channels-last" in found["rae_seed1"]

    keeps: list[dict] = []

    def fake_keep(output_dir, model_ids, since, store_command, **kwargs):
        keeps.append({"ids": list(model_ids), **kwargs})
        return [], [], list(model_ids)

    monkeypatch.setattr(session, "keep", fake_keep)
    out = tmp_path / "results"
    (out / ".config").mkdir(parents=True)
    (out / ".config" / "abc.yaml").write_text(config_file.read_text())
    args = ["--configfile", str(config_file)]
    refused = session.train_session(["rae_seed1"], 1.0, args, output_dir=out,
                                    run_command=[sys.executable, "-c", "raise SystemExit(7)"])
    assert (refused.returncode, refused.skipped, keeps) == (None, ["rae_seed1"], [])     # nothing ran
    result = session.train_session(["rae", "rae_seed1"], 1.0, args, output_dir=out,
                                   run_command=[sys.executable, "-c", "pass"])
    assert result.returncode == 0 and result.skipped == ["rae_seed1"]
    assert keeps[-1]["ids"] == ["rae", "rae_half"] and keeps[-1]["replace_other_arithmetic"] == []
    restarted = session.train_session(["rae_seed1"], 1.0, args, output_dir=out, restart_other_arithmetic=True,
                                      run_command=[sys.executable, "-c", "pass"])
    assert restarted.skipped == [] and keeps[-1]["ids"] == ["rae_seed1", "rae_seed1_half"]
    assert keeps[-1]["replace_other_arithmetic"] == ["rae_seed1"]


def test_the_command_says_when_every_model_is_skipped(tmp_path: Path) -> None:
    """``python -m denoisers train-session``: with only models of another arithmetic it runs nothing and exits 1."""
    import subprocess

    _, config_file = _checkpoint_of_another_arithmetic(tmp_path)
    repo = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-m", "denoisers", "train-session", "--minutes", "1", "--snakemake",
                           f"--configfile {config_file}", "rae_seed1_half"], cwd=repo, capture_output=True, text=True)
    assert done.returncode == 1, done.stderr[-2000:]
    assert "rae_seed1_half: the stored checkpoint of rae_seed1 (step 3)" in done.stderr
    assert "nothing to train on this machine: skipped rae_seed1_half" in done.stderr
    assert not (tmp_path / "results").exists()


def test_the_arithmetic_check_reads_the_config_with_its_command_line_overrides(tmp_path: Path) -> None:
    """``--config`` overrides in the session's Snakemake arguments change what the run trains, so the check of stored
    checkpoints reads them too: with one seed in the file ``rae_seed1`` is no training of the config; with
    ``--config 'training={seeds: 2}'`` it is, and its checkpoint of another arithmetic is found."""
    import yaml

    from denoisers.store.session import other_arithmetic, session_config
    from scenegen.config import ConfigError

    cfg, config_file = _checkpoint_of_another_arithmetic(tmp_path)
    written = yaml.safe_load(config_file.read_text())
    written["training"]["seeds"] = 1
    config_file.write_text(yaml.safe_dump(written, sort_keys=False))
    plain = session_config(["--configfile", str(config_file), "--cores", "2"])
    assert plain["training"]["seeds"] == 1 and other_arithmetic(plain, ["rae_seed1"]) == {}
    overridden = session_config(["--configfile", str(config_file), "--config", "training={seeds: 2}", "--cores", "2"])
    assert overridden["training"]["seeds"] == 2                  # an int, as the workflow parses it
    assert list(other_arithmetic(overridden, ["rae_seed1"])) == ["rae_seed1"]
    with pytest.raises(ConfigError, match=r"(?s)with --config training=\{seeds: many\}.*training\.seeds"):
        session_config(["--configfile", str(config_file), "--config", "training={seeds: many}"])


def test_runs_that_continue_here_go_first_unless_the_arguments_prioritize(tmp_path: Path) -> None:
    """A run part-way in the store with this machine's arithmetic is prioritized (its twin names the same run);
    one of another arithmetic, a stored model and one not started are not; given ``--prioritize`` wins."""
    import json

    from denoisers.store import ModelStore, checkpoint_key
    from denoisers.store.keys import short
    from denoisers.store.session import continued_here, priority_args
    from denoisers.training.models import model_spec
    from denoisers.training.precision import resolve_compute

    cfg, _ = _checkpoint_of_another_arithmetic(tmp_path)      # rae_seed1: part-way in another arithmetic
    here = resolve_compute(model_spec(cfg, "rae").compute).fingerprint()
    folder = ModelStore.of(cfg).root / "checkpoints" / "rae" / short(checkpoint_key(cfg, "rae"))
    folder.mkdir(parents=True)
    (folder / "meta.json").write_text(json.dumps({"step": 3, "compute": here}))
    ids = ["rae", "rae_half", "rae_seed1", "rae_seed1_half"]
    assert continued_here(cfg, ids) == ["rae"]
    assert continued_here(cfg, ["rae_half"]) == ["rae"] and continued_here(cfg, ["rae_seed1"]) == []
    out = tmp_path / "results"
    assert priority_args(cfg, ids, out, ["--configfile", "c.yaml"]) == ["--prioritize", f"{out}/models/rae"]
    assert priority_args(cfg, ids, out, ["--prioritize", "x"]) == []
    assert priority_args(cfg, ids, out, ["-P", "x"]) == []
    assert priority_args(cfg, ["rae_seed1"], out, []) == []
