"""Run-config validation: defaults equal pyproject, bad values fail with one sentence."""

from __future__ import annotations

import dataclasses
import re
import tomllib

import pytest

from zk0.config import ConfigError, RunConfig, from_run_config
from zk0.data.registry import PROJECT_ROOT


def test_defaults_equal_the_pyproject_table():
    table = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["config"]
    assert from_run_config(table) == RunConfig()
    assert set(table) == set(RunConfig().to_flat())


def documented_defaults(page: str) -> list[tuple[str, object]]:
    """(key, default) of each row of a page's run-config tables: | `key` | `TOML value` | meaning |."""
    text = (PROJECT_ROOT / page).read_text()
    rows = re.findall(r"^\| `([a-z0-9-]+)` \| `([^`]*)` \|", text, flags=re.MULTILINE)
    return [(key, tomllib.loads(f"v = {value}")["v"]) for key, value in rows]


def test_the_configuration_page_documents_every_key_once_with_its_default():
    table = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["config"]
    documented = documented_defaults("docs/configuration.md")
    keys = [key for key, _ in documented]
    assert sorted(keys) == sorted(table), "docs/configuration.md and [tool.flwr.app.config] name the same keys"
    assert len(keys) == len(set(keys)), f"documented twice: {sorted({k for k in keys if keys.count(k) > 1})}"
    assert {key: default for key, default in documented} == table


def test_the_readme_shows_ten_keys_with_their_defaults():
    table = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["config"]
    documented = documented_defaults("README.md")
    assert len(documented) == 10 and all(table[key] == default for key, default in documented), documented


def test_overrides_are_applied():
    cfg = from_run_config({"num-server-rounds": 5, "local-steps": 10, "lr": 1, "proximal-mu": 0})
    assert (cfg.num_server_rounds, cfg.local_steps, cfg.total_steps) == (5, 10, 50)
    assert cfg.proximal_mu == 0.0 and isinstance(cfg.proximal_mu, float) and isinstance(cfg.lr, float)


def test_local_epochs_is_an_alias_of_local_steps():
    assert from_run_config({"local-epochs": 7}).local_steps == 7
    assert from_run_config({"local-epochs": 0, "local-steps": 3}).local_steps == 3


@pytest.mark.parametrize(
    ("overrides", "needles"),
    [
        ({"num-rounds": 3}, ["'num-rounds'", "num-server-rounds"]),
        ({"local-steps": "ten"}, ["'local-steps'", "'ten'", "int"]),
        ({"local-steps": 2.5}, ["'local-steps'", "2.5", "int"]),
        ({"use-wandb": 1}, ["'use-wandb'", "bool"]),
        ({"local-steps": 0}, ["'local-steps'", ">= 1"]),
        ({"fraction-train": 0.0}, ["'fraction-train'", "> 0"]),
        ({"fraction-evaluate": 1.5}, ["'fraction-evaluate'", "<= 1"]),
        ({"lr": -1e-4}, ["'lr'", "-0.0001"]),
        ({"device": "tpu"}, ["'device'", "'tpu'"]),
        ({"device": "auto:1"}, ["'device'", "'auto:1'", "cuda:N"]),
        ({"device": "cuda:x"}, ["'device'", "'cuda:x'"]),
        ({"phase-timeout": 0}, ["'phase-timeout'", "> 0"]),
        ({"frame-cache-gb": -1}, ["'frame-cache-gb'", "-1.0", ">= 0"]),
        ({"personal-steps": -5}, ["'personal-steps'", "-5", ">= 0"]),
        ({"personal-lr": 2.0}, ["'personal-lr'", "2.0", "<= 1"]),
        ({"personal-mu": -0.1}, ["'personal-mu'", "-0.1", ">= 0"]),
        ({"local-time-s": -30}, ["'local-time-s'", "-30.0", ">= 0"]),
        ({"averaging": "fedbuff"}, ["'averaging'", "'fedbuff'", "['fednova', 'samples']"]),
    ],
)
def test_bad_values_fail_with_one_sentence(overrides, needles):
    with pytest.raises(ConfigError) as err:
        from_run_config(overrides)
    message = str(err.value)
    assert all(n in message for n in needles), message
    assert message.endswith(".") and "\n" not in message


def test_evaluation_schedule():
    cfg = dataclasses.replace(RunConfig(), num_server_rounds=5, eval_frequency=2)
    assert [r for r in range(1, 6) if cfg.evaluates_in(r)] == [2, 4, 5]


def test_checkpoint_schedule_keeps_every_interval_and_the_last_round():
    cfg = dataclasses.replace(RunConfig(), num_server_rounds=7, checkpoint_interval=3)
    assert [r for r in range(8) if cfg.checkpoints_in(r)] == [3, 6, 7]
    assert from_run_config({"device": "cuda:1"}).device == "cuda:1"


def test_an_output_dir_that_cannot_be_created_is_named(tmp_path):
    from zk0.artifacts.run_folder import new_run_dir
    from zk0.common.errors import Zk0Error

    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(Zk0Error, match="'output-dir' got .*file/runs.*expected a writable folder"):
        new_run_dir(tmp_path / "file" / "runs")
    assert new_run_dir(tmp_path / "runs").parent == tmp_path / "runs"
