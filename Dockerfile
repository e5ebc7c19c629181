# zk0: federated SmolVLA for SO-100/SO-101 arms. One image for simulation, SuperLink and SuperNodes.
#   docker build -t zk0 .
#   docker run --rm --gpus all --shm-size=8g -v "$(pwd)/outputs:/workspace/outputs" -v zk0-cache:/home/zk0/.cache \
#       zk0 ./train.sh -m gpu-serial        (./train.sh --docker -m gpu-serial does this)
#   docker run --rm -p 9093:9093 -v "$(pwd)/certificates:/workspace/certificates:ro" zk0 zk0 superlink
# torch's wheels bring their own CUDA libraries; the CUDA base image supplies the rest of the runtime.
FROM nvidia/cuda:13.0.1-cudnn-runtime-ubuntu24.04

SHELL ["/bin/bash", "-o", "pipefail", "-c"]
ENV DEBIAN_FRONTEND=noninteractive \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# Python 3.12 (Ubuntu 24.04's own), FFmpeg's libraries for torchcodec, tmux for --detached runs.
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        python3.12 python3.12-venv ffmpeg tmux ca-certificates libegl1 libgl1 libosmesa6 \
    && rm -rf /var/lib/apt/lists/*

# Ubuntu 24.04 images already use uid 1000 (user ubuntu), so zk0 gets its own.
# Writable for any uid too: ./train.sh --docker runs as the host user so outputs/ stays theirs.
RUN useradd --create-home --uid 10001 zk0 \
    && mkdir -p /workspace/outputs /workspace/.flwr /home/zk0/.cache /opt/zk0 \
    && chown zk0:zk0 /workspace /workspace/outputs /workspace/.flwr /home/zk0/.cache /opt/zk0 \
    && chmod 1777 /workspace/outputs /workspace/.flwr /home/zk0/.cache
USER 10001:10001
WORKDIR /workspace

# Dependencies first (cached while only the code changes), then the project itself, editable,
# into the .venv that ./train.sh and ./test.sh look for; the stamp tells them it is up to date.
# .venv links to /opt/zk0/venv, as scripts/setup.sh does: `flwr run` walks every file under the
# project folder to pack the app but does not enter linked folders.
COPY --chown=zk0:zk0 pyproject.toml README.md ./
COPY --chown=zk0:zk0 zk0/__init__.py zk0/__init__.py
RUN python3.12 -m venv /opt/zk0/venv \
    && ln -s /opt/zk0/venv .venv \
    && .venv/bin/pip install -e ".[test]"
COPY --chown=zk0:zk0 . .
RUN .venv/bin/pip install --no-deps -e . -e plugins/lerobot_env_zk0 \
    && cat pyproject.toml plugins/lerobot_env_zk0/pyproject.toml | sha256sum | cut -d' ' -f1 > .venv/.zk0-installed

ENV PATH=/opt/zk0/venv/bin:$PATH \
    FLWR_HOME=/workspace/.flwr \
    FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION=1 \
    HF_HOME=/home/zk0/.cache/huggingface \
    ZK0_CACHE=/home/zk0/.cache/zk0
# Models, datasets and the offline assets persist across containers in this volume.
VOLUME ["/home/zk0/.cache"]
EXPOSE 9093

CMD ["./train.sh"]
