"""Reward-model training time: 400 contexts x 4 pairs (about 1,600 pairs), default ``RewardConfig``, 2 cores.

Data: the campaign database behind the bundled reward model ``reference_models/reward/ctg_no_collision``
(``--db``): campaign ``ctg-nc-train``, CTG + no-collision candidates (``trafficrlhf feedback create --model ctg
--guidance no_collision --candidates 5 --seconds 5``) on every long-enough nuScenes train scene (CC BY-NC-SA 4.0),
labeled by the noisy synthetic annotator ``synth-noisy`` (``trafficrlhf feedback label --synthetic --beta 20
--epsilon 0.1``); the first 400 contexts of the export's "train" side. Without that database the model-free tiny
campaign of ``trafficrlhf_sdk.testing.feedback`` stands in (400 contexts of three cars; shorter, 3 s candidates).

Times the featurization (every future once) and the training itself: the paper's 512-512-512-128-32 MLP, up
to ``max_epochs`` with early stopping on the held-out contexts. Target: <= 60 s for training.

``--device cuda`` runs the optimiser steps on a GPU (featurization stays on the CPU); the time then includes
moving each batch to the device.

Run: .venv/bin/python benchmarks/bench_reward_training.py  [--threads N] [--db FILE] [--device cuda]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import torch

from _common import header, peak_rss_mb

from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig, export_preferences
from trafficrlhf_sdk.reward import RewardConfig, RewardTrainer, build_pair_data, filter_pairs
from trafficrlhf_sdk.reward.model import get_reward_model_architecture


def load_dataset(db: str, campaign: str, annotator: str):  # type: ignore[no-untyped-def]
    """400 training contexts (+ the held-out ones) from ``db``, or a tiny synthetic campaign when it is absent."""
    if os.path.isfile(db):
        data = filter_pairs(export_preferences(FeedbackStore(db), campaign, val_fraction=0.1472), [annotator])
        return data, f"{campaign} in {db} ({annotator})"
    from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

    store = FeedbackStore(os.path.join(tempfile.mkdtemp(), "tiny.db"))
    make_tiny_campaign(store, num_contexts=470)
    SyntheticAnnotator(store, "noisy", SyntheticAnnotatorConfig(epsilon=0.1)).label("tiny")
    return export_preferences(store, "tiny", val_fraction=0.1472), "tiny synthetic campaign (no database found)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", default="out/reward/ctg_no_collision.db")
    parser.add_argument("--campaign", default="ctg-nc-train")
    parser.add_argument("--annotator", default="synth-noisy")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu", help="Where the optimiser steps run (cpu, cuda, ...).")
    args = parser.parse_args()
    header("reward-model training: 400 contexts, default RewardConfig")
    tic = time.perf_counter()
    dataset, label = load_dataset(args.db, args.campaign, args.annotator)
    print(f"   data: {label}; loaded in {time.perf_counter() - tic:.1f} s")
    config = RewardConfig(progress=False, num_threads=args.threads, device=args.device)
    template = get_reward_model_architecture(config.architecture)(config.architecture_config)
    tic = time.perf_counter()
    data = build_pair_data(template.prepare, dataset)
    featurize_s = time.perf_counter() - tic
    train_ids = [i for i, s in enumerate(data.split) if s == "train"][:400]
    val_ids = [i for i, s in enumerate(data.split) if s == "val"]
    data = data.subset(train_ids + val_ids)
    train = data.split_subset("train")
    print(f"   {len(train)} training pairs over {len(train_ids)} contexts ({len(train.inputs)} agent-steps), "
          f"{len(data) - len(train)} held-out pairs over {len(val_ids)} contexts; {template.num_parameters:,} "
          f"parameters; featurized {len(dataset.pairs[:, 0].unique())} contexts in {featurize_s:.1f} s")
    times = []
    for _ in range(args.repeats):
        tic = time.perf_counter()
        result = RewardTrainer(config, train_dataset=data).train()
        times.append(time.perf_counter() - tic)
        epochs = len(result.history)
        print(f"   trained {epochs} epochs (best {result.best_epochs[0]}) in {times[-1]:.1f} s "
              f"({times[-1] / epochs:.1f} s/epoch): held-out accuracy {result.metrics['val_accuracy']:.3f}, "
              f"loss {result.metrics['val_loss']:.3f}")
    best = min(times)
    where = torch.cuda.get_device_name(torch.device(args.device)) if args.device.startswith("cuda") else "CPU"
    print(f"   training on {args.device} ({where})")
    print(f"   training time {best:.1f} s (min of {len(times)}), + featurization {featurize_s:.1f} s; target <= 60 s: "
          f"{'met' if best <= 60 else 'NOT met'}; {torch.get_num_threads()} torch threads, peak RSS "
          f"{peak_rss_mb():.0f} MB, load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
