"""Tests of the two training-data switches (issue 11 §2): which sample layers a frame uses (``layers: random |
first``, denoisers/training/data.py) and where crops are taken (``crops: uniform | importance``,
denoisers/training/crops.py), on small synthetic clips."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from denoisers.training.crops import RELATIVE_EPS, ImportanceCrops
from denoisers.training.data import SequenceConfig, SequenceDataset, _orient, fixed_batches
from denoisers.training.job import sequence_config
from denoisers.training.models import model_spec
from scenegen.config import ConfigError, load_config, validate_config
from scenegen.dataset import Clip
from tests.test_training import synthetic_clip

REPO_ROOT = Path(__file__).resolve().parents[1]


def plans(dataset: SequenceDataset, count: int) -> list:
    return [dataset.plan(dataset.generator(i)) for i in range(count)]


def corner_clip(size: int = 32, corner: int = 8, layers: int = 4, frames: int = 4) -> Clip:
    """A clip whose noisy radiance equals the reference except in the top-left ``corner x corner`` pixels."""
    clip = synthetic_clip(frames=frames, layers=layers, height=size, width=size)
    reference = clip.reference["radiance"]                                           # (T, 3, H, W)
    radiance = np.repeat(reference[:, None], layers, axis=1).copy()                  # (T, S, 3, H, W)
    radiance[..., :corner, :corner] *= np.random.default_rng(1).exponential(1.0, radiance[..., :corner, :corner].shape)
    clip.samples["radiance"] = radiance.astype(np.float32)
    return clip


# ------------------------------------------------------------------------------------------ layers
def test_first_layers_are_the_first_spp_except_at_camera_stops() -> None:
    config = SequenceConfig(length=5, crop=8, spp=2, stop_prob=0.4, layers="first")
    stops = 0
    for plan in plans(SequenceDataset([synthetic_clip(frames=6, layers=5)], config, seed=3), 200):
        for i, (frame, layers) in enumerate(zip(plan.frames, plan.layers)):
            if i > 0 and plan.frames[i - 1] == frame:                                # camera stop: fresh noise
                assert not set(layers) & set(plan.layers[i - 1]), plan.layers
                assert len(set(layers)) == 2
                stops += 1
            else:
                assert layers == (0, 1), plan.describe()
    assert stops > 100
    # Without stops every frame uses layers 0..spp-1.
    quiet = SequenceDataset([synthetic_clip(layers=4)], SequenceConfig(length=3, crop=8, spp=3, stop_prob=0.0,
                                                                        layers="first"), seed=0)
    assert all(plan.layers == ((0, 1, 2),) * 3 for plan in plans(quiet, 20))
    # A stack too small for fresh noise (3 layers, spp 2): stops reuse the first layers, as random does.
    small = SequenceDataset([synthetic_clip(layers=3)], SequenceConfig(length=3, crop=8, spp=2, stop_prob=1.0,
                                                                        layers="first"), seed=0)
    assert all(plan.layers == ((0, 1),) * 3 for plan in plans(small, 10))


def test_random_layers_draw_every_stored_layer_about_equally() -> None:
    config = SequenceConfig(length=3, crop=8, spp=2, stop_prob=0.0)
    assert config.layers == "random" and config.crops == "uniform"
    counts = np.zeros(5)
    for plan in plans(SequenceDataset([synthetic_clip(layers=5)], config, seed=5), 400):
        for layers in plan.layers:
            assert len(set(layers)) == 2
            counts[list(layers)] += 1
    expected = 400 * 3 * 2 / 5                                                       # 480 per layer, sd ~ 20
    assert np.all(np.abs(counts - expected) < 0.15 * expected), counts


def test_random_layers_keep_the_drawn_order_so_a_prefix_is_a_random_subset() -> None:
    """spp = every stored layer (NTASD carries all 32 and reads each pixel's first k): the layers come in the
    order drawn, so the first two of a frame are any two of the five, each about equally often, and the
    batch's layer axis follows that order."""
    config = SequenceConfig(length=2, crop=8, spp=5, stop_prob=0.0, color_range=None)
    clip = synthetic_clip(layers=5)
    dataset = SequenceDataset([clip], config, seed=2)
    firsts = np.zeros(5)
    for plan in plans(dataset, 300):
        for layers in plan.layers:
            assert sorted(layers) == [0, 1, 2, 3, 4]
            firsts[list(layers[:2])] += 1
    expected = 300 * 2 * 2 / 5                                                       # 240 per layer, sd ~ 13
    assert np.all(np.abs(firsts - expected) < 0.2 * expected), firsts
    plan = dataset.plan(dataset.generator(0))
    sequence = dataset.sequence(plan)
    row, column = plan.crop
    frame, layers = plan.frames[0], list(plan.layers[0])
    direct = clip.samples["radiance"][frame][layers][..., row:row + 8, column:column + 8]
    oriented = np.stack([np.ascontiguousarray(_orient(layer, plan.rotation, plan.flip)) for layer in direct])
    assert np.allclose(sequence["radiance"][0].numpy(), oriented)


def test_validation_ignores_the_switches() -> None:
    """Validation sequences (random layers, uniform crops) are the same for every arm of a comparison."""
    clips = [corner_clip(size=16, frames=6)]
    base = SequenceConfig(length=3, crop=8, spp=2)
    switched = SequenceConfig(length=3, crop=8, spp=2, layers="first", crops="importance", importance_floor=0.0)
    assert (switched.without_augmentation().layers, switched.without_augmentation().crops) == ("random", "uniform")
    a, b = fixed_batches(clips, base, 6, seed=9), fixed_batches(clips, switched, 6, seed=9)
    assert [x.describe() for x in a] == [y.describe() for y in b]
    assert all(torch.equal(x["radiance"], y["radiance"]) for x, y in zip(a, b))


# ------------------------------------------------------------------------------------------- crops
def test_importance_crops_prefer_the_noisy_corner() -> None:
    clip = corner_clip()
    def overlap_rate(crops: str) -> float:
        config = SequenceConfig(length=3, crop=8, spp=1, stop_prob=0.0, crops=crops, importance_floor=0.2)
        return float(np.mean([p.crop[0] < 8 and p.crop[1] < 8
                              for p in plans(SequenceDataset([clip], config, seed=11), 400)]))

    uniform, importance = overlap_rate("uniform"), overlap_rate("importance")
    # Uniform: 64 of 625 positions overlap the corner (10 %); importance: >= 80 % + 20 % of 10 %.
    assert uniform < 0.2 and importance > 0.7, (uniform, importance)


def test_a_positive_floor_keeps_every_position_reachable() -> None:
    crops = ImportanceCrops(corner_clip(), 8)
    frames = [0, 1, 1]
    positions = 25 * 25
    bare = crops.probabilities(frames, 0.0)
    assert bare.shape == (25, 25) and np.isclose(bare.sum(), 1.0) and bare[20:, 20:].max() == 0
    floored = crops.probabilities(frames, 0.05)
    assert np.isclose(floored.sum(), 1.0) and floored.min() >= 0.05 / positions * (1 - 1e-9)
    assert np.allclose(crops.probabilities(frames, 1.0), 1.0 / positions)
    rng = np.random.default_rng(0)
    drawn = {crops.draw(rng, frames, 0.0) for _ in range(500)}
    assert all(row < 8 and column < 8 for row, column in drawn)                     # floor 0: only error counts
    far = {crops.draw(rng, frames, 0.5) for _ in range(2000)}
    assert any(row >= 8 or column >= 8 for row, column in far)


def test_the_crop_distribution_equals_a_direct_computation() -> None:
    clip = synthetic_clip(frames=4, layers=3, height=12, width=12, seed=2)
    crop, floor, frames = 4, 0.3, [2, 2, 3]
    samples, reference = clip.samples["radiance"].astype(np.float64), clip.reference["radiance"].astype(np.float64)
    expected_frames = []
    for t in range(4):
        error = (((samples[t].mean(axis=0) - reference[t]) ** 2) / (reference[t] ** 2 + RELATIVE_EPS)).mean(axis=0)
        scores = np.array([[error[r:r + crop, c:c + crop].mean() for c in range(12 - crop + 1)]
                           for r in range(12 - crop + 1)])
        expected_frames.append(scores / scores.sum())
    expected = (1 - floor) * np.mean([expected_frames[t] for t in frames], axis=0) + floor / 81
    actual = ImportanceCrops(clip, crop).probabilities(frames, floor)
    np.testing.assert_allclose(actual, expected, rtol=1e-5, atol=1e-9)


def test_batches_are_deterministic_with_both_switches() -> None:
    config = SequenceConfig(length=3, crop=8, spp=2, stop_prob=0.3, layers="first", crops="importance")
    clips = [corner_clip(size=16, frames=6), synthetic_clip(frames=6, layers=4, seed=3, scene="other")]
    one, two = SequenceDataset(clips, config, seed=7), SequenceDataset(clips, config, seed=7)
    for index in (0, 5):
        a, b = one.batch(index, 3), two.batch(index, 3)
        assert a.describe() == b.describe()
        assert all(torch.equal(a[key], b[key]) for key in a.tensors)
    assert one.batch(0, 3).describe() != one.batch(1, 3).describe()
    assert one.describe()["config"]["layers"] == "first" and one.describe()["config"]["crops"] == "importance"
    assert one.describe() != SequenceDataset(clips, SequenceConfig(length=3, crop=8, spp=2, stop_prob=0.3),
                                             seed=7).describe()


# ------------------------------------------------------------------------------------------ config
@pytest.mark.parametrize("key, value", [("layers", "last"), ("crops", "gaussian"), ("importance_floor", 1.5)])
def test_unknown_values_are_rejected_naming_the_key(key: str, value) -> None:
    with pytest.raises(ValueError, match=f"'{key}'"):
        SequenceConfig(**{key: value})
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    broken = copy.deepcopy(cfg)
    broken["training"]["models"][0].setdefault("data", {})[key] = value
    with pytest.raises(ConfigError, match=key):
        validate_config(broken)


def test_the_switches_flow_from_the_config_to_the_sequences() -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    default = sequence_config(model_spec(cfg, "rae"), ("radiance",))
    assert (default.layers, default.crops, default.importance_floor) == ("random", "uniform", 0.2)
    cfg["training"]["models"][0]["data"] = {**cfg["training"]["models"][0].get("data", {}), "layers": "first",
                                            "crops": "importance", "importance_floor": 0.5}
    switched = sequence_config(model_spec(cfg, "rae"), ("radiance",))
    assert (switched.layers, switched.crops, switched.importance_floor) == ("first", "importance", 0.5)


def test_data_choice_arms_name_their_training_scenes(tmp_path) -> None:
    """benchmarks/train_data_choice.py: an arm's scene keys (train, root) and its render time from the sidecars."""
    import json

    from tests.benchmark_modules import load_benchmark

    choice = load_benchmark("train_data_choice")
    COMPUTE_PREFIX, OPT_PREFIX, parse_arm, prefixed_overrides, render_seconds, scene_list, split_arm = (
        choice.COMPUTE_PREFIX, choice.OPT_PREFIX, choice.parse_arm, choice.prefixed_overrides, choice.render_seconds,
        choice.scene_list, choice.split_arm)
    # net.* keys override the network, opt.* the optimiser; both leave the data keys alone.
    assert prefixed_overrides("net.width=0.25,layers=first,net.levels=4") == {"width": 0.25, "levels": 4}
    assert prefixed_overrides("net.width=0.25,opt.ema_decay=0.99", OPT_PREFIX) == {"ema_decay": 0.99}
    assert prefixed_overrides("comp.precision=fp32,layers=first", COMPUTE_PREFIX) == {"precision": "fp32"}
    assert prefixed_overrides("opt.schedule.name=cosine,opt.schedule.total_steps=30,opt.lr=0.002", OPT_PREFIX) == {
        "schedule": {"name": "cosine", "total_steps": 30}, "lr": 0.002}
    assert "precision" not in parse_arm("comp.precision=fp32", {"length": 3, "crop": 32, "spp": 1})
    base = {"length": 3, "crop": 32, "spp": 1}
    data = parse_arm("net.width=0.25,layers=first,opt.ema_decay=null", base)
    assert data["layers"] == "first" and not {"net.width", "width", "opt.ema_decay", "ema_decay"} & set(data)
    assert scene_list("train_000..train_003") == ["train_000", "train_001", "train_002", "train_003"]
    assert scene_list("train_004+train_009") == ["train_004", "train_009"]
    with pytest.raises(ValueError, match="same prefix"):
        scene_list("train_000..test_002")
    assert split_arm("root=/r,train=train_000..train_001,layers=first") == (
        {"root": "/r", "train": "train_000..train_001"}, "layers=first")
    for kind, seconds in (("noisy", [1.5, 2.0]), ("reference", [10.0, 20.5])):
        chunk = tmp_path / "train_000" / kind / "chunk_000"
        chunk.mkdir(parents=True)
        for frame, value in enumerate(seconds):
            (chunk / f"frame_{frame:04d}.json").write_text(json.dumps({"timing_s": value}))
    assert render_seconds([tmp_path / "train_000"]) == pytest.approx(34.0)
    with pytest.raises(FileNotFoundError, match="no frame sidecars"):
        render_seconds([tmp_path / "missing"])


def test_hue_permutation_and_grayscale_recolour_input_albedo_and_target_alike() -> None:
    """Hasselgren et al. 2020's augmentations for direct prediction: one channel order per sequence for every
    colour buffer (radiance, albedo, reference), so demodulated colour is permuted consistently; grayscale = the
    CCIR 601 grey (0.2989, 0.587, 0.114) in all three channels; normals and depth are left alone."""
    import dataclasses

    from denoisers.training.data import SequenceConfig, SequenceDataset
    from tests.test_training import synthetic_clip

    clip = synthetic_clip(frames=4, layers=2)
    base = dict(length=3, crop=8, spp=1, color_range=None, rotate=False, flip=False)
    dataset = SequenceDataset([clip], SequenceConfig(**base, permute_channels=True, grayscale_prob=0.5), seed=3)
    plans = [dataset.plan(dataset.generator(i)) for i in range(12)]
    assert {p.channels for p in plans} - {(0, 1, 2)} and {p.grayscale for p in plans} == {True, False}
    plan = next(p for p in plans if p.channels != (0, 1, 2))
    plain = dataset.sequence(dataclasses.replace(plan, channels=(0, 1, 2), grayscale=False))
    permuted = dataset.sequence(dataclasses.replace(plan, grayscale=False))
    order = list(plan.channels)
    for key in ("radiance", "albedo"):
        assert torch.equal(permuted[key], plain[key][:, :, order])
    assert torch.equal(permuted["reference.radiance"], plain["reference.radiance"][:, order])
    assert torch.equal(permuted["normal"], plain["normal"]) and torch.equal(permuted["depth"], plain["depth"])
    grey = dataset.sequence(dataclasses.replace(plan, channels=(0, 1, 2), grayscale=True))
    for key, source in (("radiance", plain["radiance"]), ("albedo", plain["albedo"])):
        expected = 0.2989 * source[:, :, 0] + 0.587 * source[:, :, 1] + 0.114 * source[:, :, 2]
        for c in range(3):
            torch.testing.assert_close(grey[key][:, :, c], expected)
    # Validation never recolours; switches that are off stay out of the data's fingerprint.
    off = SequenceConfig(**base)
    assert not {"permute_channels", "grayscale_prob"} & set(off.to_dict())
    assert {"permute_channels", "grayscale_prob"} <= set(dataset.config.to_dict())
    validation = dataset.config.without_augmentation()
    assert not validation.permute_channels and validation.grayscale_prob == 0
    # Off, the random stream is the one it always was: the same plans as a config that never had the switches.
    same = SequenceDataset([clip], SequenceConfig(**base, permute_channels=False, grayscale_prob=0.0), seed=3)
    default = SequenceDataset([clip], SequenceConfig(**base), seed=3)
    assert same.plan(same.generator(5)) == default.plan(default.generator(5))


def test_benchmarks_and_the_job_build_one_sequence_config_per_task() -> None:
    """The training job and the training benchmarks (train_data_choice, train_precision_quality) load the same
    buffers and build the same batches: the task's per-sample, per-pixel and mean buffers (NTASD's mean albedo
    was missing from the benchmarks' batches, which then failed on 'mean.albedo')."""
    import yaml

    from denoisers.training.job import clip_buffers, task_sequence_config
    from denoisers.training.tasks import task_builder

    cfg = validate_config(yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text()))
    for model_id in ("rae", "ntasd"):
        spec = model_spec(cfg, model_id)
        builder = task_builder(spec.method)
        sequences = task_sequence_config(builder, spec, [])
        assert set(builder.mean_buffers) <= set(clip_buffers(builder))
        assert sequences.mean_buffers == builder.mean_buffers and sequences.pixel_buffers == builder.pixel_buffers
        assert sequences.sample_buffers == builder.sample_buffers and sequences.reference_buffers == ("radiance",)
    assert task_builder("ntasd").mean_buffers == ("albedo",)
    from tests.benchmark_modules import load_benchmark

    for module in (load_benchmark("train_data_choice"), load_benchmark("train_precision_quality")):
        assert module.task_sequence_config is task_sequence_config and module.clip_buffers is clip_buffers
