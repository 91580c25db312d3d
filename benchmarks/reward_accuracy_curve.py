"""Reward-model accuracy vs number of labeled training contexts (the paper's Figure 3), with spread over seeds.

Data: the campaign database behind the bundled reward model ``reference_models/reward/ctg_no_collision``
(``--db``): CTG + no-collision candidates (``trafficrlhf feedback create --model ctg --guidance no_collision
--candidates 5 --seconds 5``) on every long-enough nuScenes train scene (campaign ``ctg-nc-train``) and on the
first 100 val scenes (``ctg-nc-val``); nuScenes, CC BY-NC-SA 4.0. Training contexts come from the train-split
campaign labeled by the noisy synthetic annotator (B-Pref style); the contexts of that campaign that the export
marks "val" are the early-stopping set. Accuracy is measured on the held-out val-split campaign labeled by the
noise-free annotator (beta -> inf, epsilon = 0): the share of its pairs with r(S_w) > r(S_l), over the pairs whose
winner is strictly more realistic under the annotator's hidden judgment (ties carry no preference), and also over
all its pairs.

Every future is featurized once; each (size, seed) run trains a fresh single model (default ``RewardConfig``;
smaller batches and more epochs for small sizes) on the first ``size`` contexts of a seeded permutation of the
400 training contexts.

Run (about 15-25 min on 2 shared cores):
    .venv/bin/python benchmarks/reward_accuracy_curve.py --out docs/images/reward_accuracy_vs_contexts.png
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import torch

from _common import header

from trafficrlhf_sdk.feedback import FeedbackStore, export_preferences
from trafficrlhf_sdk.reward import RewardConfig, RewardTrainer, build_pair_data, evaluate_pairs, filter_pairs
from trafficrlhf_sdk.reward.model import get_reward_model_architecture
from trafficrlhf_sdk.reward.oracle import hidden_realism, strict_pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", default="out/reward/ctg_no_collision.db")
    parser.add_argument("--train-campaign", default="ctg-nc-train")
    parser.add_argument("--annotator", default="synth-noisy")
    parser.add_argument("--test-campaign", default="ctg-nc-val")
    parser.add_argument("--test-annotator", default="oracle")
    parser.add_argument("--val-fraction", type=float, default=0.1472, help="dev share of the train campaign")
    parser.add_argument("--sizes", type=int, nargs="+", default=[25, 50, 100, 200, 400])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=300, help="optimizer steps a run may take (small sizes)")
    parser.add_argument("--out", default="docs/images/reward_accuracy_vs_contexts.png")
    parser.add_argument("--json", default="out/reward/accuracy_curve.json")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--replot", action="store_true", help="only redraw --out from the numbers in --json")
    args = parser.parse_args()
    if args.replot:
        with open(args.json, encoding="utf-8") as handle:
            saved = json.load(handle)
        plot(saved["summary"], saved["runs"], args.out, saved["test_strict_pairs"], len(saved["args"]["seeds"]))
        return
    header("reward-model accuracy vs training contexts")
    store = FeedbackStore(args.db)
    base = RewardConfig(progress=False)
    template = get_reward_model_architecture(base.architecture)(base.architecture_config)

    tic = time.perf_counter()
    train_all = filter_pairs(export_preferences(store, args.train_campaign, val_fraction=args.val_fraction),
                             [args.annotator])
    data = build_pair_data(template.prepare, train_all)
    test = filter_pairs(export_preferences(store, args.test_campaign, val_fraction=0.0), [args.test_annotator])
    strict = strict_pairs(test, hidden_realism(store, test))
    test_strict = build_pair_data(template.prepare, filter_pairs(test, mask=strict))
    test_all = build_pair_data(template.prepare, test)
    train_ids = [i for i, s in enumerate(data.split) if s == "train"]
    dev_ids = [i for i, s in enumerate(data.split) if s == "val"]
    print(f"   featurized in {time.perf_counter() - tic:.1f} s: {len(train_ids)} training contexts, {len(dev_ids)} "
          f"dev contexts ({args.annotator}); test: {len(test_all)} pairs of {args.test_annotator}, "
          f"{len(test_strict)} strict")
    if max(args.sizes) > len(train_ids):
        raise SystemExit(f"--sizes asks for {max(args.sizes)} contexts; only {len(train_ids)} are there")

    rows = []
    for seed in args.seeds:
        order = torch.randperm(len(train_ids), generator=torch.Generator().manual_seed(seed)).tolist()
        for size in args.sizes:
            chosen = [train_ids[i] for i in order[:size]]
            subset = data.subset(chosen + dev_ids)
            # small training sets: smaller batches and more epochs, so every run gets a few hundred steps
            batch = 4 if size <= 50 else 8 if size <= 100 else base.batch_size
            epochs = max(10, min(40, math.ceil(args.steps * batch / size)))
            config = base.model_copy(update={"seed": seed, "max_epochs": epochs, "batch_size": batch,
                                             "num_threads": args.threads})
            began = time.perf_counter()
            result = RewardTrainer(config, train_dataset=subset).train()
            row = {"seed": seed, "contexts": size, "pairs": len(subset.split_subset("train")),
                   "accuracy": evaluate_pairs(result.model, test_strict)["accuracy"],
                   "accuracy_all_pairs": evaluate_pairs(result.model, test_all)["accuracy"],
                   "dev_accuracy": result.metrics.get("val_accuracy"), "best_epoch": result.best_epochs[0],
                   "epochs_run": len(result.history), "seconds": time.perf_counter() - began}
            rows.append(row)
            print(f"   seed {seed} contexts {size:>3}: strict accuracy {row['accuracy']:.3f}, all pairs "
                  f"{row['accuracy_all_pairs']:.3f} (dev {row['dev_accuracy']:.3f}, epoch {row['best_epoch']}/"
                  f"{row['epochs_run']}, {row['seconds']:.0f} s)", flush=True)

    summary = []
    for size in args.sizes:
        acc = torch.tensor([r["accuracy"] for r in rows if r["contexts"] == size], dtype=torch.float64)
        acc_all = torch.tensor([r["accuracy_all_pairs"] for r in rows if r["contexts"] == size], dtype=torch.float64)
        std = float(acc.std()) if len(acc) > 1 else 0.0
        summary.append({"contexts": size, "mean": float(acc.mean()), "std": std, "min": float(acc.min()),
                        "max": float(acc.max()), "mean_all_pairs": float(acc_all.mean())})
    print("\n   | training contexts | strict accuracy, mean ± std (min-max) | all pairs, mean |")
    print("   |---|---|---|")
    for s in summary:
        print(f"   | {s['contexts']} | {s['mean']:.3f} ± {s['std']:.3f} ({s['min']:.3f}-{s['max']:.3f}) | "
              f"{s['mean_all_pairs']:.3f} |")
    os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
    with open(args.json, "w", encoding="utf-8") as handle:
        json.dump({"runs": rows, "summary": summary, "test_pairs": len(test_all), "test_strict_pairs":
                   len(test_strict), "args": vars(args)}, handle, indent=2)
    plot(summary, rows, args.out, len(test_strict), len(args.seeds))
    print(f"   wrote {args.out} and {args.json}")


def plot(summary: list[dict[str, float]], rows: list[dict[str, float]], path: str, n_test: int, n_seeds: int) -> None:
    """Mean ± std over seeds (band: min-max), one dot per run; x on a log scale."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [s["contexts"] for s in summary]
    mean = [s["mean"] for s in summary]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.fill_between(x, [s["min"] for s in summary], [s["max"] for s in summary], alpha=0.15, color="tab:blue",
                    label="min-max over seeds")
    ax.errorbar(x, mean, yerr=[s["std"] for s in summary], marker="o", capsize=4, color="tab:blue",
                label=f"mean ± std ({n_seeds} seeds)")
    ax.scatter([r["contexts"] for r in rows], [r["accuracy"] for r in rows], s=10, color="tab:blue", alpha=0.5)
    ax.plot(x, [s["mean_all_pairs"] for s in summary], linestyle="--", color="tab:gray",
            label="all pairs incl. ties (mean)")
    ax.set_xscale("log")
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xticks(x)
    ax.set_xticklabels([str(v) for v in x])
    ax.set_xlabel("labeled training contexts (4 pairs each)")
    ax.set_ylabel("held-out accuracy")
    ax.set_title(f"Reward model vs noise-free annotator ({n_test} strict pairs)")
    ax.axhline(0.5, color="black", linewidth=0.5, linestyle=":")
    ax.set_ylim(0.4, 1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
