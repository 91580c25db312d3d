"""``scripts/selection_ceiling.py``: the reward-selected planner executes each agent's best sample."""

from __future__ import annotations


import pytest
import torch

from trafficrlhf_sdk.scenario import ScenarioTensor

gru = pytest.importorskip("trafficrlhf_example_gru")
class SlowestReward:
    """Per agent: minus its speed at the last scored step (prefers the slowest sample)."""

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        return -scenario.states[:, :, -1, 2] * scenario.controlled


def test_planner_executes_each_agents_best_sample(nuscenes_source, load_script) -> None:  # type: ignore[no-untyped-def]
    scene = nuscenes_source.load_batch("train", 2).replace_unchecked(current_index=30)
    context = scene.time_slice(0, 31)
    torch.manual_seed(0)
    adapter = gru.ExampleGRUAdapter()
    planner = load_script("selection_ceiling").RewardSelectedPlanner(adapter, SlowestReward(), samples=4, lookahead=30)
    planner.reset(scene)
    state = adapter._generator.get_state()
    plan = planner.plan(context, 20)
    adapter._generator.set_state(state)  # the same draw again, by hand
    with torch.no_grad():
        out = adapter.sample(context, 4, None, adapter._generator)
    futures, agents = out.futures, out.trace.agents
    # extended at constant speed, the last speed is the sample's last speed: the slowest sample wins
    best = futures[..., -1, 2].argmin(1)  # (B, A)
    assert plan.states.shape == (2, context.num_agents, 20, 4)
    for b, a in agents.nonzero().tolist():
        assert torch.allclose(plan.states[b, a], futures[b, best[b, a], a, :20])


def _crowding_score(targets: torch.Tensor):  # type: ignore[no-untyped-def]
    """Per agent: -(x - target)^2, minus 5 for every other agent within 1 m (a potential game)."""
    def score(scenes: torch.Tensor) -> torch.Tensor:  # (B, S, A, T, 4) -> (B, S, A)
        x = scenes[..., -1, 0]
        close = ((x[..., :, None] - x[..., None, :]).abs() < 1.0).float()
        close = close - torch.diag_embed(torch.diagonal(close, dim1=-2, dim2=-1))
        return -(x - targets[:, None]) ** 2 - 5.0 * close.sum(-1)
    return score


@pytest.mark.parametrize("seed", range(5))
def test_best_responses_end_where_no_agent_gains_alone(load_script, seed: int) -> None:  # type: ignore[no-untyped-def]
    best_responses = load_script("selection_ceiling").best_responses
    generator = torch.Generator().manual_seed(seed)
    b, s, a = 3, 6, 4
    scored = torch.zeros(b, s, a, 2, 4)
    scored[..., 0] = torch.rand(b, s, a, 1, generator=generator) * 4  # x of every candidate, both steps
    agents = torch.rand(b, a, generator=generator) > 0.2
    targets = torch.full((b, a), 2.0)  # every agent wants the same spot: they must spread out
    score = _crowding_score(targets)
    start = torch.zeros(b, a, dtype=torch.long)
    assert torch.equal(best_responses(scored, agents, start, score, rounds=0), start)
    choice = best_responses(scored, agents, start, score, rounds=30)
    assert torch.equal(choice[~agents], start[~agents])  # agents that do not choose keep their sample
    for j in range(a):  # no agent can raise its own score by changing its sample alone
        chosen = scored.gather(1, choice[:, None, :, None, None].expand(-1, 1, -1, 2, 4))
        own = torch.arange(a) == j
        gain = score(torch.where(own[None, None, :, None, None], scored, chosen))[:, :, j]
        current = gain.gather(1, choice[:, j:j + 1])[:, 0]
        assert torch.all(~agents[:, j] | (current >= gain.amax(1) - 1e-9))


def test_best_responses_keep_an_interaction_free_choice(nuscenes_source, load_script) -> None:  # type: ignore[no-untyped-def]
    scene = nuscenes_source.load_batch("train", 2).replace_unchecked(current_index=30)
    context = scene.time_slice(0, 31)
    module = load_script("selection_ceiling")
    plans = []
    for rounds in (0, 2):
        torch.manual_seed(0)
        planner = module.RewardSelectedPlanner(gru.ExampleGRUAdapter(), SlowestReward(), samples=4, lookahead=30,
                                               best_response_rounds=rounds)
        planner.reset(scene)
        plans.append(planner.plan(context, 20).states)
    # each agent's score ignores the others, so re-choosing beside them changes nothing
    assert torch.equal(plans[0], plans[1])
