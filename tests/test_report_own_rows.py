"""REPORT.md's first section compares a user's own method with the shipped baselines (issue 49 §3): a method
registered outside the harness gets its metrics, paired PSNR differences to every baseline row, its equal-time
line and its atlas lines, with no change outside its module and its config row."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from denoisers import registry
from denoisers.registry import Denoiser, Frame, register
from denoisers.report import build_report
from denoisers.report.collect import collect
from denoisers.report.own_rows import HARNESS_METHODS, own_rows, paired_difference
from tests.test_report import METHODS, MS, PSNR, SCENES, SPIKED_PSNR, TRMAE, report_config, write_results

OWN = "own_box_filter"


def test_the_harness_methods_are_exactly_the_registered_ones() -> None:
    """A method the harness ships is never mistaken for a user's; adding one means listing it."""
    assert sorted(HARNESS_METHODS) == registry.available()


@pytest.fixture
def own_method():
    @register(OWN, inputs=("radiance",), description="a user's 3x3 box filter")
    class OwnBox(Denoiser):
        def denoise(self, frame: Frame) -> torch.Tensor:
            return frame.mean("radiance")

    yield OwnBox
    registry._REGISTRY.pop(OWN, None)


def test_a_users_row_is_compared_with_the_baselines_at_the_top(tmp_path: Path, own_method) -> None:
    cfg = report_config()
    cfg["evaluation"]["methods"] = [*METHODS, {"id": "mine", "method": OWN}]
    # 27.5 dB at 1 spp on every scene (+3 per doubling): 0.5 above SVGF, 0.5 below wRLS, on every scene.
    values = {"psnr": {**PSNR, "mine": 27.5}, "trmae": {**TRMAE, "mine": 0.25},
              "spiked": {**SPIKED_PSNR, "mine": 20.0}}
    MS["mine"] = 2.0
    try:
        write_results(tmp_path, cfg, **values)
        build_report(cfg, tmp_path)
        res = collect(cfg, tmp_path)
    finally:
        del MS["mine"]
    assert own_rows(res) == ["mine"]
    for spp in (1, 2):
        assert paired_difference(res, "mine", "svgf", spp)[:3] == pytest.approx((0.5, 0.5, 0.5))
        assert paired_difference(res, "mine", "wrls", spp)[0] == pytest.approx(-0.5)
        assert paired_difference(res, "mine", "noisy", spp)[3] == len(SCENES)
    text = (tmp_path / "REPORT.md").read_text()
    section = text[text.index("## Your methods against the baselines"):text.index("## Quality")]
    assert "Rows whose method the harness does not ship: mine." in section
    differences = [line for line in section.splitlines() if line.startswith("| mine |") and "n=3" in line]
    assert len(differences) == 2                              # one line per spp in the differences table
    header = next(line for line in section.splitlines() if line.startswith("| row | spp | − "))
    columns = [cell.strip() for cell in header.strip("|").split("|")]
    cells = [cell.strip() for cell in differences[0].strip("|").split("|")]
    assert "(better)" in cells[columns.index("− svgf")] and "(worse)" in cells[columns.index("− wrls")]
    assert "n=3" in cells[columns.index("− noisy")]
    assert "Equal time" in section and "Failure atlas:" in section


def test_no_section_when_every_row_is_the_harness_own(tmp_path: Path) -> None:
    cfg = report_config()
    write_results(tmp_path, cfg)
    build_report(cfg, tmp_path)
    assert "## Your methods against the baselines" not in (tmp_path / "REPORT.md").read_text()


def test_timing_ranges_too_wide_to_rank_are_flagged(tmp_path: Path) -> None:
    """(max - min) / median over the timing rounds above RANK_SPREAD_LIMIT: flagged in the timing table, the
    summary's ms/frame, and the equal-time view; a narrow range (0.3 here) is not."""
    import json

    import pandas as pd

    from denoisers.report.tables import RANK_SPREAD_LIMIT, TOO_WIDE

    cfg = report_config()
    write_results(tmp_path, cfg)
    record_path = tmp_path / "timing" / "timing.json"
    record = json.loads(record_path.read_text())
    for row in record["rows"]:
        if row["method_id"] == "svgf":   # median 5 ms, rounds from 2 to 9 ms: spread 1.4
            row.update(pass_ms_per_frame=[5.0, 2.0, 9.0], ms_per_frame_min=2.0, ms_per_frame_max=9.0, spread=1.4)
    record_path.write_text(json.dumps(record))
    build_report(cfg, tmp_path)
    timing = pd.read_csv(tmp_path / "tables" / "timing.csv")
    flagged = set(timing.loc[timing["too_wide_to_rank"], "method_id"])
    assert flagged == {"svgf"} and (9.0 - 2.0) / 5.0 > RANK_SPREAD_LIMIT > 0.3
    equal_time = pd.read_csv(tmp_path / "tables" / "equal_time.csv").set_index(["method_id", "spp"])
    assert TOO_WIDE in equal_time.loc[("svgf", 1), "better"] and TOO_WIDE not in equal_time.loc[("wrls", 1), "better"]
    summary = (tmp_path / "tables" / "summary.md").read_text()
    svgf_lines = [line for line in summary.splitlines() if line.startswith("| svgf")]
    assert svgf_lines and all(TOO_WIDE in line for line in svgf_lines)
    assert not any(TOO_WIDE in line for line in summary.splitlines() if line.startswith("| wrls"))


def test_a_grid_of_many_rows_wraps_at_about_1600_pixels(tmp_path: Path) -> None:
    """20 rows (the robustness grid of a full config) wrap into bands of GRID_PANELS_PER_BAND panels, each closed by
    the reference: the PNG stays about GRID_MAX_WIDTH_PX wide (colour bar and margins beside it) and grows in height;
    a grid of two rows keeps one band."""
    import numpy as np
    from PIL import Image

    from denoisers.report.figures import GRID_MAX_WIDTH_PX, GRID_PANELS_PER_BAND, image_grid

    reference = np.ones((3, 16, 16), np.float32)
    columns = [(f"row{i}", reference * (1 + 0.01 * i)) for i in range(20)]
    image_grid(columns, reference, tmp_path / "wide.png", "wide")
    image_grid(columns[:2], reference, tmp_path / "small.png", "small")
    image_grid(columns[:2], reference, tmp_path / "maps.png", "maps", sample_maps=[None, np.full((16, 16), 3.0)])
    wide, small, maps = (Image.open(tmp_path / name).size for name in ("wide.png", "small.png", "maps.png"))
    assert GRID_PANELS_PER_BAND == 7
    assert wide[0] <= GRID_MAX_WIDTH_PX + 150, wide
    bands = -(-len(columns) // (GRID_PANELS_PER_BAND - 1))
    assert wide[1] > 0.8 * bands * small[1] and maps[1] > 1.2 * small[1]
