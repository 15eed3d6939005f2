"""Select the Mitsuba variant once per process.

The LLVM backend needs libLLVM 19 on this platform (LLVM 15 crashes in the JIT with
"Cannot select ... fminimum"), so ``DRJIT_LIBLLVM_PATH`` is pointed at it when unset.
When the LLVM variant cannot be used, the scalar variant is selected with a loud warning:
it is correct but one to two orders of magnitude slower. A CUDA variant that cannot be used is an error.
"""
from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

LLVM19_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so.1",
)
FALLBACK_VARIANT = "scalar_rgb"

_active_variant: str | None = None


class ScalarFallbackWarning(UserWarning):
    """Mitsuba runs in scalar mode: correct but very slow."""


def _point_drjit_at_llvm19() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    for candidate in LLVM19_CANDIDATES:
        if Path(candidate).exists():
            os.environ["DRJIT_LIBLLVM_PATH"] = candidate
            return


def init_mitsuba(variant: str = "llvm_ad_rgb") -> str:
    """Set the Mitsuba variant (idempotent) and return the one actually in use.

    Falls back to ``scalar_rgb`` when ``variant`` is an LLVM variant that cannot initialise.
    """
    global _active_variant
    if _active_variant is not None:
        return _active_variant
    _point_drjit_at_llvm19()
    import mitsuba as mi

    try:
        mi.set_variant(variant)
        if variant.startswith(("llvm", "cuda")):
            import drjit as dr

            # Force the JIT to initialise now so a broken LLVM shows up here, not mid-render.
            dr.eval(mi.Float(1.0) + 1.0)
        _active_variant = variant
    except Exception as exc:  # noqa: BLE001 -- any failure of the backend means fallback
        if variant.startswith("cuda"):
            # compute.device cuda was asked for (or auto found a GPU): a scalar render would be silently slow.
            raise RuntimeError(f"Mitsuba variant {variant!r} is unavailable ({type(exc).__name__}: {exc}); "
                               "set compute.device cpu to render with llvm_ad_rgb") from exc
        message = (
            f"\n{'!' * 78}\nMitsuba variant {variant!r} is unavailable ({type(exc).__name__}: {exc}).\n"
            f"Falling back to {FALLBACK_VARIANT!r}: results are identical in expectation but rendering is\n"
            f"one to two orders of magnitude slower. Install Debian's libllvm19 and set DRJIT_LIBLLVM_PATH\n"
            f"(currently {os.environ.get('DRJIT_LIBLLVM_PATH')!r}).\n{'!' * 78}"
        )
        warnings.warn(message, ScalarFallbackWarning, stacklevel=2)
        print(message, file=sys.stderr)
        mi.set_variant(FALLBACK_VARIANT)
        _active_variant = FALLBACK_VARIANT
    return _active_variant


def is_jit_variant() -> bool:
    """True when the active variant evaluates wavefronts (LLVM/CUDA), False in scalar mode."""
    return _active_variant is not None and not _active_variant.startswith("scalar")


#: Dr.Jit's thread pool is never set below this: with a pool of one thread, Mitsuba 3.9.1 / drjit 1.5.0 never
#: return from OpenEXR I/O (mi.Bitmap reading or writing an .exr blocks on a semaphore; checked on this
#: machine: an environment-map scene rendered with --threads 1 hung for 15 min at 0 % CPU).
MIN_DRJIT_THREADS = 2


def set_render_threads(threads: int) -> int:
    """Set Dr.Jit's thread count to max(threads, MIN_DRJIT_THREADS) (see there why); returns the count set.
    Call after :func:`init_mitsuba`."""
    import drjit as dr

    count = max(int(threads), MIN_DRJIT_THREADS)
    dr.set_thread_count(count)
    return count
