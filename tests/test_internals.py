"""The private lerobot/torch/Flower names zk0 uses still exist in the installed versions."""

from __future__ import annotations

import torch

from zk0 import internals


def test_every_private_name_zk0_touches_is_still_there():
    internals.check()


def test_the_check_fails_naming_versions_when_a_name_is_gone(monkeypatch):
    from lerobot.datasets.dataset_reader import DatasetReader

    monkeypatch.delattr(DatasetReader, "_query_videos")
    try:
        internals.check()
    except RuntimeError as err:
        assert "DatasetReader._query_videos" in str(err) and "lerobot 0.6" in str(err)
    else:
        raise AssertionError("the check passed without DatasetReader._query_videos")


def test_set_last_lr_is_what_get_last_lr_reports():
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)
    internals.set_last_lr(scheduler, [0.25])
    assert scheduler.get_last_lr() == [0.25]
