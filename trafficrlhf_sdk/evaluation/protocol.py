"""Evaluate a traffic model in closed loop on logged scenes: failure rate, realism deviation, reward cost."""

from __future__ import annotations

import json
import os
import platform
import time
import zipfile
from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.metrics.base import Metric
from trafficrlhf_sdk.metrics.realism import QUANTITIES, SPECS, RealismMetric
from trafficrlhf_sdk.metrics.realism_meta import RealismMetaConfig, RealismMetaMetric
from trafficrlhf_sdk.parallel import ExecutionConfig, derive_seed, run_tasks
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import ClosedLoopPolicy, policy_seed, seed_policy
from trafficrlhf_sdk.simulation.simulator import Rollout, SimulationConfig, log_rollout, simulate

__all__ = ["SCENE_HISTOGRAMS", "EvaluationConfig", "EvaluationReport", "evaluate_policy", "load_scene_histograms",
           "plot_histograms", "run_batched", "save_scene_histograms"]

SCENE_HISTOGRAMS = "scene_histograms.npz"
DEFAULT_METRICS = ("failure", "failure_corners", "realism_ctg", "realism_body", "guidance_objectives", "speed")


class EvaluationConfig(BaseModel):
    """What :func:`evaluate_policy` runs."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    simulation: SimulationConfig = Field(default_factory=SimulationConfig, description="Closed-loop protocol.")
    metrics: tuple[str, ...] = Field(DEFAULT_METRICS, description="Registered metric names to compute.")
    batch_size: int = Field(50, ge=1, description="Scenes simulated per policy batch (memory bound).")
    seed: int = Field(0, description="Seed of the run: each (rollout, batch) task seeds torch's global generator "
                      "and the policy's sampler from it (derive_seed), in-process and on Ray alike.")
    rollouts: int = Field(1, ge=1, le=64, description="K rollouts per scene, at most 64 (every rollout is held in "
                          "memory until the metrics run). K >= 2 adds the realism meta-metric (RealismMetaMetric); "
                          "the other metrics are pooled over the K rollouts.")
    meta: RealismMetaConfig | None = Field(None, description="Meta-metric options; None uses the defaults with "
                                           "K = `rollouts`.")


@dataclass
class EvaluationReport:
    """Scalar metrics of the model and of the logged data on the same scenes, plus timing and histograms."""

    values: dict[str, float]
    logged_values: dict[str, float]
    num_scenes: int
    num_controlled_agents: int
    wall_time_s: float
    simulation_time_s: float
    metadata: dict[str, Any] = field(default_factory=dict)
    histograms: dict[str, dict[str, dict[str, list[float]]]] = field(default_factory=dict)
    # per scene, in the order of ``metadata["scene_ids"]``: "controlled_agents" and every metric value that is a
    # mean over scenes (failure, collision, off-road, speed...); None where a scene has no controlled agent
    per_scene: dict[str, list[float | None]] = field(default_factory=dict)
    # per realism preset and quantity: per-scene bin counts {"simulated", "logged"} of shape (B, num_bins), in
    # the order of ``metadata["scene_ids"]``; saved as scene_histograms.npz for a bootstrap over scenes
    scene_histograms: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    # the closed-loop rollout itself (not saved): for drawing scenes, e.g. with render_failures.save_failure_png
    rollout: Rollout | None = field(default=None, repr=False, compare=False)

    def to_json(self) -> dict[str, Any]:
        """A JSON-serializable dict (NaN written as null)."""
        clean = lambda d: {k: (None if v != v else v) for k, v in d.items()}  # noqa: E731
        return {
            "metrics": clean(self.values),
            "logged": clean(self.logged_values),
            "num_scenes": self.num_scenes,
            "num_controlled_agents": self.num_controlled_agents,
            "wall_time_s": self.wall_time_s,
            "simulation_time_s": self.simulation_time_s,
            "metadata": self.metadata,
            "histograms": self.histograms,
            "per_scene": self.per_scene,
        }

    def save(self, directory: str, plot: bool = True) -> list[str]:
        """Write ``results.json`` (plus ``scene_histograms.npz`` and ``histograms.png`` when there are realism
        histograms) into ``directory``; returns the written paths."""
        os.makedirs(directory, exist_ok=True)
        paths = [os.path.join(directory, "results.json")]
        with open(paths[0], "w", encoding="utf-8") as handle:
            json.dump(self.to_json(), handle, indent=2)
        if self.scene_histograms:
            paths.append(save_scene_histograms(self.scene_histograms, os.path.join(directory, SCENE_HISTOGRAMS)))
        if plot and self.histograms:
            paths.append(plot_histograms(self.histograms, os.path.join(directory, "histograms.png"),
                                         title=str(self.metadata.get("model", ""))))
        return paths


def _simulate_task(shared: dict[str, Any], task: tuple[int, int]) -> tuple[torch.Tensor, ...]:
    """One (rollout, batch) task: seeds from the task, simulates the batch, returns its states, valid, controlled
    and timings. Runs in-process or on a Ray worker (:func:`~trafficrlhf_sdk.parallel.run_tasks`)."""
    rollout, start = task
    config: EvaluationConfig = shared["config"]
    policy = shared["policy"]
    chunk = start // config.batch_size
    seed_policy(policy, derive_seed(shared["policy_seed"], rollout))
    torch.manual_seed(derive_seed(config.seed, rollout, chunk))
    part = simulate(policy, shared["scenario"][start : start + config.batch_size], config.simulation)
    timing = torch.tensor([part.wall_time_s, part.policy_time_s], dtype=torch.float64)
    return part.simulated.states, part.simulated.valid, part.controlled, timing


def run_batched(policy: ClosedLoopPolicy, scenario: ScenarioTensor, config: EvaluationConfig,
                progress: bool = False, execution: ExecutionConfig | None = None) -> tuple[Rollout, Rollout]:
    """Simulate ``scenario`` ``config.rollouts`` times in batches of ``config.batch_size`` scenes.

    Returns ``(rollout, reference)``: the policy's rollouts over all scenes, stacked rollout-major along B (scene
    ``k * B + b`` is rollout k of scene b), and the log-replay rollout of the scenes. Each (rollout, batch) task
    seeds itself (:func:`~trafficrlhf_sdk.parallel.derive_seed`: rollout 0 keeps the policy's seed, batch 0 of
    rollout 0 keeps ``config.seed``), so ``execution`` (in-process or Ray workers) does not change the numbers.
    Batches are joined along B without copying the map rasters.
    """
    reference = log_rollout(scenario, config.simulation)
    tasks = [(k, i) for k in range(config.rollouts) for i in range(0, scenario.num_scenes, config.batch_size)]
    shared = {"policy": policy, "scenario": scenario, "config": config,
              "policy_seed": policy_seed(policy, config.seed)}
    if progress and (execution is None or not execution.uses_ray):
        from trafficrlhf_sdk.console import progress as progress_bar

        parts = [_simulate_task(shared, task) for task in progress_bar(tasks, desc="simulating", unit="batch")]
    else:
        parts = run_tasks(_simulate_task, shared, tasks, execution)
    seed_policy(policy, shared["policy_seed"])
    logged = reference.logged if config.rollouts == 1 else \
        reference.logged[torch.arange(scenario.num_scenes).repeat(config.rollouts)]
    simulated = logged.replace_unchecked(
        states=torch.cat([p[0] for p in parts]),
        valid=torch.cat([p[1] for p in parts]),
        controlled=torch.cat([p[2] for p in parts]),
    )
    timing = torch.stack([p[3] for p in parts]).sum(0)
    rollout = Rollout(simulated, logged, simulated.controlled, reference.start_index, reference.end_index,
                      float(timing[0]), float(timing[1]))
    return rollout, reference


def compute_metrics(rollout: Rollout, metrics: Sequence[Metric], per_scene: dict[str, list[float | None]] | None = None,
                    scene_histograms: dict[str, Any] | None = None) -> tuple[dict[str, float], dict[str, Any]]:
    """All scalar values of ``metrics`` on ``rollout`` and the realism histograms (simulated and logged).

    ``per_scene``, if given, receives each metric's per-scene values ``(B,)`` as lists (NaN written as None);
    ``scene_histograms`` receives each realism preset's per-scene bin counts
    (:attr:`EvaluationReport.scene_histograms`)."""
    values: dict[str, float] = {}
    histograms: dict[str, Any] = {}
    for metric in metrics:
        result = metric.compute(rollout)
        values.update(result.values)
        if per_scene is not None:
            per_scene.update({k: [None if x != x else x for x in v.double().tolist()]
                              for k, v in result.per_scene.items()})
        if isinstance(metric, RealismMetric):
            histograms[metric.preset] = {
                q: {"simulated": result.extras["simulated"][q].tolist(), "logged": result.extras["logged"][q].tolist(),
                    "low": SPECS[q].low, "high": SPECS[q].high}
                for q in QUANTITIES
            }
            if scene_histograms is not None:
                counts = result.extras["scene_counts"]
                scene_histograms[metric.preset] = {
                    q: {side: counts[side][q].round().to(torch.int32).numpy() for side in ("simulated", "logged")}
                    for q in (*QUANTITIES, "pace")
                }
    return values, histograms


def evaluate_policy(
    policy: ClosedLoopPolicy,
    scenario: ScenarioTensor,
    config: EvaluationConfig | None = None,
    extra_metrics: Sequence[Metric] = (),
    progress: bool = False,
    metadata: dict[str, Any] | None = None,
    execution: ExecutionConfig | None = None,
) -> EvaluationReport:
    """Run ``policy`` in closed loop on ``scenario`` and compute the metrics for it and for the log.

    Args:
        policy: a :class:`ClosedLoopPolicy`.
        scenario: logged scenes ``(B, A, T)``.
        config: :class:`EvaluationConfig`.
        extra_metrics: metric instances beyond the registered names (e.g. a ``RewardCostMetric``).
        progress: show progress bars.
        metadata: stored in the report (model name, source, split...).
        execution: where the (rollout, batch) tasks run: in-process (None, the default) or on Ray workers; the
            numbers are the same.

    With ``config.rollouts`` K >= 2 every scene is simulated K times: the failure, realism and other metrics are
    pooled over the K rollouts (per-scene values are the means over the rollouts) and the realism meta-metric
    (:class:`~trafficrlhf_sdk.metrics.realism_meta.RealismMetaMetric`) is added, for the policy and, as the
    ceiling at this K, for the log scored against K copies of itself.
    """
    from trafficrlhf_sdk.plugins import get_metric

    config = config or EvaluationConfig()
    metrics = [get_metric(name) for name in config.metrics] + list(extra_metrics)
    began = time.perf_counter()
    rollout, reference = run_batched(policy, scenario, config, progress, execution)
    b, k = scenario.num_scenes, config.rollouts
    per_scene: dict[str, list[float | None]] = {"controlled_agents": rollout.controlled[:b].sum(-1).tolist()}
    scene_histograms: dict[str, Any] = {}
    values, histograms = compute_metrics(rollout, metrics, per_scene, scene_histograms)
    if k > 1:  # per-scene values: the mean over the K rollouts; per-scene histogram counts: their sum
        for key, column in per_scene.items():
            if key != "controlled_agents" and len(column) == k * b:
                stacked = np.array([np.nan if v is None else v for v in column], dtype=np.float64).reshape(k, b)
                per_scene[key] = [None if v != v else float(v) for v in stacked.mean(0)]
        for by_quantity in scene_histograms.values():
            for sides in by_quantity.values():
                for side, counts in sides.items():
                    sides[side] = counts.reshape(k, b, -1).sum(0)
    logged_values, _ = compute_metrics(reference, metrics)
    if k > 1 and config.metrics:
        meta = RealismMetaMetric(config.meta or RealismMetaConfig(rollouts=k))
        if meta.config.rollouts != k:
            raise ValueError(f"config.meta.rollouts={meta.config.rollouts} differs from config.rollouts={k}; set "
                             "them equal (or leave `meta` None).")
        result, ceiling = meta.compute_with_ceiling(rollout)  # the ceiling: the log against K copies of itself
        values.update(result.values)
        per_scene.update({key: [None if x != x else float(x) for x in v.tolist()]
                          for key, v in result.per_scene.items()})
        logged_values.update(ceiling.values)
    info = {"torch_threads": torch.get_num_threads(), "machine": platform.machine(), "seed": config.seed,
            "rollouts": k}
    if execution is not None and execution.uses_ray:
        info["ray_workers"] = execution.workers
        info["ray_address"] = execution.ray_address
    info.update(metadata or {})
    return EvaluationReport(
        values=values,
        logged_values=logged_values,
        num_scenes=scenario.num_scenes,
        num_controlled_agents=int(rollout.controlled[:b].sum()),
        wall_time_s=time.perf_counter() - began,
        simulation_time_s=rollout.wall_time_s,
        metadata=info,
        histograms=histograms,
        per_scene=per_scene,
        scene_histograms=scene_histograms,
        rollout=rollout,
    )


def save_scene_histograms(scene_histograms: dict[str, dict[str, dict[str, Any]]], path: str) -> str:
    """Write :attr:`EvaluationReport.scene_histograms` to ``path`` (``.npz``, one ``preset/quantity/side`` array
    of int32 counts ``(B, num_bins)`` each); returns ``path``."""
    arrays = {f"{preset}/{q}/{side}": np.asarray(counts, dtype=np.int32)
              for preset, by_quantity in scene_histograms.items()
              for q, sides in by_quantity.items() for side, counts in sides.items()}
    np.savez_compressed(path, **arrays)
    return path


def load_scene_histograms(path: str) -> dict[str, dict[str, dict[str, Any]]]:
    """Read a :func:`save_scene_histograms` file back into ``{preset: {quantity: {side: int array (B, bins)}}}``.

    Raises DataFormatError for a file that is not such an archive."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise DataFormatError(f"{path}: not a per-scene histogram archive ({exc}); re-run "
                              "`trafficrlhf evaluate --out` to write it again.") from exc
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for key, array in arrays.items():
        parts = key.split("/")
        if len(parts) != 3 or array.ndim != 2:
            raise DataFormatError(f"{path}: unexpected entry {key!r} of shape {array.shape}; expected "
                                  "'preset/quantity/side' arrays of shape (scenes, bins).")
        out.setdefault(parts[0], {}).setdefault(parts[1], {})[parts[2]] = array
    return out


def plot_histograms(histograms: dict[str, Any], path: str, title: str = "") -> str:
    """PNG of simulated vs logged histograms: one row per realism preset, one column per quantity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    presets = list(histograms)
    fig, axes = plt.subplots(len(presets), len(QUANTITIES), figsize=(4 * len(QUANTITIES), 3 * len(presets)),
                             squeeze=False)
    units = {"lon_acc": "m/s²", "lat_acc": "m/s²", "jerk": "m/s³"}
    for row, preset in enumerate(presets):
        for col, q in enumerate(QUANTITIES):
            h = histograms[preset][q]
            edges = torch.linspace(h["low"], h["high"], len(h["logged"]) + 1)
            centres = ((edges[1:] + edges[:-1]) / 2).tolist()
            width = float(edges[1] - edges[0])
            ax = axes[row][col]
            ax.bar(centres, h["logged"], width=width, alpha=0.5, label="logged", color="tab:gray")
            ax.step(centres, h["simulated"], where="mid", label="simulated", color="tab:red")
            ax.set_title(f"{preset}: {q}")
            ax.set_xlabel(units[q])
            if col == 0:
                ax.set_ylabel("share (scene-normalized)")
            ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def seeds_summary(results: list[dict]) -> dict:
    """Runs of one policy on the same scenes at several seeds, as one JSON object.

    ``results``: each run's ``EvaluationReport.to_json()``. Returns ``seeds``; ``mean`` and ``std`` (population,
    over the runs) of every metric that all runs report as a number; ``logged`` (the logged data's values, the
    same for every seed); ``runs``: each seed's metrics; and the scene count and controlled agents.
    """
    def numbers(result: dict) -> dict[str, float]:
        return {key: float(value) for key, value in result["metrics"].items() if isinstance(value, (int, float))}

    per_run = [numbers(result) for result in results]
    keys = [key for key in per_run[0] if all(key in values for values in per_run)]
    mean = {key: sum(values[key] for values in per_run) / len(per_run) for key in keys}
    std = {key: (sum((values[key] - mean[key]) ** 2 for values in per_run) / len(per_run)) ** 0.5 for key in keys}
    seeds = [result["metadata"].get("seed") for result in results]
    return {"seeds": seeds, "mean": mean, "std": std, "logged": results[0]["logged"],
            "runs": [{"seed": seed, "metrics": result["metrics"]} for seed, result in zip(seeds, results)],
            "num_scenes": results[0]["num_scenes"], "num_controlled_agents": results[0]["num_controlled_agents"],
            "metadata": {key: value for key, value in results[0]["metadata"].items() if key != "seed"}}
