"""Training-step speed of every learned network at its config size: today's float32 eager NCHW step beside
the configured step arithmetic (``training.models[].compute``, resolved on this machine) and the other
precision / layout combinations, with GFLOP/s against matrix multiplies timed in the same run.

A thin command line over ``denoisers.training.speed`` (the measuring logic; the workflow's rule
time_training runs the same function with the config's ``training.speed`` settings and the report shows its
table "Training step speed"). Per model of ``training.models`` (today: the RAE), one trainer per variant on
the same fixed synthetic batch of the model's size (batch_size sequences x length frames x crop^2); a timed
call is the trainer's own optimiser step. Variants:

* ``fp32 NCHW``: float32, default layout -- the step as it was before the ``compute`` setting (eager);
* ``fp32 channels-last``, ``bf16 NCHW``, ``bf16 channels-last``: the other combinations (bf16 =
  ``torch.autocast`` bfloat16 forward, float32 weights / Adam / loss); the one the config resolves to
  here is marked ``*``;
* with ``--compile``: the configured variant with ``torch.compile`` of the network's forward (backward
  through AOTAutograd); its first step's extra time is the compile time, and break-even steps = compile
  time / time saved per step, printed beside the model's ``budget.max_steps``.

Unlike the workflow's job (whose default skips most emulated-bf16 rounds to stay short), every variant runs
every round here unless ``--emulated-bf16-repeats`` says otherwise. Every round runs every variant once,
then the matrix multiplies of ``--gemm-size``^3 (float32 through MKL ``torch.mm`` and oneDNN
``mkldnn_linear``, and bfloat16 ``torch.mm``), so a change in machine load hits all alike. Medians over
``--repeats`` rounds after ``--warmup``: ms/step, training pixels/s, GFLOP/s = FLOPs of the fp32 step
(forward and backward convolutions, the loss's filter included; the optimiser's elementwise work not) /
time, as a fraction of the faster float32 sgemm, and the speed-up over ``fp32 NCHW``.

On a machine shared with other work, set ``OMP_WAIT_POLICY=PASSIVE``: with libgomp's default spin-waiting,
a 2-thread training step measured 10-30x slower whenever another process held a core (each of the step's
thousands of parallel regions ends in a barrier whose spinning thread keeps the late one off its core).

Usage: python benchmarks/train_speed.py [--config config/config.yaml] [--models rae] [--threads 2]
           [--repeats 7] [--warmup 2] [--gemm-size 1024] [--emulated-bf16-repeats N] [--compile] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from denoisers.training.models import model_specs
from denoisers.training.speed import TARGET_SPEEDUP, VARIANTS, Timed, describe_record, make_trainer, time_training
from scenegen.config import load_config

COMPILED = "torch.compile"


def compile_timers(spec, batch, configured, work: Path) -> list[Timed]:
    """The configured step with torch.compile of the network's forward (the first call compiles)."""
    import torch

    trainer = make_trainer(spec, batch, configured.precision, configured.channels_last, work / f"{spec.id}-compile")
    trainer._loss_model = torch.compile(trainer._loss_model)
    return [Timed(COMPILED, trainer._train_step)]


def verdicts(record: dict, budgets: dict[str, int]) -> list[str]:
    """Per model: the configured step's speed-up against the target, and torch.compile's break-even."""
    lines = []
    for model in record["models"]:
        by_key = {v["variant"]: v for v in model["variants"]}
        configured = by_key[model["configured_variant"]]
        speedup = configured["speedup_median"]
        lines.append(f"model {model['model']}: configured step ({configured['label']}) vs fp32 NCHW eager: "
                     f"{speedup:.2f}x (target >= {TARGET_SPEEDUP}x: {'met' if speedup >= TARGET_SPEEDUP else 'NOT met'})")
        compiled = by_key.get(COMPILED)
        if compiled and compiled["status"] == "timed":
            plain, fast = configured["ms_per_step_median"], compiled["ms_per_step_median"]
            compile_s = (compiled["first_call_ms"] - plain) / 1e3
            text = (f"  torch.compile: first step {compiled['first_call_ms'] / 1e3:.1f} s (~{compile_s:.1f} s "
                    f"compiling), then {fast:.1f} vs {plain:.1f} ms/step: ")
            if plain > fast:
                even = compile_s / ((plain - fast) / 1e3)
                budget = budgets[model["model"]]
                text += (f"break-even after {even:.0f} steps; {'pays back' if even < budget else 'does NOT pay back'} "
                         f"within budget.max_steps = {budget}")
            else:
                text += "no faster, never pays back"
            lines.append(text)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--models", nargs="*", default=None, help="ids of training.models (default: all)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--gemm-size", type=int, default=1024)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--emulated-bf16-repeats", type=int, default=None,
                        help="rounds of the bf16 variants where bf16 is emulated (default: --repeats)")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile of the configured step")
    parser.add_argument("--json", type=Path, default=None, help="also write the record as JSON")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="  (%(message)s)", stream=sys.stderr)
    cfg = load_config(args.config)
    settings = {"repeats": args.repeats, "warmup": args.warmup, "gemm_size": args.gemm_size,
                "variants": args.variants, "emulated_bf16_repeats": (args.repeats if args.emulated_bf16_repeats is None
                                                                     else args.emulated_bf16_repeats)}
    try:
        record = time_training(cfg, threads=args.threads, settings=settings, model_ids=args.models,
                               extra=compile_timers if args.compile else None)
    except ValueError as error:
        raise SystemExit(f"{args.config}: {error}") from None
    print("\n".join(describe_record(record)))
    budgets = {spec.id: spec.budget.get("max_steps") or 0 for spec in model_specs(cfg)}
    print("\n".join(verdicts(record, budgets)))
    if args.json:
        args.json.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
