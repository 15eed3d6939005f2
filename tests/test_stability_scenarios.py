"""Stability scenarios (issue 15 §1): every scenario builds and renders, its masks lie where its phenomenon is
(and are empty where it is not), manifests and masks are deterministic, the config section validates, and the
smoke config's `stability` target plans the expected jobs. Renders are tiny (24 x 24, 4 frames, 2 spp,
8 spp references): the whole file takes a couple of minutes."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from scenegen.catalog import scene_ids, stability_scene_ids, training_scene_split
from scenegen.config import ConfigError, load_config, validate_config
from scenegen.scenarios import MASK_KINDS, SCENARIOS, draw_scenario, generate_scenario
from scenegen.scenarios.masks import FAST_MOTION_FRACTION

REPO_ROOT = Path(__file__).resolve().parents[1]
FRAMES, SIZE = 4, 24


def tiny_config(**stability) -> dict:
    cfg = yaml.safe_load((REPO_ROOT / "config/smoke.yaml").read_text())
    cfg["stability"] = {"frames": FRAMES, "width": SIZE, "height": SIZE, "spp": 2, "reference_spp": 8, **stability}
    return validate_config(cfg)


def build(cfg: dict, scene: str, root: Path) -> dict:
    """Generate, render (one chunk each) and mask ``scene`` below ``root``; return events.json."""
    from scenegen import jobs
    from scenegen.scenarios.masks import derive_masks

    scene_dir, render_dir = root / "scenes" / scene, root / "renders" / scene
    jobs.run_generate(cfg, scene, scene_dir)
    jobs.run_render_noisy(cfg, scene, 0, scene_dir, render_dir / "noisy/chunk_000")
    jobs.run_render_reference(cfg, scene, 0, scene_dir, render_dir / "reference/chunk_000")
    return derive_masks(cfg, scene, scene_dir, render_dir, root / "stability" / scene)


@pytest.fixture(scope="module")
def suite(tmp_path_factory) -> tuple[dict, Path]:
    """Every registered scenario rendered and masked once."""
    cfg, root = tiny_config(), tmp_path_factory.mktemp("stability")
    for scene in stability_scene_ids(cfg):
        build(cfg, scene, root)
    return cfg, root


def load(root: Path, name: str):
    """(manifest, events, clip, masks {kind: (T, H, W) bool}) of scenario ``name``."""
    from scenegen.dataset import load_clip
    from scenegen.exr import read_exr

    scene = f"stab_{name}"
    manifest = json.loads((root / "scenes" / scene / "manifest.json").read_text())
    events = json.loads((root / "stability" / scene / "events.json").read_text())
    clip = load_clip(root / "renders" / scene, buffers=["radiance"], reference=True)
    frames = [read_exr(root / "stability" / scene / "masks" / f"frame_{t:04d}.exr",
                       [f"mask.{kind}" for kind in MASK_KINDS])[0] for t in range(FRAMES)]
    masks = {kind: np.stack([frame[f"mask.{kind}"] > 0.5 for frame in frames]) for kind in MASK_KINDS}
    return manifest, events, clip, masks


# ------------------------------------------------------------------ manifests, config (no rendering)
def test_schema_lists_exactly_the_registered_scenarios() -> None:
    schema = yaml.safe_load((REPO_ROOT / "workflow/schemas/config.schema.yaml").read_text())
    scenarios = schema["properties"]["stability"]["properties"]["scenarios"]
    assert scenarios["items"]["enum"] == scenarios["default"] == list(SCENARIOS)
    default = load_config(REPO_ROOT / "config/config.yaml")
    assert default["stability"]["enabled"] and default["stability"]["scenarios"] == list(SCENARIOS)
    assert default["stability"]["rows"] is None            # the default atlas covers every evaluation row
    smoke = load_config(REPO_ROOT / "config/smoke.yaml")    # a subset, to keep the smoke run short
    assert smoke["stability"]["enabled"] and set(smoke["stability"]["scenarios"]) < set(SCENARIOS)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_builds_a_valid_deterministic_manifest(name: str, tmp_path: Path) -> None:
    cfg = tiny_config()
    manifest = draw_scenario(cfg, f"stab_{name}").manifest
    assert manifest["scene_id"] == f"stab_{name}" and manifest["n_frames"] == FRAMES
    assert len(manifest["camera"]["frames"]) == FRAMES
    assert [shape["index"] for shape in manifest["shapes"]] == list(range(len(manifest["shapes"])))
    assert all(0 <= shape["material"] < len(manifest["materials"]) for shape in manifest["shapes"])
    for shape in manifest["shapes"]:
        assert shape["to_world_per_frame"] is None or len(shape["to_world_per_frame"]) == FRAMES
    record = manifest["stability"]
    assert record["scenario"] == name and set(record["focus"]) <= set(MASK_KINDS)
    assert set(record["subject_shapes"]) <= {shape["index"] for shape in manifest["shapes"]}
    # Same config and seed: byte-identical files; another seed: another draw.
    generate_scenario(cfg, f"stab_{name}", tmp_path / "a")
    generate_scenario(cfg, f"stab_{name}", tmp_path / "b")
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert files and all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)
    other = draw_scenario({**cfg, "seed": cfg["seed"] + 1}, f"stab_{name}").manifest
    assert other["seed"] != manifest["seed"]


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_the_control_clip_holds_the_scenarios_final_frame(name: str) -> None:
    """stab_{name}__still: the scenario's content (same materials, meshes, lights) with every animated thing at its
    final-frame state in every frame and no events; only animated scenarios have one, and a scenario declared not
    animated really has nothing that changes."""
    from scenegen.scenarios import scenario_control, stability_control_ids

    cfg = tiny_config()
    scene = f"stab_{name}"
    manifest = draw_scenario(cfg, scene).manifest
    cameras = manifest["camera"]["frames"]
    changes = (any(s["to_world_per_frame"] is not None and not np.allclose(s["to_world_per_frame"],
                                                                            s["to_world_per_frame"][-1])
                   for s in manifest["shapes"])
               or any(not np.allclose(e[key], e[key][-1]) for e in manifest["emitters"] for key in e
                      if key.endswith("_per_frame"))
               or any(not np.allclose(c["origin"], cameras[-1]["origin"]) or not np.allclose(c["target"],
                      cameras[-1]["target"]) or c["cut"] for c in cameras))
    assert SCENARIOS[name].animated == changes
    control = scenario_control(cfg, scene)
    assert (control in stability_control_ids(cfg)) == changes
    if not changes:
        assert control is None
        with pytest.raises(KeyError, match="not animated"):
            draw_scenario(cfg, f"{scene}__still")
        return
    held = draw_scenario(cfg, control).manifest
    assert control == f"{scene}__still" and held["scene_id"] == control and held["n_frames"] == FRAMES
    assert held["stability"]["events"] == [] and held["stability"]["control_of"] == name
    assert held["materials"] == manifest["materials"] and held["seed"] == manifest["seed"]
    assert all(c == {**cameras[-1], "cut": False} for c in held["camera"]["frames"])
    for original, still in zip(manifest["shapes"], held["shapes"]):
        if original["to_world_per_frame"] is not None:
            assert all(np.allclose(m, original["to_world_per_frame"][-1]) for m in still["to_world_per_frame"])
            assert np.allclose(still["to_world"], original["to_world_per_frame"][-1])
        else:
            assert still == original
    for original, still in zip(manifest["emitters"], held["emitters"]):
        for key in original:
            expected = [original[key][-1]] * FRAMES if key.endswith("_per_frame") else original[key]
            assert np.allclose(still[key], expected) if key != "name" and key != "type" else still[key] == expected
    # Its own scene digest (rendered with its own noise), same content digest inputs otherwise.
    from scenegen.digests import scene_settings

    assert scene_settings(cfg, control) == {**scene_settings(cfg, scene), "control": "final frame"}


def test_config_section_is_validated_with_readable_errors() -> None:
    cfg = tiny_config()
    assert stability_scene_ids(cfg) == [f"stab_{name}" for name in SCENARIOS]
    defaults = validate_config({key: value for key, value in copy.deepcopy(cfg).items() if key != "stability"})
    assert defaults["stability"] == {"enabled": True, "scenarios": list(SCENARIOS), "frames": 8, "width": 64,
                                     "height": 64, "spp": None, "reference_spp": 256, "denoise_spp": [2],
                                     "rows": None, "margin": 0.1}
    for change, expected in (({"scenarios": ["disocclusion", "moving_shadows"]}, "stability.scenarios[1]"),
                             ({"frames": 2}, "stability.frames"), ({"reference_spp": 9}, "stability.reference_spp"),
                             ({"spp": 40}, "stability.spp"), ({"widht": 8}, "unknown config key 'stability.widht'")):
        bad = copy.deepcopy(cfg)
        bad["stability"].update(change)
        with pytest.raises(ConfigError, match=expected.replace("[", r"\[").replace("]", r"\]")):
            validate_config(bad)
    bad = copy.deepcopy(cfg)
    bad["stability"]["spp"], bad["render"]["extra_radiance_spp"] = 30, 4
    with pytest.raises(ConfigError, match="stability.spp"):
        validate_config(bad)
    assert stability_scene_ids({**cfg, "stability": {**cfg["stability"], "enabled": False}}) == []


def test_scenarios_are_neither_trained_nor_evaluated_and_change_no_existing_digest() -> None:
    from denoisers import experiment
    from denoisers.evaluate import evaluated_scene_ids

    cfg = load_config(REPO_ROOT / "config/config.yaml")
    assert not any(scene.startswith("stab_") for scene in scene_ids(cfg) + evaluated_scene_ids(cfg)
                   + sum(training_scene_split(cfg), []))
    without = {key: value for key, value in copy.deepcopy(cfg).items() if key != "stability"}
    changed = copy.deepcopy(cfg)
    changed["stability"].update(frames=5, width=32, scenarios=["disocclusion"])
    for other in (without, changed):
        assert experiment.report_digest(other) == experiment.report_digest(cfg)
        for scene in scene_ids(cfg):
            assert experiment.scene_digest(other, scene) == experiment.scene_digest(cfg, scene)
            for kind in ("noisy", "reference"):
                assert experiment.render_digest(other, scene, kind) == experiment.render_digest(cfg, scene, kind)


# ------------------------------------------------------------------ renders and masks
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_renders_and_its_focus_masks_are_filled(suite, name: str) -> None:
    cfg, root = suite
    manifest, events, clip, masks = load(root, name)
    assert clip.reference["radiance"].shape == (FRAMES, 3, SIZE, SIZE)
    assert np.all(np.isfinite(clip.reference["radiance"])) and clip.reference["radiance"].mean() > 0
    assert events["focus"] == manifest["stability"]["focus"]
    for kind in events["focus"]:
        assert masks[kind].any(), (name, kind)
        assert events["mask_pixels"][kind] == [int(n) for n in masks[kind].sum(axis=(1, 2))]
    assert not any(masks[kind][0].any() for kind in ("disocclusion", "shadow", "fast_motion"))  # no history


def test_disocclusion_mask_is_the_invalid_reprojection(suite) -> None:
    _, root = suite
    _, _, clip, masks = load(root, "disocclusion")
    assert np.array_equal(masks["disocclusion"][1:], ~clip.valid[1:, 0])
    for kind in ("shadow", "specular", "transmission", "fast_motion"):
        assert not masks[kind].any(), kind


def test_moving_shadow_has_zero_motion_and_a_shadow_where_the_shading_changed(suite) -> None:
    _, root = suite
    _, _, clip, masks = load(root, "moving_shadow")
    assert np.abs(clip.motion).max() < 1e-3 and clip.valid[1:].all()
    assert not masks["disocclusion"].any()
    shadow = masks["shadow"][1:]
    luminance = clip.reference["radiance"].mean(axis=1)
    change = np.abs(luminance[1:] - luminance[:-1])
    # Outside the shadow the moving light changes the shading too (distance, angle), and the 8-spp references are noisy.
    assert shadow.any() and change[shadow].mean() > 2.0 * change[~shadow].mean()


def test_reflection_mask_covers_the_mirror_and_the_glossy_panel(suite) -> None:
    _, root = suite
    manifest, _, clip, masks = load(root, "moving_reflection")
    panels = [shape["index"] for shape in manifest["shapes"] if shape["name"] in ("mirror", "glossy")]
    on_panels = np.isin(np.rint(clip.gbuffer["object"][:, 0]), panels)
    overlap = (masks["specular"] & on_panels).sum() / (masks["specular"] | on_panels).sum()
    assert overlap > 0.8
    _, _, _, diffuse_only = load(root, "disocclusion")
    assert not diffuse_only["specular"].any()


@pytest.mark.parametrize("name", ["transparent", "caustics"])
def test_transmission_mask_lies_on_the_glass(suite, name: str) -> None:
    _, root = suite
    manifest, _, _, masks = load(root, name)
    glass = masks["subject"]
    assert (masks["transmission"] & glass).sum() / (masks["transmission"] | glass).sum() > 0.7


def test_cut_and_light_switch_events_match_the_manifest(suite) -> None:
    _, root = suite
    manifest, events, clip, masks = load(root, "camera_cut")
    cut = manifest["animation"]["camera_cut_frame"]
    assert cut == FRAMES // 2
    assert {(e["frame"], e["source"]) for e in events["events"] if e["kind"] == "camera_cut"} == {
        (cut, "manifest"), (cut, "renderer")}
    assert not clip.valid[cut].any() and not masks["disocclusion"][cut].any() and clip.valid[cut - 1].any()
    manifest, events, clip, masks = load(root, "light_switch")
    assert [(e["frame"], e["on"]) for e in events["events"]] == [(FRAMES // 2, True)]
    luminance = clip.reference["radiance"].mean(axis=(1, 2, 3))
    assert luminance[FRAMES // 2] > 2.0 * luminance[FRAMES // 2 - 1]
    assert not masks["shadow"].any() and not masks["disocclusion"].any() and np.abs(clip.motion).max() < 1e-3


def test_fast_motion_and_low_light_masks(suite) -> None:
    _, root = suite
    _, events, clip, masks = load(root, "fast_motion")
    speed = np.linalg.norm(clip.motion, axis=1)
    assert speed[1:].max() >= FAST_MOTION_FRACTION * SIZE
    assert np.array_equal(masks["fast_motion"][1:], speed[1:] >= FAST_MOTION_FRACTION * SIZE)
    assert any(e["kind"] == "fast_motion" for e in events["events"])
    assert not load(root, "disocclusion")[3]["fast_motion"].any()
    low = load(root, "low_light")[3]["indirect_only"]
    assert low.mean() > 0.5
    assert load(root, "disocclusion")[3]["indirect_only"].mean() < 0.05


def test_masks_and_manifests_are_deterministic(suite, tmp_path: Path) -> None:
    cfg, root = suite
    build(cfg, "stab_moving_shadow", tmp_path)
    for folder in ("scenes/stab_moving_shadow", "stability/stab_moving_shadow"):
        files = sorted(p.relative_to(root / folder) for p in (root / folder).rglob("*") if p.is_file())
        assert files
        for name in files:
            assert (tmp_path / folder / name).read_bytes() == (root / folder / name).read_bytes(), name


# ------------------------------------------------------------------ workflow
@pytest.mark.slow
def test_smoke_stability_target_plans_the_expected_jobs(tmp_path: Path) -> None:
    from tests.test_workflow import copy_workflow, dry_run, expected_jobs, run_snakemake

    (tmp_path / "workflow").mkdir()
    work = copy_workflow(tmp_path / "workflow")
    cfg = load_config(work / "config/smoke.yaml")
    counts = dry_run("stability", "--forceall", "--configfile", "config/smoke.yaml", cwd=work)
    n, rows = len(cfg["stability"]["scenarios"]), len(cfg["stability"]["rows"])
    assert cfg["stability"]["denoise_spp"] == [1] and (n, rows) == (2, 3)
    # The smoke config's rows (noisy, svgf, oidn) on its two clips at 1 spp: nothing learned or tuned, so no
    # training, tuning or training-scene renders. Both scenarios are animated: each has a control clip, rendered and
    # denoised like it (no masks, no scores). One denoise and one score job per row does all its clips.
    clips = 2 * n
    assert counts == expected_jobs(cfg, "stability") == {
        "generate_scene": clips, "render_noisy": clips, "render_reference": clips, "derive_masks": n,
        "denoise_scenario_row": rows, "score_scenario_row": rows, "build_atlas": 1, "stability": 1}
    from denoisers.jobs.rows import row_clips
    from scenegen.scenarios import stability_control_ids

    scenes = stability_scene_ids(cfg) + stability_control_ids(cfg)
    assert len(scenes) == clips and row_clips(cfg, "svgf", "stability") == [(scene, 1) for scene in scenes]
    bad = run_snakemake("-n", f"{cfg['output_dir']}/stability/stab_nope", "--configfile", "config/smoke.yaml",
                        cwd=work, check=False)
    assert bad.returncode != 0 and "stab_nope is not a stability scenario" in bad.stdout + bad.stderr
    bad = run_snakemake("-n", f"{cfg['output_dir']}/stability/scores/path_x2", "--configfile",
                        "config/smoke.yaml", cwd=work, check=False)
    assert bad.returncode != 0 and "no runnable row path_x2 of evaluation.methods on the stability clips; rows: " \
        "noisy, svgf, oidn" in bad.stdout + bad.stderr


def test_stability_rows_must_be_evaluation_rows() -> None:
    from denoisers.jobs.stability import stability_rows

    cfg = load_config(REPO_ROOT / "config/smoke.yaml")
    assert [spec.id for spec in stability_rows(cfg)] == ["noisy", "svgf", "oidn"]
    cfg["stability"]["rows"] = None
    assert [spec.id for spec in stability_rows(cfg)] == [m["id"] for m in cfg["evaluation"]["methods"]]
    cfg["stability"]["rows"] = ["svgf", "no_such_row"]
    with pytest.raises(ValueError, match=r"'stability.rows' names \['no_such_row'\]"):
        stability_rows(cfg)
