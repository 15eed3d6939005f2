"""Tests of the model store (denoisers/store/): keys, install instead of train, forced training, publishing and its
refusals, corrupt entries, resuming a published checkpoint in a fresh process and folder, verify, the size budget,
and the DAG leaving a stored model's training renders out."""
from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from denoisers.store import ModelStore, StoreCollisionError, StoreError, checkpoint_key, model_key
from denoisers.store.code import code_digest, code_files
from denoisers.store.verify import verify_model
from denoisers.training import data as training_data
from denoisers.training.job import train_model, work_dir_for
from denoisers.training.loop import load_checkpoint
from denoisers.training.models import model_spec
from tests.test_training_job import synthetic_renders, tiny_training_config  # noqa: F401 (fixture)

REPO_ROOT = Path(__file__).resolve().parents[1]


def store_config(tmp_path: Path, steps: int = 4) -> dict:
    cfg = tiny_training_config()
    cfg["training"]["models"][0]["budget"] = {"max_steps": steps}
    cfg["store"] = {"path": str(tmp_path / "store"), "use": True, "force_training": False}
    (tmp_path / "store").mkdir(exist_ok=True)
    (tmp_path / "store" / "budget.json").write_text('{"max_megabytes": 5}')
    return cfg


def train(cfg: dict, root: Path, **kwargs) -> dict:
    return train_model(cfg, "rae", root / "renders", root / "models" / "rae", threads=1, progress=False, **kwargs)


def weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["model_state"]


# ---------------------------------------------------------------------------------------------------- keys
KEY_SCRIPT = ("import json, sys; from scenegen.config import load_config; from denoisers.store import model_key; "
              "cfg = load_config('config/config.yaml'); print(json.dumps([model_key(cfg, m) for m in sys.argv[1:]]))")


def test_the_same_settings_give_the_same_key_in_other_processes() -> None:
    from scenegen.config import load_config

    models = ["rae", "ntasd", "rae_inputs_color"]
    runs = [json.loads(subprocess.run([sys.executable, "-c", KEY_SCRIPT, *models], cwd=REPO_ROOT, check=True,
                                      capture_output=True, text=True, env={**os.environ, "PYTHONHASHSEED": seed})
                       .stdout) for seed in ("1", "2")]
    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    assert runs[0] == runs[1] == [model_key(cfg, m) for m in models]
    assert len(set(runs[0])) == 3


@pytest.mark.parametrize("change", [
    lambda c: c["training"]["models"][0].update(seed=99),
    lambda c: c["training"]["models"][0]["optimizer"].update(lr=0.002),
    lambda c: c["training"]["models"][0]["net"].update(width=0.25),
    lambda c: c["training"]["models"][0]["budget"].update(max_steps=5),
    lambda c: c["training"]["models"][0]["data"].update(crop=16),
    lambda c: c["training"].update(threads=2),
    lambda c: c["render"].update(spp=c["render"]["spp"] + 1),            # the training renders
    lambda c: c.update(seed=c["seed"] + 1),                                 # every scene
    lambda c: c["training"].update(validation_sequences=3),
], ids=["seed", "lr", "net", "budget", "crop", "threads", "render", "global_seed", "validation"])
def test_every_change_that_alters_the_weights_changes_the_key(change) -> None:
    cfg = tiny_training_config()
    changed = copy.deepcopy(cfg)
    change(changed)
    assert model_key(changed, "rae") != model_key(cfg, "rae")


def test_the_checkpoint_key_ignores_only_the_budget() -> None:
    cfg = tiny_training_config()
    longer = copy.deepcopy(cfg)
    longer["training"]["models"][0]["budget"] = {"max_steps": 50}
    assert checkpoint_key(longer, "rae") == checkpoint_key(cfg, "rae") != model_key(cfg, "rae")
    other = copy.deepcopy(cfg)
    other["training"]["models"][0]["seed"] = 5
    assert checkpoint_key(other, "rae") != checkpoint_key(cfg, "rae")


def _copy_code(tmp_path: Path) -> Path:
    root = tmp_path / "code"
    for package in ("denoisers", "scenegen"):
        shutil.copytree(REPO_ROOT / package, root / package, ignore=shutil.ignore_patterns("_build", "__pycache__"))
    return root


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def test_comments_and_docs_leave_the_code_digest_and_code_changes_change_it(tmp_path: Path) -> None:
    root = _copy_code(tmp_path)
    base = {m: code_digest(m, root) for m in ("rae", "ntasd", "afn")}
    assert base == {m: code_digest(m) for m in base}                   # a copy of the code: the same digests
    net = root / "denoisers" / "nets" / "rae.py"
    _edit(net, "import torch\n", "import torch  # a new comment\n\n\n")
    _edit(net, '"""', '"""A reworded docstring. ', )
    loop = root / "denoisers" / "training" / "loop.py"
    _edit(loop, "    def _train_step(self)", "    # why this step is as it is\n    def _train_step(self)")
    cpp = root / "denoisers" / "native" / "kernels.cpp"
    cpp.write_text("// a comment\n" + cpp.read_text())
    _cached_clear()
    assert {m: code_digest(m, root) for m in base} == base
    # The network: the RAE's key changes, NTASD's and AFN's do not (their code does not import it).
    text = net.read_text()
    net.write_text(text.replace("negative_slope: float = 0.1", "negative_slope: float = 0.2", 1) if "negative_slope: float = 0.1" in text
                   else text + "\nEXTRA_CONSTANT = 1\n")
    _cached_clear()
    assert code_digest("rae", root) != base["rae"]
    assert code_digest("ntasd", root) == base["ntasd"] and code_digest("afn", root) == base["afn"]
    # The training step changes every method's digest; another method's builder changes only its own.
    _edit(root / "denoisers" / "training" / "tasks.py", 'raise KeyError(f"kpcn: unknown loss keys',
          'raise ValueError(f"kpcn: unknown loss keys')
    _cached_clear()
    assert code_digest("ntasd", root) == base["ntasd"] and code_digest("kpcn", root) != code_digest("kpcn")
    _edit(loop, "self.step += 1", "self.step = self.step + 1")
    _cached_clear()
    assert code_digest("ntasd", root) != base["ntasd"]
    # The native kernels enter the methods that use them.
    assert "denoisers.native/kernels.cpp" in code_files("ntasd") and "denoisers.native/kernels.cpp" not in \
        code_files("rae")


def test_code_digests_are_cached_across_processes_under_the_sources_fingerprint(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The on-disk cache (a Snakefile parse keys every model) answers only for byte-identical sources."""
    import hashlib

    from denoisers.store import code

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    root = _copy_code(tmp_path)
    _cached_clear()
    first = code_digest("rae", root)
    fingerprint = code.source_fingerprint(root)
    assert json.loads(code.digest_cache_file().read_text()) == {fingerprint: {"rae": first}}
    # What a later process reads: a planted entry for these very sources is returned as is.
    code.digest_cache_file().write_text(json.dumps({fingerprint: {"rae": "f" * 64}}))
    _cached_clear()
    assert code_digest("rae", root) == "f" * 64
    # Any byte of a source changes the fingerprint: the digest is computed again from the sources.
    _edit(root / "denoisers" / "nets" / "rae.py", "import torch\n", "import torch  # edited\n")
    _cached_clear()
    assert code.source_fingerprint(root) != fingerprint
    expected = hashlib.sha256()
    for name, text in code_files("rae", root).items():
        expected.update(name.encode() + b"\0" + hashlib.sha256(text.encode()).hexdigest().encode() + b"\n")
    assert code_digest("rae", root) == expected.hexdigest() == first
    _cached_clear()


def _cached_clear() -> None:
    from denoisers.store import code

    code._cached_digest.cache_clear()


# ------------------------------------------------------------------------------------ install, publish
def test_a_stored_model_is_installed_instead_of_trained(tmp_path: Path, synthetic_renders,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = store_config(tmp_path)
    trained = train(cfg, tmp_path / "first")
    assert trained["store_key"] == model_key(cfg, "rae") and "cpu_isa" in trained["provenance"]
    store = ModelStore.of(cfg)
    entry, what = store.publish_model(cfg, tmp_path / "first" / "models" / "rae")
    assert what == "published" and entry.path.parent.name == "rae"
    assert {p.name for p in entry.path.iterdir()} == {"best.pt", "settings.json", "curves.csv", "validation.csv",
                                                      "summary.json"}
    assert "optimizer_state" not in torch.load(entry.path / "best.pt", weights_only=True)
    assert store.publish_model(cfg, tmp_path / "first" / "models" / "rae")[1] == "already published"

    def no_renders(*args, **kwargs):
        raise AssertionError("a stored model must not read renders")

    monkeypatch.setattr(training_data, "load_clip", no_renders)
    training_data.clear_clip_cache()
    installed = train(cfg, tmp_path / "fresh")
    out = tmp_path / "fresh" / "models" / "rae"
    assert installed["installed_from_store"]["key"] == model_key(cfg, "rae")
    assert (out / "best.pt").read_bytes() == (tmp_path / "first" / "models" / "rae" / "best.pt").read_bytes()
    assert (out / "curves.png").exists() and installed["settings_digest"] == trained["settings_digest"]
    # Forced training trains (and reads the renders).
    forced = copy.deepcopy(cfg)
    forced["store"]["force_training"] = True
    with pytest.raises(AssertionError, match="must not read renders"):
        train(forced, tmp_path / "forced")
    # An installed model is not published again as if trained.
    with pytest.raises(StoreError, match="installed from the store"):
        store.publish_model(cfg, out)


def test_forced_training_retrains_the_same_weights(tmp_path: Path, synthetic_renders) -> None:
    cfg = store_config(tmp_path)
    train(cfg, tmp_path / "first")
    ModelStore.of(cfg).publish_model(cfg, tmp_path / "first" / "models" / "rae")
    forced = copy.deepcopy(cfg)
    forced["store"]["force_training"] = True
    summary = train(forced, tmp_path / "forced")
    assert "installed_from_store" not in summary and summary["steps"] == 4
    a, b = weights(tmp_path / "first" / "models" / "rae" / "best.pt"), weights(tmp_path / "forced" / "models" / "rae" / "best.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_publishing_refuses_other_weights_under_a_stored_key_and_stale_models(tmp_path: Path,
                                                                             synthetic_renders) -> None:
    cfg = store_config(tmp_path)
    train(cfg, tmp_path / "a")
    store = ModelStore.of(cfg)
    store.publish_model(cfg, tmp_path / "a" / "models" / "rae")
    other = tmp_path / "b" / "models" / "rae"
    shutil.copytree(tmp_path / "a" / "models" / "rae", other)
    model = torch.load(other / "best.pt", weights_only=True)
    first = next(iter(model["model_state"]))
    model["model_state"][first] = model["model_state"][first] + 1e-3
    torch.save(model, other / "best.pt")
    with pytest.raises(StoreCollisionError, match="already holds different weights"):
        store.publish_model(cfg, other)
    # A model of other settings (or of older code: its recorded key differs) is refused.
    changed = copy.deepcopy(cfg)
    changed["training"]["models"][0]["optimizer"]["lr"] = 0.003
    with pytest.raises(StoreError, match="other settings"):
        store.publish_model(changed, tmp_path / "a" / "models" / "rae")
    summary = json.loads((other / "summary.json").read_text())
    summary["store_key"] = "0" * 64
    (other / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(StoreError, match="code at hand"):
        store.publish_model(cfg, other)


@pytest.mark.parametrize("damage", ["truncate", "flip", "delete"])
def test_a_corrupt_stored_weights_file_is_an_error_naming_it(tmp_path: Path, synthetic_renders, damage: str) -> None:
    cfg = store_config(tmp_path)
    train(cfg, tmp_path / "a")
    entry, _ = ModelStore.of(cfg).publish_model(cfg, tmp_path / "a" / "models" / "rae")
    weights_file = entry.path / "best.pt"
    data = weights_file.read_bytes()
    if damage == "truncate":
        weights_file.write_bytes(data[: len(data) // 2])
    elif damage == "flip":
        weights_file.write_bytes(data[:-100] + bytes([data[-100] ^ 1]) + data[-99:])
    else:
        weights_file.unlink()
    with pytest.raises(StoreError, match=str(weights_file).replace(".", r"\.")):
        train(cfg, tmp_path / "b")
    assert not (tmp_path / "b" / "models" / "rae").exists()
    from denoisers.store.cli import run
    import argparse

    args = argparse.Namespace(action="check", model_id=None, results=None)
    assert run(args, cfg) == 1


# --------------------------------------------------------------------------------------------- resume
RESUME_SCRIPT = """
import json, sys
from pathlib import Path
sys.path.insert(0, {repo!r})
from denoisers.training import data as training_data
from denoisers.training.job import train_model
from tests.test_training import synthetic_clip

def fake_load_clip(render_dir, **kwargs):
    name = Path(render_dir).name
    return synthetic_clip(frames=6, layers=4, seed=sum(map(ord, name)), scene=name)

training_data.load_clip = fake_load_clip
cfg = json.loads(Path(sys.argv[1]).read_text())
summary = train_model(cfg, "rae", Path("renders"), Path("models") / "rae", threads=1, progress=False)
print(json.dumps({{"resumed_from": summary["resumed_from"], "steps": summary["steps"]}}))
"""


def test_a_published_checkpoint_continues_in_a_fresh_process_and_folder(tmp_path: Path, synthetic_renders) -> None:
    """Train 4 steps, publish the checkpoint at 2, continue in another process in an empty folder that shares only
    the store: the weights equal those of an uninterrupted 4-step run."""
    cfg = store_config(tmp_path, steps=4)
    local = copy.deepcopy(cfg)
    local["store"]["use"] = False
    train(local, tmp_path / "straight")
    train(cfg, tmp_path / "first", stop_at_step=2)
    with pytest.raises(StoreError, match="stopped early"):
        ModelStore.of(cfg).publish_model(cfg, tmp_path / "first" / "models" / "rae")
    work = work_dir_for(tmp_path / "first" / "models", cfg, model_spec(cfg, "rae"))
    entry = ModelStore.of(cfg).publish_checkpoint(cfg, work)
    assert entry.summary()["step"] == 2 and (entry.path / "checkpoint.pt").exists()
    assert "optimizer_state" in torch.load(entry.path / "checkpoint.pt", weights_only=True)
    clone = tmp_path / "clone"
    clone.mkdir()
    (clone / "cfg.json").write_text(json.dumps(cfg))
    done = subprocess.run([sys.executable, "-c", RESUME_SCRIPT.format(repo=str(REPO_ROOT)), "cfg.json"], cwd=clone,
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1]) == {"resumed_from": 2, "steps": 4}
    straight = tmp_path / "straight" / "models"
    resumed = clone / "models"
    a, b = weights(straight / "rae" / "best.pt"), weights(resumed / "rae" / "best.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    spec = model_spec(cfg, "rae")
    a, b = (load_checkpoint(work_dir_for(root, cfg, spec) / "checkpoint.pt") for root in (straight, resumed))
    assert all(torch.equal(a["model_state"][k], b["model_state"][k]) for k in a["model_state"])
    timing = {"elapsed_s", "steps_per_s"}
    a_rows, b_rows = ([{k: v for k, v in row.items() if k not in timing} for row in c["history"]] for c in (a, b))
    assert json.dumps(a_rows, sort_keys=True) == json.dumps(b_rows, sort_keys=True)      # NaN equals NaN here
    # Publishing the finished model removes the checkpoint it supersedes, and a checkpoint of it is refused: nothing
    # would continue it.
    ModelStore.of(cfg).publish_model(cfg, resumed / "rae")
    assert ModelStore.of(cfg).checkpoint_entry(cfg, "rae") is None
    assert not entry.path.parent.exists()       # no empty folder left under the model's id
    with pytest.raises(StoreError, match="holds it finished"):
        ModelStore.of(cfg).publish_checkpoint(cfg, work_dir_for(resumed, cfg, spec))
    assert ModelStore.of(cfg).checkpoint_entry(cfg, "rae") is None


def test_a_checkpoint_of_another_step_arithmetic_is_not_continued(tmp_path: Path, synthetic_renders) -> None:
    cfg = store_config(tmp_path, steps=4)
    train(cfg, tmp_path / "first", stop_at_step=2)
    work = work_dir_for(tmp_path / "first" / "models", cfg, model_spec(cfg, "rae"))
    entry = ModelStore.of(cfg).publish_checkpoint(cfg, work)
    meta = json.loads((entry.path / "meta.json").read_text())
    meta["compute"] = {"precision": "bf16-elsewhere", "channels_last": True}
    (entry.path / "meta.json").write_text(json.dumps(meta))
    assert train(cfg, tmp_path / "fresh", stop_at_step=1)["resumed_from"] is None
    # The fresh run's checkpoint (step 1) cannot replace the other arithmetic's (step 2) unless told to.
    fresh = work_dir_for(tmp_path / "fresh" / "models", cfg, model_spec(cfg, "rae"))
    with pytest.raises(StoreError, match="bf16-elsewhere channels-last.*neither can continue the other"):
        ModelStore.of(cfg).publish_checkpoint(cfg, fresh)
    assert json.loads((entry.path / "meta.json").read_text())["step"] == 2
    replaced = ModelStore.of(cfg).publish_checkpoint(cfg, fresh, replace_other_arithmetic=True)
    stored = json.loads((replaced.path / "meta.json").read_text())
    assert replaced.path == entry.path and stored["step"] == 1 and stored["compute"] != meta["compute"]


# --------------------------------------------------------------------------------------------- verify
def test_verify_retrains_and_matches_the_stored_run(tmp_path: Path, synthetic_renders) -> None:
    cfg = store_config(tmp_path, steps=4)
    train(cfg, tmp_path / "a")
    entry, _ = ModelStore.of(cfg).publish_model(cfg, tmp_path / "a" / "models" / "rae")
    whole = verify_model(cfg, "rae", tmp_path / "renders", tmp_path / "verify" / "rae.json")
    assert whole["passed"] and whole["mode"] == "bit-identical" and whole["weights"]["passed"]
    assert whole["curves"]["values_compared"] >= 4
    first = verify_model(cfg, "rae", tmp_path / "renders", tmp_path / "verify" / "rae2.json", steps=2)
    assert first["passed"] and first["steps"] == 2 and "weights" not in first
    # A stored curve that the retraining does not reproduce fails, and leaves no output that looks complete.
    curves = (entry.path / "curves.csv").read_text().splitlines()
    header = curves[0].split(",")
    column = header.index("train_loss")
    row = curves[1].split(",")
    row[column] = str(float(row[column]) * 1.5)
    curves[1] = ",".join(row)
    (entry.path / "curves.csv").write_text("\n".join(curves) + "\n")
    with pytest.raises(StoreError, match="differs from the stored one"):
        verify_model(cfg, "rae", tmp_path / "renders", tmp_path / "verify" / "bad.json", steps=2)
    assert not (tmp_path / "verify" / "bad.json").exists() and (tmp_path / "verify" / "bad.failed.json").exists()


# ------------------------------------------------------------------------------------- the real store
def test_the_store_stays_within_its_budget_and_every_entry_is_intact() -> None:
    store = ModelStore(REPO_ROOT / "store")
    budget = store.budget_bytes()
    # The ceiling of the budget itself: models, tuning and (since 2026-12-06) the evaluated scenes' references
    # (about 54 MB for the default config's 12), which every clone carries in its history.
    # 320 MB since late 2026-12-06 for the rest of the Isik trainings: about 12 models of 1-1.3 MB, KPCN at width 0.5
    # (about 10 MB per model and twin) and its part-way checkpoint across sessions (weights, Adam, EMA: about 40 MB).
    assert 0 < budget <= 330e6
    assert store.size_bytes() <= budget, f"store/ holds {store.size_bytes() / 1e6:.1f} MB, budget {budget / 1e6} MB"
    from denoisers.store.entries import _check_files

    for kind in ("models", "checkpoints", "tuning"):
        for entry in store.entries(kind):
            record = entry.summary()
            _check_files(entry.path, (record.get("store") or record)["files"])
            assert entry.path.name == entry.key[:16]
    from scenegen.reference_store import reference_problems

    assert reference_problems(store.root) == []


# ---------------------------------------------------------------------------------------------- the DAG
def _dry_run(tmp_path: Path, *extra: str) -> str:
    env = {**os.environ, "PATH": f"{REPO_ROOT / '.venv' / 'bin'}:{os.environ['PATH']}"}
    done = subprocess.run([str(REPO_ROOT / ".venv" / "bin" / "snakemake"), f"{tmp_path / 'out'}/models/rae", "-n",
                           "--quiet", "rules", "--cores", "1", "--configfile", "config/smoke.yaml",
                           "--config", f"output_dir={tmp_path / 'out'}", *extra], cwd=REPO_ROOT, capture_output=True,
                          text=True, env=env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    return done.stdout + done.stderr


@pytest.mark.slow
def test_the_dag_installs_a_stored_model_without_planning_its_training_renders(tmp_path: Path) -> None:
    from scenegen.config import load_config

    cfg = load_config(REPO_ROOT / "config" / "smoke.yaml")
    cfg["output_dir"] = str(tmp_path / "out")
    cfg["store"] = {**cfg["store"], "path": str(tmp_path / "store")}
    trained = _dry_run(tmp_path, f"store={{path: {tmp_path / 'store'}}}")
    assert "render_noisy" in trained and "train_denoiser" in trained
    # A stored entry under the smoke config's key (its content does not matter to the planning).
    entry = tmp_path / "store" / "models" / "rae" / model_key(cfg, "rae")[:16]
    entry.mkdir(parents=True)
    (entry / "summary.json").write_text(json.dumps({"store": {"key": model_key(cfg, "rae")}}))
    installed = _dry_run(tmp_path, f"store={{path: {tmp_path / 'store'}}}")
    assert "train_denoiser" in installed and "render_noisy" not in installed and "generate_scene" not in installed
    forced = _dry_run(tmp_path, f"store={{path: {tmp_path / 'store'}, force_training: true}}")
    assert "render_noisy" in forced and "train_denoiser" in forced


# ----------------------------------------------------------------------------------------------- tuning
def test_a_tuning_result_is_stored_installed_and_checked(tmp_path: Path) -> None:
    from denoisers.experiment import DIGEST_KEY, Lineage
    from denoisers.store.code import method_code_digest
    from denoisers.store.tuning import install_tuning, publish_tuning, tuning_entry, tuning_key
    from scenegen.config import load_config

    cfg = load_config(REPO_ROOT / "config" / "config.yaml")
    cfg["store"] = {**cfg["store"], "path": str(tmp_path / "store")}
    store = ModelStore.of(cfg)
    result = {"method": "eaw", "best_params": {"sigma_color": 4.0}, "results": [], DIGEST_KEY: Lineage(cfg).tuning("eaw")}
    source = tmp_path / "results" / "tuning" / "eaw.json"
    source.parent.mkdir(parents=True)
    source.write_text(json.dumps(result))
    assert tuning_entry(store, cfg, "eaw") is None
    folder, what = publish_tuning(store, cfg, "eaw", source)
    assert what == "published" and tuning_entry(store, cfg, "eaw") == folder
    assert publish_tuning(store, cfg, "eaw", source)[1] == "already published"
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**result, "best_params": {"sigma_color": 8.0}}))
    with pytest.raises(StoreCollisionError):
        publish_tuning(store, cfg, "eaw", other)
    assert install_tuning(folder, tmp_path / "out.json")["best_params"] == {"sigma_color": 4.0}
    # The key follows the tuning settings, the training renders and the method's code, not other methods'.
    changed = copy.deepcopy(cfg)
    changed["tuning"]["spp"] = [1]
    assert tuning_key(changed, "eaw") != tuning_key(cfg, "eaw")
    assert method_code_digest("rls") == method_code_digest("wrls") != method_code_digest("eaw")
    stale = copy.deepcopy(cfg)
    stale["tuning"]["max_frames"] = 2
    with pytest.raises(StoreError, match="other settings"):
        publish_tuning(store, stale, "eaw", source)
    (folder / "result.json").write_text(json.dumps({**result, "best_params": {"sigma_color": 16.0}}))
    with pytest.raises(StoreError, match="corrupt"):
        install_tuning(folder, tmp_path / "out.json")


def test_curves_from_another_instruction_set_are_compared_within_the_stated_tolerance(tmp_path: Path) -> None:
    from denoisers.store.verify import RELATIVE_TOLERANCE, compare_curves

    stored = tmp_path / "stored.csv"
    stored.write_text("step,train_loss,val_loss\n10,0.500000,\n20,0.400000,0.450000\n30,0.300000,\n")

    def retrained(factor: float) -> Path:
        path = tmp_path / f"retrained_{factor}.csv"
        path.write_text(f"step,train_loss,val_loss\n10,{0.5 * factor:.6f},\n20,{0.4 * factor:.6f},{0.45 * factor:.6f}\n"
                        f"30,{0.3 * factor:.6f},\n")
        return path

    assert compare_curves(stored, retrained(1.0), 30, exact=True)["passed"]
    assert not compare_curves(stored, retrained(1.0 + 1e-5), 30, exact=True)["passed"]
    close = compare_curves(stored, retrained(1 + RELATIVE_TOLERANCE / 2), 30, exact=False)
    assert close["passed"] and close["values_compared"] == 4
    assert not compare_curves(stored, retrained(1 + 2 * RELATIVE_TOLERANCE), 30, exact=False)["passed"]
    assert compare_curves(stored, retrained(1.0), 20, exact=True)["values_compared"] == 3      # rows up to step 20
