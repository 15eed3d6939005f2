"""The committed store against HEAD: every stored model and checkpoint is found at the key a committed config
gives it now. Code that enters a model's key (denoisers/store/code.py: the training loop and data stream, the
method's builder and network, transitively) re-keys the models trained with it; such a change made by accident
would leave hours of stored training unreachable, and nothing else fails until a run retrains them."""
from __future__ import annotations

from pathlib import Path

from denoisers.store import ModelStore, checkpoint_key, model_key
from denoisers.store.keys import short
from denoisers.training.models import trained_model_specs
from scenegen.config import load_config

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The configs whose models the committed store holds.
CONFIGS = ("config/config.yaml", "config/isik2021.yaml", "config/cluster.yaml", "config/smoke.yaml")


def test_every_stored_model_and_checkpoint_is_found_at_heads_key() -> None:
    models: set[tuple[str, str]] = set()
    checkpoints: set[tuple[str, str]] = set()
    roots = set()
    for name in CONFIGS:
        cfg = load_config(REPO_ROOT / name)
        roots.add(ModelStore.of(cfg).root)
        for spec in trained_model_specs(cfg):
            models.add((spec.id, short(model_key(cfg, spec.id))))
            checkpoints.add((spec.id, short(checkpoint_key(cfg, spec.id))))
    assert len(roots) == 1, f"the configs name several stores: {roots}"
    root = next(iter(roots))
    root = root if root.is_absolute() else REPO_ROOT / root
    for kind, known in (("models", models), ("checkpoints", checkpoints)):
        stored = {(path.parent.name, path.name) for path in (root / kind).glob("*/*") if path.is_dir()}
        assert stored, f"{root / kind}: nothing stored"
        lost = sorted(stored - known)
        assert not lost, (f"{len(lost)} of {len(stored)} stored {kind} are found by none of {', '.join(CONFIGS)} at "
                          f"HEAD's key (first: {lost[:5]}): a change re-keyed them (code hashed into the key, "
                          "denoisers/store/code.py, or a setting); revert it, or retrain and republish them")
