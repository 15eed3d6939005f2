"""What a session's commits cost to submit, so that store commits never make a submission that cannot land.

A session's stop submits the commits on its branch after the commit the checkout was created at (its *base*), and
the submission is refused whole when they pack to more than 512 MiB or when their diffs, added up as text, pass
256 MiB (a file added in one commit and removed in a later one counts twice). A training session's keeps replace
checkpoints every interval, and each replacement's diff holds the old and the new file: on 2026-12-07 six keeps of
a 27 MB KPCN checkpoint beside other keeps passed the diff limit, and that session's work was lost.

Sizes here are upper bounds read from git's objects, no diff is made: a commit's diff costs the old blob plus the
new blob of every path it changes (a binary rewritten, or a text file rewritten, shows every old line removed and
every new line added; a small text edit is overcounted, which errs on the safe side), its pack the new blobs
uncompressed. :class:`SubmissionBudget` holds what the commits since the base cost and a limit below the
workplace's; :func:`fit_staged` unstages whole store entries (``<store>/<kind>/<id>``) that would pass it, finished
models first in, checkpoints last, so that what is committed stays a consistent store and the rest stays on disk;
an interval keep also leaves room for the last keep to replace the session's checkpoints once more.
"""
from __future__ import annotations

import subprocess
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

MIB = 1024 * 1024
#: The workplace's limits on one submission: the diffs added up as text, and the commits packed.
DIFF_LIMIT_BYTES = 256 * MIB
PACK_LIMIT_BYTES = 512 * MIB
#: What store commits may bring a submission to by default: three quarters of the diff limit, the rest left for
#: the session's code and documents.
DEFAULT_BUDGET_MIB = 192.0
#: Commit order of the store's kinds when not everything fits: a finished model before its checkpoint's removal or
#: a part-way state (another session can redo a checkpoint's interval, not a finished model's whole run).
KIND_ORDER = ("models", "references", "tuning", "checkpoints")

_NULL_OID = "0" * 40


def _git(args: Sequence[str], cwd: Path, stdin: str | None = None, env: Mapping[str, str] | None = None) -> str:
    return subprocess.run(["git", *args], cwd=cwd, input=stdin, capture_output=True, text=True, check=True,
                          env=None if env is None else dict(env)).stdout


@dataclass(frozen=True)
class Change:
    """One path a diff changes: its old and new blob (None: absent) and their sizes in bytes."""

    path: str
    old_bytes: int
    new_bytes: int
    new_oid: str | None

    @property
    def diff_bytes(self) -> int:
        return self.old_bytes + self.new_bytes


def _parse_raw(text: str) -> list[tuple[str, str | None, str | None]]:
    """(path, old oid, new oid) of ``git diff --raw -z --no-renames --no-abbrev`` output; None for an absent side
    and for a submodule (not a blob)."""
    fields = text.split("\0")
    entries = []
    for head, path in zip(fields[0::2], fields[1::2]):
        if not head.startswith(":"):
            continue
        old_mode, new_mode, old_oid, new_oid = head[1:].split()[:4]
        blob = lambda mode, oid: None if oid == _NULL_OID or mode.startswith("16") else oid  # noqa: E731
        entries.append((path, blob(old_mode, old_oid), blob(new_mode, new_oid)))
    return entries


def blob_sizes(oids: Iterable[str], cwd: Path) -> dict[str, int]:
    """Sizes in bytes of the objects ``oids`` (``git cat-file --batch-check``)."""
    oids = sorted(set(oids))
    if not oids:
        return {}
    out = _git(["cat-file", "--batch-check=%(objectname) %(objectsize)"], cwd, stdin="\n".join(oids) + "\n")
    return {oid: int(size) for oid, size in (line.split() for line in out.splitlines() if not line.endswith("missing"))}


def _changes(raw: str, cwd: Path) -> list[Change]:
    entries = _parse_raw(raw)
    sizes = blob_sizes([oid for _, old, new in entries for oid in (old, new) if oid], cwd)
    return [Change(path, sizes.get(old, 0) if old else 0, sizes.get(new, 0) if new else 0, new)
            for path, old, new in entries]


def commit_changes(commit: str, cwd: Path) -> list[Change]:
    """What ``commit`` changes against its first parent (against nothing for a root commit)."""
    parents = _git(["rev-list", "--parents", "-n", "1", commit], cwd).split()[1:]
    base = parents[0] if parents else _git(["hash-object", "-t", "tree", "/dev/null"], cwd).strip()
    return _changes(_git(["diff", "--raw", "-z", "--no-renames", "--no-abbrev", base, commit], cwd), cwd)


def staged_changes(cwd: Path, paths: Sequence[str] = (), env: Mapping[str, str] | None = None) -> list[Change]:
    """What the index (``env``'s GIT_INDEX_FILE, default the checkout's) holds against HEAD under ``paths``
    (default everywhere)."""
    raw = _git(["diff", "--cached", "--raw", "-z", "--no-renames", "--no-abbrev", "--", *paths], cwd, env=env)
    return _changes(raw, cwd)


def session_base(cwd: Path) -> str:
    """The commit this checkout's branch was created at: the oldest entry of the branch's reflog (a checkout made
    for a session starts there, so the commits after it are what its stop submits); HEAD where there is no
    reflog."""
    branch = _git(["rev-parse", "--abbrev-ref", "HEAD"], cwd).strip()
    try:
        log = _git(["reflog", "show", "--format=%H", branch, "--"], cwd).split() if branch != "HEAD" else []
    except subprocess.CalledProcessError:
        log = []
    return log[-1] if log else _git(["rev-parse", "HEAD"], cwd).strip()


@dataclass
class SubmissionBudget:
    """The commits after ``base`` and what they cost: ``diff_bytes`` (old + new blob of every changed path, summed
    over the commits) and ``pack_bytes`` (every blob they add, once, uncompressed), against a diff budget
    ``limit_bytes`` (and the pack limit scaled alike)."""

    base: str
    limit_bytes: int
    diff_bytes: int = 0
    pack_bytes: int = 0
    commits: int = 0
    per_commit: list[tuple[int, str]] = field(default_factory=list, repr=False)   # (diff bytes, commit)
    _blobs: set[str] = field(default_factory=set, repr=False)

    @classmethod
    def measure(cls, cwd: Path, base: str | None = None, limit_mib: float = DEFAULT_BUDGET_MIB) -> SubmissionBudget:
        base = base or session_base(cwd)
        budget = cls(_git(["rev-parse", base], cwd).strip(), int(limit_mib * MIB))
        for commit in _git(["rev-list", "--reverse", f"{budget.base}..HEAD"], cwd).split():
            changes = commit_changes(commit, cwd)
            budget.add(changes)
            budget.commits += 1
            budget.per_commit.append((sum(c.diff_bytes for c in changes), commit))
        return budget

    @property
    def pack_limit_bytes(self) -> int:
        return int(self.limit_bytes * PACK_LIMIT_BYTES / DIFF_LIMIT_BYTES)

    def cost(self, changes: Sequence[Change]) -> tuple[int, int]:
        """(diff bytes, new pack bytes) that ``changes`` would add."""
        new = {c.new_oid: c.new_bytes for c in changes if c.new_oid and c.new_oid not in self._blobs}
        return sum(c.diff_bytes for c in changes), sum(new.values())

    def fits(self, changes: Sequence[Change], room_bytes: int = 0) -> bool:
        """Whether ``changes`` fit, leaving ``room_bytes`` of diffs (and of pack) unspent."""
        diff, pack = self.cost(changes)
        return (self.diff_bytes + diff + room_bytes <= self.limit_bytes
                and self.pack_bytes + pack + room_bytes // 2 <= self.pack_limit_bytes)

    def add(self, changes: Sequence[Change]) -> None:
        diff, pack = self.cost(changes)
        self.diff_bytes += diff
        self.pack_bytes += pack
        self._blobs.update(c.new_oid for c in changes if c.new_oid)

    def describe(self) -> str:
        return (f"{self.commits} commits since {self.base[:12]}: diffs {self.diff_bytes / MIB:.1f} MiB of the "
                f"{self.limit_bytes / MIB:.3g} MiB budget (limit {DIFF_LIMIT_BYTES // MIB}), packed at most "
                f"{self.pack_bytes / MIB:.1f} MiB (limit {PACK_LIMIT_BYTES // MIB})")


def entry_of(path: str, store_prefix: str) -> str:
    """The store entry a path belongs to: ``<store>/<kind>/<id>`` (the path itself outside such a folder)."""
    relative = path[len(store_prefix):].lstrip("/") if path.startswith(store_prefix) else path
    parts = relative.split("/")
    return f"{store_prefix}/{'/'.join(parts[:2])}" if len(parts) > 2 else path


def _kind(entry: str, store_prefix: str) -> str:
    return entry[len(store_prefix):].lstrip("/").split("/")[0]


def fit_staged(budget: SubmissionBudget, store_prefix: str, cwd: Path, env: Mapping[str, str] | None = None,
               reserve_for_end: bool = False) -> tuple[list[str], list[str]]:
    """Keep staged only the store entries that fit ``budget``, whole entries in :data:`KIND_ORDER` (then by name);
    unstage the others (their files stay on disk) in the index ``env`` names (default the checkout's). Returns
    (entries kept staged, entries held back); the budget counts the kept ones.

    ``reserve_for_end`` (an interval keep): a checkpoint goes in only while the budget keeps room for the session's
    last keep to replace every checkpoint the session has committed once more (twice its bytes: the old and the
    new file), so that interval keeps of a large checkpoint cannot spend what its last state needs; finished models
    are not held back for that room."""
    groups: dict[str, list[Change]] = {}
    for change in staged_changes(cwd, [store_prefix], env=env):
        groups.setdefault(entry_of(change.path, store_prefix), []).append(change)
    reserve: dict[str, int] = {}     # checkpoint entry -> the bytes its replacement at the last keep costs
    if reserve_for_end:
        raw = _git(["diff", "--raw", "-z", "--no-renames", "--no-abbrev", budget.base, "HEAD", "--",
                    f"{store_prefix}/checkpoints"], cwd)
        for change in _changes(raw, cwd):
            entry = entry_of(change.path, store_prefix)
            reserve[entry] = reserve.get(entry, 0) + 2 * change.new_bytes

    def order(entry: str) -> tuple[int, str]:
        kind = _kind(entry, store_prefix)
        return (KIND_ORDER.index(kind) if kind in KIND_ORDER else len(KIND_ORDER), entry)

    kept, held = [], []
    for entry in sorted(groups, key=order):
        changes = groups[entry]
        room = 0
        if reserve_for_end and _kind(entry, store_prefix) == "checkpoints":
            after = {**reserve, entry: 2 * sum(c.new_bytes for c in changes)}
            room = sum(after.values())
        if budget.fits(changes, room):
            budget.add(changes)
            if room:
                reserve = after
            kept.append(entry)
        else:
            held.append(entry)
    if held:
        _git(["reset", "-q", "--", *held], cwd, env=env)
    return kept, held


def submission_report(cwd: Path, base: str | None = None, largest: int = 5) -> tuple[str, bool]:
    """Lines that say what the commits after ``base`` (default :func:`session_base`) cost against the workplace's
    limits, with the ``largest`` costliest commits; and whether they are within both limits."""
    budget = SubmissionBudget.measure(cwd, base, DIFF_LIMIT_BYTES / MIB)
    within = budget.diff_bytes <= DIFF_LIMIT_BYTES and budget.pack_bytes <= PACK_LIMIT_BYTES
    lines = [f"{budget.commits} commits since {budget.base[:12]}: diffs {budget.diff_bytes / MIB:.1f} MiB of "
             f"{DIFF_LIMIT_BYTES // MIB} MiB, new objects at most {budget.pack_bytes / MIB:.1f} MiB of "
             f"{PACK_LIMIT_BYTES // MIB} MiB packed: " + ("within the limits" if within else "PAST THE LIMITS, the "
                                                           "submission would be refused whole")]
    for size, commit in sorted(budget.per_commit, reverse=True)[:largest]:
        subject = _git(["log", "-1", "--format=%s", commit], cwd).strip()
        lines.append(f"  {size / MIB:8.1f} MiB  {commit[:12]}  {subject[:90]}")
    return "\n".join(lines), within
