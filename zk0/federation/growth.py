"""An owner who records more episodes between rounds: the client trains on them from its next round.

Owners keep recording: ``lerobot-record --resume=true`` (lerobot's ``LeRobotDataset.resume``)
appends episodes to the same dataset while a federation runs. At the start of each round the
client reads its dataset's metadata again. Episodes recorded since are checked as the pre-flight
checks a dataset (every file they point to there and not empty) and the training set is reopened
with them; its frame cache is keyed on the video files, so it is rebuilt, never read stale. The
held-out episodes stay the episodes they were (kept in ``Context.state`` for a process that
rebuilds the client), so the evaluation figures stay comparable across rounds; the normalisation
statistics stay those the client started the run with (its processors are built once). New
episodes that fail their check are refused in one sentence, and the owner goes on training on
the episodes it had.
"""

from __future__ import annotations

import json

from loguru import logger

from zk0.config import RunConfig
from zk0.data.loaders import DataError, DatasetSplit, open_metadata, with_training
from zk0.learning.preflight import check_episodes


def grown(split: DatasetSplit, run: RunConfig, policy_cfg, said: set[str]) -> DatasetSplit | None:
    """``split`` with the episodes recorded since it was opened in its training set (None: none new,
    not a local dataset, or refused). New episodes are checked every round until they pass (an
    owner may fix a missing file); ``said`` holds the sentences already said, so a dataset that
    stays broken is named once, not every round."""
    entry = split.entry
    if entry.local_root() is None:  # a Hub dataset changes by revision, which is another dataset
        return None
    known = split.meta.total_episodes
    info = entry.local_root() / "meta" / "info.json"  # one small file a round; the metadata only when it grew
    if json.loads(info.read_text()).get("total_episodes", 0) <= known:
        return None
    meta = open_metadata(entry)
    new = list(range(known, meta.total_episodes))
    if run.dp == "record":  # DP-SGD's accounting is for the demonstrations it started with
        _say_once(said, f"Dataset {entry.name!r} has {len(new)} new episode(s); under dp='record' they wait for the "
                        f"next run (its epsilon is accounted for the {known} it started with).")  # fmt: skip
        return None
    try:
        check_episodes(entry, meta, new)
    except DataError as err:
        _say_once(said, f"{err} Its new episodes {new[0]}-{new[-1]} are refused; training goes on with the {known} "
                        "it had.")  # fmt: skip
        return None
    split = with_training(split, meta, policy_cfg, run, [*split.train.episodes, *new])
    logger.info("Dataset {!r}: training on {} new episode(s) too ({} in all; the same {} held out).",
                entry.name, len(new), len(split.train.episodes), len(split.evaluation.episodes))  # fmt: skip
    return split


def _say_once(said: set[str], sentence: str) -> None:
    if sentence not in said:
        said.add(sentence)
        logger.warning(sentence)
