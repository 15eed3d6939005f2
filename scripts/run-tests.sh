#!/usr/bin/env bash
# Set up the environment, then run the test suite. Extra arguments go to pytest, e.g.
#   bash scripts/run-tests.sh -m "not slow"   or   bash scripts/run-tests.sh tests/test_config.py
# pytest exits non-zero (5) when no test ran, so an empty run fails too.
# The tests run in one pytest-xdist worker per core, a test file per worker (module fixtures such as the smoke-DAG
# run are built once); `-n 0` after the script's name runs them in this process.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/setup.sh
exec .venv/bin/python -m pytest -q -n auto --dist loadfile "$@"
