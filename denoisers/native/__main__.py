"""``python -m denoisers.native``: build the native kernels now (scripts/setup.sh runs it) and print the
backend the filters will use and where the build lives."""
from __future__ import annotations

import logging
import sys

from denoisers import native

if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")
    backend = native.backend()
    print(f"native kernels: {backend} (build directory {native.build_directory()})")
    kernels = "native" if native.load_kernels() is not None else "torch"
    print(f"per-pixel kernel application (denoisers.kernels): {kernels}")
    affinity = "native" if native.load_affinity() is not None else "torch"
    print(f"affinity kernels (denoisers.affinity): {affinity}")
    sys.exit(0)
