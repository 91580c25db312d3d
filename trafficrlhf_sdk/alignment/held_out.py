"""Closed-loop evaluation of the model being aligned on held-out training scenes, and keeping the best weights.

The stage-III analogue of stable-baselines3's ``EvalCallback``: every ``eval_every`` epochs the current model
drives the scenes ``holdout_every`` keeps out of training (10 s, 2 Hz replanning, the run's guidance), for
``eval_seeds`` sampling seeds, and the failure rate lands in the history. With ``keep_best`` the run ends with the
evaluated weights of the lowest held-out failure rate. Why: PPO against a failure reward does not settle; the
closed-loop failure rate of consecutive checkpoints of one run moved by 0.04 (TrafficGen, held-out scenes), as
much as the gap between settings, so the last epoch's weights are a draw from that spread.

Evaluation never touches the training randomness: torch's global RNG state and the adapter's sampling seed are
restored afterwards, so a run with evaluation trains exactly as one without.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from trafficrlhf_sdk.alignment.config import AlignConfig
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["EVAL_KEYS", "HeldOutEvaluator"]

EVAL_KEYS = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body")
"""Metrics recorded per evaluation, as ``eval_<key>`` in the history (mean over the evaluation seeds)."""


class HeldOutEvaluator:
    """Evaluates ``model`` in closed loop on held-out scenes and remembers the best weights.

    Args:
        model: the adapter being aligned (a :class:`~trafficrlhf_sdk.simulation.policies.ClosedLoopPolicy`
            with ``module`` and ``options``).
        config: the run's :class:`AlignConfig` (``eval_every``, ``eval_seeds``, ``guidance``).
        scenes: a callable returning the held-out scenes as one batch ``(B, A, T)``, loaded on first use.
        guidance: the guidance the model drives with (None: the adapter's own).
    """

    def __init__(self, model: Any, config: AlignConfig, scenes: Callable[[], ScenarioTensor],
                 guidance: GuidanceSet | None) -> None:
        self.model = model
        self.config = config
        self._load_scenes = scenes
        self._scenes: ScenarioTensor | None = None
        self.guidance = guidance
        self.best_failure_rate = float("inf")
        self.best_epoch: int | None = None
        self.best_state: dict[str, torch.Tensor] | None = None

    def due(self, epochs_done: int) -> bool:
        """Whether an evaluation follows epoch ``epochs_done`` (every ``eval_every``, and after the last)."""
        every = self.config.eval_every
        return every is not None and (epochs_done % every == 0 or epochs_done == self.config.epochs)

    def evaluate(self) -> dict[str, float]:
        """``{"eval_<key>": value}`` for :data:`EVAL_KEYS`, each the mean over seeds ``0 .. eval_seeds - 1``."""
        from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy

        if self._scenes is None:
            self._scenes = self._load_scenes()
        scenario = self._scenes
        rng = torch.get_rng_state()
        options = getattr(self.model, "options", None)
        saved_guidance = getattr(self.model, "guidance", None)
        totals = dict.fromkeys(EVAL_KEYS, 0.0)
        try:
            if self.guidance is not None:
                self.model.guidance = self.guidance
            for seed in range(self.config.eval_seeds):
                if options is not None and "seed" in type(options).model_fields:
                    self.model.options = options.model_copy(update={"seed": seed})
                config = EvaluationConfig(batch_size=50, seed=seed,
                                          metrics=("failure", "realism_ctg", "realism_body"))
                with torch.no_grad():
                    values = evaluate_policy(self.model, scenario, config).values
                for key in EVAL_KEYS:
                    totals[key] += values[key] / self.config.eval_seeds
        finally:
            if options is not None:
                self.model.options = options
            if self.guidance is not None:
                self.model.guidance = saved_guidance
            torch.set_rng_state(rng)
        return {f"eval_{key}": value for key, value in totals.items()}

    def update_best(self, epochs_done: int, failure_rate: float) -> bool:
        """Remember the current weights if ``failure_rate`` is the lowest so far (ties: the later epoch)."""
        if failure_rate <= self.best_failure_rate:
            self.best_failure_rate, self.best_epoch = failure_rate, epochs_done
            self.best_state = {k: v.detach().clone() for k, v in self.model.module.state_dict().items()}
            return True
        return False

    def restore_best(self) -> int:
        """Load the remembered best weights into the model; returns their epoch."""
        if self.best_state is None or self.best_epoch is None:
            raise TrafficRLHFError("no held-out evaluation has run yet, so there are no best weights to restore; "
                                   "set `eval_every`.")
        self.model.module.load_state_dict(self.best_state)
        return self.best_epoch

    def state(self) -> dict[str, Any]:
        """JSON-able bookkeeping for checkpoints (the weights themselves go to ``best/``)."""
        return {"best_epoch": self.best_epoch, "best_failure_rate": self.best_failure_rate}
