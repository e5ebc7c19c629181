"""Policies: which lerobot policy types build here, offline, on zk0's data, and which zk0 federates.

For each type, lerobot's own ``make_policy_config`` and ``make_policy`` on the features of a
generated dataset (its state, action and the registry's two cameras), with no pretrained
backbone weights (nothing here can download them): a row with the parameters it built, or
lerobot's refusal (its first line). SmolVLA, ACT and Diffusion Policy are built as zk0 builds them
(``zk0.learning.policy``: SmolVLA on the tiny offline backbone) and marked as federated.
pi0 and pi0.5 build with random weights at their full size (about 4 billion parameters, 16 GB
in fp32): give ``--types`` without them on a small machine.

    python -m zk0.bench policies [--types smolvla act diffusion ...] [--json out.json]
"""

from __future__ import annotations

import gc
import os
import time

import torch

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser
from zk0.config import POLICIES, RunConfig
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry

# lerobot 0.6.1's policy types that train from demonstrations (sac and the reward classifier
# are reinforcement-learning parts, not policies an owner trains from a dataset).
TYPES = ("smolvla", "act", "diffusion", "vqbet", "tdmpc", "pi0", "pi05", "pi0_fast", "groot", "xvla")


def build(kind: str) -> torch.nn.Module:
    """A fresh ``kind`` policy for the quick run's first owner: zk0's way where zk0 federates it,
    lerobot's factories with no pretrained backbone weights otherwise."""
    from lerobot.configs import FeatureType
    from lerobot.policies import make_policy
    from lerobot.policies.factory import make_policy_config

    from zk0.learning.policy import build_policy, model_features

    registry = load_registry()
    entry = registry.clients[0]
    meta = open_metadata(entry)
    if kind in POLICIES:
        return build_policy(RunConfig(policy=kind, device="cpu"), meta, entry, registry.model_cameras()).policy
    cfg = make_policy_config(kind, device="cpu", push_to_hub=False)
    if hasattr(cfg, "pretrained_backbone_weights"):
        cfg.pretrained_backbone_weights = None
    features = model_features(meta, entry, registry.model_cameras())
    cfg.input_features = {key: ft for key, ft in features.items() if ft.type is not FeatureType.ACTION}
    return make_policy(cfg, ds_meta=meta, rename_map=entry.rename_map())


def survey(kind: str) -> dict:
    """One type's row: built (its parameters and seconds) or refused (lerobot's first line)."""
    started = time.perf_counter()
    try:
        policy = build(kind)
    except Exception as err:  # lerobot's refusal is the row's finding
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        return {"type": kind, "builds": False, "reason": f"{type(err).__name__}: {first}"}
    row = {
        "type": kind,
        "builds": True,
        "parameters": sum(p.numel() for p in policy.parameters()),
        "build-s": time.perf_counter() - started,
        "federated": kind in POLICIES,
    }
    del policy
    gc.collect()
    return row


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench policies", description=__doc__.splitlines()[0])
    parser.add_argument("--types", nargs="+", choices=TYPES, default=list(TYPES), help="lerobot policy types")
    parser.add_argument("--json", help="also write the rows to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ["HF_HUB_OFFLINE"] = "1"  # the question is what builds here: a refusal, never a download
    rows = [survey(kind) for kind in args.types]
    print(f"{'type':<10} {'builds':<7} {'parameters':>15}  zk0")
    for row in rows:
        if row["builds"]:
            federated = f"federated (policy='{row['type']}')" if row["federated"] else "not federated"
            print(f"{row['type']:<10} {'yes':<7} {row['parameters']:>15,}  {federated}")
        else:
            print(f"{row['type']:<10} {'no':<7} {'':>15}  {row['reason']}")
    write_json(args.json, {"rows": rows})
    return 0
