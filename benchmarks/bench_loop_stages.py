"""What each stage of the RLHF loop costs, and how it grows with the number of labelled contexts.

Runs the loop's own pipeline steps (:mod:`trafficrlhf_sdk.pipeline`), as ``trafficrlhf rlhf`` chains them, on the
4 s CTG (``ctg-4s``, no-collision guidance) and the real nuScenes train scenes, once per context count of
``--contexts`` (each in a fresh folder):

* generate: the campaign's contexts x 5 candidates of 4 s (closed loop at 2 Hz);
* label: one stand-in annotator (``attentive``) labels every context;
* featurize + train: the reward model of ``docs/recipes/ctg-ladder``'s reward settings, ``--rm-epochs`` epochs
  (featurization is timed separately by the reward trainer's own progress log);
* align epoch: ``--align-epochs`` epochs of the ladder's fine-tuning recipe against that reward model;
* evaluate: ``--scenes`` val scenes x 1 rollout, 10 s closed loop.

Each stage prints its seconds, its rate per context / per epoch / per scene, and the 1-minute load average just
before and just after it. A figure is only worth quoting when the machine was otherwise idle: the first stage
must start below ``--max-load``, and no load average may exceed one per CPU plus that (the script's own
processes stay below it); a stage that breaks either is marked UNDER LOAD and is to be discarded.
Data: nuScenes (CC BY-NC-SA 4.0).

Run alone, one thread:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_loop_stages.py --threads 1
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from _common import MAX_IDLE_LOAD, ROOT, busy_beyond_own, header, peak_rss_mb

RECIPE = os.path.join(ROOT, "docs", "recipes", "ctg-ladder.toml")
_STAGES_RUN: list[str] = []  # stages this script has run so far


def _stage(rows: list[dict], name: str, count: int, unit: str, max_load: float, fn) -> object:  # type: ignore[no-untyped-def]
    before = os.getloadavg()[0]
    tic = time.perf_counter()
    result = fn()
    seconds = time.perf_counter() - tic
    after = os.getloadavg()[0]
    # the first stage of the script must start on an idle machine; later ones see the script's own load
    alone = (before <= max_load if not _STAGES_RUN else not busy_beyond_own(before)) and not busy_beyond_own(after)
    _STAGES_RUN.append(name)
    rows.append({"stage": name, "seconds": seconds, "count": count, "unit": unit, "load_before": before,
                 "load_after": after, "alone": alone})
    flag = "" if alone else "  UNDER LOAD: discard"
    print(f"   {name:<14} {seconds:8.1f} s  {seconds / max(count, 1):7.2f} s per {unit:<8} load {before:.2f} -> "
          f"{after:.2f}{flag}", flush=True)
    return result


def run(contexts: int, args: argparse.Namespace) -> list[dict]:
    """One pass of the loop's stages over ``contexts`` train contexts; returns the stage rows."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.evaluation.runs import EvaluationRequest
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig
    from trafficrlhf_sdk.feedback.synthetic import PROFILES
    from trafficrlhf_sdk.pipeline.stages import align_step, evaluate_step, generate_step, label_step, \
        reward_model_step
    from trafficrlhf_sdk.reward.config import RewardConfig

    rows: list[dict] = []
    out = tempfile.mkdtemp(prefix=f"loop-stages-{contexts}-")
    db = os.path.join(out, "feedback.sqlite")
    campaign = CampaignConfig(name="bench", model="ctg", guidance="no_collision", split="train",
                              num_contexts=contexts, candidate_seconds=4.0, model_options={"checkpoint": "ctg-4s"})
    print(f"-- {contexts} contexts ({out})", flush=True)
    _stage(rows, "generate", contexts, "context", args.max_load,
           lambda: generate_step(os.path.join(out, "generate"), db, campaign))
    _stage(rows, "label", contexts, "context", args.max_load,
           lambda: label_step(os.path.join(out, "label"), db, "bench", {"attentive": PROFILES["attentive"]}))
    reward = RewardConfig(learning_rate=1e-3, weight_decay=0.0, max_epochs=args.rm_epochs,
                          early_stopping_patience=None, seed=0)
    rm_folder = os.path.join(out, "reward_model")
    _stage(rows, "reward model", args.rm_epochs, "epoch", args.max_load,
           lambda: reward_model_step(rm_folder, reward, db, ["bench"]))
    recipe = AlignRecipe.load(RECIPE, reward_model=rm_folder)
    recipe = recipe.model_copy(update={"align": recipe.align.model_copy(update={"epochs": args.align_epochs,
                                                                                 "progress_bar": False})})
    _stage(rows, "align", args.align_epochs, "epoch", args.max_load,
           lambda: align_step(os.path.join(out, "align"), recipe))
    request = EvaluationRequest(model="ctg", checkpoint="ctg-4s", guidance="no_collision", num_scenes=args.scenes)
    _stage(rows, "evaluate", args.scenes, "scene", args.max_load,
           lambda: evaluate_step(os.path.join(out, "evaluate"), request, progress=False))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--contexts", type=int, nargs="+", default=[20, 60], help="Context counts to run.")
    parser.add_argument("--rm-epochs", type=int, default=5, help="Reward-model epochs per run.")
    parser.add_argument("--align-epochs", type=int, default=2, help="Fine-tuning epochs per run.")
    parser.add_argument("--scenes", type=int, default=20, help="Val scenes evaluated per run.")
    parser.add_argument("--max-load", type=float, default=MAX_IDLE_LOAD, help="Largest 1-minute load average before a "
                        "stage for its figure to count as measured alone.")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (header applies it).")
    args = parser.parse_args()
    header("RLHF loop stages (ctg-4s, nuScenes train contexts)")
    table = []
    for contexts in args.contexts:
        table += [{"contexts": contexts, **row} for row in run(contexts, args)]
    print("\n| contexts | stage | seconds | per unit | load before -> after | alone |")
    print("|---|---|---|---|---|---|")
    for row in table:
        rate = row["seconds"] / max(row["count"], 1)
        print(f"| {row['contexts']} | {row['stage']} | {row['seconds']:.1f} | {rate:.2f} s / {row['unit']} | "
              f"{row['load_before']:.2f} -> {row['load_after']:.2f} | "
              f"{'yes' if row['alone'] else 'NO: discard'} |")
    print(f"peak RSS {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
