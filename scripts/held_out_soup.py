r"""Average the best K of several alignment runs, chosen by their failure rate on held-out train scenes.

Single PPO runs of one recipe differ widely: eight training seeds of the 4 s CTG recipe on a mirror-trained base
changed its val failure rate by -58 % to +29 %, and the average of all eight weights failed 0.0682 against 0.0784
for the mean single run. Each run's held-out failure rate ranked the runs as val did (Spearman 0.71), and the four
best on held out, averaged, failed 0.0482 on val (docs/explanation/alignment-log.md, session 30). The choice uses
only the scenes ``trafficrlhf align --holdout-every K`` kept out of training, never the reported val scenes.

For each run folder, drives the held-out scenes in closed loop with every seed, ranks the runs by mean held-out
failure rate (ties keep the given order; runs below ``--min-speed-ratio`` last), writes the elementwise mean of
the best ``--keep`` to OUT (``trafficrlhf average``) with ``selection.json`` (every run's per-seed figures and the
choice), and prints a table.

``--greedy`` instead of ``--keep`` builds a greedy soup (Wortsman et al. 2022, "Model soups"): start from the best
run and, in ranking order, add each next run when the average with it fails no more often on the held-out
scenes than the soup so far (and keeps ``--min-speed-ratio``). Each candidate costs one more held-out drive per
seed; every trial is recorded in ``selection.json`` under ``greedy``. On 44 held-out scenes it overfits them
(session 31: 0.0154 on held out, 0.0615 on val, against 0.0471 on val for the plain best four of the same 16 runs).

    python scripts/held_out_soup.py --model ctg --guidance no_collision --keep 4 --holdout-every 10 \
        --runs out/ctg_s0 out/ctg_s1 out/ctg_s2 out/ctg_s3 out/ctg_s4 out/ctg_s5 out/ctg_s6 out/ctg_s7 \
        --out out/ctg_best4
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile

import torch
from align_dev_eval import KEYS, comma_numbers, held_out_reports, held_out_scenes

from trafficrlhf_sdk.alignment import average_checkpoints
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

SELECTION_FILE = "selection.json"


def _mean_report(reports: list[dict[str, float]]) -> dict[str, float]:
    return {k: sum(r[k] for r in reports) / len(reports) for k in KEYS}


def greedy_soup(model: str, ranking: list[str], first_mean: dict[str, float], seeds: list[int], guidance: str | None,
                scenario: ScenarioTensor, min_speed_ratio: float | None = None) -> tuple[list[str], list[dict]]:  # type: ignore[type-arg]
    """Greedy soup over ``ranking`` (best first): the soup starts as ``ranking[0]`` (held-out means
    ``first_mean``); each next run joins when the uniform average with it has a held-out failure rate (mean over
    ``seeds``) no higher than the soup's so far and, with ``min_speed_ratio``, a speed / logged speed at least
    that. Returns (the kept runs, one record per trial: the run tried, the trial's mean figures, accepted)."""
    kept, best = [ranking[0]], first_mean
    trials = []
    with tempfile.TemporaryDirectory() as scratch:
        for index, run in enumerate(ranking[1:], start=1):
            trial_dir = os.path.join(scratch, f"trial{index}")
            average_checkpoints([*kept, run], trial_dir)
            reports = held_out_reports(model, {run: trial_dir}, guidance, scenario, seeds,
                                       f"soup of {len(kept) + 1}")[run]
            mean = _mean_report(reports)
            accepted = mean["failure_rate"] <= best["failure_rate"] and (
                min_speed_ratio is None or mean["speed_ratio"] >= min_speed_ratio)
            trials.append({"run": run, "soup_size": len(kept) + 1, "mean": mean, "per_seed": reports,
                           "accepted": accepted})
            if accepted:
                kept, best = [*kept, run], mean
    return kept, trials


def select_and_average(model: str, runs: list[str], keep: int | None, seeds: list[int], out_dir: str,
                       guidance: str | None, holdout_every: int, max_scenes: int | None = None,
                       min_speed_ratio: float | None = None) -> dict:  # type: ignore[type-arg]
    """Drive every run in ``runs`` on the held-out train scenes (every ``holdout_every``-th) with each seed, then
    average the ``keep`` runs of lowest mean failure rate into ``out_dir`` (``keep`` None: a greedy soup, see
    :func:`greedy_soup`; one kept run is copied). With ``min_speed_ratio``, runs whose mean held-out speed /
    logged speed is below it are ranked last and never kept (failures avoided by stopping do not count); an error
    if fewer than ``keep`` (greedy: one) qualify.

    Returns {"runs": [...], "per_seed": {run: [report per seed]}, "mean": {run: {metric: mean}}, "ranking":
    [runs, best first], "kept": [...], "greedy": [trial records] or None}; rates are shares of controlled agents,
    realism deviations Wasserstein distances (m/s^2, m/s^3).
    """
    if len(set(runs)) != len(runs):
        raise TrafficRLHFError(f"`runs` names a folder twice ({runs}); give each run once.")
    if keep is not None and not 2 <= keep <= len(runs):
        raise TrafficRLHFError(f"`keep` is {keep} with {len(runs)} runs; keep between 2 and {len(runs)} of them.")
    if keep is None and len(runs) < 2:
        raise TrafficRLHFError(f"a greedy soup needs at least two runs; `runs` has {len(runs)}.")
    with tempfile.TemporaryDirectory() as scratch:  # every input checked (files, same architecture) before driving
        average_checkpoints(runs, os.path.join(scratch, "check"))
    ids, scenario = held_out_scenes(holdout_every, None, "train")
    if max_scenes is not None:
        ids, scenario = ids[:max_scenes], scenario[:max_scenes]
    per_seed = held_out_reports(model, {run: run for run in runs}, guidance, scenario, seeds, "run x seed")
    mean = {run: _mean_report(reports) for run, reports in per_seed.items()}
    fast_enough = [run for run in runs if min_speed_ratio is None or mean[run]["speed_ratio"] >= min_speed_ratio]
    if len(fast_enough) < (keep or 1):
        raise TrafficRLHFError(f"only {len(fast_enough)} of {len(runs)} runs reach `min_speed_ratio` "
                               f"{min_speed_ratio} on held out; lower it" + (f" or `keep` ({keep})." if keep else "."))
    # too slow runs go last: ranked by (too slow, failure rate)
    ranking = sorted(runs, key=lambda run: (run not in fast_enough, mean[run]["failure_rate"]))
    trials = None
    if keep is None:
        candidates = [run for run in ranking if run in fast_enough]
        kept, trials = greedy_soup(model, candidates, mean[candidates[0]], seeds, guidance, scenario,
                                   min_speed_ratio)
    else:
        kept = ranking[:keep]
    if len(kept) == 1:
        os.makedirs(out_dir, exist_ok=True)
        for name in ("config.json", "model.safetensors"):
            shutil.copy2(os.path.join(kept[0], name), os.path.join(out_dir, name))
    else:
        average_checkpoints(kept, out_dir)
    return {"model": model, "runs": runs, "keep": keep, "holdout_every": holdout_every, "scenes": len(ids),
            "seeds": seeds, "min_speed_ratio": min_speed_ratio, "per_seed": per_seed, "mean": mean,
            "ranking": ranking, "kept": kept, "greedy": trials}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="Registered traffic model, e.g. ctg / trafficgen / bits.")
    parser.add_argument("--runs", nargs="+", required=True,
                        help="Aligned checkpoint folders of one recipe (same base, different training seeds).")
    size = parser.add_mutually_exclusive_group(required=True)
    size.add_argument("--keep", type=int, help="How many of the best runs to average (>= 2).")
    size.add_argument("--greedy", action="store_true",
                      help="Greedy soup: add runs best first while the held-out failure rate does not rise.")
    parser.add_argument("--seeds", default="0,1,2", type=lambda t: comma_numbers(t, int, "--seeds"),
                        help="Evaluation seeds (comma-separated) [default: 0,1,2].")
    parser.add_argument("--guidance", default=None, help="Guidance while driving, e.g. no_collision.")
    parser.add_argument("--holdout-every", type=int, default=10,
                        help="The scenes `align --holdout-every K` kept out [default: 10].")
    parser.add_argument("--max-scenes", type=int, default=None, help="Only the first N held-out scenes (smoke runs).")
    parser.add_argument("--min-speed-ratio", type=float, default=None,
                        help="Keep only runs whose held-out speed / logged speed is at least this, e.g. 0.9.")
    parser.add_argument("--out", required=True, help="Folder for the averaged checkpoint and selection.json.")
    args = parser.parse_args(argv)
    if args.holdout_every < 2:
        parser.error(f"--holdout-every is {args.holdout_every}; give the K the runs were aligned with (>= 2).")
    torch.set_num_threads(1)
    try:
        result = select_and_average(args.model, args.runs, args.keep, args.seeds, args.out, args.guidance,
                                    args.holdout_every, args.max_scenes, args.min_speed_ratio)
    except TrafficRLHFError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 2
    with open(os.path.join(args.out, SELECTION_FILE), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
    print(f"held out: {result['scenes']} scenes, seeds {args.seeds}")
    print("| rank | run | failure (per seed) | collision | off-road | realism ctg | realism body | speed / log "
          "| kept |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rank, run in enumerate(result["ranking"], start=1):
        mean = result["mean"][run]
        seeds = " / ".join(f"{r['failure_rate']:.4f}" for r in result["per_seed"][run])
        print(f"| {rank} | {run} | {mean['failure_rate']:.4f} ({seeds}) | {mean['collision_rate']:.4f} | "
              f"{mean['offroad_rate']:.4f} | {mean['realism_ctg']:.4f} | {mean['realism_body']:.4f} | "
              f"{mean['speed_ratio']:.3f} | {'yes' if run in result['kept'] else ''} |")
    for trial in result["greedy"] or []:
        print(f"greedy: soup of {trial['soup_size']} with {trial['run']}: held-out failure "
              f"{trial['mean']['failure_rate']:.4f}, speed / log {trial['mean']['speed_ratio']:.3f}"
              f"{' (kept)' if trial['accepted'] else ''}")
    print(f"averaged {len(result['kept'])} runs into {args.out}: {', '.join(result['kept'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
