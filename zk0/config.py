"""The typed run config: every ``[tool.flwr.app.config]`` key, read from the Flower ``Context``.

Flower merges ``pyproject.toml`` defaults with ``--run-config`` overrides; this module
turns that flat dict into a ``RunConfig``, checks every value once before any training
starts and fails with one sentence naming the key, the value and what is allowed.
The dataclass defaults equal the pyproject table (a test keeps them so), which also
lets the Python simulation API run with an empty run config.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from typing import Any

from loguru import logger

from zk0.common.errors import Zk0Error
from zk0.sim.tasks import SIM_SPECS

DEVICES = ("auto", "cpu", "cuda", "mps")
VIDEO_BACKENDS = ("torchcodec", "pyav")
WIRE_DTYPES = ("bfloat16", "float32")  # zk0.federation.wire encodes them
OFFLINE_MODELS = ("tiny", "tiny-128", "full-size")  # built from a generated backbone with random weights (zk0.learning.policy)
POLICIES = ("smolvla", "act", "diffusion")  # the lerobot policy types a fresh model is built as (zk0.learning.policy_types)
PEFT_METHODS = ("none", "lora")  # zk0.learning.adapters
LORA_AVERAGES = ("b", "ab")  # what a LoRA federation trains and averages (zk0.learning.adapters)
# SmolVLA's small state, action and time projections: by default trained in full next to the adapters
# rather than adapted (PEFT's modules_to_save; docs/learning.md measured why).
LORA_FULL_MODULES = "state_proj,action_in_proj,action_out_proj,action_time_mlp_in,action_time_mlp_out"
# server-optimiser -> its server-lr when the run config leaves it at 0 (zk0.federation.server_optimisers)
DEFAULT_SERVER_LR = {"fedavg": 1.0, "fedavgm": 1.0, "nesterov": 1.0, "fedadam": 1e-2, "fedyogi": 1e-2}
SERVER_OPTIMISERS = tuple(DEFAULT_SERVER_LR)
AVERAGINGS = ("fednova", "samples")  # how updates of unequal work are averaged (zk0.federation.aggregation)
DP_KINDS = (
    "off",
    "owner",
    "record",
)  # differential privacy: none, of each owner (server), of each demonstration (client)
# How the server combines the round's updates (zk0.federation.robust): the weighted mean, or a robust rule of
# Flower's or of ByzFL's; ByzFL's pre-aggregators may come first (before ByzFL's rules or the mean)
FLOWER_RULES = ("median", "trimmed-mean", "krum", "multi-krum")
BYZFL_RULES = ("geometric-median", "centered-clipping", "mda", "meamed", "caf", "smea", "monna")
AGGREGATIONS = ("mean", *FLOWER_RULES, *BYZFL_RULES)
COUNTING_RULES = ("mda", "meamed", "caf", "smea", "monna")  # ByzFL's rules that take hostile-owners (as f): n > 2 f
PRE_AGGREGATIONS = ("none", "nnm", "arc")
# dp-train -> the SmolVLA modules an owner trains under dp = "record" (None: every trainable parameter;
# head: the action expert's output projection, the last layer, Mehta et al. 2023);
# the rest stay at the global model, so the noise spreads over fewer coordinates (docs/privacy.md)
DP_PARTS = {"all": None, "projections": tuple(LORA_FULL_MODULES.split(",")), "head": ("action_out_proj",)}


class ConfigError(Zk0Error):
    """A bad run-config value; the message is one sentence naming key, value and what is allowed."""


@dataclass(frozen=True)
class RunConfig:
    """The federation's knobs, one field per run-config key (``-`` in keys becomes ``_``)."""

    num_server_rounds: int = 1
    local_steps: int = 2
    local_time_s: float = 0.0  # a client trains at most this long a round (at least one step); 0 = every local step
    averaging: str = "samples"  # updates of clients that took different steps: samples (weighted) or fednova
    local_epochs: int = 0  # deprecated alias of local_steps, 0 = unset
    batch_size: int = 8
    lr: float = 1e-4
    proximal_mu: float = 0.0
    server_optimiser: str = "nesterov"  # how the server steps from the averaged update (zk0.federation.server_optimisers)
    server_lr: float = 0.0  # the server optimiser's learning rate; 0 = its default
    server_momentum: float = 0.5  # FedAvgM's and Nesterov's momentum
    update_clip: float = 3.0  # an update above this times the others' median is scaled to it; 0 = off
    fraction_train: float = 1.0
    min_train_clients: int = 2
    fraction_evaluate: float = 1.0
    eval_frequency: int = 1
    eval_episodes: int = 2
    eval_batches: int = 4
    checkpoint_interval: int = 5
    keep_checkpoints: int = 2  # the newest N checkpoints stay on disk (models/best besides); 0 = every one
    model: str = "tiny"
    policy: str = "smolvla"  # the lerobot policy type of a fresh model; a checkpoint's own type must match
    chunk_size: int = 10
    device: str = "auto"
    seed: int = 42
    num_workers: int = 0  # -1 = chosen from the CPUs this client has (zk0.data.loaders.loader_workers)
    tolerance_s: float = 1e-4
    video_backend: str = "torchcodec"
    frame_cache_gb: float = 20.0  # disk for decoded frames per dataset (zk0.data.frames); 0 = decode every batch
    max_skip_fraction: float = 0.1
    output_dir: str = "outputs"
    registry: str = ""
    server_eval_dataset: str = "synth-so100-eval"
    use_wandb: bool = False
    hf_repo_id: str = ""
    hf_push_every_checkpoint: bool = False
    resume_from: str = ""
    wire_dtype: str = "bfloat16"
    compile: bool = False  # lerobot's compile_model; zk0.learning.policy keeps the compiled code in $ZK0_CACHE
    phase_timeout: float = 3600.0  # seconds the server waits for a round's train (or evaluate) replies
    round_deadline_s: float = 0.0  # a round's train replies not in by then are dropped (not round 1); 0 = off
    wait_for_owners_s: float = 300.0  # a round with fewer than min-train-clients connected ends the run after this; 0 = never
    peft: str = "none"  # "lora": train and exchange lerobot's LoRA adapters instead of all trainable weights
    lora_rank: int = 16
    lora_alpha: float = 32.0
    lora_targets: str = ""  # a regex of module names; "" = SmolVLA's own default targets
    lora_full_modules: str = LORA_FULL_MODULES  # comma-separated, trained in full next to the adapters; "" = none
    lora_average: str = "b"  # b: A frozen at its seeded start, B trained and averaged; ab: both trained and averaged
    sim_eval_episodes: int = 0  # closed-loop episodes in the simulator per evaluated round (zk0.sim); 0 = off
    sim_episode_length: int = 300  # steps before a closed-loop episode ends unsolved (lerobot's env.episode_length; a sort's: twice)
    personal_steps: int = 0  # each client fine-tunes the global model this many steps when it evaluates (zk0.federation.personal)
    personal_mu: float = 0.0  # the personal model's proximal pull toward the global one while it fine-tunes
    personal_lr: float = 0.0  # that fine-tuning's peak learning rate; 0 = a quarter of lr
    personal_frequency: int = 0  # fine-tune when evaluating every Nth round and the last; 0 = in checkpoint rounds
    image_transforms: bool = False  # lerobot's ImageTransforms on every training frame, on the owner's machine
    image_transforms_max: int = 3  # at most this many of them per frame (lerobot's max_num_transforms)
    image_transforms_brightness: float = 0.2  # brightness drawn within 1 +- this (lerobot's default 0.2)
    dp: str = "off"  # differential privacy: off | owner (Flower's central DP) | record (DP-SGD on each owner's machine)
    dp_clip: float = 1.0  # owner: the L2 bound on each owner's update; record: on each demonstration's gradient
    dp_noise_multiplier: float = (
        0.0  # the Gaussian noise's std over dp-clip; 0 = the least that keeps the run within the budget
    )
    dp_delta: float = 1e-5  # the delta of (epsilon, delta)-DP
    dp_epsilon_budget: float = 8.0  # the run stops before a release would spend more epsilon than this
    dp_batch: int = 0  # record: demonstrations each private step draws, in expectation; 0 = every one (q = 1)
    dp_frames: int = 8  # record: frames of each drawn demonstration averaged into its one clipped gradient
    dp_train: str = "all"  # record: what the owner trains privately (DP_PARTS); the rest keeps the global model
    aggregation: str = "mean"  # mean (weighted), or a robust rule of Flower's or ByzFL's (zk0.federation.robust)
    pre_aggregation: str = "none"  # none | nnm | arc: ByzFL's pre-aggregator before ByzFL's rule or the mean
    trim_fraction: float = 0.2  # trimmed-mean: the share of the largest and of the smallest values cut per weight
    hostile_owners: int = 1  # how many owners the rule (Krum, ByzFL's f) must outvote

    @property
    def personal_peak_lr(self) -> float:
        """The personal fine-tune's peak rate: ``personal-lr``, else a quarter of the federation's
        (at the federation's own rate the fine-tune overshot a converged model: docs/learning.md)."""
        return self.personal_lr or self.lr / 4

    @property
    def total_steps(self) -> int:
        """Optimizer steps a client that trains every round takes over the whole run."""
        return self.num_server_rounds * self.local_steps

    def evaluates_in(self, server_round: int) -> bool:
        """Evaluation runs every ``eval-frequency`` rounds and always after the last one."""
        return server_round % self.eval_frequency == 0 or server_round == self.num_server_rounds

    def checkpoints_in(self, server_round: int) -> bool:
        """A checkpoint every ``checkpoint-interval`` rounds and always after the last one."""
        return server_round > 0 and (
            server_round % self.checkpoint_interval == 0 or server_round == self.num_server_rounds
        )

    def personalises_in(self, server_round: int) -> bool:
        """Whether a client that evaluates ``server_round``'s global model fine-tunes its personal
        model from it: every ``personal-frequency`` rounds and after the last, or by default in the
        checkpoint rounds. A full-size owner pays ``personal-steps`` and a 1.8 GB write each time, so
        by default only for models a run keeps, not for every evaluation that the next replaces."""
        if self.personal_frequency:
            return server_round % self.personal_frequency == 0 or server_round == self.num_server_rounds
        return self.checkpoints_in(server_round)

    def to_flat(self) -> dict[str, Any]:
        """The run-config form (kebab-case keys), e.g. for round JSON files."""
        return {f.name.replace("_", "-"): getattr(self, f.name) for f in fields(self)}


# (lowest allowed, highest allowed, whether the lowest is excluded)
_RANGES: dict[str, tuple[float, float | None, bool]] = {
    "num_server_rounds": (1, None, False),
    "local_steps": (1, None, False),
    "local_epochs": (0, None, False),
    "batch_size": (1, None, False),
    "lr": (0, 1, True),
    "proximal_mu": (0, None, False),
    "local_time_s": (0, None, False),
    "server_lr": (0, None, False),
    "server_momentum": (0, 0.99, False),
    "fraction_train": (0, 1, True),
    "min_train_clients": (1, None, False),
    "fraction_evaluate": (0, 1, False),
    "eval_frequency": (1, None, False),
    "eval_episodes": (1, None, False),
    "eval_batches": (1, None, False),
    "checkpoint_interval": (1, None, False),
    "keep_checkpoints": (0, None, False),
    "chunk_size": (1, None, False),
    "num_workers": (-1, None, False),
    "tolerance_s": (0, None, True),
    "frame_cache_gb": (0, None, False),
    "max_skip_fraction": (0, 1, False),
    "phase_timeout": (0, None, True),
    "round_deadline_s": (0, None, False),
    "wait_for_owners_s": (0, None, False),
    "lora_rank": (1, None, False),
    "lora_alpha": (0, None, True),
    "sim_eval_episodes": (0, None, False),
    "sim_episode_length": (1, None, False),
    "personal_steps": (0, None, False),
    "personal_mu": (0, None, False),
    "personal_lr": (0, 1, False),
    "personal_frequency": (0, None, False),
    "image_transforms_max": (1, 6, False),
    "image_transforms_brightness": (0, 1, True),
    "dp_clip": (0, None, True),
    "dp_noise_multiplier": (0, None, False),
    "dp_delta": (0, 1, True),
    "dp_epsilon_budget": (0, None, True),
    "dp_batch": (0, None, False),
    "dp_frames": (1, None, False),
    "trim_fraction": (0, None, False),
    "hostile_owners": (0, None, False),
}


def from_run_config(run_config: dict[str, Any]) -> RunConfig:
    """Validate Flower's flat run config and build a ``RunConfig``."""
    known = {f.name: f for f in fields(RunConfig)}
    values: dict[str, Any] = {}
    for key, value in run_config.items():
        name = key.replace("-", "_")
        if name not in known:
            allowed = ", ".join(sorted(k.replace("_", "-") for k in known))
            raise ConfigError(f"Unknown run-config key {key!r}; allowed keys are: {allowed}.")
        values[name] = _coerce(key, value, known[name].type)
    for name, value in values.items():
        _check_range(name, value)
    if values.get("local_epochs"):
        logger.warning("Run-config key 'local-epochs' is deprecated; it now means local-steps.")
        values["local_steps"] = values["local_epochs"]
    cfg = RunConfig(**values)
    _check_choices(cfg)
    return cfg


def _coerce(key: str, value: Any, type_name: str) -> Any:
    """Accept ints where floats are expected; refuse everything else of the wrong type."""
    expected = {"int": int, "float": float, "str": str, "bool": bool}[type_name]
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, bool) != (expected is bool) or not isinstance(value, expected):
        raise ConfigError(f"Run-config key {key!r} got {value!r} ({type(value).__name__}); expected a {type_name}.")
    return value


def _check_range(name: str, value: Any) -> None:
    if name not in _RANGES:
        return
    low, high, open_low = _RANGES[name]
    too_low = value <= low if open_low else value < low
    if too_low or (high is not None and value > high):
        bound = f"{'>' if open_low else '>='} {low}" + (f" and <= {high}" if high is not None else "")
        raise ConfigError(f"Run-config key {name.replace('_', '-')!r} got {value!r}; expected a value {bound}.")


def _check_choices(cfg: RunConfig) -> None:
    if cfg.device not in DEVICES and not re.fullmatch(r"cuda:\d+", cfg.device):
        raise ConfigError(
            f"Run-config key 'device' got {cfg.device!r}; expected one of {list(DEVICES)} or cuda:N (N a GPU index)."
        )
    if cfg.wire_dtype not in WIRE_DTYPES:
        raise ConfigError(f"Run-config key 'wire-dtype' got {cfg.wire_dtype!r}; expected one of {list(WIRE_DTYPES)}.")
    if cfg.video_backend not in VIDEO_BACKENDS:
        raise ConfigError(
            f"Run-config key 'video-backend' got {cfg.video_backend!r}; expected one of {list(VIDEO_BACKENDS)}."
        )
    if cfg.hf_repo_id and not re.fullmatch(r"[\w.-]+/[\w.-]+", cfg.hf_repo_id):
        raise ConfigError(f"Run-config key 'hf-repo-id' got {cfg.hf_repo_id!r}; expected '<owner>/<model-name>'.")
    if not cfg.model:
        raise ConfigError("Run-config key 'model' is empty; expected 'tiny', a Hub repo id or a local directory.")
    _check_policy(cfg)
    _check_peft(cfg)
    _check_server_optimiser(cfg)
    _check_privacy(cfg)
    if cfg.sim_eval_episodes and cfg.server_eval_dataset not in SIM_SPECS:
        raise ConfigError(
            f"Run-config key 'sim-eval-episodes' = {cfg.sim_eval_episodes} rolls the model out in the simulator, "
            f"and server-eval-dataset={cfg.server_eval_dataset!r} was not recorded there; expected one of "
            f"{sorted(n for n, s in SIM_SPECS.items() if s.role == 'server')} (registry='configs/sim-registry.toml', "
            "or ./train.sh --preset sim) or sim-eval-episodes=0."
        )


def _check_server_optimiser(cfg: RunConfig) -> None:
    """A known optimiser; plain averaging has no learning rate; a clip that can only scale down."""
    if cfg.server_optimiser not in SERVER_OPTIMISERS:
        raise ConfigError(
            f"Run-config key 'server-optimiser' got {cfg.server_optimiser!r}; expected one of {list(SERVER_OPTIMISERS)}."
        )
    if cfg.server_optimiser == "fedavg" and cfg.server_lr not in (0.0, 1.0):
        raise ConfigError(
            f"Run-config key 'server-lr' got {cfg.server_lr!r}, and server-optimiser='fedavg' takes the average as "
            "it is; expected 0 (or 1), or server-optimiser='fedavgm' with server-momentum=0 for a scaled step."
        )
    if cfg.averaging not in AVERAGINGS:
        raise ConfigError(f"Run-config key 'averaging' got {cfg.averaging!r}; expected one of {list(AVERAGINGS)}.")
    if 0 < cfg.update_clip < 1 or cfg.update_clip < 0:
        raise ConfigError(
            f"Run-config key 'update-clip' got {cfg.update_clip!r}; expected 0 (off) or a factor >= 1 "
            "(an update larger than that many times the others' median is scaled down to the median)."
        )


def _check_policy(cfg: RunConfig) -> None:
    """A policy type zk0 builds; LoRA only where lerobot adapts it (SmolVLA)."""
    if cfg.policy not in POLICIES:
        raise ConfigError(f"Run-config key 'policy' got {cfg.policy!r}; expected one of {list(POLICIES)}.")
    if cfg.policy != "smolvla" and cfg.compile:
        raise ConfigError(
            f"Run-config key 'compile' = true compiles SmolVLA's training forward (lerobot's compile_model), and "
            f"zk0 compiles no other policy (policy={cfg.policy!r}); expected compile=false."
        )
    if cfg.policy != "smolvla" and cfg.peft != "none":
        raise ConfigError(
            f"Run-config key 'peft' = {cfg.peft!r} adapts SmolVLA, and policy={cfg.policy!r} trains in full; "
            "expected peft='none'."
        )


def _check_peft(cfg: RunConfig) -> None:
    """LoRA keys: a known method and averaging, a target regex that compiles, a pretrained base."""
    if cfg.peft not in PEFT_METHODS:
        raise ConfigError(f"Run-config key 'peft' got {cfg.peft!r}; expected one of {list(PEFT_METHODS)}.")
    if cfg.lora_average not in LORA_AVERAGES:
        raise ConfigError(
            f"Run-config key 'lora-average' got {cfg.lora_average!r}; expected one of {list(LORA_AVERAGES)}."
        )
    try:
        re.compile(cfg.lora_targets)
    except re.error as err:
        raise ConfigError(
            f"Run-config key 'lora-targets' got {cfg.lora_targets!r}, which is not a regular expression ({err})."
        ) from None
    if cfg.peft == "lora" and cfg.model in OFFLINE_MODELS:
        raise ConfigError(
            f"Run-config key 'peft' = 'lora' adapts a pretrained SmolVLA, and model={cfg.model!r} has random "
            "weights (lerobot refuses LoRA from scratch); expected 'model' to be a checkpoint folder such as "
            "outputs/<run>/models/checkpoint_round_<N> or a Hub id such as lerobot/smolvla_base."
        )


def _check_outvoting(cfg: RunConfig) -> None:
    """A ByzFL rule or pre-aggregator that counts the hostile owners needs more than twice as many
    updates a round; a round with fewer would keep the global model, so say so before any round."""
    counts = cfg.aggregation in COUNTING_RULES or cfg.pre_aggregation != "none"
    if counts and cfg.min_train_clients <= 2 * cfg.hostile_owners:
        rule = cfg.aggregation if cfg.pre_aggregation == "none" else f"{cfg.pre_aggregation} then {cfg.aggregation}"
        raise ConfigError(
            f"Run-config key 'min-train-clients' = {cfg.min_train_clients} is too few for {rule} to outvote "
            f"hostile-owners={cfg.hostile_owners}; expected min-train-clients of at least {2 * cfg.hostile_owners + 1} "
            "(more than twice the hostile owners), or fewer hostile-owners."
        )


def _check_privacy(cfg: RunConfig) -> None:
    """A known DP kind and aggregation, and no combination whose guarantee would not hold.

    Owner-level DP bounds what one owner adds to the plain average: a robust rule (a median,
    Krum) or FedNova's step weights change that bound, so the accountant's epsilon would be
    wrong. Its own fixed clip replaces ``update-clip`` (a clip relative to the others' median
    lets one owner change how much every other owner counts)."""
    if cfg.dp not in DP_KINDS:
        raise ConfigError(f"Run-config key 'dp' got {cfg.dp!r}; expected one of {list(DP_KINDS)}.")
    if cfg.aggregation not in AGGREGATIONS:
        raise ConfigError(
            f"Run-config key 'aggregation' got {cfg.aggregation!r}; expected one of {list(AGGREGATIONS)}."
        )
    if cfg.dp_delta >= 1:
        raise ConfigError(
            f"Run-config key 'dp-delta' got {cfg.dp_delta!r}; expected a value > 0 and < 1 (well below one over the "
            "number of owners or demonstrations, such as the default 1e-5)."
        )
    if cfg.trim_fraction >= 0.5:
        raise ConfigError(
            f"Run-config key 'trim-fraction' got {cfg.trim_fraction!r}; expected a value >= 0 and < 0.5 (the share "
            "cut from each end, so some values are left to average)."
        )
    if cfg.pre_aggregation not in PRE_AGGREGATIONS:
        raise ConfigError(
            f"Run-config key 'pre-aggregation' got {cfg.pre_aggregation!r}; expected one of {list(PRE_AGGREGATIONS)}."
        )
    if cfg.pre_aggregation != "none" and cfg.aggregation in FLOWER_RULES:
        raise ConfigError(
            f"Run-config key 'pre-aggregation' = {cfg.pre_aggregation!r} cannot go before Flower's "
            f"aggregation={cfg.aggregation!r}, which takes the owners' updates as they came; expected 'mean' or one "
            f"of ByzFL's rules {list(BYZFL_RULES)}, or pre-aggregation='none'."
        )
    if cfg.pre_aggregation != "none" and cfg.aggregation == "monna":
        raise ConfigError(
            f"Run-config key 'pre-aggregation' = {cfg.pre_aggregation!r} cannot go before aggregation='monna': it "
            "would mix the server's trusted update with the owners'; expected pre-aggregation='none'."
        )
    _check_outvoting(cfg)
    if cfg.dp_train not in DP_PARTS:
        raise ConfigError(f"Run-config key 'dp-train' got {cfg.dp_train!r}; expected one of {list(DP_PARTS)}.")
    if cfg.dp_train != "all" and cfg.policy != "smolvla":
        raise ConfigError(
            f"Run-config key 'dp-train' = {cfg.dp_train!r} names SmolVLA's modules, and policy={cfg.policy!r} has "
            "none of them; expected dp-train='all'."
        )
    if cfg.dp == "owner" and (cfg.aggregation != "mean" or cfg.pre_aggregation != "none"):
        raise ConfigError(
            f"Run-config key 'aggregation' = {cfg.aggregation!r} (pre-aggregation={cfg.pre_aggregation!r}) cannot go "
            "with dp='owner': the accountant's epsilon holds for the mean of clipped updates only; expected "
            "aggregation='mean' with pre-aggregation='none', or dp='record' or 'off'."
        )
    if cfg.dp == "owner" and cfg.averaging == "fednova":
        raise ConfigError(
            "Run-config key 'averaging' = 'fednova' cannot go with dp='owner': FedNova weights each update by its "
            "steps, and owner-level DP needs every owner to count alike; expected averaging='samples'."
        )
