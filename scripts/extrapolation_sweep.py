r"""Choose an extrapolation factor for an aligned checkpoint on development scenes (never the reported val ones).

For each factor f, writes base + f x (aligned - base) (``trafficrlhf extrapolate``) to OUT/x<f>, drives the
held-out scenes in closed loop with every seed, and prints a table of the mean metrics; the factor with the lowest
mean held-out failure rate is named last and recorded in OUT/sweep.json (with every per-seed figure), and
OUT/sweep.png plots failure rate and realism against the factor. With factor 0 (the base) in the sweep, it also
names the lowest-failure factor whose held-out realism deviations (ctg and body) are both not above the base's.
Read the speed columns too: a factor can cut failures by stopping agents (speed / log well below 1).

    python scripts/extrapolation_sweep.py --model trafficgen --guidance no_collision \
        --base reference_models/trafficgen/checkpoints/trafficgen_small \
        --aligned reference_models/aligned/trafficgen --factors 0,1,1.5,2,2.5,3 --holdout-every 10 --out out/sweep

``--split val`` sweeps on the val scenes after the first 100 instead (unseen by every model; see
``align_dev_eval.py``).

``--direction FROM TO --direction-weights 0,1,2`` sweeps a grid instead: base + f x (aligned - base) + w x (TO -
FROM) for every factor f and weight w (task arithmetic: e.g. TO a second fine-tuning stage run from FROM = the
aligned checkpoint, for realism). Keys and folders are then "f+w" and OUT/x<f>_d<w>; the choices are pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch
from align_dev_eval import KEYS, comma_numbers, held_out_reports, held_out_scenes

from trafficrlhf_sdk.alignment import extrapolate_checkpoint
from trafficrlhf_sdk.errors import TrafficRLHFError

REALISM = ("realism_ctg", "realism_body")  # both deviations count for "realism not worse"


def _key(factor: float, weight: float | None) -> str:
    return f"{factor:g}" if weight is None else f"{factor:g}+{weight:g}"


def sweep(model: str, base: str, aligned: str, factors: list[float], seeds: list[int], out_dir: str,
          guidance: str | None, holdout_every: int | None, first: int | None = None,
          max_scenes: int | None = None, min_speed_ratio: float | None = None,
          split: str = "train", direction: tuple[str, str] | None = None,
          direction_weights: list[float] | None = None) -> dict:  # type: ignore[type-arg]
    """Evaluate base + f x (aligned - base) for every f in ``factors`` on the development scenes of ``split``
    (held-out train scenes, or the val tail after the reported 100: ``align_dev_eval.held_out_scenes``), every seed.
    With ``direction`` = (FROM, TO), every f is combined with every w in ``direction_weights`` (+ w x (TO - FROM)).

    Returns {"factors": [...], "per_seed": {key: [report per seed]}, "mean": {key: {metric: mean}},
    "best_factor": f (or [f, w] with a direction)}; rates are shares of controlled agents, realism deviations
    Wasserstein distances (m/s^2, m/s^3). With ``min_speed_ratio``, only settings whose mean held-out speed /
    logged speed reaches it can be chosen (``best_factor`` None when none does).
    """
    ids, scenario = held_out_scenes(holdout_every, first, split)
    if max_scenes is not None:
        ids, scenario = ids[:max_scenes], scenario[:max_scenes]
    weights: list[float | None] = [None] if direction is None else list(direction_weights or [1.0])
    settings = {_key(f, w): (f, w) for f in factors for w in weights}
    # every checkpoint first: a bad input fails before any driving
    checkpoints = {}
    for key, (factor, weight) in settings.items():
        folder = f"x{factor:g}" if weight is None else f"x{factor:g}_d{weight:g}"
        extra = [] if weight is None or direction is None else [(direction[0], direction[1], weight)]
        checkpoints[key] = extrapolate_checkpoint(base, aligned, os.path.join(out_dir, folder), factor, extra)
    per_seed = held_out_reports(model, checkpoints, guidance, scenario, seeds, "setting x seed")
    mean = {f: {k: sum(r[k] for r in runs) / len(runs) for k in KEYS} for f, runs in per_seed.items()}
    fast_enough = [f for f in mean if min_speed_ratio is None or mean[f]["speed_ratio"] >= min_speed_ratio]

    def lowest_failure(candidates: list[str]) -> float | list[float] | None:
        if not candidates:
            return None
        factor, weight = settings[min(candidates, key=lambda f: mean[f]["failure_rate"])]
        return float(factor) if weight is None else [float(factor), float(weight)]

    result = {"model": model, "base": base, "aligned": aligned, "split": split, "scenes": len(ids), "seeds": seeds,
              "factors": [float(f) for f in factors], "per_seed": per_seed, "mean": mean,
              "min_speed_ratio": min_speed_ratio, "best_factor": lowest_failure(fast_enough)}
    if direction is not None:
        result["direction"] = {"from": direction[0], "to": direction[1], "weights": [float(w) for w in weights]}
    base_key = _key(0.0, None if direction is None else 0.0)
    if base_key in mean:  # the base was evaluated: also name the best setting whose realism is not worse
        keeping = [f for f in fast_enough if all(mean[f][k] <= mean[base_key][k] for k in REALISM)]
        result["best_factor_keeping_realism"] = lowest_failure(keeping)
    return result


def plot(result: dict, path: str) -> None:  # type: ignore[type-arg]
    """Failure rate (mean, and per seed without a direction), both realism deviations and the speed against the
    log, per factor; with a direction one line per direction weight (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factors = result["factors"]
    weights = result["direction"]["weights"] if "direction" in result else [None]
    fig, (left, right, speed) = plt.subplots(1, 3, figsize=(13, 3.5))
    for j, weight in enumerate(weights):
        keys = [_key(f, weight) for f in factors]
        label = "" if weight is None else f", direction x {weight:g}"
        alpha = 1.0 - 0.6 * j / len(weights)  # later direction weights fainter
        if weight is None:
            for i in range(len(result["seeds"])):
                left.plot(factors, [result["per_seed"][k][i]["failure_rate"] for k in keys], color="0.7", lw=1)
        left.plot(factors, [result["mean"][k]["failure_rate"] for k in keys], "o-", color=f"C{3 + j}",
                  label="mean of seeds" + label)
        for name, color, style in (("realism_ctg", "C0", "o-"), ("realism_body", "C2", "s--")):
            right.plot(factors, [result["mean"][k][name] for k in keys], style, color=color,
                       alpha=alpha, label=name + label)
        speed.plot(factors, [result["mean"][k]["speed_ratio"] for k in keys], "o-", color="C1",
                   alpha=alpha, label="speed / logged" + label)
        speed.plot(factors, [result["mean"][k]["stopped_share"] for k in keys], "s--", color="C4",
                   alpha=alpha, label="stopped at the end" + label)
    left.set(xlabel="factor (0 = base, 1 = aligned)", ylabel="held-out failure rate", title=result["model"])
    left.legend(fontsize=7)
    right.set(xlabel="factor", ylabel="realism deviation (lower is better)")
    right.legend(fontsize=7)
    speed.axhline(1.0, color="0.6", lw=0.8, ls="--")
    speed.set(xlabel="factor", ylabel="speed ratio / share of agents")
    speed.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="Registered traffic model, e.g. ctg / trafficgen / bits.")
    parser.add_argument("--base", required=True, help="Checkpoint folder alignment started from.")
    parser.add_argument("--aligned", required=True, help="Aligned checkpoint folder (one run or a seed average).")
    parser.add_argument("--factors", default="0,1,1.5,2,2.5,3",
                        type=lambda t: comma_numbers(t, float, "--factors"), help="Comma-separated factors >= 0.")
    parser.add_argument("--seeds", default="0,1,2", type=lambda t: comma_numbers(t, int, "--seeds"),
                        help="Evaluation seeds (comma-separated).")
    parser.add_argument("--guidance", default=None, help="Guidance while driving, e.g. no_collision.")
    parser.add_argument("--holdout-every", type=int, default=10,
                        help="The scenes `align --holdout-every K` kept out [default: 10].")
    parser.add_argument("--split", choices=("train", "val"), default="train",
                        help="train: the held-out train scenes; val: the val scenes after the first 100 (those "
                             "`trafficrlhf evaluate --scenes 100` reports on excluded; --holdout-every is ignored).")
    parser.add_argument("--max-scenes", type=int, default=None, help="Only the first N held-out scenes (smoke runs).")
    parser.add_argument("--min-speed-ratio", type=float, default=None,
                        help="Choose only among factors whose held-out speed / logged speed is at least this, "
                             "e.g. 0.9 (failures avoided by stopping do not count).")
    parser.add_argument("--direction", nargs=2, metavar=("FROM", "TO"), default=None,
                        help="Also add w x (TO - FROM) for every w in --direction-weights (a grid).")
    parser.add_argument("--direction-weights", default="0,1",
                        type=lambda t: comma_numbers(t, float, "--direction-weights"),
                        help="Weights of --direction, comma-separated [default: 0,1].")
    parser.add_argument("--out", required=True, help="Folder for the checkpoints, sweep.json and sweep.png.")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if any(f < 0 for f in args.factors):
        parser.error(f"--factors has a negative value ({args.factors}); factors are >= 0.")
    try:
        result = sweep(args.model, args.base, args.aligned, args.factors, args.seeds, args.out, args.guidance,
                       None if args.split == "val" else args.holdout_every, max_scenes=args.max_scenes,
                       min_speed_ratio=args.min_speed_ratio, split=args.split,
                       direction=tuple(args.direction) if args.direction else None,
                       direction_weights=args.direction_weights)
    except TrafficRLHFError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 2
    with open(os.path.join(args.out, "sweep.json"), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
    plot(result, os.path.join(args.out, "sweep.png"))
    print(f"held out: {result['scenes']} scenes, seeds {args.seeds}")
    first_column = "factor + direction weight" if args.direction else "factor"
    print(f"| {first_column} | failure (per seed) | collision | off-road | realism ctg | realism body | "
          "speed / log | stopped |")
    print("|---|---|---|---|---|---|---|---|")
    for key, mean in result["mean"].items():
        seeds = " / ".join(f"{r['failure_rate']:.4f}" for r in result["per_seed"][key])
        print(f"| {key} | {mean['failure_rate']:.4f} ({seeds}) | {mean['collision_rate']:.4f} | "
              f"{mean['offroad_rate']:.4f} | {mean['realism_ctg']:.4f} | {mean['realism_body']:.4f} | "
              f"{mean['speed_ratio']:.3f} | {mean['stopped_share']:.3f} |")
    pace = "" if args.min_speed_ratio is None else f" (speed / log >= {args.min_speed_ratio:g})"
    for label, key in (("lowest held-out failure rate", "best_factor"),
                       ("lowest with both realism deviations not above the base's", "best_factor_keeping_realism")):
        if key in result:
            choice = result[key]
            if choice is None:
                print(f"{label}{pace}: no factor qualifies")
            elif isinstance(choice, list):
                print(f"{label}{pace}: factor {choice[0]:g}, direction weight {choice[1]:g} "
                      f"({args.out}/x{choice[0]:g}_d{choice[1]:g})")
            else:
                print(f"{label}{pace}: factor {choice:g} ({args.out}/x{choice:g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
