"""Tests of published runs (denoisers/report/published.py): what publish-run copies, the status against HEAD, and
the README's generated numbers, which must equal the published tables."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pandas as pd
import pytest

from denoisers.report import published
from denoisers.report.published import PublishError, publish_run, readme_block, run_status, update_blocks
from scenegen.config import load_config

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_and_docs_blocks_equal_the_published_runs() -> None:
    for path in [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]:
        assert update_blocks(path, REPO_ROOT, check=True) == [], \
            f"{path.name}: run `python -m denoisers readme` (its numbers differ from the published run)"
    assert "<!-- published-run: runs/default config/config.yaml -->" in (REPO_ROOT / "README.md").read_text()


def test_every_link_of_a_committed_report_resolves() -> None:
    """runs/*/REPORT.md: the figures the publisher left out are named, not linked (issue 49 §3)."""
    import re

    runs = sorted((REPO_ROOT / "runs").glob("*/REPORT.md"))
    assert runs
    for report in runs:
        targets = re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", report.read_text())
        relative = [t for t in targets if "://" not in t]
        assert relative, report
        broken = [t for t in relative if not (report.parent / t).is_file()]
        assert broken == [], f"{report.relative_to(REPO_ROOT)}: broken links {broken[:5]}"


def test_no_config_description_states_counts() -> None:
    """Counts typed into a description drift from the keys (issue 49 §4); the report's header states them."""
    import re

    for path in sorted((REPO_ROOT / "config").glob("*.yaml")):
        description = load_config(path).get("description", "")
        assert not re.search(r"\d+\s*(x\s*\d+|scenes?|frames?|spp|clips?|px)\b", description), (path.name, description)


def fake_results(root: Path, big_figure: int = 10) -> Path:
    (root / "tables").mkdir(parents=True)
    (root / "figures").mkdir()
    summary = pd.DataFrame([
        {"method_id": m, "method": m, "role": "main", "spp": spp, "metric": metric, "higher_is_better": True,
         "mean": mean + spp, "ci_low": mean + spp - 1, "ci_high": mean + spp + 1, "n_scenes": 5}
        for m, mean in (("eaw", 21.234), ("oidn", 28.5)) for spp in (1, 4) for metric in ("psnr", "ssim")])
    summary.to_csv(root / "tables" / "summary.csv", index=False)
    (root / "tables" / "summary.md").write_text("| table |\n")
    pd.DataFrame({"claim": ["C1", "C2", "C3"], "verdict": ["reproduced", "inconclusive", "inconclusive"]}).to_csv(
        root / "tables" / "claims.csv", index=False)
    (root / "figures" / "small.png").write_bytes(b"p" * 100)
    (root / "figures" / "big.png").write_bytes(b"b" * big_figure)
    (root / "figures" / "unlinked.png").write_bytes(b"u")
    (root / "REPORT.md").write_text("# Evaluation report\n\n- Code: `abcdef1234567` (clean tree)\n\n"
                                    "![a](figures/small.png) ![b](figures/big.png) [again](figures/small.png)\n")
    return root


def test_publish_run_copies_the_report_tables_and_linked_figures_within_budget(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    monkeypatch.setattr(published, "FIGURE_BUDGET_BYTES", 1000)
    results = fake_results(tmp_path / "results", big_figure=5000)
    record = publish_run(cfg, "config/smoke.yaml", results, tmp_path / "runs" / "smoke")
    out = tmp_path / "runs" / "smoke"
    assert record["figures"] == ["figures/small.png"] and record["figures_left_out"] == ["figures/big.png"]
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == [
        "REPORT.md", "figures/small.png", "run.json", "tables/claims.csv", "tables/summary.csv", "tables/summary.md"]
    copied = (out / "REPORT.md").read_text()
    assert "](figures/big.png)" not in copied and "b (not published: `figures/big.png`" in copied
    assert copied.count("](figures/small.png)") == 2
    stored = json.loads((out / "run.json").read_text())
    from denoisers.training.models import model_specs

    assert stored["run_commit"] == "abcdef1234567" and set(stored["model_keys"]) == {s.id for s in model_specs(cfg)}
    assert stored["model_keys"]
    assert run_status(cfg, out) == []
    relabelled = copy.deepcopy(cfg) | {"description": "another label"}     # a label, not a setting
    assert run_status(relabelled, out) == []
    changed = copy.deepcopy(cfg)
    changed["evaluation"]["grid_frame"] = 0
    assert run_status(changed, out) == ["the config's settings digest"]
    first = next(iter(stored["model_keys"]))
    stored["model_keys"][first] = "0" * 64
    (out / "run.json").write_text(json.dumps(stored))
    assert run_status(cfg, out) == [f"the keys (settings or code) of models {first}"]
    # Nothing is published from an unfinished run.
    (results / "REPORT.md").unlink()
    with pytest.raises(PublishError, match="no finished report"):
        publish_run(cfg, "config/smoke.yaml", results, tmp_path / "runs" / "again")


def test_the_generated_block_quotes_the_published_tables(tmp_path: Path) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    repo = tmp_path / "repo"
    (repo / "config").mkdir(parents=True)
    (repo / "config" / "smoke.yaml").write_text((REPO_ROOT / "config" / "smoke.yaml").read_text())
    publish_run(cfg, "config/smoke.yaml", fake_results(tmp_path / "results"), repo / "runs" / "smoke")
    body = readme_block(repo, "runs/smoke", "config/smoke.yaml")
    assert "code `abcdef123456`" in body and "equal HEAD's" in body
    assert "| eaw | 22.23 [21.23, 23.23] | 25.23 [24.23, 26.23] |" in body
    assert "| oidn | 29.50 [28.50, 30.50] | 32.50 [31.50, 33.50] |" in body
    assert "Claims: 2 inconclusive, 1 reproduced (of 3" in body
    readme = repo / "README.md"
    readme.write_text("intro\n<!-- published-run: runs/smoke config/smoke.yaml -->\ntyped 99.99 dB\n"
                      "<!-- /published-run -->\nrest\n")
    assert update_blocks(readme, repo, check=True) == ["runs/smoke"]
    assert "99.99" in readme.read_text()                       # --check does not write
    update_blocks(readme, repo)
    assert update_blocks(readme, repo, check=True) == [] and "99.99" not in readme.read_text()
    assert readme.read_text().startswith("intro\n") and readme.read_text().endswith("rest\n")
    assert "No run of" in readme_block(repo, "runs/missing", "config/smoke.yaml")


def test_republishing_writes_what_moved_and_keeps_the_previous_tally(tmp_path: Path) -> None:
    """A second publish over the first: CHANGES.md lists exactly the claims whose verdict differs (one added, one
    dropped counted as moved from / to 'absent'), both tallies by hand, and the README block quotes the old tally."""
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    repo = tmp_path / "repo"
    (repo / "config").mkdir(parents=True)
    (repo / "config" / "smoke.yaml").write_text((REPO_ROOT / "config" / "smoke.yaml").read_text())
    out = repo / "runs" / "smoke"
    first = publish_run(cfg, "config/smoke.yaml", fake_results(tmp_path / "first"), out)
    assert "previous" not in first and not (out / "CHANGES.md").exists()
    assert "what moved" not in readme_block(repo, "runs/smoke", "config/smoke.yaml")
    second = fake_results(tmp_path / "second")
    pd.DataFrame({"claim": ["C1", "C2", "C4"], "statement": ["a", "b", "d"],
                  "verdict": ["reproduced", "contradicted", "not run"], "n": [12, 12, None],
                  "mean_diff_ci_95": ["1.0 [0.5, 1.5]", "-1.0 [-1.5, -0.5]", None],
                  "note": ["same", "now decided", "no rows"]}).to_csv(second / "tables" / "claims.csv", index=False)
    record = publish_run(cfg, "config/smoke.yaml", second, out)
    assert record["previous"]["tally"] == {"reproduced": 1, "contradicted": 0, "inconclusive": 2, "not run": 0}
    assert record["previous"]["run_commit"] == "abcdef1234567"
    changes = (out / "CHANGES.md").read_text()
    assert "| previous (code abcdef1, published " in changes and " | 1 | 0 | 2 | 0 | 3 |" in changes
    assert "| this (code abcdef1, published " in changes and " | 1 | 1 | 0 | 1 | 3 |" in changes
    assert "3 claim(s) moved" in changes
    assert "| C2 | b | inconclusive | contradicted |  | 12 |  | -1.0 [-1.5, -0.5] | now decided |" in changes
    assert "| C3 |  | inconclusive | absent |" in changes and "| C4 | d | absent | not run |" in changes
    assert "| C1 |" not in changes                                 # reproduced both times
    body = readme_block(repo, "runs/smoke", "config/smoke.yaml")
    assert ("The run it replaced (code abcdef1, published " in body
            and "): 1 reproduced, 0 contradicted, 2 inconclusive, 0 not run; [what moved](runs/smoke/CHANGES.md)."
            in body)


def test_the_block_shows_a_trained_rows_seed_mean_and_leaves_replicas_and_twins_to_the_report(tmp_path: Path) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    results = fake_results(tmp_path / "results")
    summary = pd.read_csv(results / "tables" / "summary.csv")
    rows = [{"method_id": "rae", "method": "rae", "role": "method", "spp": 1, "metric": "psnr",
             "higher_is_better": True, "mean": 26.0, "ci_low": 25.0, "ci_high": 27.0, "n_scenes": 5, "n_seeds": 3,
             "seed_sd": 0.284},
            {"method_id": "rae_seed1", "method": "rae", "role": "seed", "spp": 1, "metric": "psnr",
             "higher_is_better": True, "mean": 26.3, "ci_low": 25.3, "ci_high": 27.3, "n_scenes": 5, "n_seeds": 1},
            {"method_id": "rae_half", "method": "rae", "role": "budget", "spp": 1, "metric": "psnr",
             "higher_is_better": True, "mean": 25.5, "ci_low": 24.5, "ci_high": 26.5, "n_scenes": 5, "n_seeds": 3,
             "seed_sd": 0.1}]
    pd.concat([summary.assign(n_seeds=1), pd.DataFrame(rows)]).to_csv(results / "tables" / "summary.csv", index=False)
    repo = tmp_path / "repo"
    (repo / "config").mkdir(parents=True)
    (repo / "config" / "smoke.yaml").write_text((REPO_ROOT / "config" / "smoke.yaml").read_text())
    publish_run(cfg, "config/smoke.yaml", results, repo / "runs" / "smoke")
    body = readme_block(repo, "runs/smoke", "config/smoke.yaml")
    assert "| method | 1 spp | 4 spp | seeds |" in body
    assert "| rae | 26.00 [25.00, 27.00] |  | 3 (sd 0.28) |" in body
    assert "| eaw | 22.23 [21.23, 23.23] | 25.23 [24.23, 26.23] |  |" in body
    assert "rae_seed1" not in body and "rae_half" not in body
    assert "2 seed replicas and half-budget twins are rows of the [report](runs/smoke/REPORT.md)" in body
