"""What the workflow asks of the store while it builds the DAG (workflow/rules/common.smk): which models are
installed instead of trained, which are verified. Config level; the key's code digest is cached per process."""
from __future__ import annotations

from denoisers.store.entries import Entry, ModelStore, store_settings


def stored_model(cfg: dict, model_id: str) -> Entry | None:
    """The store entry train_denoiser installs for ``model_id``, or None (store unused, training forced, not
    stored)."""
    settings = store_settings(cfg)
    if not settings["use"] or settings["force_training"]:
        return None
    return ModelStore.of(cfg).model_entry(cfg, model_id)


def verify_models(cfg: dict) -> list[str]:
    """The model ids of ``store.verify.models``; when it is empty, every model of ``cfg`` stored under its key
    (variants reusing another model's weights left out)."""
    models = list((store_settings(cfg).get("verify") or {}).get("models") or [])
    if models:
        return models
    from denoisers.training.models import same_training_as, trained_model_specs

    store = ModelStore.of(cfg)
    return [spec.id for spec in trained_model_specs(cfg)
            if not same_training_as(cfg, spec.id) and store.model_entry(cfg, spec.id) is not None]


def verify_problems(cfg: dict) -> list[str]:
    """Config problems of ``store.verify``: unknown model ids, models not stored under this config's key."""
    from denoisers.training.models import same_training_as, trained_model_specs

    # Only a listed model can be wrong: the default (every stored model) is right by construction, and finding the
    # stored models computes every model's key, seconds of code digests on every Snakefile parse.
    listed = list((store_settings(cfg).get("verify") or {}).get("models") or [])
    if not listed:
        return []
    known = {spec.id for spec in trained_model_specs(cfg)}
    problems = []
    for model_id in listed:
        if model_id not in known:
            problems.append(f"store.verify.models: unknown model {model_id!r}; configured: {', '.join(sorted(known))}")
        elif same_training_as(cfg, model_id):
            problems.append(f"store.verify.models: {model_id!r} reuses {same_training_as(cfg, model_id)!r}'s weights; "
                            "verify that model")
    return problems
