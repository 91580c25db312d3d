"""A local Ray started by the SDK: its workers run with ``threads_per_worker`` threads, whatever the driver's own
setting, the driver's environment is left as it was, and workers of an earlier Ray session are never reused."""

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


def test_a_new_local_ray_does_not_reuse_the_idle_workers_of_one_shut_down_by_the_caller() -> None:
    """Idle workers are kept between calls of one Ray session. A caller that starts and stops Ray itself leaves
    them behind, and the next local Ray numbers its first job like the last one: its calls must start new
    workers, not submit to the dead ones."""
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        pytest.skip("a Ray session is already running in this process")

    def _plus_one(shared: dict, task: int) -> int:  # shipped by value (see above)
        return task + 1

    ray.init(num_cpus=2, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False)
    try:
        assert run_tasks(_plus_one, {}, [1, 2], ExecutionConfig(workers=2)) == [2, 3]
    finally:
        ray.shutdown()
    assert run_tasks(_plus_one, {}, [3, 4], ExecutionConfig(workers=2)) == [4, 5]
