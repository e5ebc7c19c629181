"""The memory pre-flight of a CPU simulation (zk0.learning.memory): the clients that train at once
sized to the memory available, a refusal in one sentence where one does not fit, and a simulated
client process that drops the owners it keeps before building another when memory is short."""

from __future__ import annotations

import subprocess

import pytest

from zk0.config import RunConfig
from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.loopback import tool
from zk0.learning.memory import GIB, NotEnoughMemory, room_for_another, session_bytes, sized_federation

CPU = {"num-supernodes": 4, "client-resources-num-cpus": 1, "client-resources-num-gpus": 0.0}


def test_full_size_clients_train_as_many_at_once_as_the_memory_holds():
    run = RunConfig(model="full-size")
    sized, said = sized_federation(run, {**CPU, "init-args-num-cpus": 4}, available=int(20 * GIB))
    # 0.8 x 20 GiB: the server of four clients (9.5 GiB, each one's update, reply and decoding besides
    # the model) and one client training (4.55 GiB)
    assert sized == {**CPU, "init-args-num-cpus": 1}
    assert said == (
        "model='full-size' needs about 4.5 GiB a simulated client and 20.0 GiB of memory is available, so 1 of "
        "the 4 clients trains at a time instead of 4."
    )
    assert sized_federation(run, {**CPU, "init-args-num-cpus": 2}, available=int(30 * GIB)) == (
        {**CPU, "init-args-num-cpus": 2}, None,
    ), "two at once already fit: the config stays as it is"  # fmt: skip
    assert sized_federation(RunConfig(model="tiny"), CPU, available=int(4 * GIB)) == (CPU, None)
    gpu = {**CPU, "client-resources-num-gpus": 0.25}
    assert sized_federation(run, gpu, available=int(4 * GIB)) == (gpu, None), "on a GPU the host holds less"


def test_a_model_that_does_not_fit_beside_the_server_is_refused_in_one_sentence():
    with pytest.raises(NotEnoughMemory) as refused:
        sized_federation(RunConfig(model="full-size"), CPU, available=int(16 * GIB))
    assert str(refused.value) == (
        "model='full-size' needs about 9.5 GiB for the server of 4 simulated clients and 4.5 GiB for each client "
        "training, and this machine has 16.0 GiB of memory available; free some, or choose a smaller model "
        "(model='tiny')."
    )


def test_a_checkpoint_folder_is_sized_by_its_weights_and_a_hub_id_is_not_guessed(tmp_path):
    (tmp_path / "model.safetensors").write_bytes(b"\0" * 1000)
    assert session_bytes(str(tmp_path)) == 2200
    assert session_bytes("lerobot/smolvla_base") is None
    assert sized_federation(RunConfig(model="lerobot/smolvla_base"), CPU, available=1) == (CPU, None)


def test_a_process_keeps_another_full_size_client_only_with_room_for_two_more():
    run = RunConfig(model="full-size")
    assert room_for_another(run, available=int(10 * GIB))
    assert not room_for_another(run, available=int(8 * GIB)), "another process may be building one too"
    assert room_for_another(RunConfig(model="tiny"), available=int(1 * GIB))


def test_zk0_check_prints_the_run_and_the_sized_federation_config_train_sh_passes_to_flwr_run():
    done = subprocess.run(
        [tool("zk0"), "check", "--print", "--run-config", "local-steps=3", "--federation-config",
         "configs/federation/cpu.toml"], cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        "local-steps=3",
        "num-supernodes=4 client-resources-num-cpus=1 client-resources-num-gpus=0.0",
    ]


def test_act_is_sized_as_act_not_as_smolvla():
    """lerobot's default ACT trains all of its 52 M parameters: more than the tiny SmolVLA's client,
    far less than full-size SmolVLA's (which 16 GiB cannot hold beside its server, above)."""
    assert session_bytes("tiny", "act") > session_bytes("tiny")
    sized, said = sized_federation(RunConfig(model="full-size", policy="act"), {**CPU, "init-args-num-cpus": 4},
                                   available=int(16 * GIB))  # fmt: skip
    assert sized == {**CPU, "init-args-num-cpus": 3}, said
