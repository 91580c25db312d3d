"""Whom do a model's closed-loop collisions involve? A diagnostic beside ``trafficrlhf evaluate``.

Runs the standard evaluation (same scenes, seed and batching as ``trafficrlhf evaluate``), then, for every
controlled agent that collides, looks at its first contact: is the other box an agent the model drives
(``controlled``) or one replayed from the log (``replayed``, which cannot react), what type it is, where it is seen
from the colliding agent (``front`` within 45 degrees of its heading, ``rear`` within 45 degrees of its back,
``side`` otherwise), whether it stands (below 0.5 m/s) and when the contact comes (``onset``: within the first
plan's 0.5 s, which no replan could change, up to 3 s, or later). Each agent is weighted as in the failure rate (one
over its scene's controlled agents, scenes averaged), so the shares of one grouping sum to the collision rate.

    python scripts/collision_partners.py --model ctg --checkpoint reference_models/aligned/ctg_4s --seed 0

The development sets of ``scripts/align_dev_eval.py`` work too (``--split``, ``--first``, ``--holdout-every``,
``--mirror``); without any of them it drives the reported val scenes. All 442 train scenes mirrored (MA):

    python scripts/collision_partners.py --model ctg --checkpoint DIR --split train --first 0 --mirror --seed 2
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from typing import Any

import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.metrics.geometry import colliding_pairs
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.simulation.simulator import Rollout

STANDING_SPEED = 0.5  # m/s: below this the partner counts as standing
FIRST_PLAN_S = 0.5  # s: the first plan runs this long before the closed loop replans (2 Hz)
EARLY_S = 3.0  # s: contacts up to this are "early", after it "late"


def first_contacts(rollout: Rollout) -> list[dict[str, Any]]:
    """One record per controlled agent that collides within the simulated window: scene, agent, step (0-based
    within the window), partner index, whether the partner is controlled, its type name, the partner's bearing
    seen from the agent (rad, 0 = straight ahead), both speeds (m/s) and the agent's weight in the scene average."""
    window = rollout.simulated.time_slice(rollout.start_index + 1, rollout.end_index + 1)
    scene, i, j, step = colliding_pairs(window.xy, window.yaw, window.extent, window.valid)
    controlled = rollout.controlled
    counts = controlled.sum(-1)
    scenes_with_agents = int((counts > 0).sum())
    # both orientations of each pair, then the earliest contact per (scene, agent); ties: lowest partner index
    me = torch.cat([i, j])
    other = torch.cat([j, i])
    scene, step = torch.cat([scene, scene]), torch.cat([step, step])
    keep = controlled[scene, me]
    scene, me, other, step = scene[keep], me[keep], other[keep], step[keep]
    order = torch.argsort(step * (other.max() + 1 if other.numel() else 1) + other, stable=True)
    records, seen = [], set()
    for k in order.tolist():
        key = (int(scene[k]), int(me[k]))
        if key in seen:
            continue
        seen.add(key)
        b, a, o, t = key[0], key[1], int(other[k]), int(step[k])
        offset = window.xy[b, o, t] - window.xy[b, a, t]
        bearing = float(wrap_angle(torch.atan2(offset[1], offset[0]) - window.yaw[b, a, t]))
        records.append({
            "scene": b, "agent": a, "step": t, "partner": o, "partner_controlled": bool(controlled[b, o]),
            "partner_type": AgentType(int(window.agent_type[b, o])).name.lower(), "bearing": bearing,
            "speed": float(window.states[b, a, t, 2]), "partner_speed": float(window.states[b, o, t, 2]),
            "time_s": (t + 1) * rollout.simulated.dt,
            "weight": 1.0 / (int(counts[b]) * scenes_with_agents),
        })
    return records


def group(record: dict[str, Any]) -> dict[str, str]:
    """The categories one first contact falls in."""
    side = "front" if abs(record["bearing"]) <= math.pi / 4 else ("rear" if abs(record["bearing"]) >= 3 * math.pi / 4
                                                                  else "side")
    return {
        "partner": "controlled" if record["partner_controlled"] else "replayed",
        "partner_type": record["partner_type"],
        "where": side,
        "partner_standing": "standing" if abs(record["partner_speed"]) < STANDING_SPEED else "moving",
        "partner_and_where": ("controlled" if record["partner_controlled"] else "replayed") + "/" + side,
        "onset": onset(record["time_s"]),
    }


def onset(time_s: float) -> str:
    """When a contact comes, ``time_s`` seconds into the closed loop: within the first plan, up to 3 s, or later."""
    if time_s <= FIRST_PLAN_S + 1e-9:
        return "first plan (<= 0.5 s)"
    return "early (<= 3 s)" if time_s <= EARLY_S + 1e-9 else "late (> 3 s)"


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Per grouping, each category's share of the collision rate (weights summed) and its agent count."""
    shares: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for record in records:
        for key, value in group(record).items():
            shares[key][value] += record["weight"]
            counts[key][value] += 1
    return {
        "collision_rate": round(math.fsum(r["weight"] for r in records), 4),
        "colliding_agents": len(records),
        "groups": {key: {value: {"rate": round(shares[key][value], 4), "agents": counts[key][value]}
                         for value in sorted(shares[key], key=lambda v: -shares[key][v])} for key in shares},
    }


def main() -> None:
    """Command-line entry point."""
    import importlib.util
    from pathlib import Path

    import click
    import pydantic

    from trafficrlhf_sdk import get_scenario_source
    from trafficrlhf_sdk.cli import format_error, parse_key_values
    from trafficrlhf_sdk.plugins import build_policy
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--guidance", default="no_collision", help="Guidance preset (default no_collision).")
    parser.add_argument("--split", choices=("train", "val"), default="val")
    parser.add_argument("--scenes", type=int, default=100,
                        help="Without a development-set option: the split's first N long-enough scenes (default "
                             "100, the reported val scenes).")
    parser.add_argument("--first", type=int, default=None,
                        help="A development set: the split's scenes [first:], as in scripts/align_dev_eval.py.")
    parser.add_argument("--holdout-every", type=int, default=None,
                        help="A development set: every K-th train scene, as `align --holdout-every K` holds out.")
    parser.add_argument("--mirror", action="store_true", help="Drive the chosen scenes mirrored.")
    parser.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                        help="A model option, as in `trafficrlhf evaluate --model-option` (repeatable).")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    try:
        options = parse_key_values(args.model_option, "--model-option")
    except click.BadParameter as error:
        parser.error(f"--model-option: {error.message}")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    try:
        policy = build_policy(args.model, {**options, "guidance": args.guidance, "checkpoint": args.checkpoint,
                                           "seed": args.seed})
        if args.first is not None or args.holdout_every or args.mirror:
            spec = importlib.util.spec_from_file_location("align_dev_eval",
                                                          Path(__file__).with_name("align_dev_eval.py"))
            assert spec is not None and spec.loader is not None
            dev = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(dev)
            _, scenario = dev.held_out_scenes(args.holdout_every, args.first, args.split, args.mirror)
        else:
            source = get_scenario_source("nuscenes_pred")
            scenario = source.load_batch(args.split, scene_ids=source.scene_ids(args.split)[: args.scenes])
        report = evaluate_policy(policy, scenario, EvaluationConfig(batch_size=50, seed=args.seed))
    except (TrafficRLHFError, pydantic.ValidationError, OSError, ValueError) as error:  # one line, as the CLI
        parser.exit(2, f"Error: {format_error(error)}\n")
    summary = summarize(first_contacts(report.rollout))
    print(json.dumps({"model": args.model, "checkpoint": args.checkpoint, "model_options": options, "seed": args.seed,
                      "split": args.split, "mirror": args.mirror, "scenes": scenario.num_scenes,
                      "failure_rate": round(report.values["failure_rate"], 4),
                      "collision_rate_metric": round(report.values["collision_rate"], 4),
                      **{key: round(report.values[key], 4) for key in ("offroad_rate", "realism_ctg", "realism_body")
                         if key in report.values}, **summary}, indent=1))


if __name__ == "__main__":
    main()
