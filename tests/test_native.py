"""The native (C++) kernels of denoisers/native against the torch implementations they replace.

Each test runs the same inputs through both paths (``MCDN_NATIVE=0`` selects torch) and compares the
outputs within float32 rounding: ``rtol=1e-4, atol=1e-6``, the tolerance of the existing fast-path
tests. The a-trous weights are exp2 of log-weights of magnitude up to ~87, which both paths evaluate
with about 1 ulp error in different orders; on well-conditioned inputs the paths differ by < 2e-5.
Inputs have depth and normal edges, zero-normal holes, odd and non-square sizes, and NaN/Inf/spike
corruption. Next to spikes (sanitised to 1e8) the luminance term amplifies rounding: there even the
torch path is off float64 arithmetic by up to ~2e-3 at single pixels, so whole corrupted streams
allow a few elements beyond ``rtol`` (see :func:`assert_close_streams`) and a separate test checks
that the native path is no further from a float64 evaluation than the torch path is.
The tests are skipped when the extension cannot be built here (the fallback itself is tested).
"""
from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from denoisers import native, registry
from denoisers.filters import LOG2_E, MIN_LOG2_WEIGHT
from denoisers.methods import svgf_terms
from denoisers.methods.eaw import filter_eaw
from denoisers.registry import Frame

RTOL, ATOL = 1e-4, 1e-6
#: Bound of the few elements of a corrupted stream past RTOL (measured: torch float32 vs float64 2e-3).
STREAM_RTOL = 5e-3

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def kernels():
    """The built extension (skips the module's comparisons when it cannot be built)."""
    module = native.load() if native.enabled() else None
    if module is None:
        pytest.skip("native kernels unavailable (no compiler/ninja, or MCDN_NATIVE=0)")
    return module


def both_paths(monkeypatch, run):
    """``run()`` with the native kernels and with the torch path: (native result, torch result)."""
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "1")
    assert native.load() is not None
    native_result = run()
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "0")
    assert native.load() is None
    torch_result = run()
    monkeypatch.delenv(native.ENVIRONMENT_SWITCH)
    return native_result, torch_result


def assert_close(actual: torch.Tensor, expected: torch.Tensor) -> None:
    assert actual.shape == expected.shape
    assert torch.isfinite(actual).all()
    torch.testing.assert_close(actual, expected, rtol=RTOL, atol=ATOL)


def assert_close_streams(actual: torch.Tensor, expected: torch.Tensor) -> None:
    """:func:`assert_close` for frames of corrupted streams: at most 0.1 % of the elements (at least 2)
    may exceed ``rtol``, all within ``STREAM_RTOL`` (the float32 error of the torch path itself there)."""
    assert actual.shape == expected.shape and torch.isfinite(actual).all()
    excess = (actual - expected).abs() > ATOL + RTOL * expected.abs()
    assert int(excess.sum()) <= max(2, expected.numel() // 1000)
    torch.testing.assert_close(actual, expected, rtol=STREAM_RTOL, atol=ATOL)


def random_guides(height: int, width: int, seed: int) -> dict[str, torch.Tensor]:
    """Colour (3) with a bright spike, unit normals (3) with a zero-normal hole and a crease, depth (1)
    with a jump, all (C, H, W)."""
    generator = torch.Generator().manual_seed(seed)
    color = torch.rand(3, height, width, generator=generator) ** 3 * 4
    color[:, height // 2, width // 3] = 1e4                       # a firefly
    normal = torch.randn(3, height, width, generator=generator) * 0.2 + torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    normal[:, :, : width // 3] += torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)   # a crease
    normal = normal / normal.norm(dim=0, keepdim=True)
    normal[:, : height // 4, : width // 4] = 0.0                  # no surface there
    depth = 2.0 + torch.rand(1, height, width, generator=generator) * 0.05
    depth[:, :, width // 2:] += 1.5                               # an object edge
    return {"color": color, "normal": normal, "depth": depth}


SIZES = [(37, 53), (64, 64), (23, 9), (5, 3), (1, 17), (70, 140)]


# -------------------------------------------------------------------------------------------------
# SVGF a-trous passes
# -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("height, width", SIZES)
@pytest.mark.parametrize("params", [{}, {"sigma_normal": 16.0, "sigma_luminance": 1.0, "iterations": 3},
                                    {"iterations": 1, "sigma_depth": 0.3}])
def test_svgf_atrous_native_matches_torch(kernels, monkeypatch, height: int, width: int, params: dict) -> None:
    guides = random_guides(height, width, seed=height * 100 + width)
    variance = torch.rand(1, height, width, generator=torch.Generator().manual_seed(width)) ** 2
    variance[:, 0, 0] = 0.0
    svgf = registry.build("svgf", params)
    gradient = svgf_terms.depth_gradient(guides["depth"])
    (out, history), (expected, expected_history) = both_paths(
        monkeypatch, lambda: svgf._atrous(guides["color"], variance, guides["normal"], guides["depth"], gradient))
    assert_close(out, expected)
    assert_close(history, expected_history)


def test_native_kernels_are_independent_of_the_thread_count(kernels) -> None:
    """Two workers split the rows (each recomputes the shared pair terms of its first rows): bit-identical."""
    height, width = 300, 64                                       # > one chunk of row_grain rows
    guides = random_guides(height, width, seed=3)
    variance = torch.rand(1, height, width) ** 2
    gradient = svgf_terms.depth_gradient(guides["depth"])
    geometry = torch.cat([guides["normal"], guides["depth"]])
    svgf = registry.build("svgf")

    def run():
        return (*svgf._atrous(guides["color"], variance, guides["normal"], guides["depth"], gradient),
                filter_eaw(guides["color"], geometry, 0.7, 5, 0.5))

    one = run()
    torch.set_num_threads(2)
    two = run()
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_native_kernels_check_their_inputs(kernels) -> None:
    image = torch.rand(3, 8, 9)
    with pytest.raises(RuntimeError, match="variance"):
        kernels.svgf_atrous(image, torch.rand(1, 8, 8), image, image[:1].contiguous(), image[:2].contiguous(), 5,
                            4.0, 128.0, 1.0, 0.6, 1e-10, 1e-3, MIN_LOG2_WEIGHT)
    with pytest.raises(RuntimeError, match="contiguous"):
        kernels.eaw_atrous(image.transpose(1, 2), torch.rand(6, 9, 8), [1.0], 1.0, MIN_LOG2_WEIGHT)


# -------------------------------------------------------------------------------------------------
# EAW
# -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("height, width", SIZES)
@pytest.mark.parametrize("geometry_channels, iterations", [(6, 5), (2, 3), (0, 2)])
def test_filter_eaw_native_matches_torch(kernels, monkeypatch, height: int, width: int, geometry_channels: int,
                                         iterations: int) -> None:
    guides = random_guides(height, width, seed=height + width)
    geometry = torch.cat([guides["normal"] / 0.5, guides["depth"].expand(3, height, width) / 0.25])
    geometry = geometry[:geometry_channels].contiguous()
    out, expected = both_paths(monkeypatch, lambda: filter_eaw(guides["color"], geometry, 0.7, iterations, 0.5))
    assert_close(out, expected)


# -------------------------------------------------------------------------------------------------
# Whole methods on corrupted multi-frame streams
# -------------------------------------------------------------------------------------------------

def corrupt(image: torch.Tensor, generator: torch.Generator, fraction: float = 0.01) -> torch.Tensor:
    """A copy with NaN, +Inf, -Inf and 1e30 spikes at random positions."""
    image = image.clone()
    flat = image.view(-1)
    count = max(4, int(fraction * flat.numel()))
    positions = torch.randperm(flat.numel(), generator=generator)[:count]
    values = torch.tensor([float("nan"), float("inf"), -float("inf"), 1e30])
    flat[positions] = values[torch.arange(count) % 4]
    return image


def stream(height: int, width: int, frames: int, spp: int, seed: int) -> list[Frame]:
    """A moving corrupted clip: sub-pixel motion, a disocclusion (invalid pixels), a camera cut."""
    generator = torch.Generator().manual_seed(seed)
    guides = random_guides(height, width, seed)
    clip = []
    for index in range(frames):
        noise = torch.rand(spp, 1, height, width, generator=generator) * 2
        radiance = guides["color"][None] * noise
        albedo = (0.2 + 0.8 * torch.rand(3, height, width, generator=generator))[None].expand(spp, -1, -1, -1)
        motion = torch.randn(2, height, width, generator=generator) * 0.7
        motion[:, : height // 3] += torch.tensor([2.5, -1.25]).view(2, 1, 1)   # a region moving faster
        valid = (torch.rand(1, height, width, generator=generator) > 0.1).float()
        depth = guides["depth"] * (1 + 0.12 * torch.rand(1, height, width, generator=generator))  # some fail
        samples = {"radiance": corrupt(radiance, generator), "albedo": corrupt(albedo, generator, 0.002),
                   "normal": corrupt(guides["normal"][None].repeat(spp, 1, 1, 1), generator, 0.002),
                   "depth": corrupt(depth[None].repeat(spp, 1, 1, 1), generator, 0.002),
                   "position": corrupt(torch.rand(spp, 3, height, width, generator=generator), generator, 0.002),
                   "flags": corrupt((torch.rand(spp, 4, height, width, generator=generator) > 0.8).float(),
                                    generator, 0.002)}
        pixel = {"motion": corrupt(motion, generator, 0.002), "valid": corrupt(valid, generator, 0.002),
                 "gbuffer.depth": corrupt(depth, generator, 0.002),
                 "gbuffer.normal": corrupt(guides["normal"], generator, 0.002)}
        clip.append(Frame(samples=samples, pixel=pixel, index=index, camera_cut=index == frames - 2))
    return clip


@pytest.mark.parametrize("height, width, spp", [(37, 53, 2), (48, 64, 1), (17, 8, 4)])
def test_svgf_stream_native_matches_torch(kernels, monkeypatch, height: int, width: int, spp: int) -> None:
    clip = stream(height, width, frames=8, spp=spp, seed=height * width)

    def run():
        svgf = registry.build("svgf")
        outputs, states = [], []
        for frame in clip:
            outputs.append(svgf.denoise(frame))
            states.append(svgf._history.state.clone())
            assert svgf.backend == native.backend()
        return outputs, states

    (outputs, states), (expected_outputs, expected_states) = both_paths(monkeypatch, run)
    for out, expected, state, expected_state in zip(outputs, expected_outputs, states, expected_states):
        assert_close_streams(out, expected)
        assert_close_streams(state, expected_state)           # the temporal state carried on
        assert torch.equal(state[5], expected_state[5])       # history lengths: bit-identical


def test_svgf_temporal_native_matches_torch(kernels, monkeypatch) -> None:
    """The temporal accumulation alone, on a random history with many failing consistency tests."""
    height, width = 29, 41
    generator = torch.Generator().manual_seed(9)
    guides = random_guides(height, width, seed=9)
    state = torch.cat([torch.rand(5, height, width, generator=generator) * 3,
                       torch.randint(1, 9, (1, height, width), generator=generator).float(),
                       guides["depth"], guides["normal"]])
    motion = torch.randn(2, height, width, generator=generator) * 3
    valid = (torch.rand(1, height, width, generator=generator) > 0.2).float()
    depth = guides["depth"] * (1 + 0.15 * torch.rand(1, height, width, generator=generator))
    frame = Frame(samples={}, pixel={"motion": corrupt(motion, generator), "valid": valid}, index=5, camera_cut=False)
    illumination = torch.rand(3, height, width, generator=generator)
    moments = torch.rand(2, height, width, generator=generator)

    def run():
        svgf = registry.build("svgf")
        svgf._history = svgf_terms.History(state=state, index=4)
        return svgf._accumulate(frame, illumination, moments, depth, guides["normal"])

    result, expected = both_paths(monkeypatch, run)
    assert 0.2 < float((expected[2] > 1).float().mean()) < 0.95          # both outcomes of the tests occur
    for out, reference in zip(result, expected):
        assert_close(out, reference)
    assert torch.equal(result[2], expected[2])


@pytest.mark.parametrize("height, width", [(37, 53), (64, 48)])
def test_eaw_method_native_matches_torch_on_corrupted_input(kernels, monkeypatch, height: int, width: int) -> None:
    frame = stream(height, width, frames=1, spp=2, seed=height + width)[0]

    def run():
        eaw = registry.build("eaw")
        out = eaw.denoise(frame)
        assert eaw.backend == native.backend()
        return out

    out, expected = both_paths(monkeypatch, run)
    assert_close_streams(out, expected)


@pytest.mark.parametrize("seed", [11, 14])
def test_svgf_atrous_native_is_as_accurate_as_torch_next_to_spikes(kernels, monkeypatch, seed: int) -> None:
    """On spiky inputs, both float32 paths against the torch path evaluated in float64: the native one has
    to stay within the error budget that the torch one meets (measured: max 1e-4 / 2.4e-4 and mean
    1.3e-6 / 1.6e-6 relative for torch / native)."""
    height, width = 48, 64
    guides = random_guides(height, width, seed=seed)
    generator = torch.Generator().manual_seed(seed + 1)
    spikes = torch.rand(1, height, width, generator=generator) < 0.01
    color = torch.where(spikes, torch.tensor(1e8), guides["color"])
    variance = torch.where(spikes, torch.tensor(1e16), torch.rand(1, height, width, generator=generator))
    gradient = svgf_terms.depth_gradient(guides["depth"])
    inputs = (color, variance, guides["normal"], guides["depth"], gradient)
    svgf = registry.build("svgf")
    (out, _), (torch_out, _) = both_paths(monkeypatch, lambda: svgf._atrous(*inputs))
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "0")
    default_dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)                 # the torch path's buffers follow it
    try:
        exact, _ = registry.build("svgf")._atrous(*(x.double() for x in inputs))
    finally:
        torch.set_default_dtype(default_dtype)
    assert exact.dtype == torch.float64

    def errors(x: torch.Tensor) -> tuple[float, float]:
        relative = (x.double() - exact).abs() / (exact.abs() + ATOL)
        return float(relative.max()), float(relative.mean())

    assert errors(torch_out)[0] > 1e-5                         # the case is ill-conditioned indeed
    for path_out in (torch_out, out):
        worst, mean = errors(path_out)
        assert worst < 5e-4 and mean < 5e-6


# -------------------------------------------------------------------------------------------------
# Loading and fallback
# -------------------------------------------------------------------------------------------------

def test_environment_switch_disables_the_kernels(monkeypatch) -> None:
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "0")
    assert not native.enabled() and native.load() is None and native.backend() == "torch"
    eaw = registry.build("eaw")
    eaw.denoise(stream(9, 11, frames=1, spp=1, seed=1)[0])
    assert eaw.backend == "torch"


def test_failed_build_warns_once_and_falls_back(monkeypatch, tmp_path, caplog) -> None:
    broken = tmp_path / "broken.cpp"
    broken.write_text("this is not C++\n")
    monkeypatch.setenv(native.DIRECTORY_VARIABLE, str(tmp_path / "extensions"))
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "1")
    monkeypatch.setattr(native, "SOURCES", (broken,))
    monkeypatch.setattr(native, "EXTENSION_NAME", "mcdn_broken_test")
    monkeypatch.setattr(native, "_built", [])
    with caplog.at_level(logging.WARNING, logger=native.__name__):
        assert native.load() is None
        assert native.load() is None
        eaw = registry.build("eaw")
        out = eaw.denoise(stream(9, 11, frames=1, spp=1, seed=2)[0])
    assert eaw.backend == "torch" and torch.isfinite(out).all()
    warnings = [record for record in caplog.records if record.name == native.__name__]
    assert len(warnings) == 1 and "torch implementation" in warnings[0].getMessage()
    assert "error" in warnings[0].getMessage().lower()


def test_build_flags_keep_ieee_semantics() -> None:
    assert "-O3" in native.CFLAGS
    assert not any(flag in native.CFLAGS for flag in ("-ffast-math", "-Ofast", "-march=native", "-ffinite-math-only"))


def test_eaw_kernel_weights_follow_exp2_over_the_clamped_range(kernels) -> None:
    """With one colour channel differing and no geometry, EAW weights are exp2(max(log2 h - d^2, min)): one
    pass over pixel pairs (0, d) checks the kernel's exp2 against torch's over the whole clamped range."""
    distances = torch.linspace(0.0, 9.5, 64)                 # d^2 up to ~90 > -MIN_LOG2_WEIGHT: clamped too
    color = torch.zeros(3, 1, 2 * distances.numel())
    color[0, 0, 1::2] = distances                           # pairs (0, d): each pixel 0 has its neighbour d
    scale = math.sqrt(LOG2_E)
    out = kernels.eaw_atrous(color, torch.zeros(0, 1, color.shape[-1]), [1.0], scale, MIN_LOG2_WEIGHT)
    h_centre, h_1, h_2 = 9 / 64, 3 / 32, 3 / 128               # B3 weights of the row taps 0, +-1, +-2
    # Pixel 2k (value 0) sees 2k+1 (d_k, tap +1), 2k-1 (d_{k-1}, tap -1), 2k +- 2 (value 0, taps +-2).
    for k in range(1, distances.numel() - 1):
        w_next = torch.exp2(torch.clamp(math.log2(h_1) - distances[k] ** 2, min=MIN_LOG2_WEIGHT))
        w_prev = torch.exp2(torch.clamp(math.log2(h_1) - distances[k - 1] ** 2, min=MIN_LOG2_WEIGHT))
        expected = (w_next * distances[k] + w_prev * distances[k - 1]) / (h_centre + 2 * h_2 + w_next + w_prev)
        torch.testing.assert_close(out[0, 0, 2 * k], expected, rtol=RTOL, atol=1e-30)


def test_build_lives_in_this_installation_not_a_shared_cache(monkeypatch) -> None:
    monkeypatch.delenv(native.DIRECTORY_VARIABLE, raising=False)
    package = Path(native.__file__).resolve().parent
    assert native.build_directory() == package / "_build"


def test_build_timeout_warns_once_and_falls_back(monkeypatch, tmp_path, caplog) -> None:
    monkeypatch.setenv(native.DIRECTORY_VARIABLE, str(tmp_path / "native"))
    monkeypatch.setenv(native.TIMEOUT_VARIABLE, "1")
    monkeypatch.setenv(native.ENVIRONMENT_SWITCH, "1")
    monkeypatch.setattr(native, "_built", [])
    with caplog.at_level(logging.WARNING, logger=native.__name__):
        assert native.load() is None and native.load() is None
    warnings = [record.getMessage() for record in caplog.records if record.name == native.__name__]
    assert len(warnings) == 1 and "timed out" in warnings[0], warnings


# Builds only the per-pixel kernel extension (the smallest source; the lock handling is the same for all three).
_BUILD_KERNELS = ("import logging; logging.basicConfig(level=logging.INFO); from denoisers import native; "
                  "print('kernels:', 'native' if native.load_kernels() is not None else 'torch')")


def _native_command(build_dir: Path, **kwargs) -> subprocess.Popen:
    env = dict(os.environ, **{native.DIRECTORY_VARIABLE: str(build_dir), native.ENVIRONMENT_SWITCH: "1"})
    return subprocess.Popen([sys.executable, "-c", _BUILD_KERNELS], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **kwargs)


@pytest.mark.slow
def test_a_build_killed_part_way_does_not_block_the_next(tmp_path) -> None:
    # A cancelled job: the build is killed (with its compiler) while torch holds its lock file.
    build_dir = tmp_path / "native"
    first = _native_command(build_dir)
    deadline = time.monotonic() + 120
    while not list(build_dir.glob("*/lock")) and time.monotonic() < deadline and first.poll() is None:
        time.sleep(0.2)
    assert first.poll() is None, "the build finished before it could be killed"
    time.sleep(2.0)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    assert list(build_dir.glob("*/lock")), "expected torch's lock file of the killed build to remain"
    second = _native_command(build_dir)
    stdout, stderr = second.communicate(timeout=900)
    assert second.returncode == 0 and "kernels: native" in stdout, stderr[-2000:]


@pytest.mark.slow
def test_the_kernel_source_ships_in_a_wheel(tmp_path) -> None:
    import zipfile

    import shutil

    repo = Path(native.__file__).resolve().parents[2]
    source = tmp_path / "source"       # setuptools writes build/ into the tree it builds: use a copy
    source.mkdir()
    shutil.copy(repo / "pyproject.toml", source)
    for package in ("scenegen", "denoisers"):
        shutil.copytree(repo / package, source / package, ignore=shutil.ignore_patterns("_build", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(tmp_path / "wheel"), str(source)], check=True, capture_output=True, timeout=600)
    wheel = next((tmp_path / "wheel").glob("*.whl"))
    assert "denoisers/native/atrous.cpp" in zipfile.ZipFile(wheel).namelist()


def test_native_loops_use_torchs_threads() -> None:
    """The extensions are built with OpenMP: at::parallel_for only splits work under _OPENMP (without it every
    native kernel ran on one thread whatever torch.set_num_threads said)."""
    assert "-fopenmp" in native.CFLAGS and "-fopenmp" in native.LDFLAGS
    module = native.load_affinity()
    if module is None:
        pytest.skip("native affinity extension unavailable")
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert module.parallel_workers(64) == 2
        torch.set_num_threads(1)
        assert module.parallel_workers(64) == 1
    finally:
        torch.set_num_threads(previous)
