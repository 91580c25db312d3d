"""``check_adapter``: a conformance check model authors run on their own :class:`TrafficModelAdapter`
(in the spirit of stable-baselines3's ``check_env``). Contract breaks raise :class:`AdapterCheckError` with what
to fix; soft issues are warnings."""

from __future__ import annotations

import tempfile
import warnings
from typing import Any

import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.models.adapter import PolicyTrace, SampleOutput, TrafficModelAdapter
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["AdapterCheckError", "check_adapter"]


class AdapterCheckError(TrafficRLHFError, AssertionError):
    """The adapter breaks the contract; the message says which part and how to fix it."""


def _fail(adapter: TrafficModelAdapter, what: str, fix: str) -> None:
    raise AdapterCheckError(f"adapter {type(adapter).__name__} ({adapter.name!r}): {what}. Fix: {fix}")


def _check_sample(adapter: TrafficModelAdapter, context: ScenarioTensor, out: Any, num_samples: int) -> None:
    if not isinstance(out, SampleOutput):
        _fail(adapter, f"sample() returned {type(out).__name__}", "return SampleOutput(futures, trace, log_prob)")
    b, a = context.num_scenes, context.num_agents
    expected = (b, num_samples, a, adapter.horizon, 4)
    if tuple(out.futures.shape) != expected:
        _fail(adapter, f"sample() futures have shape {tuple(out.futures.shape)}, expected {expected}",
              "return (B, S, A, horizon, 4) scene-frame states for every agent slot")
    if not torch.isfinite(out.futures).all():
        _fail(adapter, "sample() futures contain NaN or inf", "check the decoder and the state rollout")
    if not isinstance(out.trace, PolicyTrace):
        _fail(adapter, "sample() trace is not a PolicyTrace", "wrap what log_prob needs in PolicyTrace(tensors, ...)")
    if out.trace.now != context.current_index:
        _fail(adapter, f"trace.now is {out.trace.now}, context.current_index is {context.current_index}",
              "record the step the futures start after")
    if not isinstance(out.trace.agents, torch.Tensor) or tuple(out.trace.agents.shape) != (b, a) \
            or out.trace.agents.dtype != torch.bool:
        got = tuple(out.trace.agents.shape) if isinstance(out.trace.agents, torch.Tensor) else type(out.trace.agents)
        _fail(adapter, f"trace.agents has shape {got}, expected bool ({b}, {a})",
              "set PolicyTrace.agents to the bool (B, A) mask of the sampled agents")
    for name, tensor in out.trace.tensors.items():
        if not isinstance(tensor, torch.Tensor) or tuple(tensor.shape[:3]) != (b, num_samples, a):
            got = tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else type(tensor).__name__
            _fail(adapter, f"trace tensor {name!r} has shape {got}, expected leading dims ({b}, {num_samples}, {a})",
                  "give every trace tensor the leading dims (B, S, A) so PPO can select scenes and samples")


def _check_choices(adapter: TrafficModelAdapter, context: ScenarioTensor, choices: Any, agents: torch.Tensor) -> None:
    b, a = context.num_scenes, context.num_agents
    if not isinstance(choices, torch.Tensor) or choices.dim() != 5 or tuple(choices.shape[::2]) != (b, a, 4) \
            or choices.shape[3] != adapter.horizon:
        got = tuple(choices.shape) if isinstance(choices, torch.Tensor) else type(choices).__name__
        _fail(adapter, f"choice_futures() returned {got}, expected (B, C, A, horizon, 4) = ({b}, C, {a}, "
                       f"{adapter.horizon}, 4)", "return every choice's future for every agent slot, or None")
    if not torch.isfinite(choices).all() or choices.requires_grad:
        _fail(adapter, "choice_futures() has NaN/inf or carries gradients", "compute it under torch.no_grad()")
    log_prob = adapter.choice_log_prob(context)
    expected = (b, choices.shape[1], a)
    if not isinstance(log_prob, torch.Tensor) or tuple(log_prob.shape) != expected \
            or not torch.isfinite(log_prob).all():
        got = tuple(log_prob.shape) if isinstance(log_prob, torch.Tensor) else type(log_prob).__name__
        _fail(adapter, f"choice_log_prob() returned {got} (or NaN/inf), expected {expected}",
              "return finite (B, C, A) log-probabilities of the choices")
    if not log_prob.requires_grad:
        _fail(adapter, "choice_log_prob() has no gradient", "compute it from the module's parameters")
    if (log_prob.detach().transpose(1, 2)[~agents] != 0).any():
        _fail(adapter, "choice_log_prob() is non-zero for agents that were not sampled", "multiply by the agent mask")
    if (log_prob.detach().exp().sum(1)[agents] > 1 + 1e-4).any():
        _fail(adapter, "choice_log_prob() gives a sampled agent choice probabilities summing to more than 1",
              "return normalized log-probabilities (log-softmax of the choice logits)")


def check_adapter(
    adapter: TrafficModelAdapter,
    context: ScenarioTensor,
    num_samples: int = 3,
    check_save_load: bool = True,
    atol: float = 1e-4,
) -> dict[str, Any]:
    """Verify ``adapter`` against the contract on the logged scenes ``context`` (B >= 1, with a map).

    Checks: shapes and finiteness of ``sample``; determinism under a seeded generator; ``log_prob`` recomputed
    from the trace equals the sampling-time value and is differentiable w.r.t. the offered parameters;
    ``imitation_loss`` is a finite differentiable scalar; a training step moves only offered parameters
    (frozen parts stay bitwise equal); ``plan`` returns finite ``(B, A, >=H, 4)`` plans; a
    ``save_pretrained``/``from_pretrained`` round trip reproduces samples; where the adapter offers discrete choices,
    ``choice_futures`` and ``choice_log_prob`` have the documented shapes and ``choice_log_prob`` is differentiable.

    Returns:
        A dict of facts found (parameter counts per group, log-prob shape), for reports.
    """
    if not isinstance(adapter, TrafficModelAdapter):
        raise AdapterCheckError(f"{type(adapter).__name__} does not subclass TrafficModelAdapter; derive from it.")
    if not adapter.name:
        _fail(adapter, "the class attribute `name` is empty", "set name = 'my_model' (the registry name)")
    facts: dict[str, Any] = {}

    groups = adapter.parameter_groups()
    if not groups:
        _fail(adapter, "parameter_groups() is empty", "offer at least one named group of trainable parameters")
    all_params = {id(p) for p in adapter.module.parameters()}
    offered: dict[int, str] = {}
    for group, params in groups.items():
        if not params:
            _fail(adapter, f"parameter group {group!r} is empty", "drop empty groups")
        for p in params:
            if id(p) not in all_params:
                _fail(adapter, f"group {group!r} holds a parameter that is not in adapter.module",
                      "offer parameters of the wrapped module only")
            if id(p) in offered:
                _fail(adapter, f"a parameter is in groups {offered[id(p)]!r} and {group!r}", "put each in one group")
            offered[id(p)] = group
    facts["parameters"] = {g: sum(p.numel() for p in ps) for g, ps in groups.items()}
    facts["frozen_parameters"] = sum(p.numel() for p in adapter.module.parameters() if id(p) not in offered)

    # --- sampling and determinism
    gen = lambda: torch.Generator().manual_seed(1234)  # noqa: E731
    out = adapter.sample(context, num_samples, None, gen())
    _check_sample(adapter, context, out, num_samples)
    again = adapter.sample(context, num_samples, None, gen())
    if not torch.equal(out.futures, again.futures):
        _fail(adapter, "two sample() calls with identically seeded generators differ",
              "draw all randomness from the `generator` argument")

    # --- log-probability from the trace
    log_prob = adapter.log_prob(context, out.trace.detach())
    facts["log_prob_shape"] = tuple(log_prob.shape)
    expected = (context.num_scenes, num_samples, context.num_agents)
    if tuple(log_prob.shape[:3]) != expected or log_prob.dim() not in (3, 4):
        _fail(adapter, f"log_prob() has shape {tuple(log_prob.shape)}",
              "return (B, S, A) or per-step (B, S, A, K) log-probabilities")
    if not torch.isfinite(log_prob).all():
        _fail(adapter, "log_prob() contains NaN or inf", "clamp scales and mask agents that were not sampled")
    if out.log_prob.shape != log_prob.shape or not torch.allclose(out.log_prob.detach(), log_prob.detach(), atol=atol,
                                                                   rtol=1e-4):
        gap = (out.log_prob.detach() - log_prob.detach()).abs().max() if out.log_prob.shape == log_prob.shape else "n/a"
        _fail(adapter, f"log_prob() recomputed from the trace differs from the sampling-time value (max gap {gap})",
              "store in the trace everything the sample depended on (noise, chosen modes/cells)")
    not_sampled = ~out.trace.agents
    if (log_prob.detach()[not_sampled[:, None].expand(-1, num_samples, -1)] != 0).any():
        _fail(adapter, "log_prob() is non-zero for agents that were not sampled", "multiply by the agent mask")

    # --- gradients reach the offered parameters only; a step leaves frozen ones bitwise equal
    frozen_before = {name: p.detach().clone() for name, p in adapter.module.named_parameters() if id(p) not in offered}
    # the check takes a real optimizer step; restore the weights afterwards so the caller's adapter is unchanged
    weights_before = {name: t.detach().clone() for name, t in adapter.module.state_dict().items()}
    adapter.module.train()
    adapter.module.zero_grad(set_to_none=True)
    lp = adapter.log_prob(context, out.trace.detach())
    if not lp.requires_grad:
        _fail(adapter, "log_prob() returns a tensor without gradient, so PPO's surrogate would train nothing (only "
                       "the imitation loss would move the model)",
              "compute log_prob from the module's parameters, outside torch.no_grad(), without .detach()")
    lp.sum().backward(retain_graph=True)
    if not any(p.grad is not None and p.grad.abs().sum() > 0 for ps in groups.values() for p in ps):
        _fail(adapter, "log_prob() has no gradient with respect to any offered parameter, so PPO's surrogate would "
                       "train nothing", "compute log_prob with the parameters that parameter_groups() offers")
    adapter.module.zero_grad(set_to_none=True)
    imitation = adapter.imitation_loss(context)
    if imitation.dim() != 0 or not torch.isfinite(imitation):
        _fail(adapter, f"imitation_loss() returned {imitation!r}", "return a finite scalar tensor")
    loss = imitation - lp.sum() / max(1, int(out.trace.agents.sum()))
    loss.backward()
    moved = [g for g, ps in groups.items() if any(p.grad is not None and p.grad.abs().sum() > 0 for p in ps)]
    if not moved:
        _fail(adapter, "neither log_prob() nor imitation_loss() has a gradient w.r.t. any offered parameter",
              "compute them with the module's parameters, without torch.no_grad()")
    params = [p for ps in groups.values() for p in ps]
    optimizer = torch.optim.SGD(params, lr=1e-3)
    optimizer.step()
    adapter.module.zero_grad(set_to_none=True)
    adapter.module.eval()
    for name, p in adapter.module.named_parameters():
        if name in frozen_before and not torch.equal(p.detach(), frozen_before[name]):
            _fail(adapter, f"frozen parameter {name!r} changed in a training step on the offered groups",
                  "do not share tensors between offered and frozen parts")
    facts["groups_with_gradient"] = moved
    adapter.module.load_state_dict(weights_before)

    # --- discrete choices (optional: mixture policies)
    choices = adapter.choice_futures(context)
    if choices is not None:
        _check_choices(adapter, context, choices, out.trace.agents)
    facts["choices"] = None if choices is None else int(choices.shape[1])

    # --- closed-loop planning
    adapter.reset(context)
    plan = adapter.plan(context, max(adapter.horizon, 5))
    if plan.states.shape[:2] != (context.num_scenes, context.num_agents) or plan.states.shape[2] < 5:
        _fail(adapter, f"plan() returned states of shape {tuple(plan.states.shape)}",
              "return Plan(states (B, A, >= horizon, 4))")
    if not torch.isfinite(plan.states).all():
        _fail(adapter, "plan() states contain NaN or inf", "check the sampler")

    # --- save / load round trip
    if check_save_load:
        with tempfile.TemporaryDirectory() as tmp:
            adapter.save_pretrained(tmp)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                reloaded = type(adapter).from_pretrained(tmp, **adapter.options.model_dump(exclude={"checkpoint"}))
            a_out = adapter.sample(context, num_samples, None, gen())
            b_out = reloaded.sample(context, num_samples, None, gen())
            if not torch.allclose(a_out.futures, b_out.futures, atol=1e-5):
                _fail(adapter, "a save_pretrained/from_pretrained round trip changes the samples",
                      "save every tensor the model uses (buffers too) and rebuild the same architecture")
    return facts
