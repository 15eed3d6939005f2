"""Training-step speed of every learned network at its config size: today's float32 eager NCHW step beside
the configured step arithmetic (``training.models[].compute``, resolved on this machine) and the other
precision / layout combinations, with GFLOP/s against matrix multiplies timed in the same run.

One process. Per model of ``training.models`` (today: the RAE), one :class:`Trainer` per variant, each on
the same fixed synthetic batch of the model's size (batch_size sequences x length frames x crop^2, the
per-sample buffers of ``benchmarks/denoiser_speed.py``); a timed call is the trainer's own optimiser step
(``Trainer._train_step``: learning rate, zero_grad, the task's loss through the bf16 autocast wrapper when
that is the precision, backward, Adam). Variants:

* ``fp32 NCHW``: float32, default layout -- the step as it was before the ``compute`` setting (eager);
* ``fp32 channels-last``, ``bf16 NCHW``, ``bf16 channels-last``: the other combinations (bf16 =
  ``torch.autocast`` bfloat16 forward, float32 weights / Adam / loss); the one the config resolves to
  here is marked ``*``;
* with ``--compile``: the configured variant with ``torch.compile`` of the network's forward (backward
  through AOTAutograd); its first step's extra time is the compile time, and break-even steps = compile
  time / time saved per step, printed beside the model's ``budget.max_steps``.

Every round runs every variant once, then the matrix multiplies of ``--gemm-size``^3 (float32 through MKL
``torch.mm`` and oneDNN ``mkldnn_linear``, and bfloat16 ``torch.mm``), so a change in machine load hits
all alike. Medians over ``--repeats`` rounds after ``--warmup``: ms/step, training pixels/s (sequence
pixels per step / time), GFLOP/s = FLOPs of the fp32 step (``torch.utils.flop_counter``: forward and
backward convolutions, the loss's filter included; the optimiser's elementwise work not) / time, as a
fraction of the faster float32 sgemm, and the speed-up over ``fp32 NCHW``.

On a machine shared with other work, set ``OMP_WAIT_POLICY=PASSIVE``: with libgomp's default spin-waiting,
a 2-thread training step measured 10-30x slower whenever another process held a core (each of the step's
thousands of parallel regions ends in a barrier whose spinning thread keeps the late one off its core).

Usage: python benchmarks/train_speed.py [--config config/config.yaml] [--models rae] [--threads 2]
           [--repeats 7] [--warmup 2] [--gemm-size 1024] [--compile]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from denoisers.training.loop import Trainer, TrainerConfig
from denoisers.training.models import model_specs
from denoisers.training.precision import bf16_support, resolve_compute
from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import build_task, task_builder
from scenegen.config import load_config

try:
    from benchmarks.denoiser_speed import synthetic_frames
    from benchmarks.rae_speed import gemm_items, load_average
except ImportError:  # run as a script: benchmarks/ is on sys.path, the repository root may not be
    from denoiser_speed import synthetic_frames
    from rae_speed import gemm_items, load_average

TARGET_SPEEDUP = 1.6            # issue 11 §1: the default step at least 1.6x faster than the fp32 eager step
VARIANTS: tuple[tuple[str, str, bool], ...] = (("fp32 NCHW", "fp32", False), ("fp32 channels-last", "fp32", True),
                                               ("bf16 NCHW", "bf16", False), ("bf16 channels-last", "bf16", True))


@dataclass
class Timed:
    """One timed thing: label, a call per round, FLOPs per call (0: not counted), pixels per call."""

    label: str
    run: Callable[[], Any]
    flops: int = 0
    pixels: int = 0
    first_call: float | None = None      # seconds of the first call (compile variants)


class FixedBatch:
    """A batch source handing out the same batch every step (speed does not depend on the content)."""

    def __init__(self, batch: dict[str, torch.Tensor]) -> None:
        self._batch = batch

    def batch(self, index: int, batch_size: int) -> dict[str, torch.Tensor]:
        return self._batch

    def describe(self) -> dict[str, Any]:
        return {"fixed synthetic batch": {k: list(v.shape) for k, v in self._batch.items()}}


def synthetic_batch(spec: ModelSpec, buffers: tuple[str, ...]) -> dict[str, torch.Tensor]:
    """(N, T, S, C, crop, crop) per-sample ``buffers``, (N, T, 3, crop, crop) reference radiance and identity
    world-to-view rotations (N, T, 3, 3): N = batch_size sequences of T = length synthetic frames."""
    n, t = spec.optimizer["batch_size"], spec.data["length"]
    crop, spp = spec.data["crop"], spec.data["spp"]
    sequences = [synthetic_frames(crop, spp, t, seed=index) for index in range(n)]
    batch = {b: torch.stack([torch.stack([f.samples[b] for f in frames]) for frames in sequences]) for b in buffers}
    batch["reference.radiance"] = torch.stack([torch.stack([f.mean("radiance") for f in frames])
                                               for frames in sequences])
    batch["world_to_view"] = torch.eye(3).expand(n, t, 3, 3).clone()
    return batch


def make_trainer(spec: ModelSpec, batch: dict[str, torch.Tensor], precision: str, channels_last: bool,
                 out_dir: Path) -> Trainer:
    """A trainer of ``spec``'s task (its optimiser settings, fresh weights from its seed) on ``batch``."""
    optimizer = spec.optimizer
    config = TrainerConfig(seed=spec.seed, batch_size=optimizer["batch_size"], max_steps=10**9, lr=optimizer["lr"],
                           betas=tuple(optimizer["betas"]), schedule=dict(optimizer["schedule"]),
                           grad_clip_norm=optimizer.get("grad_clip_norm"), validate_every=0, checkpoint_every=0,
                           checkpoint_seconds=None, progress=False, precision=precision, channels_last=channels_last)
    trainer = Trainer(build_task(spec), FixedBatch(batch), [], config, out_dir)
    trainer._setup()  # model, Adam and seeds exactly as Trainer.run builds them
    return trainer


def step_flops(trainer: Trainer) -> int:
    """FLOPs of one optimiser step's forward and backward (torch.utils.flop_counter), counted on a copy-free
    extra step (the weights move on; speed does not depend on them)."""
    counter = FlopCounterMode(display=False)
    with counter:
        trainer._train_step()
    return int(counter.get_total_flops())


def model_items(spec: ModelSpec, args: argparse.Namespace, work: Path) -> tuple[list[Timed], str, dict]:
    """The timed variants of one model, the label of the configured one, and facts for the header."""
    builder = task_builder(spec.method)
    batch = synthetic_batch(spec, builder.sample_buffers)
    pixels = spec.optimizer["batch_size"] * spec.data["length"] * spec.data["crop"] ** 2
    configured = resolve_compute(spec.compute)
    items: list[Timed] = []
    flops = 0
    configured_label = ""
    for label, precision, channels_last in VARIANTS:
        trainer = make_trainer(spec, batch, precision, channels_last, work / f"{spec.id}-{len(items)}")
        if not flops:
            flops = step_flops(trainer)
        if (precision, channels_last) == (configured.precision, configured.channels_last):
            configured_label = label
        items.append(Timed(label, trainer._train_step, flops, pixels))
    if args.compile:
        trainer = make_trainer(spec, batch, configured.precision, configured.channels_last, work / f"{spec.id}-c")
        trainer._loss_model = torch.compile(trainer._loss_model)
        items.append(Timed(f"{configured_label} + torch.compile", trainer._train_step, flops, pixels))
    facts = {"pixels": pixels, "flops": flops, "configured": configured, "batch": batch}
    return items, configured_label, facts


def gemm_rates(n: int) -> list[Timed]:
    """float32 sgemm through MKL and oneDNN (``benchmarks/rae_speed.py``) and a bfloat16 torch.mm, n^3 each."""
    items = [Timed(item.label, lambda run=item.run: run(0), item.flops) for item in gemm_items(n)]
    generator = torch.Generator().manual_seed(1)
    a = torch.randn(n, n, generator=generator).bfloat16()
    b = torch.randn(n, n, generator=generator).bfloat16()
    items.append(Timed("bf16 gemm torch.mm", lambda: torch.mm(a, b), 2 * n**3))
    return items


def time_rounds(items: list[Timed], repeats: int, warmup: int) -> list[float]:
    """Median seconds per call of every item, every item once per round; the first call of each is kept."""
    seconds: list[list[float]] = [[] for _ in items]
    for index in range(warmup + repeats):
        for item, record in zip(items, seconds):
            start = time.perf_counter()
            item.run()
            elapsed = time.perf_counter() - start
            if index == 0:
                item.first_call = elapsed
            if index >= warmup:
                record.append(elapsed)
        print(f"  (round {index + 1}/{warmup + repeats} done, load {load_average()})", file=sys.stderr, flush=True)
    return [statistics.median(record) for record in seconds]


def report_model(spec: ModelSpec, items: list[Timed], medians: list[float], configured_label: str, facts: dict,
                 sgemm: float) -> None:
    """The side-by-side table of one model, then the verdict and the compile break-even."""
    base = medians[0]
    shape = " x ".join(str(v) for v in (spec.optimizer["batch_size"], spec.data["length"])) + f" x {spec.data['crop']}^2"
    print(f"\nmodel {spec.id} ({spec.method}, net {spec.net}): batch {shape} = {facts['pixels']:,} training px/step, "
          f"{facts['flops'] / 1e9:.2f} GFLOP/step (forward + backward)")
    print(f"  configured compute {spec.compute} -> {facts['configured'].describe()}")
    print(f"  {'step':36s} {'ms/step':>8s} {'Mpx/s':>7s} {'GFLOP/s':>8s} {'of sgemm':>9s} {'speed-up':>9s}")
    for item, seconds in zip(items, medians):
        mark = "*" if item.label == configured_label else " "
        rate = item.flops / seconds / 1e9
        print(f" {mark}{item.label:36s} {seconds * 1e3:8.1f} {item.pixels / seconds / 1e6:7.3f} {rate:8.1f} "
              f"{rate / sgemm:9.1%} {base / seconds:8.2f}x")
    by_label = dict(zip((item.label for item in items), medians))
    speedup = base / by_label[configured_label]
    verdict = "met" if speedup >= TARGET_SPEEDUP else "NOT met"
    print(f"  configured step ({configured_label}) vs fp32 NCHW eager: {speedup:.2f}x (target >= {TARGET_SPEEDUP}x: "
          f"{verdict})")
    compiled = [(item, t) for item, t in zip(items, medians) if item.label.endswith("torch.compile")]
    for item, seconds in compiled:
        plain = by_label[configured_label]
        compile_s = (item.first_call or 0.0) - plain
        saved = plain - seconds
        budget = spec.budget["max_steps"]
        if saved > 0:
            even = compile_s / saved
            pays = "pays back" if even < budget else "does NOT pay back"
            print(f"  torch.compile: first step {item.first_call:.1f} s (~{compile_s:.1f} s compiling), then "
                  f"{seconds * 1e3:.1f} vs {plain * 1e3:.1f} ms/step: break-even after {even:.0f} steps; "
                  f"{pays} within budget.max_steps = {budget}")
        else:
            print(f"  torch.compile: first step {item.first_call:.1f} s (~{compile_s:.1f} s compiling), then "
                  f"{seconds * 1e3:.1f} vs {plain * 1e3:.1f} ms/step: no faster, never pays back")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--models", nargs="*", default=None, help="ids of training.models (default: all)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--gemm-size", type=int, default=1024)
    parser.add_argument("--compile", action="store_true", help="also time torch.compile of the configured step")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    bases = {entry["id"] for entry in cfg["training"]["models"]}
    specs = [spec for spec in model_specs(cfg) if spec.id in bases and (args.models is None or spec.id in args.models)]
    if not specs:
        raise SystemExit(f"no model to time: training.models of {args.config} has {sorted(bases)}, asked {args.models}")
    supported, why = bf16_support()
    print(f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}, native bf16: "
          f"{supported} ({why}); {args.threads} threads, OMP_WAIT_POLICY {os.environ.get('OMP_WAIT_POLICY', 'unset')}; "
          f"median of {args.repeats} rounds after {args.warmup} warm-up "
          f"rounds, every item once per round; load average {load_average()} on {os.cpu_count()} CPUs at the start")
    np.random.seed(0)
    with tempfile.TemporaryDirectory(prefix="train_speed-") as work:
        models = [(spec, *model_items(spec, args, Path(work))) for spec in specs]
        gemms = gemm_rates(args.gemm_size)
        items = [item for _, model, _, _ in models for item in model] + gemms
        medians = dict(zip((id(item) for item in items), time_rounds(items, args.repeats, args.warmup)))
    rates = {item.label: item.flops / medians[id(item)] / 1e9 for item in gemms}
    sgemm = max(rate for label, rate in rates.items() if label.startswith("sgemm"))
    print(f"\ngemm {args.gemm_size}^3, same rounds: " + ", ".join(f"{label} {rate:.1f} GFLOP/s"
                                                               for label, rate in rates.items())
          + f"; 'of sgemm' below is against the faster float32 one, {sgemm:.1f} GFLOP/s")
    for spec, model, configured_label, facts in models:
        report_model(spec, model, [medians[id(item)] for item in model], configured_label, facts, sgemm)
    print(f"\n(load average {load_average()} at the end; above {os.cpu_count()} means threads waited for a core)")


if __name__ == "__main__":
    main()
