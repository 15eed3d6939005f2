"""Command line of the pipeline's scene and render stages (``python -m scenegen <command>``)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="scenegen", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    gen = sub.add_parser("generate", help="draw one seeded random scene")
    gen.add_argument("--config", type=Path, required=True)
    gen.add_argument("--scene", required=True, help="scene id, e.g. train_000")
    gen.add_argument("--out", type=Path, required=True, help="scene directory to create")

    for name, help_text in (("render-noisy", "render per-sample noisy frames of one chunk"),
                            ("render-reference", "render high-spp references of one chunk")):
        cmd = sub.add_parser(name, help=help_text)
        cmd.add_argument("--config", type=Path, required=True)
        cmd.add_argument("--scene", required=True)
        cmd.add_argument("--chunk", type=int, required=True)
        cmd.add_argument("--scene-dir", type=Path, required=True)
        cmd.add_argument("--out", type=Path, required=True)
        cmd.add_argument("--threads", type=int, default=None,
                         help="Dr.Jit worker threads (default: all cores); the workflow passes {threads}")
    masks = sub.add_parser("derive-masks", help="derive a stability scenario's masks and events from its renders")
    masks.add_argument("--config", type=Path, required=True)
    masks.add_argument("--scene", required=True, help="stability scene id, e.g. stab_disocclusion")
    masks.add_argument("--scene-dir", type=Path, required=True)
    masks.add_argument("--render-dir", type=Path, required=True, help="<output_dir>/renders/{scene}")
    masks.add_argument("--out", type=Path, required=True, help="<output_dir>/stability/{scene}")
    masks.add_argument("--threads", type=int, default=None, help="Dr.Jit worker threads")
    sub.add_parser("scenarios", help="list the registered stability scenarios (config key stability.scenarios)")
    share = sub.add_parser("share-renders", help="hard-link another experiment's scenes and renders into this "
                                                 "config's output folder where both configs produce them identically")
    share.add_argument("--from", dest="source", type=Path, required=True,
                       help="config whose output folder holds the renders, e.g. config/config.yaml")
    share.add_argument("--config", type=Path, required=True, help="config to share them with, e.g. config/isik2021.yaml")
    share.add_argument("--dry-run", action="store_true", help="only list what would be shared")
    compare = sub.add_parser("compare-renders", help="compare two render folders (or EXR files) by their pixels, "
                                                     "ignoring the render-time metadata; exit 1 when they differ")
    compare.add_argument("first", type=Path)
    compare.add_argument("second", type=Path)
    compare.add_argument("--atol", type=float, default=0.0, help="largest accepted |difference| (default 0: exact)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        stream=sys.stderr)
    from scenegen.config import ConfigError
    from scenegen.dataset import DatasetError
    from scenegen.exr import EXRError
    from scenegen.retry_gate import record_failure, refuse_retry, simulated_memory_kill

    # a retry of a deterministic failure stops here (and the one-node check can fake a kill for memory)
    refused = simulated_memory_kill(args.command) or refuse_retry()
    if refused is not None:
        return refused
    try:
        return _main(args)
    except (ConfigError, DatasetError, EXRError) as error:   # the config or the inputs: a retry fails alike
        record_failure(error)
        raise


def _main(args: argparse.Namespace) -> int:
    if args.command == "scenarios":
        from scenegen.scenarios import SCENARIOS

        for scenario in SCENARIOS.values():
            print(f"{scenario.name:18s} focus: {', '.join(scenario.focus) or '(events)':28s} {scenario.description}")
        return 0
    if args.command == "compare-renders":
        from scenegen.compare import compare_renders

        differences = compare_renders(args.first, args.second, args.atol)
        for difference in differences:
            print(f"differs {difference.path}: {difference.reason}")
        print(f"{len(differences)} EXR file(s) differ by their pixels" if differences
              else "the renders agree pixel by pixel")
        return 1 if differences else 0
    from scenegen.config import load_config

    cfg = load_config(args.config)
    if args.command == "share-renders":
        from scenegen.share import share_renders

        result = share_renders(load_config(args.source), cfg, dry_run=args.dry_run)
        for path, why in result.skipped:
            print(f"kept   {path}: {why}")
        for path in result.shared:
            print(f"{'would share' if args.dry_run else 'shared'} {path}")
        print(f"{len(result.shared)} folders {'to share' if args.dry_run else 'shared'}, {len(result.skipped)} left")
        return 0
    from scenegen import jobs

    if getattr(args, "threads", None):
        from scenegen.mitsuba_env import init_mitsuba, set_render_threads

        init_mitsuba(cfg["render"]["variant"])
        set_render_threads(args.threads)
    if args.command == "generate":
        jobs.run_generate(cfg, args.scene, args.out)
    elif args.command == "render-noisy":
        jobs.run_render_noisy(cfg, args.scene, args.chunk, args.scene_dir, args.out)
    elif args.command == "render-reference":
        jobs.run_render_reference(cfg, args.scene, args.chunk, args.scene_dir, args.out)
    elif args.command == "derive-masks":
        from scenegen.scenarios.masks import derive_masks

        derive_masks(cfg, args.scene, args.scene_dir, args.render_dir, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
