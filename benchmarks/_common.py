"""Helpers shared by the benchmark scripts (timing, memory, data loading)."""

from __future__ import annotations

import atexit
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:  # run as `python benchmarks/bench_x.py` from a source checkout
    sys.path.insert(0, ROOT)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; ``ru_maxrss`` is in KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def timed(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> tuple[float, float, object]:
    """(median s, min s, last result) of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    result = None
    for _ in range(warmup):
        result = fn()
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - tic)
    return statistics.median(times), min(times), result


def configure_threads() -> None:
    """``--threads N`` on the command line sets ``torch.set_num_threads(N)`` (default: torch's own choice)."""
    import argparse

    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--threads", type=int, default=None)
    args, _ = parser.parse_known_args()
    if args.threads:
        torch.set_num_threads(args.threads)


MAX_IDLE_LOAD = 0.5
"""The largest 1-minute load average before a run for its figures to count as measured alone."""


def busy_beyond_own(load: float) -> bool:
    """Whether a load average seen during a run says other jobs ran too: above one per CPU (the most a run's own
    processes reach, Ray workers included) plus :data:`MAX_IDLE_LOAD`."""
    return load > (os.cpu_count() or 1) + MAX_IDLE_LOAD


def header(title: str) -> None:
    """Apply ``--threads``, print what runs where and the load average now, and at exit the load average then,
    with a verdict: a run that started on a busy machine is marked UNDER LOAD and its figures are not to be
    reported (other jobs' work is in them)."""
    configure_threads()
    before = os.getloadavg()[0]
    print(f"== {title}")
    print(f"   python {platform.python_version()}, torch {torch.__version__}, {torch.get_num_threads()} torch threads, "
          f"{os.cpu_count()} CPUs, {platform.machine()}; load average before {before:.2f}")

    def verdict() -> None:
        after = os.getloadavg()[0]
        alone = before <= MAX_IDLE_LOAD and not busy_beyond_own(after)
        print(f"== load average before {before:.2f}, after {after:.2f}: "
              + ("measured alone" if alone else f"UNDER LOAD (before > {MAX_IDLE_LOAD}, or after above one per CPU "
                 f"+ {MAX_IDLE_LOAD}): discard these figures"))

    atexit.register(verdict)


def load_val(num_scenes: int = 100):  # type: ignore[no-untyped-def]
    """The first ``num_scenes`` long-enough nuscenes_pred val scenes and the seconds it took to load them."""
    from trafficrlhf_sdk import get_scenario_source

    tic = time.perf_counter()
    batch = get_scenario_source("nuscenes_pred").load_batch("val", num_scenes)
    return batch, time.perf_counter() - tic
