"""CPU against CUDA on one machine, side by side: rendering, each model's training step, each row's inference.

    python benchmarks/device_check.py --config config/config.yaml --out DIR [--steps 20] [--frames 4]

Writes ``DIR/device_check.json`` and prints one line per measurement. Sections (each one's failure is recorded,
the others still run):

* ``devices``: what the CPU and the GPU are (denoisers.device.device_info).
* ``render``: the config's first test scene, its first noisy chunk and its first reference chunk (at
  ``--reference-spp``) rendered with ``cuda_ad_rgb``, against the same scene rendered with ``llvm_ad_rgb`` by
  ``--make-render-baseline DIR`` on a machine with LLVM (the GPU machine's image has none, so the CPU side of
  this ratio is another machine, said so in the record); samples/s from the frames' sidecars; *statistical
  equality*: per pixel, the difference of the radiance means over every layer and frame divided by its standard
  error (z); the image-mean z and the share of pixels with |z| > 3 and > 4 (about 2.7e-3 and 6e-5 for two equal
  distributions with Gaussian means; heavy-tailed paths push them up), and the PSNR of one reference against the
  other beside each reference's halves PSNR.
* ``training``: per model of ``training.models`` with distinct settings (``--all-models``: the ablation variants
  too), timed optimiser steps after 3 untimed ones on the fixed synthetic batch of its size
  (denoisers.training.synthetic), fp32: ``--cpu-steps`` on the CPU with every core, ``--steps`` on CUDA; ms per
  step, median.
* ``inference``: per evaluation row of the config at its first spp, on the CPU noisy clip: the row's method with
  an untrained network where it needs one (weights of the training section's first step, so CPU and CUDA run the
  same network), run over ``--frames`` frames on the CPU (every core) and on CUDA, 3 passes each after one
  warm-up; ms per frame (median of passes) and the PSNR of the CUDA output against the CPU output.

Speed only counts as a ratio measured here, in one run on one machine.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _log(message: str) -> None:
    print(message, flush=True)


def _section(report: dict, name: str, function, *args: Any) -> None:
    started = time.perf_counter()
    try:
        report[name] = function(*args)
    except Exception as error:  # noqa: BLE001 -- one broken section must not hide the others
        report[name] = {"error": f"{type(error).__name__}: {error}", "traceback": traceback.format_exc()[-4000:]}
        _log(f"[{name}] FAILED: {type(error).__name__}: {error}")
    report.setdefault("seconds", {})[name] = round(time.perf_counter() - started, 1)


# ------------------------------------------------------------------------------------------------ render
def render_one(config: str, device: str, scene_dir: str, out_dir: str, reference_spp: int, generate: bool) -> dict:
    """(In a child process.) Render chunk 0 of the first test scene with ``device``; generate the scene first if
    asked. Returns timings and samples/s."""
    from denoisers.device import resolve_config_device
    from scenegen.catalog import scene_ids
    from scenegen.config import load_config
    from scenegen.jobs import run_generate, run_render_noisy, run_render_reference

    cfg = load_config(config)
    cfg["compute"] = {"device": device}
    cfg["render"]["reference_spp"] = cfg["render"]["test_reference_spp"] = int(reference_spp)
    resolve_config_device(cfg)
    scene = next(s for s in scene_ids(cfg) if s.startswith("test_"))
    record: dict[str, Any] = {"variant": cfg["render"]["variant"], "scene": scene}
    if generate:
        started = time.perf_counter()
        run_generate(cfg, scene, Path(scene_dir))
        record["generate_s"] = time.perf_counter() - started
    for kind, job in (("noisy", run_render_noisy), ("reference", run_render_reference)):
        started = time.perf_counter()
        job(cfg, scene, 0, Path(scene_dir), Path(out_dir) / kind / "chunk_000")
        record[f"{kind}_s"] = time.perf_counter() - started
        rates = [json.loads(p.read_text()).get("samples_per_s") for p in
                 sorted((Path(out_dir) / kind / "chunk_000").glob("frame_*.json"))]
        record[f"{kind}_samples_per_s"] = [float(r) for r in rates if r]
    return record


def radiance_statistics(render_dir: Path) -> dict[str, Any]:
    """Per-pixel mean and variance (3, H, W) of the radiance over every layer and frame of a rendered clip, its
    layer count, the per-(frame, layer) image means, the reference frames and their halves' PSNR."""
    import numpy as np

    from scenegen.dataset import load_clip

    clip = load_clip(render_dir, buffers=("radiance",), reference=True)
    samples = clip.samples["radiance"]                                # (T, S, 3, H, W)
    return {"mean": samples.mean(axis=(0, 1)), "var": samples.var(axis=(0, 1), ddof=1),
            "n": np.array(samples.shape[0] * samples.shape[1]), "image_means": samples.mean(axis=(2, 3, 4)).ravel(),
            "reference": clip.reference["radiance"],
            "psnr_halves": np.array([m.get("psnr_halves", np.nan) for m in clip.reference_meta or []], dtype=float)}


def equality(cpu: dict[str, Any], gpu: dict[str, Any]) -> dict[str, Any]:
    """z of the per-pixel radiance means of two renders of one scene (CPU against CUDA), of their image means,
    and the PSNR of one reference against the other beside each one's halves PSNR."""
    import numpy as np

    se = np.sqrt((cpu["var"] + gpu["var"]) / float(cpu["n"]))
    z = np.where(se > 0, (cpu["mean"] - gpu["mean"]) / np.where(se > 0, se, 1.0), 0.0)
    a, b = cpu["image_means"], gpu["image_means"]
    image_z = (a.mean() - b.mean()) / math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
    ref_a, ref_b = cpu["reference"], gpu["reference"]
    mse = float(np.mean((ref_a - ref_b) ** 2))
    peak = float(max(ref_a.max(), ref_b.max()))
    return {"layers_per_pixel": int(cpu["n"]), "image_mean_z": float(image_z),
            "pixels_abs_z_over_3": float(np.mean(np.abs(z) > 3)), "pixels_abs_z_over_4": float(np.mean(np.abs(z) > 4)),
            "max_abs_z": float(np.abs(z).max()),
            "reference_psnr_cpu_vs_cuda_db": 10 * math.log10(peak ** 2 / mse) if mse > 0 else float("inf"),
            "reference_psnr_halves_cpu_db": [float(v) for v in cpu["psnr_halves"]],
            "reference_psnr_halves_cuda_db": [float(v) for v in gpu["psnr_halves"]]}


def _render_child(config: str, device: str, scene_dir: Path, out: Path, reference_spp: int, generate: bool) -> dict:
    command = [sys.executable, __file__, "--render-child", device, "--config", config, "--scene-dir", str(scene_dir),
               "--out", str(out), "--reference-spp", str(reference_spp)] + (["--generate"] if generate else [])
    done = subprocess.run(command, capture_output=True, text=True, timeout=1200)
    if done.returncode:
        raise RuntimeError(f"{device} render failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def render_baseline(config: str, baseline: Path, reference_spp: int) -> dict:
    """The CPU side of the render comparison, made on a machine whose Mitsuba has LLVM (the GPU machine's image has
    no libLLVM): the scene, its llvm_ad_rgb render's statistics (``cpu_stats.npz``) and timings (``cpu.json``)."""
    import numpy as np

    from denoisers.device import device_info

    record = _render_child(config, "cpu", baseline / "scene", baseline / "render_cpu", reference_spp, True)
    record["devices"] = {"cpu": device_info("cpu")}
    np.savez_compressed(baseline / "cpu_stats.npz", **radiance_statistics(baseline / "render_cpu"))
    (baseline / "cpu.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def render_section(config: str, work: Path, reference_spp: int, baseline: Path) -> dict:
    """cuda_ad_rgb renders of the baseline's scene against its llvm_ad_rgb statistics and timings."""
    import numpy as np

    cpu = json.loads((baseline / "cpu.json").read_text())
    gpu = _render_child(config, "cuda", baseline / "scene", work / "render_cuda", reference_spp, False)
    result: dict[str, Any] = {"cpu": cpu, "cuda": gpu}
    with np.load(baseline / "cpu_stats.npz") as stats:
        result["equality"] = equality(dict(stats), radiance_statistics(work / "render_cuda"))
    _log(f"[render] cuda: {json.dumps(gpu)}")
    _log(f"[render] equality: {json.dumps(result['equality'])}")
    for kind in ("noisy", "reference"):
        result[f"{kind}_speedup_vs_baseline_machine"] = (statistics.median(gpu[f"{kind}_samples_per_s"])
                                                         / statistics.median(cpu[f"{kind}_samples_per_s"]))
    return result


# ---------------------------------------------------------------------------------------------- training
def _distinct_specs(cfg: dict, all_models: bool = False) -> list:
    """The config's models with distinct settings (seed and budget aside): those of ``training.models``, or with
    ``all_models`` every ablation variant too."""
    from denoisers.training.models import model_spec, model_specs

    specs_in = model_specs(cfg) if all_models else [model_spec(cfg, m["id"]) for m in cfg["training"]["models"]]
    seen, specs = set(), []
    for spec in specs_in:
        settings = _training_settings(spec)
        if settings not in seen:
            seen.add(settings)
            specs.append(spec)
    return specs


def _time_steps(spec, batch, device: Any, threads: int, steps: int, out_dir: Path):
    import torch

    from denoisers.device import default_device, synchronize
    from denoisers.training.loop import Trainer, TrainerConfig
    from denoisers.training.on_device import place
    from denoisers.training.synthetic import FixedBatch
    from denoisers.training.tasks import build_task

    torch.set_num_threads(threads)
    opt = spec.optimizer
    config = TrainerConfig(seed=spec.seed, batch_size=opt["batch_size"], max_steps=10**9, lr=opt["lr"],
                           betas=tuple(opt["betas"]), schedule=dict(opt["schedule"]),
                           grad_clip_norm=opt.get("grad_clip_norm"), validate_every=0, checkpoint_every=0,
                           checkpoint_seconds=None, progress=False, precision="fp32", channels_last=False)
    task, data, _ = place(build_task(spec), FixedBatch(batch), [], device)
    trainer = Trainer(task, data, [], config, out_dir)
    seconds = []
    with default_device(device):
        trainer._setup()
        for step in range(3 + steps):
            synchronize(device)
            started = time.perf_counter()
            trainer._train_step()
            synchronize(device)
            if step >= 3:
                seconds.append(time.perf_counter() - started)
    return trainer, 1000 * statistics.median(seconds)


def training_section(cfg: dict, steps: int, cpu_steps: int, all_models: bool, work: Path, models: dict) -> dict:
    import torch

    from denoisers.training.checkpoints import save_atomic
    from denoisers.training.loop import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
    from denoisers.training.synthetic import synthetic_batch
    from denoisers.training.tasks import task_builder

    cores = os.cpu_count() or 1
    rows = {}
    for spec in _distinct_specs(cfg, all_models):
        builder = task_builder(spec.method)
        batch = synthetic_batch(spec, builder.sample_buffers, pixel_buffers=builder.pixel_buffers,
                                mean_buffers=builder.mean_buffers)
        row: dict[str, Any] = {"method": spec.method, "batch": spec.optimizer["batch_size"],
                               "length": spec.data["length"], "crop": spec.data["crop"]}
        try:
            trainer, row["cpu_all_cores_ms"] = _time_steps(spec, batch, torch.device("cpu"), cores, cpu_steps,
                                                           work / f"cpu_{spec.id}")
            path = work / "models" / spec.id / "best.pt"
            path.parent.mkdir(parents=True, exist_ok=True)
            save_atomic({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": "model",
                         "net": trainer.task.net_spec(), "model_state": trainer.model.state_dict(), "step": 0,
                         "metrics": {}}, path)
            models[spec.id] = path
            _, row["cuda_ms"] = _time_steps(spec, batch, torch.device("cuda", 0), cores, steps,
                                            work / f"cuda_{spec.id}")
            row["speedup_vs_all_cores"] = row["cpu_all_cores_ms"] / row["cuda_ms"]
        except Exception as error:  # noqa: BLE001
            row["error"] = f"{type(error).__name__}: {error}"
            row["traceback"] = traceback.format_exc()[-3000:]
        rows[spec.id] = row
        _log(f"[training] {spec.id}: {json.dumps({k: v for k, v in row.items() if k != 'traceback'})}")
    return {"steps": steps, "cpu_steps": cpu_steps, "cores": cores, "models": rows}


# --------------------------------------------------------------------------------------------- inference
def _training_settings(spec) -> str:
    """What makes two models the same network: their settings without seed and budget."""
    return json.dumps({k: v for k, v in spec.settings().items() if k not in ("seed", "budget")}, sort_keys=True,
                      default=str)


def _model_for(cfg: dict, params: dict, models: dict) -> dict:
    """A row's constructor parameters with ``model`` replaced by the untrained network of a model trained alike."""
    from denoisers.training.models import model_spec

    params = {k: v for k, v in params.items() if k != "tuned"}
    if "model" in params:
        wanted = _training_settings(model_spec(cfg, params.pop("model")))
        twin = next((mid for mid in models if _training_settings(model_spec(cfg, mid)) == wanted), None)
        if twin is None:
            raise KeyError(f"no untrained network of these settings: {wanted}")
        params["checkpoint"] = str(models[twin])
    return params


def inference_section(cfg: dict, frames: int, work: Path, models: dict) -> dict:
    import numpy as np
    import torch

    from denoisers import registry
    from denoisers.jobs.denoise import _frames, _load_method_clip, run_method
    from denoisers.evaluate import method_specs

    cores = os.cpu_count() or 1
    render_dir = work / "render_cuda" if (work / "render_cuda").is_dir() else work / "render_cpu"
    rows = {}
    for spec in method_specs(cfg):
        if spec.role != "method" or spec.replica:
            continue
        row: dict[str, Any] = {"method": spec.method, "spp": spec.spp[0]}
        try:
            outputs, times = {}, {}
            for device in ("cpu", "cuda"):
                method = registry.build(spec.method, _model_for(cfg, spec.params, models), row=spec.id)
                method.to(torch.device(device, 0) if device == "cuda" else torch.device("cpu"))
                layers = spec.spp[0] * method.samples_factor
                clip = _load_method_clip(render_dir, spec, method, layers, reference=False)
                frame_list = _frames(clip, method, layers)[:frames]
                run_method(method, frame_list, cores)                  # warm-up (kernels, allocator, native build)
                passes = [run_method(method, frame_list, cores) for _ in range(3)]
                outputs[device] = passes[-1].radiance
                times[device] = statistics.median(1000 * statistics.fmean(p.seconds) for p in passes)
            row.update(cpu_ms_per_frame=times["cpu"], cuda_ms_per_frame=times["cuda"],
                       speedup=times["cpu"] / times["cuda"])
            a, b = outputs["cpu"], outputs["cuda"]
            mse = float(np.mean((a - b) ** 2))
            peak = float(max(np.abs(a).max(), 1e-8))
            row["psnr_cuda_vs_cpu_db"] = 10 * math.log10(peak ** 2 / mse) if mse > 0 else float("inf")
        except Exception as error:  # noqa: BLE001
            row["error"] = f"{type(error).__name__}: {error}"
            row["traceback"] = traceback.format_exc()[-3000:]
        rows[spec.id] = row
        _log(f"[inference] {spec.id}: {json.dumps({k: v for k, v in row.items() if k != 'traceback'})}")
    return {"frames": frames, "cores": cores, "rows": rows}


# ------------------------------------------------------------------------------------------------- main
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="config/config.yaml")
    parser.add_argument("--out", required=True)
    parser.add_argument("--steps", type=int, default=20, help="timed CUDA steps per model")
    parser.add_argument("--cpu-steps", type=int, default=5, help="timed CPU steps per model (every core)")
    parser.add_argument("--all-models", action="store_true", help="every ablation variant too")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--reference-spp", type=int, default=256)
    parser.add_argument("--sections", default="devices,render,training,inference")
    parser.add_argument("--render-child", choices=("cpu", "cuda"))
    parser.add_argument("--scene-dir")
    parser.add_argument("--generate", action="store_true")
    parser.add_argument("--make-render-baseline", metavar="DIR",
                        help="render the scene with llvm_ad_rgb here and keep what the GPU machine compares with")
    parser.add_argument("--render-baseline", metavar="DIR", help="a --make-render-baseline folder to compare with")
    args = parser.parse_args()
    if args.render_child:
        record = render_one(args.config, args.render_child, args.scene_dir, args.out, args.reference_spp, args.generate)
        print(json.dumps(record))
        return 0

    from denoisers.device import cuda_status, device_info
    from scenegen.config import load_config

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_config(args.config)
    sections = args.sections.split(",")
    works, why = cuda_status()
    report: dict[str, Any] = {"config": args.config, "cuda": {"works": works, "why": why}}
    _log(f"CUDA: {works} ({why})")
    work = Path(tempfile.mkdtemp(prefix="device_check-"))
    models: dict[str, Path] = {}
    if "devices" in sections:
        _section(report, "devices", lambda: {"cpu": device_info("cpu"), "cuda": device_info("cuda") if works else None})
    if args.make_render_baseline:
        _section(report, "render_baseline", render_baseline, args.config, Path(args.make_render_baseline),
                 args.reference_spp)
    if "render" in sections and args.render_baseline:
        _section(report, "render", render_section, args.config, work, args.reference_spp, Path(args.render_baseline))
    if "training" in sections:
        _section(report, "training", training_section, cfg, args.steps, args.cpu_steps, args.all_models, work, models)
    if "inference" in sections:
        _section(report, "inference", inference_section, cfg, args.frames, work, models)
    (out / "device_check.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    _log(f"wrote {out / 'device_check.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
