"""End-to-end run of the smoke configuration through Snakemake with the real renderer and denoisers.

One copy of the workflow (Snakefile, workflow/, config/, examples/) in a temporary directory is run twice:
first the stage target `scenes` alone, then the default target (renders, every configured method on
the test scene, metrics, the robustness scenario and the report). That checks the stage target on a
fresh tree, that the full run reuses the scenes, the complete dataset and the evaluation outputs in
a single DAG. The run uses the smoke config plus the README's example XML scene (custom_spheres_room, as
in the default config), so one test scene and one external scene are evaluated. Its outputs go to its
output_dir (results/smoke); afterwards a second config (seed 7, its own output_dir) runs `scenes` next to
it, which must leave the smoke experiment untouched.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from xml.etree import ElementTree
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from PIL import Image

from denoisers.adaptive import SAMPLE_MAPS_FILE
from denoisers.evaluate import (ALL_METRICS, MAPS_FILE, ROBUSTNESS_SUMMARY, TIMING_FILE, denoised_dir, method_spec,
                                metrics_csv, metrics_sidecar, plan_runs, robustness_dir, robustness_runs)
from denoisers.experiment import DIGEST_KEY, Lineage
# Aliased: pytest would collect a module-level name starting with `test_` as a test.
from denoisers.evaluate import evaluated_scene_ids
from denoisers.report import report_outputs
from denoisers.report.verdicts import INCONCLUSIVE, NOT_RUN
from denoisers.reproductions import all_claims
from denoisers.training.models import MODEL_FILES, capacity_model_ids, model_dir, model_specs
from scenegen.catalog import (CUSTOM_PREFIX, chunk_count, chunk_frames, scene_frame_count, scene_ids,
                              scene_reference_spp, volume_scene_ids)
from scenegen.config import load_config
from scenegen.channels import ALL, REFERENCE_BUFFERS, SAMPLE_BUFFERS
from scenegen.dataset import REQUIRED_REFERENCE_BUFFERS, load_clip

REPO_ROOT = Path(__file__).resolve().parents[1]
# Every test here shares one smoke DAG run (minutes): excluded by `-m "not slow"`.
pytestmark = pytest.mark.slow
SNAKEMAKE = Path(sys.executable).parent / "snakemake"
SMOKE_CONFIG = "config/smoke.yaml"
# The smoke config with the README's example XML scene added (written into the work directory).
PIPELINE_CONFIG = "smoke-external.yaml"
EXTERNAL_SCENE = {"name": "spheres_room", "xml": "examples/scenes/spheres_room/scene.xml", "frames": 4,
                  "camera": {"path": "dolly"}}
# A user's own method (issue 49): one module in the work directory's copy of denoisers/methods/ and its config
# rows (evaluation.methods; the smoke config narrows the atlas with stability.rows, so the row is listed there).
USER_MODULE = "user_box3"
USER_ROW = {"id": "my_box", "method": "user_box3"}
USER_METHOD_SOURCE = '''"""A user's method written outside the harness: a 3x3 box filter of the sample mean."""
import torch

from denoisers.filters import sanitize
from denoisers.registry import Denoiser, Frame, register


@register("user_box3", inputs=("radiance",), description="a user's 3x3 box filter of the sample mean")
class UserBox3(Denoiser):
    """Mean (3, H, W) of the (sanitised) samples, averaged over each pixel's 3x3 neighbourhood (edges replicated)."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        mean = sanitize(frame.samples["radiance"]).mean(dim=0)
        padded = torch.nn.functional.pad(mean[None], (1, 1, 1, 1), mode="replicate")
        return torch.nn.functional.avg_pool2d(padded, 3, stride=1)[0]
'''
# The second experiment: the smoke config with another seed and its own folder.
SEED7_CONFIG, SEED7_OUT = "seed7.yaml", "results/seed7"
JOB_RULES = ("generate_scene", "render_noisy", "render_reference")
# results/benchmarks/{folder}/{method}/{scene}/spp{spp}.tsv of the evaluation rules: folder -> which runs.
EVALUATION_BENCHMARKS = {"denoise": "evaluation", "evaluate": "evaluation", "robustness": "robustness"}
# A guard against runaway outputs (e.g. a full-resolution dump per job), not a tuned number: the 183-job smoke tree
# holds about 53 MB (2026-12-01; 21 of them MB of resumable training checkpoints in models/.work, 3.4 MB for the
# volumetric clips added that day), so 60 MB leaves room for a few rows more.
MAX_RESULTS_BYTES = 60 * 1024**2
# Snakemake marks every directory() output with this file; it is not part of the data.
SNAKEMAKE_MARKER = ".snakemake_timestamp"
# Generous: the machine may be shared; a hung job should fail the test rather than block forever.
SNAKEMAKE_TIMEOUT_S = 2400


def _snakemake(workdir: Path, *args: str, config: str = PIPELINE_CONFIG) -> subprocess.CompletedProcess:
    """Run the venv's snakemake in ``workdir`` with the venv first on PATH (the rules call `python`)."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    # conftest's init_mitsuba may have set DRJIT_LIBLLVM_PATH in this process; dict(os.environ) passes it on.
    # Targets and flags go first: --configfile takes several values and would swallow a target.
    return subprocess.run([str(SNAKEMAKE), *args, "--cores", "2", "--configfile", config],
                          cwd=workdir, env=env, capture_output=True, text=True, timeout=SNAKEMAKE_TIMEOUT_S)


def _check_ok(result: subprocess.CompletedProcess, what: str, workdir: Path) -> None:
    if result.returncode != 0:
        logs = "\n".join(f"--- {log}\n{log.read_text()[-3000:]}"
                         for log in sorted((workdir / "results").rglob("logs/**/*.log")))
        pytest.fail(f"{what} exited with {result.returncode}\n{result.stdout[-5000:]}\n"
                    f"{result.stderr[-5000:]}\n{logs}")


def _tree(root: Path) -> dict[str, int]:
    """{relative path: mtime_ns} of every file below ``root``."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


@dataclass
class PipelineRun:
    workdir: Path
    cfg: dict
    after_scenes: dict[str, int]      # the experiment folder's tree after `snakemake scenes`
    full: subprocess.CompletedProcess
    dry_rerun: subprocess.CompletedProcess
    after_full: dict[str, int]        # the experiment folder's tree after the full run
    after_seed7: dict[str, int]       # the same, after the seed-7 config ran `scenes` into its own folder

    @property
    def results(self) -> Path:
        """The smoke experiment's folder (its output_dir)."""
        return self.workdir / self.cfg["output_dir"]

    def runs(self, kind: str = "evaluation") -> list:
        """Runnable (method, spp) runs of the evaluation or of the robustness scenario."""
        runs = plan_runs(self.cfg) if kind == "evaluation" else robustness_runs(self.cfg)
        return [run for run in runs if run.runnable]


def _register_user_method(path: Path) -> None:
    """Import the user's module in this process too (the tests plan runs and load the config with it)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"tests_pipeline_{USER_MODULE}", path)
    spec.loader.exec_module(importlib.util.module_from_spec(spec))


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory) -> PipelineRun:
    from denoisers import registry

    workdir = tmp_path_factory.mktemp("pipeline")
    shutil.copy2(REPO_ROOT / "Snakefile", workdir / "Snakefile")
    for folder in ("workflow", "config", "examples"):
        shutil.copytree(REPO_ROOT / folder, workdir / folder)
    # The jobs run `python -m denoisers` in the work directory, so they import this copy with the user's module.
    shutil.copytree(REPO_ROOT / "denoisers", workdir / "denoisers", ignore=shutil.ignore_patterns("__pycache__"))
    user_module = workdir / "denoisers" / "methods" / f"{USER_MODULE}.py"
    user_module.write_text(USER_METHOD_SOURCE)
    _register_user_method(user_module)
    try:
        yield _run_pipeline(workdir)
    finally:
        registry._REGISTRY.pop(USER_ROW["method"], None)


def _run_pipeline(workdir: Path) -> PipelineRun:
    smoke = yaml.safe_load((workdir / SMOKE_CONFIG).read_text())
    smoke["evaluation"]["methods"].append(USER_ROW)
    smoke["stability"]["rows"].append(USER_ROW["id"])
    (workdir / PIPELINE_CONFIG).write_text(yaml.safe_dump(smoke | {"extra_scenes": [EXTERNAL_SCENE]}))
    cfg = load_config(workdir / PIPELINE_CONFIG)
    results = workdir / cfg["output_dir"]
    scenes_run = _snakemake(workdir, "scenes")
    _check_ok(scenes_run, "snakemake scenes", workdir)
    after_scenes = _tree(results)
    assert not (results / "renders").exists(), "stage target `scenes` rendered frames"

    full = _snakemake(workdir)
    _check_ok(full, "snakemake (default target)", workdir)
    after_full = _tree(results)
    seed7 = yaml.safe_load((workdir / PIPELINE_CONFIG).read_text()) | {"seed": 7, "output_dir": SEED7_OUT}
    (workdir / SEED7_CONFIG).write_text(yaml.safe_dump(seed7))
    _check_ok(_snakemake(workdir, "scenes", config=SEED7_CONFIG), "snakemake scenes (seed 7)", workdir)
    dry_rerun = _snakemake(workdir, "-n")
    return PipelineRun(workdir, cfg, after_scenes, full, dry_rerun, after_full, _tree(results))


def test_scenes_stage_target_produces_only_scenes(pipeline: PipelineRun) -> None:
    scenes = scene_ids(pipeline.cfg)
    # Two training scenes (one held out for validation), one test scene and the example XML scene.
    assert scenes == ["train_000", "train_001", "test_000", "custom_spheres_room"]
    produced = {Path(path).parts[0] for path in pipeline.after_scenes}
    # Besides scenes, a stage run may only leave bookkeeping (resolved config, logs, benchmarks).
    assert "scenes" in produced and "renders" not in produced
    assert produced <= {"scenes", ".config", "logs", "benchmarks"}, produced
    for scene in scenes:
        assert f"scenes/{scene}/manifest.json" in pipeline.after_scenes
    assert not any(path.startswith("benchmarks/render") for path in pipeline.after_scenes)


def test_full_run_reuses_the_scenes(pipeline: PipelineRun) -> None:
    scene_files = {path: mtime for path, mtime in _tree(pipeline.results).items() if path.startswith("scenes/")}
    before = {path: mtime for path, mtime in pipeline.after_scenes.items() if path.startswith("scenes/")}
    # The stage target `scenes` builds the procedural and external scenes; the full run adds the stability
    # scenarios (stab_*, target `stability`) with the control clips of the animated ones (stab_*__still) and the
    # volumetric clips (vol_*, target `volumes`) and must leave every scene that existed untouched.
    from scenegen.scenarios import stability_control_ids

    assert {path: scene_files.get(path) for path in before} == before, \
        "the full run regenerated scenes that were already up to date"
    added = {path.split("/")[1] for path in set(scene_files) - set(before)}
    assert added == ({f"stab_{name}" for name in pipeline.cfg["stability"]["scenarios"]}
                     | set(stability_control_ids(pipeline.cfg)) | set(volume_scene_ids(pipeline.cfg))), added
    assert stability_control_ids(pipeline.cfg) == [f"stab_{name}__still" for name in
                                                   pipeline.cfg["stability"]["scenarios"]]
    assert volume_scene_ids(pipeline.cfg) == ["vol_test_camera_000", "vol_train_camera_000", "vol_train_camera_001"]


def test_every_scene_has_manifest_and_all_chunks(pipeline: PipelineRun) -> None:
    cfg = pipeline.cfg
    for scene in scene_ids(cfg):
        manifest_path = pipeline.results / "scenes" / scene / "manifest.json"
        manifest = json.loads(manifest_path.read_text())
        assert manifest["n_frames"] == scene_frame_count(cfg, scene)
        if scene.startswith(CUSTOM_PREFIX):  # the XML's shapes, as authored, with what was substituted
            # Every <shape> the XML authors (counted here with ElementTree, not with the importer's parser).
            authored = ElementTree.parse(REPO_ROOT / EXTERNAL_SCENE["xml"]).getroot().iter("shape")
            assert manifest["kind"] == "custom" and len(manifest["shapes"]) == len(list(authored))
            assert manifest["render"] == {"max_depth": 6, "rr_depth": 5, "hide_emitters": True, "filter": "box"}
            assert {row["what"] for row in manifest["substitutions"]} == {
                "integrator", "resolution", "sampler", "camera"}
        else:
            assert list((manifest_path.parent / "meshes").glob("*.ply")), f"{scene}: no meshes"
        for kind in ("noisy", "reference"):
            kind_dir = pipeline.results / "renders" / scene / kind
            expected_chunks = {f"chunk_{c:03d}" for c in range(chunk_count(cfg, scene))}
            assert {p.name for p in kind_dir.iterdir()} == expected_chunks
            for chunk in range(chunk_count(cfg, scene)):
                chunk_dir = kind_dir / f"chunk_{chunk:03d}"
                expected = {f"frame_{t:04d}.{ext}" for t in chunk_frames(cfg, scene, chunk) for ext in ("exr", "json")}
                # Exact equality: also rejects leftover partial files inside a finished chunk.
                assert {p.name for p in chunk_dir.iterdir()} - {SNAKEMAKE_MARKER} == expected, chunk_dir


def test_clips_load_with_configured_shapes_and_sane_metadata(pipeline: PipelineRun) -> None:
    render = pipeline.cfg["render"]
    spp, height, width = render["spp"], render["height"], render["width"]
    for scene in scene_ids(pipeline.cfg):
        n_frames = scene_frame_count(pipeline.cfg, scene)
        clip = load_clip(pipeline.results / "renders" / scene)  # also rejects non-finite values
        assert clip.scene == scene
        assert clip.frames == list(range(n_frames))
        assert set(clip.samples) == set(ALL)         # a surface scene's buffers (the volume ones are vol_* only)
        for buffer, array in clip.samples.items():
            layers = spp + render["extra_radiance_spp"] if buffer == "radiance" else spp
            assert array.shape == (n_frames, layers, len(SAMPLE_BUFFERS[buffer]), height, width), buffer
            assert np.isfinite(array).all(), buffer
        assert clip.motion.shape == (n_frames, 2, height, width)
        # render.reference_integrator: path stores radiance and its halves; features adds the feature means.
        expected = (REFERENCE_BUFFERS if render["reference_integrator"] == "features" else REQUIRED_REFERENCE_BUFFERS)
        assert set(clip.reference) == set(expected)
        for buffer, array in clip.reference.items():
            assert array.shape == (n_frames, len(REFERENCE_BUFFERS[buffer]), height, width), buffer
            assert np.isfinite(array).all(), buffer
        assert clip.reference["radiance"].shape == (n_frames, 3, height, width)
        # Not a black clip: the generator redraws scenes whose preview is too dark.
        assert clip.reference["radiance"].mean() > 0

        n_values = n_frames * spp * height * width
        for t, meta in enumerate(clip.meta):
            assert (meta["scene"], meta["frame"], meta["width"], meta["height"]) == (scene, t, width, height)
            assert isinstance(meta["nonfinite_total"], int)
            assert meta["nonfinite_total"] == sum(meta["nonfinite"].values())
            assert meta["nonfinite_total"] < 1e-3 * n_values  # replaced NaN/inf must stay rare
            assert np.isfinite(meta["samples_per_s"]) and meta["samples_per_s"] > 0
        for t, meta in enumerate(clip.reference_meta):
            assert meta["frame"] == t and meta["spp"] == scene_reference_spp(pipeline.cfg, scene)
            assert np.isfinite(meta["psnr_halves"]), meta["psnr_halves"]
            assert isinstance(meta["nonfinite_total"], int)


def test_benchmarks_exist_for_every_job(pipeline: PipelineRun) -> None:
    bench = pipeline.results / "benchmarks"
    expected = []
    for scene in scene_ids(pipeline.cfg):
        expected.append(bench / "generate_scene" / f"{scene}.tsv")
        for chunk in range(chunk_count(pipeline.cfg, scene)):
            expected += [bench / rule / scene / f"chunk_{chunk:03d}.tsv" for rule in JOB_RULES[1:]]
    for folder, kind in EVALUATION_BENCHMARKS.items():      # one job per row (denoisers.jobs.rows)
        expected += [bench / folder / f"{row}.tsv" for row in {run.spec.id for run in pipeline.runs(kind)}]
    expected += [bench / "train" / f"{spec.id}.tsv" for spec in model_specs(pipeline.cfg)]
    expected += [bench / "build_report.tsv", bench / "time_methods.tsv", bench / "time_training.tsv"]
    for path in expected:
        assert path.is_file(), f"missing benchmark {path}"
        header, *rows = path.read_text().strip().splitlines()
        assert header.split("\t")[0] == "s" and len(rows) >= 1, path
        assert float(rows[0].split("\t")[0]) > 0, path


def test_results_are_small_and_leave_no_temporaries(pipeline: PipelineRun) -> None:
    total = sum(p.stat().st_size for p in pipeline.results.rglob("*") if p.is_file())
    assert total < MAX_RESULTS_BYTES, f"results/ holds {total / 1024**2:.1f} MB"
    for stage in ("renders", "scenes", "denoised", "metrics", "robustness", "tables", "figures"):
        leftovers = [p for p in (pipeline.results / stage).rglob("*") if p.name.startswith(".") and "tmp" in p.name]
        assert not leftovers, f"temporary files left behind: {leftovers}"


def test_second_run_has_nothing_to_do(pipeline: PipelineRun) -> None:
    assert pipeline.dry_rerun.returncode == 0, pipeline.dry_rerun.stderr
    output = pipeline.dry_rerun.stdout + pipeline.dry_rerun.stderr
    assert "Nothing to be done" in output, output[-3000:]


def test_every_planned_run_has_denoised_frames_and_metrics(pipeline: PipelineRun) -> None:
    runs = pipeline.runs()
    # The smoke config renders enough layers for every configured (method, spp), and every trained
    # ablation variant is evaluated at its ablation's own spp, if it sets one, or else evaluation.ablation_spp.
    own_spp = {a["id"]: a["spp"] for a in pipeline.cfg["training"]["ablations"] if "spp" in a}
    variant_runs = {(spec.id, s) for spec in model_specs(pipeline.cfg) if spec.ablation
                    for s in own_spp.get(spec.ablation, pipeline.cfg["evaluation"]["ablation_spp"])}
    evaluated_spp = pipeline.cfg["evaluation"]["spp"]
    assert len(runs) == (sum(len(row.get("spp") or evaluated_spp) for row in pipeline.cfg["evaluation"]["methods"])
                         + len(variant_runs))
    assert variant_runs <= {(run.spec.id, run.spp) for run in runs}
    for scene in evaluated_scene_ids(pipeline.cfg):
        frames = list(range(scene_frame_count(pipeline.cfg, scene)))
        for run in runs:
            folder = denoised_dir(pipeline.results, run.spec.id, scene, run.spp)
            timing = json.loads((folder / TIMING_FILE).read_text())
            # Adaptive rows (the Hasselgren variants) also store their per-frame sample maps, and rows with
            # diagnostic maps (the temporal AFN models: lambda) their maps.
            expected = ({f"frame_{t:04d}.{ext}" for t in frames for ext in ("exr", "png")} | {TIMING_FILE}
                        | ({SAMPLE_MAPS_FILE} if timing.get("adaptive") else set())
                        | ({MAPS_FILE} if timing.get("maps") else set()))
            assert {p.name for p in folder.iterdir()} - {SNAKEMAKE_MARKER} == expected, folder
            assert timing["spp"] == run.spp and timing["threads"] == pipeline.cfg["evaluation"]["threads"]
            assert timing["mean_seconds"] > 0 and timing["nonfinite_outputs"] == 0, (folder, timing)
            assert timing["out_of_range_outputs"] == sum(timing["out_of_range_outputs_per_frame"]), folder
            table = pd.read_csv(metrics_csv(pipeline.results, run.spec.id, scene, run.spp))
            assert list(table["frame"]) == frames
            assert set(ALL_METRICS) <= set(table.columns)
            assert np.isfinite(table["psnr"]).all() and (table["psnr"] > 0).all(), (run, table)
    assert not list((pipeline.results / "denoised").glob("*/train_*")), "a training scene was denoised"
    assert json.loads((denoised_dir(pipeline.results, "afn", "test_000", 2) / TIMING_FILE).read_text())["maps"] == \
        ["lambda"]


def test_robustness_outputs_stay_finite(pipeline: PipelineRun) -> None:
    for scene in evaluated_scene_ids(pipeline.cfg):
        for run in pipeline.runs("robustness"):
            summary = json.loads((robustness_dir(pipeline.results, run.spec.id, scene, run.spp)
                                  / ROBUSTNESS_SUMMARY).read_text())
            assert summary["injected"]["spikes"] > 0 and summary["nonfinite_inputs"] > 0, summary
            assert summary["nonfinite_outputs"] == 0, f"{run.spec.id} produced non-finite output under spikes"


def test_report_has_tables_figures_and_claims(pipeline: PipelineRun) -> None:
    outputs = report_outputs(pipeline.cfg, root=str(pipeline.results))
    for path in (path for group in outputs.values() for path in group):
        assert Path(path).is_file() and Path(path).stat().st_size > 0, path
    assert list((pipeline.results / "tables").glob("*.csv"))
    with Image.open(pipeline.results / "figures" / "quality_vs_speed.png") as chart:
        assert chart.width > 100 and chart.height > 100

    # The colour balance covers every (row, spp) that ran, the ablation variants at evaluation.ablation_spp too.
    balance = pd.read_csv(pipeline.results / "tables" / "color_balance.csv")
    assert {(r.method_id, r.spp) for r in balance.itertuples()} == {(run.spec.id, run.spp) for run in pipeline.runs()}
    assert set(balance.loc[balance.role == "ablation", "method_id"]) == {
        spec.id for spec in model_specs(pipeline.cfg) if spec.ablation}

    claims = pd.read_csv(pipeline.results / "tables" / "claims.csv").set_index("claim")
    assert list(claims.index) == [claim.id for claim in all_claims()]
    # The smoke config evaluates one test scene and the example XML scene at 1, 2 and 4 spp (most rows at 1
    # and 2 only): every claim whose rows exist is decided from n = 2 paired differences, fewer than the 3 units
    # a verdict needs (inconclusive); C4.3s needs wRLS at 4 spp, which the smoke config does not run.
    assert evaluated_scene_ids(pipeline.cfg) == ["test_000", "custom_spheres_room"]
    assert pipeline.cfg["evaluation"]["spp"] == [1, 2, 4]
    decided = ("C1.1", "C1.2", "C1.3", "C1.4", "C1.5", "C2.1", "C2.2", "C2.3", "C2.4", "C2.5", "C3.1", "C3.2",
               "C3.3", "C3.4", "C3.5", "C4.1s", "C4.2s")
    for claim in decided:
        assert claims.loc[claim, "verdict"] == INCONCLUSIVE, (claim, claims.loc[claim].to_dict())
        assert claims.loc[claim, "n"] == 2, claim
    # C4.4 (speed) is decided on the timing job's rounds: recompute its verdict from the per-round times with
    # scipy's t-interval of the log time ratios (at least MIN_SPEED_ROUNDS rounds, else inconclusive).
    from scipy import stats

    from denoisers.report.verdicts import MIN_SPEED_ROUNDS
    from denoisers.jobs.timing import TIMING_JOB_FILE, read_timing_job

    job = read_timing_job(pipeline.results / TIMING_JOB_FILE)
    logs = np.log(np.divide(job.row("wrls", 2)["pass_ms_per_frame"], job.row("rae", 2)["pass_ms_per_frame"]))
    low, high = stats.t.interval(0.95, len(logs) - 1, loc=logs.mean(), scale=stats.sem(logs))
    expected = (INCONCLUSIVE if len(logs) < MIN_SPEED_ROUNDS else
                "reproduced" if high < 0 else "contradicted" if low > 0 else INCONCLUSIVE)
    assert claims.loc["C4.4", "verdict"] == expected and claims.loc["C4.4", "n"] == len(logs) == 3
    assert claims.loc["C4.3s", "verdict"] == NOT_RUN and "no results at 4 spp for: wrls" in claims.loc["C4.3s", "note"]
    # The one volumetric clip of the smoke config: C4.1 is decided on it (n = 1: inconclusive); C4.3 needs two
    # denoised spp (the smoke config denoises at 2 only).
    assert claims.loc["C4.1", "verdict"] == INCONCLUSIVE and claims.loc["C4.1", "n"] == 1
    assert claims.loc["C4.3", "verdict"] == NOT_RUN
    volumes = pd.read_csv(pipeline.results / "tables" / "iglesias_volumes.csv")
    assert list(volumes["row"]) == ["vol_noisy", "vol_wrls", "vol_svgf", "vol_oidn_color", "vol_rae"]
    assert volumes["note"].astype(object).fillna("").eq("").all()      # every volume row ran (no note)
    # The AFN full model stores its lambda maps; the Isik section shows them (Fig. 5 layout).
    with np.load(pipeline.results / "denoised" / "afn" / "test_000" / "spp2" / "maps.npz") as maps:
        assert maps["lambda"].shape[0] == len(maps["frames"]) and (maps["lambda"][0] == 0).all()

    report = (pipeline.results / "REPORT.md").read_text()
    assert "## Claims" in report and "figures/quality_vs_speed.png" in report
    # The example XML scene has its own section with its metrics and substitutions, and is evaluated.
    assert "## External scenes" in report and "### custom_spheres_room" in report
    external = pd.read_csv(pipeline.results / "tables" / "external.csv")
    assert set(external["scene"]) == {"custom_spheres_room"} and np.isfinite(external["psnr"]).all()
    substitutions = pd.read_csv(pipeline.results / "tables" / "external_substitutions.csv")
    assert "integrator" in set(substitutions["what"])
    split = pd.read_csv(pipeline.results / "tables" / "split.csv").set_index("scene")
    assert bool(split.loc["custom_spheres_room", "evaluated"])


def test_every_configured_baseline_is_in_the_main_table(pipeline: PipelineRun) -> None:
    summary = pd.read_csv(pipeline.results / "tables" / "summary.csv")
    psnr = summary[summary["metric"] == "psnr"]
    expected = {(run.spec.id, run.spp) for run in pipeline.runs()}
    assert set(zip(psnr["method_id"], psnr["spp"])) == expected
    configured = psnr[psnr["role"] == "method"]
    assert set(configured["method_id"]) == {method["id"] for method in pipeline.cfg["evaluation"]["methods"]}
    assert np.isfinite(psnr["mean"]).all()
    assert (psnr["n_scenes"] == len(evaluated_scene_ids(pipeline.cfg))).all()
    # The Markdown summary (also embedded in REPORT.md) has one row per method at every spp it runs at.
    summary_md = (pipeline.results / "tables" / "summary.md").read_text()
    report = (pipeline.results / "REPORT.md").read_text()
    for method in pipeline.cfg["evaluation"]["methods"]:
        rows = re.findall(rf"^\| {re.escape(method['id'])} \|", summary_md, flags=re.MULTILINE)
        assert len(rows) == len(method.get("spp", pipeline.cfg["evaluation"]["spp"])), method["id"]
        assert re.search(rf"^\| {re.escape(method['id'])} \|", report, flags=re.MULTILINE), method["id"]


def test_every_configured_model_is_trained_and_reported(pipeline: PipelineRun) -> None:
    specs = model_specs(pipeline.cfg)
    assert {spec.id for spec in specs} >= {"rae", "rae_inputs_color", "rae_inputs_all", "rae_loss_spatial",
                                           "rae_loss_combined"}
    for spec in specs:
        folder = model_dir(pipeline.results, spec.id)
        assert {p.name for p in folder.iterdir()} - {SNAKEMAKE_MARKER} == set(MODEL_FILES), folder
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["steps"] == spec.budget["max_steps"] and summary["stopped_by"] == "max_steps"
        assert "test_000" not in summary["train_scenes"] + summary["validation_scenes"]
    # The smoke config's combined-loss variant is the base model's training: the job reuses its weights.
    combined = json.loads((model_dir(pipeline.results, "rae_loss_combined") / "summary.json").read_text())
    assert combined["same_training_as"] == "rae"
    assert (model_dir(pipeline.results, "rae_loss_combined") / "best.pt").read_bytes() == \
        (model_dir(pipeline.results, "rae") / "best.pt").read_bytes()
    tables = pipeline.results / "tables"
    training = pd.read_csv(tables / "training.csv")
    assert list(training["model"]) == [spec.id for spec in specs]
    assert set(training["status"]) == {"trained", "trained = rae"}          # the copy names its base
    assert training.set_index("model").loc["rae_loss_combined", "status"] == "trained = rae"
    assert len(pd.read_csv(tables / "rae_inputs.csv")) == 3 and len(pd.read_csv(tables / "rae_loss.csv")) == 2
    # Each ablation variant is scored on the test scene (what C1.2 / C1.3 are decided on).
    for name in ("rae_inputs", "rae_loss"):
        assert np.isfinite(pd.read_csv(tables / f"{name}.csv")["test_rmse_mean"]).all(), name
    # RAE is in the Fig. 8 table, the timing table and the quality-versus-speed chart (matplotlib keeps
    # every text label as a comment in the SVG).
    fig8 = pd.read_csv(tables / "chaitanya_fig8.csv")
    assert {"eaw", "svgf", "oidn", "rae"} <= set(fig8["method"]) and np.isfinite(fig8["rmse_mean"]).all()
    assert "rae" in set(pd.read_csv(tables / "timing.csv")["method_id"])
    chart = (pipeline.results / "figures" / "quality_vs_speed.svg").read_text()
    assert "<!-- rae -->" in chart
    # Its training-time panel places every learned row at its model's training time.
    assert "quality vs training time" in chart and "rae, rae_per_frame [model rae], 4 steps" in chart
    assert "ntasd_uniform, ntasd_uniform_8spp [model ntasd_uniform], 4 steps" in chart
    report = (pipeline.results / "REPORT.md").read_text()
    assert "## Learned denoisers" in report and "figures/rae_inputs_curves.png" in report
    # The capacity sweep: both sizes and the base model (same 4-step budget) scored, timed and one selected.
    capacity = pd.read_csv(tables / "capacity_rae_capacity.csv")
    assert list(capacity["variant"]) == ["width0125", "levels4", "base"] and set(capacity["status"]) == {"ran"}
    assert np.isfinite(capacity[["parameters", "psnr_mean", "ms_per_frame"]].to_numpy(float)).all()
    assert capacity["selected"].sum() == 1 and "## Model capacity" in report and "Smallest size within 0.2 dB" in report
    # Quality targets: two evaluated scenes are fewer than a verdict needs; the AFN target needs 8 spp.
    targets = pd.read_csv(tables / "targets.csv").set_index("target")
    assert list(targets.index) == ["T11", "T12", "T13"] and "## Quality targets" in report
    assert targets.loc["T11", "status"] == targets.loc["T12", "status"] == "inconclusive"
    assert targets.loc["T13", "status"] == "not run" and "8 spp" in targets.loc["T13", "note"]


def test_a_second_config_gets_its_own_complete_folder(pipeline: PipelineRun) -> None:
    """Two configs run one after the other: the second (seed 7, output_dir results/seed7) writes only into its
    own folder; the smoke experiment is byte-for-byte the tree it was (same files, same mtimes)."""
    assert pipeline.after_seed7 == pipeline.after_full
    seed7 = pipeline.workdir / SEED7_OUT
    assert not seed7.is_relative_to(pipeline.results) and not pipeline.results.is_relative_to(seed7)
    for scene in scene_ids(pipeline.cfg):
        ours = json.loads((pipeline.results / "scenes" / scene / "manifest.json").read_text())
        theirs = json.loads((seed7 / "scenes" / scene / "manifest.json").read_text())
        if not scene.startswith(CUSTOM_PREFIX):   # procedural scenes are drawn from the seed
            assert ours != theirs, scene
    assert {p.name for p in seed7.iterdir()} <= {"scenes", ".config", "logs", "benchmarks"}


def test_every_output_records_the_settings_digest_of_this_config(pipeline: PipelineRun) -> None:
    """The digests the jobs recorded equal the ones denoisers.experiment derives from the config (and the
    report checked every one of them)."""
    cfg, lineage = pipeline.cfg, Lineage(pipeline.cfg)
    checked = 0
    for scene in evaluated_scene_ids(cfg):
        for run in pipeline.runs():
            sidecar = metrics_sidecar(metrics_csv(pipeline.results, run.spec.id, scene, run.spp))
            assert json.loads(sidecar.read_text())[DIGEST_KEY] == lineage.metrics(run.spec, scene, run.spp), sidecar
            timing = json.loads((denoised_dir(pipeline.results, run.spec.id, scene, run.spp) / TIMING_FILE).read_text())
            assert timing[DIGEST_KEY] == lineage.denoised(run.spec, scene, run.spp)
            checked += 2
        for run in pipeline.runs("robustness"):
            summary = json.loads((robustness_dir(pipeline.results, run.spec.id, scene, run.spp)
                                  / ROBUSTNESS_SUMMARY).read_text())
            assert summary[DIGEST_KEY] == lineage.robustness(method_spec(cfg, run.spec.id), scene, run.spp)
            checked += 1
    # The volume rows on the evaluated volumetric clips: metrics, denoised clip, spike scenario.
    from denoisers.jobs.volumes import (volume_denoised_dir, volume_metrics_csv, volume_robustness_dir,
                                       volume_robustness_runs, volume_runs, volume_test_scene_ids)

    for scene in volume_test_scene_ids(cfg):
        for run in (run for run in volume_runs(cfg) if run.runnable):
            sidecar = metrics_sidecar(volume_metrics_csv(pipeline.results, run.spec.id, scene, run.spp))
            assert json.loads(sidecar.read_text())[DIGEST_KEY] == lineage.metrics(run.spec, scene, run.spp), sidecar
            timing = json.loads((volume_denoised_dir(pipeline.results, run.spec.id, scene, run.spp)
                                 / TIMING_FILE).read_text())
            assert timing[DIGEST_KEY] == lineage.denoised(run.spec, scene, run.spp)
            checked += 2
        for run in volume_robustness_runs(cfg):
            summary = json.loads((volume_robustness_dir(pipeline.results, run.spec.id, scene, run.spp)
                                  / ROBUSTNESS_SUMMARY).read_text())
            assert summary[DIGEST_KEY] == lineage.robustness(run.spec, scene, run.spp)
            checked += 1
    for spec in model_specs(cfg):
        summary = json.loads((model_dir(pipeline.results, spec.id) / "summary.json").read_text())
        assert summary[DIGEST_KEY] == lineage.model(spec.id)
        checked += 1
    for entry in cfg["tuning"]["methods"]:
        record = json.loads((pipeline.results / "tuning" / f"{entry['method']}.json").read_text())
        assert record[DIGEST_KEY] == lineage.tuning(entry["method"])
        checked += 1
    from denoisers.jobs.timing import TIMING_JOB_FILE, timed_runs

    timing = json.loads((pipeline.results / TIMING_JOB_FILE).read_text())
    assert timing[DIGEST_KEY] == lineage.timing("test_000", [(method_spec(cfg, r), s) for r, s in timed_runs(cfg)])
    checked += 1
    from denoisers.training.speed import TRAINING_SPEED_FILE

    speed = json.loads((pipeline.results / TRAINING_SPEED_FILE).read_text())
    assert speed[DIGEST_KEY] == lineage.training_speed()
    checked += 1
    report = (pipeline.results / "REPORT.md").read_text()
    assert f"Settings digests: {checked} outputs record this config's settings digests;" in report


def test_the_timing_job_times_every_configured_row_and_the_report_uses_it(pipeline: PipelineRun) -> None:
    """Rule time_methods: every runnable configured row at every evaluated spp, in interleaved rounds, with
    the renderer's rate at the same threads; the timing table and C4.4 read it, not the denoise jobs."""
    from denoisers.jobs.timing import TIMING_JOB_FILE, read_timing_job, timed_runs, timing_settings

    job = read_timing_job(pipeline.results / TIMING_JOB_FILE)
    settings = timing_settings(pipeline.cfg)
    assert [(row["method_id"], row["spp"]) for row in job.record["rows"]] == timed_runs(pipeline.cfg)
    # The configured rows and the capacity ablation's sizes (comparison variants share their row's network).
    assert {run.spec.id for run in pipeline.runs() if run.spec.role == "method"} | capacity_model_ids(pipeline.cfg) == \
        {row["method_id"] for row in job.record["rows"]}
    assert job.record["scene"] == "test_000" and job.threads == 2      # every core the job got (--cores 2)
    assert set(job.record["renderers"]) == set(evaluated_scene_ids(pipeline.cfg))     # every evaluated scene
    assert all(rate["threads"] == job.threads for rate in job.record["renderers"].values())
    assert all(job.renderer_samples_per_s(scene) > 0 for scene in evaluated_scene_ids(pipeline.cfg))
    for row in job.record["rows"]:
        assert len(row["pass_ms_per_frame"]) == settings["repeats"] and row["frames"] == list(range(settings["frames"]))
        assert row["ms_per_frame_min"] <= row["ms_per_frame"] <= row["ms_per_frame_max"]
    timed = [(method_spec(pipeline.cfg, row), spp) for row, spp in timed_runs(pipeline.cfg)]
    assert job.record[DIGEST_KEY] == Lineage(pipeline.cfg).timing("test_000", timed)
    table = pd.read_csv(pipeline.results / "tables" / "timing.csv").set_index(["method_id", "spp"])
    for row in job.record["rows"]:
        assert table.loc[(row["method_id"], row["spp"]), "ms_per_frame"] == pytest.approx(row["ms_per_frame"])
    claims = pd.read_csv(pipeline.results / "tables" / "claims.csv").set_index("claim")
    assert "timing job" in claims.loc["C4.4", "note"] and "over 3 rounds" in claims.loc["C4.4", "mean_diff_ci_95"]


def test_the_training_speed_job_times_every_model_and_the_report_shows_it(pipeline: PipelineRun) -> None:
    """Rule time_training: every model of training.models per variant (fp32 NCHW and the configured one in every
    round), and the report's "Training step speed" table and sentence from it."""
    from denoisers.training.speed import BASELINE, TRAINING_SPEED_FILE, read_training_speed, speed_settings

    record = read_training_speed(pipeline.results / TRAINING_SPEED_FILE)
    settings = speed_settings(pipeline.cfg)
    assert record["threads"] == settings["threads"] and record["repeats"] == settings["repeats"]
    assert [m["model"] for m in record["models"]] == [m["id"] for m in pipeline.cfg["training"]["models"]]
    for model in record["models"]:
        timed = {v["variant"]: v for v in model["variants"] if v["status"] == "timed"}
        for key in (BASELINE, model["configured_variant"]):
            assert len(timed[key]["ms_per_step"]) == settings["repeats"], key
        assert timed[BASELINE]["speedup"] == [1.0] * settings["repeats"]
    table = pd.read_csv(pipeline.results / "tables" / "training_speed.csv")
    assert len(table) == sum(len(m["variants"]) for m in record["models"]) and table["configured"].sum() == len(record["models"])
    report = (pipeline.results / "REPORT.md").read_text()
    assert "### Training step speed" in report and "1.6x target is" in report


def test_the_stability_suite_scores_every_row_and_builds_the_atlas(pipeline: PipelineRun) -> None:
    """Issue 15 in the real smoke DAG: every runnable (row, spp) of the suite is scored on every scenario (per-frame
    CSV and a summary with the failure metrics), the atlas files exist, and ATLAS.md and REPORT.md name every row."""
    from denoisers.report.atlas import atlas_outputs
    from denoisers.jobs.stability import scores_csv, stability_runs
    from scenegen.catalog import stability_scene_ids

    scenes = stability_scene_ids(pipeline.cfg)
    runs = [run for run in stability_runs(pipeline.cfg) if run.runnable]
    assert scenes and runs
    for scene in scenes:
        frames = scene_frame_count(pipeline.cfg, scene)
        for run in runs:
            csv = scores_csv(pipeline.results, run.spec.id, scene, run.spp)
            table = pd.read_csv(csv)
            assert len(table) == frames and {"psnr", "masked_psnr", "lag_mse", "flicker_trmae"} <= set(table), csv
            summary = json.loads(csv.with_suffix(".json").read_text())
            assert {"event_frame", "recovery", "ghosting_ratio", "relative_bias", DIGEST_KEY} <= set(summary), csv
    for path in atlas_outputs(pipeline.cfg, root=str(pipeline.results))["all"]:
        assert Path(path).is_file() and Path(path).stat().st_size > 0, path
    atlas = (pipeline.results / "stability" / "ATLAS.md").read_text()
    report = (pipeline.results / "REPORT.md").read_text()
    assert "stability/ATLAS.md" in report
    for run in runs:
        assert f"**{run.spec.id}**" in atlas, run.spec.id


def test_a_users_method_reaches_every_table_chart_atlas_line_and_the_top_comparison(pipeline: PipelineRun) -> None:
    """Issue 49: a new method, one module plus its config rows and nothing else, appears wherever a baseline does:
    every cross-paper table, every cross-paper chart (figures/rows.json: what each one draws), its atlas lines and
    REPORT.md's first section, which compares it with the baselines."""
    from denoisers.report.outputs import CORE_TABLES, EXTERNAL_TABLES, FIGURE_ROWS

    mine, baseline, results = USER_ROW["id"], "svgf", pipeline.results
    checked = []
    for name in CORE_TABLES + EXTERNAL_TABLES:
        table = pd.read_csv(results / "tables" / f"{name}.csv")
        column = next((c for c in ("method_id", "id") if c in table), None)
        if column and baseline in set(table[column]):
            assert mine in set(table[column]), name
            checked.append(name)
    assert {"summary", "per_scene", "timing", "equal_time", "robustness", "runs", "external", "color_balance"} \
        <= set(checked), checked
    drawn = json.loads((results / "figures" / FIGURE_ROWS).read_text())
    charts = report_outputs(pipeline.cfg, root=str(results))
    cross_paper = [Path(p).name for group in ("quality", "curves", "grids") for p in charts[group]]
    assert sorted(drawn) == sorted(cross_paper)
    for chart, rows in drawn.items():
        assert baseline in rows and mine in rows, (chart, rows)
    atlas = (results / "stability" / "ATLAS.md").read_text()
    assert f"**{mine}**" in atlas
    report = (results / "REPORT.md").read_text()
    top = report[report.index("## Your methods against the baselines"):report.index("## Quality")]
    assert f"Rows whose method the harness does not ship: {mine}." in top
    assert any(line.startswith(f"| {mine} |") for line in top.splitlines())
