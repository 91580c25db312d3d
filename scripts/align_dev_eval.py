"""Closed-loop evaluation on held-out *train* scenes, for choosing alignment settings without touching val.

Held out: the last train scenes (`--first N`: those after the N that `align --scenes N` uses; they come from one
stretch of the recording) or, better, every K-th train scene (`--holdout-every K`, for models aligned with
`align --holdout-every K`: spread over the whole split).

    python scripts/align_dev_eval.py --model ctg --guidance no_collision [--checkpoint DIR] [--first 400]
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --holdout-every 10
"""

from __future__ import annotations

import argparse
import json

import torch

from trafficrlhf_sdk import ScenarioTensor, get_scenario_source
from trafficrlhf_sdk.align.contexts import held_out_scene_ids
from trafficrlhf_sdk.cli.evaluate import build_policy
from trafficrlhf_sdk.evaluation import EvaluationConfig, evaluate_policy


KEYS = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body", "realism_body_lon_acc",
        "realism_body_lat_acc", "realism_body_jerk", "guidance_target_speed", "speed_ratio", "stopped_share")


def held_out_scenes(holdout_every: int | None, first: int = 400) -> tuple[list[str], ScenarioTensor]:
    """The held-out train scene ids and their batch (every ``holdout_every``-th scene, or those after ``first``)."""
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids("train")
    ids = held_out_scene_ids(ids, holdout_every) if holdout_every else ids[first:]
    return ids, source.load_batch("train", scene_ids=ids)


def held_out_report(model: str, checkpoint: str | None, guidance: str | None, scenario: ScenarioTensor,
                    seed: int) -> dict[str, float]:
    """Closed-loop metrics of ``model`` (optionally ``checkpoint``) on ``scenario``; failure rates are shares of
    controlled agents, realism deviations Wasserstein distances (m/s^2, m/s^3)."""
    torch.manual_seed(seed)
    policy = build_policy(model, {"guidance": guidance, "checkpoint": checkpoint, "seed": seed})
    report = evaluate_policy(policy, scenario, EvaluationConfig(batch_size=50, seed=seed))
    return {"wall_s": round(report.wall_time_s, 1), **{k: round(report.values[k], 4) for k in KEYS}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", required=True)
    parser.add_argument("--guidance", default=None)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--first", type=int, default=400, help="Held-out scenes are train scenes [first:].")
    parser.add_argument("--holdout-every", type=int, default=None,
                        help="Instead: the scenes `align --holdout-every K` held out (every K-th, spread over the "
                             "split).")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    ids, scenario = held_out_scenes(args.holdout_every, args.first)
    report = held_out_report(args.model, args.checkpoint, args.guidance, scenario, args.seed)
    print(json.dumps({"scenes": len(ids), "checkpoint": args.checkpoint, **report}))


if __name__ == "__main__":
    main()
