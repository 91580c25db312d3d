"""The paper's experiments, regenerated with this SDK: Tables 1-4 and Figure 3 of arXiv 2309.00709.

``trafficrlhf experiment paper --out DIR [--quick] [--only table1,...]`` (or :func:`run_paper`) runs, on the first
``scenes`` long-enough nuScenes val scenes, with stand-in annotators in place of people and learned reward models
only:

- **table1**: CTG (``ctg-4s``) and CTG + RM (the bundled ``ctg-aligned``) under each of the five guidances;
- **table2**: CTG, BITS and TrafficGen without and with RM, one reward model (the bundled ``ctg_loop``, trained on
  CTG candidates) scoring all and aligning BITS and TrafficGen here;
- **table3**: CTG's encoder only, decoder only and the full model fine-tuned against that reward model;
- **table4**: reward models with the CTG encoder (``ctg_mlp``) and with a TrafficGen-style encoder
  (``trafficgen_mcg``), trained on one feedback set over CTG, BITS and TrafficGen candidates, each aligning BITS
  and TrafficGen;
- **figure3**: reward-model accuracy against the number of labelled contexts, over seeds.

Each writes ``DIR/<name>/result.json``, ``result.md`` and ``result.png``; ``DIR/summary.md`` gathers the tables.
The alignment recipes are the shipped ``docs/recipes/*.toml``. Every evaluation, alignment, campaign, labelling,
reward model and Figure 3 training run is a step of :mod:`trafficrlhf_sdk.pipeline` with its ``step.json`` under
``DIR``, so a rerun only redraws the tables from the recorded outputs, and an interrupted run resumes.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Callable
from typing import Any

from trafficrlhf_sdk.config_files import set_fields
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.experiments.config import TABLES, PaperConfig
from trafficrlhf_sdk.experiments.report import COLUMNS, direction_rows, fmt, markdown_table, plot_bars, write_result
from trafficrlhf_sdk.experiments.steps import (
    ExperimentRun,
    align_all,
    align_recipe,
    evaluate,
    labelled_campaign,
    read_recipe,
    resolve_path,
    train_reward_model,
)
from trafficrlhf_sdk.pipeline.step import run_step

__all__ = ["run_paper"]

METRICS = ("realism_ctg", "realism_body", "realism_meta", "failure_rate", "reward_cost")
GUIDANCE_OBJECTIVE = {"speed_limit": "guidance_speed_limit", "target_speed": "guidance_target_speed",
                      "no_collision": "collision_rate", "no_offroad": "offroad_rate",
                      "goal_waypoint": "guidance_goal_waypoint"}

def _command(config: PaperConfig, name: str) -> str:
    return f"trafficrlhf experiment paper --out DIR{' --quick' if config.label == 'quick' else ''} --only {name}"


def _aggregation(config: PaperConfig, ensemble: bool) -> str:
    return config.reward_aggregation if ensemble else "mean"


def _flat(evaluation: dict[str, Any], reward: str = "rm") -> dict[str, Any]:
    """One evaluation's metrics with the reward cost under reward model ``reward``."""
    return {**evaluation["metrics"], "reward_cost": evaluation["reward_cost"].get(reward)}


def _recipe(config: PaperConfig, path: str, **extra: Any) -> dict[str, Any]:
    """The [align] fields of recipe file ``path`` (the experiment's guidance and seed in place of the recipe's),
    then ``extra``, then the experiment's ``align_overrides``."""
    fields = {k: v for k, v in set_fields(read_recipe(path).align).items() if k not in ("guidance", "seed")}
    return {**fields, **extra, **set_fields(config.align_overrides)}


# --------------------------------------------------------------------------------------------------------- tables
def table1(run: ExperimentRun) -> dict[str, Any]:
    """CTG and CTG + RM under each guidance: realism deviation, failure rate (and reward cost, the guidance's own
    objective)."""
    cfg = run.config
    rm = {"rm": resolve_path(cfg.reward_model)}
    rows, pairs = [], []
    for guidance in cfg.guidances:
        base = _flat(evaluate(run, cfg.ctg_base, "ctg", cfg.ctg_base, guidance, rm))
        aligned = _flat(evaluate(run, cfg.ctg_aligned, "ctg", cfg.ctg_aligned, guidance, rm))
        objective = GUIDANCE_OBJECTIVE.get(guidance)
        for name, values in (("CTG", base), ("CTG + RM", aligned)):
            rows.append({"guidance": guidance, "model": name, **{m: values.get(m) for m in METRICS},
                         "objective": objective, "objective_value": values.get(objective)})
        pairs.append((f"{guidance}: CTG → CTG + RM", base, aligned))
    headers = ["guidance", "model", *(COLUMNS[m] for m in METRICS), "guidance objective"]
    body = [[r["guidance"], r["model"], *(r[m] for m in METRICS),
             f"{r['objective']} {fmt(r['objective_value'])}"] for r in rows]
    return {"title": "Table 1: CTG and CTG + RM under each guidance", "rows": rows,
            "markdown": markdown_table(headers, body), "comparisons": direction_rows(pairs, METRICS),
            "plot": ([f"{r['guidance']}\n{r['model']}" for r in rows],
                     {m: [r[m] for r in rows] for m in ("realism_ctg", "failure_rate")}),
            "notes": [f"CTG = `{cfg.ctg_base}`, CTG + RM = `{cfg.ctg_aligned}` (aligned by the RLHF loop against a "
                      "learned reward model); reward cost under "
                      f"`{cfg.reward_model}`; the guidance objective is the metric of the guidance in use "
                      "(speed-limit violation m/s, target-speed error m/s, collision rate, off-road rate, goal "
                      "distance m)."]}


def _is_ensemble(path: str) -> bool:
    with open(os.path.join(path, "config.json"), encoding="utf-8") as handle:
        return json.load(handle).get("architecture") == "ensemble"


def table2(run: ExperimentRun) -> dict[str, Any]:
    """CTG, BITS and TrafficGen without and with RM, one reward model trained on CTG candidates."""
    cfg = run.config
    reward = resolve_path(cfg.reward_model)
    rm = {"rm": reward}
    ensemble = _is_ensemble(reward)
    aggregation = _aggregation(cfg, ensemble)
    bits_rm, tg_rm = (step["folder"] for step in align_all(run, [
        ("table2_bits_rm", align_recipe(run, "bits", cfg.bits, reward, _recipe(cfg, cfg.align_bits), aggregation)),
        ("table2_trafficgen_rm", align_recipe(run, "trafficgen", cfg.trafficgen, reward,
                                              _recipe(cfg, cfg.align_trafficgen), aggregation))]))
    entries = [("CTG", "ctg", cfg.ctg_base, cfg.ctg_base), ("CTG + RM", "ctg", cfg.ctg_aligned, cfg.ctg_aligned),
               ("BITS", "bits", cfg.bits, cfg.bits), ("BITS + RM", "bits", bits_rm, "table2_bits_rm"),
               ("TrafficGen", "trafficgen", cfg.trafficgen, cfg.trafficgen),
               ("TrafficGen + RM", "trafficgen", tg_rm, "table2_trafficgen_rm")]
    values = {name: _flat(evaluate(run, label, model, checkpoint, cfg.guidance, rm))
              for name, model, checkpoint, label in entries}
    rows = [{"model": name, **{m: values[name].get(m) for m in METRICS}} for name, *_ in entries]
    pairs = [(f"{m}: without → with RM", values[m], values[f"{m} + RM"]) for m in ("CTG", "BITS", "TrafficGen")]
    return {"title": "Table 2: CTG, BITS and TrafficGen without and with RM (one reward model, trained on CTG "
                     "candidates)", "rows": rows,
            "markdown": markdown_table(["model", *(COLUMNS[m] for m in METRICS)],
                                       [[r["model"], *(r[m] for m in METRICS)] for r in rows]),
            "comparisons": direction_rows(pairs, METRICS),
            "plot": ([r["model"] for r in rows], {m: [r[m] for r in rows] for m in ("realism_ctg", "failure_rate",
                                                                                    "reward_cost")}),
            "notes": [f"RM = `{cfg.reward_model}`; CTG + RM = `{cfg.ctg_aligned}`; BITS + RM and TrafficGen + RM "
                      f"aligned here from `{cfg.bits}` and `{cfg.trafficgen}` with the recipes `{cfg.align_bits}` and "
                      f"`{cfg.align_trafficgen}`; guidance `{cfg.guidance}`."]}


def table3(run: ExperimentRun) -> dict[str, Any]:
    """Fine-tuning CTG's encoder only, decoder only and the full model against the same reward model."""
    cfg = run.config
    reward = resolve_path(cfg.reward_model)
    rm = {"rm": reward}
    ensemble = _is_ensemble(reward)
    base = _flat(evaluate(run, cfg.ctg_base, "ctg", cfg.ctg_base, cfg.guidance, rm))
    rows = [{"variant": "CTG (not fine-tuned)", "groups": "", "epochs": None, "align_s": None,
             **{m: base.get(m) for m in METRICS}}]
    pairs = []
    names = {variant: f"table3_ctg_{variant}" for variant in cfg.table3_groups}
    aligned = align_all(run, [(names[variant], align_recipe(run, "ctg", cfg.ctg_base, reward,
                                                            _recipe(cfg, cfg.align_ctg, groups=groups),
                                                            _aggregation(cfg, ensemble)))
                              for variant, groups in cfg.table3_groups.items()])
    for (variant, name), summary in zip(names.items(), aligned, strict=True):
        values = _flat(evaluate(run, name, "ctg", summary["folder"], cfg.guidance, rm))
        rows.append({"variant": f"CTG + RM, {variant}", "groups": ",".join(summary.get("groups") or []),
                     "epochs": summary.get("epochs"), "align_s": summary.get("wall_time_s"),
                     **{m: values.get(m) for m in METRICS}})
        pairs.append((f"CTG → CTG + RM ({variant})", base, values))
    headers = ["variant", "groups trained", "epochs", "alignment s", *(COLUMNS[m] for m in METRICS)]
    body = [[r["variant"], r["groups"], "" if r["epochs"] is None else str(r["epochs"]),
             "" if r["align_s"] is None else f"{r['align_s']:.0f}", *(r[m] for m in METRICS)] for r in rows]
    return {"title": "Table 3: fine-tuning CTG's encoder only, decoder only and the full model", "rows": rows,
            "markdown": markdown_table(headers, body), "comparisons": direction_rows(pairs, METRICS),
            "plot": ([r["variant"] for r in rows], {m: [r[m] for r in rows] for m in ("realism_ctg", "failure_rate",
                                                                                      "reward_cost")}),
            "notes": [f"Recipe: `{cfg.align_ctg}` (CTG's own networks, learning rate "
                      f"{read_recipe(cfg.align_ctg).align.learning_rate}); RM = `{cfg.reward_model}`; guidance "
                      f"`{cfg.guidance}`."]}


def table4(run: ExperimentRun) -> dict[str, Any]:
    """Reward models with the CTG and the TrafficGen encoder on one feedback set over CTG, BITS and TrafficGen
    candidates, each aligning BITS and TrafficGen."""
    from trafficrlhf_sdk.feedback.synthetic import PROFILES

    cfg = run.config
    folder = run.folder("table4")
    unknown = [p for p in cfg.annotators if p not in PROFILES]
    if unknown:
        raise TrafficRLHFError(f"annotator profiles {unknown} are unknown; use some of {sorted(PROFILES)}.")
    annotators = {p: PROFILES[p].model_copy(update={"seed": cfg.seed}) for p in cfg.annotators}
    labels = labelled_campaign(run, folder, "mixed", cfg.feedback_models[0], cfg.feedback_contexts, "train",
                               annotators, cfg.guidance, candidate_models=list(cfg.feedback_models),
                               candidates=len(cfg.feedback_models), seconds=cfg.feedback_seconds)
    ensemble = cfg.reward.ensemble_size > 1
    reward_models, accuracy, feedback = {}, {}, {}
    for index, (backbone, spec) in enumerate(cfg.backbones.items()):
        card = train_reward_model(run, os.path.join(folder, f"reward_model_{index}"), labels,
                                  {**set_fields(cfg.reward), **set_fields(spec)},
                                  title=f"Table 4 reward model: {backbone}")
        reward_models[backbone] = card["folder"]
        accuracy[backbone] = card["metrics"].get("val_accuracy")
        feedback = card["preferences"]
    costs = {f"rm{i}": path for i, path in enumerate(reward_models.values())}
    bases = {"BITS": ("bits", cfg.bits, cfg.align_bits), "TrafficGen": ("trafficgen", cfg.trafficgen,
                                                                        cfg.align_trafficgen)}
    rows, pairs = [], []
    aggregation = _aggregation(cfg, ensemble)
    jobs = {(model, index): (f"table4_{model}_rm{index}",
                             align_recipe(run, model, checkpoint, path, _recipe(cfg, recipe), aggregation))
            for model, checkpoint, recipe in bases.values() for index, path in enumerate(reward_models.values())}
    done = dict(zip(jobs, align_all(run, list(jobs.values())), strict=True))  # every alignment side by side
    for model_name, (model, checkpoint, _) in bases.items():
        base_eval = evaluate(run, checkpoint, model, checkpoint, cfg.guidance, costs)
        rows.append({"model": model_name, "backbone": "", "rm_val_accuracy": None,
                     **base_eval["metrics"], "costs": base_eval["reward_cost"]})
        for index, backbone in enumerate(reward_models):
            name, summary = jobs[(model, index)][0], done[(model, index)]
            aligned = evaluate(run, name, model, summary["folder"], cfg.guidance, costs)
            rows.append({"model": f"{model_name} + RM", "backbone": backbone, "rm_val_accuracy": accuracy[backbone],
                         **aligned["metrics"], "costs": aligned["reward_cost"]})
            pairs.append((f"{model_name} → + RM ({backbone})", _flat(base_eval, f"rm{index}"),
                          _flat(aligned, f"rm{index}")))
    names = list(reward_models)
    headers = ["model", "RM backbone", "RM val. accuracy", *(COLUMNS[m] for m in METRICS[:4]),
               *(f"reward cost, {n} RM" for n in names)]
    body = [[r["model"], r["backbone"], r["rm_val_accuracy"], *(r.get(m) for m in METRICS[:4]),
             *(r["costs"].get(f"rm{i}") for i in range(len(names)))] for r in rows]
    return {"title": "Table 4: reward models with the CTG and the TrafficGen encoder, aligning BITS and TrafficGen",
            "rows": rows, "markdown": markdown_table(headers, body), "comparisons": direction_rows(pairs, METRICS),
            "plot": ([f"{r['model']}\n{r['backbone']}" for r in rows],
                     {m: [r.get(m) for r in rows] for m in ("realism_ctg", "failure_rate")}),
            "reward_models": reward_models, "feedback": feedback,
            "notes": [f"Feedback: {feedback['contexts']} train contexts, candidates from "
                      f"{', '.join(cfg.feedback_models)} (bundled weights), labelled by "
                      f"{', '.join(cfg.annotators)}; {cfg.contrast_scenes} contrast scenes; the same data trains "
                      "both reward models. Reward cost of a row under each reward model; the direction check uses "
                      "the reward model that aligned the row."]}


def figure3(run: ExperimentRun) -> dict[str, Any]:
    """Reward-model accuracy against the number of labelled training contexts, with its spread over seeds."""
    import torch

    from trafficrlhf_sdk.feedback.preference import export_preferences
    from trafficrlhf_sdk.feedback.store import FeedbackStore
    from trafficrlhf_sdk.feedback.synthetic import SyntheticAnnotatorConfig
    from trafficrlhf_sdk.reward import RewardConfig, filter_pairs
    from trafficrlhf_sdk.reward.oracle import hidden_realism, strict_pairs

    cfg = run.config
    folder = run.folder("figure3")
    options = {"checkpoint": cfg.ctg_base}
    noisy = {"noisy": SyntheticAnnotatorConfig(beta=20.0, epsilon=0.1, seed=cfg.seed)}
    oracle = {"oracle": SyntheticAnnotatorConfig(beta=None, epsilon=0.0, seed=cfg.seed)}
    labels = [labelled_campaign(run, folder, "train", "ctg", cfg.figure3_contexts, "train", noisy, cfg.guidance,
                                options),
              labelled_campaign(run, folder, "test", "ctg", cfg.scenes, "val", oracle, cfg.guidance, options)]
    store = FeedbackStore(os.path.join(folder, "feedback.sqlite"))
    try:
        train_all = filter_pairs(export_preferences(store, "train", val_fraction=cfg.figure3_dev_fraction,
                                                    seed=cfg.seed), ["noisy"])
        test = filter_pairs(export_preferences(store, "test", val_fraction=0.0), ["oracle"])
        strict = strict_pairs(test, hidden_realism(store, test))
    finally:
        store.close()
    base = RewardConfig(progress=False, seed=cfg.seed, **set_fields(cfg.figure3_reward))
    train_ids = [i for i, s in enumerate(train_all.context_split) if s == "train"]
    dev_ids = [i for i, s in enumerate(train_all.context_split) if s == "val"]
    sizes = [s for s in cfg.figure3_sizes if s <= len(train_ids)] or [len(train_ids)]
    features = _Figure3Features(base, train_all, test, strict)
    runs: list[dict[str, Any]] = []
    for seed in cfg.figure3_seeds:
        order = torch.randperm(len(train_ids), generator=torch.Generator().manual_seed(seed)).tolist()
        for size in sizes:
            batch = 4 if size <= 50 else 8 if size <= 100 else base.batch_size  # small sets: more, smaller steps
            epochs = max(1, min(40, math.ceil(cfg.figure3_steps * batch / size)))
            if "max_epochs" in cfg.figure3_reward.model_fields_set:
                epochs = min(epochs, cfg.figure3_reward.max_epochs)
            config = base.model_copy(update={"seed": seed, "max_epochs": epochs, "batch_size": batch,
                                             "num_threads": cfg.threads})
            chosen = [train_ids[i] for i in order[:size]] + dev_ids
            where = os.path.join(folder, "runs", f"seed_{seed}_contexts_{size}")
            inputs = {"config": config.model_dump(mode="json", exclude={"num_threads", "progress"}),
                      "contexts": chosen}
            done = run.count(run_step("figure3_run", where, inputs,
                                      lambda c=config, ids=chosen, n=size, at=where: features.run(c, ids, n, at),
                                      after=labels, **run.steps))
            runs.append({"seed": seed, **done.outputs})
            if not done.cached:
                run.log(f"figure 3: seed {seed}, {size} contexts: strict accuracy {fmt(runs[-1]['accuracy'], 3)}, "
                        f"all pairs {fmt(runs[-1]['accuracy_all_pairs'], 3)}")
    test_all, test_strict = len(test.pairs), int(strict.sum())
    summary = [_accuracy_summary(size, [r for r in runs if r["contexts"] == size]) for size in sizes]
    return {"title": "Figure 3: reward-model accuracy against the number of labelled contexts", "runs": runs,
            "rows": summary, "test_pairs": test_all, "test_strict_pairs": test_strict,
            "train_contexts": len(train_ids), "dev_contexts": len(dev_ids),
            "markdown": markdown_table(["training contexts", "pairs (mean)", "strict accuracy mean", "std", "min",
                                        "max", "all pairs, mean"],
                                       [[str(s["contexts"]), f"{s['pairs']:.0f}", s["mean"], s["std"], s["min"],
                                         s["max"], s["mean_all_pairs"]] for s in summary]),
            "comparisons": [], "figure": summary,
            "notes": [f"CTG (`{cfg.ctg_base}`, guidance `{cfg.guidance}`) candidates on {len(train_ids)} + "
                      f"{len(dev_ids)} (early stopping) train contexts labelled by a noisy stand-in annotator "
                      f"(β = 20, 10 % mistakes); accuracy on {cfg.scenes} val contexts against a noise-free one: "
                      f"{test_strict} pairs whose winner is strictly more "
                      f"realistic (ties carry no preference), and all {test_all} pairs. Seeds "
                      f"{', '.join(map(str, cfg.figure3_seeds))}; one single `ctg_mlp` model per run."]}


class _Figure3Features:
    """Figure 3's featurized pairs, built when a training run first needs them (not when every run is done)."""

    def __init__(self, base: Any, train_all: Any, test: Any, strict: Any) -> None:
        self.base, self.train_all, self.test, self.strict = base, train_all, test, strict
        self._built: tuple[Any, Any, Any] | None = None

    def _data(self) -> tuple[Any, Any, Any]:
        if self._built is None:
            from trafficrlhf_sdk.reward import build_pair_data, filter_pairs
            from trafficrlhf_sdk.reward.model import get_reward_model_architecture

            prepare = get_reward_model_architecture(self.base.architecture)(self.base.architecture_config).prepare
            strict = (build_pair_data(prepare, filter_pairs(self.test, mask=self.strict))
                      if bool(self.strict.any()) else None)
            self._built = (build_pair_data(prepare, self.train_all), build_pair_data(prepare, self.test), strict)
        return self._built

    def run(self, config: Any, contexts: list[int], size: int, folder: str) -> dict[str, Any]:
        """A reward model trained on ``contexts`` (training ones, then the dev ones), saved in ``folder``, and its
        test accuracies."""
        from trafficrlhf_sdk.reward import evaluate_pairs
        from trafficrlhf_sdk.reward.card import train_and_save

        data, test_all, test_strict = self._data()
        subset = data.subset(contexts)
        began = time.perf_counter()
        result = train_and_save(config, subset, folder, title=f"Figure 3 reward model: {size} contexts",
                                resume=None).result  # an interrupted run continues from its newest epoch
        return {"contexts": size, "pairs": len(subset.split_subset("train")),
                "accuracy": None if test_strict is None else evaluate_pairs(result.model, test_strict)["accuracy"],
                "accuracy_all_pairs": evaluate_pairs(result.model, test_all)["accuracy"],
                "dev_accuracy": result.metrics.get("val_accuracy"), "epochs_run": len(result.history),
                "seconds": time.perf_counter() - began}


def _accuracy_summary(size: int, runs: list[dict[str, Any]]) -> dict[str, Any]:
    strict = [r["accuracy"] for r in runs if r["accuracy"] is not None]
    every = [r["accuracy_all_pairs"] for r in runs]
    mean = sum(strict) / len(strict) if strict else None
    std = (sum((v - mean) ** 2 for v in strict) / (len(strict) - 1)) ** 0.5 if len(strict) > 1 else 0.0
    return {"contexts": size, "pairs": sum(r["pairs"] for r in runs) / max(len(runs), 1), "mean": mean,
            "std": std if strict else None, "min": min(strict) if strict else None,
            "max": max(strict) if strict else None, "mean_all_pairs": sum(every) / len(every) if every else None}


def plot_figure3(path: str, summary: list[dict[str, Any]], runs: list[dict[str, Any]], title: str) -> str:
    """Strict accuracy, mean ± std over seeds with the min-max band and one dot per run, and the all-pairs mean;
    x on a log scale. Returns ``path``."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [s["contexts"] for s in summary]
    nan = float("nan")
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.fill_between(x, [nan if s["min"] is None else s["min"] for s in summary],
                    [nan if s["max"] is None else s["max"] for s in summary], alpha=0.15, color="tab:blue",
                    label="min-max over seeds")
    ax.errorbar(x, [nan if s["mean"] is None else s["mean"] for s in summary],
                yerr=[0.0 if s["std"] is None else s["std"] for s in summary], marker="o", capsize=4,
                color="tab:blue", label="strict pairs: mean ± std")
    ax.scatter([r["contexts"] for r in runs], [nan if r["accuracy"] is None else r["accuracy"] for r in runs], s=10,
               color="tab:blue", alpha=0.5)
    ax.plot(x, [s["mean_all_pairs"] for s in summary], linestyle="--", color="tab:gray", label="all pairs (mean)")
    if len(set(x)) > 1:
        ax.set_xscale("log")
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xticks(x)
    ax.set_xticklabels([str(v) for v in x])
    ax.set_xlabel("labelled training contexts")
    ax.set_ylabel("held-out accuracy")
    ax.axhline(0.5, color="black", linewidth=0.5, linestyle=":")
    ax.set_ylim(0.3, 1.0)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


STEPS: dict[str, Callable[[ExperimentRun], dict[str, Any]]] = {
    "table1": table1, "table2": table2, "table3": table3, "table4": table4, "figure3": figure3}


# --------------------------------------------------------------------------------------------------------- runner
def _produce(run: ExperimentRun, name: str, results: dict[str, Any]) -> None:
    """Run table ``name``'s steps and write its result files (kept as they are when no step had work left);
    its result goes into ``results``."""
    import torch

    config, out_dir, log = run.config, run.out_dir, run.log
    folder = os.path.join(out_dir, name)
    path = os.path.join(folder, "result.json")
    log(f"{name}: starting")
    tic, ran = time.perf_counter(), run.ran
    produced = STEPS[name](run)
    if run.ran == ran and os.path.isfile(path):
        log(f"{name}: every step done before ({path}); skipped")
        with open(path, encoding="utf-8") as handle:
            results[name] = json.load(handle)
        return
    produced.update(command=_command(config, name), seed=config.seed, rollouts=config.rollouts,
                    scenes=config.scenes, wall_time_s=time.perf_counter() - tic, threads=torch.get_num_threads(),
                    machine=platform.machine(), cpus=os.cpu_count(), config=config.model_dump(mode="json"),
                    label=config.label)
    os.makedirs(folder, exist_ok=True)
    if name == "figure3":
        plot_figure3(os.path.join(folder, "result.png"), produced["figure"], produced["runs"], produced["title"])
    else:
        labels, series = produced.pop("plot")
        plot_bars(os.path.join(folder, "result.png"), labels, series, produced["title"])
    write_result(folder, produced, produced["markdown"], produced["comparisons"], produced.get("notes", ()))
    with open(path, encoding="utf-8") as handle:
        results[name] = json.load(handle)
    log(f"{name}: done in {produced['wall_time_s']:.0f} s -> {folder}")


def run_paper(config: PaperConfig, out_dir: str, log: Callable[[str], None] = print,
              overwrite: bool = False) -> dict[str, Any]:
    """Produce ``config.only`` in ``out_dir`` and write ``out_dir/summary.md``; returns ``{name: result}`` for every
    table of ``config.only`` with the total wall time of this call.

    A table's steps that are done return their recorded outputs; a table none of whose steps had work left keeps
    the ``result.json`` it has (and its wall time). A step finished with other settings is refused, naming them,
    unless ``overwrite``."""
    import torch

    os.makedirs(out_dir, exist_ok=True)
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    run = ExperimentRun(config, out_dir, log, overwrite)
    began = time.perf_counter()
    results: dict[str, Any] = {}
    from trafficrlhf_sdk.parallel import ray_session

    with ray_session(config.execution):  # one Ray for every step of the run (nothing in-process)
        for name in config.only:
            _produce(run, name, results)
    total = time.perf_counter() - began
    parts = [f"# Paper experiments ({config.label})", "",
             f"This call: {total:.0f} s on {os.cpu_count()} CPUs ({torch.get_num_threads()} torch threads).", ""]
    for name in TABLES:
        md = os.path.join(out_dir, name, "result.md")
        if os.path.isfile(md):
            with open(md, encoding="utf-8") as handle:
                parts += [handle.read(), ""]
    with open(os.path.join(out_dir, "summary.md"), "w", encoding="utf-8") as handle:
        handle.write("\n".join(parts))
    log(f"all done in {total:.0f} s: {os.path.join(out_dir, 'summary.md')}")
    return {"results": results, "wall_time_s": total}
