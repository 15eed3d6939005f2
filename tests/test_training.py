"""Tests of the training infrastructure: the sequence dataset (denoisers/training/data.py) and the trainer
(denoisers/training/loop.py), on synthetic in-memory clips and a tiny RAE."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from denoisers.filters import warp_previous
from denoisers.nets.rae import RAEConfig
from denoisers.nets.rae_task import RAETask, prepare_inputs
from denoisers.training import data as training_data
from denoisers.training.data import SequenceConfig, SequenceDataset, SequencePlan, fixed_batches
from denoisers.training.loop import (CheckpointError, NonFiniteLossError, Trainer, TrainerConfig, load_checkpoint,
                                     load_model, lr_factor)
from scenegen.camera import look_at_matrix
from scenegen.dataset import Clip

TINY_RAE = RAEConfig(width=0.125, levels=2)


@pytest.fixture(autouse=True)
def restore_torch_threads():
    """The trainer runs these tiny networks on one thread (faster on a busy machine); restore the setting."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def synthetic_clip(frames: int = 6, layers: int = 4, height: int = 16, width: int = 16, shift: tuple[int, int] = (1, 0),
                   cut: int | None = None, seed: int = 0, scene: str = "synthetic",
                   to_world: np.ndarray | None = None) -> Clip:
    """A clip whose content translates by ``shift`` = (dx, dy) pixels per frame (so motion = -shift
    exactly), with multiplicative noise per sample layer, smooth world-space normals, depth and roughness
    ramps, and a camera in every frame's meta. ``cut``: frame index of a camera cut."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    t = np.arange(frames, dtype=np.float32)[:, None, None]
    u, v = x[None] - shift[0] * t, y[None] - shift[1] * t                       # (T, H, W) content coordinates
    reference = np.stack([0.6 + 0.4 * np.sin(0.9 * u + 0.2 * v), 0.5 + 0.3 * np.cos(0.7 * v - 0.4 * u),
                          0.3 + 0.2 * np.sin(0.5 * (u + v))], axis=1).astype(np.float32)      # (T, 3, H, W)
    albedo = np.stack([0.3 + 0.5 * ((np.floor(u / 3) + np.floor(v / 3)) % 2), 0.4 + 0.1 * np.sin(u),
                       np.full_like(u, 0.6)], axis=1).astype(np.float32)
    normal = np.stack([np.sin(0.3 * u), np.cos(0.2 * v) * 0.5, np.ones_like(u)], axis=1)
    normal = (normal / np.linalg.norm(normal, axis=1, keepdims=True)).astype(np.float32)
    depth = (2.0 + 0.1 * u)[:, None].astype(np.float32)
    roughness = (0.2 + 0.6 * (v / max(height - 1, 1)))[:, None].astype(np.float32)

    def per_sample(image: np.ndarray) -> np.ndarray:                             # (T, C, H, W) -> (T, S, C, H, W)
        return np.repeat(image[:, None], layers, axis=1)

    noise = rng.exponential(1.0, (frames, layers, 3, height, width)).astype(np.float32)
    samples = {"radiance": per_sample(reference) * noise, "albedo": per_sample(albedo), "normal": per_sample(normal),
               "depth": per_sample(depth), "roughness": per_sample(roughness)}
    motion = np.zeros((frames, 2, height, width), np.float32)
    motion[:, 0], motion[:, 1] = -shift[0], -shift[1]
    valid = np.ones((frames, 1, height, width), bool)
    valid[0] = False
    if to_world is None:
        to_world = look_at_matrix(np.array([0.0, 1.0, 3.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    meta = [{"camera": {"to_world": np.asarray(to_world).tolist()}, "camera_cut": cut is not None and i == cut}
            for i in range(frames)]
    if cut is not None:
        valid[cut] = False
    gbuffer = {"depth": depth, "normal": normal, "position": np.zeros((frames, 3, height, width), np.float32),
               "object": np.zeros((frames, 1, height, width), np.float32), "albedo": albedo, "roughness": roughness}
    return Clip(scene=scene, frames=list(range(frames)), samples=samples, motion=motion, valid=valid, gbuffer=gbuffer,
                reference={"radiance": reference, "albedo": albedo}, meta=meta)


def plain(plan: SequencePlan) -> SequencePlan:
    """The same sequence without rotation, mirror or colour modulation."""
    return SequencePlan(clip=plan.clip, scene=plan.scene, frames=plan.frames, layers=plan.layers, crop=plan.crop)


# ------------------------------------------------------------------------------------------ data
def test_batches_have_the_documented_shapes_and_are_deterministic() -> None:
    config = SequenceConfig(length=3, crop=8, spp=2, pixel_buffers=("motion", "valid", "gbuffer.depth"),
                            backward_prob=0.0)
    dataset = SequenceDataset([synthetic_clip()], config, seed=5)
    batch = dataset.batch(3, batch_size=2)
    assert batch["radiance"].shape == (2, 3, 2, 3, 8, 8)
    assert batch["depth"].shape == (2, 3, 2, 1, 8, 8)
    assert batch["reference.radiance"].shape == (2, 3, 3, 8, 8)
    assert batch["motion"].shape == (2, 3, 2, 8, 8) and batch["valid"].shape == (2, 3, 1, 8, 8)
    assert batch["gbuffer.depth"].shape == (2, 3, 1, 8, 8)
    assert batch["world_to_view"].shape == (2, 3, 3, 3)
    assert all(t.dtype == torch.float32 for t in batch.tensors.values())
    again = SequenceDataset([synthetic_clip()], config, seed=5).batch(3, batch_size=2)
    assert all(torch.equal(batch[k], again[k]) for k in batch.tensors)
    assert not torch.equal(batch["radiance"], dataset.batch(4, batch_size=2)["radiance"])
    assert not torch.equal(batch["radiance"], SequenceDataset([synthetic_clip()], config, seed=6).batch(3, 2)["radiance"])


@pytest.mark.parametrize("rotation, flip", [(r, f) for r in range(4) for f in (False, True)])
def test_rotation_and_flip_transform_every_image_buffer_alike(rotation: int, flip: bool) -> None:
    config = SequenceConfig(length=3, crop=10, spp=2, reference_buffers=("radiance", "albedo"),
                            pixel_buffers=("gbuffer.depth",), backward_prob=0.0, color_range=None)
    dataset = SequenceDataset([synthetic_clip(height=12, width=14)], config, seed=1)
    base_plan = SequencePlan(clip=0, scene="synthetic", frames=(1, 2, 3), layers=((0, 1), (2, 3), (1, 3)), crop=(1, 3))
    augmented_plan = SequencePlan(**{**base_plan.__dict__, "rotation": rotation, "flip": flip})
    base, augmented = dataset.sequence(base_plan), dataset.sequence(augmented_plan)

    def orient(image: torch.Tensor) -> torch.Tensor:
        image = torch.rot90(image, rotation, dims=(-2, -1))
        return torch.flip(image, dims=(-1,)) if flip else image

    for key in ("radiance", "albedo", "normal", "depth", "roughness", "reference.radiance", "reference.albedo",
                "gbuffer.depth"):
        torch.testing.assert_close(augmented[key], orient(base[key]), rtol=0, atol=0, msg=key)


def test_view_space_normals_turn_with_the_image() -> None:
    # The camera looks along world -z with y up, so world +x is image-right: view normal (1, 0).
    clip = synthetic_clip(height=8, width=8)
    clip.samples["normal"][:] = np.array([1.0, 0.0, 0.0], np.float32)[:, None, None]
    dataset = SequenceDataset([clip], SequenceConfig(length=2, crop=8, backward_prob=0.0, color_range=None), seed=0)
    plan = SequencePlan(clip=0, scene="synthetic", frames=(0, 1), layers=((0,), (1,)), crop=(0, 0))
    # Expected image-plane direction of an image-right arrow after the re-orientation (x right, y up).
    expected = {(0, False): (1, 0), (1, False): (0, 1), (2, False): (-1, 0), (3, False): (0, -1),
                (0, True): (-1, 0), (1, True): (0, 1)}
    for (rotation, flip), direction in expected.items():
        batch = dataset.sequence(SequencePlan(**{**plan.__dict__, "rotation": rotation, "flip": flip}))
        x, _ = prepare_inputs(RAEConfig(), batch["radiance"].mean(1), batch["albedo"].mean(1), batch["normal"].mean(1),
                              batch["depth"].mean(1), batch["roughness"].mean(1), batch["world_to_view"])
        view_xy = x[:, 3:5]                                                      # (T, 2, H, W)
        torch.testing.assert_close(view_xy, torch.tensor(direction, dtype=torch.float32).view(1, 2, 1, 1)
                                   .expand_as(view_xy), atol=1e-6, rtol=0, msg=str((rotation, flip)))


@pytest.mark.parametrize("rotation, flip", [(r, f) for r in range(4) for f in (False, True)])
def test_motion_vectors_still_reproject_after_rotation_and_flip(rotation: int, flip: bool) -> None:
    clip = synthetic_clip(height=16, width=16, shift=(2, 1))
    config = SequenceConfig(length=2, crop=12, backward_prob=0.0, color_range=None, pixel_buffers=("motion",))
    dataset = SequenceDataset([clip], config, seed=0)
    sequence = dataset.sequence(SequencePlan(clip=0, scene="synthetic", frames=(2, 3), layers=((0,), (0,)),
                                             crop=(2, 2), rotation=rotation, flip=flip))
    previous, current = sequence["reference.radiance"][0], sequence["reference.radiance"][1]
    warped = warp_previous(previous, sequence["motion"][1])
    # Pixels whose previous position lies inside the crop reproject exactly (integer motion).
    inside = (slice(3, 9), slice(3, 9))
    torch.testing.assert_close(warped[:, inside[0], inside[1]], current[:, inside[0], inside[1]], atol=1e-6, rtol=0)


def test_colour_modulation_scales_input_and_target_radiance_alike_but_not_albedo() -> None:
    config = SequenceConfig(length=3, crop=8, spp=1, reference_buffers=("radiance", "albedo"))
    dataset = SequenceDataset([synthetic_clip()], config, seed=2)
    plans = [dataset.plan(dataset.generator(i)) for i in range(50)]
    factors = np.array([p.color for p in plans])
    assert factors.min() >= 0.0 and factors.max() <= 2.0 and factors.std() > 0.3
    assert len({p.color for p in plans}) == 50 and all(len(set(p.color)) == 3 for p in plans)
    plan = plans[0]
    modulated, base = dataset.sequence(plan), dataset.sequence(SequencePlan(**{**plan.__dict__, "color": (1.0,) * 3}))
    color = torch.tensor(plan.color).view(1, 3, 1, 1)
    torch.testing.assert_close(modulated["radiance"], base["radiance"] * color[None])
    torch.testing.assert_close(modulated["reference.radiance"], base["reference.radiance"] * color)
    assert torch.equal(modulated["albedo"], base["albedo"])
    assert torch.equal(modulated["reference.albedo"], base["reference.albedo"])


def test_backward_playback_reverses_the_frames() -> None:
    clip = synthetic_clip(frames=8)
    backward = SequenceDataset([clip], SequenceConfig(length=4, crop=8, backward_prob=1.0, stop_prob=0.0), seed=3)
    for i in range(20):
        plan = backward.plan(backward.generator(i))
        assert plan.backward and np.all(np.diff(plan.frames) == -1), plan.frames
    plan = backward.plan(backward.generator(0))
    forward_plan = SequencePlan(**{**plan.__dict__, "frames": plan.frames[::-1], "layers": plan.layers[::-1]})
    backward_sequence, forward_sequence = backward.sequence(plan), backward.sequence(forward_plan)
    for key in ("radiance", "reference.radiance", "depth"):
        assert torch.equal(backward_sequence[key], torch.flip(forward_sequence[key], dims=(0,)))
    mixed = SequenceDataset([clip], SequenceConfig(length=4, crop=8, backward_prob=0.5, stop_prob=0.0), seed=3)
    directions = [mixed.plan(mixed.generator(i)).backward for i in range(200)]
    assert 0.35 < np.mean(directions) < 0.65
    with pytest.raises(ValueError, match="backward playback"):
        SequenceConfig(pixel_buffers=("motion",), backward_prob=0.5)
    # One frame played backwards is the same frame: a single-frame model may keep the default.
    single = SequenceDataset([clip], SequenceConfig(length=1, crop=8, pixel_buffers=("motion", "valid"),
                                                    backward_prob=0.5), seed=3)
    assert all(len(single.plan(single.generator(i)).frames) == 1 for i in range(5))


def test_camera_stops_repeat_the_frame_with_fresh_noise() -> None:
    clip = synthetic_clip(frames=6, layers=4)
    config = SequenceConfig(length=4, crop=8, spp=2, stop_prob=1.0, backward_prob=0.0, color_range=None,
                            pixel_buffers=("motion", "valid"))
    dataset = SequenceDataset([clip], config, seed=4)
    plan = dataset.plan(dataset.generator(0))
    assert len(set(plan.frames)) == 1
    for a, b in zip(plan.layers, plan.layers[1:]):
        assert not set(a) & set(b), plan.layers                                  # disjoint layers: fresh noise
    sequence = dataset.sequence(plan)
    assert all(torch.equal(sequence["reference.radiance"][0], frame) for frame in sequence["reference.radiance"])
    assert not torch.equal(sequence["radiance"][0], sequence["radiance"][1])
    assert torch.all(sequence["motion"][1:] == 0) and torch.all(sequence["valid"][1:] == 1)
    some = SequenceDataset([clip], SequenceConfig(length=5, crop=8, stop_prob=0.3, backward_prob=0.0), seed=4)
    stops = [sum(a == b for a, b in zip(p.frames, p.frames[1:]))
             for p in (some.plan(some.generator(i)) for i in range(200))]
    assert 0.2 < np.mean(stops) / 4 < 0.4


def test_sequences_stay_inside_one_shot_and_crops_inside_the_frame() -> None:
    clip = synthetic_clip(frames=10, cut=4, height=12, width=20)
    dataset = SequenceDataset([clip], SequenceConfig(length=4, crop=8, stop_prob=0.2), seed=0)
    for i in range(100):
        plan = dataset.plan(dataset.generator(i))
        assert all(f < 4 for f in plan.frames) or all(f >= 4 for f in plan.frames), plan.frames
        assert 0 <= plan.crop[0] <= 4 and 0 <= plan.crop[1] <= 12
    with pytest.raises(ValueError, match="consecutive frames"):
        SequenceDataset([synthetic_clip(frames=10, cut=5)], SequenceConfig(length=6, crop=8))
    with pytest.raises(KeyError, match="camera"):
        broken = synthetic_clip()
        broken.meta[2] = {}
        SequenceDataset([broken], SequenceConfig(length=3, crop=8))


def test_training_clips_are_loaded_once(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    calls = []

    def fake_load_clip(render_dir, **kwargs):
        calls.append((Path(render_dir), kwargs))
        return synthetic_clip(scene=Path(render_dir).name)

    monkeypatch.setattr(training_data, "load_clip", fake_load_clip)
    training_data.clear_clip_cache()
    dirs = [tmp_path / "train_000", tmp_path / "train_001"]
    first = training_data.load_training_clips(dirs, ["radiance", "albedo"], layers=2)
    second = training_data.load_training_clips(dirs, ["radiance", "albedo"], layers=2)
    assert len(calls) == 2 and all(a is b for a, b in zip(first, second))
    assert calls[0][1] == {"buffers": ["radiance", "albedo"], "spp": 2, "reference": True}
    training_data.clear_clip_cache()


# ---------------------------------------------------------------------------------------- trainer
def make_trainer(out_dir: Path, *, steps: int = 6, seed: int = 0, task: RAETask | None = None,
                 validation: bool = True, **overrides) -> Trainer:
    clip = synthetic_clip()
    sequences = SequenceConfig(length=3, crop=8, spp=1)
    dataset = SequenceDataset([clip], sequences, seed=seed)
    batches = fixed_batches([synthetic_clip(seed=9, scene="held_out")], sequences, count=1, batch_size=2) \
        if validation else []
    settings = dict(seed=seed, batch_size=2, max_steps=steps, lr=3e-3, schedule={"name": "constant"},
                    log_every=2, validate_every=3, checkpoint_every=2, checkpoint_seconds=None, progress=False,
                    threads=1)
    settings.update(overrides)
    return Trainer(task or RAETask(TINY_RAE), dataset, batches, TrainerConfig(**settings), out_dir)


def weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["model_state"]


class Killed(Exception):
    """Stands in for a killed training job (raised from the trainer's on_step hook)."""


def kill_at_step_5(step: int) -> None:
    if step == 5:
        raise Killed


def test_resume_after_a_kill_reproduces_the_uninterrupted_weights_exactly(tmp_path: Path) -> None:
    make_trainer(tmp_path / "straight", steps=8).run()

    with pytest.raises(Killed):
        make_trainer(tmp_path / "killed", steps=8).run(on_step=kill_at_step_5)
    assert load_checkpoint(tmp_path / "killed" / "checkpoint.pt")["step"] == 4   # last checkpoint before the kill
    result = make_trainer(tmp_path / "killed", steps=8).run()
    assert result.resumed_from == 4 and result.steps == 8
    straight, resumed = weights(tmp_path / "straight" / "checkpoint.pt"), weights(tmp_path / "killed" / "checkpoint.pt")
    assert straight.keys() == resumed.keys()
    assert all(torch.equal(straight[k], resumed[k]) for k in straight)
    # The optimiser state and the training curve agree too.
    a, b = load_checkpoint(tmp_path / "straight" / "checkpoint.pt"), load_checkpoint(tmp_path / "killed" / "checkpoint.pt")
    assert all(torch.equal(a["optimizer_state"]["state"][i]["exp_avg_sq"], b["optimizer_state"]["state"][i]["exp_avg_sq"])
               for i in a["optimizer_state"]["state"])
    keys = ("step", "train_loss", "val_loss")
    assert [tuple(r.get(k) for k in keys) for r in a["history"]] == [tuple(r.get(k) for k in keys) for r in b["history"]]


def test_same_seed_same_weights_other_seed_other_weights(tmp_path: Path) -> None:
    make_trainer(tmp_path / "a", steps=3, validation=False).run()
    make_trainer(tmp_path / "b", steps=3, validation=False).run()
    make_trainer(tmp_path / "c", steps=3, seed=1, validation=False).run()
    a, b, c = (weights(tmp_path / name / "checkpoint.pt") for name in "abc")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_a_longer_budget_continues_a_finished_run(tmp_path: Path) -> None:
    first = make_trainer(tmp_path / "run", steps=3, validation=False).run()
    assert first.resumed_from is None and first.steps == 3
    again = make_trainer(tmp_path / "run", steps=3, validation=False).run()
    assert again.resumed_from == 3 and again.steps == 3
    longer = make_trainer(tmp_path / "run", steps=5, validation=False).run()
    assert longer.resumed_from == 3 and longer.steps == 5
    with pytest.raises(CheckpointError, match=r"different training configuration \(changed: trainer\)"):
        make_trainer(tmp_path / "run", steps=6, validation=False, lr=1e-2).run()


class NaNAtStep(RAETask):
    """The RAE task whose loss turns NaN at one step."""

    def __init__(self, step: int) -> None:
        super().__init__(TINY_RAE)
        self.bad_step, self.calls = step, 0

    def loss(self, model, batch):
        loss, terms = super().loss(model, batch)
        if getattr(batch, "index", None) == self.bad_step and model.training:
            loss = loss * float("nan")
        return loss, terms


def test_a_nan_loss_stops_training_naming_the_step_and_batch(tmp_path: Path) -> None:
    trainer = make_trainer(tmp_path / "nan", steps=6, task=NaNAtStep(3), validation=False)
    with pytest.raises(NonFiniteLossError, match=r"non-finite loss \(nan\) at step 3 \(batch 3: synthetic frames") as error:
        trainer.run()
    assert error.value.step == 3 and "synthetic frames" in error.value.batch
    assert f"last checkpoint: {tmp_path / 'nan' / 'checkpoint.pt'} (step 2)" in str(error.value)
    assert load_checkpoint(tmp_path / "nan" / "checkpoint.pt")["step"] == 2      # the last good state is kept


def test_a_corrupt_checkpoint_gives_an_error_naming_the_file(tmp_path: Path) -> None:
    make_trainer(tmp_path / "run", steps=2, validation=False).run()
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    content = checkpoint.read_bytes()
    checkpoint.write_bytes(content[: len(content) // 2])                          # truncated
    with pytest.raises(CheckpointError, match=rf"{checkpoint}: corrupt or unreadable checkpoint"):
        make_trainer(tmp_path / "run", steps=4, validation=False).run()
    checkpoint.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match=str(checkpoint)):
        make_trainer(tmp_path / "run", steps=4, validation=False).run()
    with pytest.raises(CheckpointError, match=str(checkpoint)):
        load_model(checkpoint)
    torch.save({"something": 1}, checkpoint)
    with pytest.raises(CheckpointError, match=rf"{checkpoint}: not a mcdenoise-checkpoint"):
        load_checkpoint(checkpoint)
    with pytest.raises(CheckpointError, match="not found"):
        load_model(tmp_path / "missing.pt")


def test_validation_best_checkpoint_curves_and_summary(tmp_path: Path) -> None:
    result = make_trainer(tmp_path / "run", steps=7).run()
    out = tmp_path / "run"
    lines = (out / "curves.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[0] == "step" and {"train_loss", "train_loss_spatial", "val_loss", "val_ssim", "lr"} <= set(header)
    rows = [dict(zip(header, line.split(","))) for line in lines[1:]]
    assert [int(r["step"]) for r in rows] == [2, 3, 4, 6, 7]                      # logs every 2, validation every 3 + end
    validated = {int(r["step"]): float(r["val_loss"]) for r in rows if r["val_loss"]}
    assert sorted(validated) == [3, 6, 7]
    best_step = min(validated, key=validated.get)
    assert result.best_step == best_step and result.best_value == pytest.approx(validated[best_step])
    best = load_checkpoint(out / "best.pt")
    assert best["kind"] == "model" and best["step"] == best_step
    # best.pt rebuilds the network and reproduces its validation loss.
    trainer = make_trainer(tmp_path / "other", steps=1)
    trainer.model = load_model(out / "best.pt")
    assert trainer.evaluate()["loss"] == pytest.approx(validated[best_step], rel=1e-5)
    assert (out / "curves.png").stat().st_size > 1000
    assert '"best_step"' in (out / "summary.json").read_text()
    assert not list(out.glob(".*tmp*"))                                           # atomic writes leave nothing behind


def test_weight_average_is_the_recursive_mean_and_what_validation_and_best_pt_use(tmp_path: Path) -> None:
    """ema_decay: after every step ema = d_t ema + (1 - d_t) w with d_t = min(decay, (1 + t) / (10 + t)), recomputed
    here from the raw weights of each step (an independent recursion); best.pt holds the average, the checkpoint both,
    and a resumed run reproduces the uninterrupted average exactly."""
    decay = 0.8
    raw: list[dict[str, torch.Tensor]] = []
    trainer = make_trainer(tmp_path / "run", steps=6, ema_decay=decay, validate_every=0)
    trainer.run(on_step=lambda step: raw.append({k: v.detach().clone() for k, v in trainer.model.state_dict().items()}))
    # The average starts at the initial weights: rebuild them from the seed like the trainer does.
    torch.manual_seed(0)
    initial = RAETask(TINY_RAE).build_model().state_dict()
    expected = {k: v.clone().double() for k, v in initial.items()}
    for t, w in enumerate(raw):
        d = min(decay, (1.0 + t) / (10.0 + t))
        expected = {k: d * expected[k] + (1.0 - d) * w[k].double() for k in expected}
    checkpoint = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    for key, value in checkpoint["ema_state"].items():
        torch.testing.assert_close(value.double(), expected[key], rtol=1e-5, atol=1e-6)
    assert not all(torch.equal(checkpoint["ema_state"][k], checkpoint["model_state"][k]) for k in initial)
    best = load_checkpoint(tmp_path / "run" / "best.pt")   # validated at the end: the average is what is stored
    assert all(torch.equal(best["model_state"][k], checkpoint["ema_state"][k]) for k in initial)

    with pytest.raises(Killed):
        make_trainer(tmp_path / "killed", steps=6, ema_decay=decay, validate_every=0).run(on_step=kill_at_step_5)
    make_trainer(tmp_path / "killed", steps=6, ema_decay=decay, validate_every=0).run()
    resumed = load_checkpoint(tmp_path / "killed" / "checkpoint.pt")["ema_state"]
    assert all(torch.equal(resumed[k], checkpoint["ema_state"][k]) for k in initial)
    # A run without averaging keeps its fingerprint (checkpoints from before the option resume), one with it does not.
    assert "ema_decay" not in TrainerConfig(max_steps=1).fingerprint_data()
    with pytest.raises(ValueError, match="ema_decay"):
        TrainerConfig(max_steps=1, ema_decay=1.0)


def test_time_budget_stops_training(tmp_path: Path) -> None:
    result = make_trainer(tmp_path / "run", steps=None, max_seconds=0.5, validation=False).run()
    assert result.steps >= 1 and result.elapsed_seconds >= 0.5
    with pytest.raises(ValueError, match="budget"):
        TrainerConfig()


def test_learning_rate_schedules() -> None:
    ramp = {"name": "ramp_inv_sqrt", "ramp_steps": 100, "ramp_factor": 10.0}
    assert lr_factor(ramp, 0) == pytest.approx(0.1)                               # tenfold ramp-up ...
    assert lr_factor(ramp, 50) == pytest.approx(10**-0.5)                         # ... geometric ...
    assert lr_factor(ramp, 100) == pytest.approx(1.0)
    assert lr_factor(ramp, 400) == pytest.approx(0.5)                             # ... then 1/sqrt(t)
    assert lr_factor(ramp, 10_000) == pytest.approx(0.1)
    cosine = {"name": "cosine", "warmup_steps": 10, "total_steps": 110, "min_factor": 0.1}
    assert lr_factor(cosine, 4) == pytest.approx(0.5) and lr_factor(cosine, 60) == pytest.approx(0.55)
    assert lr_factor(cosine, 500) == pytest.approx(0.1)
    assert lr_factor({"name": "step", "every": 10, "gamma": 0.5}, 25) == pytest.approx(0.25)
    assert lr_factor({"name": "constant"}, 7) == 1.0
    with pytest.raises(ValueError, match="unknown learning-rate schedule"):
        lr_factor({"name": "linear"}, 0)
    assert math.isclose(TrainerConfig(max_steps=1).betas[1], 0.99)                # the paper's Adam decay rates
    # A cosine schedule without total_steps decays over the step budget (and is fingerprinted that way).
    budgeted = TrainerConfig(max_steps=200, schedule={"name": "cosine", "warmup_steps": 10})
    assert budgeted.schedule["total_steps"] == 200
    assert lr_factor(budgeted.schedule, 105) == pytest.approx(0.5) and lr_factor(budgeted.schedule, 200) == 0.0
    longer = TrainerConfig(max_steps=300, schedule={"name": "cosine", "warmup_steps": 10})
    assert budgeted.fingerprint_data() != longer.fingerprint_data()   # max_steps alone is not fingerprinted
    with pytest.raises(ValueError, match="max_steps"):
        TrainerConfig(max_seconds=5.0, schedule={"name": "cosine"})
