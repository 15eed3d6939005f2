"""Wall time of a workflow run that was interrupted and resumed, from Snakemake's own logs.

A run of the default DAG outlasts a 3-hour session, so it runs in segments (one ``snakemake`` invocation
each, killed at the session's end and resumed later with ``--rerun-incomplete``), and it is sometimes paused
(``kill -STOP``) while benchmarks need the cores. Summed ``benchmark:`` times then say little: a paused job's
time includes the pause, jobs overlap, and the gaps between sessions are not the DAG's. This script reads the
job start / finish stamps of each invocation's log (``.snakemake/log/*.snakemake.log``) and prints

* per segment: its first and last stamp and its busy wall time (the union of its jobs' intervals, pauses
  removed), i.e. the time the machine spent on this DAG;
* per rule: jobs started, finished, and the summed job time with pauses removed;
* the total busy wall time over all segments: the DAG's wall time if the segments had run back to back.
* core use (``--cores``, each job holding its ``threads:``): core-minutes used, core-minutes left idle while
  some job ran (e.g. one 1-thread training alone on two cores), and the wall time of the same work packed
  onto every core, a floor no job order can beat.

A job still running when its invocation died (no ``Finished``/``Error`` line) ends at its segment's end: the
last ``--heartbeat`` stamp of the unbroken chain of beats after its last log stamp (a file of ISO times written
every minute while the session lives; a gap longer than ``--max-gap`` minutes means the machine was down, and a
beat after it belongs to the next session), or the latest ``--alive`` time before the next segment if later,
else the log's last stamp (an underestimate, said in the output). Work lost at a kill (steps
after a training's last checkpoint) is counted, as it was spent. ``--pause START/END`` (ISO times, repeatable)
removes pause windows; ``--since`` drops segments that started earlier (e.g. before a code change superseded
their work); ``--rule`` / ``--exclude-rule`` count one stage's jobs only (its busy wall time as if it had run
alone; jobs of other stages running beside it in the same segment are not subtracted). ``--superseded
REGEX@TIME`` leaves out the jobs a later change made obsolete (by their ``rule wildcards`` label and start),
e.g. trainings redone after a setting changed; unlike ``--since`` it keeps the rest of those segments.

Usage: python benchmarks/run_wall_time.py .snakemake/log/*.snakemake.log [--since 2026-12-02T03:29]
           [--pause 2026-12-02T03:37:35/2026-12-02T04:15:44 ...] [--heartbeat /path/heartbeat.log]
           [--superseded 'train_denoiser model=rae(_.*)?@2026-12-03T07:39' ...]
"""
from __future__ import annotations

import argparse
import re
from dataclasses import dataclass, field
from collections.abc import Sequence
from datetime import datetime, timedelta
from pathlib import Path

_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]\s*$")
_RULE = re.compile(r"^(?:local)?(?:checkpoint|rule) (\w+):\s*$")
_JOBID = re.compile(r"^\s+jobid: (\d+)\s*$")
_FINISHED = re.compile(r"^Finished job(?:id:)? (\d+)")
_ERROR = re.compile(r"^Error in rule (\w+):\s*$")
_THREADS = re.compile(r"^\s+threads: (\d+)\s*$")
_WILDCARDS = re.compile(r"^\s+wildcards: (.*?)\s*$")

Interval = tuple[datetime, datetime]


@dataclass
class Job:
    """One job of one invocation: ``end`` None while unfinished; ``failed`` if an error line ended it."""
    rule: str
    jobid: int
    start: datetime
    end: datetime | None = None
    failed: bool = False
    threads: int = 1                 # Snakemake prints "threads: N" for N > 1 only
    wildcards: str = ""              # as the log prints them, e.g. "model=rae"

    @property
    def label(self) -> str:
        """``rule wildcards``, e.g. ``train_denoiser model=rae``: what ``--superseded`` patterns match."""
        return f"{self.rule} {self.wildcards}".strip()


@dataclass
class Segment:
    """One ``snakemake`` invocation: its log file, first and last stamps and jobs."""
    name: str
    first: datetime
    last: datetime
    jobs: list[Job] = field(default_factory=list)
    end: datetime | None = None     # when the invocation stopped (heartbeat or last stamp)


def parse_log(text: str, name: str = "log") -> Segment | None:
    """The jobs of one Snakemake log (None when it has no time stamp: e.g. an ``--unlock`` call)."""
    stamp: datetime | None = None
    first = last = None
    jobs: dict[int, Job] = {}
    pending_rule: tuple[str, datetime] | None = None
    announced: Job | None = None     # the job whose announcement block is being read
    in_error = False
    for line in text.splitlines():
        match = _STAMP.match(line)
        if match:
            stamp = datetime.strptime(" ".join(match.group(1).split()), "%a %b %d %H:%M:%S %Y")
            first = first or stamp
            last = stamp
            pending_rule, in_error, announced = None, False, None
            continue
        if stamp is None:
            continue
        if (match := _RULE.match(line)) is not None:
            pending_rule = (match.group(1), stamp)
        elif (match := _ERROR.match(line)) is not None:
            in_error, pending_rule = True, None
        elif (match := _JOBID.match(line)) is not None:
            jobid = int(match.group(1))
            if in_error and jobid in jobs and jobs[jobid].end is None:
                jobs[jobid].end, jobs[jobid].failed = stamp, True
            elif pending_rule is not None and jobid not in jobs:
                jobs[jobid] = Job(pending_rule[0], jobid, pending_rule[1])
                announced = jobs[jobid]
            pending_rule = None
        elif (match := _THREADS.match(line)) is not None and announced is not None:
            announced.threads = int(match.group(1))
        elif (match := _WILDCARDS.match(line)) is not None and announced is not None:
            announced.wildcards = match.group(1)
        elif (match := _FINISHED.match(line)) is not None:
            jobid = int(match.group(1))
            if jobid in jobs and jobs[jobid].end is None:
                jobs[jobid].end = stamp
    if first is None:
        return None
    return Segment(name, first, last, sorted(jobs.values(), key=lambda j: (j.start, j.jobid)))


def union_length(intervals: list[Interval]) -> float:
    """Seconds covered by the union of ``intervals``."""
    total, current = 0.0, None
    for start, end in sorted(intervals):
        if current is None or start > current[1]:
            if current is not None:
                total += (current[1] - current[0]).total_seconds()
            current = [start, end]
        else:
            current[1] = max(current[1], end)
    if current is not None:
        total += (current[1] - current[0]).total_seconds()
    return total


def subtract(interval: Interval, pauses: list[Interval]) -> list[Interval]:
    """``interval`` with the ``pauses`` cut out (a list of disjoint pieces)."""
    pieces = [interval]
    for p_start, p_end in pauses:
        kept = []
        for start, end in pieces:
            if p_end <= start or p_start >= end:
                kept.append((start, end))
                continue
            if start < p_start:
                kept.append((start, p_start))
            if p_end < end:
                kept.append((p_end, end))
        pieces = kept
    return pieces


def close_segments(segments: list[Segment], heartbeats: list[datetime], alive: Sequence[datetime] = (),
                   max_gap: timedelta = timedelta(minutes=5)) -> None:
    """Set each segment's ``end``: the last heartbeat of the chain that continues its last stamp with no gap
    over ``max_gap`` (a longer gap: the machine was down), or the latest ``alive`` time before the next
    segment if later; else its last stamp. Nothing past the next segment's start counts."""
    ordered = sorted(segments, key=lambda s: s.first)
    beats = sorted(heartbeats)
    for index, segment in enumerate(ordered):
        limit = ordered[index + 1].first if index + 1 < len(ordered) else None
        end = segment.last
        for beat in beats:
            if beat <= end or (limit is not None and beat > limit):
                continue
            if beat - end > max_gap:
                break
            end = beat
        known = [t for t in alive if t > end and (limit is None or t <= limit)]
        segment.end = max(known) if known else end


def keep_rules(segments: list[Segment], only: Sequence[str] = (), exclude: Sequence[str] = ()) -> None:
    """Keep in each segment the jobs of the rules in ``only`` (all when empty) and not in ``exclude``."""
    for segment in segments:
        segment.jobs = [job for job in segment.jobs if (not only or job.rule in only) and job.rule not in exclude]


def drop_superseded(segments: list[Segment], superseded: Sequence[tuple[re.Pattern[str], datetime]]) -> int:
    """Leave out the jobs whose label (``rule wildcards``) a pattern matches (``re.fullmatch``) and that started
    before its time: work a later change redid (e.g. models retrained after their settings changed), which a
    run at the final code would not have done. Returns how many jobs were dropped."""
    dropped = 0
    for segment in segments:
        kept = [job for job in segment.jobs
                if not any(pattern.fullmatch(job.label) and job.start < before for pattern, before in superseded)]
        dropped += len(segment.jobs) - len(kept)
        segment.jobs = kept
    return dropped


def job_intervals(segment: Segment, pauses: list[Interval]) -> list[tuple[Job, list[Interval]]]:
    """Each job's interval in ``segment`` (unfinished ones end at the segment's end), pauses removed."""
    assert segment.end is not None
    return [(job, subtract((job.start, job.end or segment.end), pauses)) for job in segment.jobs]


def core_use(intervals: list[tuple[Job, list[Interval]]], cores: int) -> tuple[float, float]:
    """(core-seconds the jobs used, core-seconds left idle while at least one job ran) on ``cores`` cores; a
    job holds min(its threads, cores) cores over its intervals."""
    events = sorted((time, sign * min(job.threads, cores)) for job, pieces in intervals for start, end in pieces
                    for time, sign in ((start, 1), (end, -1)))
    used = idle = 0.0
    load, previous = 0, None
    for time, change in events:
        if previous is not None and load > 0:
            seconds = (time - previous).total_seconds()
            used += min(load, cores) * seconds
            idle += max(cores - load, 0) * seconds
        load, previous = load + change, time
    return used, idle


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("logs", nargs="+", type=Path, help="Snakemake logs, one per invocation")
    parser.add_argument("--since", type=datetime.fromisoformat, default=None,
                        help="ignore invocations that started before this ISO time")
    parser.add_argument("--pause", action="append", default=[], metavar="START/END",
                        help="a pause window in ISO times (repeatable)")
    parser.add_argument("--heartbeat", type=Path, default=None, help="file of ISO times, one per line")
    parser.add_argument("--alive", action="append", default=[], type=datetime.fromisoformat, metavar="TIME",
                        help="an ISO time known to lie inside a live session (e.g. a checkpoint's mtime), used "
                             "like a heartbeat but without the gap rule (repeatable)")
    parser.add_argument("--rule", action="append", default=[], metavar="NAME",
                        help="count only jobs of this rule (repeatable; e.g. the training stage alone)")
    parser.add_argument("--exclude-rule", action="append", default=[], metavar="NAME",
                        help="leave out jobs of this rule (repeatable)")
    parser.add_argument("--superseded", action="append", default=[], metavar="REGEX@ISO",
                        help="leave out jobs whose 'rule wildcards' label the regex matches in full and that started "
                             "before the ISO time: work a later change redid, e.g. "
                             "'train_denoiser model=rae(_.*)?@2026-12-03T07:39' (repeatable)")
    parser.add_argument("--cores", type=int, default=2,
                        help="cores of the machine the run used (for the core-use line; default 2)")
    parser.add_argument("--max-gap", type=float, default=5.0,
                        help="minutes between heartbeats beyond which the machine counts as down (default 5)")
    args = parser.parse_args()

    pauses = []
    for window in args.pause:
        start, _, end = window.partition("/")
        pauses.append((datetime.fromisoformat(start), datetime.fromisoformat(end)))
    heartbeats = ([datetime.fromisoformat(line.strip()) for line in args.heartbeat.read_text().splitlines()
                   if line.strip()] if args.heartbeat else [])
    segments = [s for path in args.logs if (s := parse_log(path.read_text(errors="replace"), path.name))]
    segments = [s for s in segments if s.jobs and (args.since is None or s.first >= args.since)]
    if not segments:
        raise SystemExit("no invocation with jobs in the given logs")
    close_segments(segments, heartbeats, args.alive, timedelta(minutes=args.max_gap))
    keep_rules(segments, args.rule, args.exclude_rule)   # after closing: the ends do not depend on the rules counted
    superseded = []
    for item in args.superseded:
        pattern, sep, before = item.rpartition("@")
        if not sep or not pattern:
            raise SystemExit(f"--superseded {item!r}: expected REGEX@ISO-TIME")
        superseded.append((re.compile(pattern), datetime.fromisoformat(before)))
    dropped = drop_superseded(segments, superseded)

    per_rule: dict[str, list[float]] = {}
    total = used = idle = 0.0
    print("segment | first stamp | end | jobs (unfinished) | busy wall min | end from")
    for segment in sorted(segments, key=lambda s: s.first):
        intervals = job_intervals(segment, pauses)
        busy = union_length([piece for _, pieces in intervals for piece in pieces])
        total += busy
        segment_used, segment_idle = core_use(intervals, args.cores)
        used, idle = used + segment_used, idle + segment_idle
        unfinished = sum(job.end is None for job in segment.jobs)
        source = "heartbeat" if segment.end > segment.last else "last stamp"
        print(f"{segment.name} | {segment.first:%m-%d %H:%M:%S} | {segment.end:%m-%d %H:%M:%S} | "
              f"{len(segment.jobs)} ({unfinished}) | {busy / 60:.1f} | {source}")
        for job, pieces in intervals:
            stats = per_rule.setdefault(job.rule, [0, 0, 0.0])
            stats[0] += 1
            stats[1] += job.end is not None and not job.failed
            stats[2] += sum((end - start).total_seconds() for start, end in pieces)
    print("\nrule | jobs started | finished | job time min (pauses removed)")
    for rule, (started, finished, seconds) in sorted(per_rule.items(), key=lambda item: -item[1][2]):
        print(f"{rule} | {started} | {finished} | {seconds / 60:.1f}")
    print(f"\nbusy wall time over {len(segments)} segments: {total / 3600:.2f} h ({total / 60:.0f} min); "
          f"{len(pauses)} pause window(s) removed; {dropped} superseded job(s) left out")
    print(f"core use on {args.cores} cores (each job holds min(threads, cores)): {used / 60:.0f} core-min used, "
          f"{idle / 60:.0f} core-min idle while jobs ran; the same work packed onto every core: "
          f"{used / args.cores / 60:.0f} min of wall")


if __name__ == "__main__":
    main()
