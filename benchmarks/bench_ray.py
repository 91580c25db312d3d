"""In-process against Ray workers: closed-loop evaluation (scenes x rollouts) and feedback-campaign candidate
generation with CTG, the same seeds in both modes. **Asserts** the results are identical, then prints both wall
times and the speed-up (Ray start-up included: a local Ray is started for each Ray run, unless ``--ray-address``
names a running one, e.g. one started with ``ray start --head --num-cpus 2``).

Run: .venv/bin/python benchmarks/bench_ray.py candidates --scenes 300 --split train --seconds 4 --workers 2
     .venv/bin/python benchmarks/bench_ray.py evaluate --scenes 100 --rollouts 8 --workers 2
Needs ``pip install 'trafficrlhf-sdk[ray]'``. Set OMP_NUM_THREADS=1: each mode then uses one thread per process
(in-process: one core; Ray: one per worker).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import torch
from _common import header, load_val, peak_rss_mb

from trafficrlhf_sdk.parallel import ExecutionConfig


def bench_evaluate(scenes: int, rollouts: int, execution: ExecutionConfig) -> None:
    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
    from trafficrlhf_sdk.plugins import build_policy

    batch, _ = load_val(scenes)
    print(f"   map rasters of the {batch.num_scenes} scenes: {batch.map.pixels.numel() / 2**20:.0f} MB")  # type: ignore[union-attr]
    config = EvaluationConfig(rollouts=rollouts, seed=0)
    runs = {}
    for label, where in (("in-process", None), (f"ray x{execution.workers}", execution)):
        policy = build_policy(None, {"checkpoint": "ctg-4s", "guidance": "no_collision", "seed": 0})
        tic = time.perf_counter()
        runs[label] = evaluate_policy(policy, batch, config, execution=where)
        wall, report = time.perf_counter() - tic, runs[label]
        # in-process, the rollout's own time is the simulation's; the rest is the metrics, computed in the driver
        # after the rollouts on Ray too (the Ray rollout's time is the sum over the workers' tasks)
        metrics = f" (of which metrics {report.wall_time_s - report.simulation_time_s:.1f} s)" if where is None else ""
        print(f"   {label:<12} {wall:8.1f} s{metrics}  realism_meta {report.values['realism_meta']:.4f}  "
              f"failure {report.values['failure_rate']:.4f}")
    first, second = runs.values()
    assert first.values == second.values and first.per_scene == second.per_scene, "in-process and Ray differ"
    assert torch.equal(first.rollout.simulated.states, second.rollout.simulated.states)
    print("   identical: values, per-scene values and rollout states")


def bench_candidates(scenes: int, execution: ExecutionConfig, split: str, seconds: float) -> None:
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    config = CampaignConfig(name="bench", model="ctg", guidance="no_collision", num_contexts=scenes, split=split,
                            candidate_seconds=seconds, model_options={"checkpoint": "ctg-4s"})
    stores = {}
    with tempfile.TemporaryDirectory() as folder:
        for label, where in (("in-process", None), (f"ray x{execution.workers}", execution)):
            store = FeedbackStore(os.path.join(folder, f"{label[:3]}.db"))
            tic = time.perf_counter()
            report = create_campaign(store, config, execution=where)
            wall = time.perf_counter() - tic
            print(f"   {label:<12} {wall:8.1f} s  {len(report.added)} contexts, {wall / len(report.added):.2f} s/scene")
            stores[label] = (store, report.added)
        (a, ids_a), (b, ids_b) = stores.values()
        for x, y in zip(ids_a, ids_b):
            assert torch.equal(a.load_context(x).candidates, b.load_context(y).candidates), "candidates differ"
    print("   identical: every context's candidates")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["evaluate", "candidates"])
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--split", default="val", help="candidates: the split of the contexts.")
    parser.add_argument("--seconds", type=float, default=5.0, help="candidates: seconds per candidate.")
    parser.add_argument("--ray-address", default=None, help="A running Ray cluster (e.g. auto) instead of a local "
                        "Ray started for the run.")
    args = parser.parse_args()
    execution = ExecutionConfig(workers=args.workers, ray_address=args.ray_address)
    where = f"the Ray cluster at {args.ray_address}" if args.ray_address else "a local Ray started for the run"
    header(f"in-process vs {args.workers} Ray workers on {where}: {args.what}, {args.scenes} scenes")
    if args.what == "evaluate":
        bench_evaluate(args.scenes, args.rollouts, execution)
    else:
        bench_candidates(args.scenes, execution, args.split, args.seconds)
    print(f"   peak RSS of the driver {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
