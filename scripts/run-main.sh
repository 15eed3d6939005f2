#!/usr/bin/env bash
# Set up the environment, then run the full workflow locally (default config, 2 cores).
# Extra arguments go to Snakemake, e.g.:
#   bash scripts/run-main.sh scenes                        # one stage target
#   bash scripts/run-main.sh --configfile config/smoke.yaml  # tiny smoke dataset
#   bash scripts/run-main.sh -n                            # dry run
# Outputs go to the config's output_dir (results/, the smoke config results/smoke/); remove them with
#   .venv/bin/python -m denoisers clean --config config/smoke.yaml [--stale] [--dry-run]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/setup.sh
exec .venv/bin/snakemake --profile workflow/profiles/local "$@"
