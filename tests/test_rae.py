"""Tests of the RAE (Chaitanya et al. 2017): network and inputs (denoisers/nets/rae.py, rae_task.py), loss
(denoisers/losses.py) and evaluation method (denoisers/methods/rae.py), on tiny tensors."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from denoisers import registry
from denoisers.losses import (PAPER_FRAME_WEIGHTS_7, frame_weights, gradient_l1, laplacian_of_gaussian, log_kernel,
                              rae_loss, spatial_l1, temporal_l1)
from denoisers.methods.rae import RecurrentAutoencoderDenoiser
from denoisers.nets import build_net, count_parameters, net_spec
from denoisers.nets import rae as rae_net
from denoisers.nets.rae import PAPER_PARAMETER_COUNT, RAEConfig, RecurrentAutoencoder, conv_flops, parameter_report
from denoisers.nets.rae_task import RAETask, decode_color, encode_color, prepare_inputs
from denoisers.nets.view import world_to_view
from denoisers.training.data import SequenceConfig, SequenceDataset, SequencePlan
from denoisers.training.loop import CheckpointError, Trainer, TrainerConfig, load_model
from scenegen.camera import look_at_matrix
from tests.test_training import synthetic_clip

REPO_ROOT = Path(__file__).resolve().parents[1]
TINY = RAEConfig(width=0.125, levels=2)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny networks run faster on one thread on a busy machine; restore the setting afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_model(seed: int = 0, config: RAEConfig = TINY) -> RecurrentAutoencoder:
    torch.manual_seed(seed)
    return RecurrentAutoencoder(config).eval()


# ------------------------------------------------------------------------------------ architecture
def test_full_size_network_is_the_paper_layer_list() -> None:
    # Fig. 4 "AE" column + §4.2 recurrent blocks, written out by hand: (input, output) features per conv.
    feedforward = [(7, 32), (32, 32), (32, 43), (43, 57), (57, 76), (76, 101), (101, 101),       # encoder (7)
                   (101 + 101, 76), (76, 76), (76 + 76, 57), (57, 57), (57 + 57, 43), (43, 43),  # decoder (10)
                   (43 + 43, 32), (32, 32), (32 + 32, 128), (128, 64),
                   (64, 3)]                                                                      # output (1)
    recurrent = [pair for c in (32, 43, 57, 76, 101, 101) for pair in ((c, c), (2 * c, c), (c, c))]
    expected = sorted(feedforward + recurrent)
    model = RecurrentAutoencoder()
    convs = [m for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 36 == len(expected)                                      # §5.1: 36 convolution layers
    assert sorted((c.in_channels, c.out_channels) for c in convs) == expected
    assert all(c.kernel_size == (3, 3) for c in convs)
    expected_count = sum(9 * a * b + b for a, b in expected)
    assert count_parameters(model) == expected_count == 1_951_935
    report = parameter_report(width=0.5)
    assert "1,951,935" in report and f"{PAPER_PARAMETER_COUNT:,}" in report and "width 0.5" in report
    assert RAEConfig().encoder_features == [32, 43, 57, 76, 101]
    assert RAEConfig(width=0.5).encoder_features == [16, 21, 28, 38, 51]
    assert RAEConfig(levels=6).encoder_features[-1] == 135                        # Fig. 4 "AE large"
    assert RAEConfig().in_channels == 7 and RAEConfig(demodulate=False, features=()).in_channels == 3
    assert conv_flops(RAEConfig(), 128, 128) == 2 * 9 * sum(
        a * b * (128 >> level) ** 2 for (a, b), level in zip(
            feedforward + recurrent,
            [0, 0, 1, 2, 3, 4, 5, 4, 4, 3, 3, 2, 2, 1, 1, 0, 0, 0] + [lv for lv in (0, 1, 2, 3, 4, 5) for _ in range(3)]))


def test_shapes_padding_and_state_of_a_tiny_network() -> None:
    model = tiny_model()
    x = torch.rand(2, 3, 7, 13, 10)                                              # not multiples of 2^levels
    y, state = model(x)
    assert y.shape == (2, 3, 3, 13, 10)
    assert [tuple(h.shape) for h in state] == [(2, 4, 16, 12), (2, 5, 8, 6), (2, 5, 4, 3)]
    with pytest.raises(ValueError, match="expected input"):
        model.step(torch.rand(1, 5, 8, 8))
    rebuilt = build_net(**net_spec(model))
    assert isinstance(rebuilt, RecurrentAutoencoder) and rebuilt.config == model.config


def test_recurrent_state_carries_information_between_frames() -> None:
    model = tiny_model()
    x = torch.rand(1, 3, 7, 8, 8)
    with torch.no_grad():
        carried, _ = model(x)
        reset, _ = model(x, reset_every_frame=True)
        torch.testing.assert_close(carried[:, 0], reset[:, 0], rtol=0, atol=0)    # first frame: zero state either way
        assert (carried[:, 1:] - reset[:, 1:]).abs().max() > 1e-4                  # later frames use the state
        # Stepping frame by frame is the same computation as the sequence call.
        state = None
        for t in range(3):
            out, state = model.step(x[:, t], state)
            torch.testing.assert_close(out, carried[:, t])
        for t in range(3):
            torch.testing.assert_close(model.step(x[:, t])[0], reset[:, t])


@pytest.mark.parametrize("fused", [True, False], ids=["onednn-fused", "fallback"])
def test_inference_step_matches_the_plain_forward_and_leaves_training_intact(fused: bool, monkeypatch) -> None:
    """The fast inference path (channels-last, oneDNN convolution with fused leaky ReLU, or its fallback
    without the fused op) computes the same frames as the plain eager step, state carried over 3 frames.
    Tolerance: the channels-last kernels sum the 3 x 3 x C_in products in another order, which moves
    outputs of magnitude ~1 by a few 1e-6 (measured <= 5e-6 here); atol 2e-5 + rtol 1e-4 allows that
    rounding and nothing larger."""
    monkeypatch.setattr(rae_net, "_FUSED_CONV", fused and rae_net.fused_conv_available())
    torch.manual_seed(1)
    model = RecurrentAutoencoder(RAEConfig(width=0.5, levels=3)).eval()           # real channel counts, 3 levels
    frames = [torch.rand(1, 7, 37, 50) * 2 - 0.5 for _ in range(3)]             # padded to 40 x 56 inside
    plain_state = fast_state = None
    for x in frames:
        with torch.no_grad():
            plain, plain_state = model.step(x, plain_state)
        fast, fast_state = model.inference_step(x, fast_state)
        assert fast.shape == plain.shape == (1, 3, 37, 50) and fast.is_contiguous()
        torch.testing.assert_close(fast, plain, rtol=1e-4, atol=2e-5)
        for a, b in zip(fast_state, plain_state):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=2e-5)
    # Either path continues from the other's state.
    torch.testing.assert_close(model.inference_step(frames[0], plain_state)[0],
                               model.step(frames[0], plain_state)[0].detach(), rtol=1e-4, atol=2e-5)
    # The model is untouched: autograd through the plain path still works after inference.
    model.train()
    out, _ = model(torch.rand(1, 2, 7, 16, 16, requires_grad=True))
    out.square().mean().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert all(p.is_contiguous() for p in model.parameters())


# ------------------------------------------------------------------------------------------ inputs
def test_zero_feature_init_starts_as_a_network_that_ignores_the_features() -> None:
    """feature_init "zero": the first convolution's weights on the feature channels (3:) are 0 and every other
    weight is the He draw of the same seed, so at initialisation the output does not depend on the features;
    their weights still receive gradient. The key round-trips; "he" (the paper's) is left out of to_dict, and a
    network without features is the same (and has the same fingerprint) either way."""
    he_config, zero_config = TINY, RAEConfig(width=0.125, levels=2, feature_init="zero")
    torch.manual_seed(3)
    he = RecurrentAutoencoder(he_config)
    torch.manual_seed(3)
    zero = RecurrentAutoencoder(zero_config)
    first = "encoder_convs.0.0.weight"
    for (name, a), (_, b) in zip(he.state_dict().items(), zero.state_dict().items()):
        if name == first:
            assert torch.equal(b[:, :3], a[:, :3]) and not b[:, 3:].any() and a[:, 3:].abs().sum() > 0
        else:
            assert torch.equal(a, b), name
    x = torch.rand(2, he_config.in_channels, 16, 16)
    changed = x.clone()
    changed[:, 3:] = torch.randn(2, he_config.in_channels - 3, 16, 16) * 5.0
    out, _ = zero.step(x)
    torch.testing.assert_close(zero.step(changed)[0], out, rtol=0, atol=0)
    assert not torch.allclose(he.step(changed)[0], he.step(x)[0])
    out.square().mean().backward()
    assert zero.encoder_convs[0][0].weight.grad[:, 3:].abs().sum() > 0
    assert RAEConfig.from_dict(zero_config.to_dict()) == zero_config and zero_config.to_dict()["feature_init"] == "zero"
    assert "feature_init" not in he_config.to_dict()
    colour_only = RAEConfig(demodulate=False, features=(), feature_init="zero")
    assert colour_only == RAEConfig(demodulate=False, features=()) and "feature_init" not in colour_only.to_dict()
    with pytest.raises(ValueError, match="feature_init"):
        RAEConfig(feature_init="xavier")


def test_view_space_normals_follow_the_camera() -> None:
    # Camera at the origin looking along world +x with y up: image-right is world +z.
    rotation = world_to_view(look_at_matrix(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])))
    torch.testing.assert_close(rotation @ torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(rotation @ torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(rotation @ torch.tensor([-1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0]))


def test_inputs_are_demodulated_and_raised_to_the_power_0_2() -> None:
    shape = (1, 4, 4)
    radiance = torch.full((3, *shape[1:]), 0.32)
    albedo = torch.tensor([0.5, 0.004, 0.0]).view(3, 1, 1).expand(3, 4, 4)
    normal = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 4, 4)
    depth, roughness = torch.full(shape, 2.5), torch.full(shape, 0.3)
    x, divisor = prepare_inputs(RAEConfig(), radiance, albedo, normal, depth, roughness, torch.eye(3))
    assert x.shape == (7, 4, 4)
    torch.testing.assert_close(divisor[:, 0, 0], torch.tensor([0.5, 0.01, 0.01]))  # albedo floor 0.01
    torch.testing.assert_close(x[:3, 0, 0], torch.tensor([0.64, 32.0, 32.0]) ** 0.2)
    torch.testing.assert_close(x[3:, 0, 0], torch.tensor([0.0, 0.0, 2.5, 0.3]))
    colour_only, ones = prepare_inputs(RAEConfig(demodulate=False, features=()), radiance, albedo, normal, depth,
                                       roughness, torch.eye(3))
    assert colour_only.shape == (3, 4, 4) and torch.equal(ones, torch.ones(3, 4, 4))
    torch.testing.assert_close(colour_only, torch.full((3, 4, 4), 0.32**0.2))
    linear = torch.rand(3, 4, 4) * 10
    torch.testing.assert_close(decode_color(encode_color(linear, divisor, 0.2), divisor, 0.2), linear)


def test_depth_enters_in_metres_or_as_log1p() -> None:
    shape = (1, 2, 2)
    radiance, albedo = torch.full((3, 2, 2), 0.5), torch.full((3, 2, 2), 0.5)
    normal = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 2, 2)
    depth = torch.tensor([[0.0, 1.0], [84.5, float("inf")]]).view(shape)
    roughness = torch.zeros(shape)
    metres, _ = prepare_inputs(RAEConfig(features=("depth",)), radiance, albedo, normal, depth, roughness,
                               torch.eye(3))
    torch.testing.assert_close(metres[3], torch.tensor([[0.0, 1.0], [84.5, 0.0]]))   # non-finite -> 0
    logged, _ = prepare_inputs(RAEConfig(features=("depth",), depth_encoding="log1p"), radiance, albedo, normal,
                               depth, roughness, torch.eye(3))
    torch.testing.assert_close(logged[3], torch.tensor([[0.0, math.log(2.0)], [math.log(85.5), 0.0]]))
    with pytest.raises(ValueError, match="depth_encoding"):
        RAEConfig(depth_encoding="inverse")
    # Checkpoints written before the key existed keep their fingerprint (the default is not serialised) and
    # load with the old behaviour; a non-default encoding round-trips.
    default = RAEConfig().to_dict()
    assert "depth_encoding" not in default
    assert RAEConfig.from_dict(default).depth_encoding == "metres"
    logged_config = RAEConfig(depth_encoding="log1p")
    assert RAEConfig.from_dict(logged_config.to_dict()) == logged_config


# ------------------------------------------------------------------------------------------ losses
def test_frame_weights_are_the_papers() -> None:
    weights = frame_weights(7)
    np.testing.assert_allclose(weights.numpy(), PAPER_FRAME_WEIGHTS_7, atol=5e-4)  # printed to 3 decimals
    assert weights[-1] == 1.0 and bool(torch.all(weights[1:] > weights[:-1]))


def test_spatial_l1_of_a_known_pair() -> None:
    pred = torch.zeros(1, 2, 3, 4, 4)
    target = torch.ones(1, 2, 3, 4, 4)
    target[0, 1] = 2.0 * (-1.0) ** torch.arange(16.0).view(4, 4)
    torch.testing.assert_close(spatial_l1(pred, target), torch.tensor([1.0, 2.0]))


def test_hfen_gradient_loss() -> None:
    kernel = log_kernel()
    assert kernel.shape == (15, 15) and abs(float(kernel.sum())) < 1e-6
    torch.testing.assert_close(kernel, kernel.flip(0).flip(1))
    # A constant image has no edges: zero gradient loss whatever the constants.
    pred, target = torch.full((2, 3, 3, 20, 20), 0.7), torch.full((2, 3, 3, 20, 20), 0.2)
    assert float(gradient_l1(pred, target).abs().max()) < 1e-6
    assert float(spatial_l1(pred, target).min()) == pytest.approx(0.5)
    # The LoG is a Laplacian of the smoothed image: (x - c)^2 has Laplacian 2 away from the borders.
    x = torch.arange(40.0) - 20
    parabola = (x**2).expand(40, 40).reshape(1, 1, 1, 40, 40)
    interior = laplacian_of_gaussian(parabola)[..., 10:30, 10:30]
    torch.testing.assert_close(interior, torch.full_like(interior, 2.0), atol=2e-3, rtol=0)
    # One bright pixel far from the border: mean |LoG| = sum |kernel| / pixels.
    impulse = torch.zeros(1, 1, 1, 32, 32)
    impulse[..., 16, 16] = 1.0
    torch.testing.assert_close(gradient_l1(impulse, torch.zeros_like(impulse)), kernel.abs().sum().view(1) / 1024)


@pytest.mark.parametrize("shape", [(2, 3, 3, 64, 64), (1, 1, 1, 5, 9), (3, 20, 33)])
def test_separable_log_equals_the_direct_convolution(shape: tuple[int, ...]) -> None:
    # Reference: torch's own 2-D correlation of the replicate-padded image with the 15 x 15 kernel (the
    # LoG's former implementation); values and the input gradient must agree, borders and tiny frames included.
    torch.manual_seed(3)
    x = torch.randn(shape, dtype=torch.float64, requires_grad=True)
    flat = x.reshape(-1, 1, shape[-2], shape[-1])
    reference = torch.nn.functional.conv2d(torch.nn.functional.pad(flat, (7, 7, 7, 7), mode="replicate"),
                                           log_kernel().double()[None, None]).reshape(shape)
    ours = laplacian_of_gaussian(x)
    torch.testing.assert_close(ours, reference, atol=1e-6, rtol=1e-6)
    weights = torch.randn(shape, dtype=torch.float64)
    grad_ours, = torch.autograd.grad((ours * weights).sum(), x)
    grad_reference, = torch.autograd.grad((reference * weights).sum(), x)
    torch.testing.assert_close(grad_ours, grad_reference, atol=1e-6, rtol=1e-6)


def test_temporal_loss() -> None:
    # Identical frames over time (but pred != target): the temporal derivatives agree, no temporal loss.
    pred = torch.rand(1, 1, 3, 6, 6).expand(1, 4, 3, 6, 6)
    target = torch.rand(1, 1, 3, 6, 6).expand(1, 4, 3, 6, 6)
    assert float(temporal_l1(pred, target).abs().max()) == 0.0 and float(spatial_l1(pred, target).min()) > 0
    # Hand-computed: pred 0, 1, 1 against target 0, 0, 0 -> |dP/dt - dT/dt| = 0 (no predecessor), 1, 0.
    pred = torch.tensor([0.0, 1.0, 1.0]).view(1, 3, 1, 1, 1).expand(2, 3, 3, 5, 5)
    torch.testing.assert_close(temporal_l1(pred, torch.zeros_like(pred)), torch.tensor([0.0, 1.0, 0.0]))


def test_combined_loss_weights_terms_and_frames_as_the_paper() -> None:
    a = torch.tensor([0.1, 0.5, 0.2, 0.9, 0.4, 0.3, 0.8])
    b = torch.tensor([0.3, 0.1, 0.2, 0.4, 0.6, 0.3, 0.1])
    pred, target = a.view(1, 7, 1, 1, 1).expand(1, 7, 3, 8, 8), b.view(1, 7, 1, 1, 1).expand(1, 7, 3, 8, 8)
    spatial = (a - b).abs()
    temporal = torch.cat([torch.zeros(1), ((a[1:] - a[:-1]) - (b[1:] - b[:-1])).abs()])
    weights = torch.tensor(PAPER_FRAME_WEIGHTS_7)
    expected = (weights * (0.8 * spatial + 0.1 * temporal)).sum()                # constant frames: no HFEN term
    total, terms = rae_loss(pred, target)
    torch.testing.assert_close(total, expected, atol=2e-3, rtol=0)
    assert set(terms) == {"spatial", "gradient", "temporal"}
    spatial_only, terms = rae_loss(pred, target, weights={"spatial": 1.0})
    torch.testing.assert_close(spatial_only, (frame_weights(7) * spatial).sum())
    assert set(terms) == {"spatial"}
    with pytest.raises(ValueError, match="unknown loss terms"):
        rae_loss(pred, target, weights={"perceptual": 1.0})


# ------------------------------------------------------------------------------------------ method
def clip_frames(clip, spp: int = 1):
    """Frames as method ``rae_samples`` reads them (features averaged over the samples)."""
    return list(registry.clip_frames(clip, registry.get("rae_samples").info, spp))


def test_method_streams_frames_and_reset_clears_the_state() -> None:
    model = tiny_model()
    frames = clip_frames(synthetic_clip(frames=3, height=12, width=10))
    method = RecurrentAutoencoderDenoiser.from_model(model)
    method.reset()
    streamed = [method.denoise(f) for f in frames]
    assert all(o.shape == (3, 12, 10) and bool(torch.isfinite(o).all()) for o in streamed)

    def alone(frame) -> torch.Tensor:
        fresh = RecurrentAutoencoderDenoiser.from_model(model)
        fresh.reset()
        return fresh.denoise(frame)

    assert not torch.allclose(streamed[2], alone(frames[2]))                      # state carried ...
    method.reset()
    torch.testing.assert_close(method.denoise(frames[2]), alone(frames[2]), rtol=0, atol=0)  # ... reset() clears it
    resetting = RecurrentAutoencoderDenoiser.from_model(model, reset_state_every_frame=True)
    resetting.reset()
    for frame in frames:
        torch.testing.assert_close(resetting.denoise(frame), alone(frame), rtol=0, atol=0)
    cut = synthetic_clip(frames=3, height=12, width=10, cut=2)
    method.reset()
    outputs = [method.denoise(f) for f in clip_frames(cut)]
    torch.testing.assert_close(outputs[2], alone(clip_frames(cut)[2]), rtol=0, atol=0)  # a camera cut resets too


@pytest.mark.parametrize("net_config", [TINY, RAEConfig(width=0.125, levels=2, features=()),
                                    RAEConfig(width=0.125, levels=2, demodulate=False, features=())],
                         ids=["all", "untextured", "colour_only"])
def test_method_matches_the_training_path(net_config: RAEConfig) -> None:
    """The evaluated method sees what training saw, for each input set of the ablation (Fig. 3)."""
    model = tiny_model(config=net_config)
    clip = synthetic_clip(frames=3, height=12, width=10)
    config = SequenceConfig(length=3, crop=None, spp=1).without_augmentation()
    batch = SequenceDataset([clip], config).sequence(
        SequencePlan(clip=0, scene=clip.scene, frames=(0, 1, 2), layers=((0,), (0,), (0,)), crop=(0, 0)))
    with torch.no_grad():
        trained = RAETask(net_config).predict(model, {k: v[None] for k, v in batch.items()})[0]
    method = RecurrentAutoencoderDenoiser.from_model(model)
    method.reset()
    streamed = torch.stack([method.denoise(f) for f in clip_frames(clip)])
    torch.testing.assert_close(streamed, trained, rtol=1e-5, atol=1e-6)


def test_gbuffer_rae_reads_the_gbuffer_and_matches_its_training_path() -> None:
    """``rae`` (the paper's): per-sample radiance, albedo and features from the pixel-centre G-buffer. Its streamed
    output equals the training task's prediction on the same clip; it follows the G-buffer albedo and ignores
    the per-sample one; each method refuses the other's models; features_from round-trips (default left out)."""
    from denoisers.methods.rae import GBufferRecurrentAutoencoderDenoiser
    from denoisers.nets.rae_task import GBUFFER_FEATURE_BUFFERS

    config = RAEConfig(width=0.125, levels=2, features_from="gbuffer")
    assert RAEConfig.from_dict(config.to_dict()) == config and "features_from" not in TINY.to_dict()
    model = tiny_model(config=config)
    clip = synthetic_clip(frames=3, height=12, width=10)
    sequence = SequenceConfig(length=3, crop=None, spp=1, sample_buffers=("radiance",),
                              pixel_buffers=GBUFFER_FEATURE_BUFFERS).without_augmentation()
    batch = SequenceDataset([clip], sequence).sequence(
        SequencePlan(clip=0, scene=clip.scene, frames=(0, 1, 2), layers=((0,), (0,), (0,)), crop=(0, 0)))
    task = RAETask(config, name="rae", buffers=("radiance",))
    with torch.no_grad():
        trained = task.predict(model, {k: v[None] for k, v in batch.items()})[0]
    info = registry.get("rae").info
    assert info.inputs == ("radiance",) and info.pixel_inputs == GBUFFER_FEATURE_BUFFERS
    frames = list(registry.clip_frames(clip, info, 1))
    method = GBufferRecurrentAutoencoderDenoiser.from_model(model)
    method.reset()
    streamed = torch.stack([method.denoise(f) for f in frames])
    torch.testing.assert_close(streamed, trained, rtol=1e-5, atol=1e-6)
    # The G-buffer albedo is the divisor: halving it changes the output; the samples carry no albedo at all.
    assert "albedo" not in frames[0].samples
    halved = registry.Frame(**{**frames[0].__dict__, "pixel": {**frames[0].pixel,
                                                              "gbuffer.albedo": frames[0].pixel["gbuffer.albedo"] / 2}})
    method.reset()
    assert not torch.allclose(method.denoise(halved), streamed[0])
    with pytest.raises(ValueError, match="method 'rae'"):
        RecurrentAutoencoderDenoiser.from_model(model)
    with pytest.raises(ValueError, match="rae_samples"):
        GBufferRecurrentAutoencoderDenoiser.from_model(tiny_model())
    with pytest.raises(ValueError, match="radiance alone"):
        RAETask(config)


def test_method_output_is_finite_for_nan_inf_and_spikes() -> None:
    frame = clip_frames(synthetic_clip(frames=1, height=8, width=8), spp=2)[0]
    frame.samples["radiance"][0, 0, 1, 1] = float("nan")
    frame.samples["radiance"][1, 1, 2, 2] = float("inf")
    frame.samples["radiance"][0, 2, 3, 3] = 1e30
    frame.samples["normal"][0, :, 4, 4] = float("nan")
    frame.samples["albedo"][1, :, 5, 5] = -float("inf")
    method = RecurrentAutoencoderDenoiser.from_model(tiny_model())
    method.reset()
    out = method.denoise(frame)
    assert out.shape == (3, 8, 8) and bool(torch.isfinite(out).all())


def test_method_registration_checkpoint_and_errors(tmp_path: Path) -> None:
    info = registry.get("rae_samples").info
    assert info.trainable and info.temporal
    assert info.inputs == ("radiance", "albedo", "normal", "depth", "roughness")
    paper = registry.get("rae").info
    assert paper.trainable and paper.temporal and paper.inputs == ("radiance",)
    assert paper.pixel_inputs == ("gbuffer.albedo", "gbuffer.normal", "gbuffer.depth", "gbuffer.roughness")
    for name in ("rae", "rae_samples"):
        with pytest.raises(ValueError, match=f"method '{name}' needs params.checkpoint"):
            registry.build(name)
    frame = clip_frames(synthetic_clip(frames=1, height=8, width=8))[0]
    missing = tmp_path / "nowhere" / "best.pt"
    method = registry.build("rae_samples", {"checkpoint": str(missing)})          # lazy: building does not read it
    with pytest.raises(CheckpointError, match=str(missing)):
        method.denoise(frame)
    no_camera = clip_frames(synthetic_clip(frames=1, height=8, width=8))[0]
    no_camera.meta = {}
    with pytest.raises(ValueError, match="camera"):
        RecurrentAutoencoderDenoiser.from_model(tiny_model()).denoise(no_camera)
    # The default config's RAE rows name a model the training section defines.
    config = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    rows = [m for m in config["evaluation"]["methods"] if m["method"] == "rae"]
    assert rows and all(m["params"]["model"] in [t["id"] for t in config["training"]["models"]] for m in rows)


def test_a_trained_checkpoint_drives_the_method(tmp_path: Path) -> None:
    dataset = SequenceDataset([synthetic_clip()], SequenceConfig(length=3, crop=8), seed=0)
    trainer = Trainer(RAETask(TINY), dataset, [], TrainerConfig(max_steps=1, batch_size=1, progress=False,
                                                               checkpoint_seconds=None), tmp_path)
    result = trainer.run()
    frames = clip_frames(synthetic_clip(frames=2, height=12, width=10))
    from_file = registry.build("rae_samples", {"checkpoint": str(result.best)})
    from_memory = RecurrentAutoencoderDenoiser.from_model(load_model(result.best))
    for method in (from_file, from_memory):
        method.reset()
    for frame in frames:
        torch.testing.assert_close(from_file.denoise(frame), from_memory.denoise(frame), rtol=0, atol=0)


# ------------------------------------------------------------------------------------------ learning
def test_a_tiny_network_overfits_one_tiny_clip(tmp_path: Path) -> None:
    """40 Adam steps (lr 3e-3, batches of 2 sequences of 3 frames, 16 x 16) cut the loss at least 5-fold."""
    clip = synthetic_clip(frames=4, height=16, width=16)
    config = SequenceConfig(length=3, crop=None, spp=1).without_augmentation()
    dataset = SequenceDataset([clip], config, seed=0)
    probe = dataset.batch(0, 1)
    task = RAETask(RAEConfig(width=0.25, levels=2))
    trainer = Trainer(task, dataset, [probe], TrainerConfig(max_steps=40, batch_size=2, lr=3e-3,
                                                           schedule={"name": "constant"}, validate_every=0,
                                                           checkpoint_every=0, checkpoint_seconds=None,
                                                           progress=False, threads=1), tmp_path)
    trainer._setup()
    before = trainer.evaluate()["loss"]
    trainer.run()
    after = trainer.evaluate()["loss"]
    assert after < before / 5, (before, after)
