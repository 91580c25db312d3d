r"""When and how do a model's closed-loop failures happen? A diagnostic beside ``trafficrlhf evaluate``.

Drives each checkpoint over the same scenes and seeds and splits the failure rate (the share of controlled agents
that ever collide or leave the road, averaged over scenes) by each agent's *first* failure:

* ``collision, boxes overlap in the log at the start``: the first failure is a collision at the first simulated
  step, and the agent's logged box already overlaps another one at the rollout start (parked cars annotated
  into each other, say). No model can avoid these.
* ``collision within 1 s`` / ``collision later``: other first failures that are collisions.
* ``off-road within 1 s`` / ``off-road later``: first failures that are off-road only.

The five parts add up to the failure rate. An alignment cannot remove the first part, and hardly the
off-road-within-1-s one (an agent already at the road edge).

    python scripts/failure_timing.py --model ctg --seeds 0 1 2 \
        --checkpoints reference_models/ctg/checkpoints/ctg_small_4s reference_models/aligned/ctg_4s_gated
"""

from __future__ import annotations

import json

from realism_by_failure import checkpoints_parser, drive

from trafficrlhf_sdk import get_scenario_source
from trafficrlhf_sdk.metrics.failure import collisions_per_step, nanmean, scene_mean
from trafficrlhf_sdk.evaluation.failures import first_failures
from trafficrlhf_sdk.simulation.simulator import Rollout

STEPS_PER_SECOND = 10  # the simulator's 0.1 s step


def failure_parts(rollout: Rollout) -> dict[str, float]:
    """The failure rate of ``rollout`` split by each controlled agent's first failure (keys as in the module
    docstring, plus ``failure_rate``); each part is a mean over scenes of a share of agents, so they add up."""
    first = first_failures(rollout)
    failed = first.step >= 0
    steps_in = (first.step - rollout.start_index).clamp_min(0)  # simulated steps since the start: 1 = 0.1 s
    overlap_at_start = collisions_per_step(rollout.logged)[..., rollout.start_index]
    collision, offroad_only = failed & first.collision, failed & ~first.collision
    early = steps_in <= STEPS_PER_SECOND
    masks = {
        "collision, boxes overlap in the log at the start": collision & (steps_in == 1) & overlap_at_start,
        "collision within 1 s": collision & early & ~((steps_in == 1) & overlap_at_start),
        "collision later": collision & ~early,
        "off-road within 1 s": offroad_only & early,
        "off-road later": offroad_only & ~early,
        "failure_rate": failed,
    }
    return {name: nanmean(scene_mean(mask, rollout.controlled)) for name, mask in masks.items()}


def main() -> None:
    parser = checkpoints_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    scenes = get_scenario_source("nuscenes_pred").load_batch(args.split, args.scenes)
    result: dict[str, dict[str, float]] = {}
    for checkpoint in args.checkpoints:
        runs = [failure_parts(drive(args, scenes, checkpoint, seed)) for seed in args.seeds]
        result[checkpoint] = {key: sum(run[key] for run in runs) / len(runs) for key in runs[0]}
    names = [c.rstrip("/").split("/")[-1] for c in args.checkpoints]
    print(f"| first failure (mean over seeds {args.seeds}) | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for key in next(iter(result.values())):
        print(f"| {key} | " + " | ".join(f"{result[c][key]:.4f}" for c in args.checkpoints) + " |")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
