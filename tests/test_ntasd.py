"""NTASD (Hasselgren et al. 2020): renderer gradient, sampling inside the networks' frame step, warp,
training and determinism, the evaluation method's sample accounting."""
from __future__ import annotations

import math

import pytest
import torch

from denoisers import adaptive, filters, kernels, registry
from denoisers.adaptive import budget_total, gather_mean, render_adaptive, renderer_derivative
from denoisers.nets.ntasd import NTASDConfig, NTASDNet, decode, encode, grey
from denoisers.nets.ntasd_task import NTASDTask
from denoisers.registry import Frame
from denoisers.training.tasks import NTASD_VARIANTS, task_problems
from denoisers.training.spec import ModelSpec

torch.set_num_threads(1)


# ------------------------------------------------------------------------------------ renderer gradient
def test_renderer_gradient_against_finite_differences_of_the_expected_error() -> None:
    """Synthetic case: Gaussian samples x ~ N(mu_p, sigma_p^2), a fixed linear 'denoiser' B (3 x 3 blur) and
    the squared error to B mu. Per pixel p, the finite difference of the expected error when p gets one more
    sample, E[L(k + e_p)] - E[L(k)], is evaluated directly (the next stored layer added at p, the loss
    recomputed); analytically it is -|B e_p|^2 sigma_p^2 / (k_p (k_p + 1)), and the renderer gradient's
    expectation, the first-order term, is exactly twice that (the second-order term gives back half).
    Checked per pixel by Monte Carlo over the same draws."""
    generator = torch.Generator().manual_seed(1)
    height = width = 5
    mu = torch.rand(height, width, generator=generator, dtype=torch.float64) + 0.5
    sigma = torch.rand(height, width, generator=generator, dtype=torch.float64) * 2 + 0.2
    k = torch.randint(1, 5, (height, width), generator=generator)
    blur = torch.rand(1, 1, 3, 3, generator=generator, dtype=torch.float64)
    target = torch.nn.functional.conv2d(mu[None, None], blur, padding=1)

    def loss(images: torch.Tensor) -> torch.Tensor:                       # (..., 1, H, W) -> (...)
        flat = images.reshape(-1, 1, height, width)
        error = torch.nn.functional.conv2d(flat, blur, padding=1) - target
        return (error ** 2).sum(dim=(1, 2, 3)).reshape(images.shape[:-3])

    draws = 20000
    samples = mu + sigma * torch.randn(draws, int(k.max()) + 1, 1, height, width, generator=generator,
                                       dtype=torch.float64)
    counts = k.expand(draws, height, width)
    means = torch.stack([gather_mean(s, c) for s, c in zip(samples, counts)])          # (D, 1, H, W)
    derivative = renderer_derivative(samples, counts, means)
    image = means.clone().requires_grad_(True)
    loss(image).sum().backward()
    gradient = (image.grad * derivative).mean(dim=0)[0]                                 # (H, W)

    one_more = torch.eye(height * width, dtype=torch.bool).reshape(-1, 1, 1, height, width)   # (M, 1, 1, H, W)
    plus_one = torch.stack([gather_mean(s, c + 1) for s, c in zip(samples, counts)])
    perturbed = torch.where(one_more, plus_one[None], means[None])                       # (M, D, 1, H, W)
    finite = (loss(perturbed) - loss(means)[None]).mean(dim=1).reshape(height, width)

    footprint = (blur ** 2).sum()                         # |B e_p|^2 away from the border
    analytic = -footprint * sigma ** 2 / (k * (k + 1))
    inner = (slice(1, -1), slice(1, -1))
    assert torch.allclose(finite[inner], analytic[inner], rtol=0.1)
    assert bool((gradient < 0).all()) and bool((finite < 0).all())
    assert torch.allclose(gradient, 2 * finite, rtol=0.1)


def test_renderer_gradient_after_the_encoding_is_the_encoded_finite_difference() -> None:
    """With the network's encoding T, the derivative is T(I_{k+1}) - T(I_k) computed from directly gathered
    means of k and k + 1 layers (k = S: T(I_S) - T(I_{S-1})), so it stays within T's range: a firefly after dark
    samples moves the encoded input by at most T(65535), whereas the chain rule T'(I_k) (I_{k+1} - I_k)
    multiplies the firefly by T's steep slope at the dark mean."""
    generator = torch.Generator().manual_seed(5)
    layers = torch.rand(2, 4, 3, 3, 5, generator=generator, dtype=torch.float64) * 0.01
    layers[0, 1, :, 1, 2] = 60000.0                              # a firefly as the second sample of one pixel
    counts = torch.randint(0, 5, (2, 3, 5), generator=generator)
    counts[0, 1, 2] = 1
    means = torch.stack([gather_mean(s, c) for s, c in zip(layers, counts)])
    derivative = renderer_derivative(layers, counts, means, transform=encode)
    more = torch.stack([gather_mean(s, (c + 1).clamp_max(4)) for s, c in zip(layers, counts)])
    fewer = torch.stack([gather_mean(s, (c - 1).clamp_min(0)) for s, c in zip(layers, counts)])
    at_end = (counts >= 4)[:, None]
    direct = torch.where(at_end, encode(means) - encode(fewer), encode(more) - encode(means))
    assert torch.allclose(derivative, direct, atol=1e-9)
    assert float(derivative.abs().max()) <= float(encode(torch.tensor(65535.0))) + 1e-9
    assert float(derivative[0, :, 1, 2].min()) > 1.0            # the firefly pixel: one more sample matters
    linear = renderer_derivative(layers, counts, means)
    dark = means.detach().clone().requires_grad_(True)
    encode(dark).sum().backward()
    chain_rule = dark.grad * linear
    assert float(chain_rule[0, :, 1, 2].min()) > 1000 * float(derivative[0, :, 1, 2].max())
    # Without a transform: the linear difference I_{k+1} - I_k, the same gathered means.
    assert torch.allclose(linear, torch.where(at_end, means - fewer, more - means), atol=1e-9)


def test_renderer_gradient_sign_follows_the_integer_step_and_the_noise() -> None:
    """Per pixel (identity denoiser, squared error): the mean derivative is -2 sigma^2 / (k (k + 1)), so it
    has the sign of E[L(k + 1)] - E[L(k)] = -sigma^2 / (k (k + 1)) and is larger where the noise is."""
    generator = torch.Generator().manual_seed(3)
    sigma = torch.tensor([[0.1, 1.0, 3.0]], dtype=torch.float64)
    mu = torch.ones_like(sigma)
    k = torch.tensor([[2, 2, 2]])
    draws = 40000
    samples = mu + sigma * torch.randn(draws, 3, 1, 1, 3, generator=generator, dtype=torch.float64)
    counts = k.expand(draws, 1, 3)
    means = torch.stack([gather_mean(s, c) for s, c in zip(samples, counts)])
    gradient = (2 * (means - mu) * renderer_derivative(samples, counts, means)).mean(dim=0)[0, 0]
    analytic = -2 * sigma[0] ** 2 / (k[0] * (k[0] + 1))
    assert torch.allclose(gradient, analytic, rtol=0.05, atol=1e-4)
    assert bool((gradient[1:] < gradient[:-1]).all())


def test_render_adaptive_spends_at_most_the_budget_and_gathers_the_first_layers() -> None:
    generator = torch.Generator().manual_seed(0)
    layers = torch.rand(3, 8, 3, 5, 7, generator=generator)
    logits = torch.randn(3, 5, 7, generator=generator, requires_grad=True)
    means, counts = render_adaptive(adaptive.density(logits, 2.5), layers, 2.5)
    for image, count, mean in zip(layers, counts, means):
        assert int(count.sum()) <= budget_total(2.5, 35)
        flat = image.reshape(8, 3, -1)
        direct = torch.stack([flat[:int(c), :, p].mean(0) if c else torch.zeros(3)
                              for p, c in enumerate(count.flatten())], -1)
        assert torch.allclose(mean.reshape(3, -1), direct, atol=1e-6)
    means.sum().backward()
    assert logits.grad is not None and torch.isfinite(logits.grad).all() and logits.grad.abs().sum() > 0
    dasr, dasr_counts = render_adaptive(1 + adaptive.density(logits.detach(), 1.5), layers, 2.5, minimum=1)
    assert int(dasr_counts.min()) >= 1 and all(int(c.sum()) <= budget_total(2.5, 35) for c in dasr_counts)


def test_warp_with_per_image_motion_equals_one_warp_per_image() -> None:
    generator = torch.Generator().manual_seed(2)
    previous = torch.rand(3, 3, 9, 11, generator=generator)
    motion = torch.randn(3, 2, 9, 11, generator=generator) * 2
    batched = kernels.warp_previous(previous, motion)
    for image, vectors, warped in zip(previous, motion, batched):
        assert torch.allclose(warped, filters.warp_previous(image, vectors))


# ------------------------------------------------------------------------------------------ networks
def test_encode_is_the_papers_log_space_and_decode_inverts_it() -> None:
    x = torch.tensor([0.0, 0.5, 3.0, 1e6, float("nan")])
    expected = torch.log1p(torch.tensor([0.0, 0.5, 3.0, 65535.0, 0.0])) ** (1 / 2.2)
    assert torch.allclose(encode(x), expected)
    assert torch.allclose(decode(encode(x[:3])), x[:3], atol=1e-5)
    tiny = torch.tensor([0.0, 1e-6, 1e-4], requires_grad=True)
    encode(tiny).sum().backward()                       # finite slope at black (0-sample pixels)
    assert torch.isfinite(tiny.grad).all()
    assert torch.allclose(decode(encode(tiny.detach())), tiny.detach(), atol=1e-9)
    assert torch.allclose(grey(torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)), torch.tensor(0.2989))


def _batch(n: int = 2, length: int = 3, layers: int = 8, size: int = 16, seed: int = 0) -> dict[str, torch.Tensor]:
    """A synthetic batch: a smooth reference, noisy layers around it, static camera (zero motion)."""
    generator = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(0.2, 1.5, size)
    reference = (ramp.view(1, size) * ramp.view(size, 1)).expand(n, length, 3, size, size).clone()
    noise = torch.rand(n, length, layers, 3, size, size, generator=generator) * 2
    return {"radiance": reference[:, :, None] * noise, "mean.albedo": torch.full((n, length, 3, size, size), 0.5),
            "gbuffer.normal": torch.zeros(n, length, 3, size, size).index_fill_(2, torch.tensor([2]), 1.0),
            "gbuffer.depth": torch.full((n, length, 1, size, size), 2.0),
            "motion": torch.zeros(n, length, 2, size, size), "valid": torch.ones(n, length, 1, size, size),
            "world_to_view": torch.eye(3).expand(n, length, 3, 3).clone(), "reference.radiance": reference}


@pytest.mark.parametrize("method", sorted(NTASD_VARIANTS))
def test_every_variant_trains_a_few_steps_and_lowers_the_loss(method: str) -> None:
    variant, sampling = NTASD_VARIANTS[method]
    torch.manual_seed(0)
    task = NTASDTask(NTASDConfig(variant=variant, sampling=sampling, width=0.25, levels=3, max_samples=8), 2.0)
    model = task.build_model()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = _batch()
    first = float(task.loss(model, batch)[0].detach())
    for _ in range(25):
        optimizer.zero_grad()
        loss, _ = task.loss(model, batch)
        loss.backward()
        optimizer.step()
    assert float(task.loss(model, batch)[0].detach()) < 0.8 * first
    if sampling != "uniform":
        assert model.sampler_head.weight.grad is not None and model.sampler_head.weight.grad.abs().sum() > 0


def test_kernel_variants_have_the_papers_heads() -> None:
    """Fig. 3: 51 per-pixel outputs at the finest level of the temporal denoiser (two 5 x 5 kernels + alpha'),
    26 at the two coarser ones (a kernel + alpha); 25 at the finest for the per-frame KPN."""
    temporal = NTASDNet(NTASDConfig(variant="temporal", sampling="uniform"))
    assert [head.out_channels for head in temporal.heads] == [51, 26, 26]
    kpn = NTASDNet(NTASDConfig(variant="kpn", sampling="uniform"))
    assert [head.out_channels for head in kpn.heads] == [25, 26, 26]
    assert NTASDNet(NTASDConfig(variant="direct", sampling="uniform")).heads[0].out_channels == 3


def test_invalid_variant_settings_are_rejected() -> None:
    with pytest.raises(ValueError, match="temporal"):
        NTASDConfig(variant="kpn", sampling="adaptive")
    spec = ModelSpec(id="x", method="ntasd", seed=0, net={"width": 0.5, "bogus": 1}, loss={},
                     data={"spp": 8, "backward_prob": 0.0}, optimizer={}, budget={}, compute={})
    assert any("bogus" in problem for problem in task_problems(spec))
    spec = ModelSpec(id="x", method="dasr", seed=0, net={}, loss={"budget": 16}, data={"spp": 8}, optimizer={},
                     budget={}, compute={})
    assert any("budget" in problem for problem in task_problems(spec))


# --------------------------------------------------------------------------------- evaluation method
def _frames(batch: dict[str, torch.Tensor], n: int = 0) -> list[Frame]:
    frames = []
    for t in range(batch["radiance"].shape[1]):
        frames.append(Frame(samples={"radiance": batch["radiance"][n, t], "albedo": batch["mean.albedo"][n, t][None]},
                            pixel={"motion": batch["motion"][n, t], "valid": batch["valid"][n, t],
                                   "gbuffer.normal": batch["gbuffer.normal"][n, t],
                                   "gbuffer.depth": batch["gbuffer.depth"][n, t]},
                            index=t, meta={"camera": {"to_world": torch.eye(4).tolist()}}, budget=3.0))
    return frames


@pytest.mark.parametrize("method", sorted(NTASD_VARIANTS))
def test_method_matches_the_training_prediction_and_keeps_the_budget(method: str) -> None:
    """The registry method streams frames through the same frame step as training's predict (identity
    camera, so view space = world space): same outputs; every sample map within the budget, a temporal
    variant's first frame sampled uniformly."""
    variant, sampling = NTASD_VARIANTS[method]
    torch.manual_seed(0)
    task = NTASDTask(NTASDConfig(variant=variant, sampling=sampling, width=0.25, levels=3, max_samples=8), 3.0)
    model = task.build_model().eval()
    batch = _batch(n=1, length=3)
    batch["world_to_view"] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])).expand(1, 3, 3, 3).clone()
    with torch.no_grad():
        expected = task.predict(model, batch)[0]
    denoiser = registry.get(method).from_model(model)
    denoiser.reset()
    with torch.no_grad():
        outputs = [denoiser.denoise(frame) for frame in _frames(batch)]
    for t, output in enumerate(outputs):
        assert torch.allclose(output.radiance, expected[t], atol=1e-5)
        assert int(output.sample_map.sum()) <= budget_total(3.0, 16 * 16)
        if t == 0 and variant == "temporal":
            assert bool((output.sample_map == 3).all())
        if sampling == "uniform":
            assert bool((output.sample_map == 3).all())


def test_trained_model_is_deterministic(tmp_path) -> None:
    """Two trainings with the same seed and data give bit-identical weights (the trainer's determinism
    applied to the adaptive variant, whose counts are a deterministic function of the weights)."""
    from denoisers.training.loop import Trainer, TrainerConfig

    class Source:
        def batch(self, index: int, batch_size: int) -> dict[str, torch.Tensor]:
            return _batch(n=batch_size, seed=index)

        def describe(self) -> dict:
            return {"synthetic": 1}

    weights = []
    for run in range(2):
        task = NTASDTask(NTASDConfig(variant="temporal", sampling="adaptive", width=0.25, levels=3, max_samples=8), 2.0)
        config = TrainerConfig(seed=5, batch_size=2, max_steps=4, lr=1e-3, validate_every=1000, checkpoint_every=1000,
                               log_every=1, progress=False, threads=1)
        trainer = Trainer(task, Source(), [], config, tmp_path / f"run{run}")
        trainer.run()
        weights.append({k: v.clone() for k, v in trainer.model.state_dict().items()})
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert not math.isnan(float(next(iter(weights[0].values())).sum()))


def test_bf16_wrapper_of_the_trainer_runs_the_frame_steps_under_autocast() -> None:
    """The trainer's bf16 step hands the task an AutocastForward wrapper; the NTASD task unwraps it, runs the
    frame steps under its autocast and returns a float32 loss close to the fp32 one (bf16 rounding only)."""
    from denoisers.training.precision import AutocastForward

    torch.manual_seed(0)
    task = NTASDTask(NTASDConfig(variant="temporal", sampling="adaptive", width=0.25, levels=3, max_samples=8), 2.0)
    model = task.build_model()
    batch = _batch()
    fp32, _ = task.loss(model, batch)
    bf16, _ = task.loss(AutocastForward(model, torch.bfloat16), batch)
    assert bf16.dtype == torch.float32 and torch.isfinite(bf16)
    assert float(bf16.detach()) == pytest.approx(float(fp32.detach()), rel=0.1)


def test_a_saturated_blend_weight_keeps_its_gradient_under_bf16_autocast() -> None:
    """The temporal blend alpha' at a logit of 8: sigmoid(8) = 0.99966 in float32, exactly 1 in bf16, where
    its gradient would vanish for good. The heads' weights are computed in float32 under autocast, so the
    blend bias gets the analytic gradient sigma'(8) * dL/dalpha' and not zero."""
    torch.manual_seed(0)
    net = NTASDNet(NTASDConfig(variant="temporal", sampling="uniform", width=0.25, levels=3))
    taps = net.config.kernel_size ** 2
    blend = 2 * taps
    with torch.no_grad():
        net.heads[0].weight[blend].zero_()
        net.heads[0].bias[blend] = 8.0
    x = torch.rand(1, net.config.denoiser_in_channels, 16, 16)
    noisy, history = torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net.denoise(x, noisy, history)
    out.float().sum().backward()
    gradient = float(net.heads[0].bias.grad[blend])
    assert abs(gradient) > 0.0
    # Reference: the same network in float32; only bf16 rounding of the other terms may differ.
    net.zero_grad()
    net.denoise(x, noisy, history).sum().backward()
    assert gradient == pytest.approx(float(net.heads[0].bias.grad[blend]), rel=0.2, abs=1e-4)


@pytest.mark.parametrize("method", sorted(m for m, (variant, _) in NTASD_VARIANTS.items() if variant == "temporal"))
def test_a_shots_first_history_is_the_noisy_uniform_image(method: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Sec. 2.2: "For the first frame, we initialize the recurrent term to the noisy uniformly sampled image at our
    target sample count." At 3 spp that is the mean of the first 3 stored layers; the frame is sampled so, within
    its budget (an adaptive sampler has no history to read yet)."""
    from denoisers.nets.ntasd_task import batch_frame, frame_step

    variant, sampling = NTASD_VARIANTS[method]
    torch.manual_seed(0)
    model = NTASDTask(NTASDConfig(variant=variant, sampling=sampling, width=0.25, levels=3, max_samples=8),
                      3.0).build_model().eval()
    batch = _batch(n=1, length=2)
    histories = []
    denoise = model.denoise
    monkeypatch.setattr(model, "denoise", lambda x, noisy, history=None: histories.append(history)
                        or denoise(x, noisy, history))
    with torch.no_grad():
        step = frame_step(model, batch_frame(batch, 0), None, 3.0)
    expected = torch.log(batch["radiance"][:, 0, :3].mean(dim=1) + 1.0) ** (1.0 / 2.2)     # the paper's encoding
    assert torch.allclose(histories[0], expected, atol=1e-6)
    assert bool((step.counts == 3).all()) and step.logits is None
