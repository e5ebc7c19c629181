#!/usr/bin/env bash
# Shared set-up for ./train.sh and ./test.sh (sourced, not run): finds a Python >= 3.12,
# creates .venv if missing (a link to a virtual environment outside the project, see
# zk0_venv_home), installs the project when pyproject.toml changed, installs
# FFmpeg where it can (torchcodec needs its shared libraries), and exports the
# environment the Flower CLI and the apps need. Prints one sentence and returns non-zero
# on failure.

ZK0_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ZK0_VENV="$ZK0_ROOT/.venv"

# Where a new .venv really lives. `flwr run` packs the app by walking every file under the
# project folder and filtering afterwards; it does not enter linked folders. A virtual
# environment's ~55,000 files made that walk 20 s of every run, so .venv links to a folder in
# the zk0 cache, one per project folder. (An existing .venv folder is kept as it is.)
zk0_venv_home() {
    local cache="${ZK0_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/zk0}"
    printf '%s/venvs/%s\n' "$cache" "$(printf '%s' "$ZK0_ROOT" | sha256sum | cut -c1-16)"
}

zk0_log() { printf '[zk0] %s\n' "$*" >&2; }

# Print the path of a Python >= 3.12, or nothing.
zk0_find_python() {
    local candidate
    for candidate in "${ZK0_PYTHON:-}" python3.13 python3.12 python3; do
        [ -n "$candidate" ] || continue
        if command -v "$candidate" >/dev/null 2>&1 &&
            "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
            command -v "$candidate"
            return 0
        fi
    done
    if command -v uv >/dev/null 2>&1; then
        candidate="$(uv python find '>=3.12' 2>/dev/null)" && [ -n "$candidate" ] && { echo "$candidate"; return 0; }
    fi
    for candidate in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.1[2-9]*/bin/python3 /root/.pyenv/versions/3.1[2-9]*/bin/python3; do
        if [ -x "$candidate" ]; then
            echo "$candidate"
            return 0
        fi
    done
    return 1
}

# As root with apt-get: log why ($1), install the Debian packages named after it, quietly.
# Fails (for the caller's one sentence) where it cannot.
zk0_apt_install() {
    local why="$1"
    shift
    [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 || return 1
    zk0_log "$why"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"; } >/dev/null 2>&1
}

zk0_ensure_ffmpeg() {
    # grep reads all of ldconfig's output: with -q it stops early, ldconfig dies of SIGPIPE, and
    # under pipefail that read as "not installed" now and then (an apt-get run for nothing).
    if ldconfig -p 2>/dev/null | grep 'libavutil\.so' >/dev/null; then
        return 0
    fi
    zk0_apt_install "Installing FFmpeg (torchcodec decodes video with it)..." ffmpeg && return 0
    zk0_log "FFmpeg libraries not found and not installable here; lerobot will decode video with PyAV (install 'ffmpeg' for torchcodec)."
}

# MuJoCo renders the simulator's cameras headless through EGL (MUJOCO_GL=egl, zk0.sim), or OSMesa.
zk0_ensure_gl() {
    if ldconfig -p 2>/dev/null | grep -E 'libEGL\.so|libOSMesa\.so' >/dev/null; then
        return 0
    fi
    zk0_apt_install "Installing EGL and OSMesa (MuJoCo renders the simulator's cameras with them)..." libegl1 libgl1 libosmesa6 && return 0
    zk0_log "No EGL or OSMesa library found and not installable here; the simulator (zk0.sim) cannot render until 'libegl1' or 'libosmesa6' is installed."
}

# The report's browser test (tests/test_report.py) renders report.html in headless Chromium;
# only ./test.sh asks for it (in CI its absence where this could install it fails that test).
zk0_ensure_chromium() {
    command -v chromium >/dev/null 2>&1 && return 0
    zk0_apt_install "Installing Chromium (the report's browser test renders report.html in it)..." chromium && return 0
    zk0_log "Chromium not found and not installable here; the report's browser test is skipped."
}

# The container test (tests/test_container.py) builds the image with podman and debootstrap; only
# ./test.sh asks for them (in CI their absence where this could install them fails that test).
zk0_ensure_podman() {
    command -v podman >/dev/null 2>&1 && command -v debootstrap >/dev/null 2>&1 && return 0
    zk0_apt_install "Installing podman and debootstrap (the container test builds and runs the zk0 image)..." podman runc debootstrap && return 0
    zk0_log "podman or debootstrap not found and not installable here; the container test is skipped."
    return 1
}

# Print the path of a containers.conf for podman on this machine (CONTAINERS_CONF): runc, since
# crun refuses cgroups in hybrid mode, and no default rlimits, which some sandboxes refuse.
zk0_containers_conf() {
    local conf="${ZK0_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/zk0}/containers.conf"
    mkdir -p "$(dirname "$conf")"
    printf '[containers]\ndefault_ulimits = []\n\n[engine]\nruntime = "runc"\n' >"$conf"
    echo "$conf"
}

# Build the zk0 image with podman from a Debian base made here (no registry needed for the
# base; pip reaches PyPI, with this machine's CA bundle where pip's `cert` setting names one).
# Both stay in podman's store: the base is made once per machine, and after a change to zk0's
# code only the image's last layer is rebuilt.
zk0_ensure_image() {
    local base=localhost/zk0-base-trixie dir
    if ! podman image exists "$base"; then
        zk0_log "Making a Debian trixie base image with debootstrap (once per machine)..."
        dir="$(mktemp -d)"
        debootstrap --variant=minbase trixie "$dir" >/dev/null &&
            tar -C "$dir" -c . | podman import - "$base" >/dev/null || {
            rm -rf "$dir"
            zk0_log "Making the base image failed; see debootstrap's or podman's message above."
            return 1
        }
        rm -rf "$dir"
    fi
    # An image labelled with this folder's build context is current: a second `podman build`,
    # even one its cache answers, walks the context again (and once spun both cores for minutes).
    [ "$(podman image inspect zk0 --format '{{ index .Labels "zk0.context" }}' 2>/dev/null)" = "$(zk0_context_hash "$ZK0_ROOT")" ] ||
        zk0_build_image "$ZK0_ROOT" zk0
}

# A digest of what `podman build` of the project folder $1 copies: its files that git does not
# ignore (.dockerignore leaves out no more of them than git does, besides deploy's party folders).
zk0_context_hash() {
    (cd "$1" && git ls-files -z -c -o --exclude-standard -- . ':!deploy/*/' 2>/dev/null | sort -z | xargs -0 -r sha256sum | sha256sum | cut -c1-16)
}

# podman build of the project folder $1 as image $2, on the base zk0_ensure_image makes, labelled
# with its context's digest.
zk0_build_image() {
    local cert build=(podman build --format docker --network host --build-arg BASE=localhost/zk0-base-trixie -t "$2")
    build+=(--label "zk0.context=$(zk0_context_hash "$1")")
    cert="${PIP_CERT:-$("$ZK0_VENV/bin/python" -m pip config list 2>/dev/null | sed -n "s/^[^=]*\.cert='\(.*\)'\$/\1/p" | head -n 1)}"
    [ -z "$cert" ] || build+=(-v "$cert:/etc/zk0-pip-cert.pem:ro" --build-arg PIP_CERT=/etc/zk0-pip-cert.pem)
    "${build[@]}" "$1"
}

# zk0's simulator as a lerobot env plugin (lerobot imports every lerobot_env_* distribution).
ZK0_ENV_PLUGIN=plugins/lerobot_env_zk0

# What the installed .venv was made from: both projects' pyproject.toml (the Dockerfile writes the same).
zk0_install_stamp() {
    cat "$1/pyproject.toml" "$1/$ZK0_ENV_PLUGIN/pyproject.toml" | sha256sum | cut -d' ' -f1
}

zk0_ensure_venv() {
    local python stamp want home
    if [ ! -x "$ZK0_VENV/bin/python" ]; then
        python="$(zk0_find_python)" || {
            zk0_log "No Python >= 3.12 found (looked for python3.13/python3.12/python3 on PATH, uv, and pyenv versions); install one or set ZK0_PYTHON."
            return 1
        }
        home="$(zk0_venv_home)"
        zk0_log "Creating .venv with $python (in $home, linked)"
        rm -rf "$ZK0_VENV" "$home"  # a dangling link, or a half-made environment
        mkdir -p "$(dirname "$home")" &&
            "$python" -m venv "$home" &&
            ln -s "$home" "$ZK0_VENV" || { zk0_log "Could not create a virtual environment in $home with $python."; return 1; }
    fi
    stamp="$ZK0_VENV/.zk0-installed"
    want="$(zk0_install_stamp "$ZK0_ROOT")"
    if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
        zk0_log "Installing zk0 and its dependencies into .venv (first time: a few minutes)..."
        if ! "$ZK0_VENV/bin/python" -m pip install -q --disable-pip-version-check -e "$ZK0_ROOT[test]" \
            -e "$ZK0_ROOT/$ZK0_ENV_PLUGIN"; then
            zk0_log "Installing the project into .venv failed; see pip's message above."
            return 1
        fi
        echo "$want" >"$stamp"
    fi
}

zk0_export_env() {
    export PATH="$ZK0_VENV/bin:$PATH"
    export FLWR_HOME="${FLWR_HOME:-$ZK0_ROOT/.flwr}"
    mkdir -p "$FLWR_HOME"
    cp "$ZK0_ROOT/configs/flower.toml" "$FLWR_HOME/config.toml"  # the project owns this Flower config
    # The SuperLink would otherwise `uv sync` the app's dependencies into a fresh env every run.
    export FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION=1
    export SVT_LOG="${SVT_LOG:-1}"
    # MuJoCo picks its GL back end when first imported; lerobot's commands import the SO-101 model's
    # plugin (which loads MuJoCo) before zk0's, so say EGL here for lerobot-eval on a headless machine.
    export MUJOCO_GL="${MUJOCO_GL:-egl}"
}

zk0_setup() {
    zk0_ensure_ffmpeg
    zk0_ensure_gl
    zk0_ensure_venv || return 1
    zk0_export_env
}
