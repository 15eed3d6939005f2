"""Command line of the evaluation stages (``python -m denoisers <command>``); the workflow's rules call it.
<out> is the config's output_dir (default results), the experiment's folder.

  train       one configured model on the training scenes          -> <out>/models/{model}/
  tune        grid search of a baseline's parameters on training scenes -> <out>/tuning/{method}.json
  denoise     one configured method on one test clip at one spp  -> <out>/denoised/{method}/{scene}/spp{spp}/
  evaluate    per-frame metrics of a denoised clip               -> <out>/metrics/{method}/{scene}/spp{spp}.csv
  robustness  one method on a clip with injected spikes/NaN/Inf  -> <out>/robustness/{method}/{scene}/spp{spp}/
  denoise-row, evaluate-row, robustness-row, score-scenarios-row  the same for every clip of one row, in one
              process (the workflow's jobs; --kind: the evaluated scenes, the stability or the volumetric clips)
                                                                  -> <out>/denoised/{method}/, metrics/{method}/, ...
  time        every row timed on the same frames, interleaved, and the renderer's rate -> <out>/timing/timing.json
  time-training  every learned model's training step per precision / layout, beside sgemm -> <out>/timing/training.json
  report      tables, figures, claims and REPORT.md              -> <out>/tables/, <out>/figures/, <out>/REPORT.md
  score-scenario  failure metrics of a denoised stability clip     -> <out>/stability/scores/{method}/{scene}/spp{spp}.csv + .json
  atlas       the failure atlas of the stability suite          -> <out>/stability/ATLAS.md, tables/, figures/
  clean       remove an experiment's outputs, or only its stale training work directories (--stale)
  publish-run  a finished run's report, tables and figures, with its digests  -> runs/<name>/
  readme      regenerate the README's and docs' published-run blocks (--check: fail when out of date)
  job-counts  regenerate the README's and docs' dag-jobs blocks from dry runs (--check: fail when out of date)
  store       the model store: list, publish, checkpoint, verify, check (denoisers.store.cli)
  submission  what this checkout's commits cost to submit, against the workplace's limits (--check: fail past them)
  methods     list the registered methods
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger("denoisers")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m denoisers", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    denoise = sub.add_parser("denoise", help="run one method on one clip")
    robustness = sub.add_parser("robustness", help="run one method on a clip with injected spikes and NaN/Inf")
    for cmd in (denoise, robustness):
        cmd.add_argument("--config", type=Path, required=True, help="resolved config YAML")
        cmd.add_argument("--method-id", required=True, help="row id in evaluation.methods")
        cmd.add_argument("--scene", required=True, help="scene id, e.g. test_000")
        cmd.add_argument("--render-dir", type=Path, required=True, help="results/renders/{scene}")
        cmd.add_argument("--out", type=Path, required=True, help="output directory (written atomically)")
        cmd.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
        cmd.add_argument("--spp", type=int, required=True, help="evaluated samples per pixel")
        cmd.add_argument("--results", type=Path, default=None,
                         help="experiment folder (default: the config's output_dir); trained models are read "
                              "from <results>/models/<id>/, tuning results from <results>/tuning/")

    denoise_row = sub.add_parser("denoise-row", help="run one row on every clip it is evaluated on")
    robustness_row = sub.add_parser("robustness-row", help="the spike/NaN scenario of one row on every clip")
    for cmd in (denoise_row, robustness_row):
        cmd.add_argument("--config", type=Path, required=True, help="resolved config YAML")
        cmd.add_argument("--method-id", required=True, help="row id (evaluation.methods, or an ablation/seed row)")
        cmd.add_argument("--render-root", type=Path, required=True, help="results/renders (holds {scene}/)")
        cmd.add_argument("--out", type=Path, required=True,
                         help="the row's folder, e.g. results/denoised/{method} (written atomically)")
        cmd.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
        cmd.add_argument("--results", type=Path, default=None,
                         help="experiment folder (default: the config's output_dir); trained models are read "
                              "from <results>/models/<id>/, tuning results from <results>/tuning/")
    denoise_row.add_argument("--kind", choices=("evaluation", "stability", "volumes"), default="evaluation",
                             help="which clips: the evaluated scenes, the stability scenarios (with their controls) "
                                  "or the evaluated volumetric clips")
    robustness_row.add_argument("--kind", choices=("robustness", "volume_robustness"), default="robustness",
                                help="the evaluated scenes, or the evaluated volumetric clips")

    timing = sub.add_parser("time", help="time every configured row on the same frames (interleaved rounds) and "
                                         "the renderer's samples/s at the same threads")
    timing.add_argument("--config", type=Path, required=True, help="resolved config YAML")
    timing.add_argument("--scene", required=True, help="evaluated scene id (evaluation.timing.scene)")
    timing.add_argument("--render-dir", type=Path, required=True, help="results/renders/{scene}")
    timing.add_argument("--scenes-root", type=Path, required=True,
                        help="results/scenes (the renderer's rate is measured on every evaluated scene)")
    timing.add_argument("--out", type=Path, required=True, help="results/timing/timing.json (written atomically)")
    timing.add_argument("--threads", type=int, required=True, help="torch and Dr.Jit threads")
    timing.add_argument("--results", type=Path, default=None, help="experiment folder (models, tuning results)")

    speed = sub.add_parser("time-training", help="time every learned model's training step (training.models) per "
                                                 "precision / layout variant, interleaved with sgemm (training.speed)")
    speed.add_argument("--config", type=Path, required=True, help="resolved config YAML")
    speed.add_argument("--out", type=Path, required=True, help="results/timing/training.json (written atomically)")
    speed.add_argument("--threads", type=int, default=None, help="torch threads (default: training.speed.threads, "
                                                                 "else training.threads)")

    train = sub.add_parser("train", help="train one configured model (training.models / ablations)")
    train.add_argument("--config", type=Path, required=True, help="resolved config YAML")
    train.add_argument("--model-id", required=True, help="model id (training.models or {ablation}_{variant})")
    train.add_argument("--render-root", type=Path, required=True, help="results/renders (one folder per scene)")
    train.add_argument("--out", type=Path, required=True, help="model directory results/models/{model} (atomic)")
    train.add_argument("--threads", type=int, default=None,
                       help="torch threads; default and only accepted value: training.threads (the weights depend on it)")

    publish = sub.add_parser("publish-run", help="commit-ready copy of a finished run: REPORT.md, tables, linked "
                                                 "figures and run.json (digests, commit) -> runs/<name>/")
    publish.add_argument("--config", type=Path, required=True, help="the run's config file (as in the repository)")
    publish.add_argument("--results", type=Path, default=None, help="the run's folder (default: output_dir)")
    publish.add_argument("--out", type=Path, required=True, help="runs/<name> (replaced)")
    readme = sub.add_parser("readme", help="regenerate the published-run blocks of README.md and docs/*.md")
    readme.add_argument("--check", action="store_true", help="only check; exit 1 when a block is out of date")
    jobs = sub.add_parser("job-counts", help="regenerate the dag-jobs blocks (a config's job counts) of README.md and "
                                             "docs/*.md from dry runs")
    jobs.add_argument("--check", action="store_true", help="only check; exit 1 when a block is out of date")

    from denoisers.store.cli import add_parser as add_store_parser
    from denoisers.store.session_cli import add_parsers as add_session_parsers

    add_store_parser(sub)
    add_session_parsers(sub)

    tune = sub.add_parser("tune", help="grid-search a baseline's parameters on the training scenes (tuning.methods)")
    tune.add_argument("--config", type=Path, required=True, help="resolved config YAML")
    tune.add_argument("--method", required=True, help="registered method name with a tuning.methods entry")
    tune.add_argument("--render-dirs", type=Path, nargs="+", required=True,
                      help="results/renders/train_NNN directories (training scenes only)")
    tune.add_argument("--out", type=Path, required=True, help="results/tuning/{method}.json (written atomically)")
    tune.add_argument("--threads", type=int, default=1, help="torch intra-op threads")

    evaluate = sub.add_parser("evaluate", help="per-frame metrics of a denoised clip against its reference")
    evaluate.add_argument("--config", type=Path, required=True)
    evaluate.add_argument("--denoised", type=Path, required=True, help="results/denoised/{method}/{scene}/spp{spp}")
    evaluate.add_argument("--render-dir", type=Path, required=True, help="results/renders/{scene}")
    evaluate.add_argument("--out", type=Path, required=True, help="CSV file")

    evaluate_row = sub.add_parser("evaluate-row", help="per-frame metrics of every clip of a denoised row")
    evaluate_row.add_argument("--config", type=Path, required=True)
    evaluate_row.add_argument("--denoised", type=Path, required=True, help="results/denoised/{method}")
    evaluate_row.add_argument("--render-root", type=Path, required=True, help="results/renders (holds {scene}/)")
    evaluate_row.add_argument("--out", type=Path, required=True, help="results/metrics/{method} (written atomically)")

    score_row = sub.add_parser("score-scenarios-row", help="failure metrics of every stability clip of a denoised row")
    score_row.add_argument("--config", type=Path, required=True)
    score_row.add_argument("--denoised", type=Path, required=True, help="results/stability/denoised/{method}")
    score_row.add_argument("--render-root", type=Path, required=True, help="results/renders (holds {scene}/)")
    score_row.add_argument("--masks-root", type=Path, required=True, help="results/stability (holds {scene}/ masks)")
    score_row.add_argument("--out", type=Path, required=True,
                           help="results/stability/scores/{method} (written atomically)")

    score = sub.add_parser("score-scenario", help="failure metrics of a denoised stability clip (masks, events)")
    score.add_argument("--config", type=Path, required=True)
    score.add_argument("--denoised", type=Path, required=True,
                       help="results/stability/denoised/{method}/{scene}/spp{spp}")
    score.add_argument("--render-dir", type=Path, required=True, help="results/renders/{scene}")
    score.add_argument("--masks", type=Path, required=True, help="results/stability/{scene} (rule derive_masks)")
    score.add_argument("--out", type=Path, required=True, help="CSV file (its .json summary is written beside it)")
    score.add_argument("--control-denoised", type=Path, default=None,
                       help="an animated scenario's control clip denoised by the same row: "
                            "results/stability/denoised/{method}/{scene}__still/spp{spp}")
    score.add_argument("--control-render-dir", type=Path, default=None, help="results/renders/{scene}__still")

    atlas = sub.add_parser("atlas", help="the failure atlas of the stability suite -> <out>/stability/ATLAS.md")
    atlas.add_argument("--config", type=Path, required=True)
    atlas.add_argument("--results", type=Path, default=None,
                       help="experiment folder to read and write (default: the config's output_dir)")

    report = sub.add_parser("report", help="aggregate every metrics CSV into tables, figures and REPORT.md")
    report.add_argument("--config", type=Path, required=True)
    report.add_argument("--results", type=Path, default=None,
                        help="experiment folder to read (default: the config's output_dir)")
    report.add_argument("--out", type=Path, default=None, help="where to write (default: --results)")

    clean = sub.add_parser("clean", help="remove an experiment's outputs (the config's output_dir)")
    clean.add_argument("--config", type=Path, required=True, help="the experiment's config file")
    clean.add_argument("--stale", action="store_true",
                       help="only training work directories no configured model resumes from, and "
                            "temporaries of interrupted jobs")
    clean.add_argument("--dry-run", "-n", action="store_true", help="list what would be removed, remove nothing")

    sub.add_parser("methods", help="list the registered methods")
    return parser


#: Commands that never build a model: their config check skips the networks' keys (which imports torch, about
#: 1.7 s of each of several hundred short jobs); the workflow checks the whole config when it parses it.
TORCH_FREE_COMMANDS = frozenset({"evaluate", "evaluate-row", "score-scenario", "score-scenarios-row"})


def load_evaluation_config(path: Path, build_models: bool = True) -> dict:
    """Load and validate a config, including the cross-key checks of the evaluation section
    (``build_models`` False: without the checks that build methods or networks, see TORCH_FREE_COMMANDS)."""
    from denoisers.evaluate import evaluation_problems
    from denoisers.training.models import training_problems
    from denoisers.jobs.tuning import tuning_problems
    from scenegen.config import ConfigError, load_config

    cfg = load_config(path)
    problems = (evaluation_problems(cfg, check_methods=build_models) + training_problems(cfg, build_models)
                + (tuning_problems(cfg) if build_models else []))      # the registry's checks import torch
    if problems:
        raise ConfigError(f"{path}: invalid configuration:\n  - " + "\n  - ".join(problems))
    return cfg


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        stream=sys.stderr)
    from denoisers.clean import CleanError
    from denoisers.evaluate import EvaluationError
    from denoisers.experiment import SettingsMismatchError
    from denoisers.errors import CheckpointError, MissingInputError, NonFiniteLossError
    from denoisers.report.published import PublishError
    from denoisers.store import StoreError
    from denoisers.jobs.tuning import TuningError
    from scenegen.config import ConfigError
    from scenegen.dataset import DatasetError
    from scenegen.exr import EXRError
    from scenegen.retry_gate import record_failure, refuse_retry, simulated_memory_kill

    # a retry of a deterministic failure stops here (and the one-node check can fake a kill for memory)
    refused = simulated_memory_kill(args.command) or refuse_retry()
    if refused is not None:
        return refused
    try:
        return _run(args)
    except (MissingInputError, EvaluationError, DatasetError, ConfigError, CheckpointError,
            NonFiniteLossError, TuningError, SettingsMismatchError, CleanError, StoreError,
            PublishError, EXRError) as error:
        # Expected failures get one clear line (the workflow prints the job's log), not a traceback; they depend
        # on the config and the inputs only, so a retry is refused (scenegen.retry_gate).
        log.error("%s", error)
        record_failure(error)
        return 1


def _run(args: argparse.Namespace) -> int:
    if args.command == "methods":
        import inspect

        from denoisers import registry

        for name in registry.available():
            info = registry.get(name).info
            print(f"{name:16s} inputs={','.join(info.inputs)} pixel={','.join(info.pixel_inputs) or '-'} "
                  f"temporal={info.temporal} trainable={info.trainable}"
                  + (" adaptive=True" if info.adaptive else "") + f"  {info.description}")
            params = ", ".join(f"{key}" + ("" if default is inspect.Parameter.empty else f"={default!r}")
                               for key, default in registry.parameters(name).items())
            print(f"{'':16s} parameters: {params or 'none'}")
        return 0

    if args.command == "readme":
        from denoisers.provenance import REPO_ROOT
        from denoisers.report.published import update_blocks

        stale = [f"{path.name}: {run}" for path in [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
                 for run in update_blocks(path, REPO_ROOT, check=args.check)]
        print(("out of date: " if args.check else "regenerated: ") + (", ".join(stale) or "none"))
        return 1 if args.check and stale else 0

    if args.command in ("submission", "train-session"):
        from denoisers.store.session_cli import run as run_session_command

        return run_session_command(args)

    if args.command == "job-counts":
        from denoisers.dag_counts import update_dag_blocks
        from denoisers.provenance import REPO_ROOT

        cache: dict[str, dict[str, int]] = {}
        stale = [f"{path.name}: {config}"
                 for path in [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
                 for config in update_dag_blocks(path, REPO_ROOT, check=args.check, counts_of=cache)]
        print(("out of date: " if args.check else "regenerated: ") + (", ".join(stale) or "none"))
        return 1 if args.check and stale else 0

    cfg = load_evaluation_config(args.config, build_models=args.command not in TORCH_FREE_COMMANDS)
    if args.command == "publish-run":
        from denoisers.report.published import publish_run
        from scenegen.config import output_root

        record = publish_run(cfg, args.config.as_posix(), args.results or output_root(cfg), args.out)
        print(f"published {args.out}: {len(record['figures'])} figures ({record['figure_bytes'] / 1e6:.1f} MB), "
              f"left out: {', '.join(record['figures_left_out']) or 'none'}")
        return 0
    from denoisers import evaluate

    if args.command == "clean":
        from denoisers.clean import clean_experiment

        removed = clean_experiment(cfg, stale_only=args.stale, dry_run=args.dry_run)
        verb = "would remove" if args.dry_run else "removed"
        for path, size in removed:
            print(f"{verb} {path} ({size / 1024**2:.1f} MB)")
        print(f"{verb} {len(removed)} entries, {sum(size for _, size in removed) / 1024**2:.1f} MB")
        return 0

    if args.command == "store":
        from denoisers.store.cli import run as run_store

        return run_store(args, cfg)
    if args.command == "train":
        from denoisers.training.job import train_model

        summary = train_model(cfg, args.model_id, args.render_root, args.out, threads=args.threads)
        log.info("model %s: %d steps in %.0f s (%.3g s/step, stopped by %s), best validation loss %.4g at "
                 "step %s", args.model_id, summary["steps"], summary["elapsed_seconds"], summary["seconds_per_step"],
                 summary["stopped_by"], summary["best_value"] or float("nan"), summary["best_step"])
    elif args.command == "denoise":
        from denoisers.jobs.denoise import denoise_clip

        record = denoise_clip(cfg, args.method_id, args.scene, args.spp, args.render_dir, args.out,
                              threads=args.threads, results=args.results)
        log.info("%s %s spp %d: %.2f ms/frame (%.3g Mpix/s), +%.0f MB peak RSS, %d non-finite inputs, "
                 "%d non-finite outputs, %d out-of-range outputs", record["method_id"], args.scene, args.spp,
                 record["mean_seconds"] * 1e3, record["mpix_per_s"], record["peak_memory_mb"],
                 record["nonfinite_inputs"], record["nonfinite_outputs"], record["out_of_range_outputs"])
    elif args.command == "tune":
        import json

        from denoisers.jobs.tuning import format_result, tune_method
        from scenegen.atomic import write_text_atomic

        from denoisers.experiment import DIGEST_KEY, Lineage

        from denoisers.store import ModelStore, store_settings
        from denoisers.store.tuning import install_tuning, tuning_entry

        settings = store_settings(cfg)
        stored = tuning_entry(ModelStore.of(cfg), cfg, args.method) \
            if settings["use"] and not settings["force_training"] else None
        if stored is not None:
            result = install_tuning(stored, args.out)
            log.info("tuning %s: installed from the store (%s); not searched", args.method, stored)
            print(format_result(result))
            return 0
        result = tune_method(cfg, args.method, {path.name: path for path in args.render_dirs}, threads=args.threads)
        result[DIGEST_KEY] = Lineage(cfg).tuning(args.method)
        print(format_result(result))
        write_text_atomic(args.out, json.dumps(result, indent=1) + "\n")
    elif args.command == "time":
        import json

        from denoisers.experiment import DIGEST_KEY, Lineage
        from denoisers.jobs.timing import timed_runs, timing_settings, time_methods
        from scenegen.atomic import write_text_atomic
        from scenegen.config import output_root

        settings = timing_settings(cfg)
        from denoisers.evaluate import evaluated_scene_ids

        scene_dirs = {scene: args.scenes_root / scene for scene in evaluated_scene_ids(cfg)}
        record = time_methods(cfg, args.scene, args.render_dir, scene_dirs, timed_runs(cfg),
                              frames=settings["frames"], repeats=settings["repeats"], threads=args.threads,
                              results=args.results or output_root(cfg))
        runs = [(evaluate.method_spec(cfg, row), spp) for row, spp in timed_runs(cfg)]
        record[DIGEST_KEY] = Lineage(cfg).timing(args.scene, runs)
        write_text_atomic(args.out, json.dumps(record, indent=1) + "\n")
        for row in record["rows"]:
            share = (f", {row['gflops_per_s']:.1f} GFLOP/s = {row['fraction_of_sgemm']:.0%} of sgemm"
                     if row["fraction_of_sgemm"] is not None else "")
            log.info("%-16s %2d spp: %8.2f ms/frame [%.2f, %.2f] (%.3g Mpix/s%s)", row["method_id"], row["spp"],
                     row["ms_per_frame"], row["ms_per_frame_min"], row["ms_per_frame_max"], row["mpix_per_s"], share)
        log.info("sgemm %d^3: %.1f GFLOP/s (median of rounds)", record["sgemm"]["size"],
                 record["sgemm"]["gflops_per_s_median"])
        for scene, rate in record["renderers"].items():
            log.info("renderer on %s: %.3g M samples/s with %d thread(s)", scene, rate["samples_per_s"] / 1e6,
                     args.threads)
    elif args.command == "time-training":
        import json

        from denoisers.experiment import DIGEST_KEY, Lineage
        from denoisers.training.speed import describe_record, time_training
        from scenegen.atomic import write_text_atomic

        record = time_training(cfg, threads=args.threads)
        record[DIGEST_KEY] = Lineage(cfg).training_speed()
        write_text_atomic(args.out, json.dumps(record, indent=1) + "\n")
        for line in describe_record(record):
            log.info("%s", line)
    elif args.command == "evaluate":
        from denoisers.jobs.scoring import evaluate_clip

        table = evaluate_clip(cfg, args.denoised, args.render_dir, args.out)
        log.info("%s: %d frames, mean PSNR %.2f dB", args.denoised, len(table), table["psnr"].mean())
    elif args.command == "robustness":
        from denoisers.jobs.robustness import robustness_clip

        summary = robustness_clip(cfg, args.method_id, args.scene, args.spp, args.render_dir, args.out,
                                  threads=args.threads, results=args.results)
        log.info("robustness %s %s: injected %s, %d non-finite outputs, %d out-of-range outputs, mean PSNR "
                 "%.2f dB", args.method_id, args.scene, summary["injected"], summary["nonfinite_outputs"],
                 summary["out_of_range_outputs"], summary["mean_psnr"])
    elif args.command == "denoise-row":
        from denoisers.jobs.rows import denoise_row

        records = denoise_row(cfg, args.method_id, args.render_root, args.out, threads=args.threads,
                              results=args.results, kind=args.kind)
        log.info("%s: %d clips denoised into %s", args.method_id, len(records), args.out)
    elif args.command == "evaluate-row":
        from denoisers.jobs.rows import evaluate_row

        count = evaluate_row(cfg, args.denoised, args.render_root, args.out)
        log.info("%s: %d clips scored into %s", args.denoised, count, args.out)
    elif args.command == "robustness-row":
        from denoisers.jobs.rows import robustness_row

        summaries = robustness_row(cfg, args.method_id, args.render_root, args.out, threads=args.threads,
                                   results=args.results, kind=args.kind)
        log.info("robustness %s: %d clips into %s", args.method_id, len(summaries), args.out)
    elif args.command == "score-scenarios-row":
        from denoisers.jobs.rows import score_scenarios_row

        count = score_scenarios_row(cfg, args.denoised, args.render_root, args.masks_root, args.out)
        log.info("%s: %d stability clips scored into %s", args.denoised, count, args.out)
    elif args.command == "score-scenario":
        from denoisers.jobs.stability import score_scenario

        record = score_scenario(cfg, args.denoised, args.render_dir, args.masks, args.out, args.control_denoised,
                                args.control_render_dir)
        log.info("%s %s spp %d: masked PSNR %s dB, frames to recover %s, flicker TRMAE %s, relative bias %s",
                 record["method_id"], record["scene"], record["spp"], record["masked_psnr"],
                 record["frames_to_recover"], record["flicker_trmae"], record["relative_bias"])
    elif args.command == "atlas":
        from denoisers.report.atlas import build_atlas

        from scenegen.config import output_root

        written = build_atlas(cfg, args.results or output_root(cfg))
        log.info("atlas: wrote %d files", len(written))
    elif args.command == "report":
        from denoisers.report import build_report

        from scenegen.config import output_root

        results = args.results or output_root(cfg)
        written = build_report(cfg, results, args.out)
        log.info("report: wrote %d files, summary in %s", len(written), (args.out or results) / "REPORT.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
