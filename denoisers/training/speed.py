"""Training-step speed of the learned models (rule time_training, ``python -m denoisers time-training``,
``benchmarks/train_speed.py``; issue 11 §1: the configured step against today's float32 eager step).

Per model of ``training.models`` (ablation variants share their base's step), one trainer per variant on the
same fixed synthetic batch of the model's size (batch_size x length x crop^2); a timed call is the trainer's
own optimiser step (``Trainer._train_step``: learning rate, zero_grad, loss (bf16 autocast forward for bf16),
backward, Adam). Variants (:data:`VARIANTS`): fp32 / bf16 x NCHW / channels-last; ``fp32_nchw`` (the step
before the ``compute`` setting, the baseline) and the configured one (``compute`` resolved here) always run.
Every round runs every variant once, then float32 sgemm (MKL ``torch.mm``, oneDNN ``mkldnn_linear``) and a
bf16 ``torch.mm`` of ``gemm_size``^3, so load changes hit all alike; ``warmup`` untimed rounds first. Per
variant: ms/step per round, median, min, max; pixels/s (pixels per step / median); GFLOP/s = FLOPs of one
fp32 step (``torch.utils.flop_counter``: forward and backward, not Adam) / median, and its fraction of the
median faster-sgemm rate; the per-round speed-up over ``fp32_nchw`` and its median and range. Where bf16 is
emulated (no ``avx512_bf16`` / ``amx_bf16``: 7-16x slower than fp32), bf16 variants other than the configured
one run only ``emulated_bf16_repeats`` rounds (0: not timed, the record says why), keeping the job short.

Config-level helpers (:func:`speed_settings`, :func:`speed_models`, :func:`read_training_speed`) import no
torch (the Snakefile calls them while parsing); the measuring functions import it.
"""
from __future__ import annotations

import json
import logging
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from denoisers.training.models import model_specs
from denoisers.training.spec import ModelSpec

if TYPE_CHECKING:
    import torch

    from denoisers.training.loop import Trainer
    from denoisers.training.precision import StepPrecision

SPEED_SCHEMA = 1
#: Where rule time_training writes, below the experiment folder.
TRAINING_SPEED_FILE = "timing/training.json"
#: Issue 11 §1: the default step at least 1.6x faster than the fp32 eager step.
TARGET_SPEEDUP = 1.6
#: Variant id -> (label, precision, channels_last); the first is the baseline of every speed-up.
VARIANTS: dict[str, tuple[str, str, bool]] = {
    "fp32_nchw": ("fp32 NCHW", "fp32", False), "fp32_channels_last": ("fp32 channels-last", "fp32", True),
    "bf16_nchw": ("bf16 NCHW", "bf16", False), "bf16_channels_last": ("bf16 channels-last", "bf16", True)}
BASELINE = "fp32_nchw"
#: The schema's defaults of ``training.speed`` (tests/test_training_speed.py checks they agree).
DEFAULT_SPEED: dict[str, Any] = {"enabled": True, "variants": list(VARIANTS), "repeats": 5, "warmup": 1,
                                 "emulated_bf16_repeats": 1, "gemm_size": 1024, "threads": None}

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------ config
def speed_settings(cfg: dict) -> dict[str, Any]:
    """``training.speed`` with defaults, ``threads`` resolved (null: ``training.threads``, the training jobs')."""
    settings = {**DEFAULT_SPEED, **(cfg.get("training") or {}).get("speed", {})}
    unknown = sorted(set(settings["variants"]) - set(VARIANTS))
    if unknown:
        raise ValueError(f"training.speed.variants: unknown {unknown}; known: {', '.join(VARIANTS)}")
    threads = settings["threads"] or (cfg.get("training") or {}).get("threads", 2)
    return {**settings, "threads": int(threads)}


def speed_models(cfg: dict) -> list[ModelSpec]:
    """The models whose step the job times: ``training.models`` (not ablation variants); none if disabled."""
    if not speed_settings(cfg)["enabled"]:
        return []
    return [spec for spec in model_specs(cfg) if spec.ablation is None]


def read_training_speed(path: Path) -> dict[str, Any]:
    """The job's record (ValueError naming the file if it is not one of :data:`SPEED_SCHEMA`)."""
    record = json.loads(Path(path).read_text())
    if record.get("schema") != SPEED_SCHEMA or not isinstance(record.get("models"), list):
        raise ValueError(f"{path}: not a training-speed record of schema {SPEED_SCHEMA} (rerun rule time_training)")
    return record


def variant_of(step: StepPrecision) -> str:
    """The variant id of a resolved step arithmetic."""
    return next(key for key, (_, precision, layout) in VARIANTS.items()
                if (precision, layout) == (step.precision, step.channels_last))


# ----------------------------------------------------------------------------------------- timers
@dataclass
class Timed:
    """One timed call: key (variant id or gemm label), the call, FLOPs and pixels per call, timed rounds."""

    key: str
    run: Callable[[], Any]
    flops: int = 0
    pixels: int = 0
    rounds: int = 0
    seconds: list[float] = field(default_factory=list)
    first_call: float | None = None


def make_trainer(spec: ModelSpec, batch: dict[str, torch.Tensor], precision: str, channels_last: bool,
                 out_dir: Path) -> Trainer:
    """A trainer of ``spec``'s task (its optimiser settings, fresh weights from its seed) on ``batch``."""
    from denoisers.training.loop import Trainer, TrainerConfig
    from denoisers.training.synthetic import FixedBatch
    from denoisers.training.tasks import build_task

    opt = spec.optimizer
    config = TrainerConfig(seed=spec.seed, batch_size=opt["batch_size"], max_steps=10**9, lr=opt["lr"],
                           betas=tuple(opt["betas"]), schedule=dict(opt["schedule"]),
                           grad_clip_norm=opt.get("grad_clip_norm"), validate_every=0, checkpoint_every=0,
                           checkpoint_seconds=None, progress=False, precision=precision, channels_last=channels_last)
    trainer = Trainer(build_task(spec), FixedBatch(batch), [], config, out_dir)
    trainer._setup()  # model, Adam and seeds exactly as Trainer.run builds them
    return trainer


def step_flops(trainer: Trainer) -> int:
    """FLOPs of one optimiser step's forward and backward, counted on an extra (untimed) step."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with counter:
        trainer._train_step()
    return int(counter.get_total_flops())


def gemm_timers(n: int) -> list[Timed]:
    """float32 sgemm n^3 through MKL torch.mm and (if available) oneDNN mkldnn_linear, and a bfloat16 torch.mm."""
    import torch

    generator = torch.Generator().manual_seed(0)
    a, b = torch.randn(n, n, generator=generator), torch.randn(n, n, generator=generator)
    timers = [Timed("sgemm torch.mm (MKL)", lambda: torch.mm(a, b), 2 * n**3)]
    try:
        a_dnnl = a.to_mkldnn()
        torch._C._nn.mkldnn_linear(a_dnnl, b, None)          # a @ b.T: the same FLOPs
        timers.append(Timed("sgemm oneDNN (mkldnn_linear)", lambda: torch._C._nn.mkldnn_linear(a_dnnl, b, None),
                            2 * n**3))
    except (AttributeError, RuntimeError) as error:
        log.info("oneDNN sgemm unavailable: %s", error)
    a16, b16 = a.bfloat16(), b.bfloat16()
    return timers + [Timed("bf16 gemm torch.mm", lambda: torch.mm(a16, b16), 2 * n**3)]


def run_rounds(timers: list[Timed], repeats: int, warmup: int) -> None:
    """``warmup`` untimed rounds, then ``repeats`` timed ones; a timer runs in a round while it has rounds left
    (``rounds`` of them), every timer once per round in list order; fills ``seconds`` and ``first_call``."""
    for index in range(warmup + repeats):
        for timer in timers:
            if not timer.rounds or (index >= warmup and len(timer.seconds) >= timer.rounds):
                continue
            start = time.perf_counter()
            timer.run()
            elapsed = time.perf_counter() - start
            timer.first_call = elapsed if timer.first_call is None else timer.first_call
            if index >= warmup:
                timer.seconds.append(elapsed)
        log.info("round %d/%d done (load average %s)", index + 1, warmup + repeats, _load())


def _load() -> list[float]:
    return [round(value, 2) for value in os.getloadavg()]


# ----------------------------------------------------------------------------------------- the job
Plan = list[tuple[str, int, str]]     # (variant, timed rounds, note)


def _plan(spec: ModelSpec, settings: dict[str, Any], native_bf16: bool, why: str) -> tuple[str, Plan]:
    """(configured variant, [(variant, timed rounds, why fewer)]) of one model."""
    from denoisers.training.precision import resolve_compute

    configured = variant_of(resolve_compute(spec.compute))
    chosen = set(settings["variants"]) | {BASELINE, configured}
    plan = []
    for key in (k for k in VARIANTS if k in chosen):
        rounds, reason = settings["repeats"], ""
        if VARIANTS[key][1] == "bf16" and not native_bf16 and key != configured:
            rounds = min(rounds, settings["emulated_bf16_repeats"])
            reason = f"bf16 is emulated here ({why}): {rounds} round(s), training.speed.emulated_bf16_repeats"
            reason += " = 0, so not timed" if not rounds else ""
        plan.append((key, rounds, reason))
    return configured, plan


def _variant_record(key: str, timer: Timed, base: list[float], sgemm: float, configured: str, reason: str) -> dict:
    label, precision, layout = VARIANTS.get(key, (key, "", False))
    record: dict[str, Any] = {"variant": key, "label": label, "precision": precision, "channels_last": layout,
                              "configured": key == configured, "rounds": len(timer.seconds), "note": reason}
    if not timer.seconds:
        return {**record, "status": "not timed"}
    ms = [s * 1e3 for s in timer.seconds]
    median = statistics.median(ms)
    speedup = [b / m for b, m in zip(base, ms)]                # same round: the baseline ran in every round
    gflops = timer.flops / (median / 1e3) / 1e9
    return {**record, "status": "timed", "ms_per_step": ms, "ms_per_step_median": median,
            "ms_per_step_min": min(ms), "ms_per_step_max": max(ms), "first_call_ms": (timer.first_call or 0) * 1e3,
            "pixels_per_s": timer.pixels / (median / 1e3), "gflops_per_s": gflops,
            "fraction_of_sgemm": gflops / sgemm if sgemm > 0 else None, "speedup": speedup,
            "speedup_median": statistics.median(speedup), "speedup_min": min(speedup), "speedup_max": max(speedup)}


ExtraTimers = Callable[[ModelSpec, dict, "StepPrecision", Path], list[Timed]]


def time_training(cfg: dict, *, threads: int | None = None, settings: dict[str, Any] | None = None,
                  model_ids: list[str] | None = None, extra: ExtraTimers | None = None) -> dict[str, Any]:
    """Time the training step of every model of :func:`speed_models` (or ``model_ids`` of them) for the variants
    of ``settings`` (default ``training.speed``) with ``threads`` torch threads (default its ``threads``);
    ``extra(spec, batch, configured step, work dir)`` may add timers per model (benchmarks: torch.compile).
    Returns the JSON-serialisable record (module docstring; times in ms, rates per second)."""
    import torch

    from denoisers.provenance import cpu_model
    from denoisers.training.precision import BF16_CPU_FLAGS, bf16_support, cpu_flags, resolve_compute
    from denoisers.training.synthetic import synthetic_batch
    from denoisers.training.tasks import task_builder

    settings = {**speed_settings(cfg), **(settings or {})}
    threads = int(threads or settings["threads"])
    specs = [spec for spec in model_specs(cfg) if spec.ablation is None and (model_ids is None or spec.id in model_ids)]
    if not specs:
        raise ValueError(f"no model to time: training.models has none{'' if model_ids is None else f' of {model_ids}'}")
    native, why = bf16_support()
    previous_threads, start, load_start = torch.get_num_threads(), time.perf_counter(), _load()
    torch.set_num_threads(threads)
    models: list[tuple[ModelSpec, str, Plan, list[Timed], dict]] = []
    try:
        with tempfile.TemporaryDirectory(prefix="time_training-") as work:
            for spec in specs:
                configured, plan = _plan(spec, settings, native, why)
                builder = task_builder(spec.method)
                batch = synthetic_batch(spec, builder.sample_buffers, pixel_buffers=builder.pixel_buffers,
                                        mean_buffers=builder.mean_buffers)
                pixels = spec.optimizer["batch_size"] * spec.data["length"] * spec.data["crop"] ** 2
                timers, flops = [], 0
                for key, rounds, _ in plan:
                    _, precision, layout = VARIANTS[key]
                    trainer = make_trainer(spec, batch, precision, layout, Path(work) / f"{spec.id}-{key}")
                    flops = flops or step_flops(trainer)      # the baseline comes first: fp32 FLOPs
                    timers.append(Timed(key, trainer._train_step, flops, pixels, rounds))
                for timer in extra(spec, batch, resolve_compute(spec.compute), Path(work)) if extra else []:
                    timers.append(Timed(timer.key, timer.run, flops, pixels, settings["repeats"]))
                    plan.append((timer.key, settings["repeats"], "extra"))
                models.append((spec, configured, plan, timers, {"pixels": pixels, "flops": flops}))
            gemms = gemm_timers(settings["gemm_size"])
            for timer in gemms:
                timer.rounds = settings["repeats"]
            run_rounds([t for *_, timers, _ in models for t in timers] + gemms, settings["repeats"], settings["warmup"])
    finally:
        torch.set_num_threads(previous_threads)
    gemm = {t.key: [t.flops / s / 1e9 for s in t.seconds] for t in gemms}
    sgemm = [max(rates) for rates in zip(*(r for key, r in gemm.items() if key.startswith("sgemm")))]
    sgemm_median = statistics.median(sgemm)
    out = []
    for spec, configured, plan, timers, facts in models:
        base = [s * 1e3 for s in timers[0].seconds]
        variants = [_variant_record(key, timer, base, sgemm_median, configured, reason)
                    for (key, _, reason), timer in zip(plan, timers)]
        step = resolve_compute(spec.compute)
        out.append({"model": spec.id, "method": spec.method, "net": spec.net,
                    "batch": {"sequences": spec.optimizer["batch_size"], "frames": spec.data["length"],
                              "crop": spec.data["crop"], "spp": spec.data["spp"]},
                    "pixels_per_step": facts["pixels"], "flops_per_step": facts["flops"], "compute": step.to_dict(),
                    "configured_variant": configured, "variants": variants})
    return {"schema": SPEED_SCHEMA, "torch": torch.__version__, "threads": threads,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
            "cpu": {"capability": torch.backends.cpu.get_cpu_capability(), "native_bf16": native, "bf16_support": why,
                    "bf16_flags": sorted(set(BF16_CPU_FLAGS) & cpu_flags())},
            "repeats": settings["repeats"], "warmup": settings["warmup"],
            "emulated_bf16_repeats": settings["emulated_bf16_repeats"], "target_speedup": TARGET_SPEEDUP,
            "gemm": {"size": settings["gemm_size"], "gflops_per_s": gemm, "sgemm_gflops_per_s": sgemm,
                     "sgemm_gflops_per_s_median": sgemm_median},
            "models": out, "load_average": {"start": load_start, "end": _load()},
            "seconds": time.perf_counter() - start}


def describe_record(record: dict[str, Any]) -> list[str]:
    """Printable lines: per model and variant ms/step [min, max], Mpix/s, GFLOP/s, of sgemm, speed-up."""
    lines = [f"torch {record['torch']}, {record['threads']} thread(s), {record['cpu']['capability']}, native bf16 "
             f"{record['cpu']['native_bf16']} ({record['cpu']['bf16_support']}); median of {record['repeats']} "
             f"rounds after {record['warmup']}; sgemm {record['gemm']['sgemm_gflops_per_s_median']:.1f} GFLOP/s; "
             f"load {record['load_average']['start']} -> {record['load_average']['end']}; {record['seconds']:.0f} s"]
    for model in record["models"]:
        lines.append(f"model {model['model']}: {model['pixels_per_step']:,} px/step, "
                     f"{model['flops_per_step'] / 1e9:.2f} GFLOP/step; compute {model['compute']['precision']}"
                     f"{' channels-last' if model['compute']['channels_last'] else ''} ({model['compute']['reason']})")
        for v in model["variants"]:
            mark = "*" if v["configured"] else " "
            if v["status"] != "timed":
                lines.append(f" {mark}{v['label']:24s} not timed: {v['note']}")
                continue
            lines.append(f" {mark}{v['label']:24s} {v['ms_per_step_median']:9.1f} ms [{v['ms_per_step_min']:.1f}, "
                         f"{v['ms_per_step_max']:.1f}] {v['pixels_per_s'] / 1e6:7.3f} Mpx/s {v['gflops_per_s']:7.1f} "
                         f"GFLOP/s {v['fraction_of_sgemm']:6.1%} of sgemm {v['speedup_median']:5.2f}x "
                         f"over {len(v['ms_per_step'])} round(s)")
    return lines
