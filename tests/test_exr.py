"""Tests for scenegen.exr: round trips, attributes, atomic writes and error reporting."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenegen.exr import EXRError, list_channels, read_exr, read_header, write_exr

H, W = 12, 20


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def _hdr_values(rng: np.random.Generator, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    """Awkward float32 values: wide dynamic range, negatives, zeros, a subnormal."""
    values = (rng.standard_normal(shape) * np.exp(rng.uniform(-30, 30, shape))).astype(np.float32)
    values[0, 0] = 0.0
    values[0, 1] = -0.0
    values[0, 2] = np.float32(1e-42)
    return values


def test_float_channels_round_trip_bit_exactly(tmp_path: Path, rng: np.random.Generator) -> None:
    channels = {"radiance.R": _hdr_values(rng), "radiance.G": _hdr_values(rng), "depth.Z": _hdr_values(rng)}
    path = tmp_path / "float.exr"
    write_exr(path, channels)
    planes, _ = read_exr(path)
    assert sorted(planes) == sorted(channels)
    for name, original in channels.items():
        assert planes[name].dtype == np.float32 and planes[name].shape == (H, W)
        np.testing.assert_array_equal(planes[name].view(np.uint32), original.view(np.uint32))


def test_half_channels_round_trip_with_half_precision(tmp_path: Path, rng: np.random.Generator) -> None:
    albedo = rng.uniform(0, 1, (H, W)).astype(np.float32)
    radiance = rng.uniform(0, 1, (H, W)).astype(np.float32)
    path = tmp_path / "half.exr"
    write_exr(path, {"albedo.R": albedo, "radiance.R": radiance}, half={"albedo.R"})
    planes, _ = read_exr(path)
    np.testing.assert_array_equal(planes["albedo.R"], albedo.astype(np.float16).astype(np.float32))
    assert not np.array_equal(planes["albedo.R"], albedo)  # really stored at reduced precision
    np.testing.assert_allclose(planes["albedo.R"], albedo, rtol=2.0**-11, atol=0)
    np.testing.assert_array_equal(planes["radiance.R"], radiance)


def test_half_predicate_and_non_contiguous_input(tmp_path: Path, rng: np.random.Generator) -> None:
    stacked = rng.uniform(-1, 1, (3, W, H)).astype(np.float32)
    # Transposed views are not C-contiguous; the bindings ignore strides, so write_exr must fix the layout.
    channels = {f"normal.{axis}": stacked[i].T for i, axis in enumerate("XYZ")}
    channels["depth.Z"] = stacked[0].T * 10
    path = tmp_path / "views.exr"
    write_exr(path, channels, half=lambda name: name.startswith("normal."))
    planes, _ = read_exr(path)
    for i, axis in enumerate("XYZ"):
        np.testing.assert_array_equal(planes[f"normal.{axis}"], stacked[i].T.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(planes["depth.Z"], stacked[0].T * 10)


def test_input_dict_is_not_modified(tmp_path: Path, rng: np.random.Generator) -> None:
    plane = rng.uniform(0, 1, (H, W)).astype(np.float32)
    channels = {"Y": plane}
    write_exr(tmp_path / "a.exr", channels)
    assert channels["Y"] is plane


def test_attributes_survive(tmp_path: Path, rng: np.random.Generator) -> None:
    meta = {"scene": "train_000", "frame": 3, "camera": {"fov_x_deg": 39.5978}, "nonfinite": {"radiance": 0}}
    path = tmp_path / "attrs.exr"
    write_exr(path, {"Y": rng.uniform(0, 1, (H, W))},
              attributes={"mcdn_meta": json.dumps(meta), "exposure": 0.25, "spp": 8, "label": "héllo"})
    _, attributes = read_exr(path)
    assert json.loads(attributes["mcdn_meta"]) == meta
    assert attributes["exposure"] == 0.25
    assert attributes["spp"] == 8
    assert attributes["label"] == "héllo"
    names, header_attributes = read_header(path)
    assert names == ["Y"] and header_attributes["spp"] == 8


def test_float_attributes_are_32_bit(tmp_path: Path) -> None:
    path = tmp_path / "f.exr"
    write_exr(path, {"Y": np.zeros((2, 2))}, attributes={"value": 0.1})
    _, attributes = read_exr(path)
    assert attributes["value"] == pytest.approx(0.1, rel=1e-7)
    assert attributes["value"] == float(np.float32(0.1))


@pytest.mark.parametrize("bad", [{"channels": "x"}, {"obj": [1, 2]}, {"big": 2**40}])
def test_bad_attributes_rejected(tmp_path: Path, bad: dict) -> None:
    path = tmp_path / "bad.exr"
    with pytest.raises(EXRError, match="bad.exr"):
        write_exr(path, {"Y": np.zeros((2, 2))}, attributes=bad)
    assert not path.exists()


def test_channels_sorted_and_listed(tmp_path: Path) -> None:
    path = tmp_path / "order.exr"
    write_exr(path, {"s01.b": np.zeros((2, 3)), "s00.z": np.ones((2, 3)), "motion.X": np.ones((2, 3))})
    assert list_channels(path) == ["motion.X", "s00.z", "s01.b"]
    planes, _ = read_exr(path, ["s01.b", "motion.X"])
    assert list(planes) == ["s01.b", "motion.X"]


def test_atomic_write_leaves_no_tmp_file_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "frame_0000.exr"
    write_exr(path, {"Y": np.zeros((4, 4))})
    write_exr(path, {"Y": np.full((4, 4), 2.0)})
    assert [p.name for p in tmp_path.iterdir()] == ["frame_0000.exr"]
    np.testing.assert_array_equal(read_exr(path)[0]["Y"], 2.0)


def test_failed_write_leaves_nothing(tmp_path: Path) -> None:
    path = tmp_path / "missing_dir" / "x.exr"
    with pytest.raises(EXRError, match="x.exr"):
        write_exr(path, {"Y": np.zeros((4, 4))})
    assert not (tmp_path / "missing_dir").exists()


@pytest.mark.parametrize("channels, message", [
    ({"a": np.zeros((4, 4)), "b": np.zeros((4, 5))}, "shape"),
    ({"a": np.zeros((4, 4, 3))}, "2-D"),
    ({}, "no channels"),
])
def test_bad_shapes_rejected(tmp_path: Path, channels: dict, message: str) -> None:
    path = tmp_path / "shape.exr"
    with pytest.raises(EXRError, match=message) as info:
        write_exr(path, channels)
    assert str(path) in str(info.value)


def test_half_overflow_rejected(tmp_path: Path) -> None:
    with pytest.raises(EXRError, match="HALF"):
        write_exr(tmp_path / "o.exr", {"a": np.full((2, 2), 1e6)}, half={"a"})


def test_lossy_compression_rejected(tmp_path: Path) -> None:
    with pytest.raises(EXRError, match="compression"):
        write_exr(tmp_path / "c.exr", {"a": np.zeros((2, 2))}, compression="dwaa")


def test_truncated_file_raises_exr_error_naming_path(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "truncated.exr"
    write_exr(path, {f"c{i}": rng.uniform(0, 1, (64, 64)) for i in range(6)})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(EXRError) as info:
        read_exr(path)
    assert str(path) in str(info.value)


def test_garbage_file_raises_exr_error(tmp_path: Path) -> None:
    path = tmp_path / "garbage.exr"
    path.write_bytes(b"not an exr at all" * 20)
    with pytest.raises(EXRError, match="garbage.exr"):
        read_exr(path)
    with pytest.raises(EXRError, match="garbage.exr"):
        list_channels(path)


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.exr"
    with pytest.raises(EXRError, match="nope.exr"):
        read_exr(path)
    with pytest.raises(EXRError, match="nope.exr"):
        list_channels(path)


def test_missing_channel_names_file_channel_and_alternatives(tmp_path: Path) -> None:
    path = tmp_path / "few.exr"
    write_exr(path, {"radiance.R": np.zeros((2, 2)), "radiance.G": np.zeros((2, 2))})
    with pytest.raises(EXRError) as info:
        read_exr(path, ["radiance.R", "albedo.R"])
    message = str(info.value)
    assert str(path) in message and "'albedo.R'" in message and "radiance.G" in message


def test_200_channels_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    """A per-sample file's size (8 samples x 5 buffers x 5 planes at 128 x 128, two planes of each buffer in HALF):
    every value comes back, the HALF planes as float16 rounds them. Its speed: benchmarks/exr_speed.py."""
    channels = {f"s{s:02d}.buf{b}.{c}": rng.uniform(0, 1, (128, 128)).astype(np.float32) * (s + b + i + 1)
                for s in range(8) for b in range(5) for i, c in enumerate("XYZRG")}
    assert len(channels) == 200
    half = {name for name in channels if name.endswith((".X", ".Y"))}
    write_exr(tmp_path / "big.exr", channels, half=half)
    assert sorted(list_channels(tmp_path / "big.exr")) == sorted(channels)
    back, _ = read_exr(tmp_path / "big.exr")
    for name, plane in channels.items():
        expected = plane.astype(np.float16).astype(np.float32) if name in half else plane
        np.testing.assert_array_equal(back[name], expected, err_msg=name)
