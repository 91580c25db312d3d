"""What the paper publishes, and how a measured change is compared with it.

**Source:** Y. Cao, B. Ivanovic, C. Xiao, M. Pavone, "Reinforcement Learning with Human Feedback for Realistic
Traffic Simulation", ICRA 2024, arXiv 2309.00709 (:data:`SOURCE`), Tables 1-4 as printed there
(:data:`PUBLISHED`: each comparison's "without" and "with RM" values of the paper's realism, failure rate and
reward cost). The paper's models are the full-size upstream CTG, BITS and TrafficGen, its feedback came from
people, its realism values are on another scale (0.36-1.68 against about 0.08 here: another histogram range or
normalisation) and its CTG fails more from the start (0.271 under `no_collision` against about 0.10 here), so
only **relative changes** are compared, never absolute values. Figure 3 prints no number.

The **direction** the method claims or optimises (:data:`EXPECTED`) decides "reproduced": aligning with a reward
model learned from human preferences makes scenarios more realistic (a lower realism deviation), and PPO maximises
that reward, so the reward cost should fall. The paper makes no general claim about the failure rate, although
its tables show it falling; no direction is claimed for it here, and its change is printed beside the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["EXPECTED", "PUBLISHED", "SOURCE", "Expectation", "compare_change", "published_change"]

SOURCE = ("Cao, Ivanovic, Xiao, Pavone: Reinforcement Learning with Human Feedback for Realistic Traffic "
          "Simulation, ICRA 2024, arXiv 2309.00709")


def _pair(table: str, real: tuple[float, float], fail: tuple[float, float],
          cost: tuple[float, float] | None = None) -> dict[str, Any]:
    values: dict[str, Any] = {"table": table, "realism_ctg": real, "failure_rate": fail}
    if cost is not None:
        values["reward_cost"] = cost
    return values


_CTG = ((0.569, 0.376), (0.271, 0.054), (13.21, 3.7))  # CTG -> CTG + RM under no collision (Tables 1-3)
PUBLISHED: dict[str, dict[str, Any]] = {
    # Table 1: CTG and CTG + RM under CTG's five guidances (realism, failure; no reward cost printed)
    "speed_limit: CTG → CTG + RM": _pair("Table 1", (0.359, 0.361), (0.165, 0.152)),
    "target_speed: CTG → CTG + RM": _pair("Table 1", (0.855, 0.732), (0.179, 0.156)),
    "no_collision: CTG → CTG + RM": _pair("Table 1", *_CTG[:2]),
    "no_offroad: CTG → CTG + RM": _pair("Table 1", (0.501, 0.392), (0.455, 0.214)),
    "goal_waypoint: CTG → CTG + RM": _pair("Table 1", (0.564, 0.734), (0.387, 0.341)),
    # Table 2: the CTG-trained reward model aligning each model (no collision)
    "CTG: without → with RM": _pair("Table 2", *_CTG),
    "BITS: without → with RM": _pair("Table 2", (1.220, 0.83), (0.314, 0.23), (12.4, 9.5)),
    "TrafficGen: without → with RM": _pair("Table 2", (1.683, 1.173), (0.39, 0.22), (15.2, 11.3)),
    # Table 3: which part of CTG is fine-tuned
    "CTG → CTG + RM (encoder)": _pair("Table 3", (0.569, 0.432), (0.271, 0.176), (13.21, 9.1)),
    "CTG → CTG + RM (decoder)": _pair("Table 3", (0.569, 0.391), (0.271, 0.102), (13.21, 5.2)),
    "CTG → CTG + RM (full)": _pair("Table 3", *_CTG),
    # Table 4: reward-model backbone, feedback on CTG candidates (this project's Table 4 labels one mixed set)
    "BITS → + RM (CTG encoder)": _pair("Table 4", (1.22, 0.83), (0.314, 0.23)),
    "BITS → + RM (TrafficGen encoder)": _pair("Table 4", (1.22, 0.81), (0.314, 0.25)),
    "TrafficGen → + RM (CTG encoder)": _pair("Table 4", (1.683, 1.173), (0.39, 0.22)),
    "TrafficGen → + RM (TrafficGen encoder)": _pair("Table 4", (1.683, 0.83), (0.39, 0.12)),
}
"""The paper's values by comparison label (as the experiments name their comparisons): ``table`` and, per metric
key, ``(without RM, with RM)``. The paper's single realism value is filed under ``realism_ctg``, the deviation in
its definition."""


def published_change(comparison: str, metric: str) -> float | None:
    """The paper's relative change ``(with - without) / without`` of ``metric`` in ``comparison``, or None where the
    paper prints no such pair."""
    pair = PUBLISHED.get(comparison, {}).get(metric)
    if pair is None or not pair[0]:
        return None
    return (pair[1] - pair[0]) / abs(pair[0])


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
    "failure_rate": Expectation(0, "no general claim (the paper's tables show it falling; printed beside)"),
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
