"""One job per evaluation row: every clip of a row (its evaluated scenes at each of its spp) in one process.

A clip is a second or less of work, and a fresh process costs more than that (importing torch alone takes about
2 s), so the workflow denoises, scores and spikes a row's clips in one job each (rules ``denoise_row``,
``evaluate_row``, ``robustness_row``). The files are those of the per-clip jobs, in the same layout below the
row's folder, written by :func:`denoisers.jobs.denoise.denoise_clip`, :func:`denoisers.jobs.scoring.evaluate_clip`
and :func:`denoisers.jobs.robustness.robustness_clip`:

* ``denoised/{row}/{scene}/spp{spp}/`` (frames, timing.json);
* ``metrics/{row}/{scene}/spp{spp}.csv`` + ``.json``;
* ``robustness/{row}/{scene}/spp{spp}/``.

The stability suite's and the volumetric clips' rows are batched the same way (rules ``denoise_scenarios``,
``score_scenarios``, ``denoise_volumes``, ``evaluate_volumes``, ``robustness_volumes``) below
``stability/denoised|scores/{row}/`` and ``volumes/denoised|metrics|robustness/{row}/``; :data:`CLIP_KINDS` names
which clips each kind of row job does.

Each clip that runs a method is denoised in a process of its own, forked from a server that has imported torch and
the methods once (:func:`in_fresh_process`): a clip's measurements (its peak memory above the process's state
before the loop, its first frame's lazy initialisations) are those of a fresh process, as with one job per clip,
without paying the import per clip. Scoring reads files only and runs in the job's own process.

The row's folder appears only once every clip is written (:func:`scenegen.atomic.atomic_directory`), so an
interrupted job leaves nothing that looks complete.
"""
from __future__ import annotations

import importlib
import logging
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from denoisers.evaluate import EvaluationError, evaluated_scene_ids, method_spec
from scenegen.atomic import atomic_directory

log = logging.getLogger(__name__)


#: Which clips a row job does: the evaluated scenes (evaluation, and the spike scenario at its spp), the stability
#: scenarios with their controls, the evaluated volumetric clips (and their spike scenario).
CLIP_KINDS = ("evaluation", "robustness", "stability", "volumes", "volume_robustness")


def _row_runs(cfg: dict, method_id: str, kind: str) -> tuple[list, list[str]]:
    """(the row's runs, the scenes it runs on) for ``kind`` (one of CLIP_KINDS)."""
    from denoisers.evaluate import plan_runs, robustness_runs

    if kind == "evaluation":
        return plan_runs(cfg, rows=[method_spec(cfg, method_id)]), evaluated_scene_ids(cfg)
    if kind == "robustness":
        return robustness_runs(cfg), evaluated_scene_ids(cfg)
    if kind == "stability":
        from denoisers.jobs.stability import stability_runs
        from scenegen.catalog import stability_scene_ids
        from scenegen.scenarios import stability_control_ids

        return stability_runs(cfg), stability_scene_ids(cfg) + stability_control_ids(cfg)
    if kind in ("volumes", "volume_robustness"):
        from denoisers.jobs.volumes import volume_robustness_runs, volume_runs, volume_test_scene_ids

        runs = volume_runs(cfg) if kind == "volumes" else volume_robustness_runs(cfg)
        return runs, volume_test_scene_ids(cfg)
    raise ValueError(f"clip kind {kind!r}; kinds: {', '.join(CLIP_KINDS)}")


def row_clips(cfg: dict, method_id: str, kind: str = "evaluation") -> list[tuple[str, int]]:
    """(scene, spp) of every clip of row ``method_id``: each scene of ``kind`` (CLIP_KINDS; 'evaluation': the
    evaluated scenes) at each runnable spp of the row there (the spike scenario: at its spp). EvaluationError if
    the row runs on none."""
    method_spec(cfg, method_id)            # KeyError naming the rows for an unknown id
    runs, scenes = _row_runs(cfg, method_id, kind)
    spps = [run.spp for run in runs if run.spec.id == method_id and run.runnable]
    if not spps or not scenes:
        where = {"evaluation": "evaluated", "robustness": "in the robustness scenario",
                 "stability": "run on the stability clips", "volumes": "run on the volumetric clips",
                 "volume_robustness": "in the volumetric clips' robustness scenario"}[kind]
        raise EvaluationError(f"row {method_id!r} is not {where} at any spp this config renders")
    return [(scene, spp) for spp in spps for scene in scenes]


#: Modules the clip processes' server imports once: torch, the registry and every method, the loaders.
PRELOADED_MODULES = ("torch", "denoisers.registry", "denoisers.methods", "scenegen.dataset", "denoisers.jobs.denoise",
                     "denoisers.jobs.robustness")


def _run_in_child(send, function: Callable, args: tuple, kwargs: dict) -> None:
    try:
        outcome = (True, function(*args, **kwargs))
    except BaseException as error:     # sent back whole: the parent raises it again
        outcome = (False, (type(error).__module__, type(error).__qualname__, str(error), traceback.format_exc()))
    send.send(outcome)
    send.close()


def _rebuilt_error(module: str, name: str, message: str, child_traceback: str) -> BaseException:
    """The child's exception as an instance of its own class (so that the command line's handling of expected
    errors applies), with the child's traceback as a note."""
    try:
        cls = getattr(importlib.import_module(module), name)
        error = cls.__new__(cls)
        error.args = (message,)
    except (ImportError, AttributeError, TypeError):
        error = EvaluationError(f"{module}.{name}: {message}")
    error.add_note(f"in the clip's process:\n{child_traceback}")
    return error


def in_fresh_process(function: Callable, *args: Any, **kwargs: Any) -> Any:
    """``function(*args, **kwargs)`` in a new process forked from a server that has imported
    :data:`PRELOADED_MODULES` (multiprocessing's forkserver: no torch thread pool or device state is inherited);
    returns its result or raises its exception. ``function`` must be importable (pickled by reference)."""
    import multiprocessing

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(PRELOADED_MODULES))
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=_run_in_child, args=(send, function, args, kwargs))
    process.start()
    send.close()
    try:
        outcome = receive.recv()
    except EOFError:
        outcome = None
    finally:
        receive.close()
        process.join()
    if outcome is None:
        raise EvaluationError(f"the clip's process ended without a result (exit code {process.exitcode}; killed "
                              "for memory?)")
    succeeded, value = outcome
    if succeeded:
        return value
    raise _rebuilt_error(*value)


def _each_clip(clips: list[tuple[str, int]], what: str, run_clip: Callable[[str, int], str]) -> None:
    for index, (scene, spp) in enumerate(clips, 1):
        log.info("%s %d/%d: %s spp %d: %s", what, index, len(clips), scene, spp, run_clip(scene, spp))


def _method_row(clip_function: Callable, describe: Callable[[dict], str], what: str, cfg: dict, method_id: str,
                render_root: Path, out_dir: Path, threads: int, results: Path | str | None,
                kind: str) -> list[dict[str, Any]]:
    """``clip_function(cfg, row, scene, spp, render_dir, clip_dir, threads=, results=)`` on every clip of the row,
    each in a fresh process, into ``out_dir/{scene}/spp{spp}/``; returns the clips' records."""
    records: list[dict[str, Any]] = []

    def one(scene: str, spp: int) -> str:
        records.append(in_fresh_process(clip_function, cfg, method_id, scene, spp, Path(render_root) / scene,
                                        staging / scene / f"spp{spp}", threads=threads, results=results))
        return describe(records[-1])

    clips = row_clips(cfg, method_id, kind)
    with atomic_directory(Path(out_dir)) as staging:
        _each_clip(clips, f"{what} {method_id}", one)
    return records


def denoise_row(cfg: dict, method_id: str, render_root: Path, out_dir: Path, threads: int = 1,
                results: Path | str | None = None, kind: str = "evaluation") -> list[dict[str, Any]]:
    """Denoise every clip of row ``method_id`` (of ``kind``: evaluation, stability or volumes) into
    ``out_dir/{scene}/spp{spp}/`` (renders read from ``render_root/{scene}``). Returns the clips' timing records."""
    from denoisers.jobs.denoise import denoise_clip

    return _method_row(denoise_clip, lambda r: (f"{r['mean_seconds'] * 1e3:.2f} ms/frame, {r['nonfinite_outputs']} "
                                                f"non-finite and {r['out_of_range_outputs']} out-of-range outputs"),
                       "denoise", cfg, method_id, render_root, out_dir, threads, results, kind)


def robustness_row(cfg: dict, method_id: str, render_root: Path, out_dir: Path, threads: int = 1,
                   results: Path | str | None = None, kind: str = "robustness") -> list[dict[str, Any]]:
    """The spike/NaN scenario on every clip of row ``method_id`` (``kind``: robustness, or volume_robustness for
    the volumetric clips) into ``out_dir/{scene}/spp{spp}/``. Returns the clips' summaries."""
    from denoisers.jobs.robustness import robustness_clip

    return _method_row(robustness_clip, lambda r: (f"injected {r['injected']}, {r['nonfinite_outputs']} non-finite "
                                                   f"outputs, mean PSNR {r['mean_psnr']:.2f} dB"),
                       "robustness", cfg, method_id, render_root, out_dir, threads, results, kind)


def _clips_on_disk(row_dir: Path, scenes: set[str] | None = None) -> list[tuple[str, int]]:
    """(scene, spp) of the clip folders ``row_dir/{scene}/spp{spp}/`` (of ``scenes`` only, when given);
    EvaluationError if there are none."""
    clips = sorted((path.parent.name, int(path.name[3:])) for path in Path(row_dir).glob("*/spp*")
                   if path.is_dir() and path.name[3:].isdigit() and (scenes is None or path.parent.name in scenes))
    if not clips:
        raise EvaluationError(f"{row_dir}: no denoised clips ({{scene}}/spp{{spp}}/)")
    return clips


def evaluate_row(cfg: dict, denoised_row: Path, render_root: Path, out_dir: Path) -> int:
    """Per-frame metrics of every clip in ``denoised_row`` (a denoise_row output) into
    ``out_dir/{scene}/spp{spp}.csv`` + ``.json``; the clips are those on disk, so no method is built (no torch).
    Returns the number of clips. EvaluationError if the folder holds none."""
    from denoisers.jobs.scoring import evaluate_clip

    denoised_row = Path(denoised_row)
    clips = _clips_on_disk(denoised_row)

    def one(scene: str, spp: int) -> str:
        table = evaluate_clip(cfg, denoised_row / scene / f"spp{spp}", Path(render_root) / scene,
                              staging / scene / f"spp{spp}.csv")
        return f"{len(table)} frames, mean PSNR {table['psnr'].mean():.2f} dB"

    with atomic_directory(Path(out_dir)) as staging:
        _each_clip(clips, f"evaluate {denoised_row.name}", one)
    return len(clips)


def score_scenarios_row(cfg: dict, denoised_row: Path, render_root: Path, masks_root: Path, out_dir: Path) -> int:
    """Failure metrics of every stability clip of a denoised row (a denoise_row output of kind 'stability') into
    ``out_dir/{scene}/spp{spp}.csv`` + ``.json``: each scenario clip against its reference, masks and events
    (``masks_root/{scene}``) and, for an animated scenario, its control clip denoised by the same row at the same
    spp (the lag metric's steady state). The controls get no scores of their own. Returns the number of clips."""
    from denoisers.jobs.stability import score_scenario
    from scenegen.catalog import stability_scene_ids
    from scenegen.scenarios import scenario_control

    denoised_row = Path(denoised_row)
    clips = _clips_on_disk(denoised_row, set(stability_scene_ids(cfg)))

    def one(scene: str, spp: int) -> str:
        control = scenario_control(cfg, scene)
        record = score_scenario(
            cfg, denoised_row / scene / f"spp{spp}", Path(render_root) / scene, Path(masks_root) / scene,
            staging / scene / f"spp{spp}.csv",
            control_denoised=None if control is None else denoised_row / control / f"spp{spp}",
            control_render_dir=None if control is None else Path(render_root) / control)
        return (f"masked PSNR {record['masked_psnr']} dB, frames to recover {record['frames_to_recover']}, "
                f"flicker TRMAE {record['flicker_trmae']}")

    with atomic_directory(Path(out_dir)) as staging:
        _each_clip(clips, f"score {denoised_row.name}", one)
    return len(clips)
