"""How far could choosing among a model's own samples go? A diagnostic for alignment, not a traffic model.

At every replan the wrapped model draws ``--samples`` futures per agent (with its guidance), extends each to
``--lookahead`` steps at constant speed and heading, scores every agent's future with a hand-written reward
(``builtin:failure-margins`` by default: it reads the drivable map) and executes, per agent, the best one. The
planner sees only the simulated past, never the log's future; agents it does not control are left out of the
scored futures. Each agent's sample k is scored beside the other agents' sample k; with ``--best-response-rounds
N`` each agent then re-chooses, one after another, beside the others' current choices (N rounds of best
responses, a joint choice that sees the interactions the first one does not). The closed-loop failure rate of
this reward-selected policy estimates what fine-tuning towards the reward's preferred samples could reach at best
(a "best-of-N" ceiling), and how much of it the aligned model has already taken.

    python scripts/selection_ceiling.py --model ctg [--checkpoint DIR] --samples 8 --lookahead 40 --seed 0
"""

from __future__ import annotations

import argparse
import contextlib
import json
from collections.abc import Callable
from typing import Any

import torch

from trafficrlhf_sdk import get_scenario_source
from trafficrlhf_sdk.reward.loading import load_reward
from trafficrlhf_sdk.plugins import build_policy
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
from trafficrlhf_sdk.models.adapter import extend_constant_velocity
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan


class RewardSelectedPlanner:
    """A closed-loop policy: ``adapter``'s samples, the best per agent by ``reward.agent_scores``."""

    def __init__(self, adapter: Any, reward: Any, samples: int, lookahead: int, reward_history: int = 10,
                 best_response_rounds: int = 0) -> None:
        self.adapter, self.reward = adapter, reward
        self.samples, self.lookahead, self.reward_history = samples, lookahead, reward_history
        self.best_response_rounds = best_response_rounds

    def reset(self, scenario: ScenarioTensor) -> None:
        """Reset the wrapped adapter (guidance fit, sampling seed) on the logged scene."""
        self.adapter.reset(scenario)

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """``Plan`` of ``(B, A, horizon, 4)``: per agent the sample with the highest reward over the lookahead."""
        adapter = self.adapter
        hold = getattr(adapter, "_hold", None)  # the adapter's stationary rule, as its own plan() applies it
        with torch.enable_grad() if adapter.guidance is not None else torch.no_grad(), \
                hold.planning() if hold is not None else contextlib.nullcontext():
            out = adapter.sample(context, self.samples, adapter.guidance, adapter._generator)
        futures = out.futures.detach()  # (B, S, A, H, 4)
        b, s, a = futures.shape[:3]
        steps = max(self.lookahead, futures.shape[-2])
        scored = extend_constant_velocity(futures, steps, context.dt).to(context.states.dtype)
        scored = torch.cat([scored[..., :3], wrap_angle(scored[..., 3:])], -1)
        agents = out.trace.agents  # (B, A) sampled agents; the others have no known future here
        valid = agents[:, None, :, None].expand(b, s, a, steps)
        now = context.current_index
        history = context[torch.arange(b).repeat_interleave(s)].time_slice(max(0, now - self.reward_history), now + 1)

        def score(states: torch.Tensor) -> torch.Tensor:  # candidate scenes (B, S, A, steps, 4) -> (B, S, A)
            scene = history.replace_unchecked(
                states=torch.cat([history.states, (states * valid[..., None]).reshape(b * s, a, steps, 4)], 2),
                valid=torch.cat([history.valid, valid.reshape(b * s, a, steps)], 2))
            with torch.no_grad():
                return self.reward.agent_scores(scene).reshape(b, s, a)

        scores = score(scored)  # agent i's sample k beside the other agents' sample k
        if adapter.guidance is not None:  # among equal rewards, the lowest guidance loss (the adapter's own rule)
            loss = adapter.guidance.loss(futures, now, context).detach()
            scores = scores - 1e-4 * loss / (loss.abs().amax(1, keepdim=True) + 1e-9)
        choice = scores.argmax(1)
        if self.best_response_rounds:
            choice = best_responses(scored, agents, choice, score, self.best_response_rounds)
        index = choice[:, None, :, None, None].expand(-1, 1, -1, futures.shape[-2], 4)
        best = futures.gather(1, index)[:, 0]
        return Plan(extend_constant_velocity(best, horizon, context.dt).cpu())


def best_responses(scored: torch.Tensor, agents: torch.Tensor, choice: torch.Tensor,
                   score: Callable[[torch.Tensor], torch.Tensor], rounds: int) -> torch.Tensor:
    """Sequential best responses: each sampled agent in turn takes the sample with the highest score beside the
    other agents' current choices, for ``rounds`` passes over the agents.

    Args:
        scored: ``(B, S, A, T, 4)`` each agent's S candidate futures.
        agents: bool ``(B, A)``, the agents that choose.
        choice: ``(B, A)`` the starting choice (sample indices).
        score: maps candidate scenes ``(B, S, A, T, 4)`` to per-agent scores ``(B, S, A)``.
        rounds: passes over the agents.

    Returns ``(B, A)``: the choices; after enough rounds no agent gains by changing its own alone.
    """
    s, a = scored.shape[1:3]
    choice = choice.clone()
    index = torch.arange(s)
    for _ in range(rounds):
        for j in agents.any(0).nonzero().flatten().tolist():
            chosen = scored.gather(1, choice[:, None, :, None, None].expand(-1, 1, -1, *scored.shape[3:]))
            own = torch.arange(a) == j
            scenes = torch.where(own[None, None, :, None, None], scored, chosen)  # agent j varies, the rest chosen
            gain = score(scenes)[:, :, j]  # (B, S)
            best = gain.argmax(1)
            keep = gain.gather(1, choice[:, j:j + 1])[:, 0] >= gain.gather(1, best[:, None])[:, 0]  # ties: stay
            choice[:, j] = torch.where(agents[:, j] & ~keep, index[best], choice[:, j])
    return choice


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="ctg")
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--guidance", default="no_collision")
    parser.add_argument("--reward-model", default="builtin:failure-margins")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--lookahead", type=int, default=40, help="Steps each sample is scored over (0.1 s).")
    parser.add_argument("--split", default="val")
    parser.add_argument("--scenes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--best-response-rounds", type=int, default=0,
                        help="Passes in which each agent re-chooses beside the others' current choices.")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    adapter = build_policy(args.model, {"guidance": args.guidance, "checkpoint": args.checkpoint,
                                        "seed": args.seed})
    policy = RewardSelectedPlanner(adapter, load_reward(args.reward_model), args.samples, args.lookahead,
                                   best_response_rounds=args.best_response_rounds)
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids(args.split)[: args.scenes]
    report = evaluate_policy(policy, source.load_batch(args.split, scene_ids=ids),
                             EvaluationConfig(batch_size=50, seed=args.seed))
    keys = ("failure_rate", "collision_rate", "offroad_rate", "realism_ctg", "realism_body")
    print(json.dumps({"model": args.model, "checkpoint": args.checkpoint, "samples": args.samples,
                      "lookahead": args.lookahead, "seed": args.seed,
                      "best_response_rounds": args.best_response_rounds,
                      **{k: round(report.values[k], 4) for k in keys}}))


if __name__ == "__main__":
    main()
