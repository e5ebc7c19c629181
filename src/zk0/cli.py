"""The ``zk0`` command: offline assets and the checks the set-up scripts need."""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path

from flwr.common.config import flatten_dict, parse_config_args

from zk0.assets import TINY_BACKBONE, AssetError, default_cache_root, ensure_backbone, ensure_dataset
from zk0.assets.datasets import SPECS
from zk0.config import from_run_config
from zk0.errors import Zk0Error
from zk0.registry import PROJECT_ROOT, load_registry


def _assets(args: argparse.Namespace) -> int:
    """(Re)generate the offline assets and print where each one is."""
    root = Path(args.cache_dir).expanduser() if args.cache_dir else default_cache_root()
    names = args.only or [TINY_BACKBONE, *SPECS]
    for name in names:
        if name != TINY_BACKBONE and name not in SPECS:
            raise AssetError(f"Unknown asset {name!r}; expected one of {[TINY_BACKBONE, *SPECS]}.")
    for name in names:
        if name == TINY_BACKBONE:
            path = ensure_backbone(root)
        else:
            path = ensure_dataset(name, root, seed=args.seed, episodes=args.episodes)
        print(f"{name}: {path}")
    return 0


def preset_path(name: str) -> Path:
    """A preset by name (``configs/presets/<name>.toml``) or by path."""
    path = Path(name) if name.endswith(".toml") else PROJECT_ROOT / "configs" / "presets" / f"{name}.toml"
    if not path.is_file():
        known = sorted(p.stem for p in (PROJECT_ROOT / "configs" / "presets").glob("*.toml"))
        raise Zk0Error(f"Preset {name!r} not found; expected one of {known} or a .toml file.")
    return path


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    return f"'{value}'" if isinstance(value, str) else repr(value)


def _check(args: argparse.Namespace) -> int:
    """Validate a preset and run-config overrides the way the apps will, before anything starts."""
    table = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["config"]
    overrides = tomllib.loads(preset_path(args.preset).read_text()) if args.preset else {}
    try:
        overrides.update(parse_config_args(args.run_config))
    except Exception as err:  # flwr raises click/TOML errors with a readable message
        raise Zk0Error(f"Run config {args.run_config} cannot be parsed: {getattr(err, 'message', err)}") from None
    run = from_run_config({**flatten_dict(table), **overrides})
    registry = load_registry(run.registry)
    registry.get(run.server_eval_dataset)
    if args.print:  # one flat override string for `flwr run --run-config`
        print(" ".join(f"{key}={_toml_value(value)}" for key, value in overrides.items()))
    else:
        print(
            f"Run config OK: {run.num_server_rounds} rounds x {run.local_steps} local steps, "
            f"{len(registry.clients)} client datasets."
        )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="zk0", description="zk0: federated SmolVLA for SO-100/SO-101 arms.")
    commands = parser.add_subparsers(dest="command", required=True)
    assets = commands.add_parser("assets", help="generate the offline datasets and tiny backbone, print their paths")
    assets.add_argument("--cache-dir", help="cache root (default: $ZK0_CACHE or ~/.cache/zk0)")
    assets.add_argument("--seed", type=int, default=0, help="generator seed (default 0, what runs use)")
    assets.add_argument("--episodes", type=int, help="episodes per dataset (default: each dataset's own)")
    assets.add_argument(
        "--only", nargs="+", metavar="NAME", help=f"only these assets: {TINY_BACKBONE} {' '.join(SPECS)}"
    )
    assets.set_defaults(func=_assets)
    check = commands.add_parser("check", help="validate run-config overrides and the dataset registry")
    check.add_argument(
        "--run-config", action="append", default=[], help='overrides as for flwr run, e.g. "local-steps=5"'
    )
    check.add_argument("--preset", help="a preset name (configs/presets/<name>.toml) or file, applied before overrides")
    check.add_argument("--print", action="store_true", help="print the merged overrides as one --run-config string")
    check.set_defaults(func=_check)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except Zk0Error as err:
        print(f"zk0: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
