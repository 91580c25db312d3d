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

from trafficrlhf_sdk import get_scenario_source
from trafficrlhf_sdk.align.contexts import held_out_scene_ids
from trafficrlhf_sdk.cli.evaluate import build_policy
from trafficrlhf_sdk.evaluation import EvaluationConfig, evaluate_policy


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
    torch.manual_seed(args.seed)
    policy = build_policy(args.model, {"guidance": args.guidance, "checkpoint": args.checkpoint, "seed": args.seed})
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids("train")
    ids = held_out_scene_ids(ids, args.holdout_every) if args.holdout_every else ids[args.first:]
    scenario = source.load_batch("train", scene_ids=ids)
    report = evaluate_policy(policy, scenario, EvaluationConfig(batch_size=50, seed=args.seed))
    keys = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body", "realism_body_lon_acc",
            "realism_body_lat_acc", "realism_body_jerk", "guidance_target_speed")
    print(json.dumps({"scenes": len(ids), "checkpoint": args.checkpoint, "wall_s": round(report.wall_time_s, 1),
                      **{k: round(report.values[k], 4) for k in keys}}))


if __name__ == "__main__":
    main()
