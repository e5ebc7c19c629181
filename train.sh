#!/usr/bin/env bash
# zk0 quick start: set up .venv if needed, then run a federation with `flwr run`.
set -euo pipefail

usage() {
    cat <<'USAGE'
Usage: ./train.sh [options]

Sets up .venv on first use (finds Python >= 3.12, installs zk0, FFmpeg where possible),
then runs the zk0 Flower app with `flwr run . local --stream`: a header, one line per round
and where the outputs and the run's report.html are. With no options: the quick federation (4 simulated SO-100/SO-101 clients,
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
      --verbose           show everything Flower, Ray and the libraries print (by default the
                          console shows zk0's own lines; the rest is in the run's logs)
  -h, --help              show this help
USAGE
}

mode="cpu"
setup_only=0
docker=0
detached=0
print_only=0
verbose="${ZK0_VERBOSE:-0}"
[ "$verbose" = 0 ] || verbose=1
preset=()
overrides=()
inner=() # the arguments again, less --docker/--detached/--print: what a wrapped train.sh gets
ROOT="$(cd "$(dirname "$0")" && pwd)"
while [ $# -gt 0 ]; do
    case "$1" in
    --docker) docker=1; shift; continue ;;
    --detached) detached=1; shift; continue ;;
    --print) print_only=1; shift; continue ;;
    --verbose) verbose=1; inner+=("$1"); shift; continue ;;
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

if [ "$detached" = 1 ] && [ "$docker" = 0 ]; then
    command -v tmux >/dev/null || [ "$print_only" = 1 ] || { echo "train.sh: --detached needs tmux; install it (e.g. apt-get install tmux)." >&2; exit 2; }
    session="zk0-$(date +%Y%m%d-%H%M%S)"
    mkdir -p "$ROOT/outputs"
    again=("$ROOT/train.sh" "${inner[@]}")
    launch tmux new-session -d -s "$session" "$(printf '%q ' "${again[@]}") 2>&1 | tee $ROOT/outputs/$session.log"
    echo "Started tmux session $session."
    echo "  attach:  tmux attach -t $session   (detach again with Ctrl-b d)"
    echo "  log:     tail -f outputs/$session.log"
    echo "  stop:    tmux kill-session -t $session"
    exit 0
fi

# Docker when its daemon answers, else podman (ZK0_ENGINE chooses); nothing when neither is here.
container_engine() {
    if [ -n "${ZK0_ENGINE:-}" ]; then echo "$ZK0_ENGINE"; return 0; fi
    if command -v docker >/dev/null && docker info >/dev/null 2>&1; then echo docker; return 0; fi
    if command -v podman >/dev/null; then echo podman; return 0; fi
    command -v docker >/dev/null && { echo docker; return 0; } # installed, daemon not running: its own message says so
    return 1
}

if [ "$docker" = 1 ]; then
    case "${ZK0_ENGINE:-docker}" in
    docker | podman) ;;
    *) echo "train.sh: ZK0_ENGINE is '$ZK0_ENGINE'; expected docker or podman." >&2; exit 2 ;;
    esac
    engine="$(container_engine)" || {
        [ "$print_only" = 1 ] && engine=docker || {
            echo "train.sh: --docker needs Docker or podman; install one (e.g. apt-get install podman) or run without --docker." >&2
            exit 2
        }
    }
    # The image's outputs/ is the host's: a run folder to resume is named by its place under it.
    for ((i = 0; i < ${#inner[@]}; i++)); do
        [ "${inner[$i]}" = --resume ] || continue
        resume="$(cd "${inner[$((i + 1))]}" && pwd)"
        case "$resume" in
        "$ROOT/outputs/"*) inner[$((i + 1))]="outputs/${resume#"$ROOT/outputs/"}" ;;
        *) echo "train.sh: --docker resumes runs under $ROOT/outputs/ only (that folder is what the container sees); got '$resume'." >&2; exit 2 ;;
        esac
    done
    # ZK0_HOST_OUTPUTS: where the container's outputs/ is on the host, for the paths it prints.
    run=("$engine" run --rm --shm-size=8g --user "$(id -u):$(id -g)" -e "ZK0_HOST_OUTPUTS=$ROOT/outputs"
        -v "$ROOT/outputs:/workspace/outputs" -v zk0-cache:/home/zk0/.cache)
    # Rootless podman maps the container's uids into the user's own range; keep-id makes the
    # host user the same uid inside, so outputs/ stays theirs.
    [ "$engine" = podman ] && [ "$(id -u)" != 0 ] && run+=(--userns=keep-id)
    if [ "$mode" != cpu ]; then
        if [ "$engine" = podman ]; then run+=(--device nvidia.com/gpu=all); else run+=(--gpus all); fi
    fi
    # A thread limit the user set reaches the run (two runs sharing a machine must not oversubscribe it).
    [ -n "${OMP_NUM_THREADS:-}" ] && run+=(-e OMP_NUM_THREADS)
    [ -n "${HF_TOKEN:-}" ] && run+=(-e HF_TOKEN)
    [ -n "${WANDB_API_KEY:-}" ] && run+=(-e WANDB_API_KEY)
    if [ "$detached" = 1 ]; then
        # A detached container needs no tmux on the host: the engine keeps it and its log.
        session="zk0-$(date +%Y%m%d-%H%M%S)"
        run=("${run[@]:0:2}" -d --name "$session" "${run[@]:2}")
    fi
    if [ "$print_only" = 0 ]; then
        # podman as root gives each container ulimits above the machine's (nofile 1048576); where even
        # root may not raise them (a sandbox, a container), runc starts nothing ("error setting rlimit"),
        # so its containers keep this machine's limits (scripts/setup.sh's containers.conf).
        if [ "$engine" = podman ] && [ -z "${CONTAINERS_CONF:-}" ] && [ "$(id -u)" = 0 ] && ! (ulimit -Hn 1048576) 2>/dev/null; then
            source "$ROOT/scripts/setup.sh"
            CONTAINERS_CONF="$(zk0_containers_conf)" && export CONTAINERS_CONF
            zk0_log "This machine lets no one raise its ulimits, so podman's containers keep its own (CONTAINERS_CONF=$CONTAINERS_CONF)."
        fi
        mkdir -p "$ROOT/outputs"
        if ! "$engine" image inspect zk0 >/dev/null 2>&1; then
            build=("$engine" build -t zk0)
            [ "$engine" = podman ] && build+=(--format docker) # keeps the Dockerfile's SHELL
            "${build[@]}" "$ROOT" || { echo "train.sh: building the zk0 image with $engine failed; see its message above." >&2; exit 1; }
        fi
    fi
    command=("${run[@]}" zk0 ./train.sh "${inner[@]}")
    [ "$print_only" = 0 ] || launch "${command[@]}"
    [ "$detached" = 1 ] || exec "${command[@]}"
    "${command[@]}" >/dev/null || exit 1 # it prints the container's id
    echo "Started container $session."
    echo "  log:     $engine logs -f $session   (all of it is kept as outputs/<run>/console.log)"
    echo "  stop:    $engine stop $session   (stops the run; what it wrote stays in outputs/)"
    exit 0
fi

source "$(dirname "$0")/scripts/setup.sh"
zk0_setup
cd "$ZK0_ROOT"
# One validated override string (preset + output folder + the user's overrides, later wins), and the
# mode's federation config with the clients that train at once sized to the memory available.
checked="$(zk0 check --print "${preset[@]}" --run-config "output-dir='$ZK0_ROOT/outputs'" "${overrides[@]}" \
    --federation-config "configs/federation/$mode.toml")" || exit 2
run_config="${checked%%$'\n'*}"
federation="${checked#*$'\n'}"
flwr_command=(flwr run . local --stream --federation-config "$federation" --run-config "$run_config")
[ "$print_only" = 0 ] || launch "${flwr_command[@]}"
export ZK0_VERBOSE="$verbose" # the ServerApp and ClientApps read it (through the SuperLink flwr run starts)
zk0 assets --run-config "$run_config" >/dev/null
if [ "$setup_only" = 1 ]; then
    zk0_log "Set-up complete; run ./train.sh to start the quick federation."
    exit 0
fi

# `flwr run` starts a local SuperLink in the background when none is running; stop the one
# it starts for this run (and everything under it: the simulation, Ray) so nothing lingers.
port="${FLWR_LOCAL_SUPERLINK_HTTP_API_PORT:-39091}"
own_superlink=0
pgrep -f "flower-superlink.*--port $port" >/dev/null || own_superlink=1
# The SuperLink and every process under it (the simulation, Ray's), listed before any of them is
# signalled: once the simulation exits, Ray's processes are no longer under the SuperLink.
superlink_tree() {
    [ "$own_superlink" = 1 ] || return 0
    # One look at the process table: a pgrep per process took seconds on a loaded machine, long
    # enough for a stopped run's short rounds to go on. The pattern travels in the environment so
    # that this awk does not match itself.
    ps -e -ww -o pid=,ppid=,args= | SUPERLINK="flower-superlink.*--port $port" awk '
        { parent[$1] = $2; pid = $1; $1 = $2 = ""; if ($0 ~ ENVIRON["SUPERLINK"]) root[pid] = 1 }
        END {
            for (pid in parent) {
                for (up = pid; (up in parent) && !(up in root); up = parent[up]) {}
                if (up in root) print pid
            }
        }'
}
stop_processes() {
    [ $# -gt 0 ] || return 0
    kill "$@" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$@" 2>/dev/null || return 0; sleep 0.2; done
    kill -9 "$@" 2>/dev/null || true
}
stop_superlink() {
    stop_processes $(superlink_tree)
}
trap stop_superlink EXIT

# Ctrl-C (or SIGTERM) stops the run itself, not only this script: `flwr stop`, then the
# private SuperLink; what the run wrote stays, and the command that continues it is printed.
interrupted() {
    trap - INT TERM
    # The ServerApp's process first and at once (it writes nothing once signalled: zk0.federation.stopping),
    # then Flower's record of the run, then everything else.
    local tree run_id run_dir last written again=() shown=""
    tree="$(superlink_tree)"
    pkill -TERM -f "flwr-(simulation|serverapp) --runtime-api-address [^ ]*:$port( |\$)" || true
    echo >&2
    run_id="$(grep -o 'Successfully started run [0-9]*' "$log" | grep -o '[0-9]*$' | head -n 1 || true)"
    zk0_log "Stopping run ${run_id:-(not started yet)}..."
    [ -z "$run_id" ] || flwr stop "$run_id" local >/dev/null 2>&1 || true
    kill "$flwr_pid" 2>/dev/null || true
    stop_processes $tree
    trap - EXIT
    run_dir="$(run_folder)"
    keep_log "$run_dir"
    if [ -z "$run_dir" ]; then
        rm -f "$log"
        zk0_log "Stopped before the run wrote anything."
        exit 130
    fi
    last="$(ls -d "$run_dir"/models/checkpoint_round_*/model.safetensors 2>/dev/null | sort -V | tail -n 1 || true)"
    written="$(ls "$run_dir"/server/round_*.json 2>/dev/null | sed 's/.*round_\([0-9]*\)\.json/\1/' | sort -n | tail -n 1 || true)"
    zk0_log "Stopped in round $((${written:-0} + 1)) (rounds up to ${written:-0} are written). Everything written so far is in $(on_host "$run_dir")"
    if [ -z "$last" ]; then
        zk0_log "No checkpoint was complete yet, so there is nothing to resume; start again with ./train.sh."
        exit 130
    fi
    zk0_log "Last complete checkpoint: $(on_host "$(dirname "$last")"). Continue the run with:"
    for ((i = 0; i < ${#inner[@]}; i++)); do
        if [ "${inner[$i]}" = --resume ]; then i=$((i + 1)); else again+=("${inner[$i]}"); fi
    done
    [ -z "${ZK0_HOST_OUTPUTS:-}" ] || again+=(--docker)
    [ ${#again[@]} -eq 0 ] || shown="$(printf ' %q' "${again[@]}")"
    printf '  ./train.sh%s --resume %q\n' "$shown" "$(on_host "$run_dir")" >&2
    exit 130
}

# A path as the user finds it: in a container started by ./train.sh --docker, the host's.
on_host() {
    case "${ZK0_HOST_OUTPUTS:-}:$1" in
    ?*:"$ZK0_ROOT/outputs/"*) echo "$ZK0_HOST_OUTPUTS/${1#"$ZK0_ROOT/outputs/"}" ;;
    *) echo "$1" ;;
    esac
}

# The run's folder, as the ServerApp names it in the log ("Writing to ...", "Resuming ... after").
run_folder() {
    sed -n -e 's/.*Writing to \(.*\)$/\1/p' -e 's/.*Resuming \(.*\) after round .*/\1/p' "$log" | head -n 1
}

# Everything `flwr run` printed goes with the run, as console.log (the full records of the server
# and of each client are in server/server.log and clients/client_<i>/client.log).
keep_log() {
    if [ -n "$1" ] && [ -d "$1" ]; then mv "$log" "$1/console.log"; fi
}

# What a person reads: the ServerApp's own lines (the header, a line per round, warnings and
# refusals, the summary), without colours. Simulated clients' lines (Ray prefixes them with
# "(ClientAppActor pid=...)") stay in their logs: the server reports each refusal, naming the
# client. --verbose shows every line.
# In a container started by ./train.sh --docker, the paths it prints are the host's (on_host).
for_a_person() {
    local host=(-e '')
    [ -z "${ZK0_HOST_OUTPUTS:-}" ] || host=(-e "s|$ZK0_ROOT/outputs/|$ZK0_HOST_OUTPUTS/|g")
    if [ "$verbose" = 1 ]; then
        sed -u "${host[@]}"
    else
        sed -u -n -E -e 's/\x1b\[[0-9;]*m//g' "${host[@]}" -e '/^\([A-Za-z]+ pid=[0-9]+\) /d' -e '/^(\[zk0\] |zk0: )/p'
    fi
}

zk0_log "Starting the federation (mode: $mode)..."
log="$(mktemp)"
# In the background, so that a signal reaches `interrupted` at once instead of after the run.
# The console filter ignores Ctrl-C (the terminal signals the whole group): it prints to the end.
"${flwr_command[@]}" > >(trap '' INT; tee "$log" | for_a_person) 2>&1 &
flwr_pid=$!
trap interrupted INT TERM
wait "$flwr_pid" || true
trap - INT TERM
wait # for the console filter to print its last lines
outputs="$(run_folder)"
# `flwr run --stream` exits 0 even when the ServerApp fails; Flower prints an exit code then.
if grep -q "Exit Code: [1-9]" "$log"; then
    keep_log "$outputs"
    if [ "$verbose" = 1 ] || [ -z "$outputs" ]; then
        zk0_log "The federation failed; the reason is in the log above."
    else
        zk0_log "The federation failed (above); the full record is in $outputs/server/server.log"
    fi
    exit 1
fi
keep_log "$outputs"
if [ -n "$outputs" ]; then zk0_log "Outputs: $(on_host "$outputs")"; else zk0_log "Outputs: none written; what flwr run printed is in $log"; fi
