"""Over-optimization monitoring: the proxy reward next to judgments the policy never trains on.

A policy optimized against a learned reward model can raise the proxy reward while getting worse by any other
measure (Gao, Schulman and Hilton 2022). Every epoch the fine-tuner therefore also samples a fixed set of contexts
from scenes it never trains on (the ``holdout_every`` scenes when set): logged windows, and windows cut shortly
before the failures of the starting model's closed-loop driving, where alignment is meant to act. They are drawn
once and sampled with the same random numbers every epoch, so the curve moves with the policy and not with the
draw. The samples are scored with

- the stand-in annotators' realism judgment (:func:`~trafficrlhf_sdk.feedback.judgment.judge_scenarios`,
  profile ``attentive``), which the reward model only saw through noisy choices, and
- optionally a second reward model trained on other annotators' labels,

records both in the history (``heldout_realism``, ``heldout_reward``), can stop early on the held-out curve and
draws ``overoptimization.png``.
"""

from __future__ import annotations

import os
from typing import Any

import torch

from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["HeldOutMonitor", "plot_overoptimization"]


class HeldOutMonitor:
    """Scores an epoch's sample scenarios with judgments the policy does not train on.

    Args:
        reward: an optional second reward model (``score(scenario) -> (B,)``), trained on other annotators.
        patience: stop once the smoothed held-out realism has not improved for this many epochs (None: never).
        smoothing: weight of the previous value in the exponential moving average of the held-out realism.
    """

    def __init__(self, reward: Any = None, patience: int | None = None, smoothing: float = 0.7) -> None:
        from trafficrlhf_sdk.feedback.synthetic import PROFILES

        self.config = PROFILES["attentive"]
        self.reward = reward
        self.patience = patience
        self.smoothing = smoothing
        self.smoothed: float | None = None
        self.best: tuple[float, int] | None = None  # (smoothed realism, epoch)
        self.best_state: dict[str, torch.Tensor] | None = None

    def scores(self, samples: ScenarioTensor, agents: torch.Tensor) -> dict[str, float]:
        """``heldout_realism`` (and ``heldout_reward``) of ``samples`` (windows whose ``current_index`` is the start
        of the sampled future, with the history before it) over ``agents (B, A)``."""
        from trafficrlhf_sdk.feedback.judgment import judge_scenarios

        with torch.no_grad():  # the judgment reads the samples' history and futures, never the logged future
            judgment = judge_scenarios(samples, agents, self.config)
            out = {"heldout_realism": float(judgment.realism.mean())}
            if self.reward is not None:
                out["heldout_reward"] = float(self.reward.score(samples).float().mean())
        return out

    def update(self, epoch: int, realism: float, params: list[torch.Tensor]) -> bool:
        """Record the held-out realism of the weights ``params`` that were scored, after ``epoch`` epochs of
        updates (0: the starting weights); keep the best weights; True when patience ran out."""
        self.smoothed = realism if self.smoothed is None else (self.smoothing * self.smoothed
                                                               + (1 - self.smoothing) * realism)
        if self.best is None or self.smoothed > self.best[0]:
            self.best = (self.smoothed, epoch)
            self.best_state = {str(i): p.detach().clone() for i, p in enumerate(params)}
            return False
        return self.patience is not None and epoch - self.best[1] >= self.patience

    def restore_best(self, params: list[torch.nn.Parameter]) -> int | None:
        """Put the best epoch's weights back into ``params``; returns that epoch (None if nothing was kept)."""
        if self.best is None or self.best_state is None:
            return None
        with torch.no_grad():
            for i, p in enumerate(params):
                p.copy_(self.best_state[str(i)])
        return self.best[1]


def plot_overoptimization(history: list[dict[str, float]], path: str) -> str:
    """PNG of the proxy reward and the held-out judgments per epoch (each on its own axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [row["epoch"] for row in history]
    fig, left = plt.subplots(figsize=(7, 3.4))
    left.plot(epochs, [row["reward_mean"] for row in history], color="tab:blue", label="proxy reward (trained on)")
    left.set(xlabel="epoch", ylabel="proxy reward")
    right = left.twinx()
    right.plot(epochs, [row.get("heldout_realism", float("nan")) for row in history], color="tab:orange",
               label="held-out realism (stand-in annotators)")
    if any("heldout_reward" in row for row in history):
        right.plot(epochs, [row.get("heldout_reward", float("nan")) for row in history], color="tab:green",
                   label="held-out reward model")
    right.set(ylabel="held-out judgment")
    handles = left.get_legend_handles_labels()[0] + right.get_legend_handles_labels()[0]
    left.legend(handles, [h.get_label() for h in handles], fontsize=7, loc="lower left")
    left.set_title("over-optimization monitor")
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
