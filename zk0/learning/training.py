"""Local training with lerobot's ``update_policy`` plus FedProx, and seeded evaluation.

FedProx adds ``(mu/2)·||w - w_global||²`` over the trainable parameters. Its gradient,
``mu·(w - w_global)``, is added by a hook on each trainable parameter, so lerobot's
``update_policy`` (autocast, backward, clipping, optimizer and scheduler step) runs
untouched. The learning-rate schedule is a function of the global step
(``(round - 1) × local-steps``), so its warm-up happens once per federation, not once
per round, whichever rounds a client happens to be sampled in.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import dataclass, field, replace

import psutil
import torch
from accelerate import Accelerator
from flwr.app import ArrayRecord
from lerobot.configs import PreTrainedConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets import compute_sampler_state
from lerobot.optim.factory import make_optimizer_and_scheduler
from lerobot.optim.schedulers import LRSchedulerConfig
from lerobot.policies.common.vla_utils import resize_with_pad
from lerobot.scripts.lerobot_train import update_policy
from lerobot.transforms.transforms import ImageTransforms
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS
from lerobot.utils.logging_utils import AverageMeter, MetricsTracker
from loguru import logger
from torch.utils.data import DataLoader

from zk0.common.errors import Zk0Error
from zk0.config import RunConfig
from zk0.data.loaders import DatasetSplit, prepare_batch
from zk0.internals import set_last_lr
from zk0.learning.augmentation import augment, frame_transforms
from zk0.learning.policy import PolicyBundle, rng_devices


class TrainingError(Zk0Error):
    """A round a client cannot complete because of its data (too many unreadable batches)."""


def check_skips(name: str, what: str, skipped: int, done: int, max_fraction: float, finished: bool = False) -> None:
    """Refuse a dataset once more than ``max-skip-fraction`` of its batches could not be decoded
    (judged after 3 skips, or when ``finished`` with nothing read at all)."""
    fraction = skipped / max(1, skipped + done)
    if (skipped >= 3 and fraction > max_fraction) or (finished and skipped and not done):
        raise TrainingError(
            f"Dataset {name!r}: {skipped} of {skipped + done} {what} batches could not be decoded, "
            f"more than max-skip-fraction={max_fraction}."
        )


class FedProx:
    """The proximal term as gradient hooks anchored at the round's global weights."""

    def __init__(self, params: dict[str, torch.nn.Parameter]):
        self.params = params
        self.mu = 0.0
        self.anchor: dict[str, torch.Tensor] = {}
        self._handles = [p.register_hook(self._hook(name)) for name, p in params.items()]

    def _hook(self, name: str):
        def add_proximal_grad(grad: torch.Tensor) -> torch.Tensor:
            if self.mu == 0.0:
                return grad
            return grad + self.mu * (self.params[name].detach() - self.anchor[name]).to(grad.dtype)

        return add_proximal_grad

    def anchor_at(self, mu: float) -> None:
        """Remember the current (global) weights as the proximal centre for this round."""
        self.mu = mu
        self.anchor = {name: p.detach().clone() for name, p in self.params.items()}

    def release(self) -> None:
        """Stop pulling: a client's personal fine-tuning (zk0.federation.personal) trains the same parameters
        with hooks of its own, and each trainer's pull must act only during its own steps."""
        self.mu, self.anchor = 0.0, {}

    def loss(self) -> float:
        """``(mu/2)·||w - w_global||²`` at the current weights."""
        if not self.anchor:
            return 0.0
        with torch.no_grad():
            sq = sum(torch.sum((p.detach() - self.anchor[n]) ** 2) for n, p in self.params.items())
        return float(self.mu / 2 * sq)


def metrics_tracker(batch_size: int, frames: int, episodes: int) -> MetricsTracker:
    """The meters ``update_policy`` writes to, as lerobot's train script registers them.

    On CUDA ``update_policy`` also records ``gpu_mem_gb``, and a tracker without that meter
    raises at the first step: a GPU-only path that no CPU run exercises.
    """
    meters = {
        "loss": AverageMeter("loss"),
        "grad_norm": AverageMeter("grdn"),
        "lr": AverageMeter("lr"),
        "update_s": AverageMeter("updt_s"),
        "dataloading_s": AverageMeter("data_s"),
    }
    if torch.cuda.is_available():
        meters["gpu_mem_gb"] = AverageMeter("mem_gb", ":.2f", reduction="max")
    return MetricsTracker(batch_size, frames, episodes, meters)


def accelerator_for(device: torch.device) -> Accelerator:
    """Single-device Accelerator: bf16 autocast on GPUs that support it, full precision elsewhere."""
    bf16 = device.type == "cuda" and torch.cuda.is_bf16_supported()
    return Accelerator(
        cpu=device.type == "cpu", mixed_precision="bf16" if bf16 else "no", step_scheduler_with_optimizer=False
    )


def peaking_at(schedule: LRSchedulerConfig | None, lr: float) -> LRSchedulerConfig | None:
    """A policy's schedule preset at peak rate ``lr``: lerobot's cosine preset names its peak;
    diffusers' schedules (Diffusion Policy's) scale the optimizer's rate, which is ``lr`` already."""
    return replace(schedule, peak_lr=lr) if hasattr(schedule, "peak_lr") else schedule


def set_schedule_step(scheduler, global_step: int) -> None:
    """Put a LambdaLR schedule (lerobot's presets) at ``global_step`` and set the learning rates;
    a policy whose preset has no schedule (ACT's) trains at its constant rate."""
    if scheduler is None:
        return
    scheduler.last_epoch = global_step
    lrs = [base * fn(global_step) for base, fn in zip(scheduler.base_lrs, scheduler.lr_lambdas, strict=True)]
    for group, lr in zip(scheduler.optimizer.param_groups, lrs, strict=True):
        group["lr"] = lr
    set_last_lr(scheduler, lrs)


@dataclass
class LocalTrainer:
    """What a client keeps across rounds: policy, data iterator, optimizer, scheduler, FedProx."""

    bundle: PolicyBundle
    split: DatasetSplit
    loader: DataLoader
    run: RunConfig
    optimizer: torch.optim.Optimizer = field(init=False)
    scheduler: torch.optim.lr_scheduler.LambdaLR | None = field(init=False)  # None: the preset's constant rate
    accelerator: Accelerator = field(init=False)
    fedprox: FedProx = field(init=False)
    transforms: ImageTransforms | None = field(init=False, default=None)  # image-transforms
    _batches: Iterator | None = field(init=False, default=None)
    batches_seen: int = field(init=False, default=0)  # batches drawn so far in this run (data order position)

    def __post_init__(self) -> None:
        cfg = self.bundle.policy.config
        schedule = cfg.get_scheduler_preset()
        train_cfg = TrainPipelineConfig(
            dataset=None,  # type: ignore[arg-type]  # only the optimizer presets and steps are read
            policy=cfg,
            # the policy's presets at this trainer's own peak rate (a personal fine-tune's is lower)
            optimizer=replace(cfg.get_optimizer_preset(), lr=self.run.lr),
            scheduler=peaking_at(schedule, self.run.lr),
            steps=self.run.total_steps,
        )
        self.optimizer, self.scheduler = make_optimizer_and_scheduler(train_cfg, self.bundle.policy)
        self.grad_clip_norm = train_cfg.optimizer.grad_clip_norm
        self.accelerator = accelerator_for(self.bundle.device)
        params = dict(self.bundle.policy.named_parameters())
        self.fedprox = FedProx({n: params[n] for n in self.bundle.trainable_names})
        self.transforms = frame_transforms(self.run)

    @property
    def dataset_name(self) -> str:
        """The dataset the batches come from (what a skipped batch's warning names)."""
        return self.split.entry.name

    def _prepare(self, batch: dict) -> dict:
        """A loader batch on the device, preprocessed with this client's processors: its camera
        mapping, task text and normalisation statistics."""
        meta, bundle = self.split.meta, self.bundle
        batch = prepare_batch(batch, meta.camera_keys, self.split.entry.task, bundle.device)
        if self.transforms is not None:
            batch = augment(batch, meta.camera_keys, self.transforms)
        return bundle.preprocessor(batch)

    def train_on(self, split: DatasetSplit, loader: DataLoader) -> None:
        """Go on with a grown training set: the same optimizer, schedule and count of batches seen,
        the next batch drawn from ``loader``."""
        self.split, self.loader, self._batches = split, loader, None

    def _open_batches(self) -> None:
        """Open the data iterator if it is not open.

        Opening one draws a seed from PyTorch's generator, so it is opened on a fork of that
        generator: a round's random numbers then do not depend on whether the round opened the
        next epoch's iterator. Without the fork, a run resumed where an epoch ended (its
        iterator opened afresh) trained other noise than the uninterrupted run, which opened
        that iterator after seeding its next round."""
        if self._batches is None:
            with torch.random.fork_rng(devices=[]):
                self._batches = iter(self.loader)

    def _next_batch(self) -> dict:
        self._open_batches()
        self.batches_seen += 1
        try:
            return next(self._batches)
        except StopIteration:
            self._batches = None
            self._open_batches()
            return next(self._batches)

    def optimizer_record(self) -> ArrayRecord:
        """The optimizer's per-parameter state (AdamW moments and step), to outlive this process."""
        state = self.optimizer.state_dict()["state"]
        return ArrayRecord({f"{index}/{name}": value for index, st in state.items() for name, value in st.items()})

    def restore(self, batches_seen: int, optimizer: ArrayRecord | None) -> None:
        """Continue where an earlier process of this client stopped: data order and optimizer state.

        The data order uses lerobot's own sample-exact resume of its ``EpisodeAwareSampler``;
        without ``optimizer`` the optimizer keeps the state it has.
        """
        sampler = self.loader.sampler
        sampler.load_state_dict(compute_sampler_state(batches_seen, len(sampler), self.run.batch_size, 1))
        self.batches_seen = batches_seen
        self._batches = None  # the next batch comes from the restored position
        if optimizer is None:
            return
        state: dict[int, dict] = {}
        for key, value in optimizer.to_torch_state_dict().items():
            index, name = key.split("/")
            state.setdefault(int(index), {})[name] = value
        full = self.optimizer.state_dict()
        self.optimizer.load_state_dict({**full, "state": state})

    def _may_step(self, done: int) -> bool:
        """Whether the round may take another step after ``done`` (a private trainer's budget says)."""
        return True

    def _step(self, tracker: MetricsTracker, batch: dict) -> int:
        """One optimizer step on ``batch`` with lerobot's ``update_policy``; the samples it trained on."""
        update_policy(
            tracker,
            self.bundle.policy,
            batch,
            self.optimizer,
            self.grad_clip_norm,
            accelerator=self.accelerator,
            lr_scheduler=self.scheduler,
        )
        return len(batch["action"])

    def fit(self, steps: int, mu: float, global_step: int, budget_s: float = 0.0) -> dict[str, float]:
        """Run ``steps`` optimizer steps from the weights already loaded; return the round's metrics.

        With ``budget_s`` (``local-time-s``) it stops after the step that reaches that many seconds
        (at least one step): a slower machine takes fewer steps, reported as ``local-steps``. The
        schedule stays on the round's grid (``global_step`` is the round's first planned step), so
        every client of a round trains at the same learning rate whatever it took before.

        The random numbers (SmolVLA's flow-matching noise and time) are seeded by the run's seed,
        the dataset and ``global_step``: a round trains the same whichever process runs it, so a
        resumed run equals an uninterrupted one."""
        self._open_batches()
        self.bundle.policy.train()  # as lerobot's training loop does: dropout on, whatever ran before
        torch.manual_seed(self.run.seed + global_step + zlib.crc32(self.dataset_name.encode()))
        self.fedprox.anchor_at(mu)
        set_schedule_step(self.scheduler, global_step)
        tracker = metrics_tracker(self.run.batch_size, self.split.meta.total_frames, self.split.meta.total_episodes)
        done = skipped = samples = 0
        started = time.perf_counter()
        if self.bundle.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        while (
            done < steps
            and not (budget_s and done and time.perf_counter() - started >= budget_s)
            and self._may_step(done)
        ):
            t0 = time.perf_counter()
            try:
                batch = self._next_batch()
            except Exception as err:  # a frame that fails to decode costs a batch, not the round
                skipped += 1
                logger.warning("Skipped an unreadable batch from {}: {}", self.dataset_name, err)
                check_skips(self.dataset_name, "training", skipped, done, self.run.max_skip_fraction)
                continue
            batch = self._prepare(batch)
            tracker.dataloading_s = time.perf_counter() - t0
            samples += self._step(tracker, batch)
            done += 1
        elapsed = time.perf_counter() - started
        proximal = self.fedprox.loss()
        self.fedprox.release()
        return {
            "train-loss": tracker.loss.avg,
            "proximal-loss": proximal,
            "grad-norm": tracker.grad_norm.avg,
            "lr": self.optimizer.param_groups[0]["lr"],
            "num-examples": samples,
            "local-steps": done,
            "skipped-batches": skipped,
            "step-time": elapsed / done,
            **peak_memory(self.bundle.device),
        }


@dataclass
class PooledTrainer(LocalTrainer):
    """Centralised training, the study's baseline (zk0.bench.study): one policy and one optimizer
    over every client's data pooled. Batches come in turn from each client's own loader and are
    preprocessed with that client's own processors, so the camera mapping and normalisation are
    the ones the federation uses; ``samples_from`` counts what each client contributed. With
    ``wide``, every step takes a batch from each client and trains on them together: the study's
    equal-steps baseline, as many samples in fewer, larger steps."""

    sources: list[LocalTrainer] = field(default_factory=list)
    wide: bool = False  # each step one batch from every source, together (the batch is sources x batch size)
    samples_from: dict[str, int] = field(init=False, default_factory=dict)
    _source: LocalTrainer | None = field(init=False, default=None)

    @classmethod
    def over(
        cls, bundle: PolicyBundle, sources: list[LocalTrainer], run: RunConfig, wide: bool = False
    ) -> PooledTrainer:
        """``bundle``'s policy trained on ``sources``' batches (the first source's split stands in
        for the loop's bookkeeping: epoch counts in lerobot's metrics tracker)."""
        return cls(bundle, sources[0].split, sources[0].loader, run, sources=sources, wide=wide)

    @property
    def dataset_name(self) -> str:
        return self._source.dataset_name if self._source else self.split.entry.name

    def _next_batch(self) -> list[tuple[LocalTrainer, dict]]:
        """The step's batches, each with the source whose processors prepare it."""
        turn = self.sources if self.wide else [self.sources[self.batches_seen % len(self.sources)]]
        self.batches_seen += 1
        drawn = []
        for source in turn:
            self._source = source  # the dataset a failed batch's warning names
            batch = source._next_batch()
            name = source.dataset_name
            self.samples_from[name] = self.samples_from.get(name, 0) + len(batch["action"])
            drawn.append((source, batch))
        return drawn

    def _open_batches(self) -> None:
        """The clients' iterators (the pooled trainer has none of its own: opening the first
        client's loader here would move that client's data order on by an epoch)."""
        for source in self.sources:
            source._open_batches()

    def _prepare(self, drawn: list[tuple[LocalTrainer, dict]]) -> dict:
        prepared = [source._prepare(batch) for source, batch in drawn]
        if len(prepared) == 1:
            return prepared[0]
        sized = [self._model_sized(batch) for batch in prepared]  # the clients' frames differ in size
        return concat_batches(sized, set(self.bundle.policy.config.input_features))

    def _model_sized(self, batch: dict) -> dict:
        """The batch's camera frames resized and padded as SmolVLA's own ``prepare_images`` does (the
        same call, which then leaves them as they are), so the clients' batches can be joined."""
        cfg = self.bundle.policy.config
        if getattr(cfg, "resize_imgs_with_padding", None) is None:  # ACT has none: its frames go in as they are
            return batch
        width, height = cfg.resize_imgs_with_padding
        return batch | {key: resize_with_pad(batch[key], height, width, pad_value=0) for key in cfg.image_features}


def concat_batches(batches: list[dict], required: set[str]) -> dict:
    """Preprocessed batches as one: tensors and lists joined along the batch, the rest from the first.

    Keys only some batches have are left out: the datasets' own ``*_is_pad`` flags under their
    original camera names, which the policy does not read; one of the policy's ``required`` inputs
    missing from a batch is an error, not a camera silently dropped for every client."""
    common = set.intersection(*(set(b) for b in batches))
    if missing := sorted(required - common):
        raise TrainingError(f"The pooled batches cannot be joined: some clients' batches lack {missing}.")
    joined = {}
    for key, value in batches[0].items():
        if key not in common:
            continue
        if key in (OBS_LANGUAGE_TOKENS, OBS_LANGUAGE_ATTENTION_MASK):
            joined[key] = _right_padded([b[key] for b in batches])
        elif isinstance(value, torch.Tensor):
            joined[key] = torch.cat([b[key] for b in batches])
        elif isinstance(value, list):
            joined[key] = [item for b in batches for item in b[key]]
        else:
            joined[key] = value
    return joined


def _right_padded(tokens: list[torch.Tensor]) -> torch.Tensor:
    """Token ids or their attention mask, each batch padded on the right to the longest (SmolVLA pads
    the text of a batch to its longest, ``pad_language_to``): the added places are masked out, so
    what the model attends to is what each batch alone gives it."""
    longest = max(t.shape[1] for t in tokens)
    return torch.cat([torch.nn.functional.pad(t, (0, longest - t.shape[1])) for t in tokens])


def peak_memory(device: torch.device) -> dict[str, float]:
    """Peak GPU memory (GiB, 0 on CPU) and this process's resident host memory (GiB)."""
    gpu = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else 0.0
    return {"peak-gpu-gib": gpu, "host-rss-gib": psutil.Process().memory_info().rss / 2**30}


def chunk_start(cfg: PreTrainedConfig) -> int:
    """Where a predicted chunk starts in the window of actions lerobot's dataset gives the policy:
    at the latest observation, which Diffusion Policy's window begins ``n_obs_steps - 1`` before."""
    return cfg.action_delta_indices.index(0)


@torch.no_grad()
def evaluate(
    bundle: PolicyBundle, split: DatasetSplit, loader: DataLoader, max_batches: int, seed: int, max_skip: float
) -> dict[str, float]:
    """Seeded flow-matching policy loss and action-chunk MSE (unnormalised units) on held-out frames,
    and the seconds it took (what evaluation adds to a round).

    A batch whose frames cannot be decoded is skipped and counted, as in training, until more than
    ``max_skip`` (``max-skip-fraction``) of the batches were.
    """
    started = time.perf_counter()
    policy = bundle.policy
    policy.eval()
    losses, sq_err, counted, samples, skipped = [], 0.0, 0, 0, 0
    autocast = (
        torch.autocast("cuda", dtype=torch.bfloat16)
        if bundle.device.type == "cuda" and torch.cuda.is_bf16_supported()
        else nullcontext()
    )
    batches = iter(loader)
    while len(losses) < max_batches:
        try:
            batch = next(batches)
        except StopIteration:
            break
        except Exception as err:  # a frame that fails to decode costs a batch, not the evaluation
            skipped += 1
            logger.warning("Skipped an unreadable held-out batch of {}: {}", split.entry.name, err)
            check_skips(split.entry.name, "held-out", skipped, len(losses), max_skip)
            continue
        index = len(losses)
        now = chunk_start(policy.config)
        raw_action, is_pad = batch["action"][:, now:].clone(), batch["action_is_pad"][:, now:].clone()
        batch = bundle.preprocessor(prepare_batch(batch, split.meta.camera_keys, split.entry.task, bundle.device))
        with torch.random.fork_rng(devices=rng_devices(bundle)), autocast:
            torch.manual_seed(seed + index)  # same noise and time every round: losses are comparable
            loss, _ = policy.forward(batch)
            policy.reset()
            chunk = bundle.postprocessor(policy.predict_action_chunk(batch)).float()
        losses.append(float(loss))
        horizon = min(chunk.shape[1], raw_action.shape[1])
        valid = ~is_pad[:, :horizon]
        err = (chunk[:, :horizon].cpu() - raw_action[:, :horizon]) ** 2
        sq_err += float(err[valid].sum())
        counted += int(valid.sum()) * raw_action.shape[-1]
        samples += len(raw_action)
    policy.train()
    check_skips(split.entry.name, "held-out", skipped, len(losses), max_skip, finished=True)
    return {
        "policy-loss": sum(losses) / max(1, len(losses)),
        "action-mse": sq_err / max(1, counted),
        "num-examples": samples,
        "skipped-batches": skipped,
        "eval-s": time.perf_counter() - started,
    }
