"""The ``zk0`` command: offline assets, the checks the set-up scripts need, a policy pretrained on
public data, the deployment's processes, and an owner's policy exported from a run."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tomllib
from pathlib import Path

from flwr.common.config import flatten_dict, parse_config_args
from tqdm import tqdm

from zk0.artifacts.logs import native_output_to
from zk0.common import machine
from zk0.common.cache import default_cache_root
from zk0.common.errors import OneSentenceParser, Zk0Error, positive
from zk0.config import RunConfig, from_run_config
from zk0.data.assets import (
    BACKBONES,
    OFFLINE_BACKBONES,
    TINY_BACKBONE,
    AssetError,
    ensure_backbone,
    ensure_dataset,
)
from zk0.data.assets.datasets import SPECS
from zk0.data.registry import PROJECT_ROOT, load_registry
from zk0.deployment import commands as deploy
from zk0.deployment.certs import make_federation_certs
from zk0.deployment.commands import SUPEREXEC_POLL, node_config, superlink_command, supernode_command, thread_env
from zk0.sim.tasks import SIM_SPECS


def _assets(args: argparse.Namespace) -> int:
    """(Re)generate the offline assets and print where each one is."""
    root = Path(args.cache_dir).expanduser() if args.cache_dir else default_cache_root()
    names = args.only or [TINY_BACKBONE, *(name for name, spec in SPECS.items() if not spec.benchmark_only)]
    if args.run_config:  # and the backbone and every dataset zk0 generates that this run names
        run, _ = _merged_run(None, args.run_config)
        smolvla = run.policy == "smolvla" and run.model in OFFLINE_BACKBONES  # the others need no backbone
        wanted = [OFFLINE_BACKBONES[run.model]] if smolvla else []
        wanted += [e.name for e in load_registry(run.registry).entries if e.synthetic]
        names += [name for name in wanted if name not in names]
    for name in names:
        if name not in BACKBONES and name not in SPECS and name not in SIM_SPECS:
            known = [*BACKBONES, *SPECS.described(), *SIM_SPECS.described()]
            raise AssetError(f"Unknown asset {name!r}; expected one of {known}.")
    paths = {}
    # One bar of zk0's own (shown once generating takes over a second); what the libraries print
    # while generating (FFmpeg's muxer, datasets' bars) goes to assets.log in the cache.
    with native_output_to(root / "assets.log") as console:
        for name in tqdm(names, desc="Offline assets", unit="asset", file=console, delay=1.0):
            if name in BACKBONES:
                paths[name] = ensure_backbone(root, kind=name)
            else:
                paths[name] = ensure_dataset(name, root, seed=args.seed, episodes=args.episodes)
    for name, path in paths.items():
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


def _merged_run(preset: str | None, run_config: list[str]) -> tuple[RunConfig, dict]:
    """The run config the apps will see (pyproject defaults, the preset, the overrides), and the overrides."""
    table = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["config"]
    overrides = tomllib.loads(preset_path(preset).read_text()) if preset else {}
    try:
        overrides.update(parse_config_args(run_config))
    except Exception as err:  # flwr raises click/TOML errors with a readable message
        raise Zk0Error(f"Run config {run_config} cannot be parsed: {getattr(err, 'message', err)}") from None
    return from_run_config({**flatten_dict(table), **overrides}), overrides


def _sized_federation(run: RunConfig, path: Path) -> str:
    """A simulation's federation config file as one ``--federation-config`` string, with the clients
    that train at once sized to the memory available (a sentence on stderr when it lowered them)."""
    from zk0.learning.memory import sized_federation

    try:
        federation = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        raise Zk0Error(
            f"--federation-config got {str(path)!r}; expected a readable TOML file such as configs/federation/cpu.toml."
        ) from None
    sized, said = sized_federation(run, federation)
    if said:
        print(f"[zk0] {said}", file=sys.stderr)
    return " ".join(f"{key}={_toml_value(value)}" for key, value in sized.items())


def _check(args: argparse.Namespace) -> int:
    """Validate a preset and run-config overrides the way the apps will, before anything starts."""
    run, overrides = _merged_run(args.preset, args.run_config)
    registry = load_registry(run.registry)
    registry.get(run.server_eval_dataset)
    if args.print:  # one flat override string for `flwr run --run-config`; datasets are not opened
        print(" ".join(f"{key}={_toml_value(value)}" for key, value in overrides.items()))
    if args.federation_config:  # the simulation's config, sized to the memory available now
        print(_sized_federation(run, Path(args.federation_config)))
    if args.print or args.federation_config:
        return 0
    from zk0.learning.preflight import check_federation  # torch and lerobot: only when datasets are checked

    report = check_federation(run, registry)
    for problem in report.problems:
        print(f"zk0: {problem}", file=sys.stderr)
    if report.problems:
        return 2
    absent = f"; not on this machine, so not checked: {', '.join(report.skipped)}" if report.skipped else ""
    print(
        f"Run config OK: {run.num_server_rounds} rounds x {run.local_steps} local steps, "
        f"{len(registry.clients)} client datasets. Datasets OK: {', '.join(report.checked) or 'none'}{absent}."
    )
    return 0


def _pretrain(args: argparse.Namespace) -> int:
    """Pretrain the run's policy on the registry's public sets; say how to federate from it."""
    run, _ = _merged_run(args.preset, args.run_config)
    from zk0.federation.pretraining import pretrain, public_sets  # torch and lerobot: after the config is checked

    public_sets(run)  # no public datasets: one sentence before anything is built
    out = Path(args.out).expanduser().resolve()
    done = pretrain(run, args.steps, out)
    print(
        f"Pretrained {run.policy} ({run.model}) for {args.steps} steps on {len(done['public-sets'])} public set(s) "
        f"in {done['wall-s']:.0f} s (train loss {done['train-loss']:.4g}): {out}"
    )
    print(f"Federate from it: flwr run . --run-config \"registry='{run.registry}' model='{out}'\"")
    return 0


def _certs(args: argparse.Namespace) -> int:
    """Create the CA, the SuperLink certificate and SuperNode key pairs; print what goes where."""
    paths = make_federation_certs(Path(args.out), args.host, args.supernode)
    print(f"CA certificate (give to every SuperNode and flwr user): {paths['ca']}")
    print(f"SuperLink certificate: {paths['server']} (+ server.key, keep private)")
    for name in args.supernode:
        print(
            f"SuperNode {name}: register {paths[name]} with `flwr supernode register`; its private key: {paths[name].with_suffix('')}"
        )
    return 0


def _superlink(args: argparse.Namespace) -> int:
    certs = None if args.insecure else Path(args.certs)
    host, port = split_address(args.address)
    database = Path(args.database) if args.database else None
    run_command(superlink_command(certs, host, port, database), args.dry_run)
    return 0


def _supernode(args: argparse.Namespace) -> int:
    certs = None if args.insecure else Path(args.certs)
    registry = load_registry(args.registry)
    entry = registry.get_client(args.dataset)  # a typo fails here, not in round 1
    cpus = len(os.sched_getaffinity(0))
    if args.cpus is not None and not 1 <= args.cpus <= cpus:
        raise Zk0Error(f"--cpus got {args.cpus}; expected a number from 1 to {cpus}, the CPUs this process may use.")
    output_dir = writable_folder(Path(args.output_dir).expanduser().resolve(), "--output-dir")
    supernodes = machine.registry_folder()  # a temporary folder others may write in: refused before anything
    config = node_config(args.dataset, output_dir, not args.no_warm_worker)
    command = supernode_command(args.superlink, certs, args.key, config, args.runtime_port)
    env = {**thread_env(args.cpus, supernodes), **SUPEREXEC_POLL}
    if args.dry_run:
        print(" ".join(f"{k}={v}" for k, v in env.items()), shlex.join(command))
        return 0
    from zk0.learning.preflight import ModelInputs, check_dataset  # torch and lerobot: only when starting for real

    check_dataset(entry, ModelInputs(tuple(registry.model_cameras())), eval_episodes=None)  # before connecting
    if args.cpus is None:
        machine.register(supernodes)  # this process becomes the SuperNode (exec keeps its pid)
    deploy.run(command, env)
    return 0


def writable_folder(path: Path, flag: str) -> Path:
    """``path``, created if missing, or one sentence when this user cannot write there."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise Zk0Error(f"{flag} got {str(path)!r}, where no folder can be created ({err.strerror}).") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise Zk0Error(f"{flag} got {str(path)!r}, which this user cannot write to; expected a writable folder.")
    return path


def split_address(address: str) -> tuple[str, int]:
    """``host:port`` -> (host, port), with one sentence when it is not that."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise Zk0Error(f"Address {address!r} is not host:port; expected e.g. 0.0.0.0:9093.")
    return host.strip("[]"), int(port)


def run_command(command: list[str], dry_run: bool) -> None:
    if dry_run:
        print(" ".join(command))
    else:
        deploy.run(command)


def _export(args: argparse.Namespace) -> int:
    """An owner's policy, normalised for their robot, in a folder lerobot loads."""
    from zk0.artifacts.export import export_policy  # lerobot's processors: only for this command

    if args.personal and args.round is not None:
        raise Zk0Error("--round names a global checkpoint; a personal model is the one its client kept, so drop one.")
    out = export_policy(Path(args.run), args.client, Path(args.out), args.personal, args.round)
    which = "personal model" if args.personal else "global model with its statistics"
    print(f"Client {args.client}'s {which}: {out}")
    print(f"Run it with: lerobot-rollout --strategy.type=base --policy.path={out} ...")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = OneSentenceParser(prog="zk0", description="zk0: federated SmolVLA for SO-100/SO-101 arms.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneSentenceParser)
    assets = commands.add_parser("assets", help="generate the offline datasets and tiny backbone, print their paths")
    assets.add_argument("--cache-dir", help="cache root (default: $ZK0_CACHE or ~/.cache/zk0)")
    assets.add_argument("--seed", type=int, default=0, help="generator seed (default 0, what runs use)")
    assets.add_argument("--episodes", type=int, help="episodes per dataset (default: each dataset's own)")
    assets.add_argument(
        "--only", nargs="+", metavar="NAME", help=f"only these assets: {' '.join([*BACKBONES, *SPECS.described(), *SIM_SPECS.described()])}"
    )
    assets.add_argument(
        "--run-config", action="append", default=[], help="also every generated dataset this run's registry names"
    )
    assets.set_defaults(func=_assets)
    check = commands.add_parser(
        "check", help="validate run-config overrides, the registry, and every dataset on this machine"
    )
    check.add_argument(
        "--run-config", action="append", default=[], help='overrides as for flwr run, e.g. "local-steps=5"'
    )
    check.add_argument("--preset", help="a preset name (configs/presets/<name>.toml) or file, applied before overrides")
    check.add_argument("--print", action="store_true", help="print the merged overrides as one --run-config string")
    check.add_argument(
        "--federation-config",
        metavar="FILE",
        help="print this simulation config (configs/federation/*.toml) as one --federation-config string, with "
        "the clients that train at once sized to the memory available; refuse if one does not fit",
    )
    check.set_defaults(func=_check)

    pretrain = commands.add_parser(
        "pretrain", help="train the run's policy on the registry's public datasets: a starting point to federate from"
    )
    pretrain.add_argument("--run-config", action="append", default=[], help="as for flwr run: registry, model, lr...")
    pretrain.add_argument("--preset", help="a preset (configs/presets/<name>.toml) or file, applied before overrides")
    pretrain.add_argument("--steps", type=positive(int), default=1000, help="optimizer steps (default 1000)")
    pretrain.add_argument("--out", required=True, help="a new folder: the lerobot policy model='<folder>' starts from")
    pretrain.set_defaults(func=_pretrain)

    certs = commands.add_parser("certs", help="create a CA, the SuperLink certificate and SuperNode key pairs")
    certs.add_argument("--out", default="certificates", help="folder to write them to (default: certificates)")
    certs.add_argument(
        "--host", action="append", default=[], help="a DNS name or IP the SuperLink is reached at (repeatable)"
    )
    certs.add_argument(
        "--supernode", action="append", default=[], metavar="NAME", help="a SuperNode key pair to create (repeatable)"
    )
    certs.set_defaults(func=_certs)

    superlink = commands.add_parser("superlink", help="start the SuperLink (TLS + SuperNode authentication)")
    superlink.add_argument("--certs", default="certificates", help="folder from `zk0 certs`")
    superlink.add_argument(
        "--address", default="0.0.0.0:9093", help="host:port for SuperNodes and flwr (default 0.0.0.0:9093)"
    )
    superlink.add_argument("--database", help="SQLite file for the SuperLink's state (default: in memory)")
    superlink.add_argument(
        "--insecure", action="store_true", help="no TLS, no authentication (trusted test networks only)"
    )
    superlink.add_argument(
        "--dry-run", action="store_true", help="print the SuperLink's command instead of running it"
    )
    superlink.set_defaults(func=_superlink)

    supernode = commands.add_parser("supernode", help="start a SuperNode for one robot owner's dataset")
    supernode.add_argument("--superlink", required=True, help="the SuperLink's host:port")
    supernode.add_argument("--dataset", required=True, help="registry name or repo id of this owner's dataset")
    supernode.add_argument("--key", help="this SuperNode's key name in <certs>/supernodes/")
    supernode.add_argument(
        "--certs", default="certificates", help="folder with ca.crt and supernodes/ (default: certificates)"
    )
    supernode.add_argument(
        "--registry", default="", help="registry TOML the dataset is looked up in (default: pyproject.toml)"
    )
    supernode.add_argument(
        "--runtime-port", type=int, default=9094, help="local port for the ClientApp runtime API (default 9094)"
    )
    supernode.add_argument(
        "--output-dir",
        default="outputs",
        help="this machine's folder for the client's logs, <output-dir>/<run>/clients/ (default: outputs)",
    )
    supernode.add_argument(
        "--cpus", type=int, help="CPU threads for training and data loading (default: all this process may use)"
    )
    supernode.add_argument(
        "--no-warm-worker",
        action="store_true",
        help="build the client in every message's own process instead of keeping it in a worker (slow)",
    )
    supernode.add_argument(
        "--insecure", action="store_true", help="no TLS, no authentication (trusted test networks only)"
    )
    supernode.add_argument(
        "--dry-run",
        action="store_true",
        help="print the flower-supernode command instead of running it (the dataset is not opened)",
    )
    supernode.set_defaults(func=_supernode)

    export = commands.add_parser(
        "export", help="write an owner's policy from a run as a lerobot folder, normalised with that owner's statistics"
    )
    export.add_argument("run", help="the run folder (outputs/<run>, or <--output-dir>/<run> on a SuperNode)")
    export.add_argument("--client", type=int, required=True, help="the owner's client index (client_<i> in the run)")
    export.add_argument("--out", required=True, help="a new folder for the policy (lerobot-rollout --policy.path)")
    export.add_argument(
        "--personal", action="store_true", help="the owner's personal model instead of the global one (personal-steps)"
    )
    export.add_argument("--round", type=int, help="the global model of this round's checkpoint (default: the last)")
    export.set_defaults(func=_export)
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
