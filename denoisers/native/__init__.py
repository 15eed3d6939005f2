"""Native (C++) kernels of the classical filters, built once per checkout, outside any timed code.

``load()`` returns the compiled extension of ``atrous.cpp`` (fused a-trous iterations of SVGF and EAW)
or None, in which case callers use their pure-torch implementation, the reference. ``scripts/setup.sh``
builds it (``python -m denoisers.native``); a process that finds no build makes one at its first
``load()`` (the evaluation calls it before any timed loop, never inside one).

Where and how (the build must neither be shared between checkouts nor hang after a killed build):

- the build directory belongs to this installation: ``denoisers/native/_build`` (inside the checkout
  for an editable install), or ``MCDN_NATIVE_DIR``; a per-user cache keyed by the package path when
  the package directory is read-only;
- builders serialise on an ``fcntl`` lock of ``build.lock`` there, which the kernel releases when its
  holder dies, so a build killed part-way cannot block later ones; under that lock, torch's own lock
  file left by a killed build is removed (torch would otherwise wait for it forever);
- the compiler runs in a child process with a timeout (``MCDN_NATIVE_BUILD_TIMEOUT`` seconds, default
  900), so a hung build is killed; a successful build leaves a stamp in a directory keyed by the
  sources, flags and torch version, after which loading is a plain import of the built module.

``load_kernels()`` does the same for the second extension, ``kernels.cpp`` (per-pixel kernel application
of kernel-predicting denoisers, denoisers/kernels.py), and ``load_affinity()`` for the third,
``affinity.cpp`` (affinity kernels of Isik et al. 2021, denoisers/affinity.py), each built separately so
that no build depends on another.

If the build fails or times out, one warning names the error and every later call returns None.
``MCDN_NATIVE=0`` in the environment disables the kernels (checked at every call, so a test can switch
paths).
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import ModuleType

log = logging.getLogger(__name__)

#: Environment variable that disables the native kernels when set to "0".
ENVIRONMENT_SWITCH = "MCDN_NATIVE"
#: Environment variable overriding the build directory.
DIRECTORY_VARIABLE = "MCDN_NATIVE_DIR"
#: Environment variable: seconds the compiler may take before the build is abandoned.
TIMEOUT_VARIABLE = "MCDN_NATIVE_BUILD_TIMEOUT"
DEFAULT_TIMEOUT_S = 900.0
#: Extension name (the module name torch builds).
EXTENSION_NAME = "mcdn_atrous"
SOURCES = (Path(__file__).with_name("atrous.cpp"),)
#: The per-pixel kernel extension (load_kernels).
KERNELS_EXTENSION_NAME = "mcdn_kernels"
KERNELS_SOURCES = (Path(__file__).with_name("kernels.cpp"),)
#: The affinity-kernel extension (load_affinity; Isik et al. 2021, denoisers/affinity.py).
AFFINITY_EXTENSION_NAME = "mcdn_affinity"
AFFINITY_SOURCES = (Path(__file__).with_name("affinity.cpp"),)
#: -O3 without -ffast-math: NaN/Inf semantics and results stay as written. -ffp-contract=off keeps
#: FMA contraction out, so the baseline and AVX2 clones of each loop give identical results;
#: -fno-trapping-math and -fno-math-errno only drop FP-exception and errno side effects, which lets
#: GCC vectorise selects and sqrt. No -march: the build may be used on another CPU. -fopenmp (compile and
#: link) is what makes at::parallel_for split rows across torch's threads: without _OPENMP the ATen header
#: runs the loop serially whatever torch.set_num_threads says. The extension then needs libgomp.so.1, the
#: soname of the runtime torch has already loaded, so both share one OpenMP thread pool.
CFLAGS = ("-O3", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno", "-fopenmp")
LDFLAGS = ("-fopenmp",)

_lock = threading.Lock()
_built: list[ModuleType | None] = []     # empty until the first build attempt, then [module or None]
_built_kernels: list[ModuleType | None] = []   # the same for load_kernels()
_built_affinity: list[ModuleType | None] = []  # the same for load_affinity()


class BuildError(RuntimeError):
    """The native build failed or timed out; the message says which."""


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


def load_kernels() -> ModuleType | None:
    """The per-pixel kernel extension (kernels.cpp), built on the first call; None when disabled or unavailable."""
    if not enabled():
        return None
    if not _built_kernels:
        with _lock:
            if not _built_kernels:
                _built_kernels.append(_build(KERNELS_EXTENSION_NAME, KERNELS_SOURCES))
    return _built_kernels[0]


def load_affinity() -> ModuleType | None:
    """The affinity-kernel extension (affinity.cpp), built on the first call; None when disabled or unavailable."""
    if not enabled():
        return None
    if not _built_affinity:
        with _lock:
            if not _built_affinity:
                _built_affinity.append(_build(AFFINITY_EXTENSION_NAME, AFFINITY_SOURCES))
    return _built_affinity[0]


def backend() -> str:
    """"native" if :func:`load` gives the extension, else "torch" (builds it if needed)."""
    return "native" if load() is not None else "torch"


def build_directory() -> Path:
    """Where this installation's extension is built (see the module docstring)."""
    override = os.environ.get(DIRECTORY_VARIABLE)
    if override:
        return Path(override)
    package = Path(__file__).resolve().parent
    if os.access(package, os.W_OK):
        return package / "_build"
    key = hashlib.sha256(str(package).encode()).hexdigest()[:12]
    return Path.home() / ".cache" / "mcdenoise" / f"native-{key}"


def build_key(name: str | None = None, sources: tuple[Path, ...] | None = None) -> str:
    """Digest of what the build depends on: sources, flags, torch and Python versions (default: the
    a-trous extension)."""
    import torch

    digest = hashlib.sha256()
    for path in sources or SOURCES:
        digest.update(Path(path).read_bytes())
    digest.update(repr((CFLAGS, LDFLAGS, name or EXTENSION_NAME, torch.__version__, sys.version_info[:2])).encode())
    return digest.hexdigest()[:16]


def _timeout() -> float:
    try:
        return float(os.environ.get(TIMEOUT_VARIABLE, DEFAULT_TIMEOUT_S))
    except ValueError:
        return DEFAULT_TIMEOUT_S


def _torch_load(directory: Path, name: str | None = None, sources: list[str] | None = None,
                cflags: list[str] | None = None) -> ModuleType:
    """torch's JIT build/load of the extension in ``directory`` (this module's settings by default)."""
    from torch.utils import cpp_extension

    _put_ninja_on_path()
    return cpp_extension.load(name=name or EXTENSION_NAME, sources=sources or [str(path) for path in SOURCES],
                              extra_cflags=list(cflags or CFLAGS), extra_ldflags=list(LDFLAGS),
                              build_directory=str(directory), verbose=False)


def _import_built(directory: Path, name: str | None = None) -> ModuleType:
    """Import the extension the child process built (a plain import: nothing is compiled here)."""
    import importlib.util

    import torch  # noqa: F401 -- the extension links against torch's libraries, loaded by this import

    name = name or EXTENSION_NAME
    path = directory / f"{name}.so"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None or not path.is_file():
        raise BuildError(f"{path}: built extension not found")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build(name: str | None = None, sources: tuple[Path, ...] | None = None) -> ModuleType | None:
    """Build (once) and import extension ``name`` from ``sources`` (default: the a-trous extension)."""
    name, sources = name or EXTENSION_NAME, sources or SOURCES
    try:
        directory = build_directory() / build_key(name, sources)
        directory.mkdir(parents=True, exist_ok=True)
        stamp = directory / "built"
        with _exclusive(directory / "build.lock", _timeout()):
            stale = directory / "lock"       # torch's FileBaton of a build that was killed part-way
            if stale.exists():
                log.info("removing stale build lock %s", stale)
                stale.unlink()
            if not stamp.exists():
                _compile_in_child(directory, _timeout(), name, sources)
                stamp.write_text("ok\n")
            return _import_built(directory, name)
    except Exception as error:    # compiler or ninja missing, compile or import error, timeout: fall back
        what = "a-trous kernels" if name == EXTENSION_NAME else f"extension {name}"
        log.warning("native %s unavailable, using the torch implementation "
                    "(set %s=0 to skip the build): %s: %s", what, ENVIRONMENT_SWITCH, type(error).__name__,
                    _summary(error))
        return None


class _exclusive:
    """Exclusive ``flock`` on ``path`` for a ``with`` block, waiting at most ``timeout`` seconds."""

    def __init__(self, path: Path, timeout: float) -> None:
        self.path, self.timeout = path, timeout

    def __enter__(self) -> None:
        self.handle = open(self.path, "a+")
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                fcntl.flock(self.handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    self.handle.close()
                    raise BuildError(f"another process held {self.path} for more than {self.timeout:.0f} s")
                time.sleep(0.2)

    def __exit__(self, *exc: object) -> None:
        fcntl.flock(self.handle, fcntl.LOCK_UN)
        self.handle.close()


def _compile_in_child(directory: Path, timeout: float, name: str | None = None,
                      sources: tuple[Path, ...] | None = None) -> None:
    """Compile in a child process (killed after ``timeout`` s); BuildError with its last lines on failure."""
    name = name or EXTENSION_NAME
    settings = json.dumps({"name": name, "sources": [str(path) for path in sources or SOURCES],
                           "cflags": list(CFLAGS)})
    command = [sys.executable, "-c", "import json, sys; from pathlib import Path; from denoisers.native import "
               "_torch_load; _torch_load(Path(sys.argv[1]), **json.loads(sys.argv[2]))", str(directory), settings]
    env = dict(os.environ, **{ENVIRONMENT_SWITCH: "1"})
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env,
                                cwd=Path(__file__).resolve().parents[2])
    except subprocess.TimeoutExpired as error:
        raise BuildError(f"build of {name} in {directory} timed out after {timeout:g} s "
                         f"({TIMEOUT_VARIABLE})") from error
    if result.returncode != 0:
        raise BuildError(f"build of {name} in {directory} failed: {result.stderr[-2000:]}")


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
