"""CUDA-only branches: run where CUDA is present, reported as skipped (with the reason) elsewhere.

The first run of zk0 on a GPU found a failure no CPU test could: on CUDA, lerobot's
``update_policy`` writes ``gpu_mem_gb`` to the metrics tracker. These tests take real steps and
evaluations on the GPU with the tiny model, so such a branch cannot break unnoticed where a GPU
is available.
"""

from __future__ import annotations

import pytest
import torch

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (no GPU on this machine)")


@pytest.fixture(scope="module")
def cuda_client(registry):
    from zk0.config import RunConfig
    from zk0.federation.client import build_client

    run = RunConfig(device="cuda:0", batch_size=4, local_steps=3, num_server_rounds=1)
    return build_client(run, registry.clients[0], registry.model_cameras())


def test_a_client_trains_on_cuda_with_bf16_and_reports_its_peak_memory(cuda_client):
    assert cuda_client.bundle.device == torch.device("cuda:0")
    assert cuda_client.trainer.accelerator.mixed_precision == ("bf16" if torch.cuda.is_bf16_supported() else "no")
    assert cuda_client.trainer.loader.pin_memory
    metrics = cuda_client.trainer.fit(3, mu=0.01, global_step=0)
    assert metrics["num-examples"] == 12 and metrics["skipped-batches"] == 0
    weights = sum(p.numel() * p.element_size() for p in cuda_client.bundle.policy.parameters()) / 2**30
    total = torch.cuda.get_device_properties(0).total_memory / 2**30
    assert weights <= metrics["peak-gpu-gib"] <= total, "GiB of this GPU, at least the weights"
    assert all(p.device.type == "cuda" for p in cuda_client.bundle.policy.parameters())


def test_evaluation_on_cuda_is_seeded(cuda_client):
    from zk0.learning.training import evaluate

    runs = [
        evaluate(cuda_client.bundle, cuda_client.split, cuda_client.eval_batches, 1, seed=3, max_skip=0.1)
        for _ in range(2)
    ]
    assert runs[0]["policy-loss"] == pytest.approx(runs[1]["policy-loss"], rel=1e-3)
    assert runs[0]["action-mse"] > 1.0  # joint positions in degrees, not normalised units


def test_frames_reach_the_gpu_as_uint8_and_the_processors_run_there(cuda_client):
    """Pinned uint8 frames are copied with non_blocking and scaled on the device; the preprocessor
    (normalisation, tokenisation) leaves every tensor on the client's GPU."""
    from zk0.data.loaders import prepare_batch

    split, bundle = cuda_client.split, cuda_client.bundle
    batch = next(iter(cuda_client.trainer.loader))
    camera = split.meta.camera_keys[0]
    assert batch[camera].dtype == torch.uint8 and batch[camera].is_pinned()
    raw = batch[camera].clone()
    moved = prepare_batch(batch, split.meta.camera_keys, split.entry.task, bundle.device)
    assert moved[camera].device == bundle.device and moved[camera].dtype == torch.float32
    torch.testing.assert_close(moved[camera].cpu(), raw.float() / 255.0, rtol=0, atol=0)
    ready = bundle.preprocessor(moved)
    tensors = [value for value in ready.values() if isinstance(value, torch.Tensor)]
    assert tensors and all(t.device == bundle.device for t in tensors)
