"""Adaptive sampling from stored layers (denoisers/adaptive.py, the adaptive method interface in
registry.py / denoise.py / scoring.py, denoisers/methods/adaptive_baselines.py)."""
from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from denoisers import adaptive, evaluate, registry
from denoisers.jobs import denoise, scoring
from denoisers.adaptive import BudgetError, budget_total, gather_mean, masked_samples, normalize_sample_map
from denoisers.evaluate import EvaluationError
from denoisers.registry import AdaptiveOutput, Denoiser, Frame
from scenegen.config import validate_config
from scenegen.channels import noisy_channels, pixel_channels, reference_channels
from scenegen.dataset import write_frame

REPO_ROOT = Path(__file__).resolve().parents[1]
HEIGHT, WIDTH, FRAMES, FULL, EXTRA = 12, 14, 3, 2, 6     # 2 full layers + 6 radiance-only layers


# ------------------------------------------------------------------------------------------------
# Eq. 2 normalisation and the budget
# ------------------------------------------------------------------------------------------------

def test_budget_total_floors_and_tolerates_decimal_budgets() -> None:
    assert budget_total(2, 10) == 20
    assert budget_total(0.1, 10) == 1            # 0.1 * 10 in floats is not below 1
    assert budget_total(1.37, 100) == 137
    assert budget_total(1.999, 3) == 5
    with pytest.raises(BudgetError):
        budget_total(-1, 4)


@pytest.mark.parametrize("rounding", adaptive.ROUNDING_SCHEMES)
@pytest.mark.parametrize("budget", [0.3, 1.0, 1.37, 2.5, 4.0, 7.9, 12.0])
@pytest.mark.parametrize("minimum", [0, 1])
def test_sample_map_never_exceeds_the_budget(rounding: str, budget: float, minimum: int) -> None:
    generator = torch.Generator().manual_seed(3)
    importance = torch.rand(13, 17, generator=generator) ** 4       # skewed, some near 0
    max_count = 8
    if minimum * importance.numel() > budget_total(budget, importance.numel()):
        with pytest.raises(BudgetError, match="below the minimum"):
            normalize_sample_map(importance, budget, max_count, minimum=minimum, rounding=rounding)
        return
    counts = normalize_sample_map(importance, budget, max_count, minimum=minimum, rounding=rounding, seed=5)
    assert counts.dtype == torch.int64 and counts.shape == importance.shape
    assert int(counts.min()) >= minimum and int(counts.max()) <= max_count
    total = budget_total(budget, counts.numel())
    assert int(counts.sum()) == min(total, max_count * counts.numel())     # spends all it may, never more
    assert counts.double().mean() <= budget + 1e-12


def test_sample_map_follows_eq2_and_clips_to_the_available_layers() -> None:
    # Proportional where nothing is clipped: importance 1:3 at budget 2 -> 1 and 3 samples exactly.
    counts = normalize_sample_map(torch.tensor([[1.0, 3.0]]), 2, 8)
    assert counts.tolist() == [[1, 3]]
    # A pixel asking for more than the stored layers is clipped; its excess goes to the others by importance.
    counts = normalize_sample_map(torch.tensor([[100.0, 1.0, 3.0, 0.0]]), 4, 8)
    assert counts.tolist() == [[8, 2, 6, 0]]
    # Zero importance everywhere: uniform. Minimum 1 (DASR's initial pass) is counted in the budget.
    assert normalize_sample_map(torch.zeros(2, 3), 3, 8).tolist() == [[3, 3, 3]] * 2
    counts = normalize_sample_map(torch.tensor([[0.0, 0.0, 1.0]]), 2, 8, minimum=1)
    assert counts.tolist() == [[1, 1, 4]]
    # Budget above the stored layers: every pixel gets them all, the mean stays below the budget.
    assert normalize_sample_map(torch.rand(3, 3), 9, 4).eq(4).all()


def test_largest_remainder_is_deterministic_and_breaks_ties_by_raster_order() -> None:
    counts = normalize_sample_map(torch.ones(2, 4), 1.5, 4)     # 8 px, 12 samples: 4 extra to the first 4
    assert counts.tolist() == [[2, 2, 2, 2], [1, 1, 1, 1]]
    importance = torch.rand(9, 11)
    assert torch.equal(normalize_sample_map(importance, 2.3, 8), normalize_sample_map(importance, 2.3, 8))


def test_round_of_the_paper_can_exceed_the_budget_ours_does_not() -> None:
    importance = torch.ones(1, 4)
    real = 4 * importance / importance.sum() * 1.5         # 1.5 per pixel
    assert torch.round(real + 1e-6).sum() > budget_total(1.5, 4)    # round half up: 8 > 6
    assert int(normalize_sample_map(importance, 1.5, 8).sum()) == 6


def test_stochastic_rounding_is_seeded_and_unbiased() -> None:
    importance = torch.tensor([[1.0, 2.0, 3.0, 4.0, 0.5, 1.5]])
    first = normalize_sample_map(importance, 1.7, 8, rounding="stochastic", seed=11)
    assert torch.equal(first, normalize_sample_map(importance, 1.7, 8, rounding="stochastic", seed=11))
    maps = torch.stack([normalize_sample_map(importance, 1.7, 8, rounding="stochastic", seed=s) for s in range(400)])
    assert len({tuple(m.flatten().tolist()) for m in maps}) > 1, "the seed changes nothing"
    assert (maps.sum(dim=(1, 2)) == budget_total(1.7, 6)).all()
    expected = importance / importance.sum() * budget_total(1.7, 6)
    np.testing.assert_allclose(maps.double().mean(0), expected.double(), atol=0.08)


def test_density_is_eq2_before_rounding_and_differentiable() -> None:
    logits = torch.randn(2, 5, 6, requires_grad=True)
    values = adaptive.density(logits, 3.0)
    flat = logits.detach().reshape(2, -1)
    expected = 30 * torch.exp(flat) / torch.exp(flat).sum(-1, keepdim=True) * 3.0
    torch.testing.assert_close(values.detach().reshape(2, -1), expected)
    torch.testing.assert_close(values.detach().mean(dim=(1, 2)), torch.tensor([3.0, 3.0]))
    (values[0, 0, 0]).backward()
    assert logits.grad is not None and torch.isfinite(logits.grad).all()


def test_invalid_importance_and_options_are_rejected() -> None:
    with pytest.raises(BudgetError, match="finite and >= 0"):
        normalize_sample_map(torch.tensor([[1.0, -1.0]]), 1, 4)
    with pytest.raises(BudgetError, match="rounding"):
        normalize_sample_map(torch.ones(2, 2), 1, 4, rounding="round")
    with pytest.raises(BudgetError, match=r"\(H, W\)"):
        normalize_sample_map(torch.ones(1, 2, 2), 1, 4)


# ------------------------------------------------------------------------------------------------
# Gathering the first k layers
# ------------------------------------------------------------------------------------------------

def test_gather_equals_a_direct_mean_of_the_chosen_layers() -> None:
    generator = torch.Generator().manual_seed(0)
    layers = torch.rand(6, 3, 5, 7, generator=generator)
    counts = torch.randint(0, 7, (5, 7), generator=generator)
    mean = gather_mean(layers, counts)
    for y in range(5):
        for x in range(7):
            k = int(counts[y, x])
            expected = layers[:k, :, y, x].mean(0) if k else torch.zeros(3)
            torch.testing.assert_close(mean[:, y, x], expected, rtol=1e-6, atol=1e-7)
    kept, mask = masked_samples(layers, counts)
    assert mask.shape == (6, 1, 5, 7) and torch.equal(mask[:, 0].sum(0), counts)
    torch.testing.assert_close(kept.sum(0), mean * counts.clamp(min=1))


def test_layers_beyond_k_never_leak_and_bad_counts_are_rejected() -> None:
    layers = torch.ones(4, 1, 2, 2)
    layers[2:] = float("nan")
    counts = torch.tensor([[1, 2], [2, 1]])
    assert torch.equal(gather_mean(layers, counts), torch.ones(1, 2, 2))
    with pytest.raises(BudgetError, match="0..4"):
        gather_mean(layers, torch.tensor([[5, 1], [1, 1]]))
    with pytest.raises(BudgetError, match="integer"):
        gather_mean(layers, torch.ones(2, 2))


def test_budget_problems_name_the_frame() -> None:
    maps = [np.full((2, 2), 2), np.array([[2, 2], [2, 3]])]
    assert adaptive.budget_problems(maps, 2, [10, 11], "row 'x'") == [
        "row 'x': frame 11 uses 9 samples for 4 pixels (mean 2.25 spp), above the budget of 2 spp (8 samples)"]
    assert adaptive.budget_problems(maps, 2.25, [10, 11]) == []


# ------------------------------------------------------------------------------------------------
# Baseline methods, called directly
# ------------------------------------------------------------------------------------------------

def _frame(layers: torch.Tensor, budget: float, index: int = 0) -> Frame:
    return Frame(samples={"radiance": layers}, index=index, budget=budget)


def test_uniform_adaptive_equals_the_non_adaptive_mean() -> None:
    layers = torch.rand(8, 3, 6, 5)
    method = registry.build("uniform_adaptive")
    assert method.info.adaptive and not registry.get("noisy").info.adaptive
    result = method.denoise(_frame(layers, 3))
    assert isinstance(result, AdaptiveOutput) and result.sample_map.eq(3).all()
    noisy = registry.build("noisy").denoise(Frame(samples={"radiance": layers[:3]}))
    torch.testing.assert_close(result.radiance, noisy)


def test_variance_adaptive_spends_the_budget_where_the_noise_is() -> None:
    generator = torch.Generator().manual_seed(1)
    layers = torch.full((16, 3, 8, 8), 0.5)
    layers[:, :, :, 4:] = torch.rand(16, 3, 8, 4, generator=generator) * 2     # right half noisy
    method = registry.build("variance_adaptive", {"pilot": 2})
    result = method.denoise(_frame(layers, 4, index=3))
    counts = result.sample_map
    assert int(counts.sum()) <= budget_total(4, 64) and int(counts.min()) >= 2 and int(counts.max()) <= 16
    assert counts[:, 4:].double().mean() > 2 * counts[:, :2].double().mean()
    torch.testing.assert_close(result.radiance, gather_mean(layers, counts))
    again = registry.build("variance_adaptive", {"pilot": 2}).denoise(_frame(layers, 4, index=3))
    assert torch.equal(again.sample_map, counts)                   # reproducible for seed and frame
    # Budget 1: no pilot variance possible, uniform 1 spp.
    assert method.denoise(_frame(layers, 1)).sample_map.eq(1).all()


# ------------------------------------------------------------------------------------------------
# Through the evaluation: jobs.denoise and jobs.scoring on a tiny synthetic clip with radiance-only layers
# ------------------------------------------------------------------------------------------------

def _write_clip(render_dir: Path, seed: int = 0) -> np.ndarray:
    """Static clip: FULL full layers + EXTRA radiance-only layers; the right half is noisier. -> reference."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    reference = np.stack([0.3 + 0.5 * x / WIDTH, 0.4 + 0.0 * y, 0.5 + 0.2 * y / HEIGHT]).astype(np.float32)
    spread = np.where(x >= WIDTH // 2, 1.0, 0.1).astype(np.float32)
    ones = np.ones((1, HEIGHT, WIDTH), np.float32)
    for kind in ("noisy", "reference"):
        (render_dir / kind / "chunk_000").mkdir(parents=True, exist_ok=True)
    for t in range(FRAMES):
        noise = rng.uniform(-1.0, 1.0, (FULL + EXTRA, 1, HEIGHT, WIDTH)).astype(np.float32)
        radiance = reference[None] * (1.0 + spread * noise)
        samples = {"radiance": radiance, "albedo": np.full((FULL, 3, HEIGHT, WIDTH), 0.5, np.float32)}
        channels, half = noisy_channels(samples)
        gbuffer = {"position": np.concatenate([ones] * 3), "normal": np.concatenate([0 * ones, 0 * ones, ones]),
                   "depth": ones, "object": ones, "albedo": np.concatenate([0.5 * ones] * 3), "roughness": ones}
        pixel, pixel_half = pixel_channels(np.zeros((2, HEIGHT, WIDTH), np.float32),
                                           np.full((1, HEIGHT, WIDTH), t > 0), gbuffer)
        channels.update(pixel)
        meta = {"scene": "test_000", "frame": t, "width": WIDTH, "height": HEIGHT, "spp": FULL,
                "extra_radiance_spp": EXTRA, "camera_cut": False, "nonfinite_total": 0}
        write_frame(render_dir / "noisy" / "chunk_000" / f"frame_{t:04d}.exr", channels, meta,
                    half=half | pixel_half)
        ref = {"radiance": reference, "radiance_half0": reference, "radiance_half1": reference,
               "diffuse": reference, "specular": np.zeros_like(reference), "albedo": np.full_like(reference, 0.5),
               "normal": np.zeros_like(reference), "depth": ones}
        write_frame(render_dir / "reference" / "chunk_000" / f"frame_{t:04d}.exr", reference_channels(ref),
                    {"scene": "test_000", "frame": t, "spp": 64, "psnr_halves": 40.0, "camera_cut": False}, half=set())
    return reference


ROWS = [{"id": "noisy", "method": "noisy"}, {"id": "uniform", "method": "uniform_adaptive"},
        {"id": "variance", "method": "variance_adaptive", "params": {"pilot": 2}}]


def _config(rows: list[dict] = ROWS) -> dict:
    cfg = yaml.safe_load((REPO_ROOT / "config" / "smoke.yaml").read_text())
    cfg["render"].update(spp=FULL, extra_radiance_spp=EXTRA)
    cfg["evaluation"].update(methods=rows, spp=[1, 2, 4], warmup_frames=1)
    return validate_config(cfg)


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    render_dir = tmp_path_factory.mktemp("renders") / "test_000"
    _write_clip(render_dir)
    return render_dir


class AuxAdaptive(Denoiser):
    """Test only: records the layers it is given, spends exactly the budget uniformly."""

    seen: list[dict[str, int]] = []

    def denoise(self, frame: Frame) -> AdaptiveOutput:
        AuxAdaptive.seen.append({b: int(v.shape[0]) for b, v in frame.samples.items()} | {"budget": frame.budget})
        counts = normalize_sample_map(torch.ones(frame.height, frame.width), frame.budget,
                                      frame.samples["radiance"].shape[0])
        return AdaptiveOutput(gather_mean(frame.samples["radiance"], counts), counts)


class Overspending(Denoiser):
    """Test only: one sample above the budget on frame 1."""

    def denoise(self, frame: Frame) -> AdaptiveOutput:
        counts = torch.full((frame.height, frame.width), int(frame.budget), dtype=torch.int64)
        if frame.index == 1:
            counts[0, 0] += 1
        return AdaptiveOutput(gather_mean(frame.samples["radiance"], counts), counts)


@pytest.fixture
def test_methods() -> Iterator[None]:
    registry.register("test_aux_adaptive", inputs=("radiance", "albedo"), adaptive=True)(AuxAdaptive)
    registry.register("test_overspending", inputs=("radiance",), adaptive=True)(Overspending)
    yield
    for name in ("test_aux_adaptive", "test_overspending"):
        registry._REGISTRY.pop(name, None)


def test_adaptive_rows_through_denoise_and_scoring(clip_dir: Path, tmp_path: Path) -> None:
    cfg = _config()
    from scenegen.dataset import load_clip

    clip = load_clip(clip_dir, buffers=("radiance",), reference=False)
    assert clip.samples["radiance"].shape[1] == FULL + EXTRA
    out = tmp_path / "uniform"
    record = denoise.denoise_clip(cfg, "uniform", "test_000", 4, clip_dir, out)
    # Uniform at budget 4 = the mean of the first 4 layers, two of them radiance-only layers.
    for t in range(FRAMES):
        image = evaluate.read_radiance_exr(out / f"frame_{t:04d}.exr")
        np.testing.assert_allclose(image, clip.samples["radiance"][t, :4].mean(0), rtol=1e-6)
    timing = json.loads((out / "timing.json").read_text())
    assert timing == record and timing["adaptive"] is True and timing["budget_spp"] == 4.0
    assert timing["realised_spp_per_frame"] == [4.0] * FRAMES and timing["realised_spp"] == 4.0
    assert timing["available_layers"] == {"radiance": FULL + EXTRA}
    with np.load(out / adaptive.SAMPLE_MAPS_FILE) as data:
        assert data["frames"].tolist() == list(range(FRAMES)) and data["sample_maps"].shape == (FRAMES, HEIGHT, WIDTH)
    table = scoring.evaluate_clip(cfg, out, clip_dir, tmp_path / "uniform.csv")
    assert table["realised_spp"].tolist() == [4.0] * FRAMES and table["budget_spp"].tolist() == [4.0] * FRAMES

    out = tmp_path / "variance"
    record = denoise.denoise_clip(cfg, "variance", "test_000", 4, clip_dir, out)
    assert all(2.0 < spp <= 4.0 for spp in record["realised_spp_per_frame"])     # pilot 2, then by variance
    with np.load(out / adaptive.SAMPLE_MAPS_FILE) as data:
        maps = data["sample_maps"].astype(np.int64)
    assert maps[:, :, WIDTH // 2:].mean() > maps[:, :, :WIDTH // 2].mean()      # the noisy half gets more
    table = scoring.evaluate_clip(cfg, out, clip_dir, tmp_path / "variance.csv")
    np.testing.assert_allclose(table["realised_spp"], maps.mean(axis=(1, 2)))
    # Non-adaptive rows keep their columns.
    denoise.denoise_clip(cfg, "noisy", "test_000", 2, clip_dir, tmp_path / "noisy")
    assert "realised_spp" not in scoring.evaluate_clip(cfg, tmp_path / "noisy", clip_dir, tmp_path / "n.csv").columns

    # A sample map edited after the fact is caught by scoring, naming the row and frame.
    maps[2, 0, 0] += 3
    np.savez_compressed(out / adaptive.SAMPLE_MAPS_FILE, frames=np.arange(FRAMES), sample_maps=maps.astype(np.uint8))
    with pytest.raises(EvaluationError, match=r"row 'variance', scene test_000: frame 2 uses"):
        scoring.evaluate_clip(cfg, out, clip_dir, tmp_path / "bad.csv")


def test_adaptive_frames_carry_all_layers_aux_from_the_full_layers_only(clip_dir: Path, tmp_path: Path,
                                                                         test_methods: None) -> None:
    rows = ROWS + [{"id": "aux", "method": "test_aux_adaptive"}, {"id": "greedy", "method": "test_overspending"}]
    cfg = _config(rows)
    runs = {(run.spec.id, run.spp): run for run in evaluate.plan_runs(cfg)}
    assert runs[("aux", 4)].runnable, runs[("aux", 4)].not_run       # albedo: 2 layers suffice for an adaptive row
    AuxAdaptive.seen.clear()
    record = denoise.denoise_clip(cfg, "aux", "test_000", 4, clip_dir, tmp_path / "aux")
    assert AuxAdaptive.seen[0] == {"radiance": FULL + EXTRA, "albedo": FULL, "budget": 4.0}
    assert record["realised_spp"] == 4.0
    with pytest.raises(EvaluationError, match=r"row 'greedy', scene test_000: frame 1 uses 169 samples for 168 pixels"):
        denoise.denoise_clip(cfg, "greedy", "test_000", 1, clip_dir, tmp_path / "greedy")
    assert not (tmp_path / "greedy").exists()


def test_a_non_adaptive_output_of_an_adaptive_method_names_method_and_frame(test_methods: None) -> None:
    class Plain(Denoiser):
        def denoise(self, frame: Frame) -> torch.Tensor:
            return frame.samples["radiance"].mean(0)

    registry.register("test_plain_adaptive", inputs=("radiance",), adaptive=True)(Plain)
    try:
        frame = _frame(torch.rand(4, 3, 4, 4), 2)
        with pytest.raises(EvaluationError, match="'test_plain_adaptive', frame 0: denoise\\(\\) returned Tensor"):
            denoise.run_method(Plain(), [frame], threads=1)
    finally:
        registry._REGISTRY.pop("test_plain_adaptive", None)
    assert math.isclose(adaptive.realised_spp(torch.tensor([[1, 2], [3, 4]])), 2.5)


def test_the_renderer_gradient_teaches_a_free_logit_map_where_to_sample() -> None:
    """End to end through density (Eq. 2), the integer maps and the renderer gradient: a free per-pixel logit map
    trained by Adam on the L1 error of the gathered means moves samples to where the layers are noisy (left
    half sigma 1, right half sigma 0.02, budget 4 spp). The expected error of a k-sample mean falls like
    sigma / sqrt(k), so the optimum gives the noisy half nearly all samples."""
    torch.manual_seed(0)
    height = width = 16
    budget, layers_n = 4.0, 32
    mu = torch.full((1, 3, height, width), 0.5)
    sigma = torch.full((1, 1, height, width), 0.02)
    sigma[..., : width // 2] = 1.0
    logits = torch.zeros(1, height, width, requires_grad=True)
    optimizer = torch.optim.Adam([logits], lr=0.05)
    for _ in range(60):
        layers = (mu[:, None] + sigma[:, None] * torch.randn(1, layers_n, 3, height, width)).clamp_min(0)
        means, counts = adaptive.render_adaptive(adaptive.density(logits, budget), layers, budget)
        loss = (means - mu).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    noisy, clean = counts[0, :, : width // 2].float().mean(), counts[0, :, width // 2:].float().mean()
    assert counts.sum() <= adaptive.budget_total(budget, height * width)
    assert noisy > 6.0 and clean < 2.0, (noisy, clean)


def test_capped_density_spends_the_budget_within_the_cap_and_keeps_gradients_alive() -> None:
    """Eq. 2 with the renderer's cap: the real counts sum to the integer budget, never exceed the stored layers,
    equal plain Eq. 2 when no pixel reaches the cap, and a pixel whose logit outgrows the rest is held at the cap
    (no gradient) while the others share the rest of the budget and keep their gradients."""
    torch.manual_seed(1)
    logits = torch.randn(2, 6, 5)
    plain = adaptive.density(logits, 4.0)
    capped = adaptive.capped_density(logits, 4.0, 32)
    torch.testing.assert_close(capped, plain.to(capped.dtype), rtol=1e-5, atol=1e-5)    # 4 x 30 = 120, nothing capped
    degenerate = torch.zeros(1, 6, 5)
    degenerate[0, 2, 3] = 1000.0
    degenerate.requires_grad_(True)
    counts = adaptive.capped_density(degenerate, 4.0, 32, minimum=1)
    values = counts.detach()
    assert float(values.sum()) == pytest.approx(adaptive.budget_total(4.0, 30))
    assert float(values[0, 2, 3]) == 32 and float(values.max()) <= 32
    others = torch.ones(30, dtype=torch.bool)
    others[2 * 5 + 3] = False
    torch.testing.assert_close(counts.flatten()[others], torch.full((29,), (120 - 32) / 29))
    weights = torch.arange(30, dtype=torch.float32).reshape(1, 6, 5)
    (counts * weights).sum().backward()
    assert float(degenerate.grad[0, 2, 3]) == 0.0 and float(degenerate.grad.abs().sum()) > 0
    # Plain Eq. 2 gives every other pixel ~0 density there: no gradient reaches them.
    plain_degenerate = degenerate.detach().clone().requires_grad_(True)
    (adaptive.density(plain_degenerate, 4.0) * weights).sum().backward()
    assert float(plain_degenerate.grad.abs().sum()) == 0.0


def test_a_sampler_stuck_on_one_pixel_recovers_with_the_capped_density() -> None:
    """The failure of the 2026-12-01 default run: one logit far above the rest (the NTASD sampler's reached
    +-1000s). With plain Eq. 2 the other pixels get no gradient and the map stays flat; with the capped density
    the same start learns to sample the noisy half (left sigma 1, right sigma 0.02)."""
    height = width = 16
    budget, layers_n = 4.0, 32
    mu = torch.full((1, 3, height, width), 0.5)
    sigma = torch.full((1, 1, height, width), 0.02)
    sigma[..., : width // 2] = 1.0
    results = {}
    for name in ("plain", "capped"):
        torch.manual_seed(0)
        logits = torch.zeros(1, height, width)
        logits[0, 15, 0] = 1000.0
        logits.requires_grad_(True)
        optimizer = torch.optim.Adam([logits], lr=0.05)
        for _ in range(60):
            layers = (mu[:, None] + sigma[:, None] * torch.randn(1, layers_n, 3, height, width)).clamp_min(0)
            d = adaptive.density(logits, budget) if name == "plain" else adaptive.capped_density(logits, budget, layers_n)
            means, counts = adaptive.render_adaptive(d, layers, budget)
            loss = (means - mu).abs().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        results[name] = (counts[0, :, : width // 2].float().mean(), counts[0, :, width // 2:].float().mean())
    assert abs(results["plain"][0] - results["plain"][1]) < 1.0, results          # stuck: flat
    assert results["capped"][0] > 6.0 and results["capped"][1] < 2.0, results
