"""Removing an experiment's outputs: ``python -m denoisers clean --config <file> [--stale] [--dry-run]``.

The experiment folder is the config's ``output_dir``. A full clean removes exactly the entries a workflow
run writes there (scenegen.config.OUTPUT_ENTRIES: scenes/, renders/, models/ with the training work
directories, ..., logs/, benchmarks/, .config/), then the folder itself if that left it empty; another
experiment nested in it (results/smoke inside results) and files the workflow does not write stay.
``--stale`` removes only what no job of the current config reads: training work directories
(models/.work/<model>-<digest>) that no configured model resumes from, left behind by earlier settings,
and the temporaries of interrupted jobs (hidden ``.<name>.tmp-<pid>`` siblings, scenegen.atomic).

Safety: the folder must not be, or contain, the working directory or the home directory, and must hold
a .config/ folder (which every workflow run writes), else nothing is removed. Symbolic links are removed
as links, never followed, and every removed path is checked to lie inside the folder. Do not clean a
folder while a workflow run writes to it.
"""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

from denoisers.training.job import WORK_DIR_NAME, work_dir_for
from denoisers.training.models import trained_model_specs
from scenegen.config import OUTPUT_ENTRIES, output_root

#: Hidden temporaries of scenegen.atomic (.<name>.tmp-<pid>) and of the resolved config (.<name>.<pid>.tmp).
TEMPORARY = re.compile(r"^\..+(\.tmp-\d+|\.\d+\.tmp)$")


class CleanError(ValueError):
    """The experiment folder cannot be cleaned safely (nothing was removed)."""


def _size(path: Path) -> int:
    """Bytes of a file, or of every file below a directory (links counted as links, never followed)."""
    if path.is_symlink() or not path.is_dir():
        return path.lstat().st_size
    return sum((Path(top) / name).lstat().st_size for top, _, files in os.walk(path) for name in files)


def experiment_folder(cfg: dict) -> Path:
    """The config's output_dir, resolved, after the safety checks; CleanError if it must not be cleaned."""
    root = output_root(cfg)
    real = root.resolve()
    for protected in (Path.cwd().resolve(), Path.home().resolve()):
        if protected == real or protected.is_relative_to(real):
            raise CleanError(f"output_dir {root} is or contains {protected}: refusing to clean it")
    if not real.is_dir():
        return real
    if not (real / ".config").is_dir():
        raise CleanError(f"output_dir {root} holds no .config/ folder, so no workflow run wrote it: refusing to "
                         f"remove anything from it")
    return real


def _checked(path: Path, real: Path) -> Path:
    """``path`` itself (not a link target), after checking that it lies inside the folder ``real``."""
    where = path.parent.resolve() / path.name
    if not where.is_relative_to(real) or where == real:
        raise CleanError(f"{path} is not inside the experiment folder {real}: refusing to remove it")
    return where


def stale_entries(cfg: dict, real: Path) -> list[Path]:
    """Training work directories no configured model resumes from, and temporaries of interrupted jobs."""
    found = []
    work = real / "models" / WORK_DIR_NAME
    if work.is_dir() and not work.is_symlink():
        keep = {work_dir_for(work.parent, cfg, spec).name for spec in trained_model_specs(cfg)}
        found += [entry for entry in sorted(work.iterdir()) if entry.name not in keep]
    tops = [real / name for name in OUTPUT_ENTRIES if (real / name).is_dir() and not (real / name).is_symlink()]
    found += [entry for entry in sorted(real.iterdir()) if TEMPORARY.match(entry.name)] if real.is_dir() else []
    for top in tops:
        for folder, dirs, files in os.walk(top):
            temporary = sorted(name for name in dirs + files if TEMPORARY.match(name))
            found += [Path(folder) / name for name in temporary]
            dirs[:] = [name for name in dirs if name not in temporary]
    return found


def clean_experiment(cfg: dict, stale_only: bool = False, dry_run: bool = False) -> list[tuple[Path, int]]:
    """Remove the experiment's outputs (or, with ``stale_only``, its stale work directories and temporaries);
    return (path, bytes) of every removed entry (of every entry that would be removed, with ``dry_run``)."""
    real = experiment_folder(cfg)
    if not real.is_dir():
        return []
    if stale_only:
        entries = stale_entries(cfg, real)
    else:
        entries = [real / name for name in OUTPUT_ENTRIES if (real / name).is_symlink() or (real / name).exists()]
    removed = [(_checked(entry, real), _size(entry)) for entry in entries]
    if dry_run:
        return removed
    for path, _ in removed:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    if not stale_only and not any(real.iterdir()) and not output_root(cfg).is_symlink():
        real.rmdir()
    return removed
