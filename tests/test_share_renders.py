"""scenegen/share.py: another experiment's scenes and renders are reused exactly where both configs' job digests
agree, by hard links with their modification times, and never half-copied or over what the target has."""
from __future__ import annotations

import copy
import os
from pathlib import Path

import pytest

from scenegen.cli import main as scenegen_main
from scenegen.catalog import chunk_count, scene_ids
from scenegen.config import load_config
from scenegen.share import all_scene_ids, share_renders

REPO_ROOT = Path(__file__).resolve().parents[1]


def configs(tmp_path: Path) -> tuple[dict, dict]:
    source = load_config(REPO_ROOT / "config" / "smoke.yaml")
    source["output_dir"] = str(tmp_path / "source")
    target = copy.deepcopy(source)
    target["output_dir"] = str(tmp_path / "target")
    target["evaluation"]["spp"] = [2]           # what the experiment evaluates does not matter to the renders
    return source, target


def fake_outputs(cfg: dict, scenes: list[str]) -> None:
    """A scene folder and every render chunk of ``scenes``, renders 10 s newer than their scene (as a run leaves)."""
    root = Path(cfg["output_dir"])
    for scene in scenes:
        (root / "scenes" / scene).mkdir(parents=True)
        (root / "scenes" / scene / "manifest.json").write_text(scene)
        os.utime(root / "scenes" / scene, (1_000_000, 1_000_000))
        for kind in ("noisy", "reference"):
            for chunk in range(chunk_count(cfg, scene)):
                folder = root / "renders" / scene / kind / f"chunk_{chunk:03d}"
                folder.mkdir(parents=True)
                (folder / "frame_0000.exr").write_bytes(b"exr " + scene.encode())
                os.utime(folder, (1_000_010, 1_000_010))


def test_identical_settings_share_every_scene_and_render_by_hard_links_with_their_times(tmp_path: Path) -> None:
    source, target = configs(tmp_path)
    scenes = all_scene_ids(source)
    fake_outputs(source, scenes)
    assert share_renders(source, target, dry_run=True).shared and not (tmp_path / "target").exists()
    result = share_renders(source, target)
    assert len(result.shared) == 3 * len(scenes) and not result.skipped
    for scene in scenes:
        copied = tmp_path / "target" / "scenes" / scene / "manifest.json"
        assert os.stat(copied).st_ino == os.stat(tmp_path / "source" / "scenes" / scene / "manifest.json").st_ino
        chunk = tmp_path / "target" / "renders" / scene / "reference" / "chunk_000"
        assert chunk.stat().st_mtime == 1_000_010 and (tmp_path / "target" / "scenes" / scene).stat().st_mtime == 1_000_000
    # A second call leaves what the target has.
    again = share_renders(source, target)
    assert not again.shared and {why for _, why in again.skipped} == {"already in the target"}


def test_other_settings_or_incomplete_renders_are_not_shared(tmp_path: Path) -> None:
    source, target = configs(tmp_path)
    scenes = all_scene_ids(source)
    fake_outputs(source, scenes)
    first = scenes[0]
    for chunk in (tmp_path / "source" / "renders" / first / "noisy").iterdir():
        chunk.rename(chunk.with_name(f".{chunk.name}.tmp-1"))        # an interrupted render job's staging
    target["render"]["reference_spp"] *= 2        # the surface scenes' references differ, nothing else does
    result = share_renders(source, target)
    skipped = dict(result.skipped)
    assert skipped[f"renders/{first}/noisy"].startswith("incomplete")
    assert not (tmp_path / "target" / "renders" / first / "noisy").exists()
    surface = set(scene_ids(source))
    assert all(skipped[f"renders/{scene}/reference"].startswith("rendered under other settings") for scene in surface)
    # (stability clips render their references at their own spp, so theirs are still the same)
    assert sorted(result.shared) == sorted([f"scenes/{s}" for s in scenes] +
                                           [f"renders/{s}/noisy" for s in scenes if s != first] +
                                           [f"renders/{s}/reference" for s in scenes if s not in surface])
    # A scene generated under other settings shares neither itself nor its renders.
    other = copy.deepcopy(target)
    other["output_dir"] = str(tmp_path / "other")
    other["seed"] += 1
    assert not share_renders(source, other).shared


def test_the_command_line_shares_and_refuses_one_folder_for_both(tmp_path: Path, capsys) -> None:
    import yaml

    source, target = configs(tmp_path)
    fake_outputs(source, all_scene_ids(source)[:1])
    paths = []
    for name, cfg in (("source.yaml", source), ("target.yaml", target)):
        (tmp_path / name).write_text(yaml.safe_dump(cfg))
        paths.append(str(tmp_path / name))
    assert scenegen_main(["share-renders", "--from", paths[0], "--config", paths[1]]) == 0
    assert "3 folders shared" in capsys.readouterr().out
    with pytest.raises(ValueError, match="share the output folder"):
        share_renders(source, source)
