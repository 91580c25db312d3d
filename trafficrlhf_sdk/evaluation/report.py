"""A one-page report of an RLHF loop: reward-model figures, the alignment's training curve, closed-loop metrics of
each evaluated model, and drawings of the scenes where they fail (``trafficrlhf report``)."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from typing import Any

from trafficrlhf_sdk.errors import DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.evaluation.compare import interval_table, read_results, run_folders

__all__ = ["write_report"]

METRIC_ROWS = (("failure_rate", "failure rate"), ("collision_rate", "collision rate"),
               ("offroad_rate", "off-road rate"), ("realism_ctg", "realism dev. (ctg)"),
               ("realism_body", "realism dev. (body)"), ("speed_ratio", "speed / logged speed"))


def _json(path: str) -> dict[str, Any]:
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{path!r} is missing; pass the folders written by `trafficrlhf rm train`, "
                                "`trafficrlhf align` and `trafficrlhf evaluate --out`.")
    with open(path, encoding="utf-8") as handle:
        return json.load(handle)


def _pooled(results: list[dict[str, Any]]) -> dict[str, Any]:
    """One evaluation's results (one per seed) pooled: the mean of each metric, with ``seeds`` and ``per_seed``."""
    pooled = dict(results[0])
    keys = set().union(*(r["metrics"] for r in results))
    values = {k: [r["metrics"].get(k) for r in results] for k in keys}
    pooled["metrics"] = {k: (sum(v) / len(v) if all(isinstance(x, (int, float)) for x in v) else None)
                         for k, v in values.items()}
    pooled["per_seed"] = values
    pooled["seeds"] = [r.get("metadata", {}).get("seed") for r in results]
    return pooled


def _plot_curve(history: list[dict[str, float]], path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [row["epoch"] for row in history]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    axes[0].plot(epochs, [row["reward_mean"] for row in history], marker="o")
    axes[0].set(xlabel="epoch", ylabel="mean reward (reward model)", title="proxy reward of the policy's samples")
    if any("heldout_realism" in row for row in history):
        axes[1].plot(epochs, [row.get("heldout_realism", float("nan")) for row in history], marker="o",
                     color="tab:orange")
        axes[1].set(xlabel="epoch", ylabel="held-out realism", title="stand-in annotators' judgment (not trained on)")
    else:
        axes[1].plot(epochs, [row.get("approx_kl", float("nan")) for row in history], marker="o", color="tab:red")
        axes[1].set(xlabel="epoch", ylabel="approx. KL to the sampling policy", title="PPO step size")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_metrics(runs: dict[str, dict[str, Any]], path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k, _ in METRIC_ROWS[:3]]
    fig, ax = plt.subplots(figsize=(8, 3.2))
    width = 0.8 / max(1, len(runs))
    for i, (label, result) in enumerate(runs.items()):
        values = [result["metrics"].get(k) or 0.0 for k in keys]
        ax.bar([j + i * width for j in range(len(keys))], values, width, label=label)
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(keys))], [name for _, name in METRIC_ROWS[:3]])
    ax.set(ylabel="share of controlled agents", title="closed loop, 10 s from logged scenes")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(out_dir: str, runs: Sequence[tuple[str, str]], reward_model_dir: str | None = None,
                 align_dir: str | None = None, title: str = "TrafficRLHF loop") -> str:
    """Write ``out_dir/report.md`` with PNGs beside it; returns its path.

    ``runs``: ``(label, folder)`` pairs of ``trafficrlhf evaluate --out`` folders, the base first; a folder of
    several seeds (``--seeds``) is pooled: the mean of each metric, and each run's change against the base with a
    paired bootstrap interval over scenes (:func:`~trafficrlhf_sdk.evaluation.compare.interval_table`);
    ``reward_model_dir``: a reward model saved by ``trafficrlhf rm train``; ``align_dir``: a ``trafficrlhf align``
    output folder (``align_history.json``). Drawings of each run's worst scenes (``--render-worst``) are linked.
    """
    slugs = [label.replace(" ", "_") for label, _ in runs]
    repeated = sorted({label for (label, _), slug in zip(runs, slugs) if slugs.count(slug) > 1})
    if repeated:
        raise TrafficRLHFError(f"runs: the label(s) {', '.join(map(repr, repeated))} name more than one run (labels "
                               "differing only in spaces and underscores count as one); give each run its own label.")
    os.makedirs(out_dir, exist_ok=True)
    folders = {label: run_folders(folder) for label, folder in runs}
    seed_runs = {label: [read_results(f) for f in folders[label]] for label, _ in runs}
    results = {label: _pooled(seed_runs[label]) for label, _ in runs}
    lines = [f"# {title}", ""]
    if reward_model_dir is not None:
        card = _json(os.path.join(reward_model_dir, "config.json"))
        metrics = card.get("metrics", {})
        data = card.get("data", {})
        lines += ["## Reward model", "",
                  f"`{reward_model_dir}`: architecture `{card.get('architecture')}`, "
                  f"{card.get('num_parameters', 'n/a')} parameters, trained on {data.get('train_pairs', 'n/a')} "
                  f"pairs from {data.get('train_contexts', 'n/a')} contexts.", "",
                  "| split | accuracy | loss |", "|---|---|---|"]
        for split in ("train", "val"):
            acc, loss = metrics.get(f"{split}_accuracy"), metrics.get(f"{split}_loss")
            if acc is not None:
                lines.append(f"| {split} | {acc:.3f} | {loss:.3f} |")
        lines.append("")
        probes = {k[len("probe_"):]: v for k, v in metrics.items() if k.startswith("probe_")}
        if probes:
            lines += ["Probes on held-out logs (share where the log scores above its perturbed copy):", "",
                      "| " + " | ".join(probes) + " |", "|---" * len(probes) + "|",
                      "| " + " | ".join(f"{v:.2f}" if v == v else "n/a" for v in probes.values()) + " |", ""]
    if align_dir is not None:
        history = _json(os.path.join(align_dir, "align_history.json"))
        summary_path = os.path.join(align_dir, "align_summary.json")
        summary = _json(summary_path) if os.path.isfile(summary_path) else {}
        curve = _plot_curve(history["history"], os.path.join(out_dir, "training_curve.png"))
        config = history["config"]
        lines += ["## Alignment", "",
                  f"`{align_dir}`: {len(history['history'])} epochs, alpha {config['alpha']}, guidance "
                  f"`{config['guidance']}`, groups {history.get('groups')}, reward `{history.get('reward_model')}`"
                  + (f", {summary['wall_time_s']:.0f} s on {summary['threads']} threads" if summary else "") + ".",
                  "", f"![training curve]({os.path.basename(curve)})", ""]
    names = list(results)
    first = next(iter(results.values()))
    seed_sets = {label: ", ".join(map(str, r["seeds"])) for label, r in results.items() if r["seeds"] != [None]}
    shared = next(iter(seed_sets.values())) if len(set(seed_sets.values())) == 1 else None
    over = ("" if not seed_sets else
            f"; seed {shared}" if shared is not None and "," not in shared else
            f"; each value the mean over seeds {shared}" if shared is not None else
            "; seeds " + "; ".join(f"{label}: {seeds}" for label, seeds in seed_sets.items()))
    lines += ["## Closed-loop evaluation", "",
              f"{first['num_scenes']} scenes, 10 s from the log, replanning at 2 Hz{over}.", "",
              "| metric | " + " | ".join(names) + " | logged |", "|---" * (len(names) + 2) + "|"]
    for key, name in METRIC_ROWS:
        cells = [results[n]["metrics"].get(key) for n in names]
        logged = first.get("logged", {}).get(key)
        fmt = [f"{v:.4f}" if isinstance(v, (int, float)) else "n/a" for v in [*cells, logged]]
        lines.append(f"| {name} | " + " | ".join(fmt) + " |")
    chart = _plot_metrics(results, os.path.join(out_dir, "metrics.png"))
    lines += ["", f"![metrics]({os.path.basename(chart)})", ""]
    base_label = names[0]
    for label in names[1:]:
        try:
            table = interval_table(base_label, seed_runs[base_label], label, seed_runs[label])
        except TrafficRLHFError as error:  # e.g. results without per-scene values, or of other scenes
            table = f"No interval: {error}"
        lines += [f"### {label} against {base_label}", "", table, ""]
    drawings = []
    for label, folder in runs:
        worst = next((os.path.join(f, "worst_scenes") for f in [folder, *folders[label]]
                      if os.path.isdir(os.path.join(f, "worst_scenes"))), "")
        pngs = sorted(f for f in os.listdir(worst) if f.endswith(".png")) if os.path.isdir(worst) else []
        if pngs:
            target = os.path.join(out_dir, f"worst_{label.replace(' ', '_')}.png")
            shutil.copyfile(os.path.join(worst, pngs[0]), target)
            drawings.append(f"**{label}**, scene {pngs[0][3:-4]}: ![{label}]({os.path.basename(target)})")
    if drawings:
        lines += ["## Where they fail", "", "The scene carrying most of each model's failures:", "", *drawings, ""]
    path = os.path.join(out_dir, "report.md")
    with open(path, "w", encoding="utf-8") as handle:
        handle.write("\n".join(lines) + "\n")
    return path
