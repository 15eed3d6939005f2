"""``python -m denoisers store <action>``: list, publish, checkpoint, verify and check the model store.

  list        every stored model and checkpoint, and whether this config's key finds it
  progress    every training of this config: stored, part-way or not started, its time so far and an estimate of
              what is left (--markdown: a table for the manual)
  publish     copy finished models from <out>/models/ into the store (refuses stale models and key collisions)
  checkpoint  copy a training run's resumable state (<out>/models/.work/<id>-*/) into the store, part-way
  verify      retrain a stored model and compare it with the stored run (rule verify_stored_model)
  check       every entry's files against their recorded digests, and the store's size against its budget
  publish-references  copy the evaluated scenes' rendered references (<results>/renders/<scene>/reference) into
              the store (scenegen.reference_store), so that a run from the store does not render them
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger("denoisers.store")


def add_parser(sub: argparse._SubParsersAction) -> None:
    store = sub.add_parser("store", help="the model store: list, progress, publish, checkpoint, verify, "
                                         "check, publish-references",
                           description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    store.add_argument("action", choices=["list", "progress", "publish", "checkpoint", "verify", "check",
                                                 "publish-references"])
    store.add_argument("--config", type=Path, required=True, help="config YAML (its store.path is the store)")
    store.add_argument("--model-id", nargs="*", default=None,
                       help="models (default for publish / checkpoint: every configured model found in the results)")
    store.add_argument("--results", type=Path, default=None, help="the experiment folder (default: output_dir)")
    store.add_argument("--render-root", type=Path, default=None,
                       help="verify, publish-references: the renders folder (default <results>/renders)")
    store.add_argument("--scene", nargs="*", default=None,
                       help="publish-references: scenes (default: every evaluated scene of the config)")
    store.add_argument("--out", type=Path, default=None, help="verify: the comparison record (JSON)")
    store.add_argument("--markdown", action="store_true", help="progress: a Markdown table")
    store.add_argument("--replace-other-arithmetic", action="store_true",
                       help="checkpoint: replace a stored checkpoint of another step arithmetic (precision, layout), "
                            "which this run cannot continue, even one further along (a run restarted on purpose)")
    store.add_argument("--steps", type=int, default=None,
                       help="verify: retrain only the first steps (default: store.verify.steps, else the whole budget)")


def run(args: argparse.Namespace, cfg: dict) -> int:
    from denoisers.store.entries import ModelStore, StoreError
    from denoisers.store.keys import short
    from denoisers.training.job import work_dir_for
    from denoisers.training.models import same_training_as, trained_model_specs
    from scenegen.config import output_root
    from scenegen.reference_store import evaluated_scenes, reference_key, reference_problems, stored_references

    store = ModelStore.of(cfg)
    results = args.results or output_root(cfg)
    configured = [spec.id for spec in trained_model_specs(cfg)]
    models = args.model_id or configured
    if args.action == "list":
        for entry in store.entries("tuning"):
            print(f"tuning     {entry.path.parent.name:24s} {short(entry.key)}")
        for kind in ("models", "checkpoints"):
            for entry in store.entries(kind):
                record = entry.summary()
                current = (store.model_entry if kind == "models" else store.checkpoint_entry)(cfg, entry.model_id) \
                    if entry.model_id in configured else None
                state = "this config" if current is not None and current.path == entry.path else "other key"
                compute = record.get("compute") or {}
                cpu = (record.get("provenance") or {}).get("cpu_model", "?")
                print(f"{kind[:-1]:10s} {entry.model_id:24s} {short(entry.key)}  step {record.get('steps', record.get('step'))}"
                      f"  {record.get('elapsed_seconds', 0) / 60:6.1f} min  {compute.get('precision', '?')}  {cpu}"
                      f"  {state}")
        current_keys = {scene: reference_key(cfg, scene) for scene in evaluated_scenes(cfg)}
        for scene, folder, meta in stored_references(store.root):
            state = "this config" if current_keys.get(scene) == meta.get("key") else "other key"
            print(f"reference  {scene:24s} {folder.name}  {meta.get('spp')} spp  {len(meta.get('files', {})) // 2} "
                  f"frames  {state}")
        print(f"store {store.root}: {store.size_bytes() / 1e6:.1f} MB of {store.budget_bytes() / 1e6:.0f} MB")
        return 0
    if args.action == "progress":
        from denoisers.store.progress import progress_table, training_progress

        print(progress_table(cfg, training_progress(cfg, store), markdown=args.markdown), end="")
        return 0
    if args.action == "publish-references":
        from denoisers.device import resolve_config_device
        from scenegen.reference_store import publish_reference

        resolve_config_device(cfg)   # the variant the workflow's render jobs resolve, hence their digests
        for scene in args.scene or evaluated_scenes(cfg):
            folder, what = publish_reference(cfg, scene, Path(args.render_root or Path(results) / "renders"))
            print(f"{what}: reference {scene} -> {folder}")
        print(f"store {store.root}: {store.size_bytes() / 1e6:.1f} MB of {store.budget_bytes() / 1e6:.0f} MB")
        return 0
    if args.action == "publish":
        for model_id in models:
            model_dir = Path(results) / "models" / model_id
            if same_training_as(cfg, model_id) or not (model_dir / "summary.json").exists():
                if args.model_id:
                    raise StoreError(f"{model_dir}: no finished model to publish" if not same_training_as(cfg, model_id)
                                     else f"model {model_id!r} reuses {same_training_as(cfg, model_id)!r}'s weights")
                continue
            if args.model_id is None and "installed_from_store" in (model_dir / "summary.json").read_text():
                continue
            entry, what = store.publish_model(cfg, model_dir)
            print(f"{what}: {model_id} -> {entry.path}")
        if args.model_id is None:
            from denoisers.store.tuning import publish_tuning

            for entry_cfg in cfg.get("tuning", {}).get("methods", []):
                result_file = Path(results) / "tuning" / f"{entry_cfg['method']}.json"
                if result_file.exists():
                    folder, what = publish_tuning(store, cfg, entry_cfg["method"], result_file)
                    print(f"{what}: tuning {entry_cfg['method']} -> {folder}")
        print(f"store {store.root}: {store.size_bytes() / 1e6:.1f} MB of {store.budget_bytes() / 1e6:.0f} MB")
        return 0
    if args.action == "checkpoint":
        from denoisers.training.models import model_spec

        for model_id in models:
            work_dir = work_dir_for(Path(results) / "models", cfg, model_spec(cfg, model_id))
            if not (work_dir / "checkpoint.pt").exists():
                if args.model_id:
                    raise StoreError(f"{work_dir}: no training checkpoint of {model_id!r}")
                continue
            if (Path(results) / "models" / model_id / "summary.json").exists() and args.model_id is None:
                continue  # finished: publish the model instead
            entry = store.publish_checkpoint(cfg, work_dir, replace_other_arithmetic=args.replace_other_arithmetic)
            print(f"checkpoint: {model_id} step {entry.summary()['step']} -> {entry.path}")
        return 0
    if args.action == "verify":
        from denoisers.store.verify import verify_model

        if not args.model_id or len(args.model_id) != 1 or args.render_root is None or args.out is None:
            raise StoreError("store verify needs one --model-id, --render-root and --out")
        steps = args.steps or (cfg.get("store", {}).get("verify") or {}).get("steps")
        record = verify_model(cfg, args.model_id[0], args.render_root, args.out, steps=steps)
        log.info("model %s: %s over %d steps: passed (%d values compared, largest relative difference %.3g)",
                 record["model_id"], record["mode"], record["steps"], record["curves"]["values_compared"],
                 record["curves"]["largest_relative_difference"])
        return 0
    # check
    problems = []
    for kind in ("models", "checkpoints", "tuning"):
        for entry in store.entries(kind):
            from denoisers.store.entries import _check_files

            record = entry.summary()
            files = (record.get("store") or record).get("files", {})
            try:
                _check_files(entry.path, files)
            except StoreError as error:
                problems.append(str(error))
    problems += reference_problems(store.root)
    size, budget = store.size_bytes(), store.budget_bytes()
    if size > budget:
        problems.append(f"store {store.root}: {size / 1e6:.1f} MB, over its budget of {budget / 1e6:.0f} MB")
    for problem in problems:
        log.error("%s", problem)
    print(f"store {store.root}: {size / 1e6:.1f} MB of {budget / 1e6:.0f} MB; {len(problems)} problems")
    return 1 if problems else 0
