"""Alignment (stage III of TrafficRLHF): PPO fine-tuning of any registered traffic model against a reward model.

- :func:`align`: one call, ``align(model, reward_model, alpha=0.3, **config) -> AlignResult(model, history)``.
- :class:`AlignConfig` + :class:`AlignTrainer`: the same with full control (checkpoints, resume, logging).
- :class:`AlignRecipe` + :func:`run_recipe`: one run as a TOML file (``trafficrlhf align --config``).
- :func:`average_checkpoints`: the weight average of several aligned runs (a model soup), e.g. training seeds.
- :func:`extrapolate_checkpoint`: base + factor x (aligned - base), past the aligned weights (ExPO) or back
  towards the base (WiSE-FT).
- :class:`TrafficRLHFEnv`: the closed-loop simulator as a Gymnasium environment with the reward model as reward,
  for stable-baselines3 agents (imported lazily: it needs ``gymnasium``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from trafficrlhf_sdk.lazy import lazy_exports

if TYPE_CHECKING:
    from trafficrlhf_sdk.alignment.trainer import AlignResult

# torch loads with the first name that needs it: reading and checking a recipe (AlignRecipe, AlignConfig) does not
_EXPORTS = {
    "PAPER_ALPHA": "config",
    "AlignConfig": "config",
    "paper_alpha": "config",
    "AlignRecipe": "recipe",
    "run_recipe": "recipe",
    "average_checkpoints": "averaging",
    "extrapolate_checkpoint": "averaging",
    "AlignResult": "trainer",
    "AlignTrainer": "trainer",
    "RewardLike": "trainer",
    "scenario_scores": "trainer",
    "TrafficRLHFEnv": "env",
}
__all__ = sorted([*_EXPORTS, "align"])
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


def align(model: Any, reward_model: Any, alpha: float | None = None, *, scenes: Any = None, reference: Any = None,
          callback: Callable[[int, dict[str, float]], bool | None] | None = None, **config: Any) -> AlignResult:
    """Fine-tune ``model`` (an adapter, or the name of a registered traffic model) against ``reward_model``.

    ``reward_model``: a reward model object, a saved reward-model folder, or ``"builtin:NAME"`` (a hand-written
    baseline). ``alpha`` weighs the PPO surrogate against the model's imitation loss; None takes the paper's
    value for the model (CTG 0.1, BITS 0.5, TrafficGen 0.3; 0.3 otherwise), as ``trafficrlhf align`` does. Every
    other :class:`AlignConfig` field can be passed as a keyword (e.g. ``epochs=70, guidance="no_collision",
    groups=("decoder",), output_dir="out/ctg"``). ``scenes`` replaces the source's training split; ``reference``
    the frozen model the KL terms hold the policy to (None: ``model`` as it starts). The adapter is updated in
    place and returned with the per-epoch history.
    """
    from trafficrlhf_sdk.alignment.config import AlignConfig, paper_alpha
    from trafficrlhf_sdk.alignment.trainer import AlignResult, AlignTrainer

    if isinstance(model, str):
        from trafficrlhf_sdk.plugins import get_traffic_model

        model = get_traffic_model(model)
    if isinstance(reward_model, str):
        from trafficrlhf_sdk.reward.loading import load_reward

        reward_model = load_reward(reward_model)
    if alpha is None:
        alpha = paper_alpha(str(getattr(model, "name", "") or ""))
    trainer = AlignTrainer(model, reward_model, AlignConfig(alpha=alpha, **config), scenes=scenes,
                           reference=reference)
    history = trainer.train(callback)
    return AlignResult(model, history)
