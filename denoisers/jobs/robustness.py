"""The robustness scenario, spikes and NaN/Inf injected into the noisy samples: what rule robustness_row does
for each clip of a row (denoisers.jobs.rows).

* ``robustness_clip``: one method on a clip with injected spikes and NaN/Inf -> CSV

The method runs through the same loop as the denoised clips (denoisers.jobs.denoise.run_method) and is
scored like them (denoisers.jobs.scoring.score_sequence), from the outputs in memory.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from denoisers.jobs.denoise import _frames, _load_method_clip, _prepare, out_of_range_record, run_method
from denoisers.evaluate import ROBUSTNESS_CSV, ROBUSTNESS_LAST_EXR, ROBUSTNESS_SUMMARY, write_radiance_exr
from denoisers.jobs.scoring import score_sequence
from scenegen.atomic import atomic_directory


def inject_corruption(samples: dict[str, np.ndarray], *, seed: int, scene: str, spike_fraction: float,
                      spike_max_factor: float, nonfinite_fraction: float, frames: Sequence[int]) -> dict[str, int]:
    """Corrupt per-sample buffers {buffer: (T, S, C, H, W)} in place and return the counts.

    Per frame: in ``radiance``, ``max(1, round(spike_fraction * S*H*W))`` random samples get
    ``m * mean`` added to every channel, m ~ U(0, spike_max_factor) and mean = the frame's mean
    radiance (Isik et al. 2021, Fig. 3: perturbations up to 500x the image mean). In every buffer,
    ``max(1, round(nonfinite_fraction * S*H*W))`` random samples have all channels set to NaN, +Inf or
    -Inf in turn (the cycle starts one step later in every frame). Positions depend only on (seed, scene, buffer, frame), so every method sees the same
    corruption of the buffers it reads.
    """
    from scenegen.seeds import derive_seed

    counts = {"spikes": 0, "nan_values": 0, "inf_values": 0}
    for buffer, stack in samples.items():
        _, n_samples, n_channels, height, width = stack.shape
        positions = n_samples * height * width
        for i, t in enumerate(frames):
            rng = np.random.default_rng(derive_seed(seed, "robustness", scene, buffer, int(t)))
            # (S, C, H, W) -> (C, S*H*W) copy so that one index picks one sample of one pixel.
            flat = np.moveaxis(stack[i], 1, 0).reshape(n_channels, positions)
            if buffer == "radiance":
                n_spikes = max(1, round(spike_fraction * positions))
                where = rng.choice(positions, n_spikes, replace=False)
                frame_mean = float(flat.mean())
                flat[:, where] += rng.uniform(0.0, spike_max_factor, n_spikes)[None, :] * frame_mean
                counts["spikes"] += n_spikes
            n_bad = max(1, round(nonfinite_fraction * positions))
            where = rng.choice(positions, n_bad, replace=False)
            # Cycle NaN, +Inf, -Inf, starting one further each frame so that every kind occurs even
            # when a frame gets a single bad sample.
            values = np.array([np.nan, np.inf, -np.inf], np.float32)[(np.arange(n_bad) + i) % 3]
            flat[:, where] = values[None, :]
            counts["nan_values"] += int(np.isnan(values).sum()) * n_channels
            counts["inf_values"] += int(np.isinf(values).sum()) * n_channels
            stack[i] = np.moveaxis(flat.reshape(n_channels, n_samples, height, width), 0, 1)
    return counts


def robustness_clip(cfg: dict, method_id: str, scene: str, spp: int, render_dir: Path, out_dir: Path,
                    threads: int = 1, results: Path | str | None = None) -> dict[str, Any]:
    """Run one method at ``spp`` on a clip whose noisy samples carry injected spikes and NaN/Inf (settings
    in ``evaluation.robustness``) and score it against the reference. Writes ``out_dir`` atomically:
    metrics.csv (per frame), summary.json (counts, settings digest), last_frame.exr (the output of the last frame)."""
    import pandas as pd

    from denoisers.experiment import DIGEST_KEY, Lineage

    settings = cfg["evaluation"]["robustness"]
    spec, method, layers = _prepare(cfg, method_id, spp, results)
    clip = _load_method_clip(Path(render_dir), spec, method, layers, reference=True)
    injected = inject_corruption(clip.samples, seed=cfg["seed"], scene=scene, frames=clip.frames,
                                 spike_fraction=settings["spike_fraction"],
                                 spike_max_factor=settings["spike_max_factor"],
                                 nonfinite_fraction=settings["nonfinite_fraction"])
    result = run_method(method, _frames(clip, method, layers), threads,
                        cfg["evaluation"]["out_of_range_factor"])
    cuts = [bool(m.get("camera_cut", False)) for m in clip.meta]
    scores = score_sequence(result.radiance, clip.reference["radiance"], cuts, cfg["evaluation"]["warmup_frames"])
    table = pd.DataFrame({"frame": clip.frames, **scores, "camera_cut": cuts,
                          "nonfinite_input": result.nonfinite_inputs, "nonfinite_output": result.nonfinite_outputs,
                          "out_of_range_output": result.out_of_range_outputs})
    summary = {"method_id": spec.id, "method": spec.method, "scene": scene, "spp": spp,
               "settings": dict(settings), "injected": injected,
               "nonfinite_inputs": int(sum(result.nonfinite_inputs)),
               "nonfinite_outputs": int(sum(result.nonfinite_outputs)),
               **out_of_range_record(result),
               "mean_psnr": float(np.nanmean(scores["psnr"])), DIGEST_KEY: Lineage(cfg).robustness(spec, scene, spp)}
    with atomic_directory(out_dir) as staging:
        (staging / ROBUSTNESS_CSV).write_text(table.to_csv(index=False), encoding="utf-8")
        (staging / ROBUSTNESS_SUMMARY).write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
        write_radiance_exr(staging / ROBUSTNESS_LAST_EXR, result.radiance[-1])
    return summary
