"""benchmarks/run_wall_time.py: job intervals from Snakemake logs, pauses and killed invocations, against
hand-computed wall times."""
from __future__ import annotations

import re
from datetime import datetime

from tests.benchmark_modules import load_benchmark

rwt = load_benchmark("run_wall_time")


def _t(hms: str) -> datetime:
    return datetime.fromisoformat(f"2026-12-02T{hms}")


def _job(stamp: str, rule: str, jobid: int) -> str:
    return f"[Wed Dec  2 {stamp} 2026]\nlocalrule {rule}:\n    input: a\n    output: b\n    jobid: {jobid}\n" \
           f"    wildcards: x=1\n\n"


def _finish(stamp: str, jobid: int, rule: str) -> str:
    return f"[Wed Dec  2 {stamp} 2026]\nFinished jobid: {jobid} (Rule: {rule})\n1 of 9 steps (11%) done\n"


# Two overlapping jobs (10:00-10:10 and 10:05-10:20), a failed one (10:20-10:21), one killed (from 10:21).
LOG = ("Using profile workflow/profiles/local for setting default command line arguments.\n"
       + _job("10:00:00", "train_denoiser", 7) + _job("10:05:00", "denoise_clip", 8)
       + _finish("10:10:00", 7, "train_denoiser") + _finish("10:20:00", 8, "denoise_clip")
       + _job("10:20:00", "evaluate_clip", 9)
       + "[Wed Dec  2 10:21:00 2026]\nError in rule evaluate_clip:\n    message: None\n    jobid: 9\n"
       + _job("10:21:00", "train_denoiser", 10))


def test_parse_log_reads_starts_finishes_errors_and_unfinished_jobs() -> None:
    segment = rwt.parse_log(LOG, "a")
    assert segment is not None
    jobs = {job.jobid: job for job in segment.jobs}
    assert (jobs[7].rule, jobs[7].start, jobs[7].end) == ("train_denoiser", _t("10:00:00"), _t("10:10:00"))
    assert (jobs[8].start, jobs[8].end, jobs[8].failed) == (_t("10:05:00"), _t("10:20:00"), False)
    assert (jobs[9].end, jobs[9].failed) == (_t("10:21:00"), True)
    assert jobs[10].end is None and segment.last == _t("10:21:00")
    assert rwt.parse_log("Using profile x\nNothing to be done.\n") is None


def test_busy_wall_is_the_union_of_job_intervals_minus_pauses() -> None:
    segment = rwt.parse_log(LOG, "a")
    # killed at 10:40 (last beat of the minute-wise chain; the next invocation starts at 11:00 and its beats
    # belong to it)
    later = rwt.parse_log(_job("11:00:00", "train_denoiser", 1) + _finish("11:30:00", 1, "train_denoiser"), "b")
    beats = [_t(f"10:{minute}:30") for minute in range(21, 40)] + [_t("10:40:00"), _t("11:10:00")]
    rwt.close_segments([segment, later], beats)
    assert segment.end == _t("10:40:00") and later.end == _t("11:30:00")
    pauses = [(_t("10:15:00"), _t("10:25:00"))]
    pieces = [piece for _, cut in rwt.job_intervals(segment, pauses) for piece in cut]
    # union 10:00-10:40 = 40 min, minus the 10-minute pause
    assert rwt.union_length(pieces) == 30 * 60
    per_job = {job.jobid: sum((e - s).total_seconds() for s, e in cut) for job, cut in rwt.job_intervals(segment,
                                                                                                         pauses)}
    assert per_job == {7: 600, 8: 600, 9: 0, 10: 15 * 60}


def test_segment_without_heartbeat_ends_at_its_last_stamp() -> None:
    segment = rwt.parse_log(LOG, "a")
    rwt.close_segments([segment], [])
    assert segment.end == _t("10:21:00")


def test_a_gap_in_the_heartbeats_ends_the_segment_where_the_machine_went_down() -> None:
    segment = rwt.parse_log(LOG, "a")
    later = rwt.parse_log(_job("11:00:00", "train_denoiser", 1) + _finish("11:30:00", 1, "train_denoiser"), "b")
    # beats every minute to 10:30, the machine is down until 10:58, the heartbeat restarts before invocation b
    beats = [_t(f"10:{minute}:10") for minute in range(22, 31)] + [_t("10:58:00"), _t("10:59:00")]
    rwt.close_segments([segment, later], beats)
    assert segment.end == _t("10:30:10")
    # an --alive time is taken as given (no chain needed), but never past the next segment's start
    rwt.close_segments([segment, later], beats, alive=[_t("10:45:00"), _t("11:05:00")])
    assert segment.end == _t("10:45:00")
    # a first beat more than max_gap after the last log stamp: no chain at all
    rwt.close_segments([segment], [_t("10:40:00")])
    assert segment.end == _t("10:21:00")


def test_one_stage_alone_counts_only_its_jobs() -> None:
    segment = rwt.parse_log(LOG, "a")
    rules = {job.rule for job in segment.jobs}
    assert len(rules) > 1
    rwt.close_segments([segment], [])
    end = segment.end
    chosen = sorted(rules)[0]
    rwt.keep_rules([segment], only=[chosen])
    assert segment.jobs and {job.rule for job in segment.jobs} == {chosen} and segment.end == end
    rwt.keep_rules([segment], exclude=[chosen])
    assert segment.jobs == []


def test_threads_are_read_and_core_use_counts_idle_cores() -> None:
    """A 2-thread render 10:00-10:10, then a 1-thread training alone 10:10-10:30 beside a 1-thread evaluation
    10:10-10:15: on 2 cores, 20 + 20 + 5 = 45 core-min used, 15 core-min idle (10:15-10:30), packed 22.5 min."""
    log = (_job("10:00:00", "render_reference", 1).replace("    wildcards: x=1\n", "    wildcards: x=1\n"
                                                             "    threads: 2\n")
           + _finish("10:10:00", 1, "render_reference")
           + _job("10:10:00", "train_denoiser", 2) + _job("10:10:00", "evaluate_clip", 3)
           + _finish("10:15:00", 3, "evaluate_clip") + _finish("10:30:00", 2, "train_denoiser"))
    segment = rwt.parse_log(log, "a")
    assert {job.rule: job.threads for job in segment.jobs} == {"render_reference": 2, "train_denoiser": 1,
                                                               "evaluate_clip": 1}
    rwt.close_segments([segment], [])
    used, idle = rwt.core_use(rwt.job_intervals(segment, []), cores=2)
    assert (used, idle) == (45 * 60, 15 * 60)
    # A job asking for more threads than there are cores holds every core, no more.
    assert rwt.core_use(rwt.job_intervals(segment, []), cores=1) == (30 * 60, 0)


def test_superseded_jobs_are_left_out_by_label_and_start() -> None:
    """A training redone after a settings change: its first run (before the change) is left out, its redo and
    the other jobs stay; the label is 'rule wildcards' as the log prints them."""
    log = (_job("09:00:00", "train_denoiser", 1) + _finish("09:30:00", 1, "train_denoiser")
           + _job("09:00:00", "denoise_clip", 2) + _finish("09:10:00", 2, "denoise_clip")
           + _job("10:00:00", "train_denoiser", 3) + _finish("10:20:00", 3, "train_denoiser"))
    segment = rwt.parse_log(log, "a")
    assert [job.label for job in segment.jobs] == ["train_denoiser x=1", "denoise_clip x=1", "train_denoiser x=1"]
    rwt.close_segments([segment], [])
    dropped = rwt.drop_superseded([segment], [(re.compile(r"train_denoiser x=1"), _t("09:45:00"))])
    assert dropped == 1 and [job.jobid for job in segment.jobs] == [2, 3]
    pieces = [piece for _, cut in rwt.job_intervals(segment, []) for piece in cut]
    assert rwt.union_length(pieces) == 30 * 60          # 09:00-09:10 and 10:00-10:20
    assert rwt.drop_superseded([segment], [(re.compile(r"train_denoiser"), _t("11:00:00"))]) == 0   # fullmatch
