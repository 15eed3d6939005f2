"""Seeded volumetric clips (scenegen.volumes.scenes): determinism of manifests and fields, one animated element
per scenario, frame 0 renders with a visible medium, and per-frame edits of a loaded scene match fresh loads."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scenegen.volumes.scenes import (FIELD_KINDS, SCENARIOS, VolumeClip, field_from_manifest, frame_updates,
                                    generate_volume_clip)

FRAMES = 3
MEDIUM_CHANNEL = 3 + 8       # RGB, then the AOVs position(3) depth sigma_t albedo(3) medium transmittance


def _bytes(manifest: dict) -> bytes:
    return json.dumps(manifest, sort_keys=True).encode()


@pytest.mark.parametrize("field_kind", FIELD_KINDS)
def test_same_seed_same_bytes(field_kind):
    a = generate_volume_clip(11, "transfer_function", FRAMES, field_kind)
    b = generate_volume_clip(11, "transfer_function", FRAMES, field_kind)
    c = generate_volume_clip(12, "transfer_function", FRAMES, field_kind)
    assert _bytes(a.manifest()) == _bytes(b.manifest())
    assert a.field.dtype == np.float32 and a.field.tobytes() == b.field.tobytes()
    assert _bytes(a.manifest()) != _bytes(c.manifest())
    assert a.field.tobytes() != c.field.tobytes()
    # The manifest (through JSON) regenerates the field and the whole clip exactly; no voxels in it.
    text = _bytes(a.manifest())
    assert len(text) < 20_000
    reloaded = json.loads(text)
    assert field_from_manifest(reloaded).tobytes() == a.field.tobytes()
    assert _bytes(VolumeClip.from_manifest(reloaded).manifest()) == text
    m = a.manifest()
    assert m["field"]["kind"] == field_kind and m["scenario"] == "transfer_function" and m["seed"] == 11
    assert len(m["transfer_function"]["frames"]) == len(m["camera"]["frames"]) == len(m["lights"]["frames"]) == FRAMES


def _differs(frames: list) -> bool:
    return any(_bytes({"x": f}) != _bytes({"x": frames[0]}) for f in frames[1:])


def _all_distinct(frames: list) -> bool:
    return len({_bytes({"x": f}) for f in frames}) == len(frames)


@pytest.mark.parametrize("field_kind", FIELD_KINDS)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_each_scenario_animates_only_its_element(scenario, field_kind):
    m = generate_volume_clip(5, scenario, FRAMES, field_kind).manifest()
    elements = {"camera": m["camera"]["frames"], "light": m["lights"]["frames"],
                "transfer_function": m["transfer_function"]["frames"]}
    for name, frames in elements.items():
        if name == scenario:
            assert _all_distinct(frames), name
        else:
            assert not _differs(frames), name


@pytest.mark.parametrize("edit", ["slide", "recolour"])
def test_transfer_function_edits(edit):
    clip = generate_volume_clip(2, "transfer_function", 4, "shells", tf_edit=edit)
    assert clip.manifest()["transfer_function"]["edit"]["kind"] == edit
    grids = [clip.medium_grids(t) for t in range(4)]
    changed = 0 if edit == "slide" else 1              # slide moves the opacity ramp, recolour the albedo
    assert all(grids[t][changed].tobytes() != grids[0][changed].tobytes() for t in range(1, 4))
    assert all(grids[t][1 - changed].tobytes() == grids[0][1 - changed].tobytes() for t in range(1, 4))


def test_invalid_arguments():
    with pytest.raises(ValueError, match="scenario"):
        generate_volume_clip(1, "wind", 2)
    with pytest.raises(ValueError, match="field kind"):
        generate_volume_clip(1, "camera", 2, "teapot")
    with pytest.raises(ValueError, match="frames"):
        generate_volume_clip(1, "camera", 0)


# ------------------------------------------------------------------------------------------------ Mitsuba
def _render(scene_or_dict, seed: int = 7) -> np.ndarray:
    import mitsuba as mi

    scene = mi.load_dict(scene_or_dict) if isinstance(scene_or_dict, dict) else scene_or_dict
    return np.array(mi.render(scene, seed=seed))


@pytest.mark.parametrize("seed, field_kind, setting, light, env", [
    (1, "noise_cloud", "open", "point", "gradient"),
    (2, "shells", "open", "area", "constant"),
    (3, "smoke_plume", "room", "area", None),
])
def test_frame_zero_renders_a_visible_medium(seed, field_kind, setting, light, env):
    pytest.importorskip("mitsuba")
    clip = generate_volume_clip(seed, "camera", 2, field_kind, setting=setting, light_kind=light, environment=env)
    image = _render(clip.scene_dict(0, width=16, height=16, spp=8))
    assert image.shape == (16, 16, 13) and np.all(np.isfinite(image))
    assert image[..., :3].mean() > 0.0
    assert image[..., MEDIUM_CHANNEL].mean() > 0.0
    bare = _render(clip.scene_dict(0, width=16, height=16, spp=8, medium=False))
    assert bare[..., MEDIUM_CHANNEL].max() == 0.0
    assert bare[..., :3].tobytes() != image[..., :3].tobytes()


@pytest.mark.parametrize("scenario, light", [
    ("transfer_function", "point"), ("camera", "point"), ("light", "point"), ("light", "area"),
])
def test_frame_updates_match_a_fresh_load(scenario, light):
    mi = pytest.importorskip("mitsuba")
    clip = generate_volume_clip(4, scenario, FRAMES, "noise_cloud", light_kind=light, resolution=12,
                                setting="open")
    scene = mi.load_dict(clip.scene_dict(0))
    first = _render(scene)
    keys = frame_updates(scene, clip, FRAMES - 1)
    assert keys
    edited = _render(scene)
    fresh = _render(clip.scene_dict(FRAMES - 1))
    assert np.all(np.isfinite(edited)) and edited.tobytes() != first.tobytes()
    assert edited.tobytes() == fresh.tobytes()


def test_occupied_bounds_are_the_voxels_a_transfer_function_makes_visible():
    """Hand-placed voxels in a (D, H, W) = [z, y, x] field inside a box from (0, 0, 0) to (4, 2, 8): the bounds
    cover exactly the voxels whose extinction passes the visibility threshold in any frame."""
    from scenegen.volumes.framing import VISIBLE_OPTICAL_DEPTH, occupied_bounds
    from scenegen.volumes.media import TransferFunction

    field = np.zeros((8, 4, 4), np.float32)          # voxels of 1 x 0.5 x 1 scene units (x, y, z)
    field[2:5, 1, 3] = 0.5                           # z 2..4, y 1, x 3: visible only in the second frame
    field[6, 3, 0] = 1.0                             # z 6, y 3, x 0: visible in both
    field[0, 0, 0] = 0.1                             # below the threshold in both frames
    threshold = VISIBLE_OPTICAL_DEPTH / 8.0
    dense = TransferFunction(extinction=((0.0, 0.0), (1.0, 4 * threshold)), albedo=((0.0, 1, 1, 1),))
    low = TransferFunction(extinction=((0.0, 0.0), (0.9, 0.0), (1.0, 1.0)), albedo=((0.0, 1, 1, 1),))
    box = ([0.0, 0.0, 0.0], [4.0, 2.0, 8.0])
    lower, upper = occupied_bounds(field, [low], *box)
    np.testing.assert_allclose(lower, [0.0, 1.5, 6.0])
    np.testing.assert_allclose(upper, [1.0, 2.0, 7.0])
    lower, upper = occupied_bounds(field, [low, dense], *box)
    np.testing.assert_allclose(lower, [0.0, 0.5, 2.0])
    np.testing.assert_allclose(upper, [4.0, 2.0, 7.0])
    empty = TransferFunction(extinction=((0.0, 0.0),), albedo=((0.0, 1, 1, 1),))
    lower, upper = occupied_bounds(field, [empty], *box)
    np.testing.assert_allclose(lower, box[0])
    np.testing.assert_allclose(upper, box[1])


@pytest.mark.parametrize("seed, scenario, aspect", [(0, "camera", 1.0), (4, "camera", 0.75), (2, "light", 1.0),
                                                    (5, "transfer_function", 0.5)])
def test_the_camera_frames_the_visible_volume(seed, scenario, aspect):
    """Mitsuba's own sensor (sensor.sample_direction) projects the visible part's corners inside the frame
    from every camera of the clip, and some corner reaches near the frame's edge (FRAME_FILL); inside a room
    whose walls hold the camera back, the view widens instead."""
    import drjit as dr
    import mitsuba as mi

    from scenegen.volumes.framing import FRAME_FILL, occupied_bounds

    width = 64
    height = int(round(width * aspect))
    clip = generate_volume_clip(seed, scenario, 4, frame_aspect=height / width)
    lower, upper = occupied_bounds(clip.field, clip.transfer_functions, clip.box_min, clip.box_max)
    corners = np.array(np.meshgrid(*zip(lower, upper), indexing="ij")).reshape(3, -1).T
    reach = []
    for frame in range(clip.frames):
        sensor = mi.load_dict(clip.scene_dict(frame, width=width, height=height, spp=1)["sensor"])
        interaction = dr.zeros(mi.Interaction3f, len(corners))
        interaction.p = mi.Point3f(*(corners[:, axis] for axis in range(3)))
        sample, _ = sensor.sample_direction(interaction, mi.Point2f(0.5, 0.5))
        uv = np.array(sample.uv, dtype=np.float64).reshape(2, -1).T           # (8, 2) film pixels
        half = np.array([width, height]) / 2
        reach.append(np.abs(uv - half) / half)                              # 1 at the frame's edge
    reach = np.concatenate(reach)
    assert FRAME_FILL - 0.05 <= reach.max() <= FRAME_FILL + 1e-3
