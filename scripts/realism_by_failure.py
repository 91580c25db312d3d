r"""Where does a model's realism deviation change? A diagnostic beside ``trafficrlhf evaluate``.

Drives each checkpoint over the same scenes and seed (as ``trafficrlhf evaluate`` does), marks every controlled
agent that collides or leaves the road in **any** of the runs, and reports each run's realism deviation over
agent groups: all; the scenes where no run fails and the others; the agents that fail in no run and those that
fail in some run. An alignment that keeps realism where it fixes failures but loses it on the agents that never
failed has changed driving that needed no change.

    python scripts/realism_by_failure.py --model ctg --seed 0 \
        --checkpoints reference_models/ctg/checkpoints/ctg_small_4s reference_models/aligned/ctg_4s
"""

from __future__ import annotations

import argparse
import json

import torch

from trafficrlhf_sdk import ScenarioTensor, get_scenario_source
from trafficrlhf_sdk.plugins import build_policy
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, run_batched
from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step
from trafficrlhf_sdk.metrics.realism import QUANTITIES, SPECS, RealismMetric, histogram_distance
from trafficrlhf_sdk.simulation.simulator import Rollout


def failing_agents(rollout: Rollout) -> torch.Tensor:
    """Bool ``(B, A)``: controlled agents that collide or have their centre off the road in the simulated steps."""
    window = rollout.window("simulated")
    bad = (collisions_per_step(window) | offroad_per_step(window)) & window.valid
    return bad.any(-1) & rollout.controlled


def agent_groups(rollouts: list[Rollout]) -> dict[str, torch.Tensor]:
    """Bool ``(B, A)`` masks of the controlled agents (the same in every run) by whether any run fails them."""
    controlled = rollouts[0].controlled
    for rollout in rollouts[1:]:
        if not torch.equal(rollout.controlled, controlled):
            raise ValueError("the runs control different agents; drive the same scenes with the same settings.")
    failing = torch.stack([failing_agents(r) for r in rollouts]).any(0)
    clean_scene = ~failing.any(-1, keepdim=True)
    return {"all": controlled, "scenes where no run fails": controlled & clean_scene,
            "other scenes": controlled & ~clean_scene, "agents failing in no run": controlled & ~failing,
            "agents failing in some run": controlled & failing}


def realism_over(rollout: Rollout, agents: torch.Tensor, preset: str = "ctg") -> dict[str, float]:
    """Realism deviation (mean of the three quantities, and each) of ``rollout`` over the ``agents (B, A)`` only."""
    metric = RealismMetric(preset)  # type: ignore[arg-type]
    simulated = metric.histograms(rollout.window("simulated"), agents)
    logged = metric.histograms(rollout.window("logged"), agents)
    values = {q: histogram_distance(logged[q], simulated[q], SPECS[q]) for q in QUANTITIES}
    values["mean"] = sum(values[q] for q in QUANTITIES) / len(QUANTITIES)
    return values


def checkpoints_parser(description: str | None) -> argparse.ArgumentParser:
    """Arguments shared by the diagnostics that drive several checkpoints over the same scenes: --model,
    --checkpoints, --guidance, --split, --scenes (the first N long-enough scenes of nuscenes_pred)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="ctg")
    parser.add_argument("--checkpoints", nargs="+", required=True)
    parser.add_argument("--guidance", default="no_collision")
    parser.add_argument("--split", default="val")
    parser.add_argument("--scenes", type=int, default=100)
    return parser


def drive(args: argparse.Namespace, scenes: ScenarioTensor, checkpoint: str, seed: int) -> Rollout:
    """One closed-loop run of ``checkpoint`` over ``scenes`` at evaluation ``seed``, as ``trafficrlhf evaluate``
    drives it (``args`` from :func:`checkpoints_parser`)."""
    torch.manual_seed(seed)
    policy = build_policy(args.model, {"guidance": args.guidance, "checkpoint": checkpoint, "seed": seed})
    return run_batched(policy, scenes, EvaluationConfig(batch_size=50, seed=seed))[0]


def main() -> None:
    parser = checkpoints_parser(__doc__)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", choices=("ctg", "body"), default="ctg")
    args = parser.parse_args()
    scenes = get_scenario_source("nuscenes_pred").load_batch(args.split, args.scenes)
    rollouts = [drive(args, scenes, checkpoint, args.seed) for checkpoint in args.checkpoints]
    result = {}
    for name, agents in agent_groups(rollouts).items():
        result[name] = {"agents": int(agents.sum()), "scenes": int(agents.any(-1).sum()),
                        **{c: realism_over(r, agents, args.preset) for c, r in zip(args.checkpoints, rollouts)}}
        cells = " | ".join(f"{c.rstrip('/').split('/')[-1]} {result[name][c]['mean']:.4f}" for c in args.checkpoints)
        print(f"{name:28s} {result[name]['agents']:4d} agents {result[name]['scenes']:4d} scenes | {cells}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
