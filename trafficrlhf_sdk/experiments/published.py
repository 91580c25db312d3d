"""What the paper publishes, as far as a source available to this repository shows it, and how a measured change is
compared with it.

**Source:** Y. Cao, B. Ivanovic, C. Xiao, M. Pavone, "Reinforcement Learning with Human Feedback for Realistic
Traffic Simulation", ICRA 2024, arXiv 2309.00709 (:data:`SOURCE`). No copy of the paper's tables or of its
Figure 3 could be read from the sources searched for this module (the arXiv abstract page, the NVIDIA research
page and third-party paper indexes carry the abstract only), so :data:`PUBLISHED` holds **no number**. A number
is added here only with the place it was read from; none is ever estimated.

What can be justified instead is the **direction** the paper's method claims or optimises
(:data:`EXPECTED`): its abstract states that aligning a traffic model with a reward model learned from human
preferences makes its scenarios more realistic (a lower realism deviation), and PPO maximises that reward model's
reward, so its reward cost, the paper's sum of (1 - r_t) / 2 over 2 Hz steps, should fall. The abstract states
nothing about the failure rate, so no direction is claimed for it; the tables report its change all the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["EXPECTED", "PUBLISHED", "SOURCE", "Expectation", "compare_change"]

SOURCE = ("Cao, Ivanovic, Xiao, Pavone: Reinforcement Learning with Human Feedback for Realistic Traffic "
          "Simulation, ICRA 2024, arXiv 2309.00709")

PUBLISHED: dict[str, dict[str, Any]] = {}
"""Numbers of the paper's tables and figure by table id, each with the place it was read from; empty: none of them
could be read from a source available to this repository (see the module docstring)."""


@dataclass(frozen=True)
class Expectation:
    """The direction of change the paper's method claims or optimises for one metric, and why.

    Fields: direction -1 (the metric should fall with the reward model), +1 (rise) or 0 (no claim); basis: where
    the direction comes from.
    """

    direction: int
    basis: str


EXPECTED: dict[str, Expectation] = {
    "realism_ctg": Expectation(-1, "abstract of arXiv 2309.00709: alignment with human feedback makes traffic "
                                   "more realistic"),
    "realism_body": Expectation(-1, "as realism_ctg (the same deviation measured in each agent's frame)"),
    "realism_meta": Expectation(+1, "as realism_ctg (the WOSAC meta-metric: higher is more realistic)"),
    "reward_cost": Expectation(-1, "the objective: PPO maximises the reward model's reward"),
    "failure_rate": Expectation(0, "no claim in a source available here"),
}


def compare_change(metric: str, base: float | None, aligned: float | None) -> dict[str, Any]:
    """The change from ``base`` to ``aligned`` of ``metric`` against :data:`EXPECTED`.

    Returns ``change`` (aligned - base), ``relative`` (change / |base|, None for a zero or missing base),
    ``expected`` (-1, +1, 0) and ``agrees``: True or False where a direction is expected and both values exist
    (a change of exactly 0 does not agree), None otherwise.
    """
    expectation = EXPECTED.get(metric, Expectation(0, "no claim"))
    if base is None or aligned is None:
        return {"change": None, "relative": None, "expected": expectation.direction, "agrees": None}
    change = aligned - base
    relative = change / abs(base) if base else None
    agrees = None if expectation.direction == 0 else (change * expectation.direction > 0)
    return {"change": change, "relative": relative, "expected": expectation.direction, "agrees": agrees}
