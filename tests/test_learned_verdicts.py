"""Learned verdicts about methods (issue 46 §1-2): seed replicas of every model (training.seeds), seed rows,
seed-averaged values and seed-robust verdicts; half-budget twins (training.half_budget), their shared training run
and budget-stable verdicts; on synthetic results with a known answer and tiny synthetic trainings.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from denoisers import evaluate
from denoisers.report.claims import claims_table, evaluate_claim
from denoisers.report.verdicts import CONTRADICTED, INCONCLUSIVE, REPRODUCED
from denoisers.report.tables import SUMMARY_METRICS, summary_table
from denoisers.store import model_key
from denoisers.training.job import train_model
from denoisers.training.loop import load_checkpoint
from denoisers.training.models import (half_budget_specs, half_of, model_spec, model_specs, replica_of,
                                       same_training_as, seed_replicas, trained_model_specs, training_problems)
from scenegen.config import validate_config
from tests.test_claims import AGAINST, CLAIMS, CLEAR, PARTS, SCALE, Table, build, claims_config
from tests.test_training_job import synthetic_renders, tiny_training_config  # noqa: F401 (a fixture)

REPO_ROOT = Path(__file__).resolve().parents[1]


def default_config(seeds: int, half_budget: bool = False) -> dict:
    """The default config with ``seeds`` replicas and, unless asked for, no half-budget twins."""
    cfg = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    cfg["training"].update(seeds=seeds, half_budget=half_budget)
    return validate_config(cfg)


# ------------------------------------------------------------------------------------------------ replicas
def test_one_seed_adds_no_replica_and_three_add_two_per_model() -> None:
    assert seed_replicas(default_config(1)) == []
    cfg = default_config(3)
    # The capacity sweeps set their own seeds: 1 (a measurement, not a claim).
    once = {spec.id for spec in model_specs(cfg) if spec.ablation in ("rae_capacity", "ntasd_capacity")}
    assert once == {"rae_capacity_width025", "ntasd_capacity_width025"}
    bases = [spec for spec in model_specs(cfg) if spec.id not in once]
    replicas = seed_replicas(cfg)
    assert len(replicas) == 2 * len(bases)
    assert [spec.id for spec in trained_model_specs(cfg)] == [s.id for s in model_specs(cfg)] + [
        f"{s.id}_seed{k}" for s in bases for k in (1, 2)]
    for base in bases:
        seeds = {base.seed} | {model_spec(cfg, f"{base.id}_seed{k}").seed for k in (1, 2)}
        assert len(seeds) == 3, base.id   # three distinct training seeds
        for k in (1, 2):
            replica = model_spec(cfg, f"{base.id}_seed{k}")
            assert replica_of(cfg, replica.id) == (base.id, k)
            # Everything but id and seed is the base's (ablation labels included).
            same = {key: value for key, value in replica.settings().items() if key not in ("id", "seed")}
            assert same == {key: value for key, value in base.settings().items() if key not in ("id", "seed")}
    # Variants of one ablation share each replica's seed, as they share the first.
    assert model_spec(cfg, "rae_inputs_color_seed1").seed == model_spec(cfg, "rae_inputs_normal_seed1").seed \
        == model_spec(cfg, "rae_seed1").seed
    assert model_spec(cfg, "ntasd_kpn_seed2").seed == model_spec(cfg, "ntasd_seed2").seed != model_spec(cfg, "ntasd").seed


def test_a_model_with_its_own_seeds_trains_that_often_and_keeps_its_key() -> None:
    """Issue 48: a model (and its ablation variants' base) may set ``seeds`` in place of training.seeds; the key of
    its first seed does not see the setting."""
    cfg = default_config(3)
    before = model_key(cfg, "dasr")
    entry = next(m for m in cfg["training"]["models"] if m["id"] == "dasr")
    entry["seeds"] = 1
    cfg = validate_config(cfg)
    ids = {spec.id for spec in trained_model_specs(cfg)}
    assert "dasr_seed1" not in ids and "ntasd_seed1" in ids and "ntasd_seed2" in ids
    assert model_key(cfg, "dasr") == before


def test_an_ablation_variant_with_its_own_seeds_trains_that_often_and_keeps_its_key() -> None:
    """A variant's ``seeds`` replaces its ablation's (Isik's KPCN at ours-single's parameter count, which C3.1
    compares at, in a sweep trained once); the other variants keep the ablation's, and no key moves."""
    cfg = default_config(3)
    before = {spec.id: model_key(cfg, spec.id) for spec in model_specs(cfg)}
    sweep = next(a for a in cfg["training"]["ablations"] if a["id"] == "rae_capacity")
    sweep["variants"] = [{**sweep["variants"][0], "seeds": 2}, {"id": "levels4", "net": {"levels": 4}}]
    variant = f"rae_capacity_{sweep['variants'][0]['id']}"
    cfg = validate_config(cfg)
    assert training_problems(cfg, build_tasks=False) == []
    ids = [spec.id for spec in trained_model_specs(cfg)]
    assert f"{variant}_seed1" in ids and f"{variant}_seed2" not in ids
    assert not any(i.startswith("rae_capacity_levels4_seed") for i in ids) and "rae_capacity_levels4" in ids
    assert all(model_key(cfg, m) == key for m, key in before.items() if m in ids)
    assert model_spec(cfg, f"{variant}_seed1").seed == model_spec(cfg, "rae_seed1").seed


def test_seed_count_does_not_re_key_the_first_seed() -> None:
    one, three = default_config(1), default_config(3)
    for spec in model_specs(one):
        assert model_key(one, spec.id) == model_key(three, spec.id), spec.id
    assert model_key(three, "rae_seed1") not in {model_key(three, spec.id) for spec in model_specs(three)}


def test_a_variant_equal_to_its_base_reuses_the_bases_replica() -> None:
    cfg = default_config(3)
    assert same_training_as(cfg, "rae_inputs_all") == "rae"
    assert same_training_as(cfg, "rae_inputs_all_seed2") == "rae_seed2"
    assert same_training_as(cfg, "rae_inputs_color_seed1") is None
    assert same_training_as(cfg, "rae_seed1") is None


def test_a_model_id_that_collides_with_a_replica_is_refused() -> None:
    cfg = default_config(2)
    extra = copy.deepcopy(cfg["training"]["models"][0])
    extra["id"] = "rae_seed1"
    cfg["training"]["models"].append(extra)
    problems = "\n".join(training_problems(cfg, build_tasks=False))
    assert "model id 'rae_seed1' more than once" in problems and "seed replicas" in problems


def test_seed_rows_evaluate_every_replica_of_a_trained_row() -> None:
    cfg = default_config(3)
    rows = {spec.id: spec for spec in evaluate.method_specs(cfg)}
    for k in (1, 2):
        row = rows[f"rae_per_frame_seed{k}"]
        assert row.role == evaluate.SEED_ROLE and row.seed_of == "rae_per_frame" and row.replica == k
        assert row.params == {**rows["rae_per_frame"].params, "model": f"rae_seed{k}"}
        assert row.spp == rows["rae_per_frame"].spp and not row.robustness
        assert rows[f"rae_inputs_color_seed{k}"].params["model"] == f"rae_inputs_color_seed{k}"
    assert not any(spec.seed_of in ("eaw", "noisy", "oidn") for spec in rows.values())
    volume = {spec.id: spec for spec in evaluate.volume_method_specs(cfg)}
    assert volume["vol_rae_seed2"].params["model"] == "rae_volume_seed2"
    assert evaluate.seed_method_specs(default_config(1), list(rows.values())) == []
    assert "rae_capacity_width025" in rows and "rae_capacity_width025_seed1" not in rows
    # Seed rows are not timed and not in the robustness scenario.
    assert all(spec.role != evaluate.SEED_ROLE for spec in (run.spec for run in evaluate.robustness_runs(cfg)))


# ------------------------------------------------------------------------------------------- aggregation
def test_tables_show_the_seed_mean_and_spread() -> None:
    cfg = claims_config()
    table = Table(cfg, 4)
    psnr = {"rae": [30.0, 31.0, 32.0, 33.0], "rae_seed1": [31.0, 32.0, 33.0, 34.0], "rae_seed2": [29.0, 29.0, 29.0, 29.0]}
    table.values[("rae", 1)]["psnr"] = psnr["rae"]
    for row in ("rae_seed1", "rae_seed2"):
        table.added_values[(row, 1)] = {"psnr": psnr[row]}
    res = build(cfg, table)
    for column in SUMMARY_METRICS:        # columns the synthetic table leaves out (timing, memory): constant
        if column not in res.per_scene:
            res.per_scene[column] = 1.0
    expected = np.mean([psnr[row] for row in psnr], axis=0)
    np.testing.assert_allclose(res.scene_values("rae", 1, "psnr").to_numpy(), expected)
    np.testing.assert_allclose(res.scene_values("rae_seed2", 1, "psnr").to_numpy(), psnr["rae_seed2"])
    summary = summary_table(res).set_index(["method_id", "spp", "metric"])
    line = summary.loc[("rae", 1, "psnr")]
    seed_means = [np.mean(psnr[row]) for row in psnr]       # 31.5, 32.5, 29.0
    assert line["n_seeds"] == 3 and line["mean"] == pytest.approx(np.mean(expected))
    assert line["seed_sd"] == pytest.approx(np.std(seed_means, ddof=1))
    assert summary.loc[("eaw", 1, "psnr")]["n_seeds"] == 1 and np.isnan(summary.loc[("eaw", 1, "psnr")]["seed_sd"])
    # The row labels: seed count and spread on a trained row with seeds; "(1 seed)" on a trained row that trains
    # once beside it (a model's own seeds: 1); nothing on a hand-written method.
    from denoisers.report.tables import _seed_label

    flat = summary_table(res)
    assert _seed_label(flat, "rae", 1, trained=True) == f"rae (3 seeds, PSNR sd {np.std(seed_means, ddof=1):.2f} dB)"
    assert _seed_label(flat, "eaw", 1, trained=False) == "eaw"
    assert _seed_label(flat, "eaw", 1, trained=True) == "eaw (1 seed)"


# ------------------------------------------------------------------------------------------ verdicts
def c11_verdict(training: dict, d: list[float], rows: tuple[str, ...] = (), rows_d: list[float] | None = None):
    """C1.1 on a synthetic table where the RAE differs from EAW by ``d`` (claim units per scene) and each of
    ``rows`` (added rows: a seed replica, half-budget twins) by ``rows_d`` instead; ``training`` overrides the
    config's training keys."""
    cfg = claims_config()
    cfg["training"].update(training)
    cfg = validate_config(cfg)
    table = Table(cfg, len(d))
    for a, a_spp, b, b_spp, metric, claimed in PARTS["C1.1"]:
        table.shift((a, a_spp), (b, b_spp), metric, claimed, d)
        if rows_d is not None:
            sign = 1.0 if claimed == "higher" else -1.0
            values = [v + sign * SCALE[metric] * x for v, x in zip(table.values[(b, b_spp)][metric], rows_d)]
            for row in rows:
                table.added_values.setdefault((row, a_spp), {})[metric] = values
    return evaluate_claim(build(cfg, table), CLAIMS["C1.1"])


def test_seeds_that_agree_decide_and_one_that_does_not_makes_it_inconclusive() -> None:
    def verdict(d, seed2=None, seeds=3):
        return c11_verdict({"seeds": seeds}, d, ("rae_seed2",), seed2)

    agreeing = verdict(CLEAR, seed2=[0.5, 0.6, 0.4, 0.5])
    assert agreeing.verdict == REPRODUCED and all(part.seed_robust for part in agreeing.parts)
    # Seed 2 alone is worse than EAW by 0.5 units: the seed mean (2 d - 0.5) / 3 still lies wholly on the
    # claimed side, but seed 2 alone does not.
    sensitive = verdict(CLEAR, seed2=[-0.5] * 4)
    assert [part.outcome for part in sensitive.parts] == [REPRODUCED, REPRODUCED]
    np.testing.assert_allclose(sensitive.parts[0].diffs, -SCALE["rmse"] * (2 * np.array(CLEAR) - 0.5) / 3)
    assert sensitive.parts[0].seed_means[2] == pytest.approx(0.5 * SCALE["rmse"])
    assert sensitive.verdict == INCONCLUSIVE and not any(part.seed_robust for part in sensitive.parts)
    assert "seed-sensitive (seed(s) 2 alone not on the reproduced side" in sensitive.seed_note()
    # The other side: contradicted by the seed mean, but seed 2 alone as claimed: not contradicted.
    against = verdict(AGAINST, seed2=[0.5] * 4)
    assert [part.outcome for part in against.parts] == [CONTRADICTED, CONTRADICTED]
    assert against.verdict == INCONCLUSIVE and "contradicted side" in against.seed_note()
    assert verdict(AGAINST).verdict == CONTRADICTED
    # Fewer than three seeds never decide a learned part.
    two = verdict(CLEAR, seeds=2)
    assert two.verdict == INCONCLUSIVE and "2 training seed(s), fewer than the 3" in two.seed_note()
    assert verdict(CLEAR, seeds=1).verdict == INCONCLUSIVE


def test_a_part_without_a_learned_row_needs_no_seeds() -> None:
    cfg = claims_config()
    cfg["training"]["seeds"] = 1
    cfg = validate_config(cfg)
    table = Table(cfg, 4)
    for a, a_spp, b, b_spp, metric, claimed in PARTS["C4.1s"]:   # wrls against svgf: no trained model
        table.shift((a, a_spp), (b, b_spp), metric, claimed, CLEAR)
    decision = evaluate_claim(build(cfg, table), CLAIMS["C4.1s"])
    assert decision.verdict == REPRODUCED and all(part.seeds == 0 for part in decision.parts)


# ------------------------------------------------------------------------------------------- half budget
def test_half_budget_twins_stop_the_full_run_at_its_middle() -> None:
    cfg = default_config(3)
    assert half_budget_specs(cfg) == []
    cfg["training"]["half_budget"] = True
    twins = {spec.id: spec for spec in half_budget_specs(cfg)}
    assert set(twins) == {f"{spec.id}_half" for spec in model_specs(cfg) + seed_replicas(cfg)}
    full, half = model_spec(cfg, "rae"), twins["rae_half"]
    assert half.budget["max_steps"] == full.budget["max_steps"] // 2 == 2000
    assert half.optimizer == full.optimizer and half.seed == full.seed and half.net == full.net
    assert half_of(cfg, "rae_seed2_half") == "rae_seed2" and half_of(cfg, "rae") is None
    assert same_training_as(cfg, "rae_inputs_all_half") == "rae_half"
    # The twins add keys of their own and change no other model's.
    plain = default_config(3)
    for spec in model_specs(plain) + seed_replicas(plain):
        assert model_key(plain, spec.id) == model_key(cfg, spec.id), spec.id
    assert model_key(cfg, "rae_half") != model_key(cfg, "rae")
    rows = {spec.id: spec for spec in evaluate.method_specs(cfg)}
    assert rows["rae_half"].role == evaluate.BUDGET_ROLE and rows["rae_half"].budget_of == "rae"
    assert rows["rae_half"].params["model"] == "rae_half" and rows["rae_half"].seed_of is None
    assert rows["rae_seed1_half"].seed_of == "rae_half" and rows["rae_seed1_half"].params["model"] == "rae_seed1_half"
    assert rows["rae_seed1_half"].budget_of == "rae_seed1" and not rows["rae_seed1_half"].robustness


def test_a_decision_that_changes_at_half_the_budget_is_inconclusive() -> None:
    def decide(half_d: list[float] | None, half_budget: bool = True):
        # every seed's half-budget model differs from EAW by half_d instead
        return c11_verdict({"half_budget": half_budget}, CLEAR, ("rae_half", "rae_seed1_half", "rae_seed2_half"),
                           half_d)

    stable = decide(None)
    assert stable.verdict == REPRODUCED and all(part.budget_stable for part in stable.parts)
    assert all(part.half.outcome == REPRODUCED for part in stable.parts)
    flipped = decide(AGAINST)      # reproduced at the full budget, contradicted at half of it
    assert [part.outcome for part in flipped.parts] == [REPRODUCED, REPRODUCED]
    assert [part.half.outcome for part in flipped.parts] == [CONTRADICTED, CONTRADICTED]
    assert flipped.verdict == INCONCLUSIVE and not any(part.budget_stable for part in flipped.parts)
    assert "budget-sensitive (at half the budget contradicted" in flipped.seed_note()
    unchecked = decide(None, half_budget=False)
    assert unchecked.verdict == INCONCLUSIVE and "not compared at half the training budget" in unchecked.seed_note()
    table = claims_table(build(claims_config(), Table(claims_config(), 4)), [CLAIMS["C1.1"]])
    assert table.loc[0, "budget"] == "rae 4000 steps"


def test_the_half_budget_job_and_the_full_job_share_one_run(tmp_path: Path, synthetic_renders) -> None:
    cfg = tiny_training_config()
    cfg["training"]["models"][0]["budget"] = {"max_steps": 4}
    cfg["training"]["half_budget"] = True
    cfg = validate_config(cfg)
    models = tmp_path / "a" / "models"
    half = train_model(cfg, "rae_half", tmp_path / "renders", models / "rae_half", threads=1, progress=False)
    assert half["steps"] == 2 and half["half_budget_of"] == "rae" and half["model_id"] == "rae_half"
    full = train_model(cfg, "rae", tmp_path / "renders", models / "rae", threads=1, progress=False)
    assert full["resumed_from"] == 2 and full["steps"] == 4
    # Independently: the full model trained without a twin, and the same run stopped at step 2.
    plain = copy.deepcopy(cfg)
    plain["training"]["half_budget"] = False
    train_model(plain, "rae", tmp_path / "renders", tmp_path / "b" / "models" / "rae", threads=1, progress=False)
    train_model(plain, "rae", tmp_path / "renders", tmp_path / "c" / "models" / "rae", threads=1, progress=False,
                stop_at_step=2)

    def weights(path: Path) -> dict:
        return load_checkpoint(path / "best.pt")["model_state"]

    for a, b in ((models / "rae", tmp_path / "b" / "models" / "rae"),
                 (models / "rae_half", tmp_path / "c" / "models" / "rae")):
        wa, wb = weights(a), weights(b)
        assert all(torch.equal(wa[k], wb[k]) for k in wa), (a, b)
    # A twin asked for after its full model has finished trains afresh (the shared run is past its step).
    again = train_model(cfg, "rae_half", tmp_path / "renders", tmp_path / "a" / "models" / "rae_half2",
                        threads=1, progress=False)
    assert again["steps"] == 2 and again["resumed_from"] is None
    wa, wb = weights(tmp_path / "a" / "models" / "rae_half2"), weights(models / "rae_half")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
