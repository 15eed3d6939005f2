"""compute.device (denoisers.device): resolution, what it does to configs and store keys, and that no code path of
training or inference hard-codes the CPU, checked here without a GPU on torch's ``meta`` device.

The meta checks put the data and the network on ``meta`` and run the job's own placement (the training job's
DeviceTask, the evaluation's Denoiser.to and default device), so a tensor that some step creates on the CPU
(``torch.from_numpy``, ``device="cpu"``, a factory call inside a custom backward, which runs outside the default
device on another thread) meets a meta tensor and fails with a device mismatch, as it would on CUDA. Meta tensors
have no values: sync points (``float``, ``item``, ``bool``) are answered with a constant, and the adaptive
sampler's data-dependent rounding is replaced by an even sample map of the right shape on the same device.
"""
from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from denoisers import device as device_module
from denoisers.device import (DeviceError, configured_device, key_device, render_variant, resolve_config_device,
                              resolve_device, to_device, torch_device)
from scenegen.config import load_config

REPO = Path(__file__).resolve().parents[1]
CONFIGS = [REPO / "config" / name for name in ("config.yaml", "isik2021.yaml")]


@pytest.fixture
def no_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(device_module, "cuda_status", lambda: (False, "no NVIDIA driver (test)"))


@pytest.fixture
def with_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(device_module, "cuda_status", lambda: (True, "CUDA works: test GPU"))


# ------------------------------------------------------------------------------------------- resolution
def test_auto_is_the_cpu_without_cuda_and_cuda_with_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(device_module, "cuda_status", lambda: (False, "none"))
    assert resolve_device("auto") == "cpu"
    monkeypatch.setattr(device_module, "cuda_status", lambda: (True, "yes"))
    assert resolve_device("auto") == "cuda"
    assert resolve_device("cpu") == "cpu"


def test_explicit_cuda_is_taken_when_planning_and_checked_when_used(no_cuda: None) -> None:
    assert resolve_device("cuda") == "cuda"            # a login node plans GPU jobs without a GPU
    with pytest.raises(DeviceError, match="compute.device is cuda.*no NVIDIA driver"):
        resolve_device("cuda", verify=True)
    with pytest.raises(DeviceError):
        torch_device({"compute": {"device": "cuda"}})
    with pytest.raises(ValueError, match="'gpu' is not one of auto, cpu, cuda"):
        resolve_device("gpu")


def test_this_machine_resolves_auto_to_what_torch_can_use() -> None:
    works, why = device_module.cuda_status()
    assert works == torch.cuda.is_available(), why
    assert configured_device({}) == ("cuda" if works else "cpu")


def test_a_config_on_the_cpu_is_unchanged_but_for_the_resolved_device(no_cuda: None) -> None:
    cfg = load_config(CONFIGS[0])
    before = {**cfg, "compute": None}
    resolve_config_device(cfg)
    assert cfg["compute"] == {"device": "cpu"} and cfg["render"]["variant"] == "llvm_ad_rgb"
    assert {**cfg, "compute": None} == before


def test_cuda_renders_with_the_cuda_variant_and_scalar_stays_scalar(with_cuda: None) -> None:
    cfg = load_config(CONFIGS[0])
    resolve_config_device(cfg)
    assert cfg["compute"]["device"] == "cuda" and cfg["render"]["variant"] == "cuda_ad_rgb"
    assert render_variant("scalar_rgb", "cuda") == "scalar_rgb"
    with pytest.raises(DeviceError, match="needs compute.device cuda"):
        render_variant("cuda_ad_rgb", "cpu")


def test_render_digests_tell_cuda_renders_from_cpu_renders(monkeypatch: pytest.MonkeyPatch) -> None:
    from scenegen.digests import render_digest

    cfg = load_config(CONFIGS[0])
    monkeypatch.setattr(device_module, "cuda_status", lambda: (False, "none"))
    cpu = resolve_config_device(load_config(CONFIGS[0]))
    monkeypatch.setattr(device_module, "cuda_status", lambda: (True, "yes"))
    cuda = resolve_config_device(load_config(CONFIGS[0]))
    for kind in ("noisy", "reference"):
        assert render_digest(cpu, "test_000", kind) == render_digest(cfg, "test_000", kind)
        assert render_digest(cuda, "test_000", kind) != render_digest(cpu, "test_000", kind)


def test_store_keys_on_the_cpu_are_the_keys_from_before_the_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every stored model keeps its key on the CPU; a CUDA-trained model is another key (and another
    checkpoint key, so a CUDA run never continues a CPU checkpoint)."""
    from denoisers.store.keys import _digest, checkpoint_key, key_inputs, model_key
    from denoisers.training.models import model_spec

    cfg = load_config(CONFIGS[0])
    monkeypatch.setattr(device_module, "cuda_status", lambda: (False, "none"))
    inputs = key_inputs(cfg, model_spec(cfg, "rae"))
    assert "device" not in inputs and key_device(cfg) == {}
    cpu_key, cpu_checkpoint = model_key(cfg, "rae"), checkpoint_key(cfg, "rae")
    assert cpu_key == _digest(inputs)
    assert model_key({**cfg, "compute": {"device": "cpu"}}, "rae") == cpu_key
    cuda_cfg = {**cfg, "compute": {"device": "cuda"}}
    assert key_device(cuda_cfg) == {"device": "cuda"}
    assert model_key(cuda_cfg, "rae") != cpu_key and checkpoint_key(cuda_cfg, "rae") != cpu_checkpoint


def test_the_stored_keys_of_the_default_config_are_found(no_cuda: None) -> None:
    """The store lookup of every default model is unchanged by the device setting (auto -> cpu here)."""
    from denoisers.store import ModelStore, model_key
    from denoisers.training.models import trained_model_specs

    cfg = load_config(CONFIGS[0])
    store = ModelStore.of(cfg)
    specs = [s for s in trained_model_specs(cfg) if "_seed" not in s.id]
    found = [s.id for s in specs if store.model_entry(cfg, s.id) is not None]
    assert found and "rae" in found, f"stored: {found}; keys {[model_key(cfg, s.id)[:16] for s in specs]}"


def test_provenance_says_what_torch_and_mitsuba_computed_on() -> None:
    from denoisers.device import device_info
    from denoisers.provenance import describe, provenance

    record = provenance({"timing": 1}, device=device_info("cpu"))
    assert record["device"]["device"] == "cpu" and record["device"]["model"] == record["cpu_model"]
    assert "torch and Mitsuba on the CPU" in describe(record)[1]
    gpu = {**record, "device": {"device": "cuda", "model": "NVIDIA H100 80GB HBM3", "driver": "580.159.04"}}
    assert "on NVIDIA H100 80GB HBM3 (CUDA, driver 580.159.04)" in describe(gpu)[1]


def test_to_device_moves_tensors_in_nested_batches() -> None:
    from denoisers.training.data import Batch

    batch = Batch({"radiance": torch.ones(1, 2)}, plans=[], index=3)
    moved = to_device({"a": [batch, (torch.zeros(1),)], "b": 1}, torch.device("meta"))
    assert moved["a"][0].tensors["radiance"].device.type == "meta" and moved["a"][0].index == 3
    assert moved["a"][1][0].device.type == "meta" and moved["b"] == 1


# -------------------------------------------------------------------------------- no hard-coded CPU
def _clear_tensor_caches() -> None:
    """Empty every functools cache of the project's modules: a cached tensor made under the meta default device
    (losses' Laplacian kernels) must not outlive the test (meta tensors cannot be copied to the CPU)."""
    import functools
    import sys

    for name, module in list(sys.modules.items()):
        if name.startswith(("denoisers", "scenegen")) and module is not None:
            for value in vars(module).values():
                if isinstance(value, functools._lru_cache_wrapper) and value is not device_module.cuda_status:
                    value.cache_clear()


@pytest.fixture
def clean_caches() -> Iterator[None]:
    _clear_tensor_caches()
    yield
    _clear_tensor_caches()


@contextlib.contextmanager
def meta_values() -> Iterator[None]:
    """Sync points of meta tensors answered with a constant; the adaptive sampler's rounding (data-dependent:
    a water-filling loop) replaced by an even map of the right shape, dtype and device."""
    import denoisers.adaptive as adaptive

    answers = {"__float__": 0.5, "item": 0.5, "__bool__": False, "__int__": 1}
    originals = {name: getattr(torch.Tensor, name) for name in answers}

    def patched(name):
        def call(self, *args, **kwargs):
            return answers[name] if self.device.type == "meta" else originals[name](self, *args, **kwargs)
        return call

    original_map = adaptive.normalize_sample_map

    def even_map(importance, budget, max_count, *args, **kwargs):
        if importance.device.type != "meta":
            return original_map(importance, budget, max_count, *args, **kwargs)
        return torch.full(importance.shape, int(budget), dtype=torch.int64, device=importance.device)

    import torch.fx.experimental._config as fx_config

    nonzero = fx_config.meta_nonzero_assume_all_nonzero
    fx_config.meta_nonzero_assume_all_nonzero = True      # data-dependent shapes: assume every element counts
    for name in answers:
        setattr(torch.Tensor, name, patched(name))
    adaptive.normalize_sample_map = even_map
    try:
        yield
    finally:
        fx_config.meta_nonzero_assume_all_nonzero = nonzero
        for name, function in originals.items():
            setattr(torch.Tensor, name, function)
        adaptive.normalize_sample_map = original_map


def _trainable_specs() -> list:
    from denoisers.training.models import model_spec

    specs, methods = [], set()
    for path in CONFIGS:
        cfg = load_config(path)
        for entry in cfg["training"]["models"]:
            spec = model_spec(cfg, entry["id"])
            if spec.method not in methods:
                methods.add(spec.method)
                # Where tensors live does not depend on their size: 32-pixel crops, 3-frame sequences, batch 1.
                small = dataclasses.replace(spec, data={**spec.data, "crop": 32, "length": min(3, spec.data["length"])},
                                            optimizer={**spec.optimizer, "batch_size": 1})
                specs.append(pytest.param(small, id=spec.method))
    return specs


@pytest.mark.parametrize("spec", _trainable_specs())
def test_a_training_step_places_nothing_on_the_cpu(spec, clean_caches: None) -> None:
    """The training job's placement (training.on_device) runs every trainable method's step on another device."""
    from denoisers.device import default_device
    from denoisers.training.on_device import place
    from denoisers.training.synthetic import FixedBatch, synthetic_batch
    from denoisers.training.tasks import task_builder

    builder = task_builder(spec.method)
    batch = synthetic_batch(spec, builder.sample_buffers, pixel_buffers=builder.pixel_buffers,
                            mean_buffers=builder.mean_buffers)
    meta = torch.device("meta")
    task, data, validation = place(builder.build(spec), FixedBatch(batch), [batch], meta)
    with meta_values(), default_device(meta):
        model = task.build_model()
        assert {p.device.type for p in model.parameters()} == {"meta"}
        loss, _ = task.loss(model, data.batch(0, 1))
        assert loss.device.type == "meta"
        loss.backward()
        assert all(p.grad is None or p.grad.device.type == "meta" for p in model.parameters())
        if hasattr(task, "predict"):
            assert task.predict(model, validation[0]).device.type == "meta"


def _inference_rows() -> list:
    from denoisers.evaluate import method_specs, volume_method_specs

    rows, methods = [], set()
    for path in CONFIGS:
        cfg = load_config(path)
        for spec in method_specs(cfg) + volume_method_specs(cfg):
            if spec.method not in methods and not spec.method.startswith("oidn"):   # OIDN: host images, own device
                methods.add(spec.method)
                rows.append(pytest.param(path, spec, id=spec.method))
    return rows


@pytest.mark.filterwarnings("ignore:for .*copying from a non-meta parameter:UserWarning")  # a meta net loads nothing
@pytest.mark.parametrize(("config", "row"), _inference_rows())
def test_inference_places_nothing_on_the_cpu(config: Path, row, tmp_path: Path, clean_caches: None) -> None:
    """Every evaluation method denoises frames on another device (Denoiser.to, the evaluation's default device),
    learned ones with an untrained network of their configured size."""
    from denoisers import registry
    from denoisers.device import default_device
    from denoisers.registry import Frame
    from denoisers.training.checkpoints import save_atomic
    from denoisers.training.loop import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
    from denoisers.training.models import model_spec
    from denoisers.training.tasks import build_task
    from scenegen.channels import PIXEL_BUFFERS, SAMPLE_BUFFERS

    cfg = load_config(config)
    params = {k: v for k, v in row.params.items() if k != "tuned"}
    if "model" in params:
        task = build_task(model_spec(cfg, params.pop("model")))
        path = tmp_path / "best.pt"
        save_atomic({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": "model",
                     "net": task.net_spec(), "model_state": task.build_model().state_dict(), "step": 0,
                     "metrics": {}}, path)
        params["checkpoint"] = str(path)
    method = registry.build(row.method, params, row=row.id)
    meta = torch.device("meta")
    method.to(meta)
    height = width = 16
    spp = row.spp[0] * method.samples_factor
    layers = spp + (cfg["render"]["extra_radiance_spp"] if method.info.adaptive else 0)
    samples = {b: torch.rand(layers if b == "radiance" else spp, len(SAMPLE_BUFFERS[b]), height, width)
               for b in method.info.inputs}
    pixel = {b: torch.rand(len(PIXEL_BUFFERS[b]), height, width) for b in method.info.pixel_inputs}
    if "valid" in pixel:
        pixel["valid"] = torch.ones(1, height, width)
    camera = {"to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
    method.reset()
    for index in range(2):
        frame = Frame(samples, pixel, index, index == 0, {"camera": camera},
                      float(row.spp[0]) if method.info.adaptive else None).to(meta)
        with meta_values(), default_device(meta), torch.no_grad():
            result = method.denoise(frame)
        radiance = result.radiance if isinstance(result, registry.AdaptiveOutput) else result
        assert radiance.device.type == "meta", f"{row.method} returned a {radiance.device} tensor"


def test_oidn_falls_back_to_its_cpu_device_where_pyoidn_has_no_cuda_one(caplog: pytest.LogCaptureFixture) -> None:
    """OIDN asked for CUDA on a machine (or pyoidn build) without it builds its CPU device and says so."""
    import logging

    from denoisers import registry

    method = registry.build("oidn")
    method.device = torch.device("cuda")          # as Denoiser.to would set it (no tensor is moved here)
    works, _ = device_module.cuda_status()
    with caplog.at_level(logging.WARNING, logger="denoisers.methods.oidn"):
        method._build(8, 8)
    assert method._filter is not None and method._size == (8, 8)
    if not works:
        assert "no CUDA device in pyoidn" in caplog.text and "runs on the CPU" in caplog.text
    method.close()


def test_the_reports_timing_line_names_the_device() -> None:
    from types import SimpleNamespace

    from denoisers.report.writer import _timing_line

    record = {"renderers": {"test_000": {"samples_per_s": 2e6, "repeats": 3, "layers": 4}}, "frames": 4,
              "scene": "test_000", "threads": 1, "repeats": 5,
              "sgemm": {"gflops_per_s_median": 50.0, "gflops_per_s": [49.0, 51.0]},
              "provenance": {"device": {"device": "cuda", "model": "NVIDIA H100 80GB HBM3", "driver": "580.159.04"}}}
    res = SimpleNamespace(timing=SimpleNamespace(record=record), cfg={"evaluation": {}})
    assert "on NVIDIA H100 80GB HBM3 (CUDA, driver 580.159.04; rows and renderer)" in _timing_line(res)
    record["provenance"] = {"device": {"device": "cpu", "model": "AMD EPYC", "cores": 2}}
    assert "on the CPU (AMD EPYC)" in _timing_line(res)
    del record["provenance"]                      # a timing job from before the setting
    assert "rule time_methods) timed every configured row (and the capacity ablations' sizes) on the first" in \
        _timing_line(res)
