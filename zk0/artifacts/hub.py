"""Model card and Hugging Face Hub upload of the federated policy.

When ``hf-repo-id`` is set, the run's best model at its end (``models/best``: the round with the
lowest server action MSE, staged as ``hub/best_round_<N>``) and with ``hf-push-every-checkpoint``
each checkpoint, tagged ``round-N`` (``hub/round_<N>``), is staged as a lerobot model directory with a
generated model card and the charts, then uploaded with ``huggingface_hub`` if
``HF_TOKEN`` is set. Without a token the staged folder stays on disk and one warning
says so. The token is read from the environment by huggingface_hub and never logged.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from huggingface_hub import HfApi
from loguru import logger

from zk0.config import DEFAULT_SERVER_LR, OFFLINE_MODELS, RunConfig
from zk0.data.registry import DatasetEntry
from zk0.learning.policy_types import LEROBOT_EXTRAS, NAMES

CARD = """---
library_name: lerobot
pipeline_tag: robotics
base_model: {base_model}
tags: [lerobot, {policy_type}, federated-learning, flower, so100, so101]
datasets:
{dataset_list}
---

# {repo_id}

A {policy_name} policy trained with **federated learning** ([zk0](https://github.com/ivelin/zk0),
[Flower](https://flower.ai) + [LeRobot](https://github.com/huggingface/lerobot)) across
{num_clients} SO-100/SO-101 robot datasets whose owners never shared their data. Each client
trained locally (FedProx mu = {mu}); the server averaged the trainable parameters (weighted
by samples) and stepped from the average with {server_optimiser}, for {rounds} rounds.

## Training

| | |
|---|---|
| base model | `{base_model}` |
| rounds x local steps | {rounds} x {local_steps} |
| batch size / learning rate | {batch_size} / {lr} |
| FedProx mu | {mu} |
| server optimiser | {server_optimiser} |
| clients | {num_clients} |
| checkpoint | {checkpoint} |

## Datasets

| role | dataset | revision | cameras (dataset -> model) |
|---|---|---|---|
{dataset_rows}

## Results (server evaluation on `{eval_dataset}`, never trained on)

{metrics}

![policy loss](policy_loss.png)
![action MSE](action_mse.png)

The processors carry normalisation statistics merged over all clients; each client's own
statistics are in `client_stats/` for robot owners who want to normalise with theirs.

## Run it on an SO-100/SO-101 arm

```bash
pip install "lerobot[{extras}]==0.6.1"
lerobot-rollout --strategy.type=base \\
  --robot.type=so101_follower --robot.port=/dev/ttyACM0 --robot.id=my_arm \\
  --robot.cameras="{{ camera1: {{type: opencv, index_or_path: 0, width: 640, height: 480, fps: 30}} }}" \\
  --task="<your task>" --duration=60 \\
  --policy.path={repo_id}
```

`--strategy.type=episodic --dataset.repo_id=<you>/rollout_{model_name} --dataset.single_task="<your task>"`
records evaluation episodes instead.

Name your cameras after the model's inputs (`camera1`, `camera2`, ...) or pass lerobot's
`--rename_map` from your camera names to `observation.images.cameraN`.
"""


def server_optimiser(run: RunConfig) -> str:
    """``nesterov (server-lr 1.0, momentum 0.5)``: how the card says the server stepped."""
    if run.server_optimiser == "fedavg":
        return "fedavg (the average as it is)"
    lr = run.server_lr or DEFAULT_SERVER_LR[run.server_optimiser]
    momentum = f", momentum {run.server_momentum}" if run.server_optimiser in ("fedavgm", "nesterov") else ""
    return f"{run.server_optimiser} (server-lr {lr}{momentum})"


def base_model(run: RunConfig) -> str:
    """What the card names as the start: a checkpoint, or the random weights zk0 built."""
    if run.model not in OFFLINE_MODELS:
        return run.model
    if run.policy == "smolvla":
        return f"zk0 offline {run.model} SmolVLM backbone"
    return f"zk0 {run.model} {NAMES[run.policy]} from random weights"


def model_card(
    run: RunConfig, repo_id: str, entries: list[DatasetEntry], server_round: int, final: dict | None, best: bool
) -> str:
    """A Hub model card: base model, every dataset with its revision, the run's settings and results."""
    rows = "\n".join(
        f"| {e.role} | `{e.repo_id}` | `{e.revision or 'local'}` | "
        + ", ".join(f"{src} -> {dst}" for src, dst in e.cameras.items())
        + " |"
        for e in entries
    )
    metrics = "\n".join(f"- **{k}**: {v:.4g}" for k, v in (final or {}).items()) or "- not evaluated"
    eval_dataset = next((e.repo_id for e in entries if e.role == "server"), "?")
    return CARD.format(
        base_model=base_model(run),
        policy_type=run.policy,
        policy_name=NAMES[run.policy],
        extras=LEROBOT_EXTRAS[run.policy],
        dataset_list="\n".join(f"  - {e.repo_id}" for e in entries),
        repo_id=repo_id,
        model_name=repo_id.split("/")[-1],
        num_clients=sum(e.role == "client" for e in entries),
        mu=run.proximal_mu,
        server_optimiser=server_optimiser(run),
        rounds=run.num_server_rounds,
        local_steps=run.local_steps,
        batch_size=run.batch_size,
        lr=run.lr,
        checkpoint=f"round {server_round}"
        + (f", the lowest server action MSE of rounds 0-{run.num_server_rounds}" if best else ""),
        dataset_rows=rows,
        eval_dataset=eval_dataset,
        metrics=metrics,
    )


def stage(checkpoint: Path, card: str, charts: list[Path], dest: Path) -> Path:
    """Copy a checkpoint, its card and the charts into ``dest``: exactly what gets uploaded."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(checkpoint, dest)
    (dest / "README.md").write_text(card)
    for chart in charts:
        if chart.exists():
            shutil.copy2(chart, dest / chart.name)
    return dest


def can_push(run: RunConfig) -> bool:
    """Whether checkpoints go to the Hub; says once why not when ``hf-repo-id`` is set without a token."""
    if not run.hf_repo_id:
        return False
    if not os.environ.get("HF_TOKEN"):
        logger.warning("hf-repo-id is set but HF_TOKEN is not; checkpoints are staged for the Hub under hub/ only.")
        return False
    return True


def upload(folder: Path, repo_id: str, server_round: int, tag: bool) -> str:
    """Upload ``folder`` to the model repo ``repo_id`` (tagged ``round-N`` if asked); the commit URL."""
    api = HfApi()
    api.create_repo(repo_id, repo_type="model", exist_ok=True)
    commit = api.upload_folder(
        repo_id=repo_id, folder_path=str(folder), commit_message=f"zk0: federated SmolVLA, round {server_round}"
    )
    if tag:
        api.create_tag(repo_id, tag=f"round-{server_round}", revision=commit.oid, exist_ok=True)
    return commit.commit_url


def publish(
    run: RunConfig,
    run_dir: Path,
    checkpoint: Path,
    server_round: int,
    entries: list[DatasetEntry],
    final: dict | None,
    push: bool,
    tag: bool = False,
) -> Path:
    """Stage the run's best model (``hub/best_round_<N>``), or with ``tag`` a round's checkpoint
    (``hub/round_<N>``, tagged ``round-N`` on the Hub); upload it if ``push``."""
    card = model_card(run, run.hf_repo_id, entries, server_round, final, best=not tag)
    charts = [run_dir / "server" / "policy_loss.png", run_dir / "server" / "action_mse.png"]
    staged = stage(checkpoint, card, charts, run_dir / "hub" / f"{'' if tag else 'best_'}round_{server_round}")
    logger.info("Round {} staged for the Hub in {}", server_round, staged)
    if push:
        url = upload(staged, run.hf_repo_id, server_round, tag=tag)
        logger.info("Round {} pushed to the Hub: {}", server_round, url)
    return staged
