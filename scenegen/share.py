"""Reuse another experiment's scenes and renders (``python -m scenegen share-renders``).

Two configs with the same seed and the same scene and render settings produce the same scenes and renders
(the pipeline is deterministic), so an experiment config over the default dataset (e.g. config/isik2021.yaml,
which differs from config/config.yaml only in what it trains and evaluates) need not render them again. This
copies them from the source config's output folder into the target's, as hard links (a plain copy across
file systems), and only where the two configs' job digests (scenegen.digests: the settings a scene or a
render depends on) are equal, so that nothing rendered under other settings is ever reused:

* a scene directory ``scenes/{scene}`` when its ``scene_digest`` agrees;
* a render folder ``renders/{scene}/{noisy,reference}`` when the scene was shared or already in the target,
  its ``render_digest`` agrees and the source holds every chunk of it.

Anything the target already has is left alone, and each copy appears under its final name only once complete.
Modification times are kept, so Snakemake sees every copied render as newer than its scene and does not
rerun it; what is not copied the target's run renders as usual.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scenegen.atomic import atomic_directory
from scenegen.catalog import chunk_count, scene_ids, stability_scene_ids, volume_scene_ids
from scenegen.config import output_root
from scenegen.digests import render_digest, scene_digest

RENDER_KINDS = ("noisy", "reference")


@dataclass
class ShareResult:
    """What :func:`share_renders` copied (``scenes/..`` and ``renders/..`` paths) and what it left, and why."""

    shared: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)


def all_scene_ids(cfg: dict[str, Any]) -> list[str]:
    """Every scene a config generates: surface scenes, stability scenarios and their controls, volumetric clips."""
    from scenegen.scenarios import stability_control_ids

    return scene_ids(cfg) + stability_scene_ids(cfg) + stability_control_ids(cfg) + volume_scene_ids(cfg)


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:   # another file system (or no hard links): a plain copy
        shutil.copy2(src, dst)


def _copy_tree(src: Path, dst: Path) -> None:
    """Copy directory ``src`` to ``dst`` (absent) by hard links, times kept, appearing only when complete."""
    with atomic_directory(dst) as staging:
        # copytree ends with the root's copystat, so the staging folder takes src's times too.
        shutil.copytree(src, staging, dirs_exist_ok=True, copy_function=_link_or_copy,
                        ignore=shutil.ignore_patterns(".*.tmp-*"))   # unfinished staging of interrupted jobs


def share_renders(source: dict[str, Any], target: dict[str, Any], dry_run: bool = False) -> ShareResult:
    """Copy into ``target``'s output folder the scenes and renders of ``source``'s output folder that ``target``
    would produce identically (module docstring); with ``dry_run`` only report what would be copied."""
    source_root, target_root = output_root(source), output_root(target)
    if source_root.resolve() == target_root.resolve():
        raise ValueError(f"source and target configs share the output folder {source_root}: nothing to share")
    result = ShareResult()
    source_scenes = set(all_scene_ids(source))
    for scene in all_scene_ids(target):
        scene_path = f"scenes/{scene}"
        if scene not in source_scenes:
            result.skipped.append((scene_path, "not a scene of the source config"))
            continue
        if scene_digest(source, scene) != scene_digest(target, scene):
            result.skipped.append((scene_path, "generated under other settings in the source config"))
            continue
        if (target_root / scene_path).exists():
            result.skipped.append((scene_path, "already in the target"))
        elif not (source_root / scene_path).is_dir():
            result.skipped.append((scene_path, f"not generated in {source_root}"))
            continue
        else:
            if not dry_run:
                _copy_tree(source_root / scene_path, target_root / scene_path)
            result.shared.append(scene_path)
        for kind in RENDER_KINDS:
            render_path = f"renders/{scene}/{kind}"
            chunks = [source_root / render_path / f"chunk_{c:03d}" for c in range(chunk_count(source, scene))]
            if render_digest(source, scene, kind) != render_digest(target, scene, kind):
                result.skipped.append((render_path, "rendered under other settings in the source config"))
            elif (target_root / render_path).exists():
                result.skipped.append((render_path, "already in the target"))
            elif not all(chunk.is_dir() for chunk in chunks):
                result.skipped.append((render_path, f"incomplete in {source_root} "
                                                    f"({sum(c.is_dir() for c in chunks)} of {len(chunks)} chunks)"))
            else:
                if not dry_run:
                    _copy_tree(source_root / render_path, target_root / render_path)
                result.shared.append(render_path)
    return result
