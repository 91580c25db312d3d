"""The closed-form per-denoising-step KL of CTG's Gaussian transitions (CTGAdapter.transition_kl)."""

from __future__ import annotations

import copy
import os

import pytest
import torch

from trafficrlhf_sdk.scenario import default_data_root

ROOT = os.path.join(default_data_root(), "nuscenes_pred")
pytestmark = pytest.mark.skipif(not os.path.isdir(os.path.join(ROOT, "label")),
                                reason=f"nuscenes_pred data not found under {ROOT!r}")


def _setup():  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk as t
    from trafficrlhf_ctg import CTGAdapter

    scenes = t.get_scenario_source("nuscenes_pred").load_batch("val", 2)
    context = scenes.time_slice(0, 31).replace_unchecked(current_index=30)
    policy = CTGAdapter(seed=0)
    with torch.no_grad():
        trace = policy.sample(context, 3, None, torch.Generator().manual_seed(0)).trace.detach()
    return policy, context, trace


def test_the_kl_is_zero_at_the_start_finite_after_a_change_and_matches_a_monte_carlo_estimate() -> None:
    policy, context, trace = _setup()
    reference = copy.deepcopy(policy)
    start = policy.transition_kl(context, trace, reference)
    assert start.shape == policy.log_prob(context, trace).shape
    assert float(start.detach().abs().max()) == 0.0
    with torch.no_grad():  # move the policy away from the reference
        for p in policy.module.parameters():
            p.add_(0.02 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    kl = policy.transition_kl(context, trace, reference)
    kl = kl.detach()
    assert torch.isfinite(kl).all() and float(kl[trace.agents[:, None, :, None].expand_as(kl)].min()) >= 0
    assert float(kl.sum()) > 0
    # independent check: E_{x ~ N(mu, s^2)} [log N(x; mu, s^2) - log N(x; mu_ref, s^2)] by sampling
    _, cond, chain, delta, scene, steer = policy._chain_inputs(context, trace)
    with torch.no_grad():
        mean, sigma = policy.model.chain_means(cond, chain, delta, scene, steer)
        ref_mean, _ = reference.model.chain_means(*reference._chain_inputs(context, trace)[1:])
        draws = mean[None] + sigma[None, ..., None, None] * torch.randn((4000, *mean.shape),
                                                                        generator=torch.Generator().manual_seed(0))
        log_ratio = (((draws - ref_mean) ** 2 - (draws - mean) ** 2).sum((-1, -2)) / (2 * sigma**2)).mean(0)
    closed = kl.permute(0, 2, 1, 3)[trace.agents]  # (N, S, K) in the chain's order
    assert torch.allclose(log_ratio, closed, rtol=0.1, atol=0.05 * float(closed.mean()))


def test_gradients_reach_the_policy_only() -> None:
    policy, context, trace = _setup()
    reference = copy.deepcopy(policy)
    with torch.no_grad():
        next(iter(policy.module.parameters())).add_(0.05)
    policy.transition_kl(context, trace, reference).sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.module.parameters())
    assert all(p.grad is None for p in reference.module.parameters())
