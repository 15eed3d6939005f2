#!/usr/bin/env bash
# Idempotent environment set-up; run it (`bash scripts/setup.sh`) or source it from another script
# (scripts/run-main.sh, scripts/run-tests.sh), which then also gets the exported variables:
#   1. the LLVM 19 shared library for Mitsuba's llvm_ad_rgb variant (Debian package libllvm19),
#   2. a Python 3.11 virtual environment in .venv,
#   3. the project installed editable with its test extras (skipped while pyproject.toml is unchanged),
#   4. the native filter kernels (python -m denoisers.native),
#   5. DRJIT_LIBLLVM_PATH, and .venv/bin first on PATH (Snakemake's `python -m scenegen` needs it).
# Without LLVM 19, Mitsuba falls back to the much slower scalar_rgb variant with a warning.

if [[ "${BASH_SOURCE[0]}" == "$0" ]]; then
    set -euo pipefail
fi

setup_main() {
    local repo_root venv python_bin llvm_lib sudo pyproject_hash stamp torch_pin
    repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
    venv="$repo_root/.venv"
    llvm_lib="/usr/lib/$(uname -m)-linux-gnu/libLLVM.so.19.1"

    # 1. LLVM 19 (LLVM 15 crashes Dr.Jit 1.5; other versions are untested).
    if [[ -e "$llvm_lib" ]]; then
        echo "[setup] LLVM 19 found: $llvm_lib" >&2
    elif command -v apt-get >/dev/null 2>&1; then
        sudo=""
        if [[ "$(id -u)" != "0" ]]; then
            sudo="sudo"
        fi
        echo "[setup] installing libllvm19 with apt-get" >&2
        $sudo apt-get update -qq || return 1
        $sudo apt-get install -y -qq libllvm19 || return 1
    else
        echo "[setup] WARNING: $llvm_lib missing and apt-get unavailable; Mitsuba will fall back to scalar_rgb" >&2
    fi

    # 2. Virtual environment.
    if [[ ! -x "$venv/bin/python" ]]; then
        python_bin="$(command -v python3.11 || command -v python3 || true)"
        if [[ -z "$python_bin" ]] || ! "$python_bin" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
            echo "[setup] ERROR: Python 3.11 is required (python3.11 or python3 on PATH)" >&2
            return 1
        fi
        echo "[setup] creating $venv with $python_bin" >&2
        "$python_bin" -m venv "$venv" || return 1
    else
        echo "[setup] virtual environment found: $venv" >&2
    fi

    # 3. Project install, keyed on the content of pyproject.toml.
    pyproject_hash="$(sha256sum "$repo_root/pyproject.toml" | cut -d' ' -f1)"
    stamp="$venv/.installed-$pyproject_hash"
    if [[ -e "$stamp" ]]; then
        echo "[setup] dependencies up to date (pyproject.toml unchanged)" >&2
    else
        # Install the pinned torch first and on its own, so pip takes the CPU wheel available
        # locally instead of resolving a different (CUDA) build as a dependency.
        torch_pin="$(grep -o '"torch==[^"]*"' "$repo_root/pyproject.toml" | tr -d '"' || true)"
        torch_pin="${torch_pin:-torch==2.13.0}"
        echo "[setup] pip install $torch_pin" >&2
        "$venv/bin/python" -m pip install --quiet "$torch_pin" || return 1
        echo "[setup] pip install -e '.[test]'" >&2
        "$venv/bin/python" -m pip install --quiet -e "$repo_root[test]" || return 1
        rm -f "$venv"/.installed-*
        touch "$stamp"
    fi

    # 4. The native filter kernels, built once into this checkout (denoisers/native/_build), so that no
    #    job compiles; quick when already built. A failed build only means the torch fallback is used.
    "$venv/bin/python" -m denoisers.native >&2 || echo "[setup] native kernels not built; filters use torch" >&2

    # 5. Environment for Mitsuba / Dr.Jit and for the workflow's shell commands.
    if [[ -e "$llvm_lib" ]]; then
        export DRJIT_LIBLLVM_PATH="$llvm_lib"
        echo "[setup] DRJIT_LIBLLVM_PATH=$DRJIT_LIBLLVM_PATH" >&2
    fi
    export VIRTUAL_ENV="$venv"
    case ":$PATH:" in
        *":$venv/bin:"*) ;;
        *) export PATH="$venv/bin:$PATH" ;;
    esac
    return 0
}

if ! setup_main; then
    echo "[setup] FAILED" >&2
    if [[ "${BASH_SOURCE[0]}" == "$0" ]]; then
        exit 1
    fi
    return 1
fi
