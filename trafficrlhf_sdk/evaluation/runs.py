"""Evaluation runs end to end: which scenes, one run per seed and their mean, results on disk.

``trafficrlhf evaluate`` is :func:`run_evaluation` plus printing. From Python::

    from trafficrlhf_sdk.evaluation import EvaluationRequest, run_evaluation

    outcome = run_evaluation(EvaluationRequest(checkpoint="ctg-aligned", num_scenes=20, seeds=(0, 1, 2)))
    outcome.runs.mean["failure_rate"]            # the mean over the seeds
    [r.values["failure_rate"] for r in outcome.runs.reports]  # each seed's value

The parts are public too: :func:`select_scenes` (the long-enough scenes asked for), :func:`load_scenes` (loaded,
too-short ones dropped and counted) and :func:`evaluate_seeds` (one :func:`evaluate_policy` per seed).
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from trafficrlhf_sdk.errors import DataFormatError, TrafficRLHFError
from trafficrlhf_sdk.evaluation.compare import run_label
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, EvaluationReport, evaluate_policy, seeds_summary
from trafficrlhf_sdk.parallel import ExecutionConfig, ray_session
from trafficrlhf_sdk.simulation.simulator import SimulationConfig

__all__ = ["EvaluationOutcome", "EvaluationRequest", "SceneSelection", "SeedRuns", "check_out_dir", "evaluate_seeds",
           "load_scenes", "render_worst", "run_evaluation", "select_scenes"]

HISTORY_S = 3.0  # the protocol's history before the closed loop starts


class SceneSelection(BaseModel):
    """The scenes a closed-loop run reads and the protocol it runs them under (shared by the requests of
    :func:`run_evaluation` and :func:`~trafficrlhf_sdk.evaluation.side_by_side.render_side_by_side`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: str = Field("nuscenes_pred", description="Registered scenario source.")
    split: str = Field("val", description="Split of the source.")
    root: str | None = Field(None, description="Data directory of the source; None: the source's default.")
    num_scenes: int = Field(100, ge=1, description="The first N long-enough scenes of the split, sorted by name.")
    scene_ids: tuple[str, ...] = Field((), description="Only these scenes (in this order); overrides `num_scenes`.")
    batch_size: int = Field(50, ge=1, description="Scenes per simulated batch.")
    simulation: SimulationConfig = Field(default_factory=SimulationConfig, description="The closed-loop protocol "
                                         "(duration, late agents, agents after their log ends).")

    def load(self, log: Callable[[str], None] | None = None) -> tuple[Any, list[str]]:
        """``(scenario, scene_ids)``: the selected scenes of the source, loaded as one batch (:func:`select_scenes`,
        :func:`load_scenes`); a protocol shorter than 10 s also admits shorter scenes."""
        from trafficrlhf_sdk.plugins import get_scenario_source

        duration = self.simulation.duration_s
        options: dict[str, Any] = {"root": self.root} if self.root else {}
        if duration != 10.0:
            options["min_future_s"] = duration
        source = get_scenario_source(self.source, **options)
        ids = select_scenes(source, self.split, self.num_scenes, self.scene_ids, duration, log)
        return load_scenes(source, self.split, ids, duration, log)


class EvaluationRequest(SceneSelection):
    """Everything :func:`run_evaluation` needs: the model, the scenes, the protocol and the seeds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: str | None = Field(None, description="Registered traffic model or built-in policy; None: the one "
                              "`checkpoint` was saved by.")
    checkpoint: str | None = Field(None, description="Weights: a folder, or a bundled checkpoint's name such as "
                                   "'ctg-aligned'.")
    guidance: str | None = Field(None, description="Guidance spec for models that support it; None keeps the one "
                                 "a bundled checkpoint's card was measured with, 'none' turns it off.")
    model_options: dict[str, Any] = Field(default_factory=dict, description="Other traffic-model options.")
    seeds: tuple[int, ...] = Field((0,), min_length=1, description="One run per seed; several give their mean.")
    rollouts: int = Field(1, ge=1, description="K rollouts per scene (K >= 2 adds the realism meta-metric).")
    reward_model: str | None = Field(None, description="Saved reward model folder: adds the reward-cost metric.")
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig, description="In-process or on Ray workers.")

    @field_validator("seeds")
    @classmethod
    def _distinct(cls, seeds: tuple[int, ...]) -> tuple[int, ...]:
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"seeds {list(seeds)} repeat a seed; give distinct seeds, e.g. (0, 1, 2).")
        return seeds

    def metadata(self, model: str, scene_ids: Sequence[str], guidance: str | None) -> dict[str, Any]:
        """What each run's ``results.json`` records about the request (``guidance``: the one in effect)."""
        return {"model": model, "source": self.source, "split": self.split, "guidance": guidance,
                "checkpoint": self.checkpoint, "reward_model": self.reward_model,
                "model_options": dict(self.model_options), "late_agents": self.simulation.late_agents,
                "after_log_end": self.simulation.after_log_end, "scene_ids": list(scene_ids),
                "rollouts": self.rollouts, "duration_s": self.simulation.duration_s}


@dataclass
class SeedRuns:
    """The runs of one policy on the same scenes, one per seed (in the order of the seeds)."""

    reports: list[EvaluationReport]

    @property
    def seeds(self) -> list[int]:
        """The seed of each run."""
        return [int(report.metadata["seed"]) for report in self.reports]

    def summary(self) -> dict[str, Any]:
        """``seeds``, ``mean`` and ``std`` over the runs, ``logged``, each run's metrics (:func:`seeds_summary`)."""
        return seeds_summary([report.to_json() for report in self.reports])

    @property
    def mean(self) -> dict[str, float]:
        """The mean over the runs of every metric they all report as a number."""
        return self.summary()["mean"]

    def save(self, directory: str) -> list[str]:
        """Write each run to ``directory/seed_<S>`` (:meth:`EvaluationReport.save`); returns the folders."""
        folders = []
        for seed, report in zip(self.seeds, self.reports):
            folders.append(os.path.join(directory, f"seed_{seed}"))
            report.save(folders[-1])
        return folders


def evaluate_seeds(build: Callable[[int], Any], scenario: Any, seeds: Sequence[int],
                   config: EvaluationConfig | None = None, **kwargs: Any) -> SeedRuns:
    """One closed-loop evaluation of ``build(seed)`` per seed, on the same scenes.

    Args:
        build: returns the policy for a seed (e.g. ``lambda s: from_pretrained("ctg-aligned", seed=s)``).
        scenario: the logged scenes ``(B, A, T)``.
        seeds: distinct seeds; each run's :class:`EvaluationConfig` takes its seed.
        config: the protocol (its ``seed`` is replaced by each seed).
        **kwargs: passed to :func:`evaluate_policy` (``extra_metrics``, ``progress``, ``metadata``,
            ``execution``).

    Returns:
        :class:`SeedRuns`: each seed's :class:`EvaluationReport` and their mean (``.mean``, ``.summary()``).
    """
    import torch

    if not seeds or len(set(seeds)) != len(seeds):
        raise TrafficRLHFError(f"seeds {list(seeds)}: give one or more distinct seeds, e.g. [0, 1, 2].")
    config = config or EvaluationConfig()
    reports = []
    with ray_session(kwargs.get("execution") or ExecutionConfig()):  # one Ray (and its workers) for every seed
        for seed in seeds:
            torch.manual_seed(seed)
            reports.append(evaluate_policy(build(seed), scenario, config.model_copy(update={"seed": seed}), **kwargs))
    return SeedRuns(reports)


def select_scenes(source: Any, split: str, num_scenes: int = 100, scene_ids: Sequence[str] = (),
                  duration_s: float = 10.0, log: Callable[[str], None] | None = None) -> list[str]:
    """The scenes to evaluate: ``scene_ids`` (each checked against the split's long-enough scenes, with close
    matches for a typo) or else the first ``num_scenes`` long-enough ones. ``log`` hears how many scenes the
    length filter left out and when fewer scenes exist than asked for."""
    long_enough = source.scene_ids(split)
    listed = getattr(source, "all_scene_ids", None)
    if log is not None and callable(listed):
        total = len(listed(split))
        if total > len(long_enough):
            log(f"{total - len(long_enough)} of {total} scenes of {split!r} are shorter than {HISTORY_S:g} s + "
                f"{duration_s:g} s and are skipped; a shorter --duration keeps more of them.")
    if scene_ids:
        known = set(long_enough)
        for name in scene_ids:
            if name not in known:
                close = difflib.get_close_matches(name, long_enough, n=3)
                hint = f" Did you mean {', '.join(close)}?" if close else ""
                raise TrafficRLHFError(f"--scene-id {name!r} is not a long-enough scene of split {split!r} "
                                       f"({len(long_enough)} are; `trafficrlhf inspect` lists them).{hint}")
        return list(dict.fromkeys(scene_ids))
    chosen = long_enough[:num_scenes]
    if not chosen:
        raise TrafficRLHFError(f"split {split!r} of source {source.name!r} has no scene long enough for a "
                               f"{duration_s:g} s rollout; try a shorter --duration.")
    if log is not None and num_scenes > len(chosen):
        log(f"--scenes {num_scenes} asked for more than the {len(chosen)} long-enough scenes of "
            f"{source.name}/{split}; evaluating all {len(chosen)}.")
    return chosen


def load_scenes(source: Any, split: str, scene_ids: Sequence[str], duration_s: float,
                log: Callable[[str], None] | None = None) -> tuple[Any, list[str]]:
    """``(scenario, scene_ids)``: the scenes loaded as one batch, without those shorter than 3 s + ``duration_s``
    (a source that lists scenes without reading them can hand over such scenes; ``log`` hears how many)."""
    import torch

    scene_ids = list(scene_ids)
    scenario = source.load_batch(split, scene_ids=scene_ids, progress=True)
    last = torch.where(scenario.valid.any(1), torch.arange(scenario.num_steps), -1).amax(-1)
    short = last < scenario.current_index + round(duration_s / scenario.dt)
    if not short.any():
        return scenario, scene_ids
    if bool(short.all()):
        raise TrafficRLHFError(f"all {len(scene_ids)} scenes are shorter than {HISTORY_S:g} s + {duration_s:g} s; "
                               "try a shorter --duration.")
    if log is not None:
        log(f"{int(short.sum())} of {len(scene_ids)} loaded scenes are shorter than {HISTORY_S:g} s + "
            f"{duration_s:g} s and are skipped; a shorter --duration keeps them.")
    return scenario[(~short).nonzero().flatten()], [s for s, drop in zip(scene_ids, short.tolist()) if not drop]


def check_out_dir(out_dir: str) -> None:
    """Refuse an output folder that cannot take the results, before anything is simulated."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise TrafficRLHFError(f"--out {out_dir!r} is a file, not a folder; pass a folder (it is created if needed).")
    parent = os.path.abspath(out_dir)
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK | os.X_OK):
        raise TrafficRLHFError(f"--out {out_dir!r} cannot be written ({parent!r} is not a writable folder); pass a "
                               "folder you can write to.")


def render_worst(report: EvaluationReport, top: int, out_dir: str) -> list[str]:
    """PNGs of the ``top`` scenes carrying most of the failure rate (scenes without a failure are not drawn),
    named ``out_dir/worst_scenes/<rank>_<scene>.png``; returns the paths."""
    from trafficrlhf_sdk.evaluation.breakdown import pooled_per_scene, worst_scenes
    from trafficrlhf_sdk.evaluation.failures import first_failures, save_failure_png

    result, rollout = report.to_json(), report.rollout
    if rollout is None:
        raise ValueError("the report holds no rollout to draw; make it with evaluate_policy.")
    scene_ids = result["metadata"]["scene_ids"]
    failures = first_failures(rollout)
    rows = [row for row in worst_scenes(pooled_per_scene([result]), top) if row.value > 0]
    return [save_failure_png(rollout, scene_ids.index(row.scene_id),
                             os.path.join(out_dir, "worst_scenes", f"{rank:02d}_{row.scene_id}.png"), failures=failures)
            for rank, row in enumerate(rows, start=1)]


@dataclass
class EvaluationOutcome:
    """What :func:`run_evaluation` made: the runs, the name of the model, and the files written."""

    runs: SeedRuns
    model: str
    folders: list[str] = field(default_factory=list)
    paths: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        """The runs' name in tables (:func:`run_label`)."""
        return run_label(self.runs.reports[0].metadata)


def run_evaluation(request: EvaluationRequest, out_dir: str | None = None, render_top: int = 0,
                   log: Callable[[str], None] | None = None, progress: bool = True,
                   seed_folders: bool | None = None) -> EvaluationOutcome:
    """Evaluate ``request``: build the model (a bad model, option or guidance fails before any data is read),
    choose and load the scenes, run once per seed, and write the results when ``out_dir`` is given.

    Each run is written to ``out_dir/seed_<S>`` when ``seed_folders`` (default: when there are several seeds),
    else to ``out_dir`` itself;
    ``render_top`` N draws the N scenes carrying most of the failure rate of each run (needs ``out_dir``).
    ``log`` hears the notes on skipped scenes."""
    import torch

    from trafficrlhf_sdk.plugins import build_policy

    if out_dir is not None:
        check_out_dir(out_dir)
    if render_top and not out_dir:
        raise TrafficRLHFError(f"--render-worst {render_top} writes PNGs under --out, which is not set; add "
                               "--out DIR (or drop --render-worst).")
    extra_metrics = []
    if request.reward_model is not None:  # load before simulating: a bad folder fails at once
        from trafficrlhf_sdk.metrics.reward_cost import RewardCostMetric
        from trafficrlhf_sdk.reward import RewardModel

        extra_metrics.append(RewardCostMetric(RewardModel.from_pretrained(request.reward_model).step_rewards))

    def build(seed: int) -> Any:
        return build_policy(request.model, {**request.model_options, "guidance": request.guidance,
                                            "checkpoint": request.checkpoint, "seed": seed})

    torch.manual_seed(request.seeds[0])
    first = build(request.seeds[0])
    model = request.model or str(getattr(first, "name", None) or type(first).__name__)
    guidance = getattr(getattr(first, "options", None), "guidance", request.guidance)
    scenario, scene_ids = request.load(log)
    config = EvaluationConfig(simulation=request.simulation, batch_size=request.batch_size, rollouts=request.rollouts)
    execution = request.execution if request.execution.uses_ray else None
    runs = evaluate_seeds(lambda seed: first if seed == request.seeds[0] else build(seed), scenario, request.seeds,
                          config, extra_metrics=extra_metrics, progress=progress, execution=execution,
                          metadata=request.metadata(model, scene_ids, guidance or None))
    if runs.reports[0].num_controlled_agents == 0:
        raise DataFormatError(
            f"none of the {len(scene_ids)} scenes ({', '.join(scene_ids[:5])}{', ...' if len(scene_ids) > 5 else ''})"
            f" of {request.source}/{request.split} has an agent to drive (a vehicle present at 'now' on the drivable "
            "layer of its map), so every metric would be empty; nothing was written. Pick other scenes, or fix the "
            "scenes' maps."
        )
    outcome = EvaluationOutcome(runs, model)
    if out_dir is not None:
        if not (len(runs.reports) > 1 if seed_folders is None else seed_folders):
            outcome.folders, outcome.paths = [out_dir], runs.reports[0].save(out_dir)
        else:
            outcome.folders = runs.save(out_dir)
        for report, folder in zip(runs.reports, outcome.folders):
            outcome.paths += render_worst(report, render_top, folder) if render_top else []
    return outcome
