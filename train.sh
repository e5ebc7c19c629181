#!/usr/bin/env bash
# zk0 quick start: set up .venv if needed, then run a federation with `flwr run`.
set -euo pipefail

usage() {
    cat <<'USAGE'
Usage: ./train.sh [options]

Sets up .venv on first use (finds Python >= 3.12, installs zk0, FFmpeg where possible),
then runs the zk0 Flower app with `flwr run . local --stream` and prints where the
outputs are. With no options: the quick federation (4 simulated SO-100/SO-101 clients,
1 round, 2 local steps, tiny offline SmolVLA on CPU).

Options:
  -m, --mode MODE         simulation mode, a file in configs/federation/:
                          cpu (default: 4 clients, one CPU each), gpu (4 clients share
                          one GPU), gpu-serial (one client at a time holds the whole GPU)
  -r, --run-config STR    run-config overrides, e.g. "num-server-rounds=5 local-steps=20";
                          repeatable; keys are listed in pyproject.toml [tool.flwr.app.config]
  -p, --preset NAME       start from a preset in configs/presets/ (so100: lerobot/smolvla_base
                          on community SO-100/SO-101 datasets; needs the Hub and a GPU)
      --resume RUN        continue the interrupted run folder RUN (outputs/<run>) from its
                          last complete checkpoint; pass the same preset/overrides as before
      --setup-only        set up .venv and the offline assets, then stop
      --docker            run the same command inside the zk0 image (built from ./Dockerfile
                          if missing); outputs/ is mounted, the HF cache lives in volume zk0-cache
      --detached          run in a tmux session named zk0-<time> and return; prints how to
                          attach, follow the log and stop it
      --print             print the command that would run, and stop
  -h, --help              show this help
USAGE
}

mode="cpu"
setup_only=0
docker=0
detached=0
print_only=0
preset=()
overrides=()
inner=() # the arguments again, less --docker/--detached/--print: what a wrapped train.sh gets
ROOT="$(cd "$(dirname "$0")" && pwd)"
while [ $# -gt 0 ]; do
    case "$1" in
    --docker) docker=1; shift; continue ;;
    --detached) detached=1; shift; continue ;;
    --print) print_only=1; shift; continue ;;
    esac
    case "$1" in
    -m | --mode | -r | --run-config | -p | --preset | --resume) [ $# -ge 2 ] && inner+=("$1" "$2") ;;
    *) inner+=("$1") ;;
    esac
    case "$1" in
    -m | --mode) [ $# -ge 2 ] || { echo "train.sh: $1 needs a value: cpu, gpu or gpu-serial." >&2; exit 2; }
        mode="$2"; shift 2 ;;
    -r | --run-config) [ $# -ge 2 ] || { echo "train.sh: $1 needs a value such as \"num-server-rounds=3\"." >&2; exit 2; }
        overrides+=(--run-config "$2"); shift 2 ;;
    -p | --preset) [ $# -ge 2 ] || { echo "train.sh: $1 needs a preset name such as so100." >&2; exit 2; }
        preset=(--preset "$2"); shift 2 ;;
    --resume) [ $# -ge 2 ] || { echo "train.sh: $1 needs a run folder such as outputs/2026-01-01_12-00-00." >&2; exit 2; }
        [ -d "$2" ] || { echo "train.sh: --resume got '$2', which is not a directory; expected a run folder under outputs/." >&2; exit 2; }
        overrides+=(--run-config "resume-from='$(cd "$2" && pwd)'"); shift 2 ;;
    --setup-only) setup_only=1; shift ;;
    -h | --help) usage; exit 0 ;;
    *) echo "train.sh: unknown option '$1'; see ./train.sh --help." >&2; exit 2 ;;
    esac
done
case "$mode" in
cpu | gpu | gpu-serial) ;;
*) echo "train.sh: unknown mode '$mode'; expected cpu, gpu or gpu-serial." >&2; exit 2 ;;
esac

# Run (or print) a wrapped command: the same train.sh inside tmux or inside the image.
launch() {
    if [ "$print_only" = 1 ]; then
        printf '%q ' "$@"
        echo
        exit 0
    fi
    "$@"
}

if [ "$detached" = 1 ]; then
    command -v tmux >/dev/null || [ "$print_only" = 1 ] || { echo "train.sh: --detached needs tmux; install it (e.g. apt-get install tmux)." >&2; exit 2; }
    session="zk0-$(date +%Y%m%d-%H%M%S)"
    mkdir -p "$ROOT/outputs"
    again=("$ROOT/train.sh" "${inner[@]}")
    [ "$docker" = 1 ] && again+=(--docker)
    launch tmux new-session -d -s "$session" "$(printf '%q ' "${again[@]}") 2>&1 | tee $ROOT/outputs/$session.log"
    echo "Started tmux session $session."
    echo "  attach:  tmux attach -t $session   (detach again with Ctrl-b d)"
    echo "  log:     tail -f outputs/$session.log"
    echo "  stop:    tmux kill-session -t $session"
    exit 0
fi

if [ "$docker" = 1 ]; then
    run=(docker run --rm --shm-size=8g --user "$(id -u):$(id -g)"
        -v "$ROOT/outputs:/workspace/outputs" -v zk0-cache:/home/zk0/.cache)
    [ "$mode" = cpu ] || run+=(--gpus all)
    [ -n "${HF_TOKEN:-}" ] && run+=(-e HF_TOKEN)
    [ -n "${WANDB_API_KEY:-}" ] && run+=(-e WANDB_API_KEY)
    if [ "$print_only" = 0 ]; then
        command -v docker >/dev/null || { echo "train.sh: --docker needs Docker; install it or run without --docker." >&2; exit 2; }
        mkdir -p "$ROOT/outputs"
        docker image inspect zk0 >/dev/null 2>&1 || docker build -t zk0 "$ROOT"
    fi
    launch "${run[@]}" zk0 ./train.sh "${inner[@]}"
fi

source "$(dirname "$0")/scripts/setup.sh"
zk0_setup
cd "$ZK0_ROOT"
# One validated override string (preset + output folder + the user's overrides, later wins).
run_config="$(zk0 check --print "${preset[@]}" --run-config "output-dir='$ZK0_ROOT/outputs'" "${overrides[@]}")" || exit 2
flwr_command=(flwr run . local --stream --federation-config "configs/federation/$mode.toml" --run-config "$run_config")
[ "$print_only" = 0 ] || launch "${flwr_command[@]}"
zk0 assets >/dev/null
if [ "$setup_only" = 1 ]; then
    zk0_log "Set-up complete; run ./train.sh to start the quick federation."
    exit 0
fi

# `flwr run` starts a local SuperLink in the background when none is running; stop the one
# it starts for this run so nothing lingers after the script.
port="${FLWR_LOCAL_SUPERLINK_HTTP_API_PORT:-39091}"
if ! pgrep -f "flower-superlink.*--port $port" >/dev/null; then
    trap 'pkill -f "flower-superlink.*--port $port" || true' EXIT
fi

zk0_log "Starting the federation (mode: $mode)..."
log="$(mktemp)"
"${flwr_command[@]}" 2>&1 | tee "$log"
# `flwr run --stream` exits 0 even when the ServerApp fails; Flower prints an exit code then.
if grep -q "Exit Code: [1-9]" "$log"; then
    rm -f "$log"
    zk0_log "The federation failed; the reason is in the log above."
    exit 1
fi
rm -f "$log"
latest="$(ls -td "$ZK0_ROOT"/outputs/*/ 2>/dev/null | head -n 1)"
zk0_log "Outputs: ${latest:-none written (see the log above)}"
