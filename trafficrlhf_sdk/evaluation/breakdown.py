"""Which scenes carry a scene-averaged metric, which scenes changed between two evaluations, and how sure the
change is (a paired bootstrap over scenes), for the failure rates and for the realism deviations.

The failure rate is a mean over scenes of per-scene shares of agents, so a scene with one controlled agent that
fails weighs as much as a scene where all twenty fail; a few small scenes can carry most of it. These helpers
read the ``per_scene`` part of ``trafficrlhf evaluate``'s ``results.json`` (lists in the order of
``metadata["scene_ids"]``, None where a scene has no controlled agent).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from trafficrlhf_sdk.errors import DataFormatError

__all__ = ["ChangeInterval", "DifferenceInterval", "SceneChange", "SceneShare", "paired_change_interval",
           "paired_difference_interval", "paired_realism_interval",
           "pooled_per_scene", "realism_deviation_draws", "scene_changes", "scenes_carrying", "worst_scenes"]


@dataclass(frozen=True)
class SceneShare:
    """One scene's value of a scene-averaged metric and its share of the sum over scenes (0-1)."""

    scene_id: str
    controlled_agents: int
    value: float
    share: float
    cumulative_share: float


@dataclass(frozen=True)
class SceneChange:
    """One scene's value in a first and a second evaluation (each a mean over its seeds)."""

    scene_id: str
    controlled_agents: int
    before: float
    after: float

    @property
    def change(self) -> float:
        """``after - before`` (same unit as the metric)."""
        return self.after - self.before


def pooled_per_scene(results: Sequence[dict[str, Any]], key: str = "failure_rate") -> dict[str, tuple[int, float]]:
    """``{scene_id: (controlled agents, mean of key over the runs)}`` from one or more ``results.json`` dicts of
    the same scenes (e.g. evaluation seeds); scenes without a value (no controlled agent) are left out."""
    if not results:
        raise ValueError("results is empty; pass at least one results.json dict.")
    ids = results[0].get("metadata", {}).get("scene_ids")
    columns = []
    for result in results:
        per_scene = result.get("per_scene") or {}
        if key not in per_scene:
            raise DataFormatError(f"results have no per-scene {key!r} (found: {sorted(per_scene) or 'none'}); "
                                  "re-run `trafficrlhf evaluate --out` with this version to write them.")
        if result.get("metadata", {}).get("scene_ids") != ids or ids is None or len(per_scene[key]) != len(ids):
            raise DataFormatError("per-scene results cover different scenes; pool only runs of the same "
                                  "--split/--scenes.")
        columns.append(per_scene[key])
    agents = results[0]["per_scene"].get("controlled_agents") or [0] * len(ids)
    pooled = {}
    for i, scene_id in enumerate(ids):
        values = [column[i] for column in columns]
        if all(v is not None for v in values):
            pooled[scene_id] = (int(agents[i]), math.fsum(values) / len(values))
    return pooled


def worst_scenes(per_scene: dict[str, tuple[int, float]], top: int | None = None) -> list[SceneShare]:
    """Scenes by decreasing value, each with its share of the total and the running share; the first ``top``
    (all if None). ``per_scene``: as returned by :func:`pooled_per_scene`."""
    total = math.fsum(value for _, value in per_scene.values())
    ranked = sorted(per_scene.items(), key=lambda item: (-item[1][1], item[0]))
    rows, running = [], 0.0
    for scene_id, (agents, value) in ranked[: len(ranked) if top is None else top]:
        running += value
        rows.append(SceneShare(scene_id, agents, value, value / total if total > 0 else 0.0,
                               running / total if total > 0 else 0.0))
    return rows


def scenes_carrying(per_scene: dict[str, tuple[int, float]], fraction: float) -> int:
    """The fewest scenes whose values sum to at least ``fraction`` (0-1] of the total (0 if the total is 0)."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}.")
    total = math.fsum(value for _, value in per_scene.values())
    if total <= 0:
        return 0
    for count, row in enumerate(worst_scenes(per_scene), start=1):
        if row.cumulative_share >= fraction - 1e-12:
            return count
    return len(per_scene)


def scene_changes(before: dict[str, tuple[int, float]], after: dict[str, tuple[int, float]],
                  top: int | None = None) -> list[SceneChange]:
    """Scenes present in both, by decreasing ``|after - before|`` (ties by scene id); the first ``top``."""
    rows = [SceneChange(s, before[s][0], before[s][1], after[s][1]) for s in before if s in after]
    rows.sort(key=lambda row: (-abs(row.change), row.scene_id))
    return rows[: len(rows) if top is None else top]


def _check_bootstrap(level: float, resamples: int) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}.")
    if resamples < 100:
        raise ValueError(f"resamples must be at least 100 for a percentile interval, got {resamples!r}.")


@dataclass(frozen=True)
class ChangeInterval:
    """The relative change of a scene-averaged metric between two evaluations of the same scenes, with a paired
    bootstrap interval over scenes. Changes are fractions: -0.66 is 66 % lower."""

    before: float
    after: float
    change: float
    low: float
    high: float
    level: float
    scenes: int
    resamples: int
    target: float | None = None
    share_meeting_target: float | None = None
    """Share of the resamples whose change is at or below ``target`` (None without a target)."""


def paired_change_interval(before: dict[str, tuple[int, float]], after: dict[str, tuple[int, float]],
                           level: float = 0.95, resamples: int = 10_000, seed: int = 0,
                           target: float | None = None) -> ChangeInterval:
    """``mean(after) / mean(before) - 1`` over the scenes present in both, with a percentile interval from
    ``resamples`` paired bootstrap draws of the scenes (each draw picks the same scenes, with replacement, for
    both evaluations).

    The scene is the resampling unit because the claim is about scenes not yet seen: the interval says how far
    the change could move on another draw of as many scenes. Evaluation-seed noise is inside it too when each
    scene's value is already a mean over seeds (:func:`pooled_per_scene`). ``before``/``after``: as returned by
    :func:`pooled_per_scene`. ``target`` (e.g. -0.7): also report the share of draws at or below it.
    """
    _check_bootstrap(level, resamples)
    scenes = sorted(s for s in before if s in after)
    if len(scenes) < 2:
        raise DataFormatError(f"the two evaluations share {len(scenes)} scene(s) with controlled agents; a paired "
                              "interval needs at least 2. Compare runs of the same --split/--scenes.")
    x = np.array([before[s][1] for s in scenes], dtype=np.float64)
    y = np.array([after[s][1] for s in scenes], dtype=np.float64)
    if x.sum() <= 0:
        raise DataFormatError("the first evaluation's metric is 0 on every shared scene, so a relative change is "
                              "undefined; compare absolute values instead.")
    draws = np.random.default_rng(seed).integers(0, len(scenes), size=(resamples, len(scenes)))
    base_sums = x[draws].sum(1)
    # a draw of only zero-valued scenes has no defined ratio; it is dropped (vanishingly rare for real rates)
    ok = base_sums > 0
    changes = y[draws].sum(1)[ok] / base_sums[ok] - 1.0
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(changes, [tail, 1.0 - tail])
    share = None if target is None else float((changes <= target).mean())
    return ChangeInterval(before=float(x.mean()), after=float(y.mean()), change=float(y.sum() / x.sum() - 1.0),
                          low=float(low), high=float(high), level=level, scenes=len(scenes),
                          resamples=int(ok.sum()), target=target, share_meeting_target=share)


SceneCounts = Mapping[str, Mapping[str, np.ndarray]]
"""One run's per-scene bin counts of one realism preset: ``{quantity: {"simulated"|"logged": (scenes, bins)}}``,
as saved in ``scene_histograms.npz`` by ``trafficrlhf evaluate --out``."""


def realism_deviation_draws(run: SceneCounts, weights: np.ndarray) -> np.ndarray:
    """The realism deviation (mean over lon_acc, lat_acc and jerk of the Wasserstein-1 distance between the
    logged and simulated scene-normalized histograms) of ``run`` for each row of ``weights (R, scenes)``: how
    many times each scene is drawn. A row of ones gives the deviation ``trafficrlhf evaluate`` reports.
    Returns ``(R,)``; NaN where a draw has no sample of a quantity."""
    from trafficrlhf_sdk.metrics.realism import QUANTITIES, SPECS  # imports torch: only when realism is asked for

    total = np.zeros(weights.shape[0])
    for q in QUANTITIES:
        if q not in run or {"simulated", "logged"} - set(run[q]):
            raise DataFormatError(f"per-scene histograms lack {q!r} (simulated and logged); found {sorted(run)}.")
        hists = []
        for side in ("logged", "simulated"):
            counts = np.asarray(run[q][side], dtype=np.float64)
            if counts.ndim != 2 or counts.shape[0] != weights.shape[1]:
                raise DataFormatError(f"{q}/{side} counts have shape {counts.shape}; expected ({weights.shape[1]}, "
                                      "bins): one row per scene of the evaluation.")
            rows = counts.sum(1, keepdims=True)
            shares = np.divide(counts, rows, out=np.zeros_like(counts), where=rows > 0)
            drawn = weights @ shares
            sums = drawn.sum(1, keepdims=True)
            hists.append(np.divide(drawn, sums, out=np.full_like(drawn, np.nan), where=sums > 0))
        spec = SPECS[q]
        width = (spec.high - spec.low) / spec.num_bins
        total += np.abs(np.cumsum(hists[0] - hists[1], 1)[:, :-1]).sum(1) * width
    return total / len(QUANTITIES)


def paired_realism_interval(before: Sequence[SceneCounts], after: Sequence[SceneCounts], level: float = 0.95,
                            resamples: int = 10_000, seed: int = 0) -> ChangeInterval:
    """Relative change of one realism deviation between two evaluations of the same scenes, with a percentile
    interval from ``resamples`` paired bootstrap draws of the scenes.

    ``before``/``after``: one :data:`SceneCounts` per evaluation seed; a draw's deviation is the mean over the
    seeds of each seed's deviation on the drawn scenes (as ``trafficrlhf compare`` averages seeds). Unlike the
    failure rate, the deviation is a distance between histograms pooled over scenes, not a mean of per-scene
    values, so each draw rebuilds the histograms from the drawn scenes' counts.
    """
    _check_bootstrap(level, resamples)
    if not before or not after:
        raise ValueError("before and after each need at least one run's per-scene histograms.")
    scenes = {np.asarray(run[q][side]).shape[0] for run in (*before, *after) for q in run for side in run[q]}
    if len(scenes) != 1:
        raise DataFormatError(f"the per-scene histograms cover different numbers of scenes ({sorted(scenes)}); "
                              "compare runs of the same --split/--scenes.")
    n = scenes.pop()
    if n < 2:
        raise DataFormatError(f"a paired interval needs at least 2 scenes; the runs have {n}.")
    everything = np.ones((1, n))
    weights = np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=resamples).astype(np.float64)

    def mean_over_seeds(runs: Sequence[SceneCounts], w: np.ndarray) -> np.ndarray:
        return np.mean([realism_deviation_draws(run, w) for run in runs], axis=0)

    x0, y0 = float(mean_over_seeds(before, everything)[0]), float(mean_over_seeds(after, everything)[0])
    if not x0 > 0:
        raise DataFormatError(f"the first evaluation's realism deviation is {x0}; a relative change needs it > 0.")
    x, y = mean_over_seeds(before, weights), mean_over_seeds(after, weights)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0)
    changes = y[ok] / x[ok] - 1.0
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(changes, [tail, 1.0 - tail])
    return ChangeInterval(before=x0, after=y0, change=y0 / x0 - 1.0, low=float(low), high=float(high), level=level,
                          scenes=n, resamples=int(ok.sum()))


@dataclass(frozen=True)
class DifferenceInterval:
    """The absolute difference of a scene-averaged score between two evaluations of the same scenes, with a
    paired bootstrap interval over scenes, and the head-to-head share of scenes where the second is higher."""

    before: float
    after: float
    difference: float
    low: float
    high: float
    level: float
    scenes: int
    resamples: int
    win_share: float
    """Share of the shared scenes where ``after`` is higher (ties count half)."""


def paired_difference_interval(before: dict[str, tuple[int, float]], after: dict[str, tuple[int, float]],
                               level: float = 0.95, resamples: int = 10_000, seed: int = 0) -> DifferenceInterval:
    """``mean(after) - mean(before)`` over the scenes present in both, with a percentile interval from
    ``resamples`` paired bootstrap draws of the scenes, and the head-to-head share (for higher-is-better scores
    such as the realism meta-metric). ``before``/``after``: as returned by :func:`pooled_per_scene`."""
    _check_bootstrap(level, resamples)
    scenes = sorted(s for s in before if s in after)
    if len(scenes) < 2:
        raise DataFormatError(f"the two evaluations share {len(scenes)} scene(s) with a value; a paired interval "
                              "needs at least 2. Compare runs of the same --split/--scenes.")
    x = np.array([before[s][1] for s in scenes], dtype=np.float64)
    y = np.array([after[s][1] for s in scenes], dtype=np.float64)
    draws = np.random.default_rng(seed).integers(0, len(scenes), size=(resamples, len(scenes)))
    differences = (y[draws] - x[draws]).mean(1)
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(differences, [tail, 1.0 - tail])
    wins = float(((y > x) + 0.5 * (y == x)).mean())
    return DifferenceInterval(before=float(x.mean()), after=float(y.mean()), difference=float((y - x).mean()),
                              low=float(low), high=float(high), level=level, scenes=len(scenes),
                              resamples=resamples, win_share=wins)
