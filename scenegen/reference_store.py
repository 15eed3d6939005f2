"""Stored references of the evaluated scenes, so that a run from the store renders none of them.

``<store>/references/<scene>/<key16>/`` holds one evaluated scene's (test_*, custom_*) reference render bit for
bit as the render_reference jobs wrote it, ``chunk_NNN/frame_TTTT.exr`` + ``.json`` per chunk, and
``meta.json`` (the full key, the spp, each file's SHA-256). The key digests the scene's id and its reference
render digest (:func:`scenegen.digests.render_digest`: the scene's content, frames, chunking, spp, pass size,
integrator and Mitsuba variant), known before anything is rendered. A render_reference job whose chunk is stored under its
digest copies it (after checking every file's SHA-256) instead of rendering: in the default run of 2026-12-06
these renders were 60 of the 107 minutes (docs/default-run.md).

As with shared renders (scenegen.share), the renderer's code is not in the key: after a change to the renderer,
republish (``python -m denoisers store publish-references``) or set ``store.references: false``. The model store
(denoisers.store) reads this module for ``store list`` / ``check``; this module imports nothing of denoisers, so
the render job stays free of the training code.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import math
import shutil
from pathlib import Path
from typing import Any, Iterator

from scenegen.atomic import atomic_directory, write_text_atomic
from scenegen.catalog import (EVALUATED_PREFIXES, chunk_count, chunk_frames, scene_ids, scene_reference_spp,
                              scene_render_config)
from scenegen.digests import render_digest
from scenegen.render import reference_batch_seeds

REFERENCES_DIR = "references"
META_FILE = "meta.json"
#: Bumped when the layout of a stored reference changes.
REFERENCE_FORMAT = 1


class ReferenceStoreError(RuntimeError):
    """A stored reference is corrupt, incomplete, or does not match what it is filed as."""


def file_digest(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks (the model store's digests too)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def store_root(cfg: dict) -> Path:
    """The store folder (``store.path``, default ``store``)."""
    return Path((cfg.get("store") or {}).get("path", "store"))


def references_enabled(cfg: dict) -> bool:
    """``store.use`` and ``store.references`` (both default true)."""
    settings = cfg.get("store") or {}
    return bool(settings.get("use", True)) and bool(settings.get("references", True))


def evaluated_scenes(cfg: dict) -> list[str]:
    """The scenes whose references may be stored: the evaluated test_* and custom_* scenes of ``cfg``."""
    return [scene for scene in scene_ids(cfg) if scene.startswith(EVALUATED_PREFIXES)]


def reference_key(cfg: dict, scene: str) -> str:
    """SHA-256 key of ``scene``'s references: its id (a render digest holds the settings a scene depends on, not
    which scene it is) and its reference render digest."""
    payload = {"format": REFERENCE_FORMAT, "scene": scene, "render": render_digest(cfg, scene, "reference")}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def entry_folder(root: Path, scene: str, key: str) -> Path:
    return Path(root) / REFERENCES_DIR / scene / key[:16]


def reference_entry(cfg: dict, scene: str) -> Path | None:
    """The stored reference folder of ``scene`` under ``cfg``'s reference render digest, or None."""
    if not scene.startswith(EVALUATED_PREFIXES):
        return None
    key = reference_key(cfg, scene)
    folder = entry_folder(store_root(cfg), scene, key)
    if not (folder / META_FILE).is_file():
        return None
    if _read_meta(folder).get("key") != key:
        raise ReferenceStoreError(f"{folder / META_FILE}: records another key than {key[:16]}, the folder it is "
                                  "filed under; restore it from git or publish the reference again")
    return folder


def _read_meta(folder: Path) -> dict[str, Any]:
    path = folder / META_FILE
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ReferenceStoreError(f"{path}: unreadable ({error})") from error


def _check(folder: Path, files: dict[str, str]) -> None:
    for name, digest in files.items():
        path = folder / name
        if not path.is_file():
            raise ReferenceStoreError(f"{path}: missing from the stored reference")
        actual = file_digest(path)
        if actual != digest:
            raise ReferenceStoreError(f"{path}: corrupt or truncated (SHA-256 {actual[:12]}…, published "
                                      f"{digest[:12]}…); restore it from git (git checkout -- {path}) or render "
                                      "with store.references false")


def chunk_name(chunk: int) -> str:
    return f"chunk_{chunk:03d}"


def install_reference_chunk(cfg: dict, scene: str, chunk: int, out_dir: Path) -> Path | None:
    """Write chunk ``chunk`` of ``scene``'s references to ``out_dir`` (atomically) from the store when it is stored
    under ``cfg``'s key and ``store.references`` is on; return the entry folder, or None (render it)."""
    if not references_enabled(cfg):
        return None
    folder = reference_entry(cfg, scene)
    if folder is None:
        return None
    prefix = chunk_name(chunk) + "/"
    files = {name: digest for name, digest in _read_meta(folder).get("files", {}).items() if name.startswith(prefix)}
    expected = {f"{prefix}frame_{frame:04d}.{ext}" for frame in chunk_frames(cfg, scene, chunk)
                for ext in ("exr", "json")}
    if set(files) != expected:
        raise ReferenceStoreError(f"{folder}: the stored {chunk_name(chunk)} holds {sorted(files)}, not the "
                                  f"frames {sorted(expected)} this config renders; publish the reference again")
    _check(folder, files)
    with atomic_directory(Path(out_dir)) as staging:
        for name in sorted(files):
            shutil.copy2(folder / name, staging / Path(name).name)
    return folder


def rendered_chunk_problems(cfg: dict, scene: str, chunk: int, chunk_dir: Path) -> list[str]:
    """Why ``chunk_dir`` is not chunk ``chunk`` of ``scene``'s references as ``cfg`` renders them (empty: it is):
    every frame's EXR and sidecar present, and the sidecars' scene, spp, sample seeds (global seed, pass size),
    variant, size and integrator."""
    render = scene_render_config(cfg, scene)
    want = {"scene": scene, "spp": scene_reference_spp(cfg, scene), "width": render["width"],
            "height": render["height"], "integrator": "path" if render["reference_integrator"] == "path"
            else "mcdn_features"}
    problems = []
    for frame in chunk_frames(cfg, scene, chunk):
        exr, sidecar = chunk_dir / f"frame_{frame:04d}.exr", chunk_dir / f"frame_{frame:04d}.json"
        if not exr.is_file() or not sidecar.is_file():
            problems.append(f"{exr if not exr.is_file() else sidecar}: missing")
            continue
        meta = json.loads(sidecar.read_text())
        for key, value in want.items():
            if meta.get(key) != value:
                problems.append(f"{sidecar}: {key} {meta.get(key)!r}, the config renders {value!r}")
        n_batches = math.ceil(want["spp"] // 2 / render["reference_batch_spp"])   # the global seed and pass size
        seeds = {f"half{half}": reference_batch_seeds(cfg["seed"], scene, frame, half, n_batches) for half in (0, 1)}
        if meta.get("seeds") != seeds:
            problems.append(f"{sidecar}: sample seeds of another seed or pass size than the config's")
        if meta.get("variant") != render["variant"]:   # e.g. a scalar_rgb fallback, or cuda_ad_rgb
            problems.append(f"{sidecar}: variant {meta.get('variant')!r}, the config renders {render['variant']!r}")
    return problems


def publish_reference(cfg: dict, scene: str, render_root: Path) -> tuple[Path, str]:
    """Store ``scene``'s rendered references (``<render_root>/<scene>/reference/chunk_*``) under ``cfg``'s key;
    refuses chunks rendered with other settings and a key that holds other files."""
    if not scene.startswith(EVALUATED_PREFIXES):
        raise ReferenceStoreError(f"{scene}: only the evaluated scenes' references (test_*, custom_*) are stored")
    key = reference_key(cfg, scene)
    folder = entry_folder(store_root(cfg), scene, key)
    source = Path(render_root) / scene / "reference"
    names = [f"{chunk_name(chunk)}/frame_{frame:04d}.{ext}" for chunk in range(chunk_count(cfg, scene))
             for frame in chunk_frames(cfg, scene, chunk) for ext in ("exr", "json")]
    problems = [problem for chunk in range(chunk_count(cfg, scene))
                for problem in rendered_chunk_problems(cfg, scene, chunk, source / chunk_name(chunk))]
    if problems:
        raise ReferenceStoreError(f"{source}: not this config's reference of {scene}:\n  " + "\n  ".join(problems))
    files = {name: file_digest(source / name) for name in names}
    if (folder / META_FILE).is_file():
        if _read_meta(folder).get("files") != files:
            raise ReferenceStoreError(f"{folder}: key {key[:16]} already holds other files; refusing (the renderer "
                                      "changed? remove the entry and publish again, in its own commit)")
        return folder, "already published"
    with atomic_directory(folder) as staging:
        for name in names:
            (staging / name).parent.mkdir(exist_ok=True)
            shutil.copy2(source / name, staging / name)
        record = {"format": REFERENCE_FORMAT, "key": key, "scene": scene, "spp": scene_reference_spp(cfg, scene),
                  "chunks": chunk_count(cfg, scene), "files": files,
                  "published": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
        write_text_atomic(staging / META_FILE, json.dumps(record, indent=1, sort_keys=True) + "\n")
    return folder, "published"


def stored_references(root: Path) -> Iterator[tuple[str, Path, dict[str, Any]]]:
    """Every stored reference under ``root``: (scene, folder, meta)."""
    for meta_file in sorted((Path(root) / REFERENCES_DIR).glob(f"*/*/{META_FILE}")):
        yield meta_file.parent.parent.name, meta_file.parent, _read_meta(meta_file.parent)


def reference_problems(root: Path) -> list[str]:
    """Every stored reference's files against their recorded digests (one line per problem)."""
    problems = []
    for _, folder, meta in stored_references(root):
        try:
            if not meta.get("files"):
                raise ReferenceStoreError(f"{folder}: the entry records no file digests")
            if folder.name != str(meta.get("key", ""))[:16]:
                raise ReferenceStoreError(f"{folder / META_FILE}: key {str(meta.get('key'))[:16]} is not its folder")
            _check(folder, meta["files"])
        except ReferenceStoreError as error:
            problems.append(str(error))
    return problems
