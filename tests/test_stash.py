"""A long benchmark's finished models and figures, kept so the same command continues (zk0.bench.stash)."""

from __future__ import annotations

import json

import pytest
import torch

from zk0.bench.stash import Stash
from zk0.common.errors import Zk0Error

SETTINGS = {"rounds": 20, "lr": 1e-3, "federations": ["Nesterov"]}


def test_a_model_is_trained_once_and_taken_from_the_folder_after(tmp_path):
    trained = []

    def train() -> dict[str, torch.Tensor]:
        trained.append(1)
        return {"w": torch.arange(6, dtype=torch.float32).reshape(2, 3).t()}  # not contiguous: saved anyway

    first = Stash(tmp_path, SETTINGS).weights("local 0", train)
    again = Stash(tmp_path, SETTINGS).weights("local 0", train)
    assert trained == [1] and torch.equal(first["w"], again["w"])
    assert (tmp_path / "models" / "local-0.safetensors").is_file()


def test_figures_are_kept_by_name_and_a_half_written_file_is_never_taken(tmp_path):
    stash = Stash(tmp_path, SETTINGS)
    assert not stash.has("rollouts-100/client 0/personal 0")
    assert stash.figures("rollouts-100/client 0/personal 0", lambda: {"outcomes": [1, 0]}) == {"outcomes": [1, 0]}
    assert stash.has("rollouts-100/client 0/personal 0")
    assert json.loads((tmp_path / "rollouts-100" / "client-0" / "personal-0.json").read_text()) == {"outcomes": [1, 0]}
    (tmp_path / "rollouts-100" / "client-0" / ".local-0.json.partial").write_text('{"outcomes": [')  # a stopped write
    assert not stash.has("rollouts-100/client 0/local 0")
    assert stash.figures("rollouts-100/client 0/local 0", lambda: {"outcomes": [0]}) == {"outcomes": [0]}

    def failing() -> dict:
        raise RuntimeError("stopped")

    with pytest.raises(RuntimeError):
        stash.figures("offline/centralised", failing)
    assert not stash.has("offline/centralised")


def test_a_folder_of_models_trained_otherwise_is_refused_in_one_sentence(tmp_path):
    Stash(tmp_path, SETTINGS)
    with pytest.raises(Zk0Error) as refused:
        Stash(tmp_path, {**SETTINGS, "rounds": 8})
    assert str(refused.value) == (
        f"{str(tmp_path)!r} holds models trained with rounds = 20, not 8: give another --output-dir, "
        "or remove that folder to start over."
    )
