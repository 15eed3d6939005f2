"""Volumetric clips through the scene jobs (scenegen.volumes.render, scenegen.volumes.motion): config ids and
settings, digests, the rendered files and their buffers, the closest-collision G-buffer, motion vectors
(zero and valid under light and transfer-function edits; under camera motion checked against Mitsuba's own
sensor projection and by warping the previous reference), determinism."""
from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from scenegen import jobs
from scenegen.catalog import scene_ids, scene_reference_spp, scene_render_config, volume_clip_spec, volume_scene_ids
from scenegen.config import load_config
from scenegen.channels import VOLUME_BUFFERS
from scenegen.dataset import MissingBufferError, load_clip, load_reference_frame
from scenegen.digests import render_digest, scene_digest
from scenegen.motion import warp_previous
from scenegen.volumes.motion import OBJECT_ENVIRONMENT, OBJECT_MEDIUM, OBJECT_SURFACE, closest_collision_gbuffer

ROOT = Path(__file__).resolve().parents[1]


def _config(**volumes) -> dict:
    cfg = load_config(ROOT / "config/smoke.yaml")
    cfg["volumes"].update({"enabled": True, "scenarios": ["camera", "light", "transfer_function"], "n_test": 1,
                           "n_train": 0, "frames": 3, "width": 24, "height": 20, "spp": 4, "reference_spp": 32,
                           "resolution": 12, **volumes})
    return cfg


def _render(cfg: dict, scene_id: str, root: Path) -> Path:
    scene_dir = root / "scenes" / scene_id
    jobs.run_generate(cfg, scene_id, scene_dir)
    jobs.run_render_noisy(cfg, scene_id, 0, scene_dir, root / "renders" / scene_id / "noisy" / "chunk_000")
    jobs.run_render_reference(cfg, scene_id, 0, scene_dir, root / "renders" / scene_id / "reference" / "chunk_000")
    return root / "renders" / scene_id


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> tuple[dict, Path]:
    cfg = _config()
    root = tmp_path_factory.mktemp("volumes")
    for scene_id in volume_scene_ids(cfg):
        _render(cfg, scene_id, root)
    return cfg, root


# --- config ----------------------------------------------------------------------------------------------------

def test_scene_ids_and_settings_come_from_the_volumes_section() -> None:
    cfg = _config(n_train=2, scenarios=["light", "transfer_function"])
    ids = volume_scene_ids(cfg)
    assert ids == ["vol_test_light_000", "vol_test_transfer_function_000", "vol_train_light_000",
                   "vol_train_light_001", "vol_train_transfer_function_000", "vol_train_transfer_function_001"]
    assert volume_clip_spec(cfg, "vol_train_transfer_function_001") == ("train", "transfer_function", 1)
    assert not set(ids) & set(scene_ids(cfg))             # never in the surface split or evaluation
    settings = scene_render_config(cfg, "vol_test_light_000")
    assert (settings["width"], settings["height"], settings["spp"], settings["extra_radiance_spp"]) == (24, 20, 4, 0)
    assert scene_reference_spp(cfg, "vol_test_light_000") == 32
    with pytest.raises(KeyError, match="vol_test_camera_000"):
        volume_clip_spec(cfg, "vol_test_camera_000")
    cfg["volumes"]["enabled"] = False
    assert volume_scene_ids(cfg) == []


def test_volumes_section_changes_only_volume_digests() -> None:
    cfg = _config()
    changed = copy.deepcopy(cfg)
    changed["volumes"]["resolution"] = 16
    changed["volumes"]["reference_spp"] = 64
    surface = scene_ids(cfg)[0]
    assert scene_digest(cfg, surface) == scene_digest(changed, surface)
    assert render_digest(cfg, surface, "reference") == render_digest(changed, surface, "reference")
    volume = volume_scene_ids(cfg)[0]
    assert scene_digest(cfg, volume) != scene_digest(changed, volume)
    assert render_digest(cfg, volume, "reference") != render_digest(changed, volume, "reference")


# --- closest collision -----------------------------------------------------------------------------------------

def test_closest_collision_gbuffer_picks_the_nearest_collided_sample() -> None:
    depth = np.array([[0.0, 3.0], [2.0, 0.0], [5.0, 0.0]], np.float32).reshape(3, 1, 1, 2)   # (S, 1, H=1, W=2)
    position = np.arange(3 * 3 * 2, dtype=np.float32).reshape(3, 3, 1, 2)
    medium = np.array([[0, 1], [1, 0], [0, 0]], np.float32).reshape(3, 1, 1, 2)
    albedo = position[::-1] / 20.0
    g = closest_collision_gbuffer({"depth": depth, "position": position, "medium": medium, "albedo": albedo})
    assert g["depth"][0, 0].tolist() == [2.0, 3.0]                 # pixel 0: layer 1; pixel 1: layer 0
    np.testing.assert_array_equal(g["position"][:, 0, 0], position[1, :, 0, 0])
    np.testing.assert_array_equal(g["position"][:, 0, 1], position[0, :, 0, 1])
    np.testing.assert_array_equal(g["albedo"][:, 0, 0], albedo[1, :, 0, 0])      # the same collision's albedo
    np.testing.assert_array_equal(g["albedo"][:, 0, 1], albedo[0, :, 0, 1])
    assert g["object"][0, 0].tolist() == [OBJECT_MEDIUM, OBJECT_MEDIUM]
    nothing = closest_collision_gbuffer({"depth": np.zeros_like(depth), "position": position, "medium": medium,
                                         "albedo": albedo})
    assert (nothing["object"] == OBJECT_ENVIRONMENT).all() and not nothing["position"].any()
    assert not nothing["albedo"].any()
    assert not g["normal"].any() and not g["roughness"].any()


# --- rendered clips --------------------------------------------------------------------------------------------

def test_rendered_clips_hold_the_volume_buffers(rendered) -> None:
    cfg, root = rendered
    for scene_id in volume_scene_ids(cfg):
        clip = load_clip(root / "renders" / scene_id, buffers=VOLUME_BUFFERS)
        assert clip.samples["radiance"].shape == (3, 4, 3, 20, 24)
        assert set(clip.samples) == set(VOLUME_BUFFERS)
        medium = clip.samples["medium"]
        assert set(np.unique(medium)) <= {0.0, 1.0} and medium.any()          # the medium is seen
        sigma_t = clip.samples["sigma_t"]
        assert (sigma_t[medium == 0] == 0).all() and (sigma_t[medium == 1] > 0).all()
        transmittance = clip.samples["transmittance"]
        assert transmittance.min() >= 0.0 and transmittance.max() <= 1.0
        assert set(np.unique(clip.gbuffer["object"])) <= {OBJECT_ENVIRONMENT, OBJECT_SURFACE, OBJECT_MEDIUM}
        with pytest.raises(MissingBufferError, match="diffuse"):
            load_clip(root / "renders" / scene_id)                 # a surface method's buffers are named
        reference, meta = load_reference_frame(root / "renders" / scene_id / "reference/chunk_000/frame_0001.exr")
        assert meta["integrator"] == "volpath" and meta["spp"] == 32
        assert set(reference) == {"radiance", "radiance_half0", "radiance_half1"}
        noisy_meta = json.loads((root / "renders" / scene_id / "noisy/chunk_000/frame_0001.json").read_text())
        assert noisy_meta["integrator"] == "mcdn_volpath_features"
        assert noisy_meta["volume"]["scenario"] == volume_clip_spec(cfg, scene_id)[1]
        # The noisy mean and the volpath reference estimate the same image (loose: 4 spp over 480 pixels).
        noisy_mean = clip.samples["radiance"].mean(axis=(1, 3, 4))
        reference_mean = reference["radiance"].mean(axis=(1, 2))
        np.testing.assert_allclose(noisy_mean[1], reference_mean, rtol=0.2)


@pytest.mark.parametrize("scenario", ["light", "transfer_function"])
def test_motion_is_zero_and_valid_when_only_the_light_or_the_transfer_function_changes(rendered, scenario) -> None:
    _, root = rendered
    clip = load_clip(root / "renders" / f"vol_test_{scenario}_000", buffers=("radiance",))
    assert not clip.motion.any()
    assert not clip.valid[0].any() and clip.valid[1:].all()


def test_camera_motion_follows_mitsubas_projection_of_the_closest_collision(rendered) -> None:
    """prev_pixel = centre + motion equals the film position Mitsuba's own sensor of the previous frame gives for
    the closest collision (sensor.sample_direction), for every pixel that has one."""
    import drjit as dr
    import mitsuba as mi

    from scenegen.volumes.scenes import VolumeClip

    cfg, root = rendered
    scene_id = "vol_test_camera_000"
    clip = load_clip(root / "renders" / scene_id, buffers=("radiance",))
    manifest = json.loads((root / "scenes" / scene_id / "manifest.json").read_text())
    volume = VolumeClip.from_manifest(manifest)
    height, width = clip.motion.shape[-2:]
    jj, ii = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    for frame in (1, 2):
        hit = clip.gbuffer["object"][frame, 0] != OBJECT_ENVIRONMENT
        assert hit.mean() > 0.5
        points = clip.gbuffer["position"][frame][:, hit].T.astype(np.float64)
        sensor = mi.load_dict(volume.scene_dict(frame - 1, width=width, height=height, spp=1)["sensor"])
        interaction = dr.zeros(mi.Interaction3f, len(points))
        interaction.p = mi.Point3f(*(points[:, axis] for axis in range(3)))
        direction_sample, _ = sensor.sample_direction(interaction, mi.Point2f(0.5, 0.5))
        expected = np.array(direction_sample.uv).reshape(2, -1)            # (2, N) film pixels
        got = np.stack([ii[hit] + clip.motion[frame, 0][hit], jj[hit] + clip.motion[frame, 1][hit]])
        np.testing.assert_allclose(got, expected, atol=2e-3)
        assert np.abs(clip.motion[frame]).max() > 0.5                       # the camera did move


@pytest.mark.slow
def test_warping_the_previous_reference_with_the_vectors_matches_the_current_one(tmp_path) -> None:
    """Where valid, the previous frame's reference warped by the motion vectors is close to the current reference:
    its tonemapped error is well below that of the unwarped previous frame and within 3x the reference's own noise
    (bilinear resampling of edges keeps it above the noise)."""
    cfg = _config(scenarios=["camera"], width=40, height=40, spp=8, reference_spp=256, resolution=16)
    render_dir = _render(cfg, "vol_test_camera_000", tmp_path)
    clip = load_clip(render_dir, buffers=("radiance",))
    references = [load_reference_frame(path)[0] for path in sorted((render_dir / "reference/chunk_000").glob("*.exr"))]

    def tonemap(x: np.ndarray) -> np.ndarray:
        return x / (1.0 + x)

    for frame in (1, 2):
        valid = clip.valid[frame, 0]
        assert valid.mean() > 0.6
        current, previous = references[frame], references[frame - 1]["radiance"]
        warped = warp_previous(previous, clip.motion[frame])
        error_warped = np.abs(tonemap(warped) - tonemap(current["radiance"])).mean(0)[valid]
        error_unwarped = np.abs(tonemap(previous) - tonemap(current["radiance"])).mean(0)[valid]
        noise = np.abs(tonemap(current["radiance_half0"]) - tonemap(current["radiance_half1"])).mean(0)[valid] / 2
        assert error_warped.mean() < 0.6 * error_unwarped.mean()
        assert np.median(error_warped) < 3.0 * np.median(noise)


def test_same_config_same_clip_bytes(rendered, tmp_path) -> None:
    cfg, root = rendered
    scene_id = "vol_test_transfer_function_000"
    again = _render(cfg, scene_id, tmp_path)
    first = (root / "scenes" / scene_id / "manifest.json").read_bytes()
    assert (tmp_path / "scenes" / scene_id / "manifest.json").read_bytes() == first
    a = load_clip(root / "renders" / scene_id, buffers=VOLUME_BUFFERS)
    b = load_clip(again, buffers=VOLUME_BUFFERS)
    for buffer in VOLUME_BUFFERS:
        np.testing.assert_array_equal(a.samples[buffer], b.samples[buffer])
    reference_a, _ = load_reference_frame(root / "renders" / scene_id / "reference/chunk_000/frame_0002.exr")
    reference_b, _ = load_reference_frame(again / "reference/chunk_000/frame_0002.exr")
    np.testing.assert_array_equal(reference_a["radiance"], reference_b["radiance"])
    shutil.rmtree(tmp_path / "scenes")


# --- bring your own volume -------------------------------------------------------------------------------------

def test_a_users_npy_field_renders_as_its_own_evaluated_clip(tmp_path) -> None:
    """volumes.extra: the .npy values are mapped linearly from [min, max] to [0, 1] and through the given transfer
    function (checked voxel by voxel by hand), the box takes the array's aspect, the clip is evaluated, and a changed
    file is refused by name."""
    from denoisers.jobs.volumes import volume_test_scene_ids
    from scenegen.volumes.scenes import VolumeClip

    field = np.zeros((4, 6, 8), np.int16)                      # [z, y, x]: x is the longest axis
    field[1:3, 2:4, 3:6] = 300
    field[2, 3, 4] = 1000
    path = tmp_path / "field.npy"
    np.save(path, field)
    tf = {"extinction": [[0.0, 0.0], [0.5, 2.0], [1.0, 10.0]], "albedo": [[0.0, 0.9, 0.9, 0.9], [1.0, 0.5, 0.6, 0.7]]}
    cfg = _config(scenarios=["light"], n_test=0)
    cfg["volumes"]["extra"] = [{"name": "user_field", "npy": str(path), "scenario": "camera", "transfer_function": tf}]
    assert volume_scene_ids(cfg) == volume_test_scene_ids(cfg) == ["vol_custom_user_field"]
    assert volume_clip_spec(cfg, "vol_custom_user_field") == ("custom", "camera", 0)
    render_dir = _render(cfg, "vol_custom_user_field", tmp_path)
    manifest = json.loads((tmp_path / "scenes/vol_custom_user_field/manifest.json").read_text())
    assert manifest["field"]["kind"] == "npy" and manifest["field"]["shape"] == [4, 6, 8]
    assert manifest["transfer_function"]["frames"][0] == tf
    clip = VolumeClip.from_manifest(manifest)
    sigma_t, albedo = clip.medium_grids(0)
    # Hand-computed voxels: 0 -> s 0 -> sigma 0; 300 -> s 0.3 -> sigma 0.3 / 0.5 x 2 = 1.2; 1000 -> s 1 -> 10.
    assert sigma_t[0, 0, 0] == 0.0 and sigma_t[2, 3, 4] == pytest.approx(10.0)
    assert sigma_t[1, 2, 3] == pytest.approx(1.2, rel=1e-6)
    np.testing.assert_allclose(albedo[1, 2, 3], [0.9 - 0.3 * 0.4, 0.9 - 0.3 * 0.3, 0.9 - 0.3 * 0.2], rtol=1e-6)
    extent = np.asarray(manifest["box"]["max"]) - np.asarray(manifest["box"]["min"])    # world (x, y, z)
    np.testing.assert_allclose(extent / extent.max(), [1.0, 6 / 8, 4 / 8], rtol=1e-6)
    assert load_clip(render_dir, buffers=("radiance", "medium")).samples["medium"].any()
    # The file changes after the scene was generated: rendering refuses it, naming the file.
    np.save(path, field * 2)
    with pytest.raises(ValueError, match="field.npy: its contents changed"):
        VolumeClip.from_manifest(manifest)
    # Bad arrays are named too.
    np.save(path, np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="3-D"):
        jobs.run_generate(cfg, "vol_custom_user_field", tmp_path / "again")
    np.save(path, np.full((3, 3, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        jobs.run_generate(cfg, "vol_custom_user_field", tmp_path / "again")
