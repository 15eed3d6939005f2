"""Stored references of the evaluated scenes (scenegen.reference_store) and per-scene reference spp
(render.test_reference_spp_per_scene): a render_reference job copies a stored chunk bit for bit instead of
rendering, only under its own render digest, and refuses corrupt or mismatched entries by name.

One tiny real reference (32x32 pixels, 2 frames, 8 spp) is rendered with Mitsuba per module."""
from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import pytest

import scenegen.jobs
from scenegen import jobs
from scenegen.catalog import scene_reference_spp
from scenegen.config import ConfigError, load_config, validate_config
from scenegen.digests import render_digest
from scenegen.reference_store import (ReferenceStoreError, install_reference_chunk, publish_reference,
                                      reference_entry, reference_key, reference_problems)

REPO_ROOT = Path(__file__).resolve().parents[1]
SCENE = "test_000"


@pytest.fixture(scope="module")
def tiny_cfg(tmp_path_factory) -> dict:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["render"].update(width=32, height=32, spp=2, reference_spp=8, test_reference_spp=8, reference_batch_spp=4)
    cfg["scenes"].update(frames=2, frames_per_chunk=2)
    cfg["store"] = {**cfg.get("store", {}), "path": str(tmp_path_factory.mktemp("store"))}
    return cfg


@pytest.fixture(scope="module")
def rendered(tiny_cfg, tmp_path_factory) -> Path:
    """<root>/renders/test_000/reference/chunk_000 rendered by the job, with an empty store."""
    root = tmp_path_factory.mktemp("run")
    jobs.run_generate(tiny_cfg, SCENE, root / "scenes" / SCENE)
    out = root / "renders" / SCENE / "reference" / "chunk_000"
    jobs.run_render_reference(tiny_cfg, SCENE, 0, root / "scenes" / SCENE, out)
    return out


@pytest.fixture(scope="module")
def published(tiny_cfg, rendered) -> Path:
    folder, what = publish_reference(tiny_cfg, SCENE, rendered.parents[2])
    assert what == "published"
    return folder


def _no_render(*args, **kwargs):
    raise AssertionError("rendered although the chunk is stored")


def test_job_copies_the_stored_chunk_bit_for_bit(tiny_cfg, rendered, published, tmp_path, monkeypatch):
    monkeypatch.setattr(scenegen.jobs, "render_reference_frame", _no_render)
    out = tmp_path / "renders" / SCENE / "reference" / "chunk_000"
    jobs.run_render_reference(tiny_cfg, SCENE, 0, tmp_path / "no-scene-needed", out)
    names = sorted(p.name for p in rendered.iterdir() if p.name.startswith("frame_"))
    assert names == sorted(p.name for p in out.iterdir()) and len(names) == 4
    for name in names:
        assert (out / name).read_bytes() == (rendered / name).read_bytes(), name
    assert published == reference_entry(tiny_cfg, SCENE)
    assert publish_reference(tiny_cfg, SCENE, rendered.parents[2])[1] == "already published"


def test_another_reference_spp_is_another_key_and_renders(tiny_cfg, published, tmp_path, monkeypatch):
    cfg = copy.deepcopy(tiny_cfg)
    cfg["render"]["test_reference_spp_per_scene"] = {SCENE: 16}
    assert render_digest(cfg, SCENE, "reference") != render_digest(tiny_cfg, SCENE, "reference")
    assert reference_key(cfg, SCENE) != reference_key(tiny_cfg, SCENE)
    assert reference_entry(cfg, SCENE) is None
    monkeypatch.setattr(scenegen.jobs, "render_reference_frame", _no_render)
    with pytest.raises(Exception, match="rendered although|manifest"):   # the job goes on to render
        jobs.run_render_reference(cfg, SCENE, 0, tmp_path / "scene", tmp_path / "out")


def test_store_references_false_renders(tiny_cfg, published, tmp_path):
    cfg = copy.deepcopy(tiny_cfg)
    cfg["store"]["references"] = False
    assert install_reference_chunk(cfg, SCENE, 0, tmp_path / "out") is None and not (tmp_path / "out").exists()


def test_the_key_tells_scenes_apart(tiny_cfg):
    """Two test scenes have equal render digests (the settings a scene depends on); their keys differ."""
    assert render_digest(tiny_cfg, "test_000", "reference") == render_digest(tiny_cfg, "test_001", "reference")
    assert reference_key(tiny_cfg, "test_000") != reference_key(tiny_cfg, "test_001")


def test_only_evaluated_scenes_are_stored(tiny_cfg, rendered):
    with pytest.raises(ReferenceStoreError, match="only the evaluated scenes"):
        publish_reference(tiny_cfg, "train_000", rendered.parents[2])
    assert reference_entry(tiny_cfg, "train_000") is None


def test_a_corrupt_stored_file_is_named(tiny_cfg, published, tmp_path):
    cfg = copy.deepcopy(tiny_cfg)
    cfg["store"]["path"] = str(tmp_path / "store")
    shutil.copytree(Path(tiny_cfg["store"]["path"]), tmp_path / "store")
    entry = reference_entry(cfg, SCENE)
    victim = entry / "chunk_000" / "frame_0001.exr"
    victim.write_bytes(victim.read_bytes()[:-10])
    with pytest.raises(ReferenceStoreError, match="frame_0001.exr: corrupt or truncated"):
        install_reference_chunk(cfg, SCENE, 0, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert any("frame_0001.exr: corrupt" in problem for problem in reference_problems(tmp_path / "store"))
    assert reference_problems(Path(tiny_cfg["store"]["path"])) == []


def test_publish_refuses_a_chunk_of_other_settings(tiny_cfg, rendered, tmp_path):
    cfg = copy.deepcopy(tiny_cfg)
    cfg["store"]["path"] = str(tmp_path / "store")
    other = tmp_path / "renders" / SCENE / "reference" / "chunk_000"
    shutil.copytree(rendered, other)
    sidecar = other / "frame_0001.json"
    sidecar.write_text(json.dumps({**json.loads(sidecar.read_text()), "spp": 4}))
    with pytest.raises(ReferenceStoreError, match=r"frame_0001.json: spp 4, the config renders 8"):
        publish_reference(cfg, SCENE, tmp_path / "renders")
    sidecar.write_text(json.dumps({**json.loads(sidecar.read_text()), "spp": 8}))
    seeded = copy.deepcopy(cfg)
    seeded["seed"] += 1
    with pytest.raises(ReferenceStoreError, match=r"frame_0001.json: sample seeds of another seed"):
        publish_reference(seeded, SCENE, tmp_path / "renders")
    (other / "frame_0000.exr").unlink()
    with pytest.raises(ReferenceStoreError, match="frame_0000.exr: missing"):
        publish_reference(cfg, SCENE, tmp_path / "renders")
    assert not (tmp_path / "store").exists()


def test_publish_refuses_other_files_under_a_stored_key(tiny_cfg, rendered, published, tmp_path):
    other = tmp_path / "renders" / SCENE / "reference" / "chunk_000"
    shutil.copytree(rendered, other)
    sidecar = other / "frame_0000.json"
    sidecar.write_text(sidecar.read_text() + " ")
    with pytest.raises(ReferenceStoreError, match="already holds other files"):
        publish_reference(tiny_cfg, SCENE, tmp_path / "renders")


def test_an_entry_filed_under_another_key_is_refused(tiny_cfg, published, tmp_path):
    cfg = copy.deepcopy(tiny_cfg)
    cfg["store"]["path"] = str(tmp_path / "store")
    shutil.copytree(Path(tiny_cfg["store"]["path"]), tmp_path / "store")
    entry = reference_entry(cfg, SCENE)
    meta = json.loads((entry / "meta.json").read_text())
    (entry / "meta.json").write_text(json.dumps({**meta, "key": "0" * 64}))
    with pytest.raises(ReferenceStoreError, match="records another key"):
        install_reference_chunk(cfg, SCENE, 0, tmp_path / "out")


# ------------------------------------------------------------------ render.test_reference_spp_per_scene
def _default() -> dict:
    return load_config(REPO_ROOT / "config" / "config.yaml")


def test_per_scene_spp_changes_only_that_scenes_reference():
    cfg = _default()
    plain = copy.deepcopy(cfg)
    plain["render"]["test_reference_spp_per_scene"] = {}
    named = set(cfg["render"]["test_reference_spp_per_scene"])
    assert named and all(scene_reference_spp(cfg, s) != cfg["render"]["test_reference_spp"] for s in named)
    for scene in ["train_000", "train_025", "test_000", "test_002", "custom_spheres_room", *sorted(named)]:
        for kind in ("noisy", "reference"):
            same = render_digest(cfg, scene, kind) == render_digest(plain, scene, kind)
            assert same == (kind == "noisy" or scene not in named), (scene, kind)


@pytest.mark.parametrize("per_scene, message", [
    ({"test_001": 4097}, "must be a multiple of 2"),
    ({"tset_001": 4096}, "tset_001"),
    ({"train_000": 4096}, "train_000"),
    ({"test_001": 0}, "out of range"),
])
def test_per_scene_spp_is_checked(per_scene, message):
    raw = _default()
    raw["render"]["test_reference_spp_per_scene"] = per_scene
    with pytest.raises(ConfigError, match=message):
        validate_config(raw)


def test_a_name_the_config_lacks_is_ignored():
    cfg = _default()
    cfg["render"]["test_reference_spp_per_scene"] = {"test_099": 8192}
    validate_config(cfg)
    from scenegen.catalog import evaluated_reference_text

    assert evaluated_reference_text(cfg) == f"{cfg['render']['test_reference_spp']} spp"
