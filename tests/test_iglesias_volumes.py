"""The Iglesias-Guitian comparison on the volumetric clips: volume rows and their not-run reasons
(denoisers.jobs.volumes), collecting their metrics with digest checks (denoisers.report.volumes), the per-scenario
table and C4.1 / C4.3 decided over the clips (denoisers.reproductions.iglesias2022)."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from denoisers.evaluate import TIMING_FILE, method_spec, volume_method_specs
from denoisers.registry import Frame
from denoisers.experiment import DIGEST_KEY, DigestLedger, Lineage, SettingsMismatchError
from denoisers.report.verdicts import CONTRADICTED, INCONCLUSIVE, NOT_RUN, REPRODUCED
from denoisers.report.volumes import VolumeResults, collect_volumes
from denoisers.reproductions import iglesias2022
from denoisers.jobs.volumes import (volume_denoised_dir, volume_metrics_csv, volume_problems, volume_runs,
                                   volume_test_scene_ids)
from scenegen.config import load_config

ROOT = Path(__file__).resolve().parents[1]
CLEAR = [1.0, 1.2, 0.9, 1.1]
AGAINST = [-1.0, -1.2, -0.9, -1.1]
SPANNING = [1.0, -1.0, 1.5, -0.5]


def volume_config(n_test: int = 2, rows: list[dict] | None = None, denoise_spp: list[int] | None = None) -> dict:
    cfg = load_config(ROOT / "config/smoke.yaml")
    cfg["volumes"].update(enabled=True, scenarios=["camera", "light"], n_test=n_test, spp=4,
                          denoise_spp=denoise_spp or [1, 2, 4])
    cfg["volumes"]["rows"] = rows if rows is not None else [
        {"id": "vol_noisy", "method": "noisy"}, {"id": "vol_wrls", "method": "wrls"},
        {"id": "vol_svgf", "method": "svgf_volume"},
        {"id": "vol_rae", "method": "rae_color", "params": {"model": "rae_volume"}}]
    return cfg


def test_volume_rows_are_their_own_and_runs_say_why_not() -> None:
    cfg = volume_config(rows=[{"id": "vol_noisy", "method": "noisy"}, {"id": "vol_svgf_surface", "method": "svgf"},
                              {"id": "vol_wrls", "method": "wrls", "spp": [2]},
                              {"id": "vol_rae_gbuffer", "method": "rae", "params": {"model": "rae"}}],
                        denoise_spp=[2, 8])
    assert [spec.id for spec in volume_method_specs(cfg)] == ["vol_noisy", "vol_svgf_surface", "vol_wrls",
                                                             "vol_rae_gbuffer"]
    assert method_spec(cfg, "vol_wrls").role == "volume" and method_spec(cfg, "vol_wrls").spp == (2,)
    runs = {(run.spec.id, run.spp): run.not_run for run in volume_runs(cfg)}
    assert runs[("vol_noisy", 2)] == "" and runs[("vol_wrls", 2)] == ""
    assert "'normal'" in runs[("vol_svgf_surface", 2)]                   # surface SVGF reads normals
    # The G-buffer RAE reads normals and roughness, which volumetric clips store as zeros.
    assert "'gbuffer.normal', which volumetric clips store as zeros" in runs[("vol_rae_gbuffer", 2)]
    assert "needs 8 sample layers, the clips have 4" in runs[("vol_noisy", 8)]
    assert ("vol_wrls", 8) not in runs
    assert volume_test_scene_ids(cfg) == ["vol_test_camera_000", "vol_test_camera_001", "vol_test_light_000",
                                          "vol_test_light_001"]


def test_volume_row_ids_must_be_unique_and_their_spp_denoised() -> None:
    cfg = volume_config(rows=[{"id": "noisy", "method": "noisy"}, {"id": "vol_a", "method": "wrls"},
                              {"id": "vol_a", "method": "rls", "spp": [3]}])
    problems = "\n".join(volume_problems(cfg))
    assert "'noisy', which an evaluation row" in problems
    assert "'vol_a' more than once" in problems
    assert "'volumes.rows[2].spp'" in problems and "[3]" in problems
    cfg = volume_config(rows=[{"id": "vol_rae", "method": "rae_color", "params": {"model": "no_such_model"}}])
    assert "row 'vol_rae' uses model 'no_such_model', which training does not define" in "\n".join(volume_problems(cfg))


# --- decisions over the clips ---------------------------------------------------------------------------------

def synthetic(cfg: dict, diffs: list[float], rows: dict[tuple[str, int], list[float]] | None = None,
              ran: set[str] | None = None) -> SimpleNamespace:
    """Results with volumes whose per-clip PSNR of wrls is noisy's + 3 + diffs, svgf's = wrls's - diffs, and TRMAE
    of wrls = svgf's - diffs (so every C4.1 part has the paired differences ``diffs`` on the claimed side)."""
    scenes = [f"vol_test_s_{i:03d}" for i in range(len(diffs))]
    base = np.linspace(20.0, 26.0, len(diffs))
    per_scene = []
    values = rows or {}
    for spp in cfg["volumes"]["denoise_spp"]:
        table = {"vol_noisy": base + spp, "vol_wrls": base + spp + 3.0 + np.array(diffs)}
        table["vol_svgf"] = table["vol_wrls"] - np.array(diffs)
        for (row, s), v in values.items():
            if s == spp:
                table[row] = np.asarray(v)
        for spec in volume_method_specs(cfg):   # seed and half-budget rows repeat their row unless given
            source = spec.budget_of or spec.seed_of
            if source in table and spec.id not in table:
                table[spec.id] = table[source]
        for row, psnr in table.items():
            trmae = 1.0 - (np.array(diffs) if row == "vol_wrls" else 0.0)
            for scene, p, t in zip(scenes, psnr, np.broadcast_to(trmae, psnr.shape)):
                per_scene.append({"method_id": row, "spp": spp, "scene": scene, "scenario": "camera", "psnr": p,
                                  "trmae": t})
    specs = volume_method_specs(cfg)
    ran = ran if ran is not None else {spec.id for spec in specs}
    runs = [{"id": spec.id, "method": spec.method, "spp": spp, "status": "ran" if spec.id in ran else "not run",
             "reason": "" if spec.id in ran else "not run (removed by the test)"}
            for spec in specs for spp in spec.spp]
    volumes = VolumeResults(specs, scenes, {scene: "camera" for scene in scenes}, runs, pd.DataFrame(),
                            pd.DataFrame(per_scene))
    return SimpleNamespace(cfg=cfg, volumes=volumes)


@pytest.mark.parametrize("diffs, expected", [(CLEAR, REPRODUCED), (AGAINST, CONTRADICTED), (SPANNING, INCONCLUSIVE),
                                             (CLEAR[:2], INCONCLUSIVE)])
def test_c41_is_decided_over_the_volumetric_clips(diffs, expected) -> None:
    decision = iglesias2022.decide_c41_volumes(synthetic(volume_config(), diffs))
    assert decision.verdict == expected
    assert [part.quantity for part in decision.parts] == ["psnr", "trmae"]
    assert all(part.n == len(diffs) for part in decision.parts)
    np.testing.assert_allclose(decision.parts[0].diffs, diffs)
    np.testing.assert_allclose(decision.parts[1].diffs, -np.array(diffs))
    # Our clips are box-filtered, the paper's Gaussian-filtered (§6): the verdict is labelled as this pipeline's.
    assert "volumetric clips" in decision.note and "box pixel filter" in decision.note
    assert "separable Gaussian" in decision.note and "this pipeline only" in decision.note


def test_c41_without_a_volume_svgf_row_or_without_volumes_is_not_run() -> None:
    cfg = volume_config()
    decision = iglesias2022.decide_c41_volumes(synthetic(cfg, CLEAR, ran={"vol_noisy", "vol_wrls", "vol_rae"}))
    assert decision.verdict == NOT_RUN and "svgf_volume" in decision.not_run and "removed by the test" in decision.not_run
    decision = iglesias2022.decide_c41_volumes(SimpleNamespace(cfg=cfg, volumes=None))
    assert decision.verdict == NOT_RUN and "no volumetric clips" in decision.not_run


def test_c43_needs_a_volume_rae_and_then_both_halves() -> None:
    cfg = volume_config()
    cfg["training"].update(seeds=3, half_budget=True)   # three seeds and the half budget (each repeats vol_rae here)
    noisy = {s: np.linspace(20.0, 26.0, 4) + s for s in (1, 2, 4)}
    # RAE 5 dB above the input at 1 spp, 5 - d at 4 spp: its gain shrinks by d.
    rae = {("vol_rae", 1): noisy[1] + 5.0, ("vol_rae", 2): noisy[2] + 5.0,
           ("vol_rae", 4): noisy[4] + 5.0 - np.array(CLEAR)}
    decision = iglesias2022.decide_c43_volumes(synthetic(cfg, CLEAR, rae))
    assert decision.verdict == REPRODUCED and len(decision.parts) == 4
    growing = {key: noisy[key[1]] + (5.0 if key[1] != 4 else 6.0) for key in rae}
    assert iglesias2022.decide_c43_volumes(synthetic(cfg, CLEAR, growing)).verdict == CONTRADICTED
    # The colour-only RAE row (method rae_color, as the default config has it) is the RAE of C4.3; one that did
    # not run is named.
    decision = iglesias2022.decide_c43_volumes(synthetic(cfg, CLEAR, rae, ran={"vol_noisy", "vol_wrls", "vol_svgf"}))
    assert decision.verdict == NOT_RUN and "vol_rae @ 1 spp" in decision.not_run
    # One training seed: the learned part is not decided, and the note says why.
    decision = iglesias2022.decide_c43_volumes(synthetic(volume_config(), CLEAR, rae))
    assert decision.verdict == INCONCLUSIVE and decision.parts[-1].outcome == REPRODUCED
    assert "1 training seed(s), fewer than the 3" in decision.seed_note()
    no_rae = volume_config(rows=[{"id": "vol_noisy", "method": "noisy"}, {"id": "vol_wrls", "method": "wrls"}])
    decision = iglesias2022.decide_c43_volumes(synthetic(no_rae, CLEAR))
    assert decision.verdict == NOT_RUN and "colour-only" in decision.not_run


def test_scenario_table_lists_rows_that_did_not_run_with_the_reason() -> None:
    res = synthetic(volume_config(), CLEAR, ran={"vol_noisy", "vol_wrls", "vol_svgf"})
    for column in ("ssim", "flip", "tpsnr"):
        res.volumes.per_scene[column] = 0.5
    table = iglesias2022.volume_scenario_table(res).set_index("row")
    assert table.loc["vol_rae", "note"] == "not run (removed by the test)"
    assert table.loc["vol_wrls", "camera: PSNR (dB, frame mean)"] != ""
    assert table.loc["vol_wrls", "note"] == ""


# --- collecting from files -----------------------------------------------------------------------------------

def _write_outputs(cfg: dict, root: Path, digest_of=None) -> None:
    lineage = Lineage(cfg)
    for run in volume_runs(cfg):
        if not run.runnable:
            continue
        for scene in volume_test_scene_ids(cfg):
            csv = volume_metrics_csv(root, run.spec.id, scene, run.spp)
            csv.parent.mkdir(parents=True, exist_ok=True)
            pd.DataFrame({"frame": [0, 1], "psnr": [20.0 + run.spp, 22.0], "ssim": 0.5, "rmse": 0.1, "relmse": 0.1,
                          "smape": 0.1, "flip": 0.1, "tpsnr": [np.nan, 20.0], "trmae": [np.nan, 1.0],
                          "camera_cut": False, "nonfinite_output": 0, "reference_psnr_halves": 40.0}).to_csv(csv, index=False)
            metrics = lineage.metrics(run.spec, scene, run.spp)
            csv.with_suffix(".json").write_text(json.dumps({DIGEST_KEY: digest_of(metrics) if digest_of else metrics}))
            denoised = volume_denoised_dir(root, run.spec.id, scene, run.spp)
            denoised.mkdir(parents=True, exist_ok=True)
            (denoised / TIMING_FILE).write_text(json.dumps({DIGEST_KEY: lineage.denoised(run.spec, scene, run.spp)}))


def test_collect_reads_every_clip_and_refuses_other_settings(tmp_path) -> None:
    cfg = volume_config(n_test=1, rows=[{"id": "vol_noisy", "method": "noisy"}, {"id": "vol_wrls", "method": "wrls"}],
                        denoise_spp=[2])
    _write_outputs(cfg, tmp_path)
    ledger = DigestLedger()
    volumes = collect_volumes(cfg, tmp_path, ledger)
    ledger.raise_if_mixed(cfg, tmp_path)
    assert volumes.scenes == ["vol_test_camera_000", "vol_test_light_000"]
    assert volumes.ran("vol_wrls", 2) and volumes.row_of("wrls") == "vol_wrls"
    assert set(volumes.per_scene.scenario) == {"camera", "light"}
    assert volumes.scene_values("vol_noisy", 2, "psnr").tolist() == [22.0, 22.0]     # frames 22 and 22
    # A missing clip: the row is not run, naming it.
    volume_metrics_csv(tmp_path, "vol_wrls", "vol_test_light_000", 2).unlink()
    volumes = collect_volumes(cfg, tmp_path, DigestLedger())
    assert not volumes.ran("vol_wrls", 2) and "vol_test_light_000" in volumes.reason("vol_wrls", 2)
    # Outputs of other settings are never combined.
    _write_outputs(cfg, tmp_path, digest_of=lambda digest: "0" * len(digest))
    ledger = DigestLedger()
    collect_volumes(cfg, tmp_path, ledger)
    with pytest.raises(SettingsMismatchError):
        ledger.raise_if_mixed(cfg, tmp_path)
    cfg["volumes"]["enabled"] = False
    assert collect_volumes(cfg, tmp_path, DigestLedger()) is None


def test_c42_is_decided_on_the_spike_scenario_over_the_clips() -> None:
    rows = [{"id": "vol_noisy", "method": "noisy"}, {"id": "vol_wrls", "method": "wrls", "robustness": True},
            {"id": "vol_rls", "method": "rls", "robustness": True}]
    cfg = volume_config(rows=rows, denoise_spp=[2])
    from denoisers.jobs.volumes import volume_robustness_runs

    assert [(run.spec.id, run.spp) for run in volume_robustness_runs(cfg)] == [("vol_wrls", 2), ("vol_rls", 2)]
    res = synthetic(cfg, CLEAR, {("vol_rls", 2): np.linspace(20.0, 26.0, 4) + 2.0})
    scenes = res.volumes.scenes
    decision = iglesias2022.decide_c42_volumes(res)
    assert decision.verdict == NOT_RUN and "robustness: true" in decision.not_run
    # Spiked PSNR of wRLS above RLS's by CLEAR; its clean PSNR (base + 5 + CLEAR) is 3 + CLEAR above RLS's (base + 2),
    # so its drop is 3 dB larger: the robustness part holds, the drop part is contradicted.
    clean_wrls = res.volumes.scene_values("vol_wrls", 2, "psnr")
    res.volumes.robustness = pd.DataFrame(
        [{"method_id": "vol_wrls", "scene": s, "spp": 2, "psnr_spiked": 15.0 + d} for s, d in zip(scenes, CLEAR)]
        + [{"method_id": "vol_rls", "scene": s, "spp": 2, "psnr_spiked": 15.0} for s in scenes])
    decision = iglesias2022.decide_c42_volumes(res)
    np.testing.assert_allclose(decision.parts[0].diffs, CLEAR)
    np.testing.assert_allclose(decision.parts[1].diffs, 3.0)
    assert decision.parts[0].outcome == REPRODUCED and decision.parts[1].outcome == CONTRADICTED
    assert decision.verdict == CONTRADICTED and "this pipeline only" in decision.note
    assert (clean_wrls.index == pd.Index(scenes)).all()


def test_dark_half_brightness_is_output_over_reference_where_the_reference_is_dark(tmp_path) -> None:
    """A row that doubles every dark pixel and keeps the bright ones reads 2; one that returns the reference, 1."""
    from denoisers.evaluate import write_radiance_exr
    from scenegen.channels import reference_channels
    from scenegen.exr import write_exr

    cfg = volume_config(n_test=1, rows=[{"id": "vol_same", "method": "noisy"}, {"id": "vol_double", "method": "noisy"}],
                        denoise_spp=[2])
    res = synthetic(cfg, [1.0, 1.0])
    res.volumes.scenes = volume_test_scene_ids(cfg)
    res.results_dir = tmp_path
    rng = np.random.default_rng(0)
    for scene in res.volumes.scenes:
        for t in range(2):
            reference = rng.uniform(0.1, 1.0, (3, 6, 5)).astype(np.float32)
            reference[:, :3] *= 10.0                                     # the top rows are the bright half
            folder = tmp_path / "renders" / scene / "reference" / "chunk_000"
            folder.mkdir(parents=True, exist_ok=True)
            write_exr(folder / f"frame_{t:04d}.exr", reference_channels(
                {"radiance": reference, "radiance_half0": reference, "radiance_half1": reference}),
                attributes={"mcdn_meta": json.dumps({"scene": scene, "frame": t})})
            doubled = reference.copy()
            doubled[:, 3:] *= 2.0
            for row, image in (("vol_same", reference), ("vol_double", doubled)):
                out = tmp_path / "volumes" / "denoised" / row / scene / "spp2"
                out.mkdir(parents=True, exist_ok=True)
                write_radiance_exr(out / f"frame_{t:04d}.exr", image)
    table = iglesias2022.volume_brightness_table(res).set_index("row")
    assert float(table.loc["vol_same", "dark half: output / reference @ 2 spp"]) == pytest.approx(1.0)
    assert float(table.loc["vol_double", "dark half: output / reference @ 2 spp"]) == pytest.approx(2.0, abs=1e-3)


# --- SVGF on volumes ------------------------------------------------------------------------------------------
def _volume_frame(seed: int, gbuffer_depth: torch.Tensor, albedo: float = 0.5) -> Frame:
    """A 2-spp 24x24 volumetric frame: radiance 1 on the left half and 1.6 on the right with per-sample noise
    (std 0.5, so luminance alone cannot tell the halves apart), per-sample depths of random scatter events,
    a per-sample albedo, zero motion and full validity."""
    generator = torch.Generator().manual_seed(seed)
    mean = torch.ones(1, 3, 24, 24)
    mean[..., 12:] = 1.6
    radiance = (mean + 0.5 * torch.randn(2, 3, 24, 24, generator=generator)).clamp_min(0.0)
    return Frame(samples={"radiance": radiance, "albedo": torch.full((2, 3, 24, 24), albedo),
                          "depth": 10.0 * torch.rand(2, 1, 24, 24, generator=generator)},
                 pixel={"motion": torch.zeros(2, 24, 24), "valid": torch.ones(1, 24, 24),
                        "gbuffer.depth": gbuffer_depth.clone()}, index=seed)


def test_svgf_volume_stops_at_the_reprojection_depth_and_does_not_demodulate() -> None:
    """The halves lie at reprojection depths 1 and 5: SVGF on volumes keeps them apart at the boundary (each
    half's known mean), while with one depth for both it blurs across; the albedo buffer changes nothing."""
    from denoisers import registry

    step = torch.ones(1, 24, 24)
    step[..., 12:] = 5.0
    flat = torch.ones(1, 24, 24)

    def boundary_error(gbuffer_depth: torch.Tensor, albedo: float = 0.5) -> tuple[float, torch.Tensor]:
        method = registry.build("svgf_volume")
        method.reset()
        outputs = [method.denoise(_volume_frame(t, gbuffer_depth, albedo)) for t in range(8)]
        last = outputs[-1][:, 2:-2]                     # (3, 20, 24), away from the top and bottom borders
        left, right = last[..., 10:12].mean(), last[..., 12:14].mean()   # the two columns each side of the edge
        return float(abs(left - 1.0) + abs(right - 1.6)), outputs[-1]

    with_edge, output = boundary_error(step)
    without_edge, _ = boundary_error(flat)
    assert with_edge < 0.12 < without_edge
    assert torch.equal(boundary_error(step, albedo=0.05)[1], output)
