"""What training in bf16 autocast costs in quality: validation PSNR of a model trained in fp32 and in bf16 at
equal steps, on real renders.

Both runs use the config's settings of ``--model`` (network, loss, optimiser, schedule, seed), with the data's
crop and sequence length overridden to fit the renders (``--crop``, ``--length``), the same training
sequences (batch i is a pure function of the seed and i), the same fixed validation sequences (seeded by the
global seed, no augmentation); only ``compute.precision`` differs, with ``compute.channels_last`` as
``--channels-last`` (default auto: each precision with the layout it trains in by default, fp32 NCHW and
bf16 channels-last, i.e. the two default steps).
Validation runs in fp32 for both (as the trainer always does): mean PSNR / SSIM / loss over the validation
sequences every ``--validate-every`` steps. ``--control`` adds two fp32 runs that set the scale against which
the bf16 - fp32 difference is judged: fp32 with the other memory layout (same seed and data: only float
rounding differs, as it does between bf16 and fp32, but at fp32's level) and fp32 with the seed + 1.

Runs go to ``--out``/{fp32,bf16,fp32_layout,fp32_seed+1}/ (trainer directories: a rerun with the same
settings resumes, and finishes at once when done; resuming is exact). Training time per step is printed but runs were not interleaved: compare speed
with ``benchmarks/train_speed.py``.

Usage: python benchmarks/train_precision_quality.py [--config config/config.yaml] [--model rae]
           [--render-root results/smoke/renders] [--train train_000] [--validate train_001] [--steps 1000]
           [--crop 32] [--length 3] [--validate-every 100] [--validation-sequences 8] [--threads 2]
           [--channels-last auto|true|false] [--control] [--out /tmp/train_precision_quality]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
from pathlib import Path
from typing import Any

import torch

from denoisers.training.data import SequenceDataset, fixed_batches, load_training_clips
from denoisers.training.job import clip_buffers, task_sequence_config, trainer_config
from denoisers.training.loop import Trainer
from denoisers.training.models import model_spec
from denoisers.training.precision import bf16_support, resolve
from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import build_task, task_builder
from scenegen.config import load_config

TOLERANCE_DB = 0.1              # issue 11 §1: bf16 within 0.1 dB of fp32 at equal steps
LAYOUTS: dict[str, bool | str] = {"auto": "auto", "true": True, "false": False}


def train(name: str, spec: ModelSpec, cfg: dict, dataset: SequenceDataset, validation: list, precision: str,
          args: argparse.Namespace, channels_last: bool | str | None = None) -> dict[str, Any]:
    """Train one variant; its validation rows by step, its seconds per step and the trainer (final weights)."""
    layout = args.channels_last if channels_last is None else channels_last
    config = dataclasses.replace(trainer_config(cfg, spec, args.threads, progress=False), precision=precision,
                                 channels_last=layout, validate_every=args.validate_every,
                                 checkpoint_every=args.validate_every, max_seconds=None, max_steps=args.steps)
    trainer = Trainer(build_task(spec), dataset, validation, config, args.out / name)
    print(f"{name}: {trainer.compute.describe()}", flush=True)
    result = trainer.run()
    rows = {row["step"]: row for row in trainer.history if "val_psnr" in row}
    return {"rows": rows, "seconds_per_step": result.elapsed_seconds / max(result.steps, 1), "result": result,
            "trainer": trainer}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--model", default="rae")
    parser.add_argument("--render-root", type=Path, default=Path("results/smoke/renders"))
    parser.add_argument("--train", nargs="+", default=["train_000"])
    parser.add_argument("--validate", nargs="+", default=["train_001"])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--crop", type=int, default=32)
    parser.add_argument("--length", type=int, default=3)
    parser.add_argument("--validate-every", type=int, default=100)
    parser.add_argument("--validation-sequences", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--channels-last", default="auto", type=lambda text: LAYOUTS[text.lower()],
                        help="auto (default), true or false")
    parser.add_argument("--control", action="store_true",
                        help="also train fp32 with the other layout, and fp32 with the seed + 1")
    parser.add_argument("--out", type=Path, default=Path("/tmp/train_precision_quality"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    spec = model_spec(cfg, args.model)
    spec = dataclasses.replace(spec, data={**spec.data, "crop": args.crop, "length": args.length},
                               budget={**spec.budget, "max_steps": args.steps, "max_seconds": None})
    builder = task_builder(spec.method)
    train_clips = load_training_clips([args.render_root / s for s in args.train], clip_buffers(builder))
    validation_clips = load_training_clips([args.render_root / s for s in args.validate], clip_buffers(builder))
    sequences = task_sequence_config(builder, spec, train_clips + validation_clips)
    validation = fixed_batches(validation_clips, sequences, args.validation_sequences, batch_size=1,
                               seed=int(cfg["seed"]))
    shape = train_clips[0].samples["radiance"].shape
    print(f"torch {torch.__version__}, native bf16: {bf16_support()}; {args.threads} threads; load average "
          f"{' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"model {spec.id}: net {spec.net}, loss {spec.loss}, seed {spec.seed}, batch {spec.optimizer['batch_size']} x "
          f"{args.length} frames x {args.crop}^2, {args.steps} steps; training {args.train}, validation {args.validate} "
          f"({args.validation_sequences} sequences); clips (frames, layers, C, H, W) = {tuple(shape)}")
    runs = {"fp32": train("fp32", spec, cfg, SequenceDataset(train_clips, sequences, seed=spec.seed), validation,
                          "fp32", args),
            "bf16": train("bf16", spec, cfg, SequenceDataset(train_clips, sequences, seed=spec.seed), validation,
                          "bf16", args)}
    if args.control:
        runs["fp32_layout"] = train("fp32_layout", spec, cfg, SequenceDataset(train_clips, sequences, seed=spec.seed),
                                    validation, "fp32", args,
                                    channels_last=not resolve("fp32", args.channels_last).channels_last)
        other = dataclasses.replace(spec, seed=spec.seed + 1)
        runs["fp32_seed+1"] = train("fp32_seed+1", other, cfg, SequenceDataset(train_clips, sequences, seed=other.seed),
                                    validation, "fp32", args)
    names = list(runs)
    steps = sorted(set.intersection(*(set(run["rows"]) for run in runs.values())))
    print("\nvalidation (fp32 inference) at equal steps; dPSNR = run - fp32:")
    header = "  ".join(f"{name + ' PSNR':>17s}" for name in names)
    print(f"  {'step':>6s}  {header}  " + "  ".join(f"{'d ' + name:>16s}" for name in names[1:])
          + f"  {'fp32 val loss':>13s}  {'bf16 val loss':>13s}")
    differences: dict[str, list[float]] = {name: [] for name in names[1:]}
    for step in steps:
        psnr = {name: runs[name]["rows"][step]["val_psnr"] for name in names}
        for name in names[1:]:
            differences[name].append(psnr[name] - psnr["fp32"])
        print(f"  {step:6d}  " + "  ".join(f"{psnr[name]:17.3f}" for name in names) + "  "
              + "  ".join(f"{psnr[name] - psnr['fp32']:+16.3f}" for name in names[1:])
              + f"  {runs['fp32']['rows'][step]['val_loss']:13.5f}  {runs['bf16']['rows'][step]['val_loss']:13.5f}")
    for name in names[1:]:
        values = differences[name]
        later = values[len(values) // 2:]
        print(f"  {name} - fp32: at the last step {values[-1]:+.3f} dB; over the second half of the validations "
              f"mean {statistics.fmean(later):+.3f} dB, max |d| {max(map(abs, later)):.3f} dB")
    last = differences["bf16"][-1]
    verdict = "within" if math.isfinite(last) and abs(last) <= TOLERANCE_DB else "NOT within"
    print(f"  bf16 at step {steps[-1]}: {last:+.3f} dB, {verdict} {TOLERANCE_DB} dB of fp32")
    print("  seconds/step (runs not interleaved; machine load differs): "
          + ", ".join(f"{name} {run['seconds_per_step']:.3f}" for name, run in runs.items()))


if __name__ == "__main__":
    main()
