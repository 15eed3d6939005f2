"""Tests for the generated report (denoisers/report/ and the paper modules in denoisers/reproductions/).

Most tests build a results tree by hand: per-frame metric CSVs with known numbers, timing.json,
robustness outputs and tiny EXRs for the image grids, so that means, confidence intervals and claim
verdicts can be checked against values computed here (scipy.stats.t for the intervals). One test
runs the real evaluation jobs on a synthetic clip and builds the report from their outputs.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from denoisers import evaluate
from denoisers.jobs import denoise, robustness, scoring
from denoisers.report import build_report, report_outputs
from denoisers.report.claims import claims_table
from denoisers.report.collect import collect
from denoisers.report.stats import HIGHER_IS_BETTER, mean_ci
from denoisers.reproductions import all_claims
from denoisers.jobs.timing import TIMING_SCHEMA
from tests.test_evaluate import smoke_config, synthetic_reference, write_synthetic_scene

SCENES = ("test_000", "test_001", "test_002")
FRAMES = 4
SIZE = (8, 10)
# Small symmetric per-frame wiggle: the frame mean of every metric is exactly its per-scene value.
WIGGLE = np.array([0.1, -0.1, 0.2, -0.2])
SCENE_OFFSET = {"test_000": 0.0, "test_001": 1.0, "test_002": -0.5}
METHODS = [{"id": "noisy", "method": "noisy"}, {"id": "path_x2", "method": "path_tracing", "params": {"factor": 2}},
           {"id": "svgf", "method": "svgf"}, {"id": "rls", "method": "rls"}, {"id": "wrls", "method": "wrls"}]
# Per-method PSNR at 1 spp (dB; + 3 dB per doubling of spp), TRMAE, ms/frame.
PSNR = {"noisy": 20.0, "path_x2": 22.0, "svgf": 27.0, "rls": 26.0, "wrls": 28.0}
TRMAE = {"noisy": 0.9, "path_x2": 0.7, "svgf": 0.30, "rls": 0.35, "wrls": 0.20}
MS = {"noisy": 0.1, "path_x2": 0.1, "svgf": 5.0, "rls": 8.0, "wrls": 4.0}
SPIKED_PSNR = {"noisy": 10.0, "path_x2": 12.0, "svgf": 18.0, "rls": 15.0, "wrls": 24.0}


def psnr_of(method: str, scene: str, spp: int) -> float:
    return PSNR[method] + 3.0 * math.log2(spp) + SCENE_OFFSET[scene]


def metric_frame(psnr: float, trmae: float, cut_at: int | None = None) -> pd.DataFrame:
    """Per-frame CSV content whose frame means are ``psnr`` and (over frames 1..) ``trmae``."""
    frames = np.arange(FRAMES)
    return pd.DataFrame({
        "frame": frames, "psnr": psnr + WIGGLE, "ssim": 0.8 + WIGGLE / 10, "rmse": 0.05 + WIGGLE / 100,
        "relmse": 0.02 + WIGGLE / 100, "smape": 0.1 + WIGGLE / 10, "flip": 0.1 + WIGGLE / 10,
        "tpsnr": np.r_[np.nan, [psnr + 5.0] * (FRAMES - 1)], "trmae": np.r_[np.nan, [trmae] * (FRAMES - 1)],
        "camera_cut": frames == cut_at, "nonfinite_output": 0, "reference_psnr_halves": 45.0,
    })


def write_results(root: Path, cfg: dict, *, psnr: dict | None = None, trmae: dict | None = None,
                  spiked: dict | None = None, scenes: dict[str, float] | None = None) -> None:
    """A complete hand-made results tree for ``cfg`` (every runnable (method, spp) on ``scenes``: {scene:
    PSNR offset}, default SCENE_OFFSET)."""
    psnr, trmae, spiked = psnr or PSNR, trmae or TRMAE, spiked or SPIKED_PSNR
    offsets = SCENE_OFFSET if scenes is None else scenes
    layers = cfg["render"]["spp"]
    for scene in offsets:
        write_synthetic_scene(root / "renders" / scene, scene=scene, frames=FRAMES, layers=layers, height=SIZE[0],
                              width=SIZE[1])
        image = synthetic_reference(*SIZE)
        for spec in cfg["evaluation"]["methods"]:
            method_id = spec["id"]
            factor = spec.get("params", {}).get("factor", 1)
            for spp in cfg["evaluation"]["spp"]:
                if spp * factor > layers:
                    continue
                value = psnr[method_id] + 3.0 * math.log2(spp) + offsets[scene]
                csv = evaluate.metrics_csv(root, method_id, scene, spp)
                csv.parent.mkdir(parents=True, exist_ok=True)
                metric_frame(value, trmae[method_id], cut_at=2).to_csv(csv, index=False)
                folder = evaluate.denoised_dir(root, method_id, scene, spp)
                folder.mkdir(parents=True, exist_ok=True)
                for t in range(FRAMES):
                    evaluate.write_radiance_exr(folder / f"frame_{t:04d}.exr", image * (1 + 0.01 * t))
                # The denoise jobs' own times are 3x the timing job's: the report must use the timing job.
                seconds = 3 * MS[method_id] / 1e3
                timing = {"mean_seconds": seconds, "mpix_per_s": SIZE[0] * SIZE[1] / seconds / 1e6,
                          "peak_memory_mb": 10.0, "nonfinite_inputs": 0, "nonfinite_outputs": 0,
                          "samples_factor": factor, "render_samples_per_s": 1.0e6, "width": SIZE[1],
                          "height": SIZE[0]}
                (folder / evaluate.TIMING_FILE).write_text(json.dumps(timing))
            robust = evaluate.robustness_dir(root, method_id, scene, cfg["evaluation"]["robustness"]["spp"])
            robust.mkdir(parents=True, exist_ok=True)
            metric_frame(spiked[method_id] + offsets[scene], trmae[method_id]).assign(
                nonfinite_input=6, nonfinite_output=0).to_csv(robust / evaluate.ROBUSTNESS_CSV, index=False)
            (robust / evaluate.ROBUSTNESS_SUMMARY).write_text(json.dumps({
                "injected": {"spikes": 4, "nan_values": 6, "inf_values": 12}, "nonfinite_inputs": 24,
                "nonfinite_outputs": 0}))
            evaluate.write_radiance_exr(robust / evaluate.ROBUSTNESS_LAST_EXR, image)
    write_timing_job(root, cfg, list(offsets))


def write_timing_job(root: Path, cfg: dict, scenes: list[str]) -> None:
    """The timing job's record: three rounds per runnable (row, spp) at 0.9, 1 and 1.2 x MS ms per frame."""
    layers, rows = cfg["render"]["spp"], []
    for spec in cfg["evaluation"]["methods"]:
        for spp in cfg["evaluation"]["spp"]:
            if spp * spec.get("params", {}).get("factor", 1) <= layers:
                passes = [MS[spec["id"]] * f for f in (1.0, 0.9, 1.2)]
                rows.append({"method_id": spec["id"], "spp": spp, "threads": 2, "width": SIZE[1], "height": SIZE[0],
                             "pass_ms_per_frame": passes, "ms_per_frame": MS[spec["id"]],
                             "ms_per_frame_min": min(passes), "ms_per_frame_max": max(passes), "repeats": 3,
                             "spread": 0.3, "mpix_per_s": SIZE[0] * SIZE[1] / (MS[spec["id"]] / 1e3) / 1e6})
    (root / "timing").mkdir(parents=True, exist_ok=True)
    (root / "timing" / "timing.json").write_text(json.dumps({
        "schema": TIMING_SCHEMA, "scene": "test_000", "frames": FRAMES, "repeats": 3, "threads": 2, "rows": rows,
        "sgemm": {"size": 1024, "gflops_per_s": [100.0, 90.0, 110.0], "gflops_per_s_median": 100.0},
        "renderers": {scene: {"samples_per_s": 1.0e6, "samples_per_s_min": 0.9e6, "samples_per_s_max": 1.1e6,
                              "repeats": 3, "layers": layers, "threads": 2} for scene in scenes}}))


def report_config() -> dict:
    cfg = smoke_config(methods=METHODS, spp=[1, 2], warmup_frames=1, ablation_spp=[])
    cfg["scenes"]["n_test"], cfg["scenes"]["n_train"] = len(SCENES), 2
    cfg["extra_scenes"] = []   # test scenes only; external scenes: tests/test_external_scenes.py
    cfg["render"]["spp"] = 2   # path_x2 at 2 spp needs 4 layers: not run
    cfg["render"]["extra_radiance_spp"] = 0
    cfg["render"]["width"], cfg["render"]["height"] = SIZE[1], SIZE[0]
    return cfg


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("results")
    cfg = report_config()
    write_results(root, cfg)
    build_report(cfg, root)
    return root, cfg


def claims_of(root: Path) -> dict[str, str]:
    table = pd.read_csv(root / "tables" / "claims.csv")
    return dict(zip(table["claim"], table["verdict"]))


def test_summary_means_and_t_intervals(built: tuple[Path, dict]) -> None:
    root, _ = built
    summary = pd.read_csv(root / "tables" / "summary.csv")
    for method in ("noisy", "svgf", "wrls"):
        for spp in (1, 2):
            row = summary[(summary.method_id == method) & (summary.spp == spp) & (summary.metric == "psnr")].iloc[0]
            per_scene = [psnr_of(method, scene, spp) for scene in SCENES]
            low, high = stats.t.interval(0.95, len(per_scene) - 1, loc=np.mean(per_scene), scale=stats.sem(per_scene))
            assert row["mean"] == pytest.approx(np.mean(per_scene))
            assert (row["ci_low"], row["ci_high"]) == (pytest.approx(low), pytest.approx(high))
            assert row["n_scenes"] == 3
    trmae = summary[(summary.method_id == "rls") & (summary.metric == "trmae")]
    assert trmae["mean"].tolist() == pytest.approx([TRMAE["rls"]] * 2)
    assert trmae["ci_high"].tolist() == pytest.approx([TRMAE["rls"]] * 2)  # identical scenes: zero width
    timing = pd.read_csv(root / "tables" / "timing.csv").set_index(["method_id", "spp"])
    speed = timing.loc[("wrls", 1)]
    assert speed["mpix_per_s"] == pytest.approx(SIZE[0] * SIZE[1] / (MS["wrls"] / 1e3) / 1e6)
    assert (speed["ms_per_frame"], speed["ms_per_frame_min"], speed["ms_per_frame_max"]) == (
        pytest.approx(MS["wrls"]), pytest.approx(0.9 * MS["wrls"]), pytest.approx(1.2 * MS["wrls"]))
    assert speed["timing_rounds"] == 3


def test_mean_ci_matches_scipy_and_handles_one_value() -> None:
    values = [1.0, 2.5, 2.0, 4.0]
    mean, low, high, n = mean_ci(values + [float("nan")])
    assert n == 4 and mean == pytest.approx(2.375)
    assert (low, high) == pytest.approx(stats.t.interval(0.95, 3, loc=2.375, scale=stats.sem(values)))
    mean, low, high, n = mean_ci([3.0])
    assert (mean, n) == (3.0, 1) and math.isnan(low) and math.isnan(high)


def test_not_run_rows_are_listed_with_the_reason(built: tuple[Path, dict]) -> None:
    root, _ = built
    runs = pd.read_csv(root / "tables" / "runs.csv")
    row = runs[(runs.id == "path_x2") & (runs.spp == 2)].iloc[0]
    assert row["status"] == "not run" and "needs 4 layers of 'radiance', 2 rendered" in row["reason"]
    assert (runs[runs.id != "path_x2"]["status"] == "ran").all()
    text = (root / "REPORT.md").read_text()
    assert "## Not run" in text and "needs 4 layers" in text


def video_psnr_of(method: str, scene: str, spp: int) -> float:
    """Isik et al. 2021 Eq. 14 on the fixture's frames: -10 log10 of the per-frame MSEs' mean."""
    frame_psnr = psnr_of(method, scene, spp) + WIGGLE
    return float(-10 * np.log10(np.mean(10 ** (-frame_psnr / 10))))


def test_video_psnr_is_pooled_and_isik_tables_need_afn_rows(built: tuple[Path, dict]) -> None:
    """Video PSNR (Isik et al. Eq. 14, the Table 3 metric) pools the frames' MSE; the Isik tables are laid out
    from AFN rows only, so this fixture (no afn row) writes none and the report says why."""
    root, cfg = built
    per_scene = collect(cfg, root).per_scene
    wrls = per_scene[(per_scene.method_id == "wrls") & (per_scene.spp == 2)].set_index("scene")["video_psnr"]
    for scene in SCENES:
        assert math.isclose(wrls[scene], video_psnr_of("wrls", scene, 2), rel_tol=1e-9)
    assert video_psnr_of("wrls", SCENES[0], 2) < psnr_of("wrls", SCENES[0], 2)     # pooled MSE != mean of dB
    assert not (root / "tables" / "isik_table2.csv").exists()
    assert "No `afn` rows are configured" in (root / "REPORT.md").read_text()
    markdown = (root / "tables" / "summary.md").read_text()
    assert "### 1 spp (3 scenes)" in markdown and "| wrls |" in markdown


def test_claims_follow_the_numbers(built: tuple[Path, dict]) -> None:
    root, _ = built
    verdicts = claims_of(root)
    # Differences are identical on the 3 scenes: zero-width intervals on the claimed side.
    assert verdicts["C4.1s"] == "reproduced"      # at 2 spp wrls 31 dB > svgf 30 dB and TRMAE 0.20 < 0.30
    assert verdicts["C4.2s"] == "reproduced"      # spiked 24 dB > 15 dB, drop 7 dB < 14 dB
    for claim in ("C1.1", "C2.1", "C3.1", "C4.3s", "C4.4"):   # no RAE, NTASD, AFN rows configured
        assert verdicts[claim] == "not run"
    table = pd.read_csv(root / "tables" / "claims.csv").set_index("claim")
    assert "RAE" in table.loc["C1.1", "note"] and "RAE" in table.loc["C4.3s", "note"]
    # Claims average each clip's steady frames: warm-up 1 and a cut at frame 2 leave frames 1 and 3.
    steady = float(np.mean(WIGGLE[[1, 3]]))
    wrls, svgf = (np.mean([psnr_of(m, scene, 2) for scene in SCENES]) + steady for m in ("wrls", "svgf"))
    assert f"PSNR (dB, frame mean): wrls @ 2 spp {wrls:.2f} vs svgf @ 2 spp {svgf:.2f}" in table.loc["C4.1s", "measured"]
    assert table.loc["C4.1s", "mean_diff_ci_95"].startswith("1.00 [1.00, 1.00]")
    assert table.loc["C4.1s", "n"] == 3


@pytest.mark.parametrize("change, claim", [
    ({"psnr": {**PSNR, "wrls": 26.5}}, "C4.1s"),          # wrls below svgf in PSNR
    ({"trmae": {**TRMAE, "wrls": 0.5}}, "C4.1s"),         # wrls flickers more than svgf
    ({"spiked": {**SPIKED_PSNR, "wrls": 14.0}}, "C4.2s"),  # wrls worse than rls under spikes
])
def test_flipping_the_numbers_flips_the_verdict(tmp_path: Path, change: dict, claim: str) -> None:
    cfg = report_config()
    write_results(tmp_path, cfg, **change)
    res = collect(cfg, tmp_path)
    verdicts = dict(zip(*claims_table(res, all_claims())[["claim", "verdict"]].T.values))
    assert verdicts[claim] == "contradicted"


def test_missing_method_makes_claims_not_run(tmp_path: Path) -> None:
    cfg = report_config()
    cfg["evaluation"]["methods"] = [m for m in METHODS if m["id"] != "svgf"]
    write_results(tmp_path, cfg)
    table = claims_table(collect(cfg, tmp_path), all_claims()).set_index("claim")
    assert table.loc["C4.1s", "verdict"] == "not run" and "SVGF" in table.loc["C4.1s", "note"]
    assert table.loc["C4.2s", "verdict"] == "reproduced"


def test_equal_time_view_picks_the_nearest_path_tracing_row(built: tuple[Path, dict]) -> None:
    root, _ = built
    table = pd.read_csv(root / "tables" / "equal_time.csv").set_index(["method_id", "spp"])
    # svgf at 1 spp: 5 ms x 1e6 samples/s / 80 px = 62.5 extra spp -> 63.5 spp equal time; the nearest
    # rendered plain path tracing has 2 spp in total: noisy at 2 spp (path_x2 at 1 spp ties; the first wins).
    row = table.loc[("svgf", 1)]
    assert row["equal_time_spp"] == pytest.approx(1 + 5e-3 * 1e6 / 80)
    assert row["path_tracing_row"] == "noisy @ 2 spp" and row["path_tracing_spp"] == 2
    assert row["psnr_diff_mean"] == pytest.approx(psnr_of("svgf", "test_000", 1) - psnr_of("noisy", "test_000", 2))
    assert row["better"].startswith("svgf (nearest rendered PT has 2 spp")


def test_noise_floor_and_split(built: tuple[Path, dict]) -> None:
    root, _ = built
    floor = pd.read_csv(root / "tables" / "noise_floor.csv").set_index("scene")
    assert floor.loc["test_001", "reference_noise_floor_psnr"] == pytest.approx(45.0 + 10 * math.log10(4))
    assert floor.loc["test_001", "best_method"] == "wrls"
    split = pd.read_csv(root / "tables" / "split.csv")
    assert split[split.evaluated]["scene"].tolist() == list(SCENES)
    assert split[~split.evaluated]["scene"].tolist() == ["train_000", "train_001"]


def test_robustness_table(built: tuple[Path, dict]) -> None:
    root, _ = built
    table = pd.read_csv(root / "tables" / "robustness.csv").set_index("method_id")
    assert table.loc["wrls", "psnr_spiked_mean"] == pytest.approx(SPIKED_PSNR["wrls"] + np.mean(list(SCENE_OFFSET.values())))
    assert table.loc["wrls", "psnr_drop_mean"] == pytest.approx(PSNR["wrls"] + 3.0 - SPIKED_PSNR["wrls"])
    assert table.loc["rls", "nonfinite_inputs"] == 3 * 24 and table.loc["rls", "spikes"] == 3 * 4


def test_every_output_and_link_exists(built: tuple[Path, dict]) -> None:
    root, cfg = built
    for group in report_outputs(cfg, root=str(root)).values():
        for path in group:
            assert Path(path).is_file() and Path(path).stat().st_size > 0, path
    text = (root / "REPORT.md").read_text()
    links = re.findall(r"\]\(([^)]+)\)", text)
    assert "figures/quality_vs_speed.png" in links and "tables/claims.csv" in links
    assert "figures/grid_test_002_spp1.png" in links and "figures/frame_curves_test_000.png" in links
    for link in links:
        assert (root / link).is_file(), link
    assert "| C4.1s |" in text and "reproduced" in text
    assert "Provenance of this report" in text and "logical cores" in text


def test_report_from_real_evaluation_outputs(tmp_path: Path) -> None:
    """denoise + evaluate + robustness jobs on a synthetic clip, then the report, end to end in-process."""
    cfg = smoke_config(methods=METHODS[:2], spp=[1, 2], warmup_frames=1, ablation_spp=[])
    cfg["scenes"]["n_test"], cfg["extra_scenes"] = 1, []
    write_synthetic_scene(tmp_path / "renders" / "test_000")
    for run in evaluate.plan_runs(cfg):
        if run.runnable:
            out = evaluate.denoised_dir(tmp_path, run.spec.id, "test_000", run.spp)
            denoise.denoise_clip(cfg, run.spec.id, "test_000", run.spp, tmp_path / "renders" / "test_000", out)
            scoring.evaluate_clip(cfg, out, tmp_path / "renders" / "test_000",
                                  evaluate.metrics_csv(tmp_path, run.spec.id, "test_000", run.spp))
    for run in evaluate.robustness_runs(cfg):
        robustness.robustness_clip(cfg, run.spec.id, "test_000", run.spp, tmp_path / "renders" / "test_000",
                                   evaluate.robustness_dir(tmp_path, run.spec.id, "test_000", run.spp))
    written = build_report(cfg, tmp_path)
    assert all(p.is_file() for p in written)
    summary = pd.read_csv(tmp_path / "tables" / "summary.csv")
    psnr = summary[summary.metric == "psnr"].set_index(["method_id", "spp"])["mean"]
    assert psnr[("path_x2", 1)] > psnr[("noisy", 1)]  # twice the samples of the same clip
    assert pd.read_csv(tmp_path / "tables" / "claims.csv").set_index("claim").loc["C4.1s", "verdict"] == "not run"


def test_metric_directions_agree_with_the_metrics_module() -> None:
    from denoisers import metrics

    for name in evaluate.ALL_METRICS:
        assert HIGHER_IS_BETTER[name] == metrics.METRICS[name].higher_is_better, name


def test_color_balance_measures_a_channel_cast(tmp_path: Path) -> None:
    """One row's outputs are the reference with its channels scaled by (1.2, 1.0, 0.8): ratios 1.2 / 1.0 / 0.8,
    brightness 1 and cast 0.2 exactly; rows that keep the reference's colour have no cast."""
    from denoisers.report.color_balance import color_balance_table
    from scenegen.dataset import find_frames, load_reference_frame

    cfg = report_config()
    write_results(tmp_path, cfg)
    method = cfg["evaluation"]["methods"][1]["id"]
    for scene in SCENE_OFFSET:
        folder = evaluate.denoised_dir(tmp_path, method, scene, 1)
        for t, path in find_frames(tmp_path / "renders" / scene / "reference").items():
            reference = load_reference_frame(path, ["radiance"])[0]["radiance"]
            evaluate.write_radiance_exr(folder / f"frame_{t:04d}.exr",
                                        reference * np.array([1.2, 1.0, 0.8], np.float32)[:, None, None])
    table = color_balance_table(collect(cfg, tmp_path)).set_index(["method_id", "spp"])
    row = table.loc[(method, 1)]
    np.testing.assert_allclose(row[["ratio_r", "ratio_g", "ratio_b", "brightness", "cast", "cast_max"]].astype(float),
                               [1.2, 1.0, 0.8, 1.0, 0.2, 0.2], rtol=1e-4)
    assert row["scenes"] == len(SCENE_OFFSET)
    others = table.drop(index=(method, 1))
    assert len(others) and (others["cast"] < 1e-3).all()


def test_report_shows_the_color_balance(built: tuple[Path, dict]) -> None:
    root, _ = built
    table = pd.read_csv(root / "tables" / "color_balance.csv")
    assert len(table) and (table["cast"] < 1e-3).all()
    assert "### Colour balance" in (root / "REPORT.md").read_text()
