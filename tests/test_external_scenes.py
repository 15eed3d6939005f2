"""External (bring-your-own XML, ``custom_*``) scenes in the evaluation and the report: they are evaluated
scenes, units of the claims, and get their own report section listing what the harness substituted.

The results tree is hand-made (tests/test_report.py's writer), so every number is known here.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd
import pytest

from denoisers import evaluate
from denoisers.report import build_report, report_outputs
from denoisers.report.claims import claims_table
from denoisers.report.collect import collect
from denoisers.reproductions import all_claims
from tests.test_report import FRAMES, PSNR, SCENE_OFFSET, psnr_of, report_config, write_results

CUSTOM = "custom_room"
EXAMPLE_XML = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "spheres_room" / "scene.xml"
CUSTOM_OFFSET = 2.0
SUBSTITUTIONS = [
    {"what": "integrator", "authored": "path", "used": "mcdn_features", "why": "feature buffers"},
    {"what": "pixel filter", "authored": "gaussian (radius 2 px, the film's default)", "used": "box (radius 0.5 px)",
     "why": "one independent sample per pixel"},
    {"what": "resolution", "authored": "64x64", "used": "render.width x render.height of the config",
     "why": "one resolution per run"},
]


def external_config() -> dict:
    cfg = report_config()
    # A real XML: a custom scene's digest covers its files (the results tree itself is hand-made).
    cfg["extra_scenes"] = [{"name": "room", "xml": str(EXAMPLE_XML), "frames": FRAMES,
                            "camera": {"path": "dolly", "up": [0.0, 1.0, 0.0]}}]
    return cfg


def write_external(root: Path, cfg: dict, custom_psnr: dict | None = None) -> None:
    """The test scenes as in test_report, the custom scene with ``custom_psnr`` and its manifest."""
    write_results(root, cfg)
    write_results(root, cfg, psnr=custom_psnr, scenes={CUSTOM: CUSTOM_OFFSET})
    manifest = {"kind": "custom", "scene_id": CUSTOM, "xml": "/data/room.xml", "n_frames": FRAMES,
                "camera": {"path": "dolly"}, "substitutions": SUBSTITUTIONS,
                "render": {"max_depth": 6, "rr_depth": 5, "hide_emitters": True, "filter": "box"}}
    (root / "scenes" / CUSTOM).mkdir(parents=True)
    (root / "scenes" / CUSTOM / "manifest.json").write_text(json.dumps(manifest))


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("external")
    cfg = external_config()
    write_external(root, cfg)
    build_report(cfg, root)
    return root, cfg


def test_custom_scenes_are_evaluated_after_the_test_scenes() -> None:
    cfg = external_config()
    assert evaluate.evaluated_scene_ids(cfg) == ["test_000", "test_001", "test_002", CUSTOM]
    outputs = report_outputs(cfg)
    assert "results/tables/external.csv" in outputs["tables"]
    assert f"results/figures/grid_{CUSTOM}_spp1.png" in outputs["grids"]
    cfg["extra_scenes"] = []
    assert "results/tables/external.csv" not in report_outputs(cfg)["tables"]


def test_grid_frame_must_exist_in_every_external_clip() -> None:
    cfg = external_config()
    cfg["extra_scenes"][0]["frames"] = 2
    cfg["evaluation"]["grid_frame"] = 3   # within the 4 frames of the test scenes
    problems = [p for p in evaluate.evaluation_problems(cfg) if "grid_frame" in p]
    assert len(problems) == 1 and CUSTOM in problems[0] and "-2..1" in problems[0]
    cfg["evaluation"]["grid_frame"] = -1
    assert not [p for p in evaluate.evaluation_problems(cfg) if "grid_frame" in p]


@pytest.mark.slow  # the shared report build takes 20-45 s
def test_external_section_lists_metrics_and_substitutions(built: tuple[Path, dict]) -> None:
    root, cfg = built
    table = pd.read_csv(root / "tables" / "external.csv")
    assert set(table["scene"]) == {CUSTOM}
    psnr = table.set_index(["method_id", "spp"])["psnr"]
    assert psnr[("wrls", 2)] == pytest.approx(PSNR["wrls"] + 3.0 + CUSTOM_OFFSET)
    assert psnr[("noisy", 1)] == pytest.approx(PSNR["noisy"] + CUSTOM_OFFSET)
    subs = pd.read_csv(root / "tables" / "external_substitutions.csv")
    assert list(subs["what"]) == [row["what"] for row in SUBSTITUTIONS] and set(subs["scene"]) == {CUSTOM}
    width, height = cfg["render"]["width"], cfg["render"]["height"]
    assert subs.set_index("what").loc["resolution", "used"] == f"{width}x{height} (render.width x render.height)"

    report = (root / "REPORT.md").read_text()
    section = report[report.index("## External scenes"):report.index("## Claims")]
    assert f"### {CUSTOM}" in section
    assert "max_depth 6 (-1 = no limit), rr_depth 5, hide_emitters true, box filter" in section
    assert "| pixel filter | gaussian (radius 2 px, the film's default) | box (radius 0.5 px) |" in section
    assert re.search(r"^\| wrls \| 2 \| " + re.escape(f"{PSNR['wrls'] + 3.0 + CUSTOM_OFFSET:.2f}"), section,
                     flags=re.MULTILINE), section
    for link in re.findall(r"\]\(([^)]+)\)", section):
        assert (root / link).is_file(), link


@pytest.mark.slow  # the shared report build takes 20-45 s
def test_custom_scene_is_a_unit_everywhere(built: tuple[Path, dict]) -> None:
    root, _ = built
    split = pd.read_csv(root / "tables" / "split.csv").set_index("scene")
    assert split.loc[CUSTOM, "split"] == "custom" and bool(split.loc[CUSTOM, "evaluated"])
    summary = pd.read_csv(root / "tables" / "summary.csv")
    wrls = summary[(summary.metric == "psnr") & (summary.method_id == "wrls") & (summary.spp == 2)].iloc[0]
    assert wrls["n_scenes"] == 4
    expected = [psnr_of("wrls", scene, 2) for scene in SCENE_OFFSET] + [PSNR["wrls"] + 3.0 + CUSTOM_OFFSET]
    assert wrls["mean"] == pytest.approx(sum(expected) / 4)
    claims = pd.read_csv(root / "tables" / "claims.csv").set_index("claim")
    assert claims.loc["C4.1s", "n"] == 4 and claims.loc["C4.1s", "verdict"] == "reproduced"
    assert (root / "figures" / f"grid_{CUSTOM}_spp1.png").is_file()


def test_the_custom_scene_alone_can_change_a_verdict(tmp_path: Path) -> None:
    """On the three test scenes wrls beats svgf by 1 dB; on the custom scene it loses by 0.5 dB. As a fourth
    unit, the paired differences [1, 1, 1, -0.5] give a t-interval spanning 0: C4.1s becomes inconclusive."""
    cfg = external_config()
    write_external(tmp_path, cfg, custom_psnr={**PSNR, "wrls": PSNR["svgf"] - 0.5})
    claims = claims_table(collect(cfg, tmp_path), all_claims()).set_index("claim")
    assert claims.loc["C4.1s", "n"] == "4" and claims.loc["C4.1s", "verdict"] == "inconclusive"
