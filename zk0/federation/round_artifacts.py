"""What the server keeps of every round: clients' records, JSON and charts, the report, checkpoints,
the best model so far, the Hub staging, W&B, and one progress line a person reads.

The best model is the one with the lowest server action MSE of every evaluated round, round 0
(the starting model) included, kept in ``models/best``: a run that starts from a pretrained
model never hands back one that does worse on the server's evaluation set than where it began.
A middle round's models/best is written in a thread while the next round's clients train (a
full-size model is 1.8 GB: seconds the clients would otherwise wait for); the server's next use
of the policy waits for it (``PolicyBundle.lock``), and so does the next round's end.

``RoundArtifacts`` is the observer ``zk0.federation.aggregation.ValidatingStrategy`` calls: with the client
replies each phase counted or lost (``record_clients``), and once a round is over, after Flower's
``evaluate_fn`` evaluated the global model (``round_ended``). It writes only from what it is
given, so a simulation and a deployment leave the same files. Once the run is stopped (Ctrl-C,
``flwr stop``) it writes nothing more (``zk0.federation.stopping``).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
from flwr.app import ArrayRecord, MetricRecord, RecordDict
from loguru import logger

from zk0.artifacts.hub import can_push, publish
from zk0.artifacts.logs import say
from zk0.artifacts.report import epsilon_spent, write_report
from zk0.artifacts.run_folder import (
    ROUND_FILE,
    History,
    clients_trained,
    link_checkpoint,
    prune_checkpoints,
    prune_videos,
    save_checkpoint,
)
from zk0.artifacts.tracking import Tracker
from zk0.config import RunConfig
from zk0.data.registry import DatasetEntry, Registry
from zk0.federation import stopping
from zk0.federation.stats import stats_from_record, with_merged_stats
from zk0.federation.wire import CLIENT
from zk0.learning.policy import PolicyBundle, set_trainable
from zk0.learning.rates import model_choice, simulator_text, success_text

LATE_WARNING = 3  # rounds in a row a client misses the deadline before the server warns about it
STRAGGLER = 0.5  # with a time budget, a client that took less than this share of the fastest one's steps


class RoundArtifacts:
    """Every file a run writes on the server, written as each round ends."""

    def __init__(
        self,
        run: RunConfig,
        registry: Registry,
        bundle: PolicyBundle,
        eval_entry: DatasetEntry,
        history: History,
        tracker: Tracker,
        client_stats: dict[int, dict],
        first_round: int,
        best: dict | None = None,
    ):
        self.run, self.registry, self.bundle, self.eval_entry = run, registry, bundle, eval_entry
        self.history, self.tracker = history, tracker
        self.client_stats = client_stats  # dataset index -> that client's normalisation statistics
        self.first_round = first_round  # this process's first round (a resumed run's is not 1)
        self.best = best  # {"round", "action-mse"} of models/best (a resumed run's, read from its folder)
        self.start_mse: float | None = None  # round 0's server action MSE
        self.unsaved: tuple[ArrayRecord, dict] | None = None  # the best model, until written to models/best
        self.writing: threading.Thread | None = None  # models/best being written while the next round trains
        self.write_error: BaseException | None = None
        self.push = can_push(run)
        self.started = time.perf_counter()
        self.last_end = self.started  # when the latest round's line was written

    def record_clients(
        self,
        phase: str,
        server_round: int,
        replies: list[RecordDict],
        aggregate: MetricRecord | None,
        failures: dict[int, str],
    ) -> None:
        """Keep each client's metrics (by dataset index, never node id), their aggregate, dataset
        statistics, and why a client's reply failed (``failures``: dataset index -> reason)."""
        for index, reason in failures.items():
            self.history.add_client(server_round, phase, index, {"error": reason})
        if aggregate:
            self.history.add(server_round, f"aggregate-{phase}", dict(aggregate))
        for content in replies:
            index = int(content[CLIENT]["index"])
            self.history.add_client(server_round, phase, index, dict(content["metrics"]))
            if "stats" in content:
                self.client_stats[index] = stats_from_record(content["stats"])
        if phase == "evaluate" and any("personal-action-mse" in content["metrics"] for content in replies):
            say(self.personal_line(server_round))

    def record_privacy(self, server_round: int, spent: dict) -> None:
        """Owner-level DP's epsilon once this round's model is released (``privacy`` in its JSON,
        with the accountant's state a resumed run continues from)."""
        self.history.add(server_round, "privacy", spent)

    def record_late(self, server_round: int, clients: list[int], nodes: list[int]) -> None:
        """The round's clients whose update missed the deadline (``late`` in its JSON); a client
        late three rounds in a row is warned about: its owner's work is not being counted."""
        self.history.add(server_round, "late", {"clients": clients, "nodes": nodes})
        for index in clients:
            rounds = 0
            while index in self.history.rounds.get(server_round - rounds, {}).get("late", {}).get("clients", []):
                rounds += 1
            if rounds >= LATE_WARNING:
                name = self.history.client_names.get(index, "?")
                logger.warning(
                    "Client {} ({}) has sent no update within round-deadline-s={:g} in each of the last {} rounds, so "
                    "its owner's work is not counted; set local-time-s below the deadline or raise round-deadline-s.",
                    index,
                    name,
                    self.run.round_deadline_s,
                    rounds,
                )

    def personal_line(self, server_round: int) -> str:
        """``Personal models after round 2 (...): client 0 235 -> 199, ...``: each owner's global and
        personal model on its own held-out episodes, and in simulated conditions in its own set-up."""
        clients = self.history.round(server_round)["clients"]
        scored = {
            i: c["evaluate"] for i, c in sorted(clients.items()) if "personal-action-mse" in c.get("evaluate", {})
        }
        mse = ", ".join(
            f"client {i} {e['action-mse']:.4g} -> {e['personal-action-mse']:.4g}" for i, e in scored.items()
        )
        line = f"Personal models after round {server_round} (held-out action MSE, global -> personal): {mse}"
        own = {i: e for i, e in scored.items() if "own-success-rate" in e}
        if own:
            rates = ", ".join(
                f"client {i} {success_text(e, 'own-')} -> {success_text(e, 'personal-own-')}"
                + (f", {choice}" if (choice := model_choice(e)) else "")
                for i, e in own.items()
            )
            line += f"; success in the owner's own conditions: {rates}"
        return line

    def round_ended(
        self,
        server_round: int,
        arrays: ArrayRecord,
        evaluation: MetricRecord | None,
        server_state: dict[str, np.ndarray],
    ) -> None:
        """The round's JSON, charts and report, a checkpoint (with the server optimiser's state) when
        the run keeps one, W&B, the progress line."""
        self.finish_writes()
        stopping.check(server_round)
        self.history.add(server_round, "global-arrays", {"tensors": len(arrays), "bytes": arrays.count_bytes()})
        if evaluation is not None:
            self.history.add(server_round, "server-evaluate", dict(evaluation))
            self.keep_if_best(server_round, arrays, dict(evaluation))
        # round 0's model is written once a round has trained; a checkpoint round's best after its checkpoint
        if server_round and self.unsaved and not self.checkpoint_holds_best(server_round):
            stopping.check(server_round)
            if server_round < self.run.num_server_rounds:
                self.write_best_while_clients_train()
            else:
                self.save(self.best["round"], *self.unsaved, "best")
                self.unsaved = None
        self.history.add(server_round, "best", self.best)
        prune_videos(self.history.run_dir, self.run.keep_checkpoints, self.best["round"] if self.best else None)
        self.history.add(server_round, "wall-s", time.perf_counter() - self.started)
        self.history.write_round(server_round)
        write_report(
            self.history.run_dir, self.history.snapshot(), self.run.to_flat(), self.best, self.run.num_server_rounds
        )
        if self.run.checkpoints_in(server_round):
            stopping.check(server_round)
            path = self.checkpoint(server_round, arrays, evaluation, server_state)
            if self.unsaved:  # this round's model is the best
                stopping.check(server_round)
                link_checkpoint(path, "best")
                self.unsaved = None
        if server_round == self.run.num_server_rounds and self.run.hf_repo_id:
            self.publish_best()
        self.tracker.log(server_round, self.history.round(server_round))
        if server_round:
            say(self.progress(server_round))
        elif evaluation is not None:
            say(self.starting_line(dict(evaluation)))

    def checkpoint(
        self,
        server_round: int,
        arrays: ArrayRecord,
        evaluation: MetricRecord | None,
        server_state: dict[str, np.ndarray],
    ) -> Path:
        """A lerobot pretrained-model directory of the global model and the server optimiser's state
        (staged and pushed for the Hub, tagged, with ``hf-push-every-checkpoint``); its path."""
        state = (self.run.server_optimiser, server_state)
        path = self.save(server_round, arrays, dict(evaluation) if evaluation else None, server_state=state)
        logger.info("Round {} checkpoint: {}", server_round, path)
        if removed := prune_checkpoints(self.history.run_dir, self.run.keep_checkpoints):
            logger.info("keep-checkpoints={}: removed the checkpoints of rounds {}", self.run.keep_checkpoints, removed)
        if self.run.hf_repo_id and self.run.hf_push_every_checkpoint:
            metrics = dict(evaluation) if evaluation else None
            publish(self.run, self.history.run_dir, path, server_round, self.entries(), metrics, self.push, tag=True)
        return path

    def checkpoint_holds_best(self, server_round: int) -> bool:
        """This round's model is the best and the round keeps a checkpoint: ``models/best`` is then
        made from the checkpoint's files once it is written, not written a second time."""
        return self.run.checkpoints_in(server_round) and self.best is not None and self.best["round"] == server_round

    def keep_if_best(self, server_round: int, arrays: ArrayRecord, evaluation: dict) -> None:
        """Remember this round's model as the best when it beats every earlier one (written to
        ``models/best`` at the round's end; round 0's only once a round trained, so a run that
        cannot train writes no model). With closed-loop evaluation the best is the highest success
        rate, ties going to the lower server action MSE; without, the lowest action MSE."""
        mse = float(evaluation["action-mse"])
        if server_round == 0:
            self.start_mse = mse
        candidate = {"round": server_round, "action-mse": mse}
        if "success-rate" in evaluation:
            candidate["success-rate"] = float(evaluation["success-rate"])
            candidate["episodes"] = int(evaluation.get("episodes", 0))
        if self.best is not None and rank(candidate) <= rank(self.best):
            return
        self.best = candidate
        self.unsaved = (arrays, evaluation)

    def write_best_while_clients_train(self) -> None:
        """Write the unsaved best model to ``models/best`` in a thread: it runs while Flower sends
        the next round's messages and waits for the clients' replies, when the server has nothing
        else to do. ``finish_writes`` waits for it."""
        (arrays, evaluation), best_round = self.unsaved, self.best["round"]
        self.unsaved = None
        stats = dict(self.client_stats)  # the round loop adds the next round's while this writes

        def write() -> None:
            try:
                stopping.check(best_round)
                self.save(best_round, arrays, evaluation, "best", client_stats=stats)
            except BaseException as err:  # raised in the round loop, by finish_writes
                self.write_error = err

        self.writing = threading.Thread(target=write, name="zk0-models-best")
        self.writing.start()

    def finish_writes(self) -> None:
        """Wait for models/best's write, if one is under way; its error (a stop, a full disk) is
        the round loop's."""
        if self.writing is not None:
            self.writing.join()
            self.writing = None
        if self.write_error is not None:
            error, self.write_error = self.write_error, None
            raise error

    def save(
        self,
        server_round: int,
        arrays: ArrayRecord,
        evaluation: dict | None,
        name: str | None = None,
        server_state: tuple[str, dict[str, np.ndarray]] | None = None,
        client_stats: dict[int, dict] | None = None,
    ):
        """``arrays`` as a checkpoint of ``server_round`` (under ``models/<name>``, if named), with
        ``client_stats`` (default: every client's known so far)."""
        client_stats = self.client_stats if client_stats is None else client_stats
        names = self.history.client_names
        per_client = {f"client_{i}_{names[i]}": stats for i, stats in sorted(client_stats.items())}
        with self.bundle.lock:
            set_trainable(self.bundle, arrays)
            bundle, run_dir = self.checkpoint_bundle(client_stats), self.history.run_dir
            return save_checkpoint(bundle, run_dir, server_round, per_client, name, evaluation, server_state)

    def entries(self) -> list[DatasetEntry]:
        """The datasets a model card lists: the clients that took part, and the server's."""
        return [self.registry.get(n) for n in self.history.participants().values()] + [self.eval_entry]

    def publish_best(self) -> None:
        """At the run's end, the best model (not necessarily the last) goes to the Hub."""
        if self.best is None:
            return
        path = self.history.run_dir / "models" / "best"
        evaluation = json.loads((path / ROUND_FILE).read_text())["server-evaluate"]
        publish(self.run, self.history.run_dir, path, self.best["round"], self.entries(), evaluation, self.push)

    def elapsed(self) -> float:
        """Seconds since this process's first round began (a resumed run counts from its resume)."""
        return time.perf_counter() - self.started

    def summary(self) -> str:
        """Which round ``models/best`` holds, as the run's last line says it."""
        if self.best is None:
            return "the server evaluated no round, so there is no models/best"
        start = "" if self.start_mse is None else f"; round 0: {self.start_mse:.4g}"
        success = f"success {success_text(self.best)}, " if "success-rate" in self.best else ""
        if self.best["round"] == 0:
            return (
                f"no round beat the starting model ({success}server action MSE {self.best['action-mse']:.4g}), "
                "so models/best is round 0, the model this run started from"
            )
        return f"models/best is round {self.best['round']} ({success}server action MSE {self.best['action-mse']:.4g}{start})"

    @staticmethod
    def starting_line(evaluation: dict) -> str:
        """Round 0's line: how the model the run starts from does on the server's evaluation."""
        success = f"{simulated}, " if (simulated := simulator_text(evaluation)) else ""
        return f"Round 0 (the starting model): {success}server action MSE {evaluation['action-mse']:.4g}"

    def checkpoint_bundle(self, client_stats: dict[int, dict]) -> PolicyBundle:
        """The global policy with processors carrying the clients' merged statistics (lerobot's aggregation)."""
        return with_merged_stats(self.bundle, list(client_stats.values()))

    def progress(self, server_round: int) -> str:
        """``Round 3/10: 4 clients trained, train loss 0.53, server action MSE 61.5, 12.3 s/round, about 1m 26s left``
        (the time left at the latest round's pace)."""
        record = self.history.round(server_round)
        trained = clients_trained(record)
        refused = sum("error" in c.get("train", {}) for c in record["clients"].values())
        loss = record.get("aggregate-train", {}).get("train-loss")
        server = record.get("server-evaluate", {})
        mse = server.get("action-mse")
        # The latest round's time: the first also builds every client, and would inflate an average.
        now = time.perf_counter()
        per_round, self.last_end = now - self.last_end, now
        left = round(per_round * (self.run.num_server_rounds - server_round))
        replied = record["clients"].items()
        steps = {int(i): int(c["train"]["local-steps"]) for i, c in replied if "local-steps" in c.get("train", {})}
        return (
            f"Round {server_round}/{self.run.num_server_rounds}: {trained} client{'s' * (trained != 1)} trained, "
            + (f"{refused} refused, " if refused else "")
            + (f"{steps_text(list(steps.values()), self.run.local_steps)}, " if self.run.local_time_s and steps else "")
            + (f"{stragglers}, " if (stragglers := stragglers_text(record, steps, self.run)) else "")
            + f"train loss {'-' if loss is None else f'{loss:.4g}'}, "
            f"server action MSE {'not evaluated' if mse is None else f'{mse:.4g}'}, "
            + (f"{simulated}, " if (simulated := simulator_text(server)) else "")
            + (f"{privacy}, " if (privacy := privacy_text(record, self.run)) else "")
            + f"{per_round:.1f} s/round, about {left // 60}m {left % 60:02d}s left"
            + (f", best round {self.best['round']}" if self.best else "")
        )


def privacy_text(record: dict, run: RunConfig) -> str:
    """``epsilon 2.31 of 8 (owner-level)``, or with record-level DP the most any owner's
    demonstrations have spent: what a round line says of the privacy spent so far."""
    if (spent := epsilon_spent(record)) is None:
        return ""
    if run.dp == "owner":
        return f"epsilon {spent:.3g} of {run.dp_epsilon_budget:g} (owner-level)"
    return f"epsilon up to {spent:.3g} of {run.dp_epsilon_budget:g} (each owner's demonstrations)"


def steps_text(steps: list[int], planned: int) -> str:
    """``12-75 of 75 steps``: what a time budget let the round's clients take."""
    low, high = min(steps), max(steps)
    return f"{low if low == high else f'{low}-{high}'} of {planned} steps"


def stragglers_text(record: dict, steps: dict[int, int], run: RunConfig) -> str:
    """``stragglers: client 2 (18 steps), client 3 (late)``: the clients a time budget let take
    less than half the steps of the round's fastest, and those whose update missed the deadline."""
    late = record.get("late", {})
    fastest = max(steps.values(), default=0)
    slow = [(i, n) for i, n in sorted(steps.items()) if run.local_time_s and n < STRAGGLER * fastest]
    named = [f"client {i} ({n} step{'s' * (n != 1)})" for i, n in slow]
    named += [f"client {i} (late)" for i in late.get("clients", [])]
    named += [f"node {n} (late)" for n in late.get("nodes", [])]
    return f"stragglers: {', '.join(named)}" if named else ""


def rank(best: dict) -> tuple[float, float]:
    """What makes a round's model better: a higher success rate (when measured), then a lower action MSE."""
    return (best.get("success-rate", 0.0), -best["action-mse"])
