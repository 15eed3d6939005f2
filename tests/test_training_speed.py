"""Tests of the training-speed job (denoisers/training/speed.py, rule time_training): the record of a tiny
config, the emulated-bf16 plan, the config keys (training.speed) and the report's "Training step speed" table."""
from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest
import torch

from denoisers.report import training_tables
from denoisers.report.writer import _training_speed_lines
from denoisers.training import precision, speed
from denoisers.training.models import model_specs
from denoisers.training.synthetic import synthetic_batch
from scenegen.config import ConfigError, load_config, load_schema, validate_config

REPO_ROOT = Path(__file__).resolve().parents[1]
EMULATED = "CPU has none of avx512_bf16, amx_bf16"


def smoke_config(**speed_keys) -> dict:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["training"]["speed"].update(speed_keys)
    return cfg


def no_native_bf16(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(precision, "bf16_support", lambda: (False, EMULATED))


# ------------------------------------------------------------------------------------------ record
@pytest.fixture(scope="module")
def tiny_record() -> dict:
    """The smoke config's RAE (width 0.25, 2 sequences x 3 frames x 32^2) with 1 thread, 2 rounds, fp32 only
    (its compute set to fp32 NCHW so that the configured variant is fp32 on every machine)."""
    cfg = smoke_config(variants=["fp32_nchw", "fp32_channels_last"], repeats=2, warmup=1, gemm_size=128)
    cfg["training"]["models"][0]["compute"] = {"precision": "fp32", "channels_last": False}
    threads = torch.get_num_threads()
    record = speed.time_training(cfg, threads=1, model_ids=["rae"])     # the smoke config also has 5 NTASD models
    assert torch.get_num_threads() == threads        # restored
    return record


def test_record_has_the_documented_keys(tiny_record: dict) -> None:
    record = tiny_record
    json.dumps(record, allow_nan=False)
    assert record["schema"] == speed.SPEED_SCHEMA and record["torch"] == torch.__version__
    assert record["threads"] == 1 and (record["repeats"], record["warmup"]) == (2, 1)
    assert {"capability", "native_bf16", "bf16_support", "bf16_flags"} <= set(record["cpu"])
    assert set(record["cpu"]["bf16_flags"]) <= set(precision.BF16_CPU_FLAGS)
    assert record["target_speedup"] == speed.TARGET_SPEEDUP
    assert len(record["gemm"]["sgemm_gflops_per_s"]) == 2 and record["gemm"]["size"] == 128
    assert "bf16 gemm torch.mm" in record["gemm"]["gflops_per_s"]
    [model] = record["models"]
    assert model["model"] == "rae" and model["batch"] == {"sequences": 2, "frames": 3, "crop": 32, "spp": 1}
    assert model["pixels_per_step"] == 2 * 3 * 32 * 32 and model["flops_per_step"] > 0
    assert model["compute"]["precision"] == "fp32" and model["compute"]["reason"]
    assert model["configured_variant"] == "fp32_nchw"
    assert [v["variant"] for v in model["variants"]] == ["fp32_nchw", "fp32_channels_last"]
    assert [v["configured"] for v in model["variants"]] == [True, False]


def test_record_numbers_are_consistent(tiny_record: dict) -> None:
    [model] = tiny_record["models"]
    sgemm = tiny_record["gemm"]["sgemm_gflops_per_s"]
    assert tiny_record["gemm"]["sgemm_gflops_per_s_median"] == pytest.approx(statistics.median(sgemm))
    base = model["variants"][0]["ms_per_step"]
    for v in model["variants"]:
        ms = v["ms_per_step"]
        assert v["status"] == "timed" and v["rounds"] == len(ms) == 2 and all(t > 0 for t in ms)
        assert v["ms_per_step_min"] <= v["ms_per_step_median"] <= v["ms_per_step_max"]
        assert (v["ms_per_step_min"], v["ms_per_step_max"]) == (min(ms), max(ms))
        median_s = v["ms_per_step_median"] / 1e3
        assert v["gflops_per_s"] == pytest.approx(model["flops_per_step"] / median_s / 1e9)
        assert v["pixels_per_s"] == pytest.approx(model["pixels_per_step"] / median_s)
        assert v["fraction_of_sgemm"] == pytest.approx(v["gflops_per_s"] / statistics.median(sgemm))
        assert v["speedup"] == pytest.approx([b / t for b, t in zip(base, ms)])
        assert v["speedup_min"] <= v["speedup_median"] <= v["speedup_max"]
    assert model["variants"][0]["speedup"] == [1.0, 1.0] and model["variants"][0]["speedup_median"] == 1.0


def test_describe_record_marks_the_configured_variant(tiny_record: dict) -> None:
    lines = speed.describe_record(tiny_record)
    assert any(line.startswith(" *fp32 NCHW") for line in lines)
    assert any(line.startswith("  fp32 channels-last") for line in lines)


# -------------------------------------------------------------------------------------------- plan
def test_emulated_bf16_variants_get_fewer_rounds_but_baseline_and_configured_always_run(
        monkeypatch: pytest.MonkeyPatch) -> None:
    no_native_bf16(monkeypatch)
    spec = model_specs(smoke_config())[0]                                   # compute auto -> fp32 here
    settings = {**speed.speed_settings(smoke_config()), "repeats": 5, "emulated_bf16_repeats": 1}
    configured, plan = speed._plan(spec, settings, False, EMULATED)
    assert configured == "fp32_nchw"
    assert [(key, rounds) for key, rounds, _ in plan] == [("fp32_nchw", 5), ("fp32_channels_last", 5),
                                                          ("bf16_nchw", 1), ("bf16_channels_last", 1)]
    assert EMULATED in plan[2][2] and "emulated_bf16_repeats" in plan[2][2]
    configured, plan = speed._plan(spec, {**settings, "variants": ["bf16_nchw"], "emulated_bf16_repeats": 0}, False,
                                   EMULATED)
    assert [(key, rounds) for key, rounds, _ in plan] == [("fp32_nchw", 5), ("bf16_nchw", 0)]
    assert "not timed" in plan[1][2]
    # An explicitly configured bf16 step is timed every round even where bf16 is emulated.
    bf16 = model_specs(smoke_config())[0]
    bf16.compute.update(precision="bf16")
    configured, plan = speed._plan(bf16, {**settings, "variants": []}, False, EMULATED)
    assert configured == "bf16_channels_last" and [(k, r) for k, r, _ in plan] == [("fp32_nchw", 5),
                                                                                   ("bf16_channels_last", 5)]


def test_synthetic_batch_has_the_model_size() -> None:
    spec = model_specs(smoke_config())[0]
    batch = synthetic_batch(spec, ("radiance", "albedo", "normal", "depth", "roughness"))
    assert batch["radiance"].shape == (2, 3, 1, 3, 32, 32) and batch["depth"].shape == (2, 3, 1, 1, 32, 32)
    assert batch["reference.radiance"].shape == (2, 3, 3, 32, 32) and batch["world_to_view"].shape == (2, 3, 3, 3)
    assert all(bool(torch.isfinite(value).all()) for value in batch.values())
    assert float(batch["radiance"].min()) >= 0 and float(batch["normal"].norm(dim=3).mean()) == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------ config
def test_schema_defaults_are_the_code_defaults() -> None:
    properties = load_schema()["properties"]["training"]["properties"]["speed"]["properties"]
    assert {key: value["default"] for key, value in properties.items()} == speed.DEFAULT_SPEED
    assert properties["variants"]["items"]["enum"] == list(speed.VARIANTS)
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    assert speed.speed_settings(cfg)["threads"] == cfg["training"]["threads"]
    assert [spec.id for spec in speed.speed_models(cfg)] == [m["id"] for m in cfg["training"]["models"]]
    assert speed.speed_models(smoke_config(enabled=False)) == []


@pytest.mark.parametrize("key, value, message", [
    ("variants", ["fp16_nchw"], "training.speed.variants[0]"), ("repeats", 0, "training.speed.repeats"),
    ("emulated_bf16_repeats", -1, "training.speed.emulated_bf16_repeats"), ("gemm", 512, "gemm")])
def test_bad_speed_settings_are_rejected_naming_the_key(key: str, value: object, message: str) -> None:
    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["training"]["speed"][key] = value
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        validate_config(cfg)


def test_the_digest_follows_the_speed_settings_and_the_step_not_the_budget() -> None:
    from denoisers.experiment import Lineage

    base = Lineage(smoke_config()).training_speed()
    assert Lineage(smoke_config(repeats=4)).training_speed() != base
    budget = smoke_config()
    budget["training"]["models"][0]["budget"]["max_steps"] = 99
    assert Lineage(budget).training_speed() == base
    crop = smoke_config()
    crop["training"]["models"][0]["data"]["crop"] = 48
    assert Lineage(crop).training_speed() != base


# ------------------------------------------------------------------------------------------ report
def synthetic_record() -> dict:
    """One model: fp32 NCHW (configured) 100 ms median [90, 110], fp32 channels-last 50 ms [45, 55] (2x every
    round), bf16 NCHW not timed; 1 Mpix and 5 GFLOP per step, sgemm 100 GFLOP/s."""
    def variant(key: str, ms: list[float], configured: bool = False) -> dict:
        label, precision_, layout = speed.VARIANTS[key]
        speedup = [b / t for b, t in zip([100.0, 110.0, 90.0], ms)]
        median = statistics.median(ms)
        return {"variant": key, "label": label, "precision": precision_, "channels_last": layout,
                "configured": configured, "rounds": len(ms), "note": "", "status": "timed", "ms_per_step": ms,
                "ms_per_step_median": median, "ms_per_step_min": min(ms), "ms_per_step_max": max(ms),
                "pixels_per_s": 1e6 / (median / 1e3), "gflops_per_s": 5.0 / (median / 1e3),
                "fraction_of_sgemm": 5.0 / (median / 1e3) / 100.0, "speedup": speedup,
                "speedup_median": statistics.median(speedup), "speedup_min": min(speedup),
                "speedup_max": max(speedup)}

    skipped = {"variant": "bf16_nchw", "label": "bf16 NCHW", "precision": "bf16", "channels_last": False,
               "configured": False, "rounds": 0, "status": "not timed",
               "note": f"bf16 is emulated here ({EMULATED}): 0 round(s)"}
    return {"schema": 1, "torch": "2.x", "threads": 2, "cpu_model": "Test CPU", "repeats": 3, "warmup": 1,
            "cpu": {"capability": "AVX2", "native_bf16": False, "bf16_support": EMULATED, "bf16_flags": []},
            "target_speedup": 1.6, "gemm": {"size": 1024, "sgemm_gflops_per_s_median": 100.0},
            "models": [{"model": "rae", "configured_variant": "fp32_nchw", "pixels_per_step": 10**6,
                        "flops_per_step": 5 * 10**9,
                        "compute": {"precision": "fp32", "channels_last": False, "configured": "auto",
                                    "reason": f"auto: {EMULATED}"},
                        "variants": [variant("fp32_nchw", [100.0, 110.0, 90.0], True),
                                     variant("fp32_channels_last", [50.0, 55.0, 45.0]), skipped]}]}


def test_training_speed_table_from_a_synthetic_record() -> None:
    table = training_tables.training_speed_table(synthetic_record()).set_index("variant")
    assert list(table.index) == ["fp32_nchw", "fp32_channels_last", "bf16_nchw"]
    base, fast = table.loc["fp32_nchw"], table.loc["fp32_channels_last"]
    assert (base.ms_per_step, base.ms_per_step_min, base.ms_per_step_max) == (100.0, 90.0, 110.0)
    assert base.mpix_per_s == pytest.approx(10.0) and base.gflops_per_s == pytest.approx(50.0)
    assert base.fraction_of_sgemm == pytest.approx(0.5) and base.speedup == base.speedup_min == base.speedup_max == 1
    assert fast.ms_per_step == 50.0 and fast.mpix_per_s == pytest.approx(20.0) and fast.gflops_per_s == pytest.approx(100)
    assert fast.fraction_of_sgemm == pytest.approx(1.0) and fast.speedup == fast.speedup_min == fast.speedup_max == 2
    assert bool(base.configured) and not bool(fast.configured)
    assert table.loc["bf16_nchw", "status"] == "not timed" and math.isnan(table.loc["bf16_nchw", "ms_per_step"])
    markdown = training_tables.training_speed_markdown(training_tables.training_speed_table(synthetic_record()))
    assert "fp32 NCHW *" in markdown and "100.0 [90.0, 110.0]" in markdown and "1.00x [1.00, 1.00]" in markdown
    assert "50.0 [45.0, 55.0]" in markdown and "2.00x [2.00, 2.00]" in markdown and "50.0%" in markdown
    assert "10.000" in markdown and "not timed: bf16 is emulated here" in markdown


def test_training_speed_verdict_explains_a_missed_target() -> None:
    text = training_tables.training_speed_verdict(synthetic_record())
    assert "1.00x the fp32 eager (NCHW) step" in text and "range 1.00-1.00x" in text
    assert "1.6x target is not met" in text and f"auto resolved to fp32 ({EMULATED})" in text
    record = synthetic_record()
    model = record["models"][0]
    model["configured_variant"] = "fp32_channels_last"
    model["variants"][0]["configured"], model["variants"][1]["configured"] = False, True
    assert "2.00x" in training_tables.training_speed_verdict(record) and "target is met" in training_tables.training_speed_verdict(record)


def test_report_subsection_and_its_not_run_line(tmp_path: Path) -> None:
    cfg = smoke_config()
    lines = _training_speed_lines(SimpleNamespace(cfg=cfg, training_speed=synthetic_record()), tmp_path)
    text = "\n".join(lines)
    assert "### Training step speed" in text and "fp32 NCHW *" in text and "target is not met" in text
    assert len(pd.read_csv(tmp_path / "training_speed.csv")) == 3 and (tmp_path / "training_speed.md").is_file()
    lines = _training_speed_lines(SimpleNamespace(cfg=cfg, training_speed=None), tmp_path)
    assert "Not run (timing/training.json is missing" in "\n".join(lines)
    assert "not run" in pd.read_csv(tmp_path / "training_speed.csv")["status"][0]
    lines = _training_speed_lines(SimpleNamespace(cfg=smoke_config(enabled=False), training_speed=None), tmp_path)
    assert "training.speed.enabled is false" in "\n".join(lines)
