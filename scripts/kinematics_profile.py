"""How a model's closed-loop kinematics differ from the log's: the spread behind the realism deviations.

The realism deviations are Wasserstein distances between histograms; a larger one does not say whether the model
accelerates, turns or jerks more than the log or less. This drives a model for 10 s from the first ``--scenes``
long-enough val scenes (``no_collision`` by default, evaluation seed ``--seed``, as ``trafficrlhf evaluate``) and
prints, for the controlled agents that move at the first statistics sample, the mean absolute value and the
quantiles of longitudinal / lateral acceleration (m/s^2), jerk (m/s^3) and speed (m/s) at 0.5 s, for the log and
for the model (the metrics' ``body`` preset: accelerations along and across the heading).

    python scripts/kinematics_profile.py --model ctg --checkpoint reference_models/aligned/ctg_4s
"""

from __future__ import annotations

import argparse

import torch

from trafficrlhf_sdk import ScenarioTensor, get_scenario_source
from trafficrlhf_sdk.plugins import build_policy
from trafficrlhf_sdk.metrics.realism import kinematics
from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate

QUANTITIES = ("lon_acc", "lat_acc", "jerk", "speed")
QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9, 0.99)


def kinematic_values(scenario: ScenarioTensor, agents: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per quantity, the flat values of ``agents (B, A)`` over the window ``scenario`` at the 0.5 s statistics
    step, for samples whose inputs are valid and agents moving at the first sample (body frame)."""
    values, valid, moving = kinematics(scenario, "body")
    keep = valid & agents[:, :, None] & moving[:, :, None]
    return {q: values[q][keep].float() for q in QUANTITIES}


def profile(values: torch.Tensor) -> dict[str, float]:
    """``n``, ``mean_abs`` and the :data:`QUANTILES` (keys ``q10`` ...) of a flat tensor."""
    qs = torch.quantile(values, torch.tensor(QUANTILES)) if values.numel() else torch.full((len(QUANTILES),),
                                                                                           float("nan"))
    return {"n": float(values.numel()), "mean_abs": float(values.abs().mean()) if values.numel() else float("nan"),
            **{f"q{round(100 * q)}": float(v) for q, v in zip(QUANTILES, qs)}}


def closed_loop_profiles(model: str, checkpoint: str | None, guidance: str | None, scenario: ScenarioTensor,
                         seed: int, batch_size: int = 50) -> dict[str, dict[str, dict[str, float]]]:
    """``{"log" | "model": {quantity: profile}}`` of ``scenario`` driven 10 s by ``model`` from ``current_index``."""
    torch.manual_seed(seed)
    policy = build_policy(model, {"guidance": guidance, "checkpoint": checkpoint, "seed": seed})
    logged: dict[str, list[torch.Tensor]] = {q: [] for q in QUANTITIES}
    driven: dict[str, list[torch.Tensor]] = {q: [] for q in QUANTITIES}
    for start in range(0, scenario.num_scenes, batch_size):
        part = scenario[start: start + batch_size]
        rollout = simulate(policy, part, SimulationConfig(duration_s=10.0, start_index=part.current_index))
        now, end = part.current_index, rollout.simulated.num_steps  # the same steps for both
        for q, v in kinematic_values(part.time_slice(now, end), rollout.controlled).items():
            logged[q].append(v)
        for q, v in kinematic_values(rollout.simulated.time_slice(now, end), rollout.controlled).items():
            driven[q].append(v)
    return {"log": {q: profile(torch.cat(v)) for q, v in logged.items()},
            "model": {q: profile(torch.cat(v)) for q, v in driven.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--guidance", default="no_collision")
    parser.add_argument("--scenes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids("val")[: args.scenes]
    result = closed_loop_profiles(args.model, args.checkpoint, args.guidance,
                                  source.load_batch("val", scene_ids=ids), args.seed)
    keys = ["mean_abs"] + [f"q{round(100 * q)}" for q in QUANTILES]
    print("| quantity | source | n | " + " | ".join(keys) + " |")
    print("|---|---|---|" + "---|" * len(keys))
    for q in QUANTITIES:
        for who in ("log", "model"):
            row = result[who][q]
            print(f"| {q} | {who} | {int(row['n'])} | " + " | ".join(f"{row[k]:+.2f}" for k in keys) + " |")


if __name__ == "__main__":
    main()
