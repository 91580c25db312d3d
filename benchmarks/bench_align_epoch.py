"""Where an alignment epoch's time goes: a CTG recipe on the real nuScenes train scenes, 2 cores.

Runs ``--epochs`` epochs of :class:`~trafficrlhf_sdk.alignment.AlignTrainer` on the 4 s CTG base
(``ctg_small_4s``, ``builtin:realism-margins``, 16 contexts x 8 samples, 75 % failure contexts from 24 scenes
driven 10 s with no-collision guidance, per-agent credit) and splits each epoch into: the closed-loop failure
drive, the rest of the rollout (cutting contexts, guided sampling, reward), and the PPO updates. Prints seconds
per epoch (mean over the epochs after the first, which also loads the scenes) and the projection to 70 epochs.
Data: nuScenes (CC BY-NC-SA 4.0).

Run: .venv/bin/python benchmarks/bench_align_epoch.py  [--threads N] [--epochs 5] [--checkpoint DIR]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict

from _common import ROOT, header, peak_rss_mb

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.reward.builtin import RealismReward

RECIPE = dict(alpha=3.0, denoising_steps=4, guidance="no_collision", contexts_per_epoch=16, samples_per_context=8,
              failure_fraction=0.75, failure_scenes=24, credit="agent", holdout_every=10, progress_bar=False)


def run(checkpoint: str, epochs: int) -> dict[str, list[float]]:
    """Seconds per epoch of each phase for ``epochs`` epochs."""
    from trafficrlhf_sdk.plugins import build_policy

    model = build_policy("ctg", {"checkpoint": checkpoint, "seed": 0})  # as `trafficrlhf align --model ctg` does
    trainer = AlignTrainer(model, RealismReward(margins=True),
                           AlignConfig(epochs=epochs, **RECIPE))
    phases: dict[str, float] = defaultdict(float)

    def timing(name: str, fn):  # type: ignore[no-untyped-def]
        def wrapped(*args, **kwargs):  # type: ignore[no-untyped-def]
            tic = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                phases[name] += time.perf_counter() - tic
        return wrapped

    sampler = trainer.context_sampler
    sampler.drive_for_failures = timing("drive", sampler.drive_for_failures)  # type: ignore[method-assign]
    trainer._rollout = timing("rollout", trainer._rollout)  # type: ignore[method-assign]
    trainer._optimize = timing("ppo", trainer._optimize)  # type: ignore[method-assign]
    per_epoch: dict[str, list[float]] = defaultdict(list)

    def record(epoch: int, stats: dict[str, float]) -> None:
        per_epoch["total"].append(stats["time_s"])
        per_epoch["drive"].append(phases["drive"])
        per_epoch["rollout_rest"].append(phases["rollout"] - phases["drive"])
        per_epoch["ppo"].append(phases["ppo"])
        phases.clear()

    trainer.train(callback=record)
    return per_epoch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--epochs", type=int, default=5,
                        help="epochs (the first is dropped)")
    parser.add_argument("--checkpoint", default=os.path.join(ROOT, "reference_models/ctg/checkpoints/ctg_small_4s"))
    args = parser.parse_args()
    header("alignment epoch: CTG recipe, failure drive vs sampling vs PPO")
    print(f"   checkpoint {os.path.relpath(args.checkpoint, ROOT)}, {args.epochs} epochs")
    print("| drive s/epoch | rest of rollout s/epoch | PPO s/epoch | total s/epoch | 70 epochs (min) |")
    print("|---|---|---|---|---|")
    res = run(args.checkpoint, max(3, args.epochs))
    mean = {k: sum(v[1:]) / len(v[1:]) for k, v in res.items()}
    print(f"| {mean['drive']:.2f} | {mean['rollout_rest']:.2f} | {mean['ppo']:.2f} | "
          f"{mean['total']:.2f} | {70 * mean['total'] / 60:.1f} |", flush=True)
    print(f"   peak RSS {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
