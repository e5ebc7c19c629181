"""An owner records more episodes while the federation runs: the client trains on them from its next round."""

from __future__ import annotations

import shutil
from pathlib import Path

from tests.test_preflight import SERVER
from zk0.data.assets import ensure_dataset
from zk0.data.assets.datasets import SPECS, append_synthetic_episodes


def test_episodes_recorded_mid_run_are_checked_trained_on_and_the_held_out_ones_stay(tmp_path, isolated_logging):
    """Round 1 on the owner's 6 episodes (4 trained, 2 held out). The owner records 2 more with
    lerobot's LeRobotDataset.resume, but one camera's new video file is missing: rounds 2 and 3
    refuse them in one sentence, said once, and train on the 4. With the file back, round 4 trains
    on 6, the frame cache holds the new episodes, and the held-out episodes are the same two; a
    process that builds the client again holds out those two too, not the grown dataset's last."""
    from flwr.app import ConfigRecord, Context, RecordDict
    from loguru import logger

    from zk0 import app_fingerprint
    from zk0.common.cache import default_cache_root
    from zk0.federation import client
    from zk0.federation.wire import encode
    from zk0.learning.policy import trainable_tensors

    root = Path(shutil.copytree(ensure_dataset("synth-so100-stacking"), tmp_path / "owner" / "stacking"))
    registry = tmp_path / "registry.toml"
    registry.write_text(
        f'{SERVER}[tool.zk0.datasets.stacking]\nrepo_id = "zk0/synth_so100_stacking"\nroot = "{root}"\n'
        'cameras = { laptop = "camera1", phone = "camera2" }\n'
    )
    run_config = {"registry": str(registry), "batch-size": 2, "local-steps": 2, "output-dir": str(tmp_path / "out")}
    context = Context(run_id=1, node_id=1, node_config={"dataset": "stacking"}, state=RecordDict(), run_config=run_config)
    config = {"run-name": "2026-01-01_00-00-00", "proximal-mu": 0.0}
    warnings = []
    client.release_sessions()
    try:
        session, _ = client.session_for(context, ConfigRecord({**config, "server-round": 1}))
        logger.add(lambda m: warnings.append(m.record["message"]), level="WARNING")  # after the client's set-up
        config |= {"app-fingerprint": app_fingerprint(), "backbone-fingerprint": session.fingerprint}
        arrays = encode(trainable_tensors(session.bundle), session.run.wire_dtype)

        def train(server_round: int) -> dict:
            content = RecordDict({"config": ConfigRecord({**config, "server-round": server_round}), "arrays": arrays})
            return next(iter(client.handle("train", content, context).metric_records.values()))

        train(1)
        held_out, trained = list(session.split.evaluation.episodes), list(session.split.train.episodes)
        assert (trained, held_out) == ([0, 1, 2, 3], [4, 5])

        append_synthetic_episodes(SPECS["synth-so100-stacking"], root, seed=1, episodes=2)
        meta = session.split.meta.__class__("zk0/synth_so100_stacking", root=root)
        missing = meta.get_video_file_path(6, "observation.images.laptop")
        (root / missing).rename(tmp_path / "hidden.mp4")
        for server_round in (2, 3):
            assert train(server_round)["local-steps"] == 2
            assert list(session.split.train.episodes) == trained and session.split.meta.total_episodes == 6
        refusal = (
            f"Dataset 'stacking' lacks '{missing}', which its episodes use, under '{root}'. Its new episodes 6-7 are "
            "refused; training goes on with the 6 it had."
        )
        assert warnings.count(refusal) == 1, warnings

        (tmp_path / "hidden.mp4").rename(root / missing)
        train(4)
        assert list(session.split.train.episodes) == [0, 1, 2, 3, 6, 7]
        assert list(session.split.evaluation.episodes) == held_out
        assert session.trainer.split is session.split and set(session.trainer.loader.dataset.episodes) == {0, 1, 2, 3, 6, 7}
        cached = {p.name for p in (default_cache_root() / "frames" / "zk0--synth_so100_stacking").rglob("episode_*.npy")}
        assert {"episode_000006.npy", "episode_000007.npy"} <= cached

        client.release_sessions()
        rebuilt, _ = client.session_for(context, ConfigRecord({**config, "server-round": 5}))
        assert rebuilt is not session and list(rebuilt.split.evaluation.episodes) == held_out
        assert list(rebuilt.split.train.episodes) == [0, 1, 2, 3, 6, 7]
    finally:
        client.release_sessions()
