"""``python -m denoisers train-session`` and ``python -m denoisers submission``: a training session that outlives
its machine through the store (denoisers.store.session), and what the checkout's commits cost to submit
(denoisers.store.submission)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from denoisers.store.submission import DEFAULT_BUDGET_MIB, submission_report


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The ``train-session`` and ``submission`` commands."""
    session = sub.add_parser("train-session", help="train models until a deadline, then publish the finished ones "
                                                   "and checkpoint the rest into the store (denoisers.store.session)")
    session.add_argument("models", nargs="*", help="model ids (seed replicas and _half twins included); none: every "
                                                   "training of the config (the stored ones installed)")
    session.add_argument("--minutes", type=float, required=True, help="stop the run after this many minutes")
    session.add_argument("--snakemake", default="", help="more Snakemake arguments, one string, e.g. "
                                                         "\"--configfile config/isik2021.yaml --config 'training={seeds: 3}'\"")
    session.add_argument("--log", type=Path, help="append the run's output here (default: the terminal)")
    session.add_argument("--keep-every", type=float, default=None, metavar="MINUTES",
                         help="pause the run this often and keep what it reached (publish / checkpoint), so a machine "
                              "lost before the deadline loses at most this much")
    session.add_argument("--commit", action="store_true",
                         help="commit the store after every keep (the store only, whatever else is staged stays "
                              "staged; within --submission-budget)")
    session.add_argument("--restart-other-arithmetic", action="store_true",
                         help="train afresh the models whose stored checkpoint has another step arithmetic than this "
                              "machine resolves (bf16 / fp32), and let their checkpoints replace it (default: skip them)")
    session.add_argument("--submission-budget", type=float, default=DEFAULT_BUDGET_MIB, metavar="MIB",
                         help="with --commit: the MiB of diffs (old + new bytes of every changed file, summed over the "
                              "commits since --submission-base) the session's commits may reach; a keep that would "
                              "pass it stays on disk (default %(default)g of the 256 MiB a submission may hold; 0: no "
                              "budget)")
    session.add_argument("--submission-base", default=None, metavar="REV",
                         help="the commit the session's submission starts after (default: where this checkout's "
                              "branch began, the oldest entry of its reflog)")

    submission = sub.add_parser("submission", help="what this checkout's commits cost to submit: the diffs (old + new "
                                                   "bytes per changed file) and new objects of the commits after the "
                                                   "base, against the workplace's limits (denoisers.store.submission)")
    submission.add_argument("--base", default=None, metavar="REV",
                            help="the commit the submission starts after (default: where this checkout's branch "
                                 "began, the oldest entry of its reflog)")
    submission.add_argument("--check", action="store_true", help="exit 1 when the commits pass the workplace's limits")
    submission.add_argument("--largest", type=int, default=5, help="list this many of the costliest commits")


def run(args: argparse.Namespace) -> int:
    """Run ``train-session`` or ``submission``; the exit status."""
    if args.command == "submission":
        from denoisers.store.code import REPO_ROOT

        text, within = submission_report(REPO_ROOT, args.base, args.largest)
        print(text)
        return 1 if args.check and not within else 0

    if args.command == "train-session":
        import shlex

        from denoisers.store.session import train_session

        result = train_session(args.models, args.minutes, shlex.split(args.snakemake), log=args.log,
                               keep_every_minutes=args.keep_every, commit=args.commit,
                               restart_other_arithmetic=args.restart_other_arithmetic,
                               submission_budget_mib=args.submission_budget or None,
                               submission_base=args.submission_base)
        if result.returncode is None and not result.stopped_at_deadline:
            print(f"nothing to train on this machine: skipped {', '.join(result.skipped)} (their stored checkpoints "
                  "have another step arithmetic)", file=sys.stderr)
            return 1
        state = "stopped at the deadline" if result.stopped_at_deadline else f"finished (exit {result.returncode})"
        print(f"run {state}; published: {', '.join(result.published) or 'none'}; checkpointed: "
              f"{', '.join(result.checkpointed) or 'none'}; untouched: {', '.join(result.untouched) or 'none'}"
              + (f"; stored before: {', '.join(result.already_stored)}" if result.already_stored else "")
              + (f"; skipped (another arithmetic): {', '.join(result.skipped)}" if result.skipped else ""))
        if not args.commit:
            print("commit store/ now: only what is committed survives the machine")
        elif result.uncommitted:
            print(f"left on disk, not committed: {', '.join(result.uncommitted)} (`python -m denoisers "
                  "submission` says what the session's commits cost; commit more only within its limits)")
        return 0 if result.stopped_at_deadline or result.returncode == 0 else 1
    raise ValueError(f"not a session command: {args.command}")
