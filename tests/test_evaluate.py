"""Tests for the evaluation planning and jobs (denoisers/evaluate.py, jobs/denoise.py, jobs/scoring.py,
jobs/robustness.py): rows and runs, denoise, per-frame metrics, robustness.

Every test runs on a tiny synthetic clip written in the on-disk data format (no rendering): a static
smooth image with multiplicative noise per sample layer and constant auxiliary buffers.
"""
from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from denoisers import evaluate, metrics, registry
from denoisers.jobs import denoise, robustness, scoring
from denoisers.registry import Denoiser, Frame, MissingInputError
from scenegen.config import validate_config
from scenegen.channels import noisy_channels, pixel_channels, reference_channels
from scenegen.dataset import write_frame
from scenegen.exr import read_exr

REPO_ROOT = Path(__file__).resolve().parents[1]
HEIGHT, WIDTH, FRAMES, LAYERS = 12, 16, 4, 4


def synthetic_reference(height: int = HEIGHT, width: int = WIDTH) -> np.ndarray:
    """(3, H, W) smooth positive radiance: a diagonal ramp with a brighter disc."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    ramp = 0.2 + 0.6 * (x + y) / (height + width)
    disc = ((x - width / 2) ** 2 + (y - height / 2) ** 2 < (min(height, width) / 4) ** 2) * 1.5
    return np.stack([ramp + disc, 0.8 * ramp + disc, 0.6 * ramp + disc]).astype(np.float32)


def write_synthetic_scene(render_dir: Path, *, scene: str = "test_000", frames: int = FRAMES, layers: int = LAYERS,
                          height: int = HEIGHT, width: int = WIDTH, omit: tuple[str, ...] = (),
                          reference_size: tuple[int, int] | None = None, seed: int = 0,
                          camera_cut: int | None = None) -> np.ndarray:
    """Write noisy and reference frames of a static clip under ``render_dir`` (= results/renders/{scene});
    returns the (3, H, W) reference. ``omit`` leaves per-sample buffers out of the noisy files."""
    rng = np.random.default_rng(seed)
    reference = synthetic_reference(height, width)
    noisy_dir, reference_dir = render_dir / "noisy" / "chunk_000", render_dir / "reference" / "chunk_000"
    noisy_dir.mkdir(parents=True, exist_ok=True)
    reference_dir.mkdir(parents=True, exist_ok=True)
    ones = np.ones((1, height, width), np.float32)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    position = np.stack([x, y, np.zeros_like(x)])
    normal = np.concatenate([0 * ones, 0 * ones, ones])
    for t in range(frames):
        radiance = reference[None] * rng.uniform(0.0, 2.0, (layers, 1, height, width)).astype(np.float32)
        samples = {
            "radiance": radiance, "diffuse": radiance, "specular": np.zeros_like(radiance),
            "albedo": np.full((layers, 3, height, width), 0.5, np.float32),
            "normal": np.repeat(normal[None], layers, 0), "depth": np.repeat(ones[None], layers, 0),
            "roughness": np.repeat(ones[None], layers, 0), "flags": np.zeros((layers, 4, height, width), np.float32),
            "position": np.repeat(position[None], layers, 0),
        }
        samples = {b: a for b, a in samples.items() if b not in omit}
        channels, half = noisy_channels(samples)
        gbuffer = {"position": position, "normal": normal, "depth": ones, "object": ones,
                   "albedo": np.concatenate([0.5 * ones] * 3), "roughness": ones}
        pixel, pixel_half = pixel_channels(np.zeros((2, height, width), np.float32),
                                           np.full((1, height, width), t > 0), gbuffer)
        channels.update(pixel)
        cut = camera_cut is not None and t == camera_cut
        meta = {"scene": scene, "frame": t, "width": width, "height": height, "spp": layers, "extra_radiance_spp": 0,
                "camera_cut": cut, "nonfinite_total": 0}
        write_frame(noisy_dir / f"frame_{t:04d}.exr", channels, meta, half=half | pixel_half)
        ref_h, ref_w = reference_size or (height, width)
        ref = synthetic_reference(ref_h, ref_w)
        ref_buffers = {"radiance": ref, "radiance_half0": ref, "radiance_half1": ref, "diffuse": ref,
                       "specular": np.zeros_like(ref), "albedo": np.full_like(ref, 0.5),
                       "normal": np.zeros_like(ref), "depth": np.ones((1, ref_h, ref_w), np.float32)}
        write_frame(reference_dir / f"frame_{t:04d}.exr", reference_channels(ref_buffers),
                    {"scene": scene, "frame": t, "spp": 64, "psnr_halves": 40.0 + t, "camera_cut": cut,
                     "samples_per_s": 2.0e6}, half=set())
    return reference


def smoke_config(**evaluation) -> dict:
    """The smoke config with the given evaluation keys replaced, validated (defaults filled)."""
    cfg = yaml.safe_load((REPO_ROOT / "config" / "smoke.yaml").read_text())
    cfg["render"]["spp"] = LAYERS
    cfg["evaluation"].update(evaluation)
    return validate_config(cfg)


BASIC_METHODS = [{"id": "noisy", "method": "noisy"}, {"id": "path_x2", "method": "path_tracing", "params": {"factor": 2}}]


class Box3(Denoiser):
    """Sanitises non-finite samples to 0, then averages the 3x3 neighbourhood of the sample mean."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        mean = torch.nan_to_num(frame.samples["radiance"], nan=0.0, posinf=0.0, neginf=0.0).mean(0)
        return torch.nn.functional.avg_pool2d(mean[None], 3, stride=1, padding=1, count_include_pad=False)[0]


@pytest.fixture
def box_method() -> Iterator[str]:
    """Registers Box3 as 'test_box3' (reads radiance and albedo) for one test only, so that tests of
    other modules that iterate over the registry never see it."""
    registry.register("test_box3", inputs=("radiance", "albedo"), description="test only: 3x3 box filter")(Box3)
    yield "test_box3"
    registry._REGISTRY.pop("test_box3", None)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    render_dir = tmp_path_factory.mktemp("renders") / "test_000"
    write_synthetic_scene(render_dir)
    return render_dir


def test_plan_marks_runs_that_need_more_layers_than_rendered() -> None:
    cfg = smoke_config(methods=BASIC_METHODS, spp=[1, 2, 4, 8])
    radiance_layers = LAYERS + cfg["render"]["extra_radiance_spp"]
    assert radiance_layers == 8  # 4 full layers + the smoke config's 4 radiance-only layers
    runs = {(run.spec.id, run.spp): run for run in evaluate.plan_runs(cfg)}
    assert all(runs[("noisy", s)].runnable for s in (1, 2, 4, 8))
    assert runs[("path_x2", 4)].runnable and runs[("path_x2", 4)].layers == 8
    assert runs[("path_x2", 8)].not_run == ("not run (needs 16 layers of 'radiance', 8 rendered; raise "
                                            "render.spp or render.extra_radiance_spp)")


def test_evaluation_problems_name_the_keys() -> None:
    cfg = smoke_config(methods=BASIC_METHODS + [{"id": "noisy", "method": "noisy"}], spp=[1, 16])
    cfg["evaluation"]["robustness"]["spp"] = 3
    problems = "\n".join(evaluate.evaluation_problems(cfg))
    assert "'evaluation.spp'" in problems and "[16]" in problems
    assert "id 'noisy' more than once" in problems
    assert "'evaluation.robustness.spp' = 3" in problems


def test_test_scenes_exclude_training_scenes() -> None:
    cfg = smoke_config()
    cfg["scenes"]["n_train"], cfg["scenes"]["n_test"] = 3, 2
    cfg["extra_scenes"] = [{"name": "spheres_room", "xml": "examples/scenes/spheres_room/scene.xml", "frames": 4,
                            "camera": {"path": "dolly"}}]
    # The test scenes, then the external (custom_*) scenes; never a training scene.
    assert evaluate.evaluated_scene_ids(cfg) == ["test_000", "test_001", "custom_spheres_room"]
    cfg["extra_scenes"] = []
    assert evaluate.evaluated_scene_ids(cfg) == ["test_000", "test_001"]


def test_denoise_writes_exr_png_and_timing(scene_dir: Path, tmp_path: Path) -> None:
    cfg = smoke_config(methods=BASIC_METHODS)
    out = tmp_path / "denoised" / "path_x2" / "test_000" / "spp2"
    record = denoise.denoise_clip(cfg, "path_x2", "test_000", 2, scene_dir, out, threads=1)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"frame_{t:04d}.{ext}" for t in range(FRAMES) for ext in ("exr", "png")]
                           + ["timing.json"])
    assert not list(out.parent.glob(".*tmp*")), "staging directory left behind"
    # The path-tracing row averages factor x spp = 4 layers: compare with the mean of the stored layers.
    from scenegen.dataset import load_clip

    clip = load_clip(scene_dir, buffers=("radiance",), spp=4, reference=False)
    planes, _ = read_exr(out / "frame_0002.exr")
    image = np.stack([planes[f"radiance.{c}"] for c in "RGB"])
    np.testing.assert_allclose(image, clip.samples["radiance"][2].mean(0), rtol=1e-6)
    from PIL import Image

    png = np.asarray(Image.open(out / "frame_0002.png"))
    assert png.shape == (HEIGHT, WIDTH, 3) and png.dtype == np.uint8
    expected = np.clip(np.asarray(metrics.tonemap(image)), 0, 1).transpose(1, 2, 0) * 255
    assert np.abs(png.astype(float) - expected).max() <= 1.0

    timing = json.loads((out / "timing.json").read_text())
    assert timing == record
    assert timing["samples_factor"] == 2 and timing["sample_layers"] == 4 and timing["threads"] == 1
    assert len(timing["seconds_per_frame"]) == FRAMES and timing["warmup_frames_excluded"] == 1
    assert timing["mean_seconds"] == pytest.approx(np.mean(timing["seconds_per_frame"][1:]))
    assert timing["mpix_per_s"] == pytest.approx(HEIGHT * WIDTH / timing["mean_seconds"] / 1e6)
    assert timing["peak_memory_mb"] >= 0 and timing["nonfinite_inputs"] == timing["nonfinite_outputs"] == 0
    assert timing["render_samples_per_s"] == pytest.approx(2.0e6)


def test_evaluate_writes_per_frame_metrics(scene_dir: Path, tmp_path: Path) -> None:
    cfg = smoke_config(methods=BASIC_METHODS, warmup_frames=2)
    denoised = tmp_path / "denoised"
    denoise.denoise_clip(cfg, "noisy", "test_000", 4, scene_dir, denoised)
    table = scoring.evaluate_clip(cfg, denoised, scene_dir, tmp_path / "m.csv")
    on_disk = pd.read_csv(tmp_path / "m.csv")
    assert list(on_disk.columns) == ["frame", *evaluate.ALL_METRICS, "camera_cut", "nonfinite_output",
                                     "reference_psnr_halves"]
    assert len(on_disk) == FRAMES and on_disk["frame"].tolist() == list(range(FRAMES))
    pred = np.stack([evaluate.read_radiance_exr(denoised / f"frame_{t:04d}.exr") for t in range(FRAMES)])
    reference = synthetic_reference()
    for t in range(FRAMES):
        assert on_disk.loc[t, "psnr"] == pytest.approx(metrics.psnr(pred[t], reference), rel=1e-9)
        assert on_disk.loc[t, "ssim"] == pytest.approx(metrics.ssim(pred[t], reference), rel=1e-9)
    expected_tpsnr = metrics.temporal_metrics(pred, np.stack([reference] * FRAMES), 2)["tpsnr"]
    np.testing.assert_allclose(on_disk["tpsnr"], expected_tpsnr, equal_nan=True)
    assert on_disk["tpsnr"].isna().tolist() == [True, True, False, False]
    assert on_disk["reference_psnr_halves"].tolist() == [40.0, 41.0, 42.0, 43.0]
    pd.testing.assert_frame_equal(table.reset_index(drop=True), on_disk, check_dtype=False)


def test_temporal_metrics_restart_after_a_camera_cut(tmp_path: Path) -> None:
    render_dir = tmp_path / "test_000"
    write_synthetic_scene(render_dir, frames=5, camera_cut=3)
    cfg = smoke_config(methods=BASIC_METHODS, warmup_frames=1)
    denoise.denoise_clip(cfg, "noisy", "test_000", 1, render_dir, tmp_path / "d")
    table = scoring.evaluate_clip(cfg, tmp_path / "d", render_dir, tmp_path / "m.csv")
    # Frame 3 follows the cut: its "temporal difference" spans two shots and is not scored.
    assert table["tpsnr"].isna().tolist() == [True, False, False, True, False]
    assert table["camera_cut"].tolist() == [False, False, False, True, False]


def test_missing_buffer_names_buffer_and_method(tmp_path: Path, box_method: str) -> None:
    render_dir = tmp_path / "test_000"
    write_synthetic_scene(render_dir, omit=("albedo",))
    cfg = smoke_config(methods=[{"id": "box", "method": "test_box3"}])
    with pytest.raises(MissingInputError) as excinfo:
        denoise.denoise_clip(cfg, "box", "test_000", 1, render_dir, tmp_path / "out")
    assert excinfo.value.buffer == "albedo"
    assert "'albedo'" in str(excinfo.value) and "box (test_box3)" in str(excinfo.value)
    assert not (tmp_path / "out").exists()


def test_too_few_layers_is_a_missing_input_error(scene_dir: Path, tmp_path: Path) -> None:
    cfg = smoke_config(methods=BASIC_METHODS)
    with pytest.raises(MissingInputError, match=r"path_x2 \(path_tracing\).*'radiance'.*8 sample layers needed"):
        denoise.denoise_clip(cfg, "path_x2", "test_000", 4, scene_dir, tmp_path / "out")


def test_resolution_mismatch_names_both_files(tmp_path: Path) -> None:
    render_dir = tmp_path / "test_000"
    write_synthetic_scene(render_dir, reference_size=(HEIGHT, WIDTH - 2))
    cfg = smoke_config(methods=BASIC_METHODS)
    denoise.denoise_clip(cfg, "noisy", "test_000", 1, render_dir, tmp_path / "d")
    # The loader compares noisy and reference sizes as well; evaluate reads the files directly.
    with pytest.raises(evaluate.EvaluationError, match=r"resolution mismatch: .*frame_0000\.exr is 12x16.*"
                                                       r"reference .*frame_0000\.exr is 12x14"):
        scoring.evaluate_clip(cfg, tmp_path / "d", render_dir, tmp_path / "m.csv")
    assert not (tmp_path / "m.csv").exists()


def test_frame_count_mismatch_names_both_directories(scene_dir: Path, tmp_path: Path) -> None:
    cfg = smoke_config(methods=BASIC_METHODS)
    denoised = tmp_path / "d"
    denoise.denoise_clip(cfg, "noisy", "test_000", 1, scene_dir, denoised)
    (denoised / "frame_0003.exr").unlink()
    with pytest.raises(evaluate.EvaluationError, match=r"frame count mismatch: .*d holds 3 denoised frames.*"
                                                       r"reference holds 4 reference frames"):
        scoring.evaluate_clip(cfg, denoised, scene_dir, tmp_path / "m.csv")


def test_corruption_counts_and_is_seeded() -> None:
    rng = np.random.default_rng(1)
    clean = {"radiance": rng.uniform(0.5, 1.5, (2, 4, 3, 20, 25)).astype(np.float32),
             "normal": rng.uniform(-1, 1, (2, 4, 3, 20, 25)).astype(np.float32)}
    settings = {"seed": 7, "scene": "test_000", "spike_fraction": 0.01, "spike_max_factor": 500.0,
                "nonfinite_fraction": 0.003, "frames": [0, 1]}
    first, second = copy.deepcopy(clean), copy.deepcopy(clean)
    counts = robustness.inject_corruption(first, **settings)
    robustness.inject_corruption(second, **settings)
    np.testing.assert_array_equal(first["radiance"], second["radiance"])  # same seed, same corruption
    positions = 4 * 20 * 25
    n_spikes, n_bad = round(0.01 * positions), round(0.003 * positions)  # 20 and 6 per frame
    assert counts["spikes"] == 2 * n_spikes
    # Per buffer and frame, n_bad samples x 3 channels cycle through NaN, +Inf, -Inf.
    assert counts["nan_values"] == 2 * 2 * 3 * 2 and counts["inf_values"] == 2 * 2 * 3 * 4
    for buffer in clean:
        assert (~np.isfinite(first[buffer])).sum() == 2 * n_bad * 3
    finite = np.isfinite(first["radiance"])
    raised = (first["radiance"] - clean["radiance"])[finite]
    frame_mean = clean["radiance"].mean()
    assert raised.min() >= 0 and raised.max() <= 500 * frame_mean * 1.1
    assert (raised > 0).sum() >= 2 * (n_spikes - n_bad) * 3 - 6  # spikes hit all channels of their sample
    untouched = np.isfinite(first["normal"])
    np.testing.assert_array_equal(first["normal"][untouched], clean["normal"][untouched])  # no spikes in features


def test_robustness_reports_counts_and_finite_outputs(scene_dir: Path, tmp_path: Path, box_method: str) -> None:
    cfg = smoke_config(methods=[{"id": "box", "method": "test_box3"}, *BASIC_METHODS])
    out = tmp_path / "robust"
    summary = robustness.robustness_clip(cfg, "box", "test_000", 2, scene_dir, out, threads=1)
    positions = 2 * HEIGHT * WIDTH
    assert summary["injected"]["spikes"] == FRAMES * max(1, round(0.001 * positions))
    # radiance and albedo each get at least one non-finite sample (3 channels) per frame.
    assert summary["injected"]["nan_values"] + summary["injected"]["inf_values"] == FRAMES * 2 * 3
    assert summary["nonfinite_inputs"] == FRAMES * 2 * 3
    assert summary["nonfinite_outputs"] == 0
    table = pd.read_csv(out / evaluate.ROBUSTNESS_CSV)
    assert len(table) == FRAMES and np.isfinite(table["psnr"]).all()
    assert (table["nonfinite_output"] == 0).all() and (table["nonfinite_input"] == 6).all()
    assert np.isfinite(evaluate.read_radiance_exr(out / evaluate.ROBUSTNESS_LAST_EXR)).all()

    # The noisy row sanitises its samples (non-finite ones count as 0): nothing non-finite comes out.
    # Scoring of non-finite outputs: test_nonfinite_outputs_are_counted_and_scored_as_zero.
    noisy = robustness.robustness_clip(cfg, "noisy", "test_000", 2, scene_dir, tmp_path / "noisy", threads=1)
    table = pd.read_csv(tmp_path / "noisy" / evaluate.ROBUSTNESS_CSV)
    assert noisy["nonfinite_outputs"] == 0 and (table["nonfinite_output"] == 0).all()
    assert np.isfinite(table["psnr"]).all()


#: (channel, y, x, value) written over the output of NonFiniteOutput, x shifted by the frame index.
BAD_OUTPUT_VALUES = ((0, 2, 3, np.nan), (1, 2, 3, np.nan), (2, 2, 3, np.nan), (0, 6, 9, np.inf),
                     (2, 9, 1, -np.inf))


def nonfinite_output(frame_index: int, height: int = HEIGHT, width: int = WIDTH) -> np.ndarray:
    """What NonFiniteOutput returns for a frame: 1.2 x the reference with the values of
    BAD_OUTPUT_VALUES set, at x + frame_index (so the bad pixels move from frame to frame)."""
    image = 1.2 * synthetic_reference(height, width)
    for channel, y, x, value in BAD_OUTPUT_VALUES:
        image[channel, y, (x + frame_index) % width] = value
    return image


class NonFiniteOutput(Denoiser):
    """Ignores its input and returns :func:`nonfinite_output`: NaN, +Inf and -Inf at known pixels."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        return torch.from_numpy(nonfinite_output(frame.index, frame.height, frame.width))


@pytest.fixture
def nonfinite_method() -> Iterator[str]:
    """Registers NonFiniteOutput as 'test_nonfinite' for one test only (see box_method)."""
    registry.register("test_nonfinite", inputs=("radiance",), description="test only: NaN/Inf output")(NonFiniteOutput)
    yield "test_nonfinite"
    registry._REGISTRY.pop("test_nonfinite", None)


def _tau(x: np.ndarray) -> np.ndarray:
    """Isik 2021 Eq. 15 written out here: (max(x, 0) / (1 + max(x, 0)))^(1/2.4), float64."""
    x = np.maximum(np.asarray(x, np.float64), 0.0)
    return (x / (1.0 + x)) ** (1.0 / 2.4)


def test_nonfinite_outputs_are_counted_and_scored_as_zero(scene_dir: Path, tmp_path: Path,
                                                           nonfinite_method: str) -> None:
    """A method whose output holds NaN/+-Inf: every path that scores it (robustness_clip from the
    outputs in memory, evaluate_clip from the EXRs denoise_clip wrote) counts the bad values per frame
    and scores the frame as if they were 0, as score_sequence documents."""
    cfg = smoke_config(methods=[{"id": "bad", "method": nonfinite_method}, *BASIC_METHODS], warmup_frames=1)
    reference = synthetic_reference().astype(np.float64)
    outputs = np.stack([nonfinite_output(t) for t in range(FRAMES)])
    per_frame = len(BAD_OUTPUT_VALUES)
    assert (~np.isfinite(outputs)).sum(axis=(1, 2, 3)).tolist() == [per_frame] * FRAMES
    zeroed = np.where(np.isfinite(outputs), outputs, 0.0)
    # The expected scores, on the zero-substituted frames: PSNR straight from its definition, and every
    # metric through denoisers.metrics (which refuses non-finite input, so it must see the zeroed image).
    mse = ((_tau(zeroed) - _tau(reference)) ** 2).mean(axis=(1, 2, 3))
    expected_psnr = -10.0 * np.log10(mse)
    expected = {t: metrics.frame_metrics(zeroed[t], reference) for t in range(FRAMES)}
    expected_temporal = metrics.temporal_metrics(zeroed, np.stack([reference] * FRAMES), 1)
    # The substitution matters: the zeroed frames score far from the clean output, from skipping the bad
    # values (= substituting the reference) and from +Inf -> a huge finite value (tau -> 1).
    for alternative in (1.2 * np.stack([reference] * FRAMES), np.where(np.isfinite(outputs), outputs, reference),
                        np.nan_to_num(outputs, nan=0.0, posinf=1e30, neginf=0.0)):
        other = -10.0 * np.log10(((_tau(alternative) - _tau(reference)) ** 2).mean(axis=(1, 2, 3)))
        assert np.abs(other - expected_psnr).min() > 0.5

    def check(table: pd.DataFrame) -> None:
        assert table["nonfinite_output"].tolist() == [per_frame] * FRAMES
        np.testing.assert_allclose(table["psnr"], expected_psnr, rtol=1e-6)
        for name in evaluate.FRAME_METRICS:
            np.testing.assert_allclose(table[name], [expected[t][name] for t in range(FRAMES)], rtol=1e-6,
                                       err_msg=name)
        for name in evaluate.TEMPORAL_METRICS:
            np.testing.assert_allclose(table[name], expected_temporal[name], rtol=1e-6, equal_nan=True, err_msg=name)

    summary = robustness.robustness_clip(cfg, "bad", "test_000", 2, scene_dir, tmp_path / "robust", threads=1)
    assert summary["nonfinite_outputs"] == FRAMES * per_frame
    assert summary["nonfinite_inputs"] > 0  # the corruption was injected; the method ignores it
    check(pd.read_csv(tmp_path / "robust" / evaluate.ROBUSTNESS_CSV))
    assert summary["mean_psnr"] == pytest.approx(expected_psnr.mean(), rel=1e-6)
    last = evaluate.read_radiance_exr(tmp_path / "robust" / evaluate.ROBUSTNESS_LAST_EXR)
    np.testing.assert_array_equal(last, outputs[-1])  # written as returned, NaN and Inf included

    denoised = tmp_path / "denoised"
    record = denoise.denoise_clip(cfg, "bad", "test_000", 2, scene_dir, denoised, threads=1)
    assert record["nonfinite_outputs"] == FRAMES * per_frame
    assert record["nonfinite_outputs_per_frame"] == [per_frame] * FRAMES
    check(scoring.evaluate_clip(cfg, denoised, scene_dir, tmp_path / "m.csv"))
    check(pd.read_csv(tmp_path / "m.csv"))


def test_cli_prints_one_line_for_missing_inputs(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                box_method: str) -> None:
    from denoisers.cli import main

    render_dir = tmp_path / "test_000"
    write_synthetic_scene(render_dir, omit=("albedo",))
    cfg = smoke_config(methods=[{"id": "box", "method": "test_box3"}])
    config_file = tmp_path / "cfg.yaml"
    config_file.write_text(yaml.safe_dump(cfg))
    code = main(["denoise", "--config", str(config_file), "--method-id", "box", "--scene", "test_000", "--spp", "1",
                 "--render-dir", str(render_dir), "--out", str(tmp_path / "out")])
    assert code == 1
    assert "method 'box (test_box3)' needs buffer 'albedo'" in caplog.text


# ---------------------------------------------------------------------------------------------------
# Rows: their own spp and robustness keys, and the rows of the trained ablation variants
# ---------------------------------------------------------------------------------------------------

def test_rows_have_their_own_spp_and_ablation_variants_get_rows() -> None:
    from denoisers.training.models import model_specs

    cfg = smoke_config(methods=[*BASIC_METHODS, {"id": "eaw", "method": "eaw", "spp": [2], "robustness": False}],
                       spp=[1, 2], ablation_spp=[1])
    variants = [model for model in model_specs(cfg) if model.ablation]
    assert len(variants) == 7  # the smoke config's rae_inputs (3), rae_loss (2) and rae_capacity (2) variants
    specs = evaluate.method_specs(cfg)
    assert [spec.id for spec in specs] == ["noisy", "path_x2", "eaw", *(model.id for model in variants)]
    assert specs[0] == evaluate.MethodSpec("noisy", "noisy", {}, (1, 2), True, evaluate.METHOD_ROLE)
    assert specs[2].spp == (2,) and specs[2].robustness is False and specs[2].role == evaluate.METHOD_ROLE
    for spec, model in zip(specs[3:], variants):
        assert (spec.method, spec.params, spec.spp, spec.robustness, spec.role) == (
            model.method, {"model": model.id}, (1,), False, evaluate.ABLATION_ROLE)
    assert evaluate.method_spec(cfg, "rae_loss_spatial").params == {"model": "rae_loss_spatial"}

    # Each row at its own spp (intersected with the requested ones); robustness only for rows that ask.
    ablation_runs = {(model.id, 1) for model in variants}
    assert {(run.spec.id, run.spp) for run in evaluate.plan_runs(cfg)} == {
        ("noisy", 1), ("noisy", 2), ("path_x2", 1), ("path_x2", 2), ("eaw", 2), *ablation_runs}
    assert {(run.spec.id, run.spp) for run in evaluate.plan_runs(cfg, [2])} == {("noisy", 2), ("path_x2", 2),
                                                                                ("eaw", 2)}
    assert [(run.spec.id, run.spp) for run in evaluate.robustness_runs(cfg)] == [("noisy", 2), ("path_x2", 2)]

    cfg["evaluation"]["ablation_spp"] = [1, 2]
    assert {(run.spec.id, run.spp) for run in evaluate.plan_runs(cfg) if run.spec.role == evaluate.ABLATION_ROLE} \
        == ablation_runs | {(model.id, 2) for model in variants}
    cfg["evaluation"]["ablation_spp"] = []
    assert [spec.id for spec in evaluate.method_specs(cfg)] == ["noisy", "path_x2", "eaw"]
    with pytest.raises(KeyError, match="rae_inputs_color"):
        evaluate.method_spec(cfg, "rae_inputs_color")


def test_a_misspelled_method_parameter_names_row_method_and_allowed_keys() -> None:
    cfg = smoke_config(methods=[{"id": "eaw_soft", "method": "eaw", "params": {"sigma_colour": 4.0}}],
                       ablation_spp=[])
    with pytest.raises(ValueError) as error:
        evaluate.plan_runs(cfg)
    message = str(error.value)
    assert "evaluation row 'eaw_soft' (method 'eaw')" in message and "'sigma_colour'" in message
    assert "did you mean 'sigma_color'?" in message and "allowed: sigma_color, sigma_normal" in message
    assert registry.build("eaw", {"sigma_color": 4.0}).info.name == "eaw"       # a correct one still builds


@pytest.mark.parametrize("grid_frame, ok", [(-1, True), (0, True), (3, True), (-4, True), (4, False), (99, False),
                                             (-5, False)])
def test_grid_frame_must_index_a_frame(grid_frame: int, ok: bool) -> None:
    cfg = smoke_config(grid_frame=grid_frame)            # the smoke clips have 4 frames
    assert cfg["scenes"]["frames"] == 4
    problems = [p for p in evaluate.evaluation_problems(cfg) if "grid_frame" in p]
    assert (problems == []) == ok, problems
    if not ok:
        assert f"'evaluation.grid_frame' = {grid_frame}" in problems[0] and "-4..3" in problems[0]


def test_evaluation_problems_name_row_spp_ablation_spp_and_ablation_ids() -> None:
    taken = {"id": "rae_loss_spatial", "method": "rae", "params": {"model": "rae_loss_spatial"}, "spp": [1, 4]}
    cfg = smoke_config(methods=[*BASIC_METHODS, taken], spp=[1, 2], ablation_spp=[1, 3])
    problems = "\n".join(evaluate.evaluation_problems(cfg))
    assert "config key 'evaluation.methods[2].spp' (row 'rae_loss_spatial') = [1, 4] has values [4]" in problems
    assert "config key 'evaluation.ablation_spp' = [1, 3] has values [3]" in problems
    assert "config key 'evaluation.methods' has the id 'rae_loss_spatial'" in problems
    assert "ablation variant" in problems
    # Without the ablation rows the id is free; without ablation variants ablation_spp is not checked.
    cfg["evaluation"]["ablation_spp"] = []
    cfg["evaluation"]["methods"][2]["spp"] = [1]
    assert evaluate.evaluation_problems(cfg) == []
    cfg = smoke_config(methods=BASIC_METHODS, spp=[2], ablation_spp=[1])
    assert "'evaluation.ablation_spp' = [1]" in "\n".join(evaluate.evaluation_problems(cfg))
    cfg["training"]["ablations"] = []
    assert evaluate.evaluation_problems(cfg) == []


# ---------------------------------------------------------------------------------------------------
# Out-of-range outputs: finite, but above out_of_range_factor x the frame's largest input sample
# ---------------------------------------------------------------------------------------------------

#: Output pixels (y, x) inside the bright disc of the synthetic clip; Exploding multiplies the first
#: frame.index + 1 of them by 1e6.
EXPLODED_PIXELS = ((6, 6), (6, 7), (6, 8), (6, 9))


class Exploding(Denoiser):
    """The sanitised sample mean with the first frame.index + 1 pixels of EXPLODED_PIXELS (all channels)
    multiplied by 1e6, plus one NaN and one +Inf value (non-finite: counted as such, not as out of range)."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        out = torch.nan_to_num(frame.samples["radiance"], nan=0.0, posinf=0.0, neginf=0.0).mean(0)
        for y, x in EXPLODED_PIXELS[:frame.index + 1]:
            out[:, y, x] *= 1e6
        out[0, 0, 0], out[1, 0, 1] = float("nan"), float("inf")
        return out


class AlbedoOnly(Denoiser):
    """Reads no radiance: the albedo mean x 1e6 (no input range to compare with, so nothing is counted)."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        return frame.mean("albedo") * 1e6


@pytest.fixture
def exploding_methods() -> Iterator[None]:
    """Registers Exploding ('test_exploding') and AlbedoOnly ('test_albedo_only') for one test only."""
    registry.register("test_exploding", inputs=("radiance",), description="test only: 1e6 x on pixels")(Exploding)
    registry.register("test_albedo_only", inputs=("albedo",), description="test only: no radiance")(AlbedoOnly)
    yield
    registry._REGISTRY.pop("test_exploding", None)
    registry._REGISTRY.pop("test_albedo_only", None)


def test_out_of_range_outputs_are_counted_per_frame(scene_dir: Path, tmp_path: Path, exploding_methods: None) -> None:
    cfg = smoke_config(methods=[{"id": "boom", "method": "test_exploding"},
                                {"id": "albedo", "method": "test_albedo_only"}, *BASIC_METHODS])
    assert cfg["evaluation"]["out_of_range_factor"] == 10
    expected = [3 * (t + 1) for t in range(FRAMES)]  # every channel of frame.index + 1 pixels
    record = denoise.denoise_clip(cfg, "boom", "test_000", 2, scene_dir, tmp_path / "boom", threads=1)
    assert record["out_of_range_outputs_per_frame"] == expected
    assert record["out_of_range_outputs"] == sum(expected) == 30
    assert record["out_of_range_factor"] == 10 and record["out_of_range_checked"] is True
    assert record["nonfinite_outputs_per_frame"] == [2] * FRAMES  # NaN / Inf are not out of range
    assert json.loads((tmp_path / "boom" / evaluate.TIMING_FILE).read_text()) == record

    # The spike/NaN scenario: its inputs carry spikes up to 500 x the frame mean, still far below 1e6 x.
    summary = robustness.robustness_clip(cfg, "boom", "test_000", 2, scene_dir, tmp_path / "robust", threads=1)
    assert summary["out_of_range_outputs"] == 30 and summary["out_of_range_factor"] == 10
    table = pd.read_csv(tmp_path / "robust" / evaluate.ROBUSTNESS_CSV)
    assert table["out_of_range_output"].tolist() == expected

    # The factor comes from the config: 1e7 x the largest sample is above every output of Exploding.
    cfg["evaluation"]["out_of_range_factor"] = 1e7
    record = denoise.denoise_clip(cfg, "boom", "test_000", 2, scene_dir, tmp_path / "boom_1e7", threads=1)
    assert record["out_of_range_outputs"] == 0 and record["out_of_range_factor"] == 1e7

    # A method that reads no radiance has no input range: nothing counted, and the record says so.
    record = denoise.denoise_clip(cfg, "albedo", "test_000", 2, scene_dir, tmp_path / "albedo", threads=1)
    assert record["out_of_range_outputs"] == 0 and record["out_of_range_outputs_per_frame"] == [0] * FRAMES
    assert record["out_of_range_checked"] is False


@pytest.mark.parametrize("method", ["noisy", "eaw"])
def test_normal_methods_have_no_out_of_range_outputs(scene_dir: Path, tmp_path: Path, method: str) -> None:
    cfg = smoke_config(methods=[{"id": method, "method": method}])
    record = denoise.denoise_clip(cfg, method, "test_000", 4, scene_dir, tmp_path / method, threads=1)
    assert record["out_of_range_outputs"] == 0 and record["out_of_range_outputs_per_frame"] == [0] * FRAMES
    assert record["out_of_range_checked"] is True
    summary = robustness.robustness_clip(cfg, method, "test_000", 2, scene_dir, tmp_path / "robust", threads=1)
    assert summary["out_of_range_outputs"] == 0
