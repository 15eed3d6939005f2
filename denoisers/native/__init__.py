"""Native (C++) kernels of the classical filters, built just in time on first use.

``load()`` returns the compiled extension of ``atrous.cpp`` (fused a-trous iterations of SVGF and EAW)
or None, in which case callers use their pure-torch implementation, the reference. The build runs
once per process at the first call (never at import), through ``torch.utils.cpp_extension.load``: torch
caches the result in TORCH_EXTENSIONS_DIR (default ~/.cache/torch_extensions), rebuilds it when the
source or flags change, and serialises concurrent builds of several processes with a file lock. If
the compiler or ninja is missing or the build fails, one warning names the error and every later call
returns None. ``MCDN_NATIVE=0`` in the environment disables the kernels (checked at every call, so a
test can switch paths).
"""
from __future__ import annotations

import logging
import os
import shutil
import threading
from pathlib import Path
from types import ModuleType

log = logging.getLogger(__name__)

#: Environment variable that disables the native kernels when set to "0".
ENVIRONMENT_SWITCH = "MCDN_NATIVE"
#: Extension name (the build directory under TORCH_EXTENSIONS_DIR).
EXTENSION_NAME = "mcdn_atrous"
SOURCES = (Path(__file__).with_name("atrous.cpp"),)
#: -O3 without -ffast-math: NaN/Inf semantics and results stay as written. -ffp-contract=off keeps
#: FMA contraction out, so the baseline and AVX2 clones of each loop give identical results;
#: -fno-trapping-math and -fno-math-errno only drop FP-exception and errno side effects, which lets
#: GCC vectorise selects and sqrt. No -march: the cached build may be used on another CPU.
CFLAGS = ("-O3", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno")

_lock = threading.Lock()
_built: list[ModuleType | None] = []     # empty until the first build attempt, then [module or None]


def enabled() -> bool:
    """Whether the native kernels may be used (``MCDN_NATIVE`` is not "0")."""
    return os.environ.get(ENVIRONMENT_SWITCH, "1").strip() != "0"


def load() -> ModuleType | None:
    """The native extension, building it on the first call; None when disabled or unavailable."""
    if not enabled():
        return None
    if not _built:
        with _lock:
            if not _built:
                _built.append(_build())
    return _built[0]


def backend() -> str:
    """"native" if :func:`load` gives the extension, else "torch" (builds it if needed)."""
    return "native" if load() is not None else "torch"


def _build() -> ModuleType | None:
    try:
        from torch.utils import cpp_extension

        _put_ninja_on_path()
        return cpp_extension.load(name=EXTENSION_NAME, sources=[str(path) for path in SOURCES],
                                  extra_cflags=list(CFLAGS), verbose=False)
    except Exception as error:    # compiler or ninja missing, compile or import error: fall back
        log.warning("native a-trous kernels unavailable, using the torch implementation "
                    "(set %s=0 to skip the build): %s: %s", ENVIRONMENT_SWITCH, type(error).__name__,
                    _summary(error))
        return None


def _put_ninja_on_path() -> None:
    """torch runs ``ninja`` from PATH; when it is not there (a venv used without activating it), add the
    directory of the ninja Python package's binary, a project dependency."""
    if shutil.which("ninja") is not None:
        return
    try:
        import ninja
    except ImportError:
        return                     # torch's build then fails and names the missing ninja
    os.environ["PATH"] = os.pathsep.join([ninja.BIN_DIR, os.environ.get("PATH", "")])


def _summary(error: Exception, limit: int = 600) -> str:
    """The informative part of a build error: its compiler error lines if any, else its first line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower()]
    text = " | ".join(errors[:3] if errors else lines[:1]) or repr(error)
    return text if len(text) <= limit else text[:limit] + "..."
