"""The README and the manual (docs/*.md) link only to files that exist and to headings that exist."""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pandas as pd
import pytest
import yaml

from denoisers.manual import CONFIG_REFERENCE_PAGE, ISIK_TRAINING_PAGE

REPO_ROOT = Path(__file__).resolve().parents[1]
PAGES = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def without_fences(text: str) -> str:
    """``text`` without fenced code blocks."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code (links there are examples, not links)."""
    return re.sub(r"`[^`\n]*`", "", without_fences(text))


def anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a markdown file: lower case, punctuation dropped, spaces as hyphens."""
    headings = re.findall(r"^#{1,6} (.+)$", without_fences(path.read_text()), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-") for heading in headings}


def test_anchor_rule_matches_github_on_known_headings(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# Title\n## Measured stage costs and the 6-hour budget\n## Isik et al. 2021: AFN, its ablations\n"
                    "## Volumetric clips (`vol_*` scenes)\n```\n# not a heading\n```\n")
    assert anchors(page) == {"title", "measured-stage-costs-and-the-6-hour-budget", "isik-et-al-2021-afn-its-ablations",
                             "volumetric-clips-vol_-scenes"}


@pytest.mark.parametrize("page", PAGES, ids=lambda path: path.relative_to(REPO_ROOT).as_posix())
def test_every_relative_link_and_anchor_resolves(page: Path) -> None:
    broken = []
    for target in LINK.findall(prose(page.read_text())):
        if re.match(r"^[a-z]+:", target):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if dest in (REPO_ROOT / "docs" / CONFIG_REFERENCE_PAGE, REPO_ROOT / "docs" / ISIK_TRAINING_PAGE):
            continue   # generated into the site only; the strict build below checks it
        if not dest.exists():
            shown = dest.relative_to(REPO_ROOT) if dest.is_relative_to(REPO_ROOT) else dest
            broken.append(f"{target}: no file {shown}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(REPO_ROOT)}")
    assert not broken, f"{page.relative_to(REPO_ROOT)}: broken links:\n" + "\n".join(broken)


def test_the_readme_is_a_front_page() -> None:
    """Issue 49: the README holds the two commands, the generated results, how to add a method and a scene, and
    links into the manual; the measurement history lives in docs/."""
    lines = (REPO_ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; measurements and how-tos belong in docs/"


def readme_block(language: str, page: str = "README.md") -> str:
    """The first fenced ``language`` block of ``page`` (the worked examples of "Add a method")."""
    match = re.search(rf"^```{language}\n(.*?)^```", (REPO_ROOT / page).read_text(), flags=re.M | re.S)
    assert match, f"{page} has no ```{language} block"
    return match.group(1)


def test_the_readmes_method_example_registers_runs_and_plans() -> None:
    """The "Add a method" example as a user pastes it: it registers, denoises a frame into (3, H, W) equal to the
    3x3 mean over the in-image neighbours (computed here by shifting), and its config row passes the config check."""
    import numpy as np
    import torch

    from denoisers import registry
    from denoisers.evaluate import EvaluationError, evaluation_problems, plan_runs
    from denoisers.registry import Frame
    from scenegen.config import load_config

    namespace: dict = {"__name__": "readme_example"}
    try:
        exec(compile(readme_block("python"), "README.md", "exec"), namespace)
        method = registry.get("box3")
        samples = torch.rand(4, 3, 9, 11, generator=torch.Generator().manual_seed(0)) * 5.0
        out = method().denoise(Frame(samples={"radiance": samples}))
        mean = samples.mean(dim=0).numpy()
        padded = np.pad(mean, ((0, 0), (1, 1), (1, 1)), constant_values=np.nan)
        shifted = [padded[:, 1 + dy:10 + dy, 1 + dx:12 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        np.testing.assert_allclose(out.numpy(), np.nanmean(shifted, axis=0), rtol=1e-5)
        row = yaml.safe_load(readme_block("yaml"))["evaluation"]["methods"][0]
        cfg = load_config(REPO_ROOT / "config" / "config.yaml")
        cfg["evaluation"]["methods"].append(row)
        assert evaluation_problems(cfg) == []
        assert {(run.spec.id, run.spp) for run in plan_runs(cfg) if run.spec.id == "box3"} == {
            ("box3", spp) for spp in cfg["evaluation"]["spp"]}
        cfg["evaluation"]["methods"][-1] = {**row, "method": "box4"}
        index = len(cfg["evaluation"]["methods"]) - 1   # the config check names it, before any planning
        assert [problem for problem in evaluation_problems(cfg) if "box4" in problem] == [
            f"config key 'evaluation.methods[{index}].method' (row 'box3') = 'box4' is not a registered method "
            f"(did you mean 'box3'?); allowed: {', '.join(registry.available())}"]
        with pytest.raises(EvaluationError, match="did you mean 'box3'"):
            plan_runs(cfg)
    finally:
        registry._REGISTRY.pop("box3", None)


def test_the_readme_states_the_store_budget_that_is_checked() -> None:
    budget = json.loads((REPO_ROOT / "store" / "budget.json").read_text())["max_megabytes"]
    assert f"{budget:g} MB in `store/budget.json`" in " ".join((REPO_ROOT / "README.md").read_text().split())


def test_the_manuals_temporal_example_keeps_history_and_forgets_it_at_a_cut_and_a_reset() -> None:
    """docs/adding-a-method.md's temporal method, run on three frames: output = alpha x mean + (1 - alpha) x
    previous output (its formula), the first frame and a camera cut start from the mean, reset() forgets."""
    import torch

    from denoisers import registry
    from denoisers.registry import Frame

    try:
        exec(compile(readme_block("python", "docs/adding-a-method.md"), "adding-a-method.md", "exec"),
             {"__name__": "manual_example"})
        assert registry.get("ema_history").info.temporal
        method = registry.build("ema_history", {"alpha": 0.3}, row="ema")
        frames = [torch.rand(2, 3, 4, 5, generator=torch.Generator().manual_seed(k)) for k in range(4)]
        means = [samples.mean(dim=0) for samples in frames]
        out = [method.denoise(Frame(samples={"radiance": s}, index=i)) for i, s in enumerate(frames[:2])]
        torch.testing.assert_close(out[0], means[0])
        torch.testing.assert_close(out[1], 0.3 * means[1] + 0.7 * means[0])
        cut = method.denoise(Frame(samples={"radiance": frames[2]}, index=2, camera_cut=True))
        torch.testing.assert_close(cut, means[2])
        method.reset()
        torch.testing.assert_close(method.denoise(Frame(samples={"radiance": frames[3]})), means[3])
        with pytest.raises(ValueError, match="did you mean 'alpha'"):
            registry.build("ema_history", {"alpah": 0.3}, row="ema")
        with pytest.raises(ValueError, match="alpha must be in"):
            registry.build("ema_history", {"alpha": 0.0})
    finally:
        registry._REGISTRY.pop("ema_history", None)


def test_the_manual_builds_strictly_offline(tmp_path: Path) -> None:
    """`mkdocs build --strict` (mkdocs.yml): a broken anchor between pages, a bad API reference or a failing
    generated page fails; the configuration reference lists every top-level key of the schema."""
    import subprocess
    import sys

    mkdocs = Path(sys.executable).parent / "mkdocs"
    result = subprocess.run([str(mkdocs), "build", "--strict", "--site-dir", str(tmp_path / "site")], cwd=REPO_ROOT,
                            capture_output=True, text=True, timeout=600, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, result.stdout + result.stderr
    reference = (tmp_path / "site" / "configuration-reference.html").read_text()
    schema = yaml.safe_load((REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())
    missing = [key for key in schema["properties"] if f"<code>{key}</code>" not in reference]
    assert not missing, f"configuration reference lacks {missing}"
    # One page per reproduced paper, generated from the published run: its claims rows and its figures.
    from denoisers.manual import PAPERS_DIR, paper_slug
    from denoisers.reproductions import all_reproductions

    claims = pd.read_csv(REPO_ROOT / "runs" / "default" / "tables" / "claims.csv")
    images = 0
    for reproduction in all_reproductions():
        page = (tmp_path / "site" / PAPERS_DIR / f"{paper_slug(reproduction.source)}.html").read_text()
        ran = [c.id for c in reproduction.claims if c.id in set(claims["claim"])]
        assert all(f"<td>{claim}</td>" in page for claim in ran), (reproduction.paper, ran)
        for image in re.findall(r'<img [^>]*src="([^"]+)"', page):
            assert (tmp_path / "site" / PAPERS_DIR / image).is_file(), (reproduction.paper, image)
            images += 1
    assert images >= 4            # the published Fig. 3 / loss curves, Fig. 7 and the sample maps at least
    # The Isik run's training progress, generated from the committed store: one row per training of its config.
    from denoisers.manual import ISIK_CONFIG
    from denoisers.training.models import trained_model_specs
    from scenegen.config import load_config

    progress = (tmp_path / "site" / ISIK_TRAINING_PAGE.replace(".md", ".html")).read_text()
    ids = [spec.id for spec in trained_model_specs(load_config(REPO_ROOT / ISIK_CONFIG))]
    assert all(f"<code>{model_id}</code>" in progress for model_id in ids)
    assert f"{len(ids)} trainings: " in progress
