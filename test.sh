#!/usr/bin/env bash
# Set up .venv (as ./train.sh does) and run the test suite in parallel, offline.
# Extra arguments go to pytest, e.g. ./test.sh -k config
set -euo pipefail
source "$(dirname "$0")/scripts/setup.sh"
zk0_setup
cd "$ZK0_ROOT"
export HF_HUB_OFFLINE=1
exec python -m pytest -n auto --dist worksteal "$@"
