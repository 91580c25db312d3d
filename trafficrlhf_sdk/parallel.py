"""Run independent tasks in this process (the default) or on Ray workers (``pip install trafficrlhf-sdk[ray]``).

One function and one shared payload (a model, a batch of scenes) serve every task. On Ray the payload is put in
the object store once and each worker (an actor) receives it once per call; tasks then carry only their own
small arguments (a rollout and a chunk index, a scene id). Results come back in task order, and every task seeds
its own randomness from its arguments, so the same seeds give the same numbers in-process and on Ray.

The workers outlive a call: a call that ends normally hands its workers back to the Ray session, and the next
call with the same threads per worker takes them with their torch already imported (an alignment samples on the
workers several times per epoch). A call that fails or stops early lets its workers go.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.errors import TrafficRLHFError

__all__ = ["ExecutionConfig", "derive_seed", "iter_tasks", "ray_session", "run_tasks"]

T = TypeVar("T")


class ExecutionConfig(BaseModel):
    """Where tasks run: in this process (``workers=0``, no ``ray_address``) or on Ray."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    workers: int = Field(0, ge=0, description="Ray workers (actors); 0 runs in-process. With `ray_address` and 0: "
                         "one worker per CPU of the cluster.")
    ray_address: str | None = Field(None, description="Address of an existing Ray cluster (e.g. 'auto' or "
                                    "'10.0.0.5:6379'); None starts a local Ray for the run when workers > 0.")
    threads_per_worker: int = Field(1, ge=1, description="torch threads inside each Ray worker.")

    @property
    def uses_ray(self) -> bool:
        """Whether tasks go to Ray."""
        return self.workers > 0 or self.ray_address is not None


def derive_seed(seed: int, *keys: int) -> int:
    """A 31-bit seed from ``seed`` and integer ``keys`` (e.g. rollout, chunk); ``seed`` itself when every key is 0,
    so a single rollout of a single chunk keeps the run's own seed."""
    if not any(keys):
        return seed
    return int(np.random.SeedSequence([seed & 0xFFFFFFFF, *keys]).generate_state(1)[0]) % (2**31 - 1)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise TrafficRLHFError("--workers/--ray-address run on Ray, which is not installed; install it with "
                               "`pip install 'trafficrlhf-sdk[ray]'` (or drop --workers to run in-process).") from exc
    return ray


@contextlib.contextmanager
def ray_session(execution: ExecutionConfig) -> Iterator[Any]:
    """Connect to ``execution.ray_address`` or start a local Ray with ``execution.workers`` CPUs; yields the
    ``ray`` module (None in-process). A Ray started here is shut down on exit; one already running is reused."""
    if not execution.uses_ray:
        yield None
        return
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        threads = str(execution.threads_per_worker)
        if execution.ray_address is not None:  # the cluster's workers get their threads from a runtime env
            ray.init(address=execution.ray_address, runtime_env={"env_vars": {"OMP_NUM_THREADS": threads}},
                     **options)
        else:  # a local head on the loopback address: nothing listens on other interfaces. Its workers inherit
            # the environment it starts with, which is quicker than a runtime env (that starts an agent per worker)
            before = os.environ.get("OMP_NUM_THREADS")
            os.environ["OMP_NUM_THREADS"] = threads
            try:
                ray.init(num_cpus=execution.workers, _node_ip_address="127.0.0.1", **options)
            finally:
                if before is None:
                    del os.environ["OMP_NUM_THREADS"]
                else:
                    os.environ["OMP_NUM_THREADS"] = before
        started = True
    try:
        yield ray
    finally:
        if started:
            _IDLE.clear()
            ray.shutdown()


class _Worker:
    """A Ray actor with ``threads`` torch threads; holds one call's function and shared payload at a time and runs
    ``fn(shared, task)`` per task."""

    def __init__(self, threads: int) -> None:
        import torch

        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = str(threads)
        self.fn: Callable[[Any, Any], Any] | None = None
        self.shared: Any = None

    def load(self, fn: Callable[[Any, Any], Any] | None, shared: Any) -> None:
        self.fn, self.shared = fn, shared

    def run(self, task: Any) -> Any:
        assert self.fn is not None, "load() first"
        return self.fn(self.shared, task)


_IDLE: dict[str, list[tuple[int, Any]]] = {}
"""Workers between calls, per Ray session (:func:`_session`): ``(threads, actor)``."""


def _session(ray: Any) -> str:
    """This driver's Ray session: its node and job. A job id alone repeats when a new local Ray is started after
    a shutdown (its first job is again job 1), and the idle workers of the old one are gone."""
    context = ray.get_runtime_context()
    return f"{context.get_node_id()}/{context.get_job_id()}"


def _take_workers(ray: Any, count: int, threads: int) -> list[Any]:
    """``count`` workers with ``threads`` torch threads: idle ones of this Ray session first, then new ones. Before
    new ones start, the other idle workers are let go, so they do not hold CPUs the new ones need; otherwise they
    stay idle for a later call."""
    session = _session(ray)
    for other in [key for key in _IDLE if key != session]:  # handles of an earlier Ray session (shut down since)
        del _IDLE[other]
    idle = _IDLE.pop(session, [])
    mine = [i for i, (t, _) in enumerate(idle) if t == threads][:count]
    taken = [idle[i][1] for i in mine]
    rest = [entry for i, entry in enumerate(idle) if i not in mine]
    if len(taken) == count:
        _IDLE[session] = rest
        return taken
    for _, actor in rest:
        ray.kill(actor)
    remote = ray.remote(num_cpus=threads)(_Worker)
    return taken + [remote.remote(threads) for _ in range(count - len(taken))]


def run_tasks(fn: Callable[[Any, Any], T], shared: Any, tasks: Sequence[Any],
              execution: ExecutionConfig | None = None) -> list[T]:
    """``[fn(shared, task) for task in tasks]``, in-process or on Ray workers, in task order.

    ``fn`` must be a module-level function (Ray ships it by reference) and must seed any randomness from its
    task, never rely on state left by an earlier task: tasks run on different workers in any order.
    """
    return list(iter_tasks(fn, shared, tasks, execution))


def iter_tasks(fn: Callable[[Any, Any], T], shared: Any, tasks: Sequence[Any],
               execution: ExecutionConfig | None = None) -> Iterator[T]:
    """:func:`run_tasks` as an iterator: each result, in task order, as soon as it and those before it are done,
    so a caller can store results while the workers compute the rest (the Ray session lasts until the iterator
    is exhausted or closed)."""
    execution = execution or ExecutionConfig()
    if not execution.uses_ray or not tasks:
        for task in tasks:
            yield fn(shared, task)
        return
    with ray_session(execution) as ray:
        threads = execution.threads_per_worker
        cpus = int(ray.cluster_resources().get("CPU", 1)) // threads
        workers = execution.workers or max(1, cpus)
        workers = min(workers, len(tasks))
        actors = _take_workers(ray, workers, threads)
        shared_ref = ray.put(shared)  # once into the object store; each actor fetches it once
        for worker in actors:  # runs before the worker's tasks: Ray keeps one caller's calls to an actor in order
            worker.load.remote(fn, shared_ref)
        yield from _in_task_order(ray, actors, list(tasks))
        for worker in actors:  # back to the session without the payload (only after every result was read)
            worker.load.remote(None, None)
        _IDLE.setdefault(_session(ray), []).extend((threads, a) for a in actors)


def _in_task_order(ray: Any, actors: Sequence[Any], tasks: Sequence[Any]) -> Iterator[Any]:
    """Run ``tasks`` on ``actors`` and yield their results in task order. Each actor gets the next task as soon as
    it finishes one, whatever the order the results are read in (Ray's ``ActorPool.map`` frees an actor only once
    its result is the next one read, so a fast actor idles behind a slow one); finished results wait in the
    object store until their turn."""
    queue = iter(enumerate(tasks))
    running: dict[Any, tuple[int, Any]] = {}  # object ref -> (task index, actor)
    finished: dict[int, Any] = {}

    def start(worker: Any) -> None:
        item = next(queue, None)
        if item is not None:
            running[worker.run.remote(item[1])] = (item[0], worker)

    for worker in actors:
        start(worker)
    for index in range(len(tasks)):
        while index not in finished:
            ready, _ = ray.wait(list(running), num_returns=1)
            done, worker = running.pop(ready[0])
            finished[done] = ready[0]
            start(worker)
        yield ray.get(finished.pop(index))
