#!/usr/bin/env bash
# Set up .venv (as ./train.sh does) and run the test suite in parallel, offline, with a
# temporary directory and a Flower home that start empty, as a new machine's do (an earlier
# run's leftovers once hid a fault that every new machine showed). Both are removed afterwards.
#   ./test.sh          the whole suite (~20 min on 2 cores, after the set-up and the image build;
#                      each test's allowance in seconds: tests/README.md)
#   ./test.sh --fast   all but the federations, deployments and other slow tests (markers
#                      in pyproject.toml; ~2 min)
# Other arguments go to pytest, e.g. ./test.sh --fast -k config
set -euo pipefail
source "$(dirname "$0")/scripts/setup.sh"
args=()
for arg in "$@"; do
    if [ "$arg" = --fast ]; then args+=(-m "not e2e and not deployment and not slow and not container"); else args+=("$arg"); fi
done
# Short names: Ray's and the warm worker's Unix sockets live below TMPDIR (108 bytes a path).
fresh_tmp="$(mktemp -d)"
fresh_home="$(mktemp -d)"
trap 'rm -rf "$fresh_tmp" "$fresh_home"' EXIT
export TMPDIR="$fresh_tmp" FLWR_HOME="$fresh_home"
zk0_setup
zk0_ensure_chromium
# The whole suite runs the image: build it first (or find it current), outside pytest's time.
# (Given arguments, the container test builds it itself when it is among the tests chosen.)
if [ $# -eq 0 ] && zk0_ensure_podman; then
    zk0_log "Building the zk0 image with podman (first time on a machine: minutes, most of it pip fetching torch; then seconds)..."
    CONTAINERS_CONF="$(zk0_containers_conf)" zk0_ensure_image >"$fresh_tmp/image-build.log" 2>&1 ||
        zk0_log "Building the image failed; the container test says why."
fi
cd "$ZK0_ROOT"
export HF_HUB_OFFLINE=1
python -m pytest -n auto --dist worksteal "${args[@]}"
