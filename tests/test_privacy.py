"""Owner-level DP (Flower's mechanism and accountant), robust rules (Flower's) and record-level DP
(Opacus) on real Flower Messages, a real SmolVLA and real accountants: no mocks."""

from __future__ import annotations

import re

import dp_accounting
import numpy as np
import pytest
import torch
from flwr.app import ArrayRecord, Message, MessageType, MetricRecord, RecordDict
from flwr.serverapp.strategy import FedAvg

from tests.test_aggregation import Recorder, reply
from zk0.config import ConfigError, from_run_config
from zk0.federation.aggregation import ValidatingStrategy
from zk0.federation.privacy import OwnerLevelDP, calibrated_noise
from zk0.federation.robust import make_rule
from zk0.federation.server_optimisers import make_strategy
from zk0.federation.updates import array_signature

pytestmark = pytest.mark.usefixtures("flower_task")  # the tests play the ServerApp of run 1

SIZE = 40_000  # weights per update: the noise's spread is measured over this many values


def model(values: np.ndarray) -> ArrayRecord:
    """A global model (or an update's result) of two tensors holding ``values``."""
    return ArrayRecord(
        {"w": torch.from_numpy(values[: SIZE // 2].copy()), "v": torch.from_numpy(values[SIZE // 2 :].copy())}
    )


def flat(record: ArrayRecord) -> np.ndarray:
    return np.concatenate([record["w"].numpy().ravel(), record["v"].numpy().ravel()])


class Observer(Recorder):
    def record_privacy(self, rnd, spent):
        self.recorded.append(("privacy", rnd, spent["epsilon"]))

    def record_late(self, rnd, clients, nodes):
        self.recorded.append(("late", rnd, clients, nodes))


def strategy(
    run_config: str, owners: int = 4, server_optimiser: str = "fedavg", kind: type = ValidatingStrategy
) -> ValidatingStrategy:
    """zk0's strategy (or its subclass ``kind``) with the run's privacy and rule, its global model at zero."""
    run = from_run_config(parse(run_config))
    inner = make_strategy(server_optimiser, 0.0, 0.5, min_train_nodes=1)
    start = model(np.zeros(SIZE, dtype=np.float32))
    strat = kind(
        inner,
        expected=array_signature(start),
        evaluates_in=lambda rnd: False,
        observer=Observer([]),
        last_round=run.num_server_rounds,
        wire_dtype="float32",
        update_clip=run.update_clip,
        privacy=OwnerLevelDP(run, owners) if run.dp == "owner" else None,
        rule=make_rule(run, inner.weighted_by_key),
    )
    strat.current = start
    if server_optimiser != "fedavg":
        inner.current_arrays = {name: array.numpy() for name, array in start.items()}
    return strat


def parse(run_config: str) -> dict:
    """``"dp=owner dp-clip=1.0"`` as Flower hands a run config to the apps (typed values)."""
    values = {}
    for item in run_config.split():
        key, value = item.split("=")
        for kind in (int, float):
            try:
                values[key] = kind(value)
                break
            except ValueError:
                continue
        else:
            values[key] = value
    return values


def updates(count: int, norm: float, seed: int = 0) -> list[np.ndarray]:
    """``count`` random updates of L2 norm ``norm``."""
    rng = np.random.default_rng(seed)
    drawn = rng.normal(size=(count, SIZE)).astype(np.float32)
    return [u * (norm / np.linalg.norm(u)) for u in drawn]


def test_the_noise_matches_the_updates_averaged_when_a_deadline_drops_one_of_four():
    """Four owners sampled, the fourth's update past the deadline: the three updates are clipped
    to dp-clip and averaged, and the noise on the average has std ``z * clip / 3`` (Flower's
    wrapper would add ``z * clip / 4``, the noise for four). Over 40,000 weights the sample
    variance is within 5 of its standard errors (sqrt(2/n)) of the expected one: a false alarm
    about once in 1.7 million runs; the noise for four owners is 54 standard errors away."""
    z, clip = 2.0, 1.0
    strat = strategy(f"dp=owner dp-clip={clip} dp-noise-multiplier={z} num-server-rounds=5")
    strat.sampled = {1, 2, 3, 4}
    sent = updates(3, norm=10.0)
    result, _ = strat.aggregate_train(1, [reply(node, model(u), examples=10 * node) for node, u in enumerate(sent, 1)])
    clipped_mean = np.mean([u * (clip / 10.0) for u in sent], axis=0)  # equal weights, whatever the samples
    noise = flat(result) - clipped_mean
    expected = (z * clip / 3) ** 2
    tolerance = 5 * np.sqrt(2 / SIZE)
    assert abs(noise.var() / expected - 1) < tolerance, (noise.var(), expected)
    assert abs(noise.mean()) < 5 * np.sqrt(expected / SIZE)
    assert abs(noise.var() / (z * clip / 4) ** 2 - 1) > 10 * tolerance, "the noise is not the noise for four"
    assert strat.observer.recorded[-2][0] == "privacy"


def test_clipping_bounds_each_update_and_the_weights_are_equal():
    """Noise a millionth of the clip: the release is the equal-weight mean of the updates, each
    clipped to dp-clip, so an owner sending a million times the others moves it by clip / n at most."""
    strat = strategy("dp=owner dp-clip=0.5 dp-noise-multiplier=1e-6 dp-epsilon-budget=1e12 num-server-rounds=2")
    small, huge = updates(1, norm=0.25, seed=1)[0], updates(1, norm=1e6, seed=2)[0]
    replies = [reply(1, model(small), examples=1), reply(2, model(huge), examples=1000)]
    result, _ = strat.aggregate_train(1, replies)
    np.testing.assert_allclose(flat(result), (small + huge * (0.5 / 1e6)) / 2, atol=1e-5)
    scales = [r.content["metrics"]["update-scale"] for r in replies]
    assert scales[0] == 1.0 and scales[1] == pytest.approx(0.5 / 1e6)


def test_epsilon_after_n_rounds_is_the_accountants_own_figure():
    """Five releases: the epsilon the strategy reports equals Google's dp-accounting RDP accountant's
    for five Gaussian mechanisms at the same noise (no sampling amplification), and the noise
    calibrated for a budget over N rounds spends that budget in N rounds and no more."""
    z = 1.7
    strat = strategy(f"dp=owner dp-noise-multiplier={z} dp-epsilon-budget=1000 num-server-rounds=5")
    for rnd in range(1, 6):
        strat.aggregate_train(rnd, [reply(n, model(u), 1) for n, u in enumerate(updates(3, 2.0, seed=rnd), 1)])
    accountant = dp_accounting.rdp.RdpAccountant()
    accountant.compose(dp_accounting.SelfComposedDpEvent(dp_accounting.GaussianDpEvent(z), 5))
    spent = strat.privacy.spent()
    assert spent["releases"] == 5
    assert spent["epsilon"] == pytest.approx(accountant.get_epsilon(1e-5), rel=1e-9)

    noise = calibrated_noise(8.0, 1e-5, 20)
    budgeted = dp_accounting.rdp.RdpAccountant()
    budgeted.compose(dp_accounting.SelfComposedDpEvent(dp_accounting.GaussianDpEvent(noise), 20))
    assert 7.99 < budgeted.get_epsilon(1e-5) <= 8.0


def test_a_resumed_accountant_continues_and_a_spent_budget_is_one_sentence():
    run = from_run_config({"dp": "owner", "dp-noise-multiplier": 1.0, "dp-epsilon-budget": 20.0})
    first = OwnerLevelDP(run, 4)
    for _ in range(3):
        first.accountant.compose(first._event(4))
    resumed = OwnerLevelDP(run, 4, first.spent()["accountant"])
    assert resumed.spent()["epsilon"] == first.spent()["epsilon"] and resumed.spent()["releases"] == 3
    with pytest.raises(
        ConfigError, match=r"has spent epsilon 9.01 of dp-epsilon-budget=3 and one more round would pass it"
    ):
        OwnerLevelDP(from_run_config({"dp": "owner", "dp-noise-multiplier": 1.0, "dp-epsilon-budget": 3.0}), 4,
                     first.spent()["accountant"])  # fmt: skip
    with pytest.raises(ConfigError, match=r"'dp-noise-multiplier' = 0.1 spends more than dp-epsilon-budget=8"):
        OwnerLevelDP(from_run_config({"dp": "owner", "dp-noise-multiplier": 0.1}), 4)


@pytest.mark.parametrize(
    ("config", "sentence"),
    [
        ({"dp": "yes"}, "Run-config key 'dp' got 'yes'; expected one of ['off', 'owner', 'record']."),
        ({"aggregation": "mode"}, "Run-config key 'aggregation' got 'mode'; expected one of"),
        ({"dp": "owner", "aggregation": "krum"}, "'aggregation' = 'krum' (pre-aggregation='none') cannot go with dp="),
        (
            {"dp": "owner", "pre-aggregation": "nnm", "min-train-clients": 3},
            "(pre-aggregation='nnm') cannot go with dp=",
        ),
        ({"pre-aggregation": "bucketing"}, "Run-config key 'pre-aggregation' got 'bucketing'; expected one of"),
        ({"pre-aggregation": "nnm", "aggregation": "krum", "min-train-clients": 4}, "cannot go before Flower's"),
        (
            {"pre-aggregation": "nnm", "aggregation": "monna", "min-train-clients": 3},
            "'pre-aggregation' = 'nnm' cannot go before aggregation='monna': it would mix the server's trusted",
        ),
        (
            {"aggregation": "mda", "hostile-owners": 2, "min-train-clients": 4},
            "Run-config key 'min-train-clients' = 4 is too few for mda to outvote hostile-owners=2; expected "
            "min-train-clients of at least 5",
        ),
        ({"dp": "owner", "averaging": "fednova"}, "'averaging' = 'fednova' cannot go with dp='owner'"),
        ({"trim-fraction": 0.5}, "Run-config key 'trim-fraction' got 0.5; expected a value >= 0 and < 0.5"),
        ({"dp-delta": 1.0}, "Run-config key 'dp-delta' got 1.0; expected a value > 0 and < 1"),
        ({"dp-clip": 0.0}, "Run-config key 'dp-clip' got 0.0; expected a value > 0."),
    ],
)
def test_bad_privacy_settings_are_one_sentence(config, sentence):
    with pytest.raises(ConfigError) as refused:
        from_run_config(config)
    assert sentence in str(refused.value)


HOSTILE = 16  # the hostile owner's node: 15 honest owners before it


def hostile_round(run_config: str) -> tuple[float, float]:
    """15 honest owners whose updates share a direction (plus their own noise), one hostile owner
    sending the honest mean negated and scaled to 2.9x its norm (under update-clip=3 x the median):
    how far the combination lands from the honest mean, against the honest mean's own norm."""
    rng = np.random.default_rng(7)
    direction = rng.normal(size=SIZE).astype(np.float32)
    direction /= np.linalg.norm(direction)
    honest = [direction + 0.1 * u for u in updates(HOSTILE - 1, 1.0, seed=3)]
    target = np.mean(honest, axis=0)
    hostile = -2.9 * target * (np.median([np.linalg.norm(h) for h in honest]) / np.linalg.norm(target))
    strat = strategy(run_config, owners=HOSTILE)
    replies = [reply(n, model(u), examples=10) for n, u in enumerate([*honest, hostile], 1)]
    result, _ = strat.aggregate_train(1, replies)
    assert all(r.content["metrics"]["update-scale"] == 1.0 for r in replies), "the hostile update passes the clip"
    return float(np.linalg.norm(flat(result) - target)), float(np.linalg.norm(target))


def test_a_hostile_owner_that_passes_the_clip_moves_the_mean_and_not_the_robust_rules():
    """The mean is pulled a fifth of the honest update's length off by one owner of 16; Flower's
    median, trimmed mean and Multi-Krum land within a fifth of the mean's error of the honest mean,
    Krum (one honest update, with its own noise) within half of it."""
    mean_error, honest_norm = hostile_round("aggregation=mean")
    assert mean_error > 0.2 * honest_norm
    for rule in ("median", "trimmed-mean", "multi-krum"):
        error, _ = hostile_round(f"aggregation={rule} trim-fraction=0.1")
        assert error < 0.2 * mean_error, rule
    krum_error, _ = hostile_round("aggregation=krum")
    assert krum_error < 0.5 * mean_error


@pytest.mark.parametrize(
    ("rule", "bound"),
    [
        ("aggregation=geometric-median", 0.2),
        ("aggregation=centered-clipping", 0.2),
        ("aggregation=mda", 0.2),
        ("aggregation=meamed", 0.2),
        ("aggregation=caf", 0.2),
        ("aggregation=smea", 0.2),
        ("pre-aggregation=nnm", 0.2),  # then the mean
        ("pre-aggregation=nnm aggregation=geometric-median", 0.2),
        ("pre-aggregation=arc", 0.7),  # clips the hostile update to the largest honest one's norm, no more
    ],
)
def test_byzfls_rules_keep_a_hostile_owner_that_passes_the_clip_near_the_honest_mean(rule, bound):
    """The same round under ByzFL's rules and pre-aggregators (``f`` = 1 of 16): each lands within
    a fifth of the mean's error of the honest mean; ARC alone, which only clips, within 0.7 of it
    (the hostile update keeps its direction at an honest owner's norm: a third of the pull)."""
    mean_error, _ = hostile_round("aggregation=mean")
    error, _ = hostile_round(f"{rule} min-train-clients=3")
    assert error < bound * mean_error, (rule, error / mean_error)


def test_a_byzfl_rule_short_of_updates_keeps_the_global_model_and_draws_the_same_each_round():
    """Two updates cannot outvote one hostile owner: Meamed's round keeps the global model. SMEA
    draws its directions from a generator seeded by the round, so a resumed run combines the
    same updates into the same model, and the server's own random state is left as it was."""
    strat = strategy("aggregation=meamed min-train-clients=3")
    two = [reply(n, model(u), examples=10) for n, u in enumerate(updates(2, 1.0, seed=1), 1)]
    assert strat.aggregate_train(1, two) == (None, None)

    def smea_round() -> np.ndarray:
        strat = strategy("aggregation=smea min-train-clients=3")
        five = [reply(n, model(u), examples=10) for n, u in enumerate(updates(5, 1.0, seed=2), 1)]
        return flat(strat.aggregate_train(3, five)[0])

    torch.manual_seed(0)
    first = smea_round()
    after = torch.rand(1)
    torch.manual_seed(0)
    np.testing.assert_array_equal(smea_round(), first)
    assert torch.equal(torch.rand(1), after), "the server's torch generator is untouched"


@pytest.mark.parametrize(
    ("attack", "expected"),
    [
        ("sign-flipping", lambda honest, own: -honest.mean(axis=0)),
        ("ipm", lambda honest, own: -2.0 * honest.mean(axis=0)),
        ("alie", lambda honest, own: honest.mean(axis=0) + 1.5 * honest.std(axis=0, ddof=1)),
        ("mimic", lambda honest, own: honest[0]),
        ("negated", lambda honest, own: -2.9 * own),
    ],
)
def test_the_benchmarks_attacker_replaces_the_hostile_updates_before_zk0_checks_them(attack, expected):
    """``python -m zk0.bench privacy --attacks``: the hostile clients' (4 and 5) updates arrive at
    zk0's checks as ByzFL's attack of the three honest ones (or their own times the factor), each
    the same; with the mean and no clip (``update-clip=0``) the round's model is their average."""
    from zk0.bench.attacks import AttackedStrategy

    AttackedStrategy.attack, AttackedStrategy.hostile, AttackedStrategy.factor = attack, frozenset({4, 5}), -2.9
    sent = np.stack(updates(5, 1.0, seed=11))
    strat = strategy("update-clip=0", kind=AttackedStrategy)
    valid = strat.valid_updates(1, [reply(n, model(u), examples=10) for n, u in enumerate(sent, 1)])
    received = {int(m.content["client"]["index"]): flat(m.content["arrays"]) for m in valid}
    honest = sent[:3]
    for client in (4, 5):
        np.testing.assert_allclose(received[client], expected(honest, sent[client - 1]), rtol=1e-4, atol=1e-6)
    for client in (1, 2, 3):
        np.testing.assert_array_equal(received[client], sent[client - 1])


def test_the_trusted_direction_leaves_a_flipped_update_out_of_monnas_mean(caplog):
    """``aggregation = "monna"``: four honest owners and one sending their mean flipped; the server's
    own update (here the honest mean, as its public data would point) is the trusted one. MoNNA
    averages the five updates nearest to it, its own included: the flipped one gets no weight,
    and the server log names it."""
    from loguru import logger

    from zk0.federation.robust import ByzflRule

    rng = np.random.default_rng(5)
    direction = rng.normal(size=SIZE).astype(np.float32)
    honest = [direction + 0.1 * u for u in updates(4, 1.0, seed=9)]
    flipped = -np.mean(honest, axis=0)
    server = np.mean(honest, axis=0)
    asked = []

    def trusted(server_round: int, current: dict) -> torch.Tensor:
        asked.append((server_round, sorted(current)))
        return torch.from_numpy(server.copy())

    strat = strategy("update-clip=0 min-train-clients=3")
    strat.rule = ByzflRule("monna", "none", 1, trusted)
    said = []
    sink = logger.add(lambda message: said.append(str(message)), level="INFO")
    try:
        result, _ = strat.aggregate_train(2, [reply(n, model(u), 10) for n, u in enumerate([*honest, flipped], 1)])
    finally:
        logger.remove(sink)
    np.testing.assert_allclose(flat(result), np.mean([*honest, server], axis=0), rtol=1e-5, atol=1e-6)
    assert asked == [(2, ["v", "w"])], "the server's update is asked for once, from the round's global model"
    assert any("Round 2: left out the update(s) of client(s) [5], farthest from the server's own" in m for m in said)


def test_the_server_optimiser_steps_from_the_robust_combination():
    """Nesterov (the default) with momentum 0.5 steps 1.5x from a rule's combination, as from a mean."""
    honest = updates(3, 1.0, seed=5)
    strat = strategy("aggregation=median", server_optimiser="nesterov")
    result, _ = strat.aggregate_train(1, [reply(n, model(u), 10) for n, u in enumerate(honest, 1)])
    np.testing.assert_allclose(flat(result), 1.5 * np.median(honest, axis=0), rtol=1e-5, atol=1e-6)


def test_dp_off_is_flowers_weighted_mean_byte_for_byte():
    """``dp = "off"`` with the mean: the release is exactly what Flower's own FedAvg makes of the same
    updates (weighted by samples, nothing clipped, no noise), to the last bit of every weight."""
    sent = updates(3, norm=1.0, seed=7)
    strat = strategy("dp=off aggregation=mean num-server-rounds=2")
    result, _ = strat.aggregate_train(1, [reply(n, model(u), examples=7 * n) for n, u in enumerate(sent, 1)])
    plain = [
        Message(
            RecordDict({"arrays": model(u), "metrics": MetricRecord({"num-examples": 7 * n})}),
            reply_to=Message(RecordDict({}), dst_node_id=n, message_type=MessageType.TRAIN),
        )
        for n, u in enumerate(sent, 1)
    ]
    flowers, _ = FedAvg().aggregate_train(1, plain)
    assert flat(result).tobytes() == flat(flowers).tobytes()
    assert strat.privacy is None and strat.rule is None


@pytest.fixture
def private_client(registry):
    """Client 0 (6 training demonstrations) built for record-level DP, 4 demonstrations a step expected, one frame each."""
    from zk0.federation.client import build_client

    run = from_run_config(
        {
            "dp-batch": 4,
            "dp-frames": 1,
            "lr": 1e-3,
            "dp": "record",
            "dp-noise-multiplier": 1.0,
            "dp-epsilon-budget": 11.0,
        }
    )
    return build_client(run, registry.clients[0], registry.model_cameras())


@pytest.mark.parametrize("part", ["projections", "head"])
def test_the_small_data_recipe_steps_every_demonstration_once_and_trains_only_its_part(registry, part):
    """``dp-batch = 0`` draws every demonstration each step (q = 1 in the accountant), ``dp-frames``
    frames of each make one clipped gradient per demonstration, and ``dp-train`` moves its part of
    SmolVLA alone: the rest keeps the global model, and is trainable again after the step (a
    personal fine-tune trains it)."""
    from opacus.accountants import RDPAccountant

    from zk0.config import DP_PARTS
    from zk0.federation.client import build_client
    from zk0.learning.policy import snapshot
    from zk0.learning.training import metrics_tracker

    run = from_run_config({"dp": "record", "dp-batch": 0, "dp-frames": 3, "dp-train": part,
                           "dp-noise-multiplier": 1.0, "lr": 1e-3})  # fmt: skip
    client = build_client(run, registry.clients[0], registry.model_cameras())
    trainer = client.trainer
    demonstrations = len(trainer.split.train.episodes)
    assert trainer.sample_rate == 1.0
    batch = trainer._next_batch()
    episodes = batch["episode_index"].tolist()
    assert len(episodes) == 3 * demonstrations
    assert [episodes[i : i + 3] for i in range(0, len(episodes), 3)] == [[e] * 3 for e in trainer.split.train.episodes]
    before = snapshot(client.bundle)
    assert trainer._step(metrics_tracker(4, 100, 10), trainer._prepare(batch)) == 3 * demonstrations
    after = snapshot(client.bundle)
    moved = {name for name in before if not torch.equal(before[name], after[name])}
    private = {name for name in before if set(name.split(".")) & set(DP_PARTS[part])}
    assert moved == private and private, f"the {part} move, the rest keeps the global model"
    assert all(p.requires_grad for n, p in client.bundle.policy.named_parameters() if n in before)
    metrics = trainer.fit(1, 0.0, 1)
    accountant = RDPAccountant()
    accountant.step(noise_multiplier=1.0, sample_rate=1.0)
    accountant.step(noise_multiplier=1.0, sample_rate=1.0)
    assert metrics["local-steps"] == 1 and trainer.private_steps == 2, "the draw above and the round's step"
    assert metrics["record-epsilon"] == pytest.approx(accountant.get_epsilon(1e-5), rel=1e-9)


@pytest.mark.parametrize(
    ("keys", "said"),
    [
        (
            {"dp-train": "expert"},
            "Run-config key 'dp-train' got 'expert'; expected one of ['all', 'projections', 'head'].",
        ),
        ({"dp-train": "projections", "policy": "act"}, "names SmolVLA's modules, and policy='act' has none of them"),
        ({"dp-frames": 0}, "dp-frames"),
        ({"dp-batch": -1}, "dp-batch"),
    ],
)
def test_a_record_recipe_that_cannot_hold_is_refused_in_one_sentence(keys, said):
    with pytest.raises(ConfigError, match=re.escape(said)):
        from_run_config({"dp": "record", **keys})


def test_each_step_draws_each_demonstration_with_probability_q_and_one_frame_of_it(private_client):
    """A demonstration adds at most one frame to a step, and is drawn in about q of the steps
    (5-sigma binomial bounds over 300 draws); the draw is a function of the step, so a restored
    trainer draws what the first one did."""
    trainer = private_client.trainer
    dataset = trainer.split.train
    assert trainer.sample_rate == pytest.approx(4 / 6)
    drawn = {episode: 0 for episode in dataset.episodes}
    first = None
    for step in range(300):
        batch = trainer._next_batch()
        episodes = [] if batch is None else batch["episode_index"].tolist()
        assert len(episodes) == len(set(episodes)), f"step {step} drew a demonstration twice"
        for episode in episodes:
            drawn[episode] += 1
        first = batch if step == 0 else first
    q, n = trainer.sample_rate, 300
    for episode, count in drawn.items():
        assert abs(count - q * n) < 5 * np.sqrt(n * q * (1 - q)), (episode, count)
    trainer.restore(0, None)
    again = trainer._next_batch()
    assert torch.equal(again["index"], first["index"])


def test_record_level_epsilon_is_opacus_accountants_and_the_budget_ends_training(private_client):
    """Each private step is one sampled Gaussian mechanism in Opacus's RDP accountant; a round
    stops before the step that would pass dp-epsilon-budget, and the next round is refused in
    one sentence."""
    from opacus.accountants import RDPAccountant

    from zk0.learning.record_privacy import RecordBudgetSpent

    trainer = private_client.trainer
    metrics = trainer.fit(4, 0.0, 0)
    accountant = RDPAccountant()
    for _ in range(4):
        accountant.step(noise_multiplier=1.0, sample_rate=4 / 6)
    assert metrics["local-steps"] == 4
    assert metrics["record-epsilon"] == pytest.approx(accountant.get_epsilon(1e-5), rel=1e-9)
    assert metrics["record-epsilon"] < 11.0

    metrics = trainer.fit(100, 0.0, 4)
    steps = 4 + metrics["local-steps"]
    for _ in range(metrics["local-steps"]):
        accountant.step(noise_multiplier=1.0, sample_rate=4 / 6)
    assert metrics["record-epsilon"] == pytest.approx(accountant.get_epsilon(1e-5), rel=1e-9)
    assert metrics["record-epsilon"] <= 11.0 and metrics["local-steps"] == 2
    accountant.step(noise_multiplier=1.0, sample_rate=4 / 6)
    assert accountant.get_epsilon(1e-5) > 11.0, f"one more step than the {steps} taken passes the budget"
    from zk0.learning.training import metrics_tracker

    assert trainer._step(metrics_tracker(4, 100, 10), None) == 0, "a draw of no demonstration is a noise-only step"
    with pytest.raises(RecordBudgetSpent, match=r"its demonstrations have spent epsilon .* of dp-epsilon-budget=11"):
        trainer.fit(4, 0.0, steps)


def test_the_privacy_benchmark_plans_every_run_and_compares_on_paired_episodes(tmp_path, capsys):
    """What ``python -m zk0.bench privacy`` trains (its flwr runs are the federation tests' own),
    and its table: rates over every seed's episodes, each against the same seed's non-private
    model, pairwise; ``--seeds-from`` refuses figures of other settings in one sentence."""
    import json

    from zk0.bench.privacy import NON_PRIVATE, build_parser, earlier_seeds, planned_runs, summary

    args = build_parser().parse_args(["--epsilons", "8", "--aggregations", "mean", "nnm+meamed", "--hostile", "1", "3"])
    plan = planned_runs(args, owner_clip=0.3)
    assert list(plan) == [NON_PRIVATE, "record e=8", "owner e=8", "mean, negated x1", "mean, negated x3", "nnm+meamed",
                          "nnm+meamed, negated x1", "nnm+meamed, negated x3"]  # fmt: skip
    assert plan["owner e=8"]["keys"] == {"dp": "owner", "dp-clip": 0.3, "dp-epsilon-budget": 8.0, "dp-delta": 1e-5}
    assert plan["nnm+meamed, negated x3"] == {
        "keys": {"aggregation": "meamed", "pre-aggregation": "nnm", "hostile-owners": 3},
        "attack": ("negated", 3),
    }
    assert plan["nnm+meamed"]["keys"]["hostile-owners"] == 3, "its cost when nobody attacks, at the largest count"
    assert "owner e=8" not in planned_runs(args, owner_clip=None)
    quiet = build_parser().parse_args(["--epsilons", "8", "--aggregations", "mean", "--attacks"])
    assert list(planned_runs(quiet, owner_clip=None)) == [NON_PRIVATE, "record e=8"], "--attacks alone: none"
    compared = build_parser().parse_args(["--epsilons", "8", "--aggregations", "mean", "--attacks", "--recipes",
                                          "full:dp-batch=0 local-steps=3",
                                          "head:dp-train='head'"])  # fmt: skip
    plan = planned_runs(compared, owner_clip=None)
    assert list(plan) == [NON_PRIVATE, "record e=8 full", "record e=8 head"]
    ceiling = build_parser().parse_args(["--epsilons", "8", "2", "--aggregations", "mean", "--attacks", "--recipes",
                                         "full:dp-batch=0", "noiseless:dp-batch=0 dp-noise-multiplier=1e-12"])  # fmt: skip
    assert list(planned_runs(ceiling, owner_clip=None)) == [NON_PRIVATE, "record e=8 full", "record noiseless",
                                                            "record e=2 full"], "a recipe with its own noise runs once"  # fmt: skip
    assert plan["record e=8 full"]["keys"] == {"dp": "record", "dp-epsilon-budget": 8.0, "dp-delta": 1e-5,
                                               "dp-batch": 0, "local-steps": 3}  # fmt: skip

    outcomes = {NON_PRIVATE: [1, 1, 1, 1, 0, 0, 0, 0], "median": [1, 1, 0, 0, 0, 0, 0, 0]}
    success = {f"{label} seed {seed}": {"outcomes": o, "success-rate": sum(o) / 8} for label, o in outcomes.items()
               for seed in (42, 43)}  # fmt: skip
    table = summary(success, [42, 43], list(outcomes))
    assert table["median"]["success-rate"] == 0.25 and table["median"]["episodes"] == 16
    assert table["median"]["vs-non-private"] == pytest.approx(0.5)
    assert table["median"]["mcnemar-p"] == pytest.approx(0.125)  # 4 discordant episodes, all one way

    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"settings": {**vars(args), "owners": 8, "seeds": [41]}}))
    parser = build_parser()
    with pytest.raises(SystemExit):
        earlier_seeds(parser.parse_args(["--epsilons", "8", "--aggregations", "mean", "median",
                                         "--seeds-from", str(earlier)]), parser)  # fmt: skip
    said = capsys.readouterr().err
    assert f"--seeds-from {earlier} was run with --owners 8, this run with 16; expected the same settings" in said

    from zk0.bench.privacy import main

    with pytest.raises(SystemExit):
        main(["--public", "-1", "--output-dir", str(tmp_path / "bench")])
    assert "--public got -1; expected 0 (none) or more" in capsys.readouterr().err
    for recipes, said in (
        (["dp-batch=0"], "--recipes got 'dp-batch=0'; expected NAME:KEYS with a name of its own"),
        (["a:dp-batch=0", "a:dp-frames=2"], "--recipes got 'a:dp-frames=2'; expected NAME:KEYS with a name of its own"),
        (["x:dp-train='expert'"], "--recipes x: Run-config key 'dp-train' got 'expert'; expected one of"),
        (["lora:peft='lora'"], "--recipes lora: Run-config key 'peft' = 'lora' adapts a pretrained SmolVLA"),
    ):
        with pytest.raises(SystemExit):
            main(["--recipes", *recipes, "--output-dir", str(tmp_path / "bench")])
        assert said in capsys.readouterr().err
    assert not (tmp_path / "bench").exists(), "refused before anything is written"
    for argv in (["--aggregations", "monna"], ["--pretrain-steps", "10"]):
        with pytest.raises(SystemExit):
            main([*argv, "--owners", "4", "--output-dir", str(tmp_path / "bench")])
        assert (
            "--pretrain-steps and --aggregations monna need public sets; expected --public N" in capsys.readouterr().err
        )
    assert "public = 0" in (tmp_path / "bench" / "owners-registry.toml").read_text(), "refused before any recording"


def test_the_noise_crossover_isolates_record_level_noise_and_solves_for_the_owners():
    """The benchmark's comparison of the two kinds: record-level noise is a measured share of an
    owner's update, its noise multiplier Opacus's for the run, and the owners owner-level needs
    follow from its own figures."""
    import argparse
    import math

    from opacus.accountants.utils import get_noise_multiplier

    from zk0.bench.privacy import noise_crossover
    from zk0.data.registry import PROJECT_ROOT

    args = argparse.Namespace(model="tiny", start=None, rounds=4, local_steps=3, lr=1e-3, delta=1e-5)
    found = noise_crossover(args, PROJECT_ROOT / "pyproject.toml", 8.0)
    assert 0.0 < found["record-noise-share"] < 100.0
    assert -1.0 <= found["record-update-cosine"] < 1.0, "the noise turns the update"
    rate = found["sample-rate"]
    assert rate == 1.0, "dp-batch = 0: every demonstration, every step"
    expected = get_noise_multiplier(target_epsilon=8.0, target_delta=1e-5, sample_rate=rate, steps=12, accountant="rdp")
    assert found["record-noise-multiplier"] == pytest.approx(expected)
    share = found["owner-noise-multiplier"] * math.sqrt(found["weights"])
    assert found["owners-to-match"] == math.ceil((share / found["record-noise-share"]) ** 2)


@pytest.mark.parametrize("policy", ["act", "diffusion"])
def test_record_level_dp_trains_every_policy_zk0_federates(registry, policy):
    """Per-sample gradients come from one forward and backward per sample through the policy's own
    ``forward``, not from Opacus's layer hooks, so ACT and Diffusion Policy (whose loss draws its
    own noise and timestep) take private steps too: every parameter moves, and the step is counted."""
    from zk0.federation.client import build_client
    from zk0.learning.policy import snapshot

    run = from_run_config({"policy": policy, "batch-size": 4, "lr": 1e-3, "dp": "record", "dp-noise-multiplier": 1.0})
    client = build_client(run, registry.clients[0], registry.model_cameras())
    before = snapshot(client.bundle)
    metrics = client.trainer.fit(2, 0.0, 0)
    after = snapshot(client.bundle)
    assert metrics["local-steps"] == 2 and 0 < metrics["record-epsilon"] < 8.0
    assert all(not torch.equal(before[name], after[name]) for name in before), "the noise reaches every parameter"
