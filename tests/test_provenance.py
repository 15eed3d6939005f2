"""Provenance records (denoisers/provenance.py) against what the machine and the checkout say."""
from __future__ import annotations

import datetime
import os
import subprocess
from pathlib import Path

import torch

from denoisers.provenance import describe, provenance

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_provenance_matches_git_torch_and_the_machine() -> None:
    record = provenance({"evaluation": 1})
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True)
    if head.returncode == 0:
        assert record["commit"] == head.stdout.strip()
        porcelain = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO_ROOT,
                                   capture_output=True, text=True).stdout
        assert record["dirty"] == bool(porcelain.strip())
    assert record["packages"]["torch"].split("+")[0] == torch.__version__.split("+")[0]
    assert record["cpu_count"] == os.cpu_count() and record["cpu_model"]
    age = datetime.datetime.now(datetime.timezone.utc) - datetime.datetime.fromisoformat(record["date"])
    assert datetime.timedelta(0) <= age < datetime.timedelta(minutes=5)
    lines = "\n".join(describe(record))
    assert f"torch {record['packages']['torch']}" in lines and "evaluation 1" in lines
    if record["commit"]:
        assert record["commit"][:12] in lines


def test_outside_a_checkout_the_commit_is_unknown(monkeypatch, tmp_path: Path) -> None:
    from denoisers import provenance as module

    monkeypatch.setattr(module, "REPO_ROOT", tmp_path)
    record = module.provenance()
    assert record["commit"] is None and record["dirty"] is None
    assert "not a git checkout" in "\n".join(describe(record))
