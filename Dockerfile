# zk0: federated SmolVLA for SO-100/SO-101 arms. One image for simulation, SuperLink and SuperNodes.
#   docker build -t zk0 .                     (podman: podman build --format docker -t zk0 .)
#   ./train.sh --docker -m gpu-serial         (runs ./train.sh in the image: outputs/ mounted, cache in volume zk0-cache)
#   docker compose -f deploy/compose.yaml up  (a SuperLink and two SuperNodes, TLS + authentication; see README)
# BASE: the CUDA runtime by default, for `--gpus all`; torch's wheels bring their own CUDA libraries,
# so any Debian or Ubuntu base with Python >= 3.12 builds the same image (debian:trixie: 3.13).
# pip's own settings pass through as build arguments (PIP_INDEX_URL, PIP_EXTRA_INDEX_URL, PIP_CERT)
# for builds behind a mirror or a TLS-inspecting proxy.
ARG BASE=nvidia/cuda:13.0.1-cudnn-runtime-ubuntu24.04
FROM ${BASE} AS system

SHELL ["/bin/bash", "-o", "pipefail", "-c"]
ENV DEBIAN_FRONTEND=noninteractive \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The base's own Python and its shared library (torchcodec links to it), FFmpeg's libraries for
# torchcodec, tmux for --detached runs, procps for train.sh (it finds and stops its SuperLink
# with pgrep and ps), EGL/OSMesa for the simulator.
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        python3 python3-venv ffmpeg tmux procps ca-certificates libegl1 libgl1 libosmesa6 \
    && { python3 -c 'import sys; sys.exit(sys.version_info < (3, 12))' \
        || { echo "zk0 needs Python >= 3.12; this BASE has $(python3 --version)." >&2; exit 1; }; } \
    && version="$(python3 -c 'import sys; print(*sys.version_info[:2], sep=".")')" \
    && apt-get install -y --no-install-recommends \
        "$(apt-cache search --names-only "^libpython${version}(t64)?\$" | cut -d' ' -f1 | head -n 1)" \
    && rm -rf /var/lib/apt/lists/*

# Ubuntu 24.04 images already use uid 1000 (user ubuntu), so zk0 gets its own.
# Writable for any uid too: ./train.sh --docker runs as the host user so outputs/ stays theirs.
RUN useradd --create-home --uid 10001 zk0 \
    && mkdir -p /workspace/outputs /workspace/.flwr /home/zk0/.cache /opt/zk0 \
    && chown zk0:zk0 /workspace /workspace/outputs /workspace/.flwr /home/zk0/.cache /opt/zk0 \
    && chmod 1777 /workspace/outputs /workspace/.flwr /home/zk0/.cache
USER 10001:10001
WORKDIR /workspace

# The dependency list alone, so that the layer installing it (torch and the rest, minutes) is
# rebuilt only when the list changes, not when another part of pyproject.toml does (a run-config
# key, a test setting).
FROM system AS requirements
COPY pyproject.toml /tmp/pyproject.toml
RUN python3 -c "import tomllib; print(*tomllib.load(open('/tmp/pyproject.toml', 'rb'))['project']['dependencies'], sep='\n')" \
    > /tmp/requirements.txt

# Dependencies first, then the project itself, editable, into the .venv that ./train.sh looks
# for (a change to zk0's code rebuilds only the last layer); the stamp tells train.sh the install
# is current. .venv links to /opt/zk0/venv, as scripts/setup.sh does: `flwr run` walks every
# file under the project folder to pack the app, but not linked folders. (SHELL, with pipefail,
# comes from the system stage.)
FROM system
ARG PIP_INDEX_URL
ARG PIP_EXTRA_INDEX_URL
ARG PIP_CERT
COPY --from=requirements /tmp/requirements.txt /opt/zk0/requirements.txt
RUN python3 -m venv /opt/zk0/venv \
    && ln -s /opt/zk0/venv .venv \
    && .venv/bin/pip install -r /opt/zk0/requirements.txt
COPY --chown=zk0:zk0 . .
# hadolint ignore=DL4006
RUN .venv/bin/pip install --no-deps -e . -e plugins/lerobot_env_zk0 \
    && cat pyproject.toml plugins/lerobot_env_zk0/pyproject.toml | sha256sum | cut -d' ' -f1 > .venv/.zk0-installed

ENV PATH=/opt/zk0/venv/bin:$PATH \
    FLWR_HOME=/workspace/.flwr \
    FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION=1 \
    HF_HOME=/home/zk0/.cache/huggingface \
    ZK0_CACHE=/home/zk0/.cache/zk0 \
    MUJOCO_GL=egl
# Models, datasets and the offline assets persist across containers in this volume.
VOLUME ["/home/zk0/.cache"]
EXPOSE 9093

CMD ["./train.sh"]
