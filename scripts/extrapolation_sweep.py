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
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch
from align_dev_eval import KEYS, held_out_report, held_out_scenes
from tqdm import tqdm

from trafficrlhf_sdk.align import extrapolate_checkpoint
from trafficrlhf_sdk.errors import TrafficRLHFError

REALISM = ("realism_ctg", "realism_body")  # both deviations count for "realism not worse"


def _numbers(text: str, kind: type, option: str) -> list:  # type: ignore[type-arg]
    try:
        values = [kind(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values:
        raise argparse.ArgumentTypeError(f"{option} is {text!r}; give comma-separated numbers such as 1,1.5,2.")
    return values


def sweep(model: str, base: str, aligned: str, factors: list[float], seeds: list[int], out_dir: str,
          guidance: str | None, holdout_every: int | None, first: int | None = None,
          max_scenes: int | None = None, min_speed_ratio: float | None = None,
          split: str = "train") -> dict:  # type: ignore[type-arg]
    """Evaluate base + f x (aligned - base) for every f in ``factors`` on the development scenes of ``split``
    (held-out train scenes, or the val tail after the reported 100: ``align_dev_eval.held_out_scenes``), every seed.

    Returns {"factors": [...], "per_seed": {f: [report per seed]}, "mean": {f: {metric: mean}}, "best_factor": f};
    rates are shares of controlled agents, realism deviations Wasserstein distances (m/s^2, m/s^3). With
    ``min_speed_ratio``, only factors whose mean held-out speed / logged speed reaches it can be chosen
    (``best_factor`` None when none does).
    """
    ids, scenario = held_out_scenes(holdout_every, first, split)
    if max_scenes is not None:
        ids, scenario = ids[:max_scenes], scenario[:max_scenes]
    # every checkpoint first: a bad input fails before any driving
    checkpoints = {f"{f:g}": extrapolate_checkpoint(base, aligned, os.path.join(out_dir, f"x{f:g}"), f)
                   for f in factors}
    per_seed: dict[str, list[dict[str, float]]] = {}
    progress = tqdm(total=len(factors) * len(seeds), desc="factor x seed", unit="run")
    for factor, checkpoint in checkpoints.items():
        per_seed[factor] = []
        for seed in seeds:
            per_seed[factor].append(held_out_report(model, checkpoint, guidance, scenario, seed))
            progress.update()
    progress.close()
    mean = {f: {k: sum(r[k] for r in runs) / len(runs) for k in KEYS} for f, runs in per_seed.items()}
    fast_enough = [f for f in mean if min_speed_ratio is None or mean[f]["speed_ratio"] >= min_speed_ratio]

    def lowest_failure(candidates: list[str]) -> float | None:
        return float(min(candidates, key=lambda f: mean[f]["failure_rate"])) if candidates else None

    result = {"model": model, "base": base, "aligned": aligned, "split": split, "scenes": len(ids), "seeds": seeds,
              "factors": [float(f) for f in factors], "per_seed": per_seed, "mean": mean,
              "min_speed_ratio": min_speed_ratio, "best_factor": lowest_failure(fast_enough)}
    if "0" in mean:  # the base was evaluated: also name the best factor whose realism is not worse than the base's
        keeping = [f for f in fast_enough if all(mean[f][k] <= mean["0"][k] for k in REALISM)]
        result["best_factor_keeping_realism"] = lowest_failure(keeping)
    return result


def plot(result: dict, path: str) -> None:  # type: ignore[type-arg]
    """Failure rate (mean and per seed), both realism deviations and the speed against the log, per factor (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factors = result["factors"]
    keys = [f"{f:g}" for f in factors]
    fig, (left, right, speed) = plt.subplots(1, 3, figsize=(13, 3.5))
    for i in range(len(result["seeds"])):
        left.plot(factors, [result["per_seed"][k][i]["failure_rate"] for k in keys], color="0.7", lw=1)
    left.plot(factors, [result["mean"][k]["failure_rate"] for k in keys], "o-", color="C3", label="mean of seeds")
    left.set(xlabel="factor (0 = base, 1 = aligned)", ylabel="held-out failure rate", title=result["model"])
    left.legend()
    for name, color in (("realism_ctg", "C0"), ("realism_body", "C2")):
        right.plot(factors, [result["mean"][k][name] for k in keys], "o-", color=color, label=name)
    right.set(xlabel="factor", ylabel="realism deviation (lower is better)")
    right.legend()
    speed.plot(factors, [result["mean"][k]["speed_ratio"] for k in keys], "o-", color="C1", label="speed / logged")
    speed.plot(factors, [result["mean"][k]["stopped_share"] for k in keys], "o-", color="C4",
               label="stopped at the end")
    speed.axhline(1.0, color="0.6", lw=0.8, ls="--")
    speed.set(xlabel="factor", ylabel="speed ratio / share of agents")
    speed.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="Registered traffic model, e.g. ctg / trafficgen / bits.")
    parser.add_argument("--base", required=True, help="Checkpoint folder alignment started from.")
    parser.add_argument("--aligned", required=True, help="Aligned checkpoint folder (one run or a seed average).")
    parser.add_argument("--factors", default="0,1,1.5,2,2.5,3",
                        type=lambda t: _numbers(t, float, "--factors"), help="Comma-separated factors >= 0.")
    parser.add_argument("--seeds", default="0,1,2", type=lambda t: _numbers(t, int, "--seeds"),
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
    parser.add_argument("--out", required=True, help="Folder for the checkpoints, sweep.json and sweep.png.")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if any(f < 0 for f in args.factors):
        parser.error(f"--factors has a negative value ({args.factors}); factors are >= 0.")
    try:
        result = sweep(args.model, args.base, args.aligned, args.factors, args.seeds, args.out, args.guidance,
                       None if args.split == "val" else args.holdout_every, max_scenes=args.max_scenes,
                       min_speed_ratio=args.min_speed_ratio, split=args.split)
    except TrafficRLHFError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 2
    with open(os.path.join(args.out, "sweep.json"), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
    plot(result, os.path.join(args.out, "sweep.png"))
    print(f"held out: {result['scenes']} scenes, seeds {args.seeds}")
    print("| factor | failure (per seed) | collision | off-road | realism ctg | realism body | speed / log | stopped |")
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
            factor = result[key]
            print(f"{label}{pace}: " + ("no factor qualifies" if factor is None else f"factor {factor:g} "
                                                                                  f"({args.out}/x{factor:g})"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
