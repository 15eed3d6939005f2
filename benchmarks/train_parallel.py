"""Training throughput on a 2-core machine: one training at 2 threads versus two trainings side by side at 1
thread each, per model of a config, in alternating rounds.

Small networks do not keep two cores busy: much of their step is single-threaded (Python, small kernels,
the optimiser's elementwise work), so one training at 2 threads leaves a core idle part of the time, which a
second training running beside it would use. This measures whether that holds for each model: the
aggregate steps/s of two concurrent 1-thread trainings of the model against one 2-thread training, both
timed over the same wall-clock window, in interleaved rounds (``solo`` then ``pair`` per round) so that a
change in machine load hits both. Each worker is a fresh process that builds the model's configured
training step (``denoisers.training.speed.make_trainer`` on the model's synthetic batch: its batch size,
frames and crop; precision and layout as ``compute`` resolves here), warms up, waits for a common start
signal and counts optimiser steps for ``--seconds``.

The ratio pair / solo is the speed-up of the training stage when the workflow may run two such trainings at
once with one thread each (``training.threads``); above 1 the pairing pays.

``--solo-fp32`` runs the solo training in float32, NCHW, eager (the step before issue 11's precision work)
while the pair keeps the configured precision and layout: the ratio is then the training stage's throughput as
configured (bf16 + channels-last where the CPU supports them, two 1-thread trainings) against one fp32 training
at 2 threads, measured side by side.

Usage: python benchmarks/train_parallel.py [--config config/config.yaml] [--models rae ntasd_kpn]
           [--rounds 3] [--seconds 30] [--warmup-steps 3] [--solo-fp32] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def worker(config: Path, model: str, threads: int, seconds: float, warmup: int, ready: Path, go: Path,
           out: Path, fp32: bool = False) -> None:
    """One training process: build, warm up, signal ``ready``, wait for ``go``, count steps for ``seconds``;
    ``fp32``: float32 NCHW whatever the model's ``compute``."""
    import torch

    from denoisers.training.models import model_spec
    from denoisers.training.precision import resolve, resolve_compute
    from denoisers.training.speed import make_trainer
    from denoisers.training.synthetic import synthetic_batch
    from denoisers.training.tasks import task_builder
    from scenegen.config import load_config

    torch.set_num_threads(threads)
    spec = model_spec(load_config(config), model)
    builder = task_builder(spec.method)
    batch = synthetic_batch(spec, builder.sample_buffers, pixel_buffers=builder.pixel_buffers,
                            mean_buffers=builder.mean_buffers)
    step = resolve("fp32", False) if fp32 else resolve_compute(spec.compute)
    with tempfile.TemporaryDirectory(prefix="train_parallel-") as work:
        trainer = make_trainer(spec, batch, step.precision, step.channels_last, Path(work))
        for _ in range(warmup):
            trainer._train_step()
        ready.touch()
        while not go.exists():
            time.sleep(0.01)
        start, steps = time.perf_counter(), 0
        while time.perf_counter() - start < seconds:
            trainer._train_step()
            steps += 1
        elapsed = time.perf_counter() - start
    out.write_text(json.dumps({"steps": steps, "seconds": elapsed}))


def run_group(config: Path, model: str, threads: list[int], seconds: float, warmup: int,
              fp32: bool = False) -> list[dict]:
    """Start one worker per entry of ``threads`` at once (``fp32``: in float32 NCHW); returns their
    {steps, seconds}."""
    with tempfile.TemporaryDirectory(prefix="train_parallel-group-") as tmp:
        tmp_path, go = Path(tmp), Path(tmp) / "go"
        procs, outs, readies = [], [], []
        for i, count in enumerate(threads):
            ready, out = tmp_path / f"ready{i}", tmp_path / f"out{i}.json"
            env = {**os.environ, "OMP_NUM_THREADS": str(count)}
            procs.append(subprocess.Popen([sys.executable, __file__, "--worker", "--config", str(config), "--models",
                                           model, "--threads", str(count), "--seconds", str(seconds),
                                           "--warmup-steps", str(warmup), "--ready", str(ready), "--go", str(go),
                                           "--out", str(out)] + (["--solo-fp32"] if fp32 else []), env=env))
            outs.append(out)
            readies.append(ready)
        while not all(r.exists() for r in readies):
            if any(p.poll() not in (None, 0) for p in procs):
                raise RuntimeError(f"a worker for {model} failed before its timed window")
            time.sleep(0.05)
        go.touch()
        for p in procs:
            if p.wait() != 0:
                raise RuntimeError(f"a worker for {model} exited with {p.returncode}")
        return [json.loads(o.read_text()) for o in outs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--models", nargs="+", default=["rae"])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=30.0, help="timed window per group")
    parser.add_argument("--warmup-steps", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--solo-fp32", action="store_true",
                        help="the solo training in float32 NCHW (the pair as configured): the whole training-stage gain")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--ready", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--go", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.config, args.models[0], args.threads, args.seconds, args.warmup_steps, args.ready, args.go,
               args.out, fp32=args.solo_fp32)
        return
    load = os.getloadavg()
    record = {"config": str(args.config), "rounds": args.rounds, "seconds": args.seconds, "models": {},
              "solo_fp32": args.solo_fp32, "load_average_start": load}
    for model in args.models:
        solo, pair = [], []
        for _ in range(args.rounds):
            (one,) = run_group(args.config, model, [2], args.seconds, args.warmup_steps, fp32=args.solo_fp32)
            solo.append(one["steps"] / one["seconds"])
            pair.append(sum(w["steps"] / w["seconds"] for w in run_group(args.config, model, [1, 1], args.seconds,
                                                                        args.warmup_steps)))
        ratios = [p / s for p, s in zip(pair, solo)]
        record["models"][model] = {"solo_2_threads_steps_per_s": solo, "pair_1_thread_steps_per_s": pair,
                                   "ratio": ratios}
        solo_kind = "fp32 NCHW" if args.solo_fp32 else "as configured"
        print(f"{model}: one training at 2 threads ({solo_kind}) {statistics.median(solo):.3f} steps/s "
              f"({1 / statistics.median(solo) * 1e3:.0f} ms/step); two at 1 thread each "
              f"{statistics.median(pair):.3f} steps/s together; pair / solo {statistics.median(ratios):.2f}x "
              f"[{min(ratios):.2f}, {max(ratios):.2f}] over {args.rounds} round(s)", flush=True)
    record["load_average_end"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
