"""Closed-loop evaluation on scenes kept out of both alignment and the reported val figures, for choosing settings.

Two kinds of development scenes:

* held-out *train* scenes: the last ones (`--first N`: those after the N that `align --scenes N` uses; one
  stretch of the recording) or every K-th (`--holdout-every K`, for models aligned with `align --holdout-every K`).
  The bundled base models were trained on every train scene, these included, so they are easier for the base
  than unseen roads (4 s CTG: 0.082 held out against 0.138 on val) and rank settings differently from val;
* the *val tail* (`--split val`): the long-enough val scenes after the first `--first` (default 100), those that
  `trafficrlhf evaluate --scenes 100` reports on excluded (60 scenes, 240 controlled agents). Unseen by every
  model and disjoint from the reported scenes, but other roads: the 4 s CTG fails 0.031 there against 0.138 on
  the reported 100, and collisions, not off-road, dominate (docs/explanation/alignment-log.md, session 12).
  A check that a setting carries to other roads more than a place to tune failure rates.

`--mirror` reflects the chosen scenes (`trafficrlhf_sdk.scenario.mirror_scenario`: y -> -y, left-hand traffic
becomes right-hand and back). Mirrored held-out train scenes are roads neither the base nor the alignment ever
saw in that form, and the base fails there as it fails on val: mostly off the road (4 s CTG, seeds 0-7: failure
0.086, off-road 0.073, collision 0.023; unmirrored, collisions dominate). It is the development set that can see
an off-road gain (docs/explanation/alignment-log.md, session 42). `--first 0 --mirror` drives all 442
long-enough train scenes mirrored (about 4 min per seed on one thread): collision-heavy for the base too, and
it did not order session 43's runs as val did.

    python scripts/align_dev_eval.py --model ctg --guidance no_collision [--checkpoint DIR] [--first 400]
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --holdout-every 10
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --split val
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --holdout-every 10 --mirror
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --holdout-every 10 --mirror \
        --seeds 0-7
    python scripts/align_dev_eval.py --model ctg --guidance no_collision --checkpoint DIR --holdout-every 10 \
        --model-option steer_gate_offset=2
"""

from __future__ import annotations

import argparse
import json
import os

import click
import pydantic
import torch
from tqdm import tqdm

from trafficrlhf_sdk import ScenarioTensor, get_scenario_source
from trafficrlhf_sdk.alignment.contexts import held_out_scene_ids
from trafficrlhf_sdk.cli import format_error, parse_key_values
from trafficrlhf_sdk.plugins import build_policy
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
from trafficrlhf_sdk.scenario.transforms import mirror_scenario


KEYS = ("failure_rate", "collision_rate", "collision_rate_own", "collision_rate_replayed", "offroad_rate",
        "realism_ctg", "realism_body", "realism_body_lon_acc", "realism_body_lat_acc", "realism_body_jerk",
        "realism_body_speed", "guidance_target_speed", "speed_ratio", "stopped_share")


DEFAULT_FIRST = {"train": 400, "val": 100}


def held_out_scenes(holdout_every: int | None, first: int | None = None, split: str = "train",
                    mirror: bool = False) -> tuple[list[str], ScenarioTensor]:
    """The development scene ids of ``split`` and their batch: every ``holdout_every``-th scene (train only), or
    the long-enough scenes after the first ``first`` (default 400 for train, 100 for val); ``mirror``: the batch
    reflected across each scene's x axis (ids unchanged)."""
    if split not in DEFAULT_FIRST:
        raise ValueError(f"split is {split!r}; use 'train' (held-out train scenes) or 'val' (the val tail).")
    if split == "val" and holdout_every:
        raise ValueError(f"holdout_every is {holdout_every} with split 'val'; alignment never sees val, so use "
                         "`first` (the val tail after the reported scenes) instead.")
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids(split)
    if holdout_every:
        ids = held_out_scene_ids(ids, holdout_every)
    else:
        ids = ids[DEFAULT_FIRST[split] if first is None else first:]
    batch = source.load_batch(split, scene_ids=ids)
    return ids, mirror_scenario(batch) if mirror else batch


def held_out_report(model: str, checkpoint: str | None, guidance: str | None, scenario: ScenarioTensor,
                    seed: int, options: dict[str, object] | None = None, out_dir: str | None = None,
                    metadata: dict[str, object] | None = None) -> dict[str, float]:
    """Closed-loop metrics of ``model`` (optionally ``checkpoint``, and ``options`` as `--model-option` gives
    them) on ``scenario``; failure rates are shares of controlled agents, realism deviations Wasserstein
    distances (m/s^2, m/s^3). ``out_dir``: also write the full report there as ``results.json`` (the format of
    `trafficrlhf evaluate --out`, per-scene values included, ``metadata`` added), for `trafficrlhf compare`."""
    torch.manual_seed(seed)
    policy = build_policy(model, {**(options or {}), "guidance": guidance, "checkpoint": checkpoint, "seed": seed})
    report = evaluate_policy(policy, scenario, EvaluationConfig(batch_size=50, seed=seed))
    if out_dir is not None:
        report.metadata.update({"model": model, "guidance": guidance, "checkpoint": checkpoint, "seed": seed,
                                "model_options": options or {}, **(metadata or {})})
        report.save(out_dir, plot=False)
    return {"wall_s": round(report.wall_time_s, 1), **{k: round(report.values[k], 4) for k in KEYS}}


def comma_numbers(text: str, kind: type, option: str) -> list:  # type: ignore[type-arg]
    """``"1,1.5,2"`` -> ``[1.0, 1.5, 2.0]`` (``kind`` float) for an argparse ``type=``; ``option`` names the flag
    in the error."""
    try:
        values = [kind(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values:
        raise argparse.ArgumentTypeError(f"{option} is {text!r}; give comma-separated numbers such as 1,1.5,2.")
    return values


def seed_list(text: str) -> list[int]:
    """``"0-3,8"`` -> ``[0, 1, 2, 3, 8]`` for an argparse ``type=`` (ranges inclusive, order kept); a seed named
    twice is refused, as `trafficrlhf evaluate --seeds` refuses it."""
    seeds: list[int] = []
    try:
        for part in filter(None, (piece.strip() for piece in text.split(","))):
            first, _, last = part.partition("-")
            span = range(int(first), int(last or first) + 1)
            if not span:
                raise ValueError(part)
            seeds += span
    except ValueError:
        seeds = []
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"--seeds is {text!r}; give distinct seeds and inclusive ranges such as "
                                         "0-7 or 0,1,2 or 0-3,8.")
    return seeds


def mean_report(reports: list[dict[str, float]]) -> dict[str, float]:
    """The per-key mean of several :func:`held_out_report` results (``wall_s`` summed)."""
    mean = {key: round(sum(r[key] for r in reports) / len(reports), 4) for key in reports[0] if key != "wall_s"}
    return {"wall_s": round(sum(r["wall_s"] for r in reports), 1), **mean}


def held_out_reports(model: str, checkpoints: dict[str, str], guidance: str | None, scenario: ScenarioTensor,
                     seeds: list[int], desc: str = "checkpoint x seed") -> dict[str, list[dict[str, float]]]:
    """``{key: [held_out_report per seed]}`` for every ``key: checkpoint`` in ``checkpoints``, with a progress bar."""
    reports: dict[str, list[dict[str, float]]] = {key: [] for key in checkpoints}
    progress = tqdm(total=len(checkpoints) * len(seeds), desc=desc, unit="run")
    for key, checkpoint in checkpoints.items():
        for seed in seeds:
            reports[key].append(held_out_report(model, checkpoint, guidance, scenario, seed))
            progress.update()
    progress.close()
    return reports


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", required=True)
    parser.add_argument("--guidance", default=None)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--split", choices=sorted(DEFAULT_FIRST), default="train",
                        help="train: held-out train scenes; val: the val tail after the reported scenes.")
    parser.add_argument("--first", type=int, default=None,
                        help="Development scenes are the split's scenes [first:] (default 400 for train, 100 for "
                             "val).")
    parser.add_argument("--holdout-every", type=int, default=None,
                        help="Instead: the scenes `align --holdout-every K` held out (every K-th, spread over the "
                             "split).")
    parser.add_argument("--mirror", action="store_true",
                        help="Drive the scenes mirrored (left- and right-hand traffic swapped): roads the base never "
                             "imitated, and alignment only with --mirror-scenes.")
    parser.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                        help="A model option, as in `trafficrlhf evaluate --model-option` (repeatable).")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="Also write each seed's full report to DIR/seed_S/results.json (per-scene values "
                             "included), so that `trafficrlhf compare DIR_A/seed_* DIR_B/seed_* --interval` can "
                             "pair two models scene by scene.")
    seeds = parser.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=int, default=0)
    seeds.add_argument("--seeds", type=seed_list, default=None, metavar="LIST",
                       help="Several evaluation seeds (0-7, 0,1,2 or 0-3,8): one JSON line per seed, then one "
                            "with their means under 'mean'. One development seed moves a failure rate by up to "
                            "0.04, so compare models over eight or more.")
    args = parser.parse_args()
    try:
        options = parse_key_values(args.model_option, "--model-option")
    except click.BadParameter as error:
        parser.error(f"--model-option: {error.message}")
    torch.set_num_threads(1)
    if args.split == "val" and args.holdout_every:
        parser.error(f"--holdout-every {args.holdout_every} with --split val: use --first for the val tail.")
    ids, scenario = held_out_scenes(args.holdout_every, args.first, args.split, args.mirror)
    header = {"split": args.split, "mirror": args.mirror, "scenes": len(ids), "checkpoint": args.checkpoint,
              "model_options": options}
    reports = []
    for seed in tqdm(args.seeds or [args.seed], desc="seeds", unit="run", disable=not args.seeds):
        try:
            report = held_out_report(args.model, args.checkpoint, args.guidance, scenario, seed, options,
                                     out_dir=args.out and os.path.join(args.out, f"seed_{seed}"),
                                     metadata={"scene_ids": ids, "split": args.split, "mirror": args.mirror,
                                               "source": "nuscenes_pred"})
        except (TrafficRLHFError, pydantic.ValidationError, OSError) as error:  # one line, as the CLI gives it
            parser.exit(2, f"Error: {format_error(error)}\n")
        reports.append(report)
        print(json.dumps({**header, **({"seed": seed} if args.seeds else {}), **report}), flush=True)
    if args.seeds:
        print(json.dumps({**header, "seeds": args.seeds, "mean": mean_report(reports)}))


if __name__ == "__main__":
    main()
