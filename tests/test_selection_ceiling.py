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
