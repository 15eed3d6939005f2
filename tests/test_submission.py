"""denoisers.store.submission: what a session's commits cost to submit, and store commits held within a budget.

The references are the byte sizes of the files the tests write (a diff costs the old plus the new file of every
changed path, a pack the new files), not git's own accounting."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from denoisers.store.session import commit_store, uncommitted_entries
from denoisers.store.submission import (MIB, SubmissionBudget, entry_of, session_base, submission_report)


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout


@pytest.fixture()
def repo(tmp_path: Path, monkeypatch) -> Path:
    for role in ("AUTHOR", "COMMITTER"):
        monkeypatch.setenv(f"GIT_{role}_NAME", "t")
        monkeypatch.setenv(f"GIT_{role}_EMAIL", "t@t")
    origin = tmp_path / "origin"
    origin.mkdir()
    _git(origin, "init", "-q", "-b", "main")
    (origin / "README").write_text("landed\n")
    _git(origin, "add", "README")
    _git(origin, "commit", "-q", "-m", "landed")
    _git(tmp_path, "clone", "-q", str(origin), "work")
    return tmp_path / "work"


def _write(path: Path, size: int, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(os.urandom(size) if seed else bytes((i * 7 + 1) % 251 for i in range(size)))
    return path


def _commit_all(repo: Path, message: str) -> None:
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", message)


def test_a_session_is_the_commits_after_where_its_checkout_began(repo: Path) -> None:
    landed = _git(repo, "rev-parse", "HEAD").strip()
    assert session_base(repo) == landed
    _write(repo / "a.bin", 10)
    _commit_all(repo, "one")
    assert session_base(repo) == landed            # the reflog's oldest entry, not HEAD
    assert SubmissionBudget.measure(repo).commits == 1


def test_diffs_count_the_old_and_new_file_and_packs_the_new_ones(repo: Path) -> None:
    _write(repo / "store" / "checkpoints" / "x" / "k" / "state.pt", 1000, seed=1)
    _commit_all(repo, "add 1000")                  # diff 1000, pack 1000
    _write(repo / "store" / "checkpoints" / "x" / "k" / "state.pt", 1500, seed=2)
    _commit_all(repo, "replace by 1500")           # diff 1000 + 1500, pack 1500
    (repo / "store" / "checkpoints" / "x" / "k" / "state.pt").unlink()
    _commit_all(repo, "remove")                    # diff 1500: an added then removed file counts twice
    budget = SubmissionBudget.measure(repo)
    assert (budget.commits, budget.diff_bytes, budget.pack_bytes) == (3, 1000 + 2500 + 1500, 1000 + 1500)
    text, within = submission_report(repo, largest=1)
    assert within and "3 commits" in text and "replace by 1500" in text.splitlines()[1]


def test_the_report_says_when_the_commits_pass_the_limits(repo: Path, monkeypatch) -> None:
    import denoisers.store.submission as submission

    _write(repo / "big.bin", 3000, seed=1)
    _commit_all(repo, "big")
    monkeypatch.setattr(submission, "DIFF_LIMIT_BYTES", 2000)
    text, within = submission_report(repo)
    assert not within and "PAST THE LIMITS" in text


def test_store_entries_are_their_kind_and_id() -> None:
    assert entry_of("store/models/afn/abc/best.pt", "store") == "store/models/afn"
    assert entry_of("store/budget.json", "store") == "store/budget.json"


def test_a_keep_past_the_budget_commits_models_first_and_leaves_the_rest_on_disk(repo: Path) -> None:
    _write(repo / "store" / "checkpoints" / "kpcn" / "k" / "state.pt", 40_000, seed=1)
    _commit_all(repo, "an earlier keep")                         # 40 000 of the budget spent
    _write(repo / "code.py", 10)
    _git(repo, "add", "code.py")                                 # staged by hand: not the store's to commit
    _write(repo / "store" / "models" / "afn" / "k" / "best.pt", 20_000, seed=2)
    _write(repo / "store" / "checkpoints" / "kpcn" / "k" / "state.pt", 40_000, seed=3)   # a replaced checkpoint
    _write(repo / "store" / "checkpoints" / "afn2" / "k" / "state.pt", 30_000, seed=4)
    budget = SubmissionBudget.measure(repo, limit_mib=100_000 / MIB)
    assert budget.diff_bytes == 40_000
    assert commit_store(repo / "store", "keep", cwd=repo, budget=budget)
    # 40 000 + 20 000 (the model) + 30 000 (afn2's checkpoint) fit 100 000; kpcn's replacement (80 000) does not.
    subject = _git(repo, "log", "-1", "--format=%s").strip()
    assert subject == "keep (left on disk for the submission budget: store/checkpoints/kpcn)"
    committed = _git(repo, "show", "--name-only", "--format=", "HEAD").split()
    assert committed == \
        ["store/checkpoints/afn2/k/state.pt", "store/models/afn/k/best.pt"]
    assert _git(repo, "diff", "--cached", "--name-only").split() == ["code.py"]
    assert uncommitted_entries(repo / "store", cwd=repo) == ["store/checkpoints/kpcn"]
    assert SubmissionBudget.measure(repo).diff_bytes == 90_000             # code.py is staged, not committed
    # Nothing fits any more: no commit, the files stay as they are.
    head = _git(repo, "rev-parse", "HEAD")
    full = SubmissionBudget.measure(repo, limit_mib=100_000 / MIB)
    assert not commit_store(repo / "store", "keep", cwd=repo, budget=full)
    assert _git(repo, "rev-parse", "HEAD") == head
    assert (repo / "store" / "checkpoints" / "kpcn" / "k" / "state.pt").stat().st_size == 40_000
    # Without a budget everything goes in.
    assert commit_store(repo / "store", "keep", cwd=repo)
    assert uncommitted_entries(repo / "store", cwd=repo) == []


def test_interval_keeps_leave_room_for_the_last_keep_to_replace_the_checkpoint(repo: Path) -> None:
    """A 20 000-byte checkpoint replaced at every keep, budget 100 000: each interval keep commits it only while
    40 000 (its replacement: old + new) stay free for the end keep, which then fits."""
    state = repo / "store" / "checkpoints" / "kpcn" / "k" / "state.pt"

    def keep(seed: int, final: bool) -> bool:
        _write(state, 20_000, seed=seed)
        budget = SubmissionBudget.measure(repo, limit_mib=100_000 / MIB)
        return commit_store(repo / "store", "keep", cwd=repo, budget=budget, reserve_for_end=not final)

    assert keep(1, final=False)                    # 20 000 spent, 40 000 kept free: 60 000
    assert keep(2, final=False)                    # + 40 000 = 60 000 spent, 40 000 kept free: 100 000
    assert not keep(3, final=False)                # + 40 000 would leave no room for the end: left on disk
    assert uncommitted_entries(repo / "store", cwd=repo) == ["store/checkpoints/kpcn"]
    assert keep(4, final=True)                     # the end keep takes the room: 100 000
    assert SubmissionBudget.measure(repo).diff_bytes == 100_000
    assert uncommitted_entries(repo / "store", cwd=repo) == []
