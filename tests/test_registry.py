"""The dataset registry and the camera mapping onto the global model's inputs."""

from __future__ import annotations

import dataclasses

import pytest

from zk0.config import RunConfig
from zk0.data.loaders import DataError, open_metadata, split_episodes
from zk0.data.registry import RegistryError, load_registry
from zk0.learning.policy import PolicyError, model_features


def test_project_registry_lists_four_clients_and_a_server_dataset(registry):
    assert [e.name for e in registry.clients] == [
        "synth-so100-pickplace",
        "synth-so100-stacking",
        "synth-so101-sorting",
        "synth-so101-reach",
    ]
    assert registry.get("synth-so100-eval").role == "server"
    assert registry.server.name == "synth-so100-eval"
    assert registry.get("zk0/synth_so100_stacking").name == "synth-so100-stacking"
    assert registry.model_cameras() == ["observation.images.camera1", "observation.images.camera2"]


def test_a_registry_without_a_server_set_says_so_when_one_is_asked_for(registry):
    clients_only = dataclasses.replace(registry, entries=registry.clients)
    with pytest.raises(RegistryError) as err:
        _ = clients_only.server
    assert str(err.value).startswith(
        'The registry has no server evaluation set; expected an entry with role = "server"'
    )


def test_differently_named_cameras_map_to_identical_model_inputs(registry):
    keys = set()
    for entry in registry.clients[:3]:  # front/wrist, laptop/phone, top/wrist
        meta = open_metadata(entry)
        keys.add(tuple(model_features(meta, entry, registry.model_cameras())))
    assert keys == {("observation.images.camera1", "observation.images.camera2", "observation.state", "action")}


def test_dataset_without_a_mapped_camera_is_refused_with_its_name(registry):
    entry = dataclasses.replace(registry.clients[1], cameras={"laptop": "camera9"})
    with pytest.raises(PolicyError) as err:
        model_features(open_metadata(entry), entry, registry.model_cameras())
    assert "'synth-so100-stacking' has no camera mapped" in str(err.value)
    assert "observation.images.laptop" in str(err.value)


def test_fewer_cameras_use_smolvla_empty_camera_slots(registry):
    from zk0.data.loaders import open_split, train_loader
    from zk0.learning.policy import build_policy
    from zk0.learning.training import LocalTrainer

    entry = dataclasses.replace(registry.clients[1], cameras={"phone": "camera2"})
    meta = open_metadata(entry)
    assert list(model_features(meta, entry, registry.model_cameras()))[:2] == registry.model_cameras()
    run = RunConfig(batch_size=2)
    bundle = build_policy(run, meta, entry, registry.model_cameras())
    assert bundle.policy.config.empty_cameras == 1
    split = open_split(entry, meta, bundle.policy.config, run)
    trainer = LocalTrainer(bundle, split, train_loader(split.train, run, bundle.device), run)
    assert trainer.fit(steps=1, mu=0.0, global_step=0)["num-examples"] == 2


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ('[tool.zk0.datasets.a]\nrepo_id = "x/a"\ncameras = { top = "camera1" }\nrole = "judge"\n', "role 'judge'"),
        ('[tool.zk0.datasets.a]\nrepo_id = "x/a"\n', "maps no cameras"),
        ('[tool.zk0.datasets.a]\ncameras = { top = "camera1" }\n', "'a' is invalid"),
        ('[tool.zk0.datasets.b]\nrepo_id = "x/b"\nsynthetic = true\ncameras = { top = "camera1" }\n', "synthetic"),
        ("[tool.other]\n", "no [tool.zk0.datasets]"),
        ("[tool.zk0.owners]\ncount = 0\n", "count = 0; expected a whole number from 1 to 1000"),
        ("[tool.zk0.owners]\ncount = 2.5\n", "count = 2.5"),
        (
            '[tool.zk0.owners]\ncount = 4\nkind = "robots"\n',
            "kind = 'robots'; expected one of ['synth', 'sim', 'sim-cube', 'sim-tasks', 'sim-tasks-cube']",
        ),
        ("[tool.zk0.owners]\ncount = 4\nseed = 1\n", "unknown key 'seed'"),
        ("[tool.zk0]\nowners = 16\n", "[tool.zk0.owners] must be a table"),
        (
            '[tool.zk0.owners]\ncount = 2\n[tool.zk0.datasets.synth-owner-1]\nrepo_id = "x/b"\ncameras = { top = "camera1" }\n',
            "'synth-owner-1' is also one of [tool.zk0.owners]",
        ),
    ],
)
def test_bad_registry_files_fail_with_one_sentence(tmp_path, table, needle):
    path = tmp_path / "registry.toml"
    path.write_text(table)
    with pytest.raises(RegistryError) as err:
        load_registry(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("kind", "client", "server"),
    [
        ("synth", "synth-owner-{}", "synth-so100-eval"),
        ("sim", "sim-so101-owner-{}", "sim-so101-eval"),
        ("sim-cube", "sim-so101-owner-{}-cube", "sim-so101-eval-cube"),
        ("sim-tasks", "sim-so101-owner-{}-task", "sim-so101-eval-pick-place-stack-sort"),
        ("sim-tasks-cube", "sim-so101-owner-{}-task-cube", "sim-so101-eval-pick-place-stack-sort-cube"),
    ],
)
def test_one_table_makes_many_owners_and_their_server_set(tmp_path, kind, client, server):
    path = tmp_path / "owners.toml"
    path.write_text(f'[tool.zk0.owners]\ncount = 64\nkind = "{kind}"\n')
    registry = load_registry(path)
    assert [e.name for e in registry.clients] == [client.format(i) for i in range(64)]
    assert [e.name for e in registry.entries if e.role == "server"] == [server]
    assert registry.model_cameras() == ["observation.images.camera1", "observation.images.camera2"]
    assert all(e.synthetic and sorted(e.cameras.values()) == ["camera1", "camera2"] for e in registry.entries)
    assert registry.for_partition(63).name == client.format(63)


def test_the_owners_table_keeps_the_files_own_entries_and_server(tmp_path):
    path = tmp_path / "owners.toml"
    path.write_text(
        "[tool.zk0.owners]\ncount = 2\n"
        '[tool.zk0.datasets.mine]\nrepo_id = "me/mine"\nroot = "/data/mine"\ncameras = { top = "camera1" }\n'
        '[tool.zk0.datasets.judge]\nrepo_id = "me/judge"\nrole = "server"\ncameras = { top = "camera1" }\n'
    )
    registry = load_registry(path)
    assert [e.name for e in registry.entries] == ["synth-owner-0", "synth-owner-1", "mine", "judge"]


def test_the_shipped_owners_registry_has_sixteen_owners():
    registry = load_registry("configs/owners-registry.toml")
    assert len(registry.clients) == 16 and registry.get("synth-so100-eval").role == "server"


def test_lookups_name_the_bad_value(registry):
    with pytest.raises(RegistryError, match="Partition id 4 has no dataset"):
        registry.for_partition(4)
    with pytest.raises(RegistryError, match="'lerobot/nope' is not in the registry"):
        registry.get("lerobot/nope")
    with pytest.raises(RegistryError, match="cannot be read"):
        load_registry("/nonexistent/registry.toml")


def test_last_episodes_are_held_out():
    assert split_episodes(6, 2, "d") == ([0, 1, 2, 3], [4, 5])
    with pytest.raises(DataError, match="eval-episodes=6 leaves none to train on"):
        split_episodes(6, RunConfig(eval_episodes=6).eval_episodes, "d")


def test_loader_workers_follow_the_client_cpus(monkeypatch):
    from zk0.data.loaders import loader_workers

    assert loader_workers(RunConfig(num_workers=3)) == 3
    assert loader_workers(RunConfig(num_workers=0)) == 0
    for cpus, workers in (("4", 3), ("20", 8), ("1", 0)):  # one CPU is the training loop's; at most 8
        monkeypatch.setenv("ZK0_CPUS", cpus)  # what `zk0 supernode --cpus` sets
        assert loader_workers(RunConfig(num_workers=-1)) == workers, cpus


@pytest.mark.slow  # a process of its own, which imports lerobot
def test_spawned_workers_give_the_same_batches(registry):
    from zk0.data.loaders import eval_loader, open_split
    from zk0.learning.policy import policy_config, resolve_device

    entry = registry.clients[0]
    run = RunConfig(batch_size=4, num_workers=1)
    split = open_split(entry, open_metadata(entry), policy_config(run, resolve_device("cpu")), run)
    spawned = next(iter(eval_loader(split.evaluation, run)))
    inline = next(iter(eval_loader(split.evaluation, dataclasses.replace(run, num_workers=0))))
    assert spawned["index"].tolist() == inline["index"].tolist()
    assert (spawned["observation.images.front"] == inline["observation.images.front"]).all()


def test_a_mapped_camera_the_dataset_lacks_is_an_empty_slot(registry):
    from zk0.learning.policy import build_policy

    entry = dataclasses.replace(registry.clients[1], cameras={"phone": "camera2", "overhead": "camera1"})
    bundle = build_policy(RunConfig(batch_size=2), open_metadata(entry), entry, registry.model_cameras())
    assert bundle.policy.config.empty_cameras == 1


def test_opening_a_synthetic_entry_never_generates_it(registry, tmp_path, monkeypatch, capsys):
    """Generation is `zk0 assets`' job: a machine without the dataset is told so in one sentence."""
    from zk0.cli import main as zk0_main
    from zk0.data.registry import RegistryError

    monkeypatch.setenv("ZK0_CACHE", str(tmp_path / "empty-cache"))
    entry = registry.get("synth-so100-pickplace")
    with pytest.raises(RegistryError) as missing:
        entry.local_root()
    sentence = (
        "Dataset 'synth-so100-pickplace' is generated by zk0 and not yet on this machine; "
        "run `zk0 assets` (./train.sh does) first."
    )
    assert str(missing.value) == sentence
    assert not (tmp_path / "empty-cache" / "datasets").exists(), "nothing was generated"
    assert zk0_main(["check"]) == 2
    assert f"zk0: {sentence}" in capsys.readouterr().err.splitlines()
