"""Determinism, seeding, atomic outputs and error reporting of the pipeline's jobs (scenegen.jobs).

Jobs run in-process on one tiny scene (32x32 pixels, 2 frames, 2 spp, 8-spp references), generated
once per module.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import scenegen.dataset
import scenegen.exr
import scenegen.mitsuba_scene
from scenegen import jobs
from scenegen.config import ConfigError, load_config
from scenegen.dataset import load_clip
from scenegen.exr import read_exr

REPO_ROOT = Path(__file__).resolve().parents[1]
SCENE = "train_000"
# Sidecar keys that measure wall-clock time and so legitimately differ between identical renders.
TIMING_KEYS = {"timing_s", "samples_per_s"}
# Per-pixel channels from the non-jittered pixel-centre pass: independent of the sample seed.
PIXEL_CENTRE_PREFIXES = ("motion.", "gbuffer.")


class SimulatedCrash(Exception):
    """Raised by the monkeypatched writers to interrupt a job."""


@pytest.fixture(scope="module")
def tiny_cfg() -> dict:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["render"].update(width=32, height=32, spp=2, reference_spp=8, reference_batch_spp=4)
    cfg["scenes"].update(frames=2, frames_per_chunk=2)
    return cfg


@pytest.fixture(scope="module")
def work_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("determinism")


@pytest.fixture(scope="module")
def scene_dir(tiny_cfg, work_dir) -> Path:
    out = work_dir / "scenes" / SCENE
    jobs.run_generate(tiny_cfg, SCENE, out)
    return out


def _render_noisy(cfg: dict, scene_dir: Path, out: Path) -> Path:
    jobs.run_render_noisy(cfg, SCENE, 0, scene_dir, out)
    return out


@pytest.fixture(scope="module")
def noisy_a(tiny_cfg, scene_dir, work_dir) -> Path:
    return _render_noisy(tiny_cfg, scene_dir, work_dir / "a" / "noisy" / "chunk_000")


@pytest.fixture(scope="module")
def noisy_b(tiny_cfg, scene_dir, work_dir) -> Path:
    return _render_noisy(tiny_cfg, scene_dir, work_dir / "b" / "noisy" / "chunk_000")


@pytest.fixture(scope="module")
def noisy_other_seed(tiny_cfg, scene_dir, work_dir) -> Path:
    cfg = copy.deepcopy(tiny_cfg)
    cfg["seed"] += 1
    return _render_noisy(cfg, scene_dir, work_dir / "other_seed" / "noisy" / "chunk_000")


@pytest.fixture(scope="module")
def reference_a(tiny_cfg, scene_dir, work_dir) -> Path:
    out = work_dir / "a" / "reference" / "chunk_000"
    jobs.run_render_reference(tiny_cfg, SCENE, 0, scene_dir, out)
    return out


def _frames(chunk_dir: Path) -> list[Path]:
    frames = sorted(chunk_dir.glob("frame_*.exr"))
    assert [p.name for p in frames] == ["frame_0000.exr", "frame_0001.exr"]
    return frames


def _without_timing(meta: dict) -> dict:
    return {key: value for key, value in meta.items() if key not in TIMING_KEYS}


def _meta(exr_path: Path) -> dict:
    return json.loads(exr_path.with_suffix(".json").read_text())


def _bits(plane: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(plane, dtype=np.float32).view(np.uint32)


# ---------------------------------------------------------------------------------------------------
# Determinism and seeds
# ---------------------------------------------------------------------------------------------------

def test_noisy_render_is_bit_exact_across_runs(noisy_a: Path, noisy_b: Path) -> None:
    for path_a, path_b in zip(_frames(noisy_a), _frames(noisy_b)):
        planes_a, _ = read_exr(path_a)
        planes_b, _ = read_exr(path_b)
        assert sorted(planes_a) == sorted(planes_b)
        assert any(name.startswith("s01.radiance") for name in planes_a)
        differing = [name for name in planes_a if not np.array_equal(_bits(planes_a[name]), _bits(planes_b[name]))]
        assert not differing, f"{path_a.name}: channels differ between identical runs: {differing}"
        assert _without_timing(_meta(path_a)) == _without_timing(_meta(path_b))


def test_other_global_seed_changes_radiance_but_not_pixel_centre_buffers(noisy_a: Path,
                                                                         noisy_other_seed: Path) -> None:
    for path_a, path_other in zip(_frames(noisy_a), _frames(noisy_other_seed)):
        planes_a, _ = read_exr(path_a)
        planes_other, _ = read_exr(path_other)
        for name in (n for n in planes_a if ".radiance." in n):
            # 32x32 independent samples: identical planes would mean the seed is ignored.
            assert not np.array_equal(planes_a[name], planes_other[name]), f"{path_a.name}: {name} unchanged"
        for name in (n for n in planes_a if n.startswith(PIXEL_CENTRE_PREFIXES)):
            assert np.array_equal(_bits(planes_a[name]), _bits(planes_other[name])), name
        assert _meta(path_a)["seeds"] != _meta(path_other)["seeds"]


def _as_seed_list(value) -> list[int]:
    return [int(v) for v in value] if isinstance(value, list) else [int(value)]


@pytest.mark.slow
def test_reference_halves_have_own_seeds_and_differ(tiny_cfg: dict, noisy_a: Path, reference_a: Path) -> None:
    n_batches = tiny_cfg["render"]["reference_spp"] // 2 // tiny_cfg["render"]["reference_batch_spp"]
    noisy_seeds = {seed for path in _frames(noisy_a) for seed in _as_seed_list(_meta(path)["seeds"]["layers"])}
    seen: set[int] = set()
    for path in _frames(reference_a):
        meta = _meta(path)
        half0, half1 = meta["seeds"]["half0"], meta["seeds"]["half1"]
        assert len(half0) == len(half1) == n_batches
        frame_seeds = half0 + half1
        assert len(set(frame_seeds)) == len(frame_seeds), f"{path.name}: a seed is reused {meta['seeds']}"
        assert not set(frame_seeds) & noisy_seeds, f"{path.name}: reference reuses a noisy seed"
        assert not set(frame_seeds) & seen, f"{path.name}: reference reuses another frame's seed"
        seen |= set(frame_seeds)

        planes, _ = read_exr(path)
        h0 = np.stack([planes[f"radiance_half0.{c}"] for c in "RGB"])
        h1 = np.stack([planes[f"radiance_half1.{c}"] for c in "RGB"])
        full = np.stack([planes[f"radiance.{c}"] for c in "RGB"])
        assert not np.array_equal(h0, h1), f"{path.name}: the two halves are identical"
        np.testing.assert_allclose(full, 0.5 * (h0 + h1), rtol=1e-5, atol=1e-6)
        assert np.isfinite(meta["psnr_halves"])


# ---------------------------------------------------------------------------------------------------
# Interrupted jobs
# ---------------------------------------------------------------------------------------------------

def _crash_on_second_write(monkeypatch) -> list[set[str]]:
    """Patch write_exr so the first call writes and the second raises SimulatedCrash.

    Returns a list that receives, at the crash, the names in the directory being written, so the
    test can check that a complete-looking first frame really existed before the crash.
    """
    real_write = scenegen.exr.write_exr
    calls: list[Path] = []
    seen_at_crash: list[set[str]] = []

    def flaky_write(path, *args, **kwargs):
        calls.append(Path(path))
        if len(calls) >= 2:
            seen_at_crash.append({p.name for p in Path(path).parent.iterdir()})
            raise SimulatedCrash(f"simulated crash while writing {path}")
        return real_write(path, *args, **kwargs)

    monkeypatch.setattr(scenegen.exr, "write_exr", flaky_write)
    monkeypatch.setattr(jobs, "write_exr", flaky_write, raising=False)  # in case jobs imports it at top level
    monkeypatch.setattr(scenegen.dataset, "write_exr", flaky_write)      # the frame writer (dataset.write_frame)
    return seen_at_crash


@pytest.mark.parametrize("kind", ["noisy", "reference"])
def test_interrupted_render_leaves_no_output(kind: str, tiny_cfg, scene_dir: Path, tmp_path: Path,
                                             monkeypatch) -> None:
    seen_at_crash = _crash_on_second_write(monkeypatch)
    out = tmp_path / "renders" / SCENE / kind / "chunk_000"
    run = jobs.run_render_noisy if kind == "noisy" else jobs.run_render_reference
    with pytest.raises(SimulatedCrash):
        run(tiny_cfg, SCENE, 0, scene_dir, out)
    assert seen_at_crash and {"frame_0000.exr", "frame_0000.json"} <= seen_at_crash[0], \
        "the crash did not happen after a complete first frame, so the test proves nothing"
    assert not out.exists()
    assert list(out.parent.iterdir()) == [], "a temporary directory was left beside the output"


def test_interrupted_rerun_keeps_previous_complete_output(tiny_cfg, scene_dir: Path, noisy_a: Path,
                                                          tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "noisy" / "chunk_000"
    shutil.copytree(noisy_a, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    _crash_on_second_write(monkeypatch)
    with pytest.raises(SimulatedCrash):
        jobs.run_render_noisy(tiny_cfg, SCENE, 0, scene_dir, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in out.parent.iterdir()] == ["chunk_000"]


def test_interrupted_generate_leaves_no_output(tiny_cfg, tmp_path: Path, monkeypatch) -> None:
    seen_manifest: list[bool] = []

    def crashing_preview(manifest: dict, draft_dir: Path) -> float:
        # Called after the draft's manifest, meshes and textures are written: the worst moment to die.
        seen_manifest.append((Path(draft_dir) / "manifest.json").is_file())
        raise SimulatedCrash("simulated crash during the preview render")

    monkeypatch.setattr(scenegen.mitsuba_scene, "preview_mean_luminance", crashing_preview)
    out = tmp_path / "scenes" / SCENE
    with pytest.raises(SimulatedCrash):
        jobs.run_generate(tiny_cfg, SCENE, out)
    assert seen_manifest == [True]
    assert not out.exists()
    assert list(out.parent.iterdir()) == [], "a temporary directory was left beside the output"


# ---------------------------------------------------------------------------------------------------
# Corrupt input and bad configuration
# ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["noisy", "reference"])
def test_render_without_manifest_names_the_manifest(kind: str, tiny_cfg, tmp_path: Path) -> None:
    scene_without_manifest = tmp_path / "scenes" / SCENE
    (scene_without_manifest / "meshes").mkdir(parents=True)
    out = tmp_path / "renders" / SCENE / kind / "chunk_000"
    run = jobs.run_render_noisy if kind == "noisy" else jobs.run_render_reference
    with pytest.raises(Exception) as caught:
        run(tiny_cfg, SCENE, 0, scene_without_manifest, out)
    assert str(scene_without_manifest / "manifest.json") in str(caught.value)
    assert not out.exists()


@pytest.mark.parametrize("keep_fraction", [0.5, 0.01])  # pixel data cut / header cut
def test_load_clip_names_a_truncated_frame(keep_fraction: float, noisy_a: Path, tmp_path: Path) -> None:
    render_dir = tmp_path / "renders" / SCENE
    shutil.copytree(noisy_a, render_dir / "noisy" / "chunk_000")
    broken = render_dir / "noisy" / "chunk_000" / "frame_0001.exr"
    data = broken.read_bytes()
    broken.write_bytes(data[: max(1, int(len(data) * keep_fraction))])
    with pytest.raises(Exception) as caught:
        load_clip(render_dir, reference=False)
    assert str(broken) in str(caught.value)


def test_config_with_zero_spp_is_rejected_naming_the_key(tmp_path: Path) -> None:
    minimal = tmp_path / "minimal.yaml"
    minimal.write_text("render: {spp: 0}\n")
    with pytest.raises(ConfigError, match=r"render\.spp"):
        load_config(minimal)

    # In an otherwise valid config, spp is the only problem reported.
    smoke = (REPO_ROOT / "config" / "smoke.yaml").read_text()
    assert "  spp: 4\n" in smoke
    full = tmp_path / "full.yaml"
    full.write_text(smoke.replace("  spp: 4\n", "  spp: 0\n"))
    with pytest.raises(ConfigError) as caught:
        load_config(full)
    problems = [line for line in str(caught.value).splitlines() if line.strip().startswith("- ")]
    assert len(problems) == 1 and "render.spp" in problems[0], str(caught.value)
