"""Does a training-data switch help? Train the config's model once per arm -- arms differ only in training-data
keys, e.g. ``layers=random layers=first`` or ``crops=uniform crops=importance`` (issue 11 §2) -- and compare
validation loss / PSNR / SSIM at equal steps.

Every arm uses the config's settings of ``--model`` (network, loss, optimiser, schedule, seed, compute), with
the data's crop and sequence length overridden to fit the renders (``--crop``, ``--length``) and then the
arm's data keys; the same seed, and the same fixed validation sequences (seeded by the global seed, without
augmentation; validation always uses random layers and uniform crops, so the arms are validated on identical
data). After training, each arm's final weights are scored per validation sequence, and every arm is compared
with the first arm by the paired per-sequence PSNR difference, its mean and 95 % t-interval (scipy.stats.t).
The interval covers the validation sequences only (one training run per arm, one seed): it says whether the
difference is larger than the spread over validation data, not over training seeds.

Training scenes come from ``--train-root`` (default ``--render-root``), validation scenes from ``--render-root``.
An arm may also name its own training scenes and their root with the non-data keys ``train`` (scene ids joined
by ``+``, or a range ``train_000..train_005``) and ``root`` -- e.g. the data-scale comparison of issue 11 §2,
``root=A,train=train_000..train_005`` (6 scenes with 1024-spp references) against
``root=B,train=train_000..train_023`` (24 scenes with 256-spp references). ``gbuffer_albedo_spp=K`` gives an arm
an antialiased G-buffer albedo (the mean of K jittered primary rays per pixel, rendered from ``--scene-root``)
in its training and validation clips instead of the stored pixel-centre one: the same validation crops, so the
pairing holds (docs/findings.md "RAE: demodulation by an aliased albedo"). Every arm prints the render time of
its training data: the sum of the ``timing_s`` of the noisy and reference sidecars of its training clips.
Runs go to ``--out``/<arm>/ (trainer directories: a rerun with the same settings resumes, and finishes at once
when done). Training is slow on a CPU: the checks in docs/findings.md use tiny settings only.

Usage: python benchmarks/train_data_choice.py [--config config/config.yaml] [--model rae]
           [--render-root results/smoke/renders] [--train-root DIR] [--train train_000] [--validate train_001]
           [--arms layers=random layers=first] [--steps 1000] [--crop 32] [--length 3] [--validate-every 100]
           [--validation-sequences 8] [--threads 2] [--out /tmp/train_data_choice]
Arm syntax: key=value[,key=value...] over the training_data keys of the schema, e.g.
``crops=importance,importance_floor=0.1``; ``net.<key>=value`` overrides the network instead (a size
comparison on identical data, e.g. ``net.width=0.5 net.width=0.25``), ``opt.<key>=value`` the optimiser
(e.g. ``opt.ema_decay=null opt.ema_decay=0.99``; dotted keys nest: ``opt.schedule.name=cosine,
opt.schedule.total_steps=3000`` replaces the schedule), ``comp.<key>=value`` the step arithmetic (e.g.
``comp.precision=fp32 comp.precision=bf16``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import statistics
from pathlib import Path
from typing import Any

import jsonschema
import torch
import yaml
from scipy import stats

from remodulation_ceiling import rendered_footprint_albedo  # benchmarks/ is sys.path[0] when run as a script
from train_precision_quality import train
from denoisers.training.data import SequenceDataset, fixed_batches, load_training_clips
from denoisers.training.job import clip_buffers, task_sequence_config
from denoisers.training.models import _schema_defaults, model_spec
from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import task_builder
from scenegen.config import load_config


#: Arm keys that are not training-data keys: the arm's training scenes, the folder holding their renders, and
#: ``gbuffer_albedo_spp`` (K > 1: the G-buffer albedo of the arm's training and validation clips is replaced by
#: its mean over K jittered primary rays per pixel, rendered here from the scenes: the antialiased G-buffer
#: albedo that render.gbuffer_albedo_spp stores, without re-rendering; 1 keeps the stored one).
SCENE_KEYS: tuple[str, ...] = ("train", "root", "gbuffer_albedo_spp")
#: Arm keys starting with this override the model's ``net`` (e.g. ``net.width=0.25``): a size comparison on
#: the same data and validation sequences (the network's config class checks the key when it is built).
NET_PREFIX = "net."
#: Arm keys starting with this override the model's ``optimizer`` (e.g. ``opt.ema_decay=0.99``).
OPT_PREFIX = "opt."
#: Arm keys starting with this override the model's ``compute`` (e.g. ``comp.precision=fp32``): the step
#: arithmetic, e.g. to ask whether bf16 autocast costs something PSNR does not see.
COMPUTE_PREFIX = "comp."


def scene_list(text: str) -> list[str]:
    """``a+b+c`` or a range ``train_000..train_005`` (same prefix, inclusive) -> scene ids."""
    if ".." in text:
        first, last = text.split("..", 1)
        prefix, start = first.rsplit("_", 1)
        last_prefix, stop = last.rsplit("_", 1)
        if prefix != last_prefix:
            raise ValueError(f"scene range {text!r}: both ends need the same prefix")
        return [f"{prefix}_{i:0{len(start)}d}" for i in range(int(start), int(stop) + 1)]
    return [scene for scene in text.split("+") if scene]


def split_arm(text: str) -> tuple[dict[str, str], str]:
    """An arm's scene keys (``train``, ``root``) and the rest of its text (the data and net keys)."""
    scene_keys, rest = {}, []
    for part in filter(None, text.split(",")):
        key = part.partition("=")[0].strip()
        if key in SCENE_KEYS:
            scene_keys[key] = part.partition("=")[2].strip()
        else:
            rest.append(part)
    return scene_keys, ",".join(rest)


def prefixed_overrides(text: str, prefix: str = NET_PREFIX) -> dict[str, Any]:
    """An arm's ``<prefix><key>=value`` parts (``net.``, ``opt.`` or ``comp.``) as {key: value}; a dotted key
    builds a nested value, e.g. ``opt.schedule.name=cosine,opt.schedule.total_steps=3000`` -> {'schedule':
    {'name': 'cosine', 'total_steps': 3000}} (which replaces the whole base value of that key)."""
    out: dict[str, Any] = {}
    for part in filter(None, split_arm(text)[1].split(",")):
        key, _, value = part.partition("=")
        if key.strip().startswith(prefix):
            *parents, leaf = key.strip()[len(prefix):].split(".")
            target = out
            for parent in parents:
                target = target.setdefault(parent, {})
            target[leaf] = yaml.safe_load(value)
    return out


def render_seconds(render_dirs: list[Path]) -> float:
    """Render time of clips: the sum of ``timing_s`` over every noisy and reference frame sidecar below them."""
    total = 0.0
    for render_dir in render_dirs:
        sidecars = sorted(Path(render_dir).glob("*/chunk_*/frame_*.json"))
        if not sidecars:
            raise FileNotFoundError(f"{render_dir}: no frame sidecars (*/chunk_*/frame_*.json)")
        total += sum(float(json.loads(path.read_text())["timing_s"]) for path in sidecars)
    return total


def parse_arm(text: str, base: dict[str, Any]) -> dict[str, Any]:
    """``key=value[,key=value]`` -> ``base`` data with the keys overridden and checked against the schema
    (``$defs/training_data``); ValueError naming the bad key. Scene keys (:data:`SCENE_KEYS`) are ignored here."""
    overrides: dict[str, Any] = {}
    for part in filter(None, split_arm(text)[1].split(",")):
        key, sep, value = part.partition("=")
        if not sep:
            raise ValueError(f"arm {text!r}: {part!r} is not key=value")
        if not key.strip().startswith((NET_PREFIX, OPT_PREFIX, COMPUTE_PREFIX)):
            overrides[key.strip()] = yaml.safe_load(value)
    try:
        return _schema_defaults("training_data", {**base, **overrides})
    except jsonschema.ValidationError as err:
        where = ".".join(map(str, err.absolute_path)) or "data"
        raise ValueError(f"arm {text!r}: data key {where!r}: {err.message}") from None


def with_footprint_albedo(clips: list, cfg: dict, scene_root: Path, spp: int, cache: dict) -> list:
    """Copies of ``clips`` whose ``gbuffer["albedo"]`` (T, 3, H, W) is the mean over ``spp`` jittered primary rays
    per pixel (rendered from ``scene_root``/<scene>; cached in ``cache`` by (scene, spp)); ``spp`` <= 1 returns
    ``clips`` unchanged."""
    if spp <= 1:
        return clips
    out = []
    for clip in clips:
        key = (clip.scene, spp)
        if key not in cache:
            cache[key] = rendered_footprint_albedo(cfg, scene_root / clip.scene, clip.frames, spp, "gbuffer")
        if cache[key].shape != clip.gbuffer["albedo"].shape:
            raise ValueError(f"{clip.scene}: rendered albedo {cache[key].shape} != stored "
                             f"{clip.gbuffer['albedo'].shape}")
        out.append(dataclasses.replace(clip, gbuffer={**clip.gbuffer, "albedo": cache[key]}))
    return out


def t_interval(values: list[float], level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high) of the Student-t interval of the mean of ``values`` (nan bounds for fewer than 2)."""
    mean = statistics.fmean(values)
    if len(values) < 2:
        return mean, float("nan"), float("nan")
    half = stats.t.ppf(0.5 + level / 2, len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return mean, mean - half, mean + half


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    parser.add_argument("--model", default="rae")
    parser.add_argument("--render-root", type=Path, default=Path("results/smoke/renders"))
    parser.add_argument("--train-root", type=Path, default=None, help="root of the training scenes (default: --render-root)")
    parser.add_argument("--train", nargs="+", default=["train_000"])
    parser.add_argument("--validate", nargs="+", default=["train_001"])
    parser.add_argument("--arms", nargs="+", default=["layers=random", "layers=first"])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--crop", type=int, default=32)
    parser.add_argument("--length", type=int, default=3)
    parser.add_argument("--validate-every", type=int, default=100)
    parser.add_argument("--validation-sequences", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("/tmp/train_data_choice"))
    parser.add_argument("--scene-root", type=Path, default=None,
                        help="generated scenes, for arms with gbuffer_albedo_spp (default: <render-root>/../scenes)")
    args = parser.parse_args()
    if len(set(args.arms)) != len(args.arms):
        parser.error(f"--arms repeats an arm: {args.arms}")
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    spec = model_spec(cfg, args.model)
    base_data = {**spec.data, "crop": args.crop, "length": args.length}
    try:
        arms = {arm: parse_arm(arm, base_data) for arm in args.arms}
    except ValueError as err:
        parser.error(str(err))
    base = dataclasses.replace(spec, data=base_data, budget={**spec.budget, "max_steps": args.steps, "max_seconds": None})
    args.channels_last = base.compute.get("channels_last", "auto")   # read by train()
    builder = task_builder(base.method)
    buffers = clip_buffers(builder)
    train_root = args.train_root or args.render_root
    arm_scenes: dict[str, list[Path]] = {}
    for arm in args.arms:
        keys = split_arm(arm)[0]
        root = Path(keys.get("root", train_root))
        arm_scenes[arm] = [root / scene for scene in (scene_list(keys["train"]) if "train" in keys else args.train)]
    train_clips = load_training_clips(arm_scenes[args.arms[0]], buffers)
    validation_clips = load_training_clips([args.render_root / s for s in args.validate], buffers)
    validation_config = task_sequence_config(builder, base, validation_clips)
    scene_root = args.scene_root or args.render_root.parent / "scenes"
    footprints: dict = {}

    def arm_albedo_spp(arm: str) -> int:
        return int(split_arm(arm)[0].get("gbuffer_albedo_spp", 1))

    def arm_validation(arm: str) -> list:
        clips = with_footprint_albedo(validation_clips, cfg, scene_root, arm_albedo_spp(arm), footprints)
        return fixed_batches(clips, validation_config, args.validation_sequences, batch_size=1, seed=int(cfg["seed"]))
    shape = train_clips[0].samples["radiance"].shape
    print(f"torch {torch.__version__}; {args.threads} threads; load average "
          f"{' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"model {base.id}: net {base.net}, loss {base.loss}, seed {base.seed}, batch {base.optimizer['batch_size']} x "
          f"{args.length} frames x {args.crop}^2, {args.steps} steps; training {args.train} ({train_root}), "
          f"validation {args.validate} ({args.render_root}, {args.validation_sequences} sequences); "
          f"clips (frames, layers, C, H, W) = {tuple(shape)}")

    runs: dict[str, dict[str, Any]] = {}
    for arm, data in arms.items():
        arm_spec: ModelSpec = dataclasses.replace(base, data=data, net={**base.net, **prefixed_overrides(arm)},
                                                  optimizer=_schema_defaults("training_optimizer", {
                                                      **base.optimizer, **prefixed_overrides(arm, OPT_PREFIX)}),
                                                  compute=_schema_defaults("training_compute", {
                                                      **base.compute, **prefixed_overrides(arm, COMPUTE_PREFIX)}))
        clips = with_footprint_albedo(load_training_clips(arm_scenes[arm], buffers), cfg, scene_root,
                                      arm_albedo_spp(arm), footprints)
        validation = arm_validation(arm)
        seconds = render_seconds(arm_scenes[arm])
        print(f"{arm}: {len(clips)} training clips ({', '.join(p.name for p in arm_scenes[arm])}), "
              f"{sum(len(c.frames) for c in clips)} frames, rendered in {seconds / 60:.1f} min (sidecars)", flush=True)
        dataset = SequenceDataset(clips, task_sequence_config(builder, arm_spec, clips + validation_clips),
                                  seed=arm_spec.seed)
        name = re.sub(r"[^A-Za-z0-9_.=-]+", "_", arm)
        runs[arm] = train(name, arm_spec, cfg, dataset, validation, arm_spec.compute.get("precision", "auto"), args,
                          channels_last=arm_spec.compute.get("channels_last", "auto"))
        trainer = runs[arm]["trainer"]
        runs[arm]["sequences"] = [trainer.evaluate([batch]) for batch in validation]

    names = list(runs)
    width = max(len(arm) for arm in names)
    steps = sorted(set.intersection(*(set(run["rows"]) for run in runs.values())))
    print("\nvalidation at equal steps (mean over the validation sequences):")
    print(f"  {'step':>6s}  {'arm':<{width}s}  {'val loss':>10s}  {'PSNR dB':>8s}  {'SSIM':>7s}")
    for step in steps:
        for arm in names:
            row = runs[arm]["rows"][step]
            print(f"  {step:6d}  {arm:<{width}s}  {row['val_loss']:10.5f}  {row['val_psnr']:8.3f}  {row['val_ssim']:7.4f}")
    reference = names[0]
    print(f"\npaired per-validation-sequence PSNR difference of the final weights (step {args.steps}), arm - {reference}:")
    print(f"  {'arm':<{width}s}  {'mean dB':>8s}  {'95% t-interval':>20s}  {'wins':>7s}")
    for arm in names[1:]:
        differences = [a["psnr"] - b["psnr"] for a, b in zip(runs[arm]["sequences"], runs[reference]["sequences"])]
        mean, low, high = t_interval(differences)
        wins = sum(d > 0 for d in differences)
        print(f"  {arm:<{width}s}  {mean:+8.3f}  [{low:+8.3f}, {high:+8.3f}]  {wins:3d}/{len(differences):<3d}")
    print("  training-data render time (sidecars): " + ", ".join(
        f"{arm} {render_seconds(arm_scenes[arm]) / 60:.1f} min" for arm in names))
    print("  seconds/step (runs not interleaved; machine load differs): "
          + ", ".join(f"{arm} {run['seconds_per_step']:.3f}" for arm, run in runs.items()))


if __name__ == "__main__":
    main()
