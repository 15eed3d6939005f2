"""Where a config's trainings stand in the store: finished, part-way or not started, with their measured cost.

A long experiment (the Isik run, issue 48) trains across many short-lived machines, so what is done and what is
left is read from the committed store, not from a results folder. ``python -m denoisers store progress --config C
[--markdown]`` lists every training of ``C`` (seed replicas and half-budget twins included):

* ``stored``: the finished model under this config's key (its steps and training wall time);
* ``part-way``: a stored checkpoint under this config's key (the step it reached, the time so far);
* ``not started``: neither; ``reuses <id>``: an ablation variant that publishes another model's weights.

``trained`` is the wall time of every session together (pauses included: a trainer stopped with ``kill -STOP``
while a test suite ran keeps its clock); ``s/step`` is the median of the trainer's logged step rates (curves.csv,
a checkpoint's history), which pauses and validation do not move. It comes from the row itself, else from the run it
shares (a twin is its full model's run stopped at
half its steps), else from a seed replica of the same model, else from a model of the same shape (same method,
data, loss, optimizer, budget, compute and network width and kind, only the network's switches differ, such as
Isik's ablations of the temporal model; labelled "same shape"); the estimate of what is left is that rate times the
steps left, on the host that measured it (precision and CPU are listed, a bf16 host trains at another rate than
an fp32 one). The totals count each run once: a twin's time is part of its full model's run, which continues it.

Which machine comes next is not known, so the totals also plan per step arithmetic (:func:`host_plan`): for a host
that trains in bf16, and one that trains in fp32, what is left of the runs it can start or continue, at rates that
rows of that arithmetic measured; a part-way run whose checkpoint holds the other arithmetic is listed apart (it
continues only on such a host, denoisers.store.session).
"""
from __future__ import annotations

import csv
import json
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from denoisers.store.entries import Entry, ModelStore
from denoisers.training.spec import ModelSpec
from denoisers.training.models import (half_of, replica_ids, replica_of, same_training_as, trained_model_specs)

STORED, PART_WAY, NOT_STARTED = "stored", "part-way", "not started"


@dataclass(frozen=True)
class TrainingProgress:
    """One training of a config. ``step`` and ``elapsed_s`` (wall seconds, all sessions together) are 0 when not
    started; ``precision`` and ``cpu`` describe the host that trained it (empty when not started)."""

    model_id: str
    state: str
    step: int
    max_steps: int
    elapsed_s: float
    precision: str = ""
    cpu: str = ""
    half_of: str | None = None
    reuses: str | None = None
    seconds_per_step: float | None = None


@dataclass(frozen=True)
class Estimate:
    """What is left of a row: ``remaining_s`` at the rate ``seconds_per_step`` measured on row ``rate_from``
    (None: no row of this model or of its shape has trained yet); ``same_shape``: ``rate_from`` is another model of
    the same shape (:func:`shape_of`), not a run or seed of this one."""

    remaining_steps: int
    seconds_per_step: float | None
    rate_from: str | None
    same_shape: bool = False

    @property
    def remaining_s(self) -> float | None:
        return None if self.seconds_per_step is None else self.remaining_steps * self.seconds_per_step


def _median_step_seconds(rates: Sequence[float]) -> float | None:
    """Median seconds per step of the trainer's logged rates (steps/s), None without any."""
    rates = [float(r) for r in rates if r not in (None, "") and float(r) > 0]
    return 1.0 / statistics.median(rates) if rates else None


def logged_step_seconds(entry: Entry) -> float | None:
    """Median seconds per training step of a stored model (its curves.csv) or checkpoint (its history)."""
    curves = entry.path / "curves.csv"
    if curves.exists():
        with curves.open(newline="") as handle:
            return _median_step_seconds([row.get("steps_per_s") for row in csv.DictReader(handle)])
    checkpoint = entry.path / "checkpoint.pt"
    if checkpoint.exists():
        from denoisers.training.checkpoints import load_checkpoint

        history = load_checkpoint(Path(checkpoint)).get("history") or []
        return _median_step_seconds([row.get("steps_per_s") for row in history])
    return None


def _row(model_id: str, state: str, entry: Entry | None, max_steps: int, full: str | None) -> TrainingProgress:
    if entry is None:
        return TrainingProgress(model_id, state, 0, max_steps, 0.0, half_of=full)
    record = entry.summary()
    compute = record.get("compute") or {}
    return TrainingProgress(model_id, state, int(record.get("steps", record.get("step")) or 0), max_steps,
                            float(record.get("elapsed_seconds") or 0.0), str(compute.get("precision", "?")),
                            str((record.get("provenance") or {}).get("cpu_model", "?")), half_of=full,
                            seconds_per_step=logged_step_seconds(entry))


def training_progress(cfg: dict, store: ModelStore | None = None) -> list[TrainingProgress]:
    """Every training of ``cfg`` (:func:`trained_model_specs` order) with its state in ``store`` (default: the
    config's)."""
    store = store or ModelStore.of(cfg)
    rows = []
    for spec in trained_model_specs(cfg):
        max_steps = int(spec.budget.get("max_steps") or 0)
        full = half_of(cfg, spec.id)
        reused = same_training_as(cfg, spec.id)
        if reused is not None:
            rows.append(TrainingProgress(spec.id, f"reuses {reused}", 0, max_steps, 0.0, half_of=full, reuses=reused))
            continue
        model = store.model_entry(cfg, spec.id)
        if model is not None:
            rows.append(_row(spec.id, STORED, model, max_steps, full))
            continue
        # A twin's run is its full model's: the full model's checkpoint past the twin's steps holds the twin too.
        checkpoint = store.checkpoint_entry(cfg, full or spec.id)
        if checkpoint is not None:
            rows.append(_row(spec.id, PART_WAY, checkpoint, max_steps, full))
            continue
        rows.append(_row(spec.id, NOT_STARTED, None, max_steps, full))
    return rows


def _rate_sources(cfg: dict, row: TrainingProgress) -> list[str]:
    """Rows whose measured rate stands for ``row``'s: itself, the run it shares, then the same model's seed
    replicas (and their twins)."""
    full = row.half_of or row.model_id
    base = (replica_of(cfg, full) or (full, 0))[0]
    siblings = [m for m in replica_ids(cfg, base) if m != full]
    return [row.model_id, full, f"{full}_half", *siblings, *(f"{m}_half" for m in siblings)]


#: ``net`` keys of the AFN, KPCN, RAE and NTASD configs that size a network (layers, features, kernels, what runs per
#: frame); models that differ only in other ``net`` keys, switches such as ``temporal_kernel`` or ``fixed_lambda``,
#: are of the same shape.
SHAPE_KEYS = ("width", "temporal", "kernels", "kernel_size", "kernel_kind", "affinity_dim", "dilate",
              "temporal_kernel_size", "embed_features", "layers", "features", "conv_size", "levels", "base_features",
              "growth", "final_features", "variant", "sampling", "max_samples")


def shape_of(spec: ModelSpec) -> str:
    """What fixes a training's cost per step, as a comparable key: everything but the seed, the id and the
    network's switches that are not in :data:`SHAPE_KEYS`."""
    net = {key: spec.net.get(key) for key in SHAPE_KEYS}
    return json.dumps([spec.method, net, spec.loss, spec.data, spec.optimizer, spec.budget, spec.compute,
                       spec.threads], sort_keys=True, default=str)


def _same_shape(cfg: dict, model_id: str) -> list[str]:
    """Full models of ``cfg`` of the same shape as ``model_id`` (config order), ``model_id`` itself left out."""
    specs = {spec.id: spec for spec in trained_model_specs(cfg)}
    own = specs.get(model_id)
    if own is None:
        return []
    key = shape_of(own)
    return [m for m, spec in specs.items() if m != model_id and half_of(cfg, m) is None and shape_of(spec) == key]


def estimate(cfg: dict, rows: Sequence[TrainingProgress], row: TrainingProgress,
             precision: str | None = None) -> Estimate:
    """What is left of ``row`` and how long it should take (:class:`Estimate`): at the rate of the row itself, its
    run, a seed replica (``rate_from`` that row), else of a model of the same shape (``same_shape`` True); with
    ``precision`` ("bf16", "fp32") only rows trained in that arithmetic lend their rate."""
    remaining = 0 if row.state == STORED or row.reuses else max(0, row.max_steps - row.step)
    by_id = {r.model_id: r for r in rows if precision is None or r.precision == precision}
    for source in _rate_sources(cfg, row):
        other = by_id.get(source)
        if other is not None and other.seconds_per_step is not None:
            return Estimate(remaining, other.seconds_per_step, source)
    if remaining:
        for source in _same_shape(cfg, row.half_of or row.model_id):
            other = by_id.get(source)
            if other is not None and other.seconds_per_step is not None:
                return Estimate(remaining, other.seconds_per_step, source, same_shape=True)
    return Estimate(remaining, None, None)


@dataclass(frozen=True)
class HostPlan:
    """What is left for a host that trains in ``precision``: ``seconds`` of training steps over the runs it can start
    or continue (``runs`` of them), at rates that rows of that arithmetic measured (:func:`estimate`); ``unknown``:
    such runs with no rate of that arithmetic; ``elsewhere``: part-way runs whose checkpoint holds another
    arithmetic (they continue on a host of that kind); ``measured_on``: the CPUs of the rows that lent the rates
    (one arithmetic runs at other rates on another CPU: on 2026-12-07 the temporal AFN took 2.8 s/step in bf16 on
    an Intel Xeon, 1.1 on an AMD EPYC)."""

    precision: str
    seconds: float
    runs: int
    unknown: list[str]
    elsewhere: list[str]
    measured_on: tuple[str, ...] = ()


def host_plan(cfg: dict, rows: Sequence[TrainingProgress], precision: str) -> HostPlan:
    """:class:`HostPlan` of ``rows`` (:func:`training_progress`) for a host whose step arithmetic is ``precision``;
    each run counted once (:func:`runs`)."""
    seconds, count, unknown, elsewhere, cpus = 0.0, 0, [], [], []
    cpu_of = {r.model_id: r.cpu for r in rows}
    for row in runs(rows):
        if row.state == PART_WAY and row.precision != precision:
            elsewhere.append(row.model_id)
            continue
        left = estimate(cfg, rows, row, precision)
        if not left.remaining_steps:
            continue
        count += 1
        if left.remaining_s is None:
            unknown.append(row.model_id)
        else:
            seconds += left.remaining_s
            cpus.append(cpu_of.get(left.rate_from) or "?")
    return HostPlan(precision, seconds, count, unknown, elsewhere, tuple(dict.fromkeys(sorted(cpus))))


#: The step arithmetics a host here trains in (denoisers.training.precision: bf16 where the CPU has it).
HOST_PRECISIONS = ("bf16", "fp32")


def host_plan_text(plan: HostPlan) -> str:
    """One sentence of the totals: what a host of ``plan.precision`` has left."""
    text = (f"On a host that trains in {plan.precision}: about {_hours(plan.seconds)} for the {plan.runs} runs it can "
            f"start or continue, at {plan.precision} rates"
            + (f" measured on {' and '.join(plan.measured_on)} (another CPU trains at other rates)"
               if plan.measured_on else ""))
    if plan.unknown:
        text += f" (not counting {len(plan.unknown)} with no {plan.precision} rate: {', '.join(plan.unknown)})"
    if plan.elsewhere:
        text += (f"; {len(plan.elsewhere)} part-way runs hold another arithmetic's checkpoint and continue on such "
                 f"a host ({', '.join(plan.elsewhere)})")
    return text + "."


def runs(rows: Sequence[TrainingProgress]) -> list[TrainingProgress]:
    """The rows that are runs of their own: every full model and every twin whose full model is not configured
    (a twin's time is counted with its full model's run)."""
    ids = {r.model_id for r in rows}
    return [r for r in rows if r.reuses is None and (r.half_of is None or r.half_of not in ids)]


def _hours(seconds: float | None) -> str:
    return "?" if seconds is None else f"{seconds / 3600:.2f} h"


def progress_table(cfg: dict, rows: Sequence[TrainingProgress], markdown: bool = False) -> str:
    """``rows`` as a table (plain text, or Markdown for the manual) with the totals under it."""
    header = ["model", "state", "step", "of", "wall so far", "s/step", "left (estimate)", "precision", "host"]
    lines = []
    for row in rows:
        left = estimate(cfg, rows, row)
        rate = row.seconds_per_step
        lines.append([row.model_id, row.state, str(row.step), str(row.max_steps),
                      _hours(row.elapsed_s) if row.elapsed_s else "-", f"{rate:.3f}" if rate else "-",
                      "-" if left.remaining_steps == 0 else
                      _hours(left.remaining_s) + ("" if left.rate_from in (None, row.model_id)
                                                   else f" (rate of {left.rate_from}"
                                                   + (", same shape)" if left.same_shape else ")")),
                      row.precision or "-", row.cpu or "-"])
    own = runs(rows)
    done = sum(r.elapsed_s for r in own)
    left = [estimate(cfg, rows, r) for r in own]
    unknown = [r.model_id for r, e in zip(own, left) if e.remaining_steps and e.remaining_s is None]
    counts = {state: sum(1 for r in rows if r.state == state) for state in (STORED, PART_WAY, NOT_STARTED)}
    totals = (f"{len(rows)} trainings: {counts[STORED]} stored, {counts[PART_WAY]} part-way, {counts[NOT_STARTED]} "
              f"not started, {len(rows) - sum(counts.values())} reuse another's weights. Training time so far "
              f"{_hours(done)} over {len(own)} runs (a twin's time is its full model's); left about "
              f"{_hours(sum(e.remaining_s or 0.0 for e in left))} of training steps at the logged rates (validation "
              f"not included)"
              + (f", not counting {len(unknown)} runs with no measured rate ({', '.join(unknown)})" if unknown else "")
              + ".")
    if any(e.remaining_steps for e in left):
        totals += ("\n\n" if markdown else "\n").join(
            ["", *(host_plan_text(host_plan(cfg, rows, p)) for p in HOST_PRECISIONS)])
    if markdown:
        table = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        table += ["| " + " | ".join(f"`{c}`" if i == 0 else c for i, c in enumerate(line)) + " |" for line in lines]
        return "\n".join(table) + "\n\n" + totals + "\n"
    widths = [max(len(h), *(len(line[i]) for line in lines)) if lines else len(h) for i, h in enumerate(header)]
    text = ["  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in [header, *lines]]
    return "\n".join(text) + "\n" + totals + "\n"
