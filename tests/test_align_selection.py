"""Best-of-K credit (``AlignConfig.selection_credit``): the estimator against the exact policy gradient of the
executed sample's reward, its invariances, and its use by the trainer."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
from trafficrlhf_sdk.alignment.selection import best_of_k_returns
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario import ScenarioTensor

SCORES = torch.tensor([0.3, 1.2, -0.5, 2.0, 0.7, 1.5, 1.2])  # two cells share a score: one class


def exact_best_of_k_gradient(logits: torch.Tensor, rewards: torch.Tensor, k: int) -> torch.Tensor:
    """d/d logits of E[R(best of k iid cells)] for a categorical over cells with scores ``SCORES`` (ties drawn
    uniformly, so a class's reward is its members' probability-weighted mean)."""
    logits = logits.detach().requires_grad_(True)
    p = logits.softmax(0)
    at_most = (SCORES[None, :] <= SCORES[:, None]).float()  # [c, z]: s_z <= s_c
    below = (SCORES[None, :] < SCORES[:, None]).float()
    same = at_most - below
    h, g = at_most @ p, below @ p
    class_reward = (same @ (p * rewards)) / (same @ p)
    # each class appears once per member in the sum: divide by the class size
    value = (class_reward * (h**k - g**k) / same.sum(1)).sum()
    (grad,) = torch.autograd.grad(value, logits)
    return grad


def test_the_returns_give_the_policy_gradient_of_the_executed_sample() -> None:
    torch.manual_seed(0)
    logits, rewards, k = torch.randn(7), torch.randn(7), 5
    exact = exact_best_of_k_gradient(logits, rewards, k)
    p = logits.softmax(0)
    cells = torch.multinomial(p, 100 * 300, replacement=True, generator=torch.Generator().manual_seed(1))
    cells = cells.reshape(100, 300)  # 100 groups of 300 samples
    returns = best_of_k_returns(rewards[cells], SCORES[cells], k)
    score_function = torch.nn.functional.one_hot(cells, 7).float() - p  # d log p(cell) / d logits
    estimate = (score_function * returns[..., None]).mean((0, 1))
    torch.testing.assert_close(estimate, exact, atol=0.015, rtol=0)
    # the single-sample gradient, what PPO follows without the selection, is a different direction
    single = p * (rewards - (p * rewards).sum())
    assert (single - exact).abs().max() > 0.05


def test_one_draw_is_the_plain_centred_reward() -> None:
    rewards = torch.tensor([[0.5, -1.0, 2.0, 0.1]])
    returns = best_of_k_returns(rewards, torch.tensor([[3.0, 1.0, 2.0, 0.0]]), 1)
    torch.testing.assert_close(returns, rewards - rewards.mean())


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 9), st.integers(1, 6), st.floats(-5, 5), st.integers(0, 10**6))
def test_returns_ignore_the_reward_offset_and_follow_the_samples(s: int, k: int, offset: float, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    rewards = torch.randn(3, s, 2, generator=gen, dtype=torch.float64)
    scores = torch.randint(0, 4, (3, s, 2), generator=gen).double()  # ties on purpose
    returns = best_of_k_returns(rewards, scores, k)
    assert returns.shape == rewards.shape and torch.isfinite(returns).all()
    torch.testing.assert_close(best_of_k_returns(rewards + offset, scores, k), returns)
    order = torch.randperm(s, generator=gen)
    torch.testing.assert_close(best_of_k_returns(rewards[:, order], scores[:, order], k), returns[:, order])
    # groups are independent: the sample dimension may sit anywhere
    torch.testing.assert_close(best_of_k_returns(rewards.transpose(0, 1), scores.transpose(0, 1), k, dim=0),
                               returns.transpose(0, 1))


def test_bad_inputs_get_one_clear_error() -> None:
    rewards = torch.zeros(2, 4)
    with pytest.raises(TrafficRLHFError, match="same shape"):
        best_of_k_returns(rewards, torch.zeros(2, 5), 3)
    with pytest.raises(TrafficRLHFError, match="k >= 1"):
        best_of_k_returns(rewards, torch.zeros(2, 4), 0)
    with pytest.raises(TrafficRLHFError, match="NaN"):
        best_of_k_returns(rewards, torch.full((2, 4), float("nan")), 3)


gru = pytest.importorskip("trafficrlhf_example_gru")
FAST = dict(epochs=1, contexts_per_epoch=4, samples_per_context=4, minibatch_contexts=2, ppo_epochs=1,
            progress_bar=False, log_formats=("csv",), credit="agent", seed=3)


class SelectingGRU(gru.ExampleGRUAdapter):  # type: ignore[misc, name-defined]
    """The example model with a planner that would execute the fastest of ``k`` samples."""

    k = 5

    def selection_scores(self, context, output, guidance=None):  # type: ignore[no-untyped-def]
        return output.futures[..., 2].mean(-1).detach(), self.k


def test_the_trainer_credits_the_selection_only_when_asked(train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import FailureReward

    def advantages(model, **extra):  # type: ignore[no-untyped-def]
        torch.manual_seed(0)
        model.module.load_state_dict(state)
        trainer = AlignTrainer(model, FailureReward(margins=True), AlignConfig(**FAST, **extra),
                               scenes=train_scene_list)
        return trainer._rollout(0)

    torch.manual_seed(0)
    state = SelectingGRU().module.state_dict()
    plain = advantages(SelectingGRU())
    credited = advantages(SelectingGRU(), selection_credit=True)
    torch.testing.assert_close(credited.rewards, plain.rewards)  # logged rewards stay the raw ones
    assert not torch.allclose(credited.advantages, plain.advantages)
    one = SelectingGRU()
    one.k = 1  # a planner drawing one sample executes it: the plain advantages
    torch.testing.assert_close(advantages(one, selection_credit=True).advantages, plain.advantages)


def test_selection_credit_needs_a_selecting_adapter(train_scene_list: list[ScenarioTensor]) -> None:
    from trafficrlhf_sdk.reward.builtin import FailureReward

    with pytest.raises(TrafficRLHFError, match="selection_scores"):
        AlignTrainer(gru.ExampleGRUAdapter(), FailureReward(), AlignConfig(**FAST, selection_credit=True),
                     scenes=train_scene_list)
    with pytest.raises(ValueError, match="selection_credit"):
        AlignConfig(**FAST, selection_credit=True, counterfactual_credit=True)
