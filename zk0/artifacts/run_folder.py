"""Everything a run leaves on disk, written by the server from what clients report.

Layout under ``<output-dir>/<YYYY-MM-DD_HH-MM-SS>/``::

    report.html                    the run on one page, opened from disk (zk0.artifacts.report)
    server/server.log, round_<N>.json, metrics_history.json, policy_loss.png, action_mse.png
    server/success_rate.png, lifted_rate.png, videos/round_<N>.mp4   with closed-loop evaluation (zk0.sim;
                                   the newest keep-checkpoints and the best round's)
    clients/client_<i>/client.log (written by the client), round_<N>.json
    models/checkpoint_round_<N>/   a lerobot pretrained-model directory (LoRA: merged, adapter/ beside)
    models/best/                   the same, of the best round (round 0 included): the highest success
                                   rate in the simulator when measured, else the lowest server action MSE

JSON and charts are rewritten after every round, so an interrupted run keeps them;
checkpoints are written under a temporary name and renamed; nothing is pickled.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
from lerobot.datasets.utils import serialize_dict
from matplotlib.figure import Figure  # the object API: no pyplot state, no GUI backend
from matplotlib.ticker import MaxNLocator
from safetensors.numpy import save_file

from zk0.common.errors import Zk0Error
from zk0.learning import adapters
from zk0.learning.policy import PolicyBundle
from zk0.learning.rates import wilson

CHARTS = {"policy-loss": "policy_loss.png", "action-mse": "action_mse.png"}
SIM_CHARTS = {"success-rate": "success_rate.png", "lifted-rate": "lifted_rate.png"}  # with closed-loop evaluation


def new_run_dir(output_dir: str | Path) -> Path:
    """A fresh ``<output-dir>/<timestamp>`` folder (suffixed if two runs start in the same second)."""
    stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    base = Path(output_dir).expanduser().resolve()
    for suffix in ["", *(f"_{i}" for i in range(1, 100))]:
        candidate = base / f"{stamp}{suffix}"
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            continue
        except OSError as err:
            raise Zk0Error(
                f"Run-config key 'output-dir' got {str(output_dir)!r}, where no folder can be created ({err.strerror}); expected a writable folder."
            ) from None
    raise Zk0Error(f"Could not create a new run folder under {str(base)!r}; 100 runs started in the same second.")


def client_dir(run_dir: Path, index: int) -> Path:
    return run_dir / "clients" / f"client_{index}"


def replace_with(path: Path, write: Callable[[Path], None], suffix: str = ".tmp") -> None:
    """``write`` a temporary file beside ``path``, then rename it to ``path``: readers never see half
    of it, and a write that fails (a full disk) leaves neither a half file nor the temporary one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix)
    os.close(handle)
    try:
        write(Path(name))
        os.replace(name, path)
    except BaseException as err:
        Path(name).unlink(missing_ok=True)
        if isinstance(err, OSError) and not err.filename:  # a failed write names no file: this one
            err.filename = str(path)
        raise


def write_text(path: Path, text: str) -> None:
    """Write a file atomically (temp file + rename)."""
    replace_with(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_json(path: Path, data: dict) -> None:
    """Write JSON atomically."""
    write_text(path, json.dumps(data, indent=2, sort_keys=True))


def clients_trained(record: dict) -> int:
    """How many clients' training counted in a round's record (a refused one carries its ``error``)."""
    return sum("train" in c and "error" not in c["train"] for c in record["clients"].values())


@dataclass
class History:
    """Per-round metrics: clients' train and evaluate replies, their aggregates, and server eval."""

    run_dir: Path
    client_names: dict[int, str]
    rounds: dict[int, dict] = field(default_factory=dict)
    _late: set[int] = field(default_factory=set)  # earlier rounds whose client evaluation came since

    def round(self, server_round: int) -> dict:
        return self.rounds.setdefault(server_round, {"round": server_round, "clients": {}})

    def add_client(self, server_round: int, phase: str, index: int, metrics: dict) -> None:
        """A client's reply; the first training reply of a client that joined after round 1 is noted
        in its round's ``joined`` (an owner whose SuperNode connected mid-run took part from then on;
        its evaluation of the round before rides on that reply and is recorded in the round before)."""
        if phase == "train" and server_round > 1 and not self.trained_before(index, server_round):
            self.round(server_round).setdefault("joined", []).append(index)
        clients = self.round(server_round)["clients"]
        self._late.add(server_round)
        clients.setdefault(str(index), {"dataset": self.client_names.get(index, "?")})[phase] = metrics

    def trained_before(self, index: int, server_round: int) -> bool:
        """Whether client ``index`` replied to a train message in a round before ``server_round``."""
        return any("train" in r["clients"].get(str(index), {}) for n, r in self.rounds.items() if n < server_round)

    def add(self, server_round: int, key: str, value: dict | float | None) -> None:
        """Set ``key`` of the round's record (nothing for None or an empty dict)."""
        if value or value == 0:
            self.round(server_round)[key] = value

    def write_round(self, server_round: int) -> None:
        """``round_<N>.json`` for the server and each client (again for an earlier round whose client
        evaluation arrived with this round's training), the history, and both charts."""
        for number in sorted(self._late | {server_round}):
            record = self.round(number)
            write_json(self.run_dir / "server" / f"round_{number}.json", record)
            for index, metrics in record["clients"].items():
                write_json(client_dir(self.run_dir, int(index)) / f"round_{number}.json", metrics)
        self._late.clear()
        write_json(self.run_dir / "server" / "metrics_history.json", self.snapshot())
        for metric, filename in CHARTS.items():
            self.chart(metric, self.run_dir / "server" / filename)
        for metric, filename in SIM_CHARTS.items():
            if any(metric in record.get("server-evaluate", {}) for record in self.rounds.values()):
                self.chart(metric, self.run_dir / "server" / filename)

    def snapshot(self) -> dict:
        """The whole history as ``metrics_history.json`` holds it: participants and every round."""
        return {"clients": self.participants(), "rounds": [self.rounds[r] for r in sorted(self.rounds)]}

    def participants(self) -> dict[str, str]:
        """Short index -> dataset name of every client that has replied so far."""
        seen = {int(i) for record in self.rounds.values() for i in record["clients"]}
        return {str(i): self.client_names.get(i, "?") for i in sorted(seen)}

    def chart(self, metric: str, path: Path) -> None:
        """One line per client, the clients' weighted aggregate, and the server's own evaluation."""
        fig = Figure(figsize=(7, 4.5))
        ax = fig.subplots()
        rounds = sorted(self.rounds)
        for index, name in self.participants().items():
            points = [
                (r, self.rounds[r]["clients"].get(str(index), {}).get("evaluate", {}).get(metric)) for r in rounds
            ]
            _line(ax, points, f"client {index} ({name})", "-", 1.0)
        _line(
            ax,
            [(r, self.rounds[r].get("aggregate-evaluate", {}).get(metric)) for r in rounds],
            "clients (weighted)",
            "--",
            2.0,
        )
        server = [(r, self.rounds[r].get("server-evaluate", {})) for r in rounds]
        _line(ax, [(r, s.get(metric)) for r, s in server], "server eval", "-", 2.5)
        if metric in SIM_CHARTS:  # a rate over seeded episodes: its 95% interval as a band
            _band(ax, [(r, s[metric], int(s["episodes"])) for r, s in server if metric in s and "episodes" in s])
        ax.set(xlabel="round", ylabel=metric, title=f"{metric} per round")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        replace_with(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"), suffix=".png")


def _band(ax, points: list[tuple[int, float, int]]) -> None:
    """The server's rate with its Wilson interval shaded: 20 episodes leave about +-20 points."""
    if points:
        bounds = [wilson(round(rate * n), n) for _, rate, n in points]
        ax.fill_between([r for r, _, _ in points], *zip(*bounds, strict=True), alpha=0.2, label="server, 95% interval")


def _line(ax, points: list[tuple[int, float | None]], label: str, style: str, width: float) -> None:
    points = [(r, v) for r, v in points if v is not None]
    if points:
        ax.plot(*zip(*points, strict=True), style, marker="o", linewidth=width, label=label)


ROUND_FILE = "zk0_round.json"  # in every checkpoint: the round it holds and the server's evaluation of it
CHECKPOINT = re.compile(r"checkpoint_round_(\d+)")
VIDEO = re.compile(r"round_(\d+)\.mp4")
SERVER_STATE_FILE = "server_optimiser.safetensors"  # in every checkpoint: the server optimiser's state
PERSONAL = "personal"  # a client's personal model: its folder under the client's models/


def save_checkpoint(
    bundle: PolicyBundle,
    run_dir: Path,
    server_round: int,
    client_stats: dict[str, dict],
    name: str | None = None,
    evaluation: dict | None = None,
    server_state: tuple[str, dict[str, np.ndarray]] | None = None,
    evaluated_by: str = "server-evaluate",
) -> Path:
    """A lerobot pretrained-model directory, written to a temporary name and renamed into place.

    A LoRA policy is saved with its adapters merged in (and alone under ``adapter/``), so the
    directory loads like any other. ``name`` (default ``checkpoint_round_<N>``) is its folder under
    ``models/``; ``zk0_round.json`` says which round it holds and how it was evaluated (under
    ``evaluated_by``: the server's evaluation, or a client's of its personal model).
    Its processors carry the merged statistics; ``client_stats/<client>.json`` keeps each
    client's own statistics, so a robot owner can run the policy normalised for their robot.
    ``server_state`` (the server optimiser's name and arrays) goes to ``server_optimiser.safetensors``,
    for a resumed run to continue the optimiser where it was.
    """
    models = run_dir / "models"
    models.mkdir(parents=True, exist_ok=True)
    final = models / (name or f"checkpoint_round_{server_round}")

    def round_files(staging: Path) -> None:
        write_json(staging / ROUND_FILE, {"round": server_round, evaluated_by: evaluation or {}})
        if server_state is not None:
            optimiser, arrays = server_state
            save_file(arrays, staging / SERVER_STATE_FILE, metadata={"server-optimiser": optimiser})

    return save_policy_folder(bundle, final, client_stats, round_files)


def save_policy_folder(
    bundle: PolicyBundle, final: Path, client_stats: dict[str, dict], extra: Callable[[Path], None] | None = None
) -> Path:
    """``bundle`` as a lerobot pretrained-model folder at ``final`` (its policy, LoRA merged, and
    processors; ``client_stats/<name>.json`` each dataset's own statistics; whatever ``extra``
    writes), written under a temporary name beside it and renamed into place."""
    staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    try:
        adapters.merged(bundle.policy).save_pretrained(staging)
        if adapters.is_adapted(bundle.policy):
            bundle.policy.save_pretrained(staging / adapters.ADAPTER_DIR)  # PEFT's format: adapters, full modules
        bundle.preprocessor.save_pretrained(staging)
        bundle.postprocessor.save_pretrained(staging)
        for client, stats in client_stats.items():
            write_json(staging / "client_stats" / f"{client}.json", serialize_dict(stats))
        if extra:
            extra(staging)
        _swap_in(staging, final)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return final


def checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    """The run's complete checkpoints, oldest first: (round, folder). A folder is renamed into
    place only once complete, so one that has its weights is whole."""
    return sorted(
        (int(m.group(1)), p)
        for p in (run_dir / "models").glob("checkpoint_round_*")
        if (m := CHECKPOINT.fullmatch(p.name)) and (p / "model.safetensors").is_file()
    )


def prune_checkpoints(run_dir: Path, keep: int) -> list[int]:
    """Remove all but the newest ``keep`` complete checkpoints (0: keep every one); the rounds removed.

    Called once a new checkpoint is complete, so resume always has one. ``models/best`` is a folder
    of its own (hard links to its checkpoint's files), so it stays whole when its checkpoint goes."""
    done = checkpoints(run_dir)
    old = done[:-keep] if keep else []
    for _, folder in old:
        shutil.rmtree(folder)
    return [number for number, _ in old]


def prune_videos(run_dir: Path, keep: int, best: int | None) -> None:
    """Keep the newest ``keep`` closed-loop videos (0: every one) and the best round's: the two the
    report shows. A video a round is megabytes; a week-long run evaluates hundreds of rounds."""
    videos = sorted(
        (int(m.group(1)), p)
        for p in (run_dir / "server" / "videos").glob("round_*.mp4")
        if (m := VIDEO.fullmatch(p.name))
    )
    for number, path in videos[:-keep] if keep else []:
        if number != best:
            path.unlink()


def link_checkpoint(checkpoint: Path, name: str) -> Path:
    """``models/<name>``: the model of ``checkpoint`` (a folder ``save_checkpoint`` wrote) without the
    server optimiser's state, its files hard-linked instead of written again (a full-size model
    is 1.8 GB, seconds to write), or copied where the file system has no hard links. zk0 never
    changes a written file in place: a later save replaces the whole folder, so the other keeps its files.
    """
    final = checkpoint.parent / name
    staging = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=checkpoint.parent))
    try:
        for source in sorted(checkpoint.rglob("*")):
            target = staging / source.relative_to(checkpoint)
            if source.is_dir():
                target.mkdir()
            elif source.name != SERVER_STATE_FILE:
                try:
                    os.link(source, target)
                except OSError:
                    shutil.copy2(source, target)
        _swap_in(staging, final)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return final


def _swap_in(staging: Path, final: Path) -> None:
    """A complete folder takes ``final``'s place (a reader never sees a half-written one there)."""
    if final.exists():
        shutil.rmtree(final)
    staging.rename(final)
