"""Generated job counts in the manual (denoisers.dag_counts): parsing Snakemake's job-stats table, the block's
text and its regeneration. That the committed blocks equal a fresh dry run is checked where the dry runs
already happen (tests/test_workflow.py, assert_documented)."""
from __future__ import annotations

from pathlib import Path

from denoisers.dag_counts import dag_block, parse_job_stats, update_dag_blocks

OUTPUT = """Building DAG of jobs...
Job stats:
job                  count
-----------------  -------
all                      1
denoise_clip          1037
render_noisy            64
total                 1102

Reasons:
    forced: all
Job stats:
job      count
-----  -------
other        9
"""


def test_the_first_job_stats_table_is_parsed_without_its_total() -> None:
    assert parse_job_stats(OUTPUT) == {"all": 1, "denoise_clip": 1037, "render_noisy": 64}
    assert parse_job_stats("Nothing to be done.\n") == {}


def test_the_block_states_the_total_and_every_rule_largest_first() -> None:
    body = dag_block("config/x.yaml", {"all": 1, "render_noisy": 64, "denoise_clip": 1037, "a_rule": 64})
    lines = body.splitlines()
    assert lines[0].startswith("`snakemake -n --forceall --configfile config/x.yaml --config 'store={force_training: "
                               "true}'` (every model trained, as without the store) lists 1,166 jobs")
    assert lines[4:] == ["| `denoise_clip` | 1,037 |", "| `a_rule` | 64 |", "| `render_noisy` | 64 |", "| `all` | 1 |"]


def test_blocks_are_regenerated_and_checked(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("intro\n<!-- dag-jobs: config/x.yaml -->\ntyped 2,570 jobs\n<!-- /dag-jobs -->\nrest\n")
    counts = {"config/x.yaml": {"all": 1, "render_noisy": 4}}     # a cached dry run: no Snakemake here
    assert update_dag_blocks(page, tmp_path, check=True, counts_of=counts) == ["config/x.yaml"]
    assert "typed 2,570" in page.read_text()                          # --check writes nothing
    assert update_dag_blocks(page, tmp_path, counts_of=counts) == ["config/x.yaml"]
    text = page.read_text()
    assert "2,570" not in text and "lists 5 jobs" in text and text.startswith("intro\n") and text.endswith("rest\n")
    assert update_dag_blocks(page, tmp_path, check=True, counts_of=counts) == []
