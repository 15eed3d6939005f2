"""Estimate the wall time of a config's whole DAG on this machine from measured rates (issue 11 §5).

Nothing is rendered or trained; every figure is a measured rate times the work the config asks for:

* render_reference: the config's reference samples per chunk (every scene, stability and volumetric clips
  included, each at its own reference spp and size) divided by the reference samples/s recorded in the frame
  sidecars of finished render folders (``--renders``, pooled; median, and the 25-75 % range over their frames,
  since the rate differs by scene several-fold), per reference integrator (``render.reference_integrator``;
  the stability clips always use the feature integrator, volumetric clips ``volpath``). Sidecars of the other
  surface integrator are scaled by ``benchmarks/reference_speed.py``'s measured rate ratio
  (``--reference-speed``);
* render_noisy: seconds per pixel-layer of the noisy sidecars (per integrator: surface features or the
  volumetric one), times the config's pixel-layers (spp + extra radiance layers) per chunk;
* train_denoiser: every model's steps (``budget.max_steps``) times its s/step: the elapsed seconds per step of
  the same model in a finished run (``--run``: ``models/*/summary.json``, validation and data preparation
  included; a model that shared the cores there is slower than it will be), else the step time of a
  training-speed record (``--train-speed``: ``benchmarks/train_speed.py --json`` or a run's
  ``timing/training.json``, the configured variant; the optimiser step alone, a lower bound). Ablation and
  capacity variants neither times take their base model's s/step scaled by their FLOPs per step (counted on
  one synthetic step each);
* every other rule: the job count of ``snakemake -n --forceall`` times the median seconds per job of that
  rule in a finished run's ``benchmarks/`` (``--run``); rules the run never ran are listed as unmeasured.

Render and timing jobs take every core (one at a time); training jobs run ``cores / training.threads`` at a
time (an observed s/step is the rate the model had beside another training: what it will have again), the
others ``cores / evaluation.threads``, so their wall time is their summed time divided by that.

Usage: python benchmarks/dag_budget.py [--config config/config.yaml] --renders RESULTS/renders [...]
           --train-speed training.json [--run RESULTS [RESULTS ...]] [--cores 2] [--reference-speed reference_speed.json]
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from run_summary import benchmark_jobs  # benchmarks/ is sys.path[0] when run as a script

#: Rules whose jobs take every core (they run one at a time).
EXCLUSIVE_RULES = ("render_noisy", "render_reference", "train_denoiser", "time_methods", "time_training")
#: Rules estimated from the config and measured rates rather than from a prior run's per-job median.
MODELLED_RULES = ("render_noisy", "render_reference", "train_denoiser")
#: benchmarks/<folder>/... -> rule, where the folder is not the rule's name (workflow/rules/*.smk). The
#: evaluation's folders hold one file per row job (denoise/{row}.tsv); a run from before the row jobs has one per
#: clip there (denoise/{row}/{scene}/spp{spp}.tsv), whose median is a clip's, not a row's.
BENCHMARK_FOLDERS = {"denoise": "denoise_row", "evaluate": "evaluate_row", "robustness": "robustness_row",
                     "denoise_scenario": "denoise_scenario_row", "score_scenario": "score_scenario_row",
                     "denoise_volume": "denoise_volume_row", "evaluate_volume": "evaluate_volume_row",
                     "robustness_volume": "robustness_volume_row", "train": "train_denoiser", "tune": "tune_method"}


#: Sidecar ``integrator`` of reference frames rendered before the key was recorded.
DEFAULT_REFERENCE_INTEGRATOR = "mcdn_features"
#: Sidecar ``integrator`` of surface noisy frames (they do not record it); volumetric clips record theirs.
DEFAULT_NOISY_INTEGRATOR = "mcdn_features"
#: Integrators of a volumetric clip's references and noisy layers (scenegen.volumes.render).
VOLUME_REFERENCE_INTEGRATOR, VOLUME_NOISY_INTEGRATOR = "volpath", "mcdn_volpath_features"


def sidecar_rates(*folders: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """({reference integrator: samples/s per frame}, {noisy integrator: seconds per pixel-layer per frame})
    from the frame sidecars of one or more render folders."""
    reference: dict[str, list[float]] = {}
    noisy: dict[str, list[float]] = {}
    for renders in folders:
        for path in renders.glob("*/reference/chunk_*/frame_*.json"):
            meta = json.loads(path.read_text())
            integrator = meta.get("integrator", DEFAULT_REFERENCE_INTEGRATOR)
            reference.setdefault(integrator, []).append(float(meta["samples_per_s"]))
        for path in renders.glob("*/noisy/chunk_*/frame_*.json"):
            meta = json.loads(path.read_text())
            layers = int(meta["spp"]) + int(meta.get("extra_radiance_spp", 0))
            noisy.setdefault(meta.get("integrator", DEFAULT_NOISY_INTEGRATOR), []).append(
                float(meta["timing_s"]) / (int(meta["width"]) * int(meta["height"]) * layers))
    if not reference or not noisy:
        sys.exit(f"{', '.join(map(str, folders))}: no reference or noisy frame sidecars "
                 "(*/{reference,noisy}/chunk_*/frame_*.json)")
    return ({name: np.asarray(rates) for name, rates in reference.items()},
            {name: np.asarray(costs) for name, costs in noisy.items()})


def reference_rates(sidecars: dict[str, np.ndarray], needed: set[str], speed: dict | None) -> dict[str, tuple[np.ndarray, str]]:
    """{integrator: (samples/s per frame, source)} for every integrator the config renders references with:
    the sidecars' own rates, or the other integrator's scaled by ``benchmarks/reference_speed.py``'s
    median path/features rate ratio (``--reference-speed``)."""
    out = {}
    for name in needed:
        if name in sidecars:
            out[name] = (sidecars[name], "sidecars")
            continue
        if name == VOLUME_REFERENCE_INTEGRATOR:
            sys.exit(f"no volumetric reference sidecars ({name!r}) in --renders (have: {', '.join(sidecars)}); "
                     "add a render folder that holds volumetric clips (e.g. a smoke run's renders)")
        other = "mcdn_features" if name == "path" else "path"
        if other not in sidecars or speed is None:
            sys.exit(f"no reference sidecars rendered with {name!r} in --renders (have: {', '.join(sidecars)}); "
                     "pass --reference-speed (benchmarks/reference_speed.py --json) to scale the other integrator's rates")
        ratio = float(speed["median_path_rate_ratio"])
        factor = ratio if name == "path" else 1.0 / ratio
        out[name] = (sidecars[other] * factor, f"{other} sidecars x {factor:.2f} (reference_speed.py)")
    return out


def render_work(cfg: dict) -> pd.DataFrame:
    """One row per (scene, chunk): reference samples and noisy pixel-layers the config asks for, and the
    integrators that render them (volumetric clips: one chunk each, at the ``volumes`` section's settings)."""
    from scenegen.catalog import (chunk_count, chunk_frames, scene_ids, scene_reference_spp, scene_render_config,
                                  stability_scene_ids, volume_scene_ids)

    from scenegen.scenarios import stability_control_ids

    # The stability clips and the control clips of the animated ones (empty unless stability.enabled).
    scenes = scene_ids(cfg) + stability_scene_ids(cfg) + stability_control_ids(cfg)
    rows = []
    for scene in scenes:
        render = scene_render_config(cfg, scene)
        pixels = int(render["width"]) * int(render["height"])
        layers = int(render["spp"]) + int(render.get("extra_radiance_spp") or 0)
        for chunk in range(chunk_count(cfg, scene)):
            frames = len(chunk_frames(cfg, scene, chunk))
            integrator = "path" if render.get("reference_integrator", "path") == "path" else "mcdn_features"
            rows.append({"scene": scene, "chunk": chunk, "frames": frames, "reference_integrator": integrator,
                         "noisy_integrator": DEFAULT_NOISY_INTEGRATOR,
                         "reference_samples": frames * pixels * scene_reference_spp(cfg, scene),
                         "noisy_pixel_layers": frames * pixels * layers})
    volumes = cfg.get("volumes") or {}
    for scene in volume_scene_ids(cfg):
        frames, pixels = int(volumes["frames"]), int(volumes["width"]) * int(volumes["height"])
        rows.append({"scene": scene, "chunk": 0, "frames": frames, "reference_integrator": VOLUME_REFERENCE_INTEGRATOR,
                     "noisy_integrator": VOLUME_NOISY_INTEGRATOR,
                     "reference_samples": frames * pixels * int(volumes["reference_spp"]),
                     "noisy_pixel_layers": frames * pixels * int(volumes["spp"])})
    return pd.DataFrame(rows)


def observed_step_seconds(runs: list[Path]) -> dict[str, float]:
    """{model id: elapsed seconds per step} of every trained model (``models/*/summary.json``) of finished runs,
    the first run that has it; validation and data preparation included, unlike ``time_training``."""
    observed: dict[str, float] = {}
    for run in runs:
        for path in sorted((run / "models").glob("*/summary.json")):
            summary = json.loads(path.read_text())
            steps, seconds = int(summary.get("steps") or 0), float(summary.get("elapsed_seconds") or 0.0)
            if steps > 0 and seconds > 0:
                observed.setdefault(path.parent.name, seconds / steps)
    return observed


def training_work(cfg: dict, speed: dict, observed: dict[str, float] | None = None) -> pd.DataFrame:
    """One row per model: steps, s/step and seconds. The s/step is the model's own in a finished run
    (``observed``: elapsed per step, validation included), else the training-speed record's step time, else its
    base model's scaled by their FLOPs per step."""
    import torch

    from denoisers.training.models import model_specs, same_training_as
    from denoisers.training.speed import make_trainer, step_flops
    from denoisers.training.synthetic import synthetic_batch
    from denoisers.training.tasks import task_builder

    measured = {}
    for model in speed["models"]:
        timed = {v["variant"]: v for v in model["variants"] if v.get("status") == "timed"}
        variant = timed.get(model["configured_variant"]) or timed.get("fp32_nchw")
        if variant:
            measured[model["model"]] = (variant["ms_per_step_median"] / 1e3, float(model["flops_per_step"]))
    specs = model_specs(cfg)
    bases = {spec.id: spec for spec in specs if spec.ablation is None}
    ablation_base = {ablation["id"]: ablation["model"] for ablation in cfg["training"].get("ablations", [])}
    rows = []
    torch.set_num_threads(1)   # FLOPs do not depend on threads; one thread never spin-waits on a busy machine
    with tempfile.TemporaryDirectory(prefix="dag_budget-") as work:
        for spec in specs:
            steps = int(spec.budget.get("max_steps") or 0)
            source = same_training_as(cfg, spec.id)
            if source is not None:   # its job copies the base's weights
                rows.append({"model": spec.id, "steps": 0, "s_per_step": 0.0, "seconds": 0.0,
                             "how": f"same training as {source}"})
                continue
            if observed and spec.id in observed:
                rows.append({"model": spec.id, "steps": steps, "s_per_step": observed[spec.id],
                             "seconds": steps * observed[spec.id], "how": "observed in --run"})
                continue
            if spec.id in measured:
                seconds_per_step, how = measured[spec.id][0], "measured"
            else:
                base = bases.get(ablation_base.get(spec.ablation))
                if base is None or base.id not in measured:
                    rows.append({"model": spec.id, "steps": steps, "s_per_step": np.nan, "seconds": np.nan,
                                 "how": "no measured base model"})
                    continue
                builder = task_builder(spec.method)
                batch = synthetic_batch(spec, builder.sample_buffers, pixel_buffers=builder.pixel_buffers,
                                        mean_buffers=builder.mean_buffers)
                flops = step_flops(make_trainer(spec, batch, "fp32", False, Path(work) / spec.id))
                base_seconds, base_flops = measured[base.id]
                seconds_per_step = base_seconds * flops / base_flops
                how = f"{base.id} x {flops / base_flops:.2f} FLOPs"
            rows.append({"model": spec.id, "steps": steps, "s_per_step": seconds_per_step,
                         "seconds": steps * seconds_per_step, "how": how})
    return pd.DataFrame(rows)


def dry_run_counts(config: Path) -> dict[str, int]:
    """Jobs per rule of ``snakemake -n --forceall`` for the config."""
    out = subprocess.run(["snakemake", "-n", "--forceall", "--quiet", "rules", "--configfile", str(config)],
                         capture_output=True, text=True, check=True).stdout
    counts = {}
    for line in out.splitlines():
        match = re.fullmatch(r"(\w+)\s+(\d+)", line.strip())
        if match and match.group(1) != "total":
            counts[match.group(1)] = int(match.group(2))
    return counts


def per_job_seconds(run: Path) -> dict[str, float]:
    """Median wall seconds per job of every rule with benchmark files under ``run``/benchmarks."""
    jobs = benchmark_jobs(run)
    rules = jobs["rule"].map(lambda folder: BENCHMARK_FOLDERS.get(folder, folder))
    return {rule: float(seconds) for rule, seconds in jobs.groupby(rules)["seconds"].median().items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--renders", type=Path, nargs="+", required=True,
                        help="finished render folders (frame sidecars; their rates are pooled per integrator)")
    parser.add_argument("--train-speed", type=Path, required=True, help="training-speed record (JSON)")
    parser.add_argument("--run", type=Path, nargs="+", default=None,
                        help="finished runs' folders (their benchmarks/); a rule's median comes from the first run "
                             "that has it (e.g. the default run, then the smoke run for rules the first lacks)")
    parser.add_argument("--step-only", action="store_true",
                        help="ignore the trained models' observed s/step in --run (use the training-speed record)")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--reference-speed", type=Path, default=None,
                        help="benchmarks/reference_speed.py --json output: scales the sidecars' reference rates "
                             "when they were rendered with the other integrator than the config's")
    args = parser.parse_args()

    from scenegen.config import load_config

    cfg = load_config(args.config)
    sidecars, noisy_cost = sidecar_rates(*args.renders)
    work = render_work(cfg)
    speed = json.loads(args.reference_speed.read_text()) if args.reference_speed else None
    rates = reference_rates(sidecars, set(work["reference_integrator"]), speed)
    print(f"config {args.config}: {work.scene.nunique()} scenes, {len(work)} chunks")
    reference_seconds = np.zeros(3)   # at the 75 %, median and 25 % rates
    for integrator, group in work.groupby("reference_integrator"):
        rate, source = rates[integrator]
        q25, q50, q75 = np.percentile(rate, [25, 50, 75])
        samples = float(group["reference_samples"].sum())
        reference_seconds += samples / np.array([q75, q50, q25])
        print(f"reference ({integrator}): {samples / 1e9:.2f} G samples at a median {q50 / 1e6:.2f} M samples/s "
              f"(25-75 %: {q25 / 1e6:.2f}-{q75 / 1e6:.2f}; {len(rate)} frames, {source})")
    noisy_seconds, noisy_how = 0.0, []
    for integrator, group in work.groupby("noisy_integrator"):
        if integrator not in noisy_cost:
            sys.exit(f"no noisy sidecars rendered with {integrator!r} in --renders (have: {', '.join(noisy_cost)})")
        cost = float(np.median(noisy_cost[integrator]))
        noisy_seconds += float(group["noisy_pixel_layers"].sum()) * cost
        noisy_how.append(f"{integrator} {cost * 1e9:.0f} ns per pixel-layer")
    fast, typical, slow = reference_seconds
    stages = [("render_reference", len(work), typical, f"{fast / 60:.0f}-{slow / 60:.0f} min"),
              ("render_noisy", len(work), noisy_seconds, "; ".join(noisy_how))]
    observed = observed_step_seconds(args.run) if args.run and not args.step_only else {}
    training = training_work(cfg, json.loads(args.train_speed.read_text()), observed)
    print(training.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    trainings_at_once = max(1, args.cores // int(cfg["training"].get("threads") or 1))
    stages.append(("train_denoiser", len(training), float(training["seconds"].sum()) / trainings_at_once,
                   f"steps x s/step (observed: validation included; step records: not), {trainings_at_once} at a time"))
    unmeasured = []
    if args.run is not None:
        counts, medians, source = dry_run_counts(args.config), {}, {}
        for run in args.run:
            for rule, seconds in per_job_seconds(run).items():
                if rule not in medians:
                    medians[rule], source[rule] = seconds, run
        parallel = max(1, args.cores // int(cfg["evaluation"].get("threads") or 1))
        for rule, count in counts.items():
            if rule in MODELLED_RULES or rule == "all":
                continue
            if rule not in medians:
                unmeasured.append(f"{rule} ({count})")
                continue
            concurrent = 1 if rule in EXCLUSIVE_RULES else parallel
            stages.append((rule, count, count * medians[rule] / concurrent,
                           f"{medians[rule]:.1f} s/job in {source[rule]}, {concurrent} at a time"))
    print(f"\n{'stage':<18} {'jobs':>5} {'wall min':>9}  how")
    for rule, jobs, seconds, how in stages:
        print(f"{rule:<18} {jobs:>5} {seconds / 60:>9.1f}  {how}")
    total = sum(seconds for *_, seconds, _ in stages if np.isfinite(seconds))
    print(f"{'total':<18} {'':>5} {total / 60:>9.1f}  = {total / 3600:.2f} h")
    if unmeasured:
        print("not estimated (no benchmark files in --run): " + ", ".join(unmeasured))


if __name__ == "__main__":
    main()
