"""Tests of the training step's arithmetic (denoisers/training/precision.py and its use by the trainer and the
training job): the config setting, the bf16 detection, fp32 master state under bf16 autocast, determinism."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch

from denoisers.nets import rae_task as rae_task_module
from denoisers.training import precision
from denoisers.training.job import trainer_config, work_dir_for
from denoisers.training.loop import TrainerConfig, load_checkpoint
from denoisers.training.models import model_spec, model_specs
from scenegen.config import ConfigError, load_config, load_schema, validate_config
from tests.test_training import make_trainer

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def restore_torch_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def machine(monkeypatch: pytest.MonkeyPatch, flags: set[str], torch_bf16: bool = True) -> None:
    """Pretend the CPU has ``flags`` and torch's oneDNN does (not) run bf16."""
    monkeypatch.setattr(precision, "cpu_flags", lambda path=precision.CPUINFO: frozenset(flags))
    monkeypatch.setattr(precision, "torch_has_bf16", lambda: torch_bf16)


# ------------------------------------------------------------------------------------------ config
def test_schema_defaults_are_the_code_defaults_and_variants_inherit_them() -> None:
    assert load_schema()["$defs"]["training_compute"]["properties"]["precision"]["enum"] == list(precision.PRECISIONS)
    defaults = {key: value["default"] for key, value in
                load_schema()["$defs"]["training_compute"]["properties"].items()}
    assert defaults == precision.DEFAULT_COMPUTE
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    specs = model_specs(cfg)
    assert all(spec.compute == specs[0].compute for spec in specs)
    assert set(specs[0].compute) == set(precision.DEFAULT_COMPUTE)
    assert "compute" in specs[0].settings()


@pytest.mark.parametrize("compute, message", [
    ({"precision": "fp16"}, "'fp16'"), ({"precision": "bf16", "channels_last": "yes"}, "'yes'"),
    ({"dtype": "bf16"}, "dtype")])
def test_bad_compute_settings_are_rejected_by_the_schema(compute: dict, message: str) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["training"]["models"][0]["compute"] = compute
    with pytest.raises(ConfigError) as excinfo:
        validate_config(cfg)
    text = str(excinfo.value)
    assert message in text and "compute" in text
    if "precision" in compute and compute["precision"] == "fp16":
        assert "auto" in text and "bf16" in text and "fp32" in text


def test_explicit_settings_reach_the_trainer_and_change_the_digest() -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    before = model_spec(cfg, "rae").settings()
    cfg["training"]["models"][0]["compute"] = {"precision": "bf16", "channels_last": False}
    validate_config(cfg)
    spec = model_spec(cfg, "rae")
    config = trainer_config(cfg, spec, threads=1, progress=False)
    assert (config.precision, config.channels_last) == ("bf16", False)
    assert spec.settings() != before and spec.settings()["compute"] == {"precision": "bf16", "channels_last": False}
    with pytest.raises(ValueError, match="'fp16' is not one of auto, bf16, fp32"):
        TrainerConfig(max_steps=1, precision="fp16")


# --------------------------------------------------------------------------------------- detection
def test_cpu_flags_are_read_from_cpuinfo(tmp_path: Path) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: X\nflags\t\t: fpu avx2 avx512f avx512_bf16\n\n"
                       "processor\t: 1\nflags\t\t: fpu\n")
    assert precision.cpu_flags(cpuinfo) == {"fpu", "avx2", "avx512f", "avx512_bf16"}
    assert precision.cpu_flags(tmp_path / "missing") == frozenset()


@pytest.mark.parametrize("flags, torch_bf16, expected", [
    (set(), True, "fp32"), ({"avx2", "avx512f", "avx512bw"}, True, "fp32"),     # AVX-512 alone: emulated bf16
    ({"avx512_bf16"}, True, "bf16"), ({"amx_bf16", "amx_tile"}, True, "bf16"), ({"avx512_bf16"}, False, "fp32")])
def test_auto_is_bf16_only_with_native_bf16(monkeypatch: pytest.MonkeyPatch, flags: set[str], torch_bf16: bool,
                                            expected: str) -> None:
    machine(monkeypatch, flags, torch_bf16)
    step = precision.resolve("auto", channels_last=True)
    assert step.precision == expected and step.channels_last and step.configured == "auto"
    assert step.describe().startswith("bf16 autocast" if expected == "bf16" else "fp32")
    # The default layout follows the precision: channels-last with bf16, NCHW (today's fp32 step) without.
    assert precision.resolve_compute({}).fingerprint() == {"precision": expected, "channels_last": expected == "bf16"}
    assert precision.resolve("fp32", "auto").channels_last is False and precision.resolve("bf16").channels_last
    # Explicit settings are kept whatever the CPU.
    assert precision.resolve("fp32").precision == "fp32"
    assert precision.resolve("bf16").precision == "bf16"
    assert ("emulated" in precision.resolve("bf16").reason) == (expected == "fp32")


def test_work_dir_follows_what_auto_resolves_to(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    spec = model_spec(cfg, "rae")
    machine(monkeypatch, set())
    without = work_dir_for(tmp_path, cfg, spec)
    assert work_dir_for(tmp_path, cfg, spec) == without
    machine(monkeypatch, {"avx512_bf16"})
    assert work_dir_for(tmp_path, cfg, spec) != without


# ---------------------------------------------------------------------------------------- training
def test_bf16_step_runs_convolutions_in_bf16_and_keeps_fp32_state(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    loss_inputs: list[torch.dtype] = []
    original = rae_task_module.rae_loss

    def recording_loss(pred, target, weights=None):
        loss_inputs.append(pred.dtype)
        return original(pred, target, weights)

    monkeypatch.setattr(rae_task_module, "rae_loss", recording_loss)
    trainer = make_trainer(tmp_path / "bf16", steps=2, validation=True, validate_every=2, precision="bf16",
                           channels_last=True)
    conv_outputs: list[torch.dtype] = []
    trainer._setup()
    trainer.model.encoder_convs[0][0].register_forward_hook(lambda m, i, o: conv_outputs.append(o.dtype))
    loss, _ = trainer._train_step()
    assert conv_outputs == [torch.bfloat16] * 3              # one per frame of the 3-frame sequences
    assert loss_inputs == [torch.float32] and torch.isfinite(torch.tensor(loss))
    model, optimizer = trainer.model, trainer.optimizer
    assert all(p.dtype == torch.float32 and p.grad.dtype == torch.float32 for p in model.parameters())
    assert model.encoder_convs[0][0].weight.is_contiguous(memory_format=torch.channels_last)
    states = list(optimizer.state.values())
    assert len(states) == len(list(model.parameters()))
    assert all(s["exp_avg"].dtype == s["exp_avg_sq"].dtype == torch.float32 for s in states)
    # A whole run: the choice is logged once and recorded in summary.json; validation runs in fp32.
    runner = make_trainer(tmp_path / "run", steps=2, validate_every=2, precision="bf16", channels_last=True)
    with caplog.at_level(logging.INFO, logger=precision.__name__):
        outcome = runner.run()
    assert [r.getMessage() for r in caplog.records].count(f"train rae_samples: {runner.compute.describe()}") == 1
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["compute"]["precision"] == "bf16" and summary["compute"]["channels_last"] is True
    assert loss_inputs[-1] == torch.float32 and outcome.steps == 2
    state = load_checkpoint(outcome.checkpoint)
    assert all(t.dtype == torch.float32 for t in state["model_state"].values())


def test_fp32_step_is_unchanged_by_default(tmp_path: Path) -> None:
    trainer = make_trainer(tmp_path / "fp32", steps=1)
    trainer._setup()
    assert trainer._loss_model is trainer.model and trainer.compute.fingerprint() == {"precision": "fp32",
                                                                                     "channels_last": False}
    assert trainer.model.encoder_convs[0][0].weight.is_contiguous()


def test_two_bf16_runs_with_the_same_seed_give_identical_weights(tmp_path: Path) -> None:
    runs = [make_trainer(tmp_path / name, steps=3, validation=False, precision="bf16", channels_last=True).run()
            for name in ("a", "b")]
    other = make_trainer(tmp_path / "fp32", steps=3, validation=False, precision="fp32", channels_last=True).run()
    a, b, c = (load_checkpoint(run.checkpoint)["model_state"] for run in (*runs, other))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)            # bf16 does compute differently


def test_bf16_channels_last_resume_reproduces_the_uninterrupted_weights(tmp_path: Path) -> None:
    settings = dict(validation=False, precision="bf16", channels_last=True, checkpoint_every=2)
    make_trainer(tmp_path / "straight", steps=4, **settings).run()
    make_trainer(tmp_path / "resumed", steps=2, **settings).run()
    result = make_trainer(tmp_path / "resumed", steps=4, **settings).run()
    assert result.resumed_from == 2
    a = load_checkpoint(tmp_path / "straight" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "resumed" / "checkpoint.pt")
    assert all(torch.equal(a["model_state"][k], b["model_state"][k]) for k in a["model_state"])
    assert all(torch.equal(a["optimizer_state"]["state"][i]["exp_avg"], b["optimizer_state"]["state"][i]["exp_avg"])
               for i in a["optimizer_state"]["state"])
