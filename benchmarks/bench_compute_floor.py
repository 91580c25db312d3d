"""How fast a traffic model's closed-loop evaluation can be on this CPU: its arithmetic against the CPU's best rate.

Counts the floating-point operations of one closed-loop rollout (10 s, replanning at 2 Hz) of every scene with
``torch.utils.flop_counter.FlopCounterMode`` (convolutions and matrix products, the model's bulk), times the same
rollout without the counter, and measures the CPU's best single-precision matrix-multiply rate on square matrices
(MKL's sgemm, the fastest kernel this torch build has). A model's rollout cannot run faster than its operation
count at that rate, so ``scenes x K x FLOPs per scene-rollout / best rate`` is a floor for K rollouts per scene,
before any of the elementwise work (normalization, activations, sampling, simulation, metrics) is paid.

The number of operations of a rollout depends only on which agents are driven and how often the model is called,
not on the random draws, so K rollouts cost K times one.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_compute_floor.py --threads 1
"""

from __future__ import annotations

import argparse
import time

import torch
from _common import header, load_val


def best_matmul_rate(sizes: tuple[int, ...] = (512, 1024, 2048), repeats: int = 3) -> tuple[float, int]:
    """(FLOP/s, size) of the fastest square float32 matrix product among ``sizes``, best of ``repeats``."""
    best, best_size = 0.0, sizes[0]
    for n in sizes:
        a, b = torch.randn(n, n), torch.randn(n, n)
        a @ b
        calls = max(3, int(4e9 / (2 * n**3)))
        for _ in range(repeats):
            tic = time.perf_counter()
            for _ in range(calls):
                a @ b
            rate = 2 * n**3 * calls / (time.perf_counter() - tic)
            if rate > best:
                best, best_size = rate, n
    return best, best_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=100, help="first N long-enough val scenes (default 100)")
    parser.add_argument("--checkpoint", default="ctg-4s", help="a checkpoint of the `ctg` model (default ctg-4s)")
    parser.add_argument("--guidance", default="no_collision", help="guidance of the rollout (default no_collision)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (see benchmarks/README.md)")
    args = parser.parse_args()
    header(f"compute floor: {args.checkpoint} + {args.guidance}, {args.scenes} val scenes, 10 s closed loop")

    from torch.utils.flop_counter import FlopCounterMode

    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, run_batched
    from trafficrlhf_sdk.plugins import build_policy

    batch, _ = load_val(args.scenes)
    config = EvaluationConfig(rollouts=1, seed=0)

    def policy() -> object:
        return build_policy(None, {"checkpoint": args.checkpoint, "guidance": args.guidance, "seed": 0})

    counter = FlopCounterMode(display=False)
    with counter:
        run_batched(policy(), batch, config)
    per_op = {str(op).removeprefix("aten."): n for op, n in counter.get_flop_counts()["Global"].items()}
    flops = counter.get_total_flops() / batch.num_scenes
    print(f"   operations per scene-rollout: {flops / 1e9:.2f} GFLOP ("
          + ", ".join(f"{op} {n / batch.num_scenes / 1e9:.3f}" for op, n in sorted(per_op.items())) + ")")

    tic = time.perf_counter()
    run_batched(policy(), batch, config)
    wall = time.perf_counter() - tic
    achieved = flops * batch.num_scenes / wall
    print(f"   one rollout of the {batch.num_scenes} scenes: {wall:.1f} s ({wall / batch.num_scenes:.3f} s per "
          f"scene-rollout), {achieved / 1e9:.1f} GFLOP/s of the model's products")

    rate, size = best_matmul_rate()
    print(f"   best float32 matrix product on {torch.get_num_threads()} thread(s): {rate / 1e9:.1f} GFLOP/s "
          f"({size} x {size}); the rollout's products ran at {achieved / rate:.0%} of it, end to end")
    for rollouts, goal in ((8, 60.0), (32, 240.0)):
        floor = flops * batch.num_scenes * rollouts / rate
        print(f"   K = {rollouts:>2}: floor {floor:6.1f} s (products alone, at the best rate); "
              f"at this run's rate {wall * rollouts:6.1f} s; goal {goal:.0f} s")


if __name__ == "__main__":
    main()
