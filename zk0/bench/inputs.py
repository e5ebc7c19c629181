"""Inputs benchmark: which inputs a centrally trained policy uses (real, blank or shuffled images; shuffled state).

It trains one policy on every client's data pooled (the study's centralised baseline,
``zk0.learning.training.PooledTrainer``) for ``--steps``, then evaluates it on the server's held-out
episodes as the server does, four times: as recorded; with every camera black; with each
sample's camera frames swapped for another sample's of the same batch; with the joint state
swapped likewise. A policy that looks at the cube loses accuracy when frames are swapped; one
whose error does not move has learnt nothing from the cameras' content.

    python -m zk0.bench inputs [--registry configs/sim-registry.toml] [--model tiny-128] [--steps 4000] [--lr 1e-3] [--json out.json]
"""

from __future__ import annotations

from dataclasses import replace

import torch

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.data.loaders import eval_loader, open_evaluation, open_metadata
from zk0.data.registry import load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import build_policy, set_trainable, snapshot
from zk0.learning.training import PooledTrainer, evaluate

VARIANTS = ("recorded", "blank images", "shuffled images", "shuffled state")


class Altered:
    """A preprocessor that changes one input of every batch before the policy's own processors."""

    def __init__(self, preprocessor, cameras: list[str], variant: str, seed: int):
        """``cameras``: the dataset's own camera keys (the preprocessor renames them for the model)."""
        self.preprocessor, self.cameras, self.variant = preprocessor, cameras, variant
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(self, batch: dict) -> dict:
        keys = self.cameras if "images" in self.variant else ["observation.state"] if "state" in self.variant else []
        for key in keys:
            if self.variant == "blank images":
                batch[key] = torch.zeros_like(batch[key])
            else:
                batch[key] = batch[key][torch.randperm(len(batch[key]), generator=self.generator)]
        return self.preprocessor(batch)


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench inputs", description=__doc__.splitlines()[0])
    parser.add_argument("--registry", default="configs/sim-registry.toml", help="whose clients and server set")
    parser.add_argument("--model", default="tiny-128", choices=OFFLINE_MODELS)
    parser.add_argument("--steps", type=positive(int), default=4000, help="centralised training steps")
    parser.add_argument("--lr", type=positive(float), default=1e-3)
    parser.add_argument("--batch-size", type=positive(int), default=8)
    parser.add_argument("--eval-batches", type=positive(int), default=20)
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    registry = load_registry(args.registry)
    server = registry.server
    run = RunConfig(
        registry=args.registry, server_eval_dataset=server.name, model=args.model, batch_size=args.batch_size,
        lr=args.lr, local_steps=args.steps, eval_batches=args.eval_batches,
    )
    cameras = registry.model_cameras()
    sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients)]
    bundle = build_policy(run, sessions[0].split.meta, sessions[0].split.entry, cameras)
    trained = PooledTrainer.over(bundle, [s.trainer for s in sessions], run).fit(args.steps, mu=0.0, global_step=0)
    meta = open_metadata(server)
    judge = build_policy(run, meta, server, cameras)
    set_trainable(judge, snapshot(bundle))
    split = open_evaluation(server, meta, judge.policy.config, run)
    loader = eval_loader(split.evaluation, run)
    figures = {"model": args.model, "steps": args.steps, "train-loss": trained["train-loss"], "server": server.name}
    print(f"centralised {args.model}, {args.steps} steps on {len(sessions)} clients "
          f"(train loss {trained['train-loss']:.3g}); "
          f"{server.name}'s held-out episodes:")
    for variant in VARIANTS:
        altered = replace(judge, preprocessor=Altered(judge.preprocessor, split.meta.camera_keys, variant, run.seed))
        m = evaluate(altered, split, loader, run.eval_batches, run.seed, run.max_skip_fraction)
        figures[variant] = {"action-mse": m["action-mse"], "policy-loss": m["policy-loss"]}
        print(f"  {variant:<16} action MSE {m['action-mse']:8.3f}   policy loss {m['policy-loss']:.4f}")
    write_json(args.json, figures)
    return 0
