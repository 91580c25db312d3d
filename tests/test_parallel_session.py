"""A local Ray started by the SDK: its workers run with ``threads_per_worker`` threads, whatever the driver's own
setting, and the driver's environment is left as it was."""

from __future__ import annotations

import os

import pytest

from trafficrlhf_sdk.parallel import ExecutionConfig, run_tasks


def test_a_local_ray_gives_its_workers_their_threads_and_leaves_the_drivers_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        pytest.skip("a Ray session is already running in this process")
    def _threads(shared: dict, task: int) -> tuple[str | None, int]:  # shipped by value: workers cannot import
        import os  # this test module

        import torch

        return os.environ.get("OMP_NUM_THREADS"), torch.get_num_threads()

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    results = run_tasks(_threads, {}, [0, 1, 2], ExecutionConfig(workers=2, threads_per_worker=1))
    assert results == [("1", 1)] * 3
    assert os.environ["OMP_NUM_THREADS"] == "3" and not ray.is_initialized()
