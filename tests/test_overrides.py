"""Nested command-line overrides (scenegen/overrides.py): ``--config 'render={spp: 8}'`` works."""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from denoisers.device import resolve_config_device
from scenegen.config import config_digest, load_config, validate_config
from scenegen.overrides import coerce_override_strings
from tests.test_workflow import copy_workflow, run_snakemake

REPO_ROOT = Path(__file__).resolve().parents[1]
SCHEMA = yaml.safe_load((REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())


def test_string_leaves_become_the_schema_type() -> None:
    cfg = yaml.safe_load((REPO_ROOT / "config" / "smoke.yaml").read_text())
    cfg["render"].update(spp="2", variant="scalar_rgb")
    cfg["evaluation"].update(spp="[1, 2]", out_of_range_factor="12.5")
    cfg["evaluation"]["robustness"]["enabled"] = "false"
    coerce_override_strings(cfg, SCHEMA)
    assert cfg["render"]["spp"] == 2 and cfg["render"]["variant"] == "scalar_rgb"
    assert cfg["evaluation"]["spp"] == [1, 2] and cfg["evaluation"]["out_of_range_factor"] == 12.5
    assert cfg["evaluation"]["robustness"]["enabled"] is False
    validate_config(cfg)


def test_unparseable_strings_are_left_for_the_schema_to_reject() -> None:
    cfg = {"render": {"spp": "eight"}, "description": "8"}
    coerce_override_strings(cfg, SCHEMA)
    assert cfg == {"render": {"spp": "eight"}, "description": "8"}


def test_nested_override_on_the_command_line(tmp_path: Path) -> None:
    workflow = copy_workflow(tmp_path)
    result = run_snakemake("scenes", "-n", "-p", "--configfile", "config/smoke.yaml", "--config", "render={reference_spp: 32}",
                           cwd=workflow)
    # The jobs get the resolved config by its digest name (a dry run does not write it): the name is the digest of
    # the smoke config with only render.reference_spp changed, so the override merged into render, not replaced it.
    assert result.returncode == 0, result.stderr
    names = set(re.findall(r"--config \S*/\.config/([0-9a-f]{16})\.yaml", result.stdout + result.stderr))
    merged = load_config(workflow / "config" / "smoke.yaml")
    assert merged["render"]["width"] == 48
    merged["render"]["reference_spp"] = 32
    # ...and compute.device resolved where the DAG is planned (denoisers.device; auto -> cpu or cuda)
    assert names == {config_digest(resolve_config_device(validate_config(merged)))[:16]}
