"""Realism deviation: Wasserstein-1 distance between histograms of kinematic quantities of simulated and logged
agents over the same scenes and window.

Preset ``ctg`` reproduces CTG's ``parse_scene_edit_results.py --estimate_dist`` pipeline (facts in
shared/reference/upstream-models-and-metrics.md §2.5): positions down-sampled to a 0.5 s step; velocity,
acceleration and jerk by first differences whose first element is linearly extrapolated (so the first two
accelerations are 0); longitudinal/lateral acceleration = |a| cos(yaw) and |a| sin(yaw) with the *world* yaw
(an upstream quirk); jerk = d|a|/dt; 20 bins on [-2, 2] m/s^2 and [-1, 1] m/s^3 that drop values outside;
agents slower than 0.5 m/s at the start masked; per-scene normalized histograms averaged over scenes.

Preset ``body`` keeps the sampling, bins and masks but decomposes the acceleration vector in the vehicle's own
frame (longitudinal along the heading, lateral across it), takes jerk as the derivative of the longitudinal
acceleration, and drops the extrapolated first samples instead of zero-filling them.

Beside the three-quantity mean, each preset reports ``realism_<preset>_speed``: the same distance between speed
histograms on 0-20 m/s (1 m/s bins; CTG's own velocity bins, 0-4 m/s, see almost none of nuScenes' driving).
It is not part of the mean (the paper's deviation has three quantities), but it is the one that sees traffic
stop: agents standing still add accelerations and jerks near 0, the log's most common values, so a model can
lower the three-quantity deviation by stopping, while its speed histogram moves away from the log's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from trafficrlhf_sdk.metrics.base import Metric, MetricResult
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.simulator import Rollout

__all__ = [
    "PACE_SPEC",
    "HistogramSpec",
    "RealismMetric",
    "agent_kinematics",
    "grouped_counts",
    "grouped_histogram",
    "histogram_distance",
    "kinematics",
    "scene_histogram",
    "scene_normalized",
]

Preset = Literal["ctg", "body"]
QUANTITIES = ("lon_acc", "lat_acc", "jerk")


@dataclass(frozen=True)
class HistogramSpec:
    """Bins of one quantity: ``num_bins`` equal bins on ``[low, high]`` (values outside are dropped)."""

    low: float
    high: float
    num_bins: int = 20

    @property
    def edges(self) -> torch.Tensor:
        """The ``num_bins + 1`` bin edges."""
        return torch.linspace(self.low, self.high, self.num_bins + 1, dtype=torch.float64)


SPECS = {
    "speed": HistogramSpec(0.0, 4.0),
    "lon_acc": HistogramSpec(-2.0, 2.0),
    "lat_acc": HistogramSpec(-2.0, 2.0),
    "jerk": HistogramSpec(-1.0, 1.0),
}
PACE_SPEC = HistogramSpec(0.0, 20.0)  # speed (m/s) for realism_<preset>_speed; nuScenes' 95th percentile: 12.7
STAT_DT = 0.5  # s, CTG's STAT_DT


def _diff_extrapolated(x: torch.Tensor) -> torch.Tensor:
    """``np.diff(x, prepend=x0 - (x1 - x0))`` along dim 1 of ``(N, K, ...)``: element 0 repeats element 1."""
    d = x[:, 1:] - x[:, :-1]
    return torch.cat([d[:, :1], d], 1)


def kinematics(scenario: ScenarioTensor,
               preset: Preset = "ctg") -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """Kinematic quantities of every agent at the statistics step (0.5 s).

    Args:
        scenario: a window of steps ``(B, A, T)`` at ``scenario.dt``.
        preset: ``"ctg"`` or ``"body"`` (module docstring).

    Returns:
        (quantities, sample_valid, moving): quantities maps ``speed`` (m/s), ``lon_acc``, ``lat_acc`` (m/s^2),
        ``jerk`` (m/s^3) to ``(B, A, K)`` tensors; ``sample_valid (B, A, K)`` marks samples whose inputs are all
        valid; ``moving (B, A)`` marks agents faster than 0.5 m/s at the first sample.
    """
    b, a = scenario.num_scenes, scenario.num_agents
    quantities, sample_valid, moving = agent_kinematics(
        scenario.xy.flatten(0, 1), scenario.yaw.flatten(0, 1), scenario.valid.flatten(0, 1), scenario.dt, preset
    )
    unflatten = lambda t: t.reshape(b, a, *t.shape[1:])  # noqa: E731
    return {k: unflatten(v) for k, v in quantities.items()}, unflatten(sample_valid), unflatten(moving)


def agent_kinematics(
    xy: torch.Tensor, yaw: torch.Tensor, valid: torch.Tensor, dt: float, preset: Preset = "ctg"
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """:func:`kinematics` for a flat list of N agent tracks: ``xy (N, T, 2)``, ``yaw (N, T)``, ``valid (N, T)``
    at step ``dt`` (s); returns quantities and ``sample_valid`` of shape ``(N, K)`` and ``moving (N,)``."""
    stride = max(1, round(STAT_DT / dt))
    dt = stride * dt
    pos = xy[:, ::stride].double()
    yaw = yaw[:, ::stride].double()
    valid = valid[:, ::stride]
    if pos.shape[1] < 3:
        raise ValueError(f"realism needs at least 3 samples at {dt} s; the window has {pos.shape[1]}.")
    if preset == "ctg":
        vel = _diff_extrapolated(pos) / dt
        acc = _diff_extrapolated(vel) / dt
        acc_norm = torch.linalg.vector_norm(acc, dim=-1)
        quantities = {
            "speed": torch.linalg.vector_norm(vel, dim=-1),
            "lon_acc": acc_norm * torch.cos(yaw),
            "lat_acc": acc_norm * torch.sin(yaw),
            "jerk": _diff_extrapolated(acc_norm) / dt,
        }
        # every quantity at k reads positions k-3..k (k+1 for the extrapolated first samples)
        padded = torch.cat([valid[:, 1:2].expand(-1, 3), valid], 1)
        sample_valid = padded[:, 3:] & padded[:, 2:-1] & padded[:, 1:-2] & padded[:, :-3]
        sample_valid[:, 0] &= valid[:, 1]
        moving = quantities["speed"][:, 0] > 0.5
    elif preset == "body":
        vel = torch.nn.functional.pad((pos[:, 1:] - pos[:, :-1]) / dt, (0, 0, 1, 0))
        acc = torch.nn.functional.pad((vel[:, 1:] - vel[:, :-1]) / dt, (0, 0, 1, 0))
        heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
        normal = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)
        lon = (acc * heading).sum(-1)
        quantities = {
            "speed": torch.linalg.vector_norm(vel, dim=-1),
            "lon_acc": lon,
            "lat_acc": (acc * normal).sum(-1),
            "jerk": torch.nn.functional.pad((lon[:, 1:] - lon[:, :-1]) / dt, (1, 0)),
        }
        run = valid.clone()
        for lag in (1, 2, 3):  # jerk at k reads positions k-3..k; earlier samples have no defined jerk
            run[:, lag:] &= valid[:, :-lag]
            run[:, :lag] = False
        sample_valid = run
        moving = quantities["speed"][:, 1] > 0.5
    else:
        raise ValueError(f"`preset` must be 'ctg' or 'body'; got {preset!r}.")
    return quantities, sample_valid, moving


def scene_histogram(values: torch.Tensor, mask: torch.Tensor, spec: HistogramSpec) -> torch.Tensor:
    """Scene-normalized histogram: each scene's counts over ``mask``-ed ``values (B, ...)`` divided by the
    scene's total (empty scenes give 0), then averaged over the B scenes; float64 ``(num_bins,)``."""
    b = values.shape[0]
    scene = torch.arange(b, device=values.device)[:, None].expand(b, values[0].numel()).reshape(-1)
    return grouped_histogram(values.reshape(-1), mask.reshape(-1), scene, b, spec)


def grouped_counts(
    values: torch.Tensor, mask: torch.Tensor, scene: torch.Tensor, num_scenes: int, spec: HistogramSpec
) -> torch.Tensor:
    """Bin counts of flat ``values (N,)`` with ``mask (N,)`` per scene ``scene (N,)`` (ints in
    ``[0, num_scenes)``): float64 ``(num_scenes, num_bins)``; values outside ``[low, high]`` are dropped."""
    flat = values.double()
    keep = mask & (flat >= spec.low) & (flat <= spec.high)
    index = ((flat - spec.low) / (spec.high - spec.low) * spec.num_bins).floor().long().clamp(0, spec.num_bins - 1)
    counts = torch.zeros(num_scenes * spec.num_bins, dtype=torch.float64, device=values.device)
    counts.scatter_add_(0, (scene * spec.num_bins + index)[keep], torch.ones_like(flat[keep]))
    return counts.reshape(num_scenes, spec.num_bins)


def scene_normalized(counts: torch.Tensor) -> torch.Tensor:
    """Each row of ``counts (..., num_scenes, num_bins)`` divided by its total (empty scenes stay 0), averaged
    over scenes: ``(..., num_bins)``. This is how the realism histograms weigh scenes (module docstring)."""
    totals = counts.sum(-1, keepdim=True)
    per_scene = torch.where(totals > 0, counts / totals.clamp_min(1), torch.zeros_like(counts))
    return per_scene.sum(-2) / max(counts.shape[-2], 1)


def grouped_histogram(
    values: torch.Tensor, mask: torch.Tensor, scene: torch.Tensor, num_scenes: int, spec: HistogramSpec
) -> torch.Tensor:
    """:func:`scene_histogram` for flat ``values (N,)`` with ``mask (N,)`` belonging to scenes ``scene (N,)``
    (ints in ``[0, num_scenes)``); scenes without values count as empty."""
    return scene_normalized(grouped_counts(values, mask, scene, num_scenes, spec))


def histogram_distance(reference: torch.Tensor, other: torch.Tensor, spec: HistogramSpec) -> float:
    """Wasserstein-1 distance between two histograms on the same bins, each renormalized to sum 1.

    Equal to ``scipy.stats.wasserstein_distance(centres, centres, reference, other)``; NaN if either is empty.
    """
    if reference.sum() <= 0 or other.sum() <= 0:
        return float("nan")
    cdf_gap = torch.cumsum(reference / reference.sum() - other / other.sum(), 0)[:-1]
    width = (spec.high - spec.low) / spec.num_bins
    return float(cdf_gap.abs().sum() * width)


class RealismMetric(Metric):
    """Realism deviation of the simulated controlled agents against the logged ones (lower is better)."""

    def __init__(self, preset: Preset = "ctg") -> None:
        if preset not in ("ctg", "body"):
            raise ValueError(f"`preset` must be 'ctg' or 'body'; got {preset!r}.")
        self.preset = preset
        self.name = f"realism_{preset}"  # type: ignore[misc]

    def scene_counts(self, window: ScenarioTensor, controlled: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-scene bin counts ``(B, num_bins)`` of every quantity for the controlled, moving agents of
        ``window`` on :data:`SPECS`, and ``pace``: speed on :data:`PACE_SPEC`."""
        scene, agent = controlled.nonzero(as_tuple=True)  # only controlled agents count: skip padding early
        quantities, sample_valid, moving = agent_kinematics(
            window.xy[scene, agent], window.yaw[scene, agent], window.valid[scene, agent], window.dt, self.preset
        )
        mask = (sample_valid & moving[:, None]).reshape(-1)
        per_sample_scene = scene[:, None].expand_as(sample_valid).reshape(-1)
        counts = {
            name: grouped_counts(values.reshape(-1), mask, per_sample_scene, window.num_scenes, SPECS[name])
            for name, values in quantities.items()
        }
        counts["pace"] = grouped_counts(quantities["speed"].reshape(-1), mask, per_sample_scene, window.num_scenes,
                                        PACE_SPEC)
        return counts

    def histograms(self, window: ScenarioTensor, controlled: torch.Tensor) -> dict[str, torch.Tensor]:
        """Scene-normalized histograms ``(num_bins,)`` of :meth:`scene_counts`."""
        return {name: scene_normalized(counts) for name, counts in self.scene_counts(window, controlled).items()}

    def compute(self, rollout: Rollout) -> MetricResult:
        """``realism_<preset>`` (mean of the three distances), each quantity's distance, and
        ``realism_<preset>_speed`` (speed histograms, m/s; not in the mean). Extras: the histograms, and
        ``scene_counts[side][quantity]`` ``(B, num_bins)`` for a bootstrap over scenes."""
        counts = {side: self.scene_counts(rollout.window(side), rollout.controlled) for side in ("simulated", "logged")}
        simulated = {name: scene_normalized(c) for name, c in counts["simulated"].items()}
        logged = {name: scene_normalized(c) for name, c in counts["logged"].items()}
        distances = {q: histogram_distance(logged[q], simulated[q], SPECS[q]) for q in QUANTITIES}
        values = {f"{self.name}_{q}": d for q, d in distances.items()}
        values[self.name] = sum(distances.values()) / len(distances)
        values[f"{self.name}_speed"] = histogram_distance(logged["pace"], simulated["pace"], PACE_SPEC)
        return MetricResult(values=values, extras={"simulated": simulated, "logged": logged, "specs": SPECS,
                                                          "scene_counts": counts})
