"""AFN (Isik et al. 2021): affinity kernels against a direct per-pixel evaluation, dilation footprints, the
analytic backward against autograd's numerical gradient, joint normalisation (Eq. 8), lambda accumulation
against the direct recursion (Eq. 3, 5), kernel size at test time, SMAPE / temporal loss on hand-computed
cases, the network against the paper's parameter count, training and determinism, the method."""
from __future__ import annotations

import math

import pytest
import torch

from denoisers import affinity, registry
from denoisers.nets import count_parameters
from denoisers.nets.afn import AFNConfig, AFNNet
from denoisers.nets.afn_task import AFNTask, afn_loss, frame_step, sample_features, smape
from denoisers.registry import Frame
from denoisers.training.spec import ModelSpec
from denoisers.training.tasks import task_builder, task_problems

torch.set_num_threads(1)


def _random(shape: tuple[int, ...], seed: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


# ------------------------------------------------------------------------------------ affinity kernels
def _direct_sums(image, features, neighbours, bandwidth, center, size, dilation):
    """Eq. 4 and the sums of Eq. 6 evaluated pixel by pixel (the reference, deliberately naive)."""
    n, channels, height, width = image.shape
    num, den = torch.zeros_like(image), torch.zeros(n, 1, height, width, dtype=image.dtype)
    radius = size // 2
    for b in range(n):
        for y in range(height):
            for x in range(width):
                for i in range(size):
                    for j in range(size):
                        v, u = y + (i - radius) * dilation, x + (j - radius) * dilation
                        if not (0 <= v < height and 0 <= u < width):
                            continue
                        if center is not None and (v, u) == (y, x):
                            w = center[b, 0, y, x]
                        else:
                            distance = ((features[b, :, y, x] - neighbours[b, :, v, u]) ** 2).sum()
                            w = torch.exp(-bandwidth[b, 0, y, x] * distance)
                        num[b, :, y, x] += w * image[b, :, v, u]
                        den[b, 0, y, x] += w
    return num, den


@pytest.mark.parametrize("size,dilation,with_center,separate", [(3, 1, True, False), (3, 2, True, False),
                                                                 (5, 1, False, True), (3, 4, False, True)])
def test_affinity_sums_match_a_direct_per_pixel_evaluation(size, dilation, with_center, separate) -> None:
    n, height, width = 2, 7, 9
    image = _random((n, 3, height, width), 1)
    features = _random((n, 2, height, width), 2) * 2
    neighbours = _random((n, 2, height, width), 3) * 2 if separate else features
    bandwidth = _random((n, 1, height, width), 4) * 3
    center = _random((n, 1, height, width), 5) if with_center else None
    expected = _direct_sums(image, features, neighbours, bandwidth, center, size, dilation)
    got = affinity.affinity_sums(image, features, bandwidth, center, size, dilation,
                                 neighbours=neighbours if separate else None, backend="torch")
    for a, b in zip(got, expected):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dilation", [1, 2, 4])
def test_dilated_kernel_reads_exactly_its_taps(dilation: int) -> None:
    """An impulse at the centre of a 21 x 21 image with bandwidth 0 (a box filter): a pixel's numerator is
    non-zero exactly where the impulse lies on one of its 3 x 3 dilated taps, and the denominator counts the
    taps inside the image."""
    size, side = 3, 21
    image = torch.zeros(1, 1, side, side)
    image[0, 0, 10, 10] = 1.0
    features = torch.zeros(1, 1, side, side)
    zero = torch.zeros(1, 1, side, side)
    num, den = affinity.affinity_sums(image, features, zero, torch.ones(1, 1, side, side), size, dilation,
                                      backend="torch")
    ys, xs = torch.nonzero(num[0, 0], as_tuple=True)
    reached = {(int(y) - 10, int(x) - 10) for y, x in zip(ys, xs)}
    assert reached == {(dy, dx) for dy, dx in affinity.tap_offsets(size, dilation)}
    inside = torch.arange(side)
    per_axis = sum(((inside + d * dilation >= 0) & (inside + d * dilation < side)).long() for d in (-1, 0, 1))
    assert torch.equal(den[0, 0], (per_axis[:, None] * per_axis[None, :]).float())


def test_analytic_backward_matches_numerical_gradients() -> None:
    """The tap-by-tap backward of _AffinitySums against torch.autograd.gradcheck (double precision), for a
    spatial kernel with a centre weight and a temporal-style kernel with separate neighbours."""
    n, height, width = 1, 5, 6
    double = torch.float64
    image = _random((n, 2, height, width), 1, double).requires_grad_()
    features = _random((n, 3, height, width), 2, double).requires_grad_()
    neighbours = _random((n, 3, height, width), 3, double).requires_grad_()
    bandwidth = (_random((n, 1, height, width), 4, double) * 2).requires_grad_()
    center = _random((n, 1, height, width), 5, double).requires_grad_()
    apply = affinity._AffinitySums.apply
    assert torch.autograd.gradcheck(lambda *t: apply(*t, 3, 2, "torch"),
                                    (image, features, features, bandwidth, center), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(lambda *t: apply(*t, None, 3, 1, "torch"),
                                    (image, features, neighbours, bandwidth), eps=1e-6, atol=1e-6)


def test_joint_normalisation_gives_weights_that_sum_to_one() -> None:
    """Eq. 8: spatial and temporal weights share one denominator, so a constant image and a constant history
    of the same value come out unchanged, and image 1 / history 0 gives the spatial share of the weight, which
    equals den_s / (den_s + den_t) of the two kernels' sums computed separately."""
    n, height, width = 1, 8, 8
    features, history_features = _random((n, 4, height, width), 1), _random((n, 4, height, width), 2)
    a, c, b = _random((n, 1, height, width), 3), _random((n, 1, height, width), 4), _random((n, 1, height, width), 5)
    ones = torch.ones(n, 3, height, width)
    same = affinity.joint_filter(2.5 * ones, features, a, c, 5, 2, 2.5 * ones, history_features, b, 3, backend="torch")
    assert torch.allclose(same, 2.5 * ones, atol=1e-5)
    share = affinity.joint_filter(ones, features, a, c, 5, 2, 0 * ones, history_features, b, 3, backend="torch")
    _, den_s = affinity.affinity_sums(ones, features, a, c, 5, 2, backend="torch")
    _, den_t = affinity.affinity_sums(ones, features, b, None, 3, 1, neighbours=history_features, backend="torch")
    assert torch.allclose(share, (den_s / (den_s + den_t)).expand_as(share), atol=1e-6)
    assert bool((share < 1).all()) and bool((share > 0).all())


# ------------------------------------------------------------------------------------ batches
BUFFERS = {"radiance": 3, "diffuse": 3, "specular": 3, "normal": 3, "depth": 1, "roughness": 1, "albedo": 3,
           "flags": 4}


class _Batch(dict):
    index = 0


def _batch(n: int = 2, length: int = 3, layers: int = 4, size: int = 16, seed: int = 0, index: int = 0) -> _Batch:
    """Synthetic sequences: a smooth reference, noisy samples around it (diffuse = radiance), static camera."""
    generator = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(0.2, 1.5, size)
    reference = (ramp.view(1, size) * ramp.view(size, 1)).expand(n, length, 3, size, size).clone()
    batch = _Batch()
    batch.index = index
    noise = torch.rand(n, length, layers, 3, size, size, generator=generator) * 2
    for name, channels in BUFFERS.items():
        batch[name] = torch.rand(n, length, layers, channels, size, size, generator=generator)
    batch["radiance"] = reference[:, :, None] * noise
    batch["diffuse"] = batch["radiance"].clone()
    batch["specular"] = torch.zeros_like(batch["radiance"])
    batch["reference.radiance"] = reference
    batch["motion"] = torch.zeros(n, length, 2, size, size)
    batch["valid"] = torch.ones(n, length, 1, size, size)
    batch["world_to_view"] = torch.eye(3).expand(n, length, 3, 3).clone()
    return batch


SMALL = dict(width=0.125, embed_features=8, kernel_size=5, temporal_kernel_size=3, affinity_dim=4)


# ------------------------------------------------------------------------------------ recursion and sizes
def test_accumulated_radiance_follows_the_direct_recursion() -> None:
    """Eq. 5 with zero motion (the nearest warp is then the identity): Lbar_0 = L_0 and
    Lbar_t = (1 - lambda_t) L_t + lambda_t Lbar_{t-1}, with lambda_t the blend map each step returns."""
    torch.manual_seed(0)
    model = AFNNet(AFNConfig(**SMALL)).eval()
    batch = _batch(n=1, length=4)
    history, expected = None, None
    with torch.no_grad():
        for t in range(4):
            samples = {b: batch[b][:, t] for b in BUFFERS}
            noisy = samples["radiance"].mean(1)
            step = frame_step(model, sample_features(samples, batch["world_to_view"][:, t]), noisy,
                              batch["motion"][:, t], batch["valid"][:, t], history, backend="torch")
            expected = noisy if t == 0 else (1 - step.blend) * noisy + step.blend * expected
            assert torch.allclose(step.history.radiance, expected, atol=1e-6)
            if t == 0:
                assert bool((step.blend == 0).all())
            else:
                assert 0 < float(step.blend.mean()) < 1
            history = step.history


def test_fixed_lambda_variant_uses_the_constant() -> None:
    model = AFNNet(AFNConfig(**SMALL, fixed_lambda=0.8)).eval()
    batch = _batch(n=1, length=2)
    history = None
    with torch.no_grad():
        for t in range(2):
            samples = {b: batch[b][:, t] for b in BUFFERS}
            step = frame_step(model, sample_features(samples, batch["world_to_view"][:, t]), samples["radiance"].mean(1),
                              batch["motion"][:, t], batch["valid"][:, t], history, backend="torch")
            history = step.history
    assert bool((step.blend == 0.8).all())


def test_kernel_size_changes_at_test_time_without_retraining() -> None:
    """The same weights run with other kernel sizes; a 1 x 1 kernel with K kernels returns the noisy mean
    (c / (eps + c) = 1 up to 1e-10 relative); larger kernels give other outputs, each a convex combination of
    the noisy pixels (non-negative weights normalised per pixel), so within their range per channel."""
    torch.manual_seed(0)
    model = AFNNet(AFNConfig(**{**SMALL, "kernel_size": 13}, temporal=False)).eval()
    batch = _batch(n=1, length=1)
    samples = {b: batch[b][:, 0] for b in BUFFERS}
    features = sample_features(samples, batch["world_to_view"][:, 0])
    noisy = samples["radiance"].mean(1)
    with torch.no_grad():
        outputs = {k: frame_step(model, features, noisy, None, None, None, kernel_size=k, backend="torch").output
                   for k in (1, 7, 13)}
    assert torch.allclose(outputs[1], noisy, rtol=1e-5)
    assert not torch.allclose(outputs[7], outputs[13])
    assert not torch.allclose(outputs[7], noisy)
    low, high = noisy.amin(dim=(2, 3), keepdim=True), noisy.amax(dim=(2, 3), keepdim=True)
    for output in outputs.values():
        assert bool((output >= low - 1e-5).all()) and bool((output <= high + 1e-5).all())


# ------------------------------------------------------------------------------------ losses and network
def test_smape_and_temporal_loss_on_hand_computed_cases() -> None:
    """Eq. 11 per element with eps 0.01: |1 - 3| / (1 + 3 + 0.01) = 2 / 4.01; the temporal term of Eq. 12 on
    frame differences: output constant (difference 0) against a reference that rises by 1: 1 / (0 + 1 + 0.01)."""
    a, b = torch.ones(1, 3, 2, 2), torch.full((1, 3, 2, 2), 3.0)
    assert math.isclose(float(smape(a, b)), 2 / 4.01, rel_tol=1e-6)
    outputs = [torch.ones(1, 3, 2, 2)] * 2
    targets = [torch.ones(1, 3, 2, 2), torch.full((1, 3, 2, 2), 2.0)]
    params = []
    total, terms = afn_loss(outputs, targets, params, temporal_weight=0.25, regularizer=1e-5)
    reconstruction = (0 + 1 / (1 + 2 + 0.01)) / 2
    assert math.isclose(terms["reconstruction"], reconstruction, rel_tol=1e-6)
    assert math.isclose(terms["temporal"], 1 / 1.01, rel_tol=1e-6)
    assert math.isclose(float(total), reconstruction + 0.25 / 1.01, rel_tol=1e-6)


def test_embedding_is_the_pointwise_network_averaged_over_samples() -> None:
    """Eq. 1 by the definition: the embedding layers applied as 1 x 1 convolutions to every sample's image, then
    the per-pixel mean over samples; 2 x 80 x 70 pixels cross the inference path's block boundaries."""
    torch.manual_seed(3)
    model = AFNNet(AFNConfig(width=0.25)).eval()
    samples = torch.randn(2, 3, 18, 80, 70)
    with torch.no_grad():
        direct = model.embedding(samples.reshape(6, 18, 80, 70)).view(2, 3, -1, 80, 70).mean(dim=1)
        embedded = model.embed(samples)
    assert embedded.shape == (2, 32, 80, 70)
    torch.testing.assert_close(embedded, direct, rtol=1e-5, atol=1e-6)
    with torch.enable_grad():            # training takes the convolution path: the same values
        torch.testing.assert_close(model.embed(samples), direct, rtol=1e-5, atol=1e-6)


def test_full_width_network_has_the_papers_size() -> None:
    """Sec. 1: "a lightweight neural network (~940k parameters)"; at width 1 (K = 3, d = 8) ours has 942 240,
    and its output convolution has the 32 channels of the paper's last 'c32'."""
    model = AFNNet(AFNConfig(width=1.0))
    assert abs(count_parameters(model) - 940_000) < 0.01 * 940_000
    assert model.unet.last[1].out_channels == 32


@pytest.mark.parametrize("net", [{}, {"temporal": False}, {"temporal": False, "kernels": 1, "dilate": False, "kernel_size": 9},
                                 {"temporal": False, "kernel_kind": "gather"}, {"history_input": "prediction"},
                                 {"temporal_kernel": False, "accumulate_radiance": False}])
def test_variants_train_a_few_steps_and_lower_the_loss(net: dict) -> None:
    torch.manual_seed(0)
    task = AFNTask(AFNConfig(**{**SMALL, **net}), spp_choices=(2,))
    model = task.build_model()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = _batch()
    first = float(task.loss(model, batch)[0].detach())
    # At initialisation the affinity features barely vary, so every weight is ~1 whatever a, and neither a nor
    # the features get much gradient: the loss sits on a plateau for 20-40 steps on this batch, then falls.
    for _ in range(60):
        optimizer.zero_grad()
        loss, _ = task.loss(model, batch)
        loss.backward()
        optimizer.step()
    assert float(task.loss(model, batch)[0].detach()) < 0.9 * first


def test_training_spp_round_robin_and_validation_at_every_layer() -> None:
    task = AFNTask(AFNConfig(**SMALL), spp_choices=(1, 2, 4))
    model = task.build_model()
    assert [task.samples_used(model, _batch(index=i)) for i in range(4)] == [1, 2, 4, 1]
    model.eval()
    assert task.samples_used(model, _batch(index=0, layers=4)) == 4


def test_trained_model_is_deterministic(tmp_path) -> None:
    from denoisers.training.loop import Trainer, TrainerConfig

    class Source:
        def batch(self, index: int, batch_size: int) -> _Batch:
            return _batch(n=batch_size, seed=index, index=index)

        def describe(self) -> dict:
            return {"synthetic": 1}

    weights = []
    for run in range(2):
        config = TrainerConfig(seed=5, batch_size=2, max_steps=3, lr=1e-3, validate_every=1000, checkpoint_every=1000,
                               log_every=1, progress=False, threads=1)
        trainer = Trainer(AFNTask(AFNConfig(**SMALL)), Source(), [], config, tmp_path / f"run{run}")
        trainer.run()
        weights.append({k: v.clone() for k, v in trainer.model.state_dict().items()})
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_task_settings_are_checked() -> None:
    def spec(net=None, loss=None, data=None) -> ModelSpec:
        return ModelSpec(id="x", method="afn", seed=0, net=net or {}, loss=loss or {},
                         data={"spp": 4, "backward_prob": 0.0, **(data or {})}, optimizer={}, budget={}, compute={})

    assert task_problems(spec()) == []
    assert any("bogus" in p for p in task_problems(spec(net={"bogus": 1})))
    assert any("spp_choices" in p for p in task_problems(spec(loss={"spp_choices": [8]})))
    assert any("backward_prob" in p for p in task_problems(spec(data={"backward_prob": 0.5})))
    assert any("gather" in p for p in task_problems(spec(net={"kernel_kind": "gather"})))
    from denoisers.nets.afn_task import SAMPLE_BUFFERS

    assert task_builder("afn").sample_buffers == SAMPLE_BUFFERS


# ------------------------------------------------------------------------------------ evaluation method
def test_method_matches_the_training_prediction() -> None:
    """The registry method streams frames through the same frame step as training's predict (identity camera:
    the data's world-to-view for an identity to_world is diag(-1, 1, -1))."""
    torch.manual_seed(0)
    task = AFNTask(AFNConfig(**SMALL))
    model = task.build_model().eval()
    batch = _batch(n=1, length=3)
    batch["world_to_view"] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])).expand(1, 3, 3, 3).clone()
    with torch.no_grad():
        expected = task.predict(model, batch)[0]
    denoiser = registry.get("afn").from_model(model)
    denoiser.reset()
    for t in range(3):
        frame = Frame(samples={b: batch[b][0, t] for b in BUFFERS},
                      pixel={"motion": batch["motion"][0, t], "valid": batch["valid"][0, t]}, index=t,
                      meta={"camera": {"to_world": torch.eye(4).tolist()}})
        assert torch.allclose(denoiser.denoise(frame), expected[t], atol=1e-5)


def test_method_reports_its_lambda_maps_and_the_evaluation_stores_them() -> None:
    """Denoiser.diagnostics of the temporal model: lambda (H, W) of the last frame, 0 at the first frame, the
    blend the frame step used; run_method (the evaluation's loop) stacks them per frame; single-frame: none."""
    from denoisers.jobs.denoise import run_method

    torch.manual_seed(0)
    model = AFNNet(AFNConfig(**SMALL)).eval()
    batch = _batch(n=1, length=3)
    frames = [Frame(samples={b: batch[b][0, t] for b in BUFFERS},
                    pixel={"motion": batch["motion"][0, t], "valid": batch["valid"][0, t]}, index=t,
                    meta={"camera": {"to_world": torch.eye(4).tolist()}}) for t in range(3)]
    result = run_method(registry.get("afn").from_model(model), frames, threads=1)
    assert set(result.maps) == {"lambda"} and result.maps["lambda"].shape == (3, 16, 16)
    assert (result.maps["lambda"][0] == 0).all() and 0 < result.maps["lambda"][1:].mean() < 1
    single = run_method(registry.get("afn").from_model(AFNNet(AFNConfig(**SMALL, temporal=False)).eval()), frames,
                        threads=1)
    assert single.maps == {}
