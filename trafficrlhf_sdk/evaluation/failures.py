"""Closed-loop failures drawn over the log: where and when each controlled agent first collides or leaves the road."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from trafficrlhf_sdk.metrics.failure import FailureMetric
from trafficrlhf_sdk.simulation.simulator import Rollout

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["FirstFailures", "first_failures", "render_failures", "save_failure_png"]


@dataclass(frozen=True)
class FirstFailures:
    """Per controlled agent, the first simulated step with a failure (the failure metric's definition).

    Fields (all ``(B, A)``): ``step``: absolute time index into ``rollout.simulated`` (-1: never fails);
    ``collision`` / ``offroad``: which kind(s) occur at that step.
    """

    step: torch.Tensor
    collision: torch.Tensor
    offroad: torch.Tensor


def first_failures(rollout: Rollout) -> FirstFailures:
    """First failure of every controlled agent of ``rollout`` over steps ``start_index+1 .. end_index``, by the
    failure metric's own per-step flags (box overlap, centre off the drivable layer)."""
    first = rollout.start_index + 1
    extras = FailureMetric().compute(rollout).extras
    collided, offroad = extras["collision_steps"], extras["offroad_steps"]
    failing = (collided | offroad) & rollout.controlled[..., None]  # (B, A, T)
    ever = failing.any(-1)
    index = failing.int().argmax(-1)  # first True (0 where none; masked below)
    at = index[..., None]
    return FirstFailures(
        step=torch.where(ever, index + first, torch.full_like(index, -1)),
        collision=collided.gather(-1, at)[..., 0] & ever,
        offroad=offroad.gather(-1, at)[..., 0] & ever,
    )


def save_failure_png(rollout: Rollout, index: int, path: str | os.PathLike[str], dpi: int = 110,
                     failures: FirstFailures | None = None) -> str:
    """Write :func:`render_failures` of scene ``index`` of ``rollout`` as a PNG at ``path``; returns the path."""
    fig = render_failures(rollout, index, failures)
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png", facecolor="white")
    return path


def render_failures(rollout: Rollout, index: int, failures: FirstFailures | None = None) -> Figure:
    """Scene ``index`` of ``rollout``: the log (filled boxes, trails) with the simulated trajectories and boxes
    (outlined) at the scene's first failure step (the last step if nothing fails); every failing agent is marked
    where it first fails (x: collision, o: off-road) and the title says who failed how and when."""
    from trafficrlhf_sdk.render import short_id, render_scene

    failures = failures or first_failures(rollout)
    steps, scene = failures.step[index], rollout.logged
    failed = (steps >= 0).nonzero()[:, 0].tolist()
    step = min((int(steps[a]) for a in failed), default=rollout.end_index)
    ids = scene.agent_ids[index] if scene.agent_ids else tuple(str(a) for a in range(scene.num_agents))
    name = scene.scene_ids[index] if scene.scene_ids and scene.scene_ids[index] else f"scene {index}"
    controlled = int(rollout.controlled[index].sum())
    fig = render_scene(scene, index, step=step, sim_states=rollout.simulated, show_ids=True, title="")
    ax = fig.axes[0]
    lines = []
    for a in sorted(failed, key=lambda a: int(steps[a])):
        x, y = rollout.simulated.states[index, a, int(steps[a]), :2].tolist()
        kinds = [k for k, flag in (("collision", failures.collision), ("off-road", failures.offroad))
                 if bool(flag[index, a])]
        ax.plot([x], [y], marker="x" if "collision" in kinds else "o", markersize=11, markeredgewidth=2.4,
                color="#d62728", markerfacecolor="none", zorder=9)
        t = (int(steps[a]) - rollout.start_index) * scene.dt
        lines.append(f"{short_id(ids[a] or str(a))}: {' + '.join(kinds)} at +{t:.1f} s")
    shown = "; ".join(lines[:3]) + (f"; {len(lines) - 3} more" if len(lines) > 3 else "")
    t_step = (step - rollout.start_index) * scene.dt
    ax.set_title(f"{name}: {len(failed)} of {controlled} controlled agents fail"
                 + (f" ({shown})" if shown else "") + f"\nshown at +{t_step:.1f} s of the closed loop "
                 "(purple: simulated; filled boxes and dashed trails: the log)", fontsize=9)
    return fig
