"""Tests for scenegen.channels and scenegen.dataset: channel tables, array <-> channel conversion and the clip loader."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from scenegen.channels import (ALL, VOLUME_BUFFERS, HALF_BUFFERS, HALF_PIXEL_BUFFERS, PIXEL_BUFFERS, REFERENCE_BUFFERS,
                               SAMPLE_BUFFERS, is_half_channel, noisy_buffers, noisy_channel_names, noisy_channels,
                               pixel_channels, reference_channel_names, reference_channels, sample_channel_names,
                               sample_layers)
from scenegen.dataset import (Clip, DatasetError, MissingBufferError, NotEnoughSamplesError, load_clip, load_frame,
                              write_frame)
from scenegen.exr import list_channels, read_exr, write_exr

H, W = 6, 10
S_FULL, S_RADIANCE = 4, 8
FRAMES_PER_CHUNK, N_CHUNKS = 2, 2
DOC = Path(__file__).resolve().parents[1] / "docs" / "data-format.md"


def _frame_arrays(t: int, omit: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Deterministic synthetic per-sample (S, C, H, W) and per-pixel (C, H, W) buffers for frame t.

    Per-pixel buffers are keyed like PIXEL_BUFFERS ('motion', 'valid', 'gbuffer.position', ...).
    """
    rng = np.random.default_rng(100 + t)
    samples = {}
    for buffer in ALL:
        suffixes = SAMPLE_BUFFERS[buffer]
        if buffer in omit:
            continue
        layers = S_RADIANCE if buffer == "radiance" else S_FULL
        samples[buffer] = rng.uniform(0, 4, (layers, len(suffixes), H, W)).astype(np.float32)
    samples["flags"] = (samples["flags"] > 2).astype(np.float32)
    pixel = {buffer: rng.uniform(-2, 2, (len(names), H, W)).astype(np.float32)
             for buffer, names in PIXEL_BUFFERS.items()}
    pixel["valid"] = np.full((1, H, W), float(t > 0), np.float32)
    pixel["gbuffer.object"] = rng.integers(-1, 5, (1, H, W)).astype(np.float32)
    return samples, pixel


def _frame_channels(samples: dict[str, np.ndarray], pixel: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """EXR channels of a noisy frame, built the way the renderer does."""
    channels, _ = noisy_channels(samples)
    gbuffer = {key[len("gbuffer."):]: array for key, array in pixel.items() if key.startswith("gbuffer.")}
    gbuffer["rgb"] = np.zeros((3, H, W), np.float32)  # the integrator's extra output, not stored
    pixel_planes, _ = pixel_channels(pixel["motion"], pixel["valid"] > 0.5, gbuffer)
    return {**channels, **pixel_planes}


def _reference_arrays(t: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(900 + t)
    return {buffer: rng.uniform(0, 1, (len(suffixes), H, W)).astype(np.float32)
            for buffer, suffixes in REFERENCE_BUFFERS.items()}


def _write_clip(render_dir: Path, omit: tuple[str, ...] = (), skip_reference: int | None = None) -> None:
    for chunk in range(N_CHUNKS):
        noisy_dir = render_dir / "noisy" / f"chunk_{chunk:03d}"
        reference_dir = render_dir / "reference" / f"chunk_{chunk:03d}"
        noisy_dir.mkdir(parents=True)
        reference_dir.mkdir(parents=True)
        for t in range(chunk * FRAMES_PER_CHUNK, (chunk + 1) * FRAMES_PER_CHUNK):
            samples, pixel = _frame_arrays(t, omit)
            meta = {"scene": "train_007", "frame": t, "spp": S_FULL, "extra_radiance_spp": S_RADIANCE - S_FULL}
            write_frame(noisy_dir / f"frame_{t:04d}.exr", _frame_channels(samples, pixel), meta)
            if t != skip_reference:
                write_frame(reference_dir / f"frame_{t:04d}.exr", reference_channels(_reference_arrays(t)),
                            {"scene": "train_007", "frame": t, "spp": 64, "psnr_halves": 40.0}, half=set())


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    render_dir = tmp_path_factory.mktemp("renders") / "train_007"
    _write_clip(render_dir)
    # Leftovers of interrupted writes must be ignored by the loader.
    (render_dir / "noisy" / "chunk_000" / ".frame_0000.exr.tmp-4242").write_bytes(b"partial")
    (render_dir / "noisy" / ".chunk_002.tmp").mkdir()
    (render_dir / "noisy" / ".chunk_002.tmp" / "frame_0004.exr").write_bytes(b"partial")
    return render_dir


def _half(array: np.ndarray) -> np.ndarray:
    return array.astype(np.float16).astype(np.float32)


# --- channel tables and conversion ---------------------------------------------------------------------------

def test_sample_channel_names() -> None:
    assert sample_channel_names("radiance", 0) == ["s00.radiance.R", "s00.radiance.G", "s00.radiance.B"]
    assert sample_channel_names("flags", 31)[-1] == "s31.flags.specular_bounce"
    with pytest.raises(ValueError):
        sample_channel_names("radiance", 32)
    with pytest.raises(KeyError):
        sample_channel_names("glossiness", 0)


def test_half_channel_rules() -> None:
    assert is_half_channel("s03.albedo.G") and is_half_channel("s00.flags.metallic")
    assert is_half_channel("motion.valid") and is_half_channel("gbuffer.normal.Z")
    assert not is_half_channel("s03.radiance.G") and not is_half_channel("s00.depth.Z")
    assert not is_half_channel("motion.X") and not is_half_channel("gbuffer.position.X")
    surface = noisy_channel_names(2)
    volume = noisy_channel_names(2, buffers=VOLUME_BUFFERS)
    assert {name.split(".")[1] for name in surface + volume if is_half_channel(name) and name[0] == "s"} \
        == set(HALF_BUFFERS)


def test_noisy_channel_names_count() -> None:
    per_layer = sum(len(SAMPLE_BUFFERS[buffer]) for buffer in ALL)
    pixel = sum(len(names) for names in PIXEL_BUFFERS.values())
    names = noisy_channel_names(8, 24)
    assert len(names) == len(set(names)) == 8 * per_layer + 24 * 3 + pixel
    assert "s31.radiance.B" in names and "s08.albedo.R" not in names
    with pytest.raises(ValueError):
        noisy_channel_names(8, 25)


def test_noisy_channels_round_trip() -> None:
    samples, _ = _frame_arrays(0)
    channels, half = noisy_channels(samples)
    assert "s05.radiance.G" in channels and "s05.albedo.R" not in channels
    assert half == {name for name in channels if is_half_channel(name)}
    assert "s03.flags.metallic" in half and "s03.radiance.R" not in half
    np.testing.assert_array_equal(channels["s02.normal.Y"], samples["normal"][2, 1])
    assert sample_layers(channels) == {b: (S_RADIANCE if b == "radiance" else S_FULL) for b in ALL}
    back = noisy_buffers(channels)
    for buffer, array in samples.items():
        np.testing.assert_array_equal(back[buffer], array)


def test_noisy_channels_rejects_inconsistent_layers() -> None:
    samples, _ = _frame_arrays(0)
    samples["albedo"] = samples["albedo"][:3]
    with pytest.raises(ValueError, match="albedo"):
        noisy_channels(samples)
    samples, _ = _frame_arrays(0)
    samples["radiance"] = samples["radiance"][:2]
    with pytest.raises(ValueError, match="radiance"):
        noisy_channels(samples)
    with pytest.raises(ValueError, match="C=3"):
        noisy_channels({"radiance": np.zeros((2, 4, H, W))})


def test_sample_layers_rejects_gaps() -> None:
    with pytest.raises(ValueError, match="s01.radiance"):
        sample_layers(["s00.radiance.R", "s00.radiance.G", "s00.radiance.B", "s02.radiance.R",
                       "s02.radiance.G", "s02.radiance.B"])


def test_pixel_and_reference_channels() -> None:
    _, pixel = _frame_arrays(1)
    gbuffer = {key[len("gbuffer."):]: array for key, array in pixel.items() if key.startswith("gbuffer.")}
    channels, half = pixel_channels(pixel["motion"], pixel["valid"] > 0.5, gbuffer)
    assert set(channels) == {name for names in PIXEL_BUFFERS.values() for name in names}
    assert half == {name for name in channels if is_half_channel(name)} == \
        {"motion.valid", "gbuffer.normal.X", "gbuffer.normal.Y", "gbuffer.normal.Z", "gbuffer.albedo.R",
         "gbuffer.albedo.G", "gbuffer.albedo.B", "gbuffer.roughness.Y"}
    np.testing.assert_array_equal(channels["motion.Y"], pixel["motion"][1])
    np.testing.assert_array_equal(channels["gbuffer.depth.Z"], pixel["gbuffer.depth"][0])
    assert channels["motion.valid"].dtype == np.float32 and channels["motion.valid"].max() == 1.0
    del gbuffer["object"]
    with pytest.raises(KeyError, match="object"):
        pixel_channels(pixel["motion"], pixel["valid"], gbuffer)
    reference = reference_channels(_reference_arrays(0))
    assert "radiance_half1.B" in reference and reference_channel_names("depth") == ["depth.Z"]


# --- loader ----------------------------------------------------------------------------------------------------

def test_load_clip_shapes_and_values(clip_dir: Path) -> None:
    clip = load_clip(clip_dir)
    n_frames = N_CHUNKS * FRAMES_PER_CHUNK
    assert isinstance(clip, Clip) and clip.scene == "train_007"
    assert clip.frames == list(range(n_frames))
    assert clip.samples["radiance"].shape == (n_frames, S_RADIANCE, 3, H, W)
    for buffer in ALL:
        suffixes = SAMPLE_BUFFERS[buffer]
        layers = S_RADIANCE if buffer == "radiance" else S_FULL
        assert clip.samples[buffer].shape == (n_frames, layers, len(suffixes), H, W)
        assert clip.samples[buffer].dtype == np.float32
    assert clip.motion.shape == (n_frames, 2, H, W) and clip.motion.dtype == np.float32
    assert clip.valid.shape == (n_frames, 1, H, W) and clip.valid.dtype == np.bool_
    assert not clip.valid[0].any() and clip.valid[1:].all()
    assert set(clip.gbuffer) == {"position", "normal", "depth", "object", "albedo", "roughness"}
    assert clip.gbuffer["normal"].shape == (n_frames, 3, H, W)
    assert clip.reference is not None and clip.reference["radiance_half0"].shape == (n_frames, 3, H, W)
    assert [m["frame"] for m in clip.meta] == clip.frames
    assert clip.reference_meta is not None and clip.reference_meta[0]["spp"] == 64

    t = 3  # second frame of the second chunk
    samples, pixel = _frame_arrays(t)
    np.testing.assert_array_equal(clip.samples["radiance"][t], samples["radiance"])  # FLOAT: exact
    np.testing.assert_array_equal(clip.samples["albedo"][t], _half(samples["albedo"]))  # HALF
    np.testing.assert_array_equal(clip.motion[t], pixel["motion"])
    np.testing.assert_array_equal(clip.gbuffer["object"][t], pixel["gbuffer.object"])
    np.testing.assert_array_equal(clip.gbuffer["normal"][t], _half(pixel["gbuffer.normal"]))
    np.testing.assert_array_equal(clip.reference["depth"][t], _reference_arrays(t)["depth"])
    np.testing.assert_allclose(clip.radiance_mean[t], samples["radiance"].mean(axis=0), rtol=1e-6)


def test_stack(clip_dir: Path) -> None:
    clip = load_clip(clip_dir, buffers=["radiance", "albedo", "normal", "depth"], reference=False)
    assert clip.reference is None
    stacked = clip.stack(["albedo", "normal", "depth"])
    assert stacked.shape == (4, S_FULL, 7, H, W)
    np.testing.assert_array_equal(stacked[:, :, 3:6], clip.samples["normal"])
    with pytest.raises(ValueError, match="spp"):
        clip.stack(["radiance", "albedo"])
    assert clip.stack(["radiance", "albedo"], spp=2).shape == (4, 2, 6, H, W)
    with pytest.raises(MissingBufferError):
        clip.stack(["position"])


def test_spp_slicing(clip_dir: Path) -> None:
    full = load_clip(clip_dir, buffers=["radiance", "albedo"], reference=False)
    sliced = load_clip(clip_dir, buffers=["radiance", "albedo"], spp=2, reference=False)
    assert sliced.samples["radiance"].shape == (4, 2, 3, H, W)
    assert sliced.samples["albedo"].shape == (4, 2, 3, H, W)
    np.testing.assert_array_equal(sliced.samples["radiance"], full.samples["radiance"][:, :2])
    radiance_only = load_clip(clip_dir, buffers=["radiance"], spp=7, reference=False)
    assert radiance_only.samples["radiance"].shape == (4, 7, 3, H, W)


def test_too_many_samples_error_names_buffer_file_and_count(clip_dir: Path) -> None:
    with pytest.raises(NotEnoughSamplesError) as info:
        load_clip(clip_dir, buffers=["radiance", "albedo"], spp=6)
    message = str(info.value)
    assert "'albedo'" in message and "frame_0000.exr" in message and f"only {S_FULL}" in message


def test_frame_subset(clip_dir: Path) -> None:
    clip = load_clip(clip_dir, buffers=["radiance"], frames=[3, 1])
    assert clip.frames == [1, 3] and clip.samples["radiance"].shape[0] == 2
    np.testing.assert_array_equal(clip.samples["radiance"][1], _frame_arrays(3)[0]["radiance"])
    with pytest.raises(DatasetError, match=r"\[9\]"):
        load_clip(clip_dir, frames=[1, 9])


def test_load_frame(clip_dir: Path) -> None:
    path = clip_dir / "noisy" / "chunk_001" / "frame_0002.exr"
    samples, pixel, meta = load_frame(path, buffers=["depth"], spp=3)
    assert list(samples) == ["depth"] and samples["depth"].shape == (3, 1, H, W)
    assert set(pixel) == set(PIXEL_BUFFERS) and pixel["motion"].shape == (2, H, W)
    assert meta["frame"] == 2
    samples, pixel, _ = load_frame(path, buffers=[], pixel=False)
    assert samples == {} and pixel == {}


def test_missing_buffer_error_names_buffer_and_file(tmp_path: Path) -> None:
    render_dir = tmp_path / "test_001"
    _write_clip(render_dir, omit=("position",))
    with pytest.raises(MissingBufferError) as info:
        load_clip(render_dir, buffers=["radiance", "position"])
    assert isinstance(info.value, KeyError)
    assert info.value.buffer == "position"
    message = str(info.value)
    assert "'position'" in message and "frame_0000.exr" in message and "radiance" in message
    assert load_clip(render_dir, buffers=["radiance", "normal"]).samples["normal"].shape[1] == S_FULL


def test_missing_reference_frame_names_file(tmp_path: Path) -> None:
    render_dir = tmp_path / "train_002"
    _write_clip(render_dir, skip_reference=2)
    with pytest.raises(DatasetError) as info:
        load_clip(render_dir)
    expected = render_dir / "reference" / "chunk_001" / "frame_0002.exr"
    assert str(expected) in str(info.value)
    assert load_clip(render_dir, reference=False).reference is None


def test_no_frames(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no frames"):
        load_clip(tmp_path / "nothing")


def test_non_finite_value_names_file_and_channel(tmp_path: Path) -> None:
    render_dir = tmp_path / "train_003"
    _write_clip(render_dir)
    path = render_dir / "noisy" / "chunk_000" / "frame_0001.exr"
    samples, pixel = _frame_arrays(1)
    samples["radiance"][1, 1, 2, 3] = np.nan
    write_frame(path, _frame_channels(samples, pixel), {"frame": 1})
    with pytest.raises(DatasetError) as info:
        load_clip(render_dir, buffers=["radiance"])
    assert str(path) in str(info.value) and "s01.radiance.G" in str(info.value)


def test_meta_from_attribute_when_sidecar_missing(tmp_path: Path) -> None:
    path = tmp_path / "frame_0000.exr"
    samples, pixel = _frame_arrays(0)
    write_frame(path, _frame_channels(samples, pixel), {"frame": 0, "spp": S_FULL})
    assert json.loads(path.with_suffix(".json").read_text()) == {"frame": 0, "spp": S_FULL}
    path.with_suffix(".json").unlink()
    _, _, meta = load_frame(path, buffers=["radiance"])
    assert meta == {"frame": 0, "spp": S_FULL}


def test_written_types_follow_tables(tmp_path: Path) -> None:
    path = tmp_path / "frame_0000.exr"
    samples, pixel = _frame_arrays(0)
    write_frame(path, _frame_channels(samples, pixel), {})
    names = list_channels(path)
    assert set(names) == set(noisy_channel_names(S_FULL, S_RADIANCE - S_FULL))
    # a value not representable in HALF comes back rounded only for HALF buffers
    value = np.float32(1.0 + 2.0**-14)
    write_exr(tmp_path / "x.exr", {"s00.albedo.R": np.full((2, 2), value), "s00.depth.Z": np.full((2, 2), value),
                                   "motion.valid": np.full((2, 2), value)}, half=is_half_channel)
    planes, _ = read_exr(tmp_path / "x.exr")
    assert planes["s00.albedo.R"][0, 0] == 1.0 and planes["motion.valid"][0, 0] == 1.0
    assert planes["s00.depth.Z"][0, 0] == value


# --- documentation ---------------------------------------------------------------------------------------------

def _doc_channel_rows() -> list[tuple[set[str], str]]:
    """(backticked channel names, type cell) of every row of the channel tables in docs/data-format.md.

    A channel table is a markdown table whose header has a 'channels' and a 'type' column.
    """
    rows: list[tuple[set[str], str]] = []
    columns: list[str] | None = None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line.startswith("|"):
            columns = None
            continue
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if columns is None:
            columns = cells
        elif {"channels", "type"} <= set(columns) and not set("".join(cells)) <= set("-: "):
            names = set(re.findall(r"`([^`]+)`", cells[columns.index("channels")]))
            rows.append((names, cells[columns.index("type")]))
    return rows


def test_doc_tables_list_every_channel() -> None:
    documented = {name for names, _ in _doc_channel_rows() for name in names}
    expected = {name.replace("s00.", "sNN.") for buffer in SAMPLE_BUFFERS for name in sample_channel_names(buffer, 0)}
    expected |= {name for names in PIXEL_BUFFERS.values() for name in names}
    expected |= {name for buffer in REFERENCE_BUFFERS for name in reference_channel_names(buffer)}
    missing = sorted(expected - documented)
    assert not missing, f"docs/data-format.md channel tables lack {missing}"


def test_doc_states_channel_types() -> None:
    """Each documented noisy channel says HALF exactly when the constants say so; references are FLOAT."""
    noisy = {f"sNN.{b}.{s}": b in HALF_BUFFERS for b, suffixes in SAMPLE_BUFFERS.items() for s in suffixes}
    noisy |= {name: b in HALF_PIXEL_BUFFERS for b, names in PIXEL_BUFFERS.items() for name in names}
    checked: set[str] = set()
    for names, type_cell in _doc_channel_rows():
        assert type_cell in ("HALF", "FLOAT"), type_cell
        for name in names:
            expected = "HALF" if noisy.get(name, False) else "FLOAT"
            assert type_cell == expected, f"{name} is {expected} but documented as {type_cell}"
            checked.add(name)
    assert set(noisy) <= checked


def test_all_is_every_surface_buffer_and_volume_buffers_complete_the_table() -> None:
    volume_only = {"sigma_t", "medium", "transmittance"}
    assert not volume_only & set(ALL)
    assert set(ALL) | set(VOLUME_BUFFERS) == set(SAMPLE_BUFFERS)
    assert list(ALL) == [name for name in SAMPLE_BUFFERS if name in ALL]      # table order
