"""KPCN (Bako et al. 2017): the demodulation and log transforms invert exactly, identity kernels give back the
noisy input through the branch composition, softmax kernels sum to 1 (renormalised at the border), the input
statistics on hand-computed cases, the parameter count against Isik et al.'s 5.08M, training (both losses) and
determinism, the optional reference buffers of the training job, the method against the task's prediction."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from denoisers import registry
from denoisers.kernels import apply_kernels_torch
from denoisers.nets import build_net, count_parameters
from denoisers.nets.kpcn import INPUTS, RAW_FEATURES, KPCNConfig, KPCNNet
from denoisers.nets.kpcn_task import (ALBEDO_EPS, SAMPLE_BUFFERS, SPLIT_REFERENCE, KPCNTask, branch_inputs, compose,
                                      demodulate, exp_transform, filter_image, frame_step, gradients, kernel_weights,
                                      log_transform, mean_and_variance, remodulate)
from denoisers.registry import Frame
from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import task_builder, task_problems

torch.set_num_threads(1)

SMALL = dict(layers=3, features=8, conv_size=3, kernel_size=5)
BUFFERS = {"radiance": 3, "diffuse": 3, "specular": 3, "albedo": 3, "normal": 3, "depth": 1}


class _Batch(dict):
    index = 0


def _batch(n: int = 2, length: int = 2, layers: int = 4, size: int = 16, seed: int = 0, split: bool = True) -> _Batch:
    """Synthetic sequences: smooth reference diffuse / specular, noisy samples around them (radiance = diffuse +
    specular), a per-pixel albedo, random features, identity world-to-view. ``split``: carry the reference
    diffuse / specular (references of the features integrator) besides the radiance."""
    generator = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator)

    ramp = torch.linspace(0.2, 1.5, size)
    smooth = (ramp.view(1, size) * ramp.view(size, 1)).expand(n, length, 3, size, size)
    reference_diffuse, reference_specular = smooth.clone(), 0.3 * smooth.flip(-1)
    batch = _Batch()
    albedo = 0.2 + 0.8 * rand(n, length, 1, 3, size, size)
    batch["albedo"] = albedo.expand(n, length, layers, 3, size, size).clone()
    batch["diffuse"] = reference_diffuse[:, :, None] * rand(n, length, layers, 3, size, size) * 2
    batch["specular"] = reference_specular[:, :, None] * -torch.log1p(-rand(n, length, layers, 1, size, size))
    batch["radiance"] = batch["diffuse"] + batch["specular"]
    batch["normal"] = torch.nn.functional.normalize(rand(n, length, layers, 3, size, size) - 0.5, dim=3)
    batch["depth"] = 1 + rand(n, length, layers, 1, size, size)
    batch["reference.radiance"] = reference_diffuse + reference_specular
    if split:
        batch["reference.diffuse"], batch["reference.specular"] = reference_diffuse, reference_specular
    batch["world_to_view"] = torch.eye(3).expand(n, length, 3, 3).clone()
    return batch


def _frame_samples(batch: _Batch, t: int = 0) -> dict[str, torch.Tensor]:
    return {b: batch[b][:, t] for b in SAMPLE_BUFFERS}


# ------------------------------------------------------------------------------------ transforms and kernels
def test_demodulation_and_log_transforms_invert_exactly() -> None:
    generator = torch.Generator().manual_seed(0)
    diffuse = torch.rand(2, 3, 16, 16, generator=generator, dtype=torch.float64) * 10
    albedo = torch.rand(2, 3, 16, 16, generator=generator, dtype=torch.float64)
    albedo[0, :, :4] = 0.0                                            # black albedo: the eps keeps it finite
    assert torch.allclose(remodulate(demodulate(diffuse, albedo), albedo), diffuse, rtol=1e-12, atol=0)
    assert torch.allclose(demodulate(diffuse, albedo)[0, :, :4], diffuse[0, :, :4] / ALBEDO_EPS, rtol=1e-12)
    specular = torch.rand(2, 3, 16, 16, generator=generator, dtype=torch.float64) * 1e3
    specular[1, :, :2] = 0.0
    assert torch.allclose(exp_transform(log_transform(specular)), specular, rtol=1e-12, atol=1e-15)
    assert torch.allclose(log_transform(exp_transform(specular / 1e3)), specular / 1e3, rtol=1e-12, atol=1e-15)


def test_softmax_kernels_sum_to_one_and_are_renormalised_at_the_border() -> None:
    """The softmax over the k*k taps sums to 1; a constant image stays constant everywhere, the border included
    (taps outside are dropped and the kernel renormalised); with equal logits (a box) an interior pixel is the
    mean of its 3 x 3 window and the corner pixel the mean of its 2 x 2 in-image taps."""
    generator = torch.Generator().manual_seed(1)
    logits = torch.randn(2, 9, 7, 8, generator=generator) * 3
    assert torch.allclose(kernel_weights(logits).sum(dim=1), torch.ones(2, 7, 8), atol=1e-6)
    assert bool((kernel_weights(logits) > 0).all())
    constant = torch.full((2, 3, 7, 8), 2.5)
    assert torch.allclose(filter_image(constant, logits, backend="torch"), constant, atol=1e-5)
    image = torch.rand(1, 3, 7, 8, generator=generator)
    box = filter_image(image, torch.zeros(1, 9, 7, 8), backend="torch")
    assert torch.allclose(box[0, :, 3, 4], image[0, :, 2:5, 3:6].mean(dim=(1, 2)), atol=1e-6)
    assert torch.allclose(box[0, :, 0, 0], image[0, :, :2, :2].mean(dim=(1, 2)), atol=1e-6)
    # Interior pixels: exactly the softmax kernel applied to the image (apply_kernels' reference).
    direct = apply_kernels_torch(image, kernel_weights(logits[:1]))
    assert torch.allclose(filter_image(image, logits[:1], backend="torch")[..., 1:-1, 1:-1], direct[..., 1:-1, 1:-1],
                          atol=1e-6)
    # Inference (native kernel when built) and training (torch) paths agree.
    with torch.no_grad():
        assert torch.allclose(filter_image(image, logits[:1]), filter_image(image, logits[:1], backend="torch"),
                              atol=1e-6)


def _identity_logits(n: int, size: int, height: int, width: int) -> torch.Tensor:
    logits = torch.full((n, size * size, height, width), -1e4)
    logits[:, size * size // 2] = 0.0
    return logits


def test_identity_kernels_give_back_the_noisy_input() -> None:
    """Logits peaked at the centre tap: each branch returns its transformed noisy colour, and the composition
    diffuse' x (albedo + eps) + exp(specular') - 1 returns the noisy mean diffuse + specular = the noisy mean
    radiance (up to float rounding of the eps round trip)."""
    batch = _batch(n=1, length=1)
    samples = _frame_samples(batch)
    inputs = branch_inputs(samples, batch["world_to_view"][:, 0])
    identity = _identity_logits(1, 5, 16, 16)
    diffuse = filter_image(inputs.diffuse, identity, backend="torch")
    specular = filter_image(inputs.specular, identity, backend="torch")
    assert torch.equal(diffuse, inputs.diffuse) and torch.equal(specular, inputs.specular)
    albedo = samples["albedo"].mean(1)
    hand = samples["diffuse"].mean(1) / (albedo + ALBEDO_EPS) * (albedo + ALBEDO_EPS) \
        + torch.expm1(torch.log1p(samples["specular"].mean(1)))
    output = compose(diffuse, specular, inputs.albedo)
    assert torch.allclose(output, hand, rtol=1e-6, atol=1e-7)
    assert torch.allclose(output, samples["radiance"].mean(1), rtol=1e-5, atol=1e-6)

    # The same through the networks: a last layer with zero weights and a bias peaked at the centre tap.
    model = KPCNNet(KPCNConfig(**SMALL)).eval()
    with torch.no_grad():
        for branch in (model.diffuse, model.specular):
            last = branch.convs[-1]
            last.weight.zero_()
            last.bias.fill_(-50.0)
            last.bias[12] = 50.0
        step = frame_step(model, samples, batch["world_to_view"][:, 0], backend="torch")
    assert torch.allclose(step.output, samples["radiance"].mean(1), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------ inputs
def test_mean_variance_and_gradients_on_hand_computed_cases() -> None:
    samples = torch.tensor([1.0, 3.0, 5.0, 7.0]).view(1, 4, 1, 1, 1).expand(1, 4, 2, 1, 1).clone()
    samples[:, :, 1] *= 2                      # channel 1: 2, 6, 10, 14
    mean, variance = mean_and_variance(samples)
    assert torch.equal(mean.flatten(), torch.tensor([4.0, 8.0]))
    # sum (x - mean)^2 / (S (S - 1)): 20 / 12 and 80 / 12; averaged over the channels: 50 / 12
    assert torch.allclose(variance.flatten(), torch.tensor([50.0 / 12]))
    assert torch.equal(mean_and_variance(samples[:, :1])[1], torch.zeros(1, 1, 1, 1))
    image = torch.tensor([[1.0, 2.0, 4.0], [3.0, 7.0, 8.0]]).view(1, 1, 2, 3)
    grad = gradients(image)
    assert torch.equal(grad[0, 0], torch.tensor([[1.0, 2.0, 0.0], [4.0, 1.0, 0.0]]))
    assert torch.equal(grad[0, 1], torch.tensor([[2.0, 5.0, 4.0], [0.0, 0.0, 0.0]]))


@pytest.mark.parametrize("raw_features", [False, True])
def test_branch_inputs_follow_the_documented_channel_list(raw_features: bool) -> None:
    batch = _batch(n=1, length=1, layers=3)
    samples = _frame_samples(batch)
    inputs = branch_inputs(samples, batch["world_to_view"][:, 0], raw_features)
    config = KPCNConfig(raw_features=raw_features)
    assert config.in_channels == (34 if raw_features else 27)
    assert [name for name, _ in config.inputs] == [name for name, _ in INPUTS + (RAW_FEATURES if raw_features else ())]
    for x, colour in ((inputs.x_diffuse, inputs.diffuse), (inputs.x_specular, inputs.specular)):
        assert x.shape == (1, config.in_channels, 16, 16) and bool(torch.isfinite(x).all())
        assert torch.equal(x[:, :3], colour)
        assert torch.equal(x[:, 4:10], gradients(colour))
    albedo = samples["albedo"].mean(1)
    assert torch.allclose(inputs.diffuse, samples["diffuse"].mean(1) / (albedo + ALBEDO_EPS), rtol=1e-6)
    assert torch.allclose(inputs.specular, torch.log1p(samples["specular"].mean(1)), rtol=1e-6)
    expected_variance = torch.log1p(samples["specular"]).var(dim=1).mean(dim=1, keepdim=True) / 3
    assert torch.allclose(inputs.x_specular[:, 3:4], expected_variance, rtol=1e-5, atol=1e-7)
    # Features are shared by the two branches; the albedo is the same in every sample here: variance 0 (rounding).
    assert torch.equal(inputs.x_diffuse[:, 10:], inputs.x_specular[:, 10:])
    assert torch.allclose(inputs.x_diffuse[:, 26:27], torch.zeros(1, 1, 16, 16), atol=1e-12)
    if raw_features:
        assert torch.allclose(inputs.x_diffuse[:, 30:31], torch.log1p(samples["depth"]).mean(1))


def test_parameter_count_matches_isik_et_al() -> None:
    """Defaults (width 0.25): 614 728; width 1 (Bako's 9 layers of 100 5 x 5 kernels, Isik's 17 x 17 kernels, 27
    input channels): 5 082 178, Isik et al. Sec. 5.4's "KPCN: 5.08M"."""
    assert count_parameters(build_net("kpcn")) == 614_728
    full = KPCNNet(KPCNConfig(width=1.0))
    assert count_parameters(full) == 5_082_178
    assert full.diffuse.convs[0].out_channels == 100 and len(full.diffuse.convs) == 9
    assert full.diffuse.convs[-1].out_channels == 17 * 17


# ------------------------------------------------------------------------------------ training
@pytest.mark.parametrize("split", [True, False])
def test_a_few_training_steps_lower_the_loss(split: bool) -> None:
    torch.manual_seed(0)
    task = KPCNTask(KPCNConfig(**SMALL))
    model = task.build_model()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = _batch(split=split)
    first, terms = task.loss(model, batch)
    assert set(terms) == ({"diffuse", "specular"} if split else {"log_radiance"})
    for _ in range(25):
        optimizer.zero_grad()
        loss, _ = task.loss(model, batch)
        loss.backward()
        optimizer.step()
    assert float(task.loss(model, batch)[0].detach()) < 0.9 * float(first.detach())


def test_bf16_wrapper_runs_the_networks_under_autocast() -> None:
    from denoisers.training.precision import AutocastForward

    torch.manual_seed(0)
    task = KPCNTask(KPCNConfig(**SMALL))
    model = task.build_model()
    loss, _ = task.loss(AutocastForward(model), _batch(n=1, length=1))
    loss.backward()
    assert loss.dtype == torch.float32 and bool(torch.isfinite(loss))
    assert model.diffuse.convs[0].weight.grad is not None


def test_trained_model_is_deterministic(tmp_path) -> None:
    from denoisers.training.loop import Trainer, TrainerConfig

    class Source:
        def batch(self, index: int, batch_size: int) -> _Batch:
            return _batch(n=batch_size, seed=index)

        def describe(self) -> dict:
            return {"synthetic": 1}

    weights = []
    for run in range(2):
        config = TrainerConfig(seed=5, batch_size=2, max_steps=3, lr=1e-3, validate_every=1000, checkpoint_every=1000,
                               log_every=1, progress=False, threads=1)
        trainer = Trainer(KPCNTask(KPCNConfig(**SMALL)), Source(), [], config, tmp_path / f"run{run}")
        trainer.run()
        weights.append({k: v.clone() for k, v in trainer.model.state_dict().items()})
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_task_settings_are_checked() -> None:
    def spec(net=None, loss=None) -> ModelSpec:
        return ModelSpec(id="x", method="kpcn", seed=0, net=net or {}, loss=loss or {},
                         data={"spp": 4, "backward_prob": 0.5}, optimizer={}, budget={}, compute={})

    assert task_problems(spec()) == []
    assert task_problems(spec(net={"layers": 4, "width": 0.1, "kernel_size": 9, "raw_features": True})) == []
    assert any("bogus" in p for p in task_problems(spec(net={"bogus": 1})))
    assert any("kernel_size" in p for p in task_problems(spec(net={"kernel_size": 16})))
    assert any("conv_size" in p for p in task_problems(spec(net={"conv_size": 0})))
    assert any("layers" in p for p in task_problems(spec(net={"layers": 1})))
    assert any("width" in p for p in task_problems(spec(net={"width": 0})))
    assert any("features" in p for p in task_problems(spec(net={"features": 0})))
    assert any("loss" in p for p in task_problems(spec(loss={"temporal": 0.25})))
    assert any("spp_choices" in p for p in task_problems(spec(loss={"spp_choices": [16]})))
    assert task_problems(spec(loss={"spp_choices": [1, 2]})) == []
    builder = task_builder("kpcn")
    assert builder.sample_buffers == SAMPLE_BUFFERS
    assert builder.optional_reference_buffers == SPLIT_REFERENCE
    with pytest.raises(KeyError, match="bogus"):
        KPCNConfig.from_dict({"bogus": 1})
    assert KPCNConfig.from_dict(KPCNConfig(width=0.5).to_dict()) == KPCNConfig(width=0.5)


def test_training_job_carries_the_split_reference_only_when_every_clip_has_it() -> None:
    """denoisers.training.job.reference_buffers: diffuse / specular references (features integrator) are carried
    when every clip holds them; a batch then trains the per-branch loss, otherwise the log-radiance fallback."""
    from denoisers.training.data import SequenceConfig, SequenceDataset
    from denoisers.training.job import reference_buffers
    from tests.test_training import synthetic_clip

    def clip(seed: int, features_reference: bool):
        c = synthetic_clip(frames=4, layers=3, seed=seed)
        c.samples["diffuse"] = 0.8 * c.samples["radiance"]
        c.samples["specular"] = 0.2 * c.samples["radiance"]
        if features_reference:
            c.reference["diffuse"] = 0.8 * c.reference["radiance"]
            c.reference["specular"] = 0.2 * c.reference["radiance"]
        return c

    builder = task_builder("kpcn")
    assert reference_buffers(builder, [clip(0, True), clip(1, True)]) == ("radiance", "diffuse", "specular")
    assert reference_buffers(builder, [clip(0, True), clip(1, False)]) == ("radiance",)
    assert reference_buffers(task_builder("afn"), [clip(0, True)]) == ("radiance",)
    task = KPCNTask(KPCNConfig(**SMALL))
    model = task.build_model()
    for features_reference, terms in ((True, {"diffuse", "specular"}), (False, {"log_radiance"})):
        clips = [clip(0, features_reference)]
        config = SequenceConfig(length=2, crop=8, spp=2, sample_buffers=SAMPLE_BUFFERS,
                                reference_buffers=reference_buffers(builder, clips))
        batch = SequenceDataset(clips, config, seed=0).batch(0, 2)
        loss, got = task.loss(model, batch)
        assert set(got) == terms and bool(torch.isfinite(loss))


# ------------------------------------------------------------------------------------ evaluation method
def test_method_matches_the_training_prediction() -> None:
    """The registry method runs the same frame step as training's predict (identity camera: the data's
    world-to-view for an identity to_world is diag(-1, 1, -1))."""
    torch.manual_seed(0)
    task = KPCNTask(KPCNConfig(**SMALL))
    model = task.build_model().eval()
    batch = _batch(n=1, length=2)
    batch["world_to_view"] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])).expand(1, 2, 3, 3).clone()
    with torch.no_grad():
        expected = task.predict(model, batch)[0]
    info = registry.get("kpcn").info
    assert info.trainable and not info.temporal and info.inputs == SAMPLE_BUFFERS
    denoiser = registry.get("kpcn").from_model(model)
    denoiser.reset()
    for t in (1, 0):                                         # single-frame: the order does not matter
        frame = Frame(samples={b: batch[b][0, t] for b in BUFFERS}, index=t,
                      meta={"camera": {"to_world": np.eye(4).tolist()}})
        assert torch.allclose(denoiser.denoise(frame), expected[t], atol=1e-5)
    with pytest.raises(ValueError, match="checkpoint"):
        registry.get("kpcn")()


def test_training_uses_the_spp_round_robin_and_validation_every_layer() -> None:
    """loss.spp_choices (2, 4): batch i denoises with the first choices[i % 2] layers in training (the input
    variance differs between 2 and 4 samples, so the outputs do), every carried layer in eval mode."""
    from denoisers.nets.kpcn_task import KPCNTask

    torch.manual_seed(0)
    task = KPCNTask(KPCNConfig(**SMALL), spp_choices=(2, 4))
    model = task.build_model()
    batch = _batch(layers=4)
    with torch.no_grad():
        batch.index = 0
        at_two = task.predict(model, batch)
        batch.index = 1
        at_four = task.predict(model, batch)
        model.eval()
        validation = task.predict(model, batch)
    assert not torch.allclose(at_two, at_four)
    assert torch.equal(validation, at_four)
    two = {k: (v[:, :, :2] if k in BUFFERS else v) for k, v in batch.items()}
    with torch.no_grad():
        assert torch.allclose(KPCNTask(KPCNConfig(**SMALL)).predict(model, _Batch(two)), at_two)
