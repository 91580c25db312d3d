"""``TrafficGenAdapter``: the compact TrafficGen (:mod:`trafficgen_reference`) behind the SDK's
:class:`TrafficModelAdapter` contract.

* Only the motion forecaster is a policy. The initializer is part of :attr:`module` (and of the checkpoint) but
  is never offered by :meth:`parameter_groups`, so fine-tuning leaves it bitwise unchanged. Rollouts,
  evaluation and fine-tuning start from the logged scene (the initialization is fixed); a scene can be
  initialized from the initializer under a fixed seed with :meth:`initialize_scene`, a utility that is not a
  parameter group and not used by ``sample``/``plan``.
* ``sample``: for every controlled agent valid now, draw a mode ``m ~ Categorical(pi)`` and actions
  ``a ~ N(mu_m, sigma_m)`` (20 steps of acceleration and yaw rate), roll them through the unicycle (speed
  floored at 0) from the agent's current scene-frame state. Trace: ``mode (B, S, A)`` and
  ``actions (B, S, A, 20, 2)``.
* ``log_prob``: ``log pi_m + log N(a | mu_m, sigma_m)``, ``(B, S, A)``: the joint density of the sampled
  (mode, action sequence) pair. This is the density PPO fine-tunes (the mode is part of the action); the
  marginal over modes is available as :meth:`marginal_log_prob`.
* ``road_head`` (option): a head that re-weights the modes from the road along their plans. For every mode, the
  mean actions are rolled out from the agent's current speed; at every 5th step the drivable layer of the
  forecaster's own map crop is read on the plan and 1.5 m to either side, with whether the point lies inside the
  crop; an MLP maps these to a change of that mode's logit. Its last layer starts at zero, so a model with a new
  head samples and scores exactly as without one; the head is its own parameter group (``road``) and is saved
  with the checkpoint.
* ``steer_head`` (option): a head that shifts each mode's mean actions from the same road features (read along the
  base's mean plan) and the agent's current speed; zero at the start like the road head, parameter group
  ``steer``. With both heads the road head reads the steered plans.
* ``plan``: with guidance, the base class draws ``plan_samples`` samples and keeps the one with the lowest
  guidance loss (sample filtering; all five SDK guidances work this way). Without guidance and with
  ``greedy_plan`` (the default) the plan is the mean of the most likely mode, as upstream executes the
  argmax-score mode.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from pydantic import Field

import trafficgen_reference
from trafficgen_reference.data import forecaster_features, future_targets, initialize_scene, select_rows, window_mask
from trafficgen_reference.model import Forecaster, ForecastOutput, TrafficGenConfig, TrafficGenModel, unicycle_rollout
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.models.adapter import (
    AdapterOptions,
    PolicyTrace,
    SampleOutput,
    TrafficModelAdapter,
    extend_constant_velocity,
)
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan

__all__ = ["TrafficGenAdapter", "TrafficGenOptions", "default_checkpoint"]


def default_checkpoint() -> Path:
    """The checkpoint bundled with ``trafficrlhf-reference-trafficgen``
    (``reference_models/trafficgen/checkpoints/trafficgen_small``)."""
    return Path(trafficgen_reference.__file__).resolve().parent.parent / "checkpoints" / "trafficgen_small"


class TrafficGenOptions(AdapterOptions):
    """Options of :class:`TrafficGenAdapter`."""

    greedy_plan: bool = Field(
        True, description="Without guidance, plan the mean of the most likely mode (upstream's argmax) instead of "
                          "one sample."
    )
    imitation_windows: int = Field(4, ge=1, description="Time steps per scene used by imitation_loss.")
    steer_head: bool = Field(False, description="Add a zero-effect head that shifts each mode's mean actions from "
                             "the drivable area along its plan (parameter group `steer`). A checkpoint saved with "
                             "the head keeps it either way.")
    road_head: bool = Field(False, description="Add a zero-effect head that re-weights the modes from the drivable "
                            "area along each mode's plan (parameter group `road`). A checkpoint saved with the head "
                            "keeps it either way.")


class TrafficGenAdapter(TrafficModelAdapter):
    """Compact TrafficGen: 6-mode Gaussian-mixture forecaster over 20 steps (2 s at 0.1 s) + a frozen initializer."""

    name = "trafficgen"
    Options = TrafficGenOptions
    horizon = 20

    # ------------------------------------------------------------ construction
    def build(self, config: dict[str, Any] | None) -> None:
        """``config`` None: architecture and weights from ``options.checkpoint`` or the bundled checkpoint.
        Otherwise build ``config`` and load weights only if ``options.checkpoint`` is set."""
        self.cfg, self.model = self.load_architecture(
            config, str(default_checkpoint()),
            "python -m trafficgen_reference.train --out reference_models/trafficgen/checkpoints/trafficgen_small",
            TrafficGenConfig, TrafficGenModel,
        )
        self.horizon = self.cfg.horizon
        self.history_steps = self.cfg.history_steps
        for option, prefix in (("road_head", "forecaster.road."), ("steer_head", "forecaster.steer.")):
            if getattr(self.options, option) and not getattr(self.cfg, option):  # a checkpoint's own head is kept
                self._add_head(option, prefix)
        self.model.initializer.requires_grad_(False)  # frozen: never offered, never given gradients
        self.model.eval()

    def _add_head(self, option: str, prefix: str) -> None:
        """Rebuild the model with the zero-effect head ``option`` and the loaded weights (the head starts at 0)."""
        cfg = dataclasses.replace(self.cfg, **{option: True})
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            model = TrafficGenModel(cfg).to(self.options.device)
        missing, unexpected = model.load_state_dict(self.model.state_dict(), strict=False)
        if unexpected or not all(k.startswith(prefix) for k in missing):
            raise ValueError(f"`{option}`: the checkpoint's weights do not fit the model with the head (missing "
                             f"{missing[:3]}, unexpected {unexpected[:3]}); use a TrafficGen checkpoint.")
        self.cfg, self.model = cfg, model

    def get_config(self) -> dict[str, Any]:
        """The model's :class:`TrafficGenConfig` as a dict (normalization statistics included)."""
        return self.cfg.to_dict()

    @property
    def module(self) -> torch.nn.Module:
        """The :class:`TrafficGenModel` (initializer and forecaster)."""
        return self.model

    def parameter_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """The forecaster only: ``encoder`` (map CNN, history/neighbour MLPs, fusion) and ``decoder`` (mode
        queries and the per-mode Gaussian head). The initializer is not offered."""
        forecaster = self.model.forecaster
        groups = {"encoder": [p for m in forecaster.encoder_modules() for p in m.parameters()],
                  "decoder": forecaster.decoder_parameters()}
        if self.cfg.road_head:
            groups["road"] = list(forecaster.road.parameters())
        if self.cfg.steer_head:
            groups["steer"] = list(forecaster.steer.parameters())
        return groups

    # ------------------------------------------------------------ helpers
    def _check_dt(self, context: ScenarioTensor) -> None:
        if abs(context.dt - self.cfg.dt) > 1e-9:
            raise ValueError(f"the TrafficGen forecaster runs at dt={self.cfg.dt} s; the scenario has dt={context.dt} "
                             "s. Load the scenes with dt=0.1.")

    def _forecast(self, context: ScenarioTensor, agents: torch.Tensor) -> tuple[ForecastOutput, torch.Tensor]:
        """Mixture parameters for the ``agents (B, A)`` rows and their current scene-frame states ``(N, 4)``."""
        rows = select_rows(forecaster_features(context, self.cfg), agents)
        return self.model.forecaster(rows), context.states[:, :, context.current_index][agents]

    def _futures(self, state_now: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Scene-frame states ``(N, S, H, 4)`` of actions ``(N, S, H, 2)`` from ``state_now (N, 4)``."""
        start = state_now[:, None].expand(-1, actions.shape[1], 4)
        return unicycle_rollout(start, actions, self.cfg.dt)

    @staticmethod
    def _scatter(rows: torch.Tensor, agents: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """Place per-row values ``(N, S, ...)`` into ``base (B, A, S, ...)`` at ``agents``.

        Returns ``(B, S, A, ...)``."""
        full = base.clone()
        full[agents] = rows.to(full.dtype)
        return full.transpose(1, 2)

    @staticmethod
    def _hold(context: ScenarioTensor, s: int, h: int) -> torch.Tensor:
        """``(B, A, S, H, 4)``: every agent standing at its current pose (the futures of agents not sampled)."""
        now = context.states[:, :, context.current_index]
        hold = torch.stack([now[..., 0], now[..., 1], torch.zeros_like(now[..., 0]), now[..., 3]], -1)
        return hold[:, :, None, None].expand(-1, -1, s, h, 4)

    # ------------------------------------------------------------ contract
    def sample(self, context: ScenarioTensor, num_samples: int, guidance: GuidanceSet | None = None,
               generator: torch.Generator | None = None) -> SampleOutput:
        """Draw ``num_samples`` futures ``(B, S, A, 20, 4)`` for the controlled agents valid now.

        ``guidance`` is accepted for the interface; TrafficGen's samples are not steered (``plan`` filters them).
        Randomness (mode uniforms and action noise, drawn for every agent slot) comes from ``generator``.
        """
        self._check_dt(context)
        now = context.current_index
        b, a, s, h = context.num_scenes, context.num_agents, num_samples, self.horizon
        agents = context.controlled & context.valid[:, :, now]
        uniform = torch.rand(b, s, a, generator=generator).to(context.device)
        noise = torch.randn(b, s, a, h, 2, generator=generator).to(context.device)
        with torch.no_grad():
            out, state_now = self._forecast(context, agents)
            mode, actions = Forecaster.draw(out, uniform.transpose(1, 2)[agents], noise.transpose(1, 2)[agents])
            log_prob = Forecaster.log_density(out, mode, actions)
            futures = self._futures(state_now, actions)
        dev = context.device
        trace = PolicyTrace(
            tensors={"mode": self._scatter(mode, agents, torch.zeros(b, a, s, dtype=torch.long, device=dev)),
                     "actions": self._scatter(actions, agents, torch.zeros(b, a, s, h, 2, device=dev))},
            agents=agents, now=now, info={"model": self.name},
        )
        return SampleOutput(self._scatter(futures, agents, self._hold(context, s, h)), trace,
                            self._scatter(log_prob, agents, torch.zeros(b, a, s, device=dev)))

    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """``(B, S, A)`` joint log-density ``log pi_m + log N(a | mu_m, sigma_m)`` of the traced (mode, actions)
        under the current parameters (0 for agents not sampled). Differentiable."""
        return self._log_prob(context, trace, marginal=False)

    def marginal_log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """``(B, S, A)`` log of the mixture density ``sum_m pi_m N(a | mu_m, sigma_m)`` of the traced actions."""
        return self._log_prob(context, trace, marginal=True)

    def _log_prob(self, context: ScenarioTensor, trace: PolicyTrace, marginal: bool) -> torch.Tensor:
        self._check_dt(context)
        if trace.now != context.current_index:
            raise ValueError(f"trace.now={trace.now} but context.current_index={context.current_index}; pass the "
                             "context the sample was drawn from.")
        agents = trace.agents.to(context.device)
        mode = trace.tensors["mode"].transpose(1, 2)[agents]  # (N, S)
        actions = trace.tensors["actions"].transpose(1, 2)[agents]  # (N, S, H, 2)
        b, s, a = trace.tensors["mode"].shape
        out, _ = self._forecast(context, agents)
        rows = Forecaster.mixture_log_density(out, actions) if marginal else Forecaster.log_density(out, mode, actions)
        return self._scatter(rows, agents, torch.zeros(b, a, s, device=context.device))

    def choice_futures(self, context: ScenarioTensor) -> torch.Tensor:
        """``(B, M, A, horizon, 4)``: each mode's mean actions rolled out, for the agents :meth:`sample` draws (the
        others hold their pose). The modes are the forecaster's discrete choice."""
        self._check_dt(context)
        agents = context.controlled & context.valid[:, :, context.current_index]
        with torch.no_grad():
            out, state_now = self._forecast(context, agents)
            futures = self._futures(state_now, out.mean)
        return self._scatter(futures, agents, self._hold(context, out.mean.shape[1], self.horizon))

    def choice_log_prob(self, context: ScenarioTensor) -> torch.Tensor:
        """``(B, M, A)`` mode log-probabilities ``log pi_m`` of the agents :meth:`sample` draws (0 elsewhere).
        Differentiable."""
        self._check_dt(context)
        agents = context.controlled & context.valid[:, :, context.current_index]
        out, _ = self._forecast(context, agents)
        m = out.log_pi.shape[1]
        return self._scatter(out.log_pi, agents, torch.zeros(context.num_scenes, context.num_agents, m,
                                                             device=context.device))

    def imitation_loss(self, batch: ScenarioTensor) -> torch.Tensor:
        """The forecaster's winner-takes-all loss on logged windows of ``batch``: every vehicle valid at ``t`` and
        over the 2 s after it, at up to ``imitation_windows`` evenly spaced keyframe steps ``t`` (from the
        batch's ``current_index`` on when it leaves room for a 2 s future, else from step 5)."""
        self._check_dt(batch)
        h = self.horizon
        first = batch.current_index if batch.current_index + h < batch.num_steps else 5
        candidates = list(range(first, batch.num_steps - h, 5))
        if len(candidates) > self.options.imitation_windows:
            pick = torch.linspace(0, len(candidates) - 1, self.options.imitation_windows).round().long().tolist()
            candidates = [candidates[i] for i in pick]
        actions_all = batch.actions()
        parts: dict[str, list[torch.Tensor]] = {}
        for t in candidates:
            mask = window_mask(batch, t, h)
            if not mask.any():
                continue
            rows = select_rows(forecaster_features(batch.replace_unchecked(current_index=t), self.cfg), mask)
            acts, future_xy = future_targets(batch, t, h, actions_all)
            rows["actions"], rows["future_xy"] = acts[mask], future_xy[mask]
            for key, value in rows.items():
                parts.setdefault(key, []).append(value)
        if not parts:
            return sum(p.sum() * 0.0 for p in self.model.forecaster.parameters())  # type: ignore[return-value]
        data = {key: torch.cat(values) for key, values in parts.items()}
        loss, _ = self.model.forecaster.loss(data, data["actions"], data["future_xy"])
        return loss

    # ------------------------------------------------------------ policy
    @torch.no_grad()
    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """With guidance (or ``greedy_plan=False``): the base class (best of ``plan_samples`` samples under the
        guidance loss, or one sample). Otherwise the mean actions of each agent's most likely mode, rolled out."""
        if self.guidance is not None or not self.options.greedy_plan:
            return super().plan(context, horizon)
        context = context.to(self.options.device)
        self._check_dt(context)
        agents = context.controlled & context.valid[:, :, context.current_index]
        out, state_now = self._forecast(context, agents)
        best = out.log_pi.argmax(-1)  # (N,)
        mean = out.mean[torch.arange(best.shape[0], device=best.device), best]  # (N, H, 2)
        futures = self._futures(state_now, mean[:, None])  # (N, 1, H, 4)
        full = self._scatter(futures, agents, self._hold(context, 1, self.horizon))[:, 0]
        return Plan(extend_constant_velocity(full, horizon, context.dt).cpu())

    # ------------------------------------------------------------ initialization utility
    @torch.no_grad()
    def initialize_scene(self, scenario: ScenarioTensor, seed: int = 0, num_agents: int | None = None
                         ) -> ScenarioTensor:
        """Place vehicles on the map of each scene of ``scenario`` with the (frozen) initializer under ``seed``.

        Per scene, the first logged vehicle valid at ``current_index`` is kept (slot 0) and up to ``num_agents``
        others (default: as many as the log has then) are placed around it, one at a time with box-overlap
        rejection. Returns a one-step scenario (``current_index`` 0), all agents controlled. Not used by
        ``sample``/``plan``: rollouts start from the logged initialization.
        """
        scenes = [initialize_scene(scenario[i], self.model, seed + i, num_agents) for i in range(scenario.num_scenes)]
        return scenes[0] if len(scenes) == 1 else ScenarioTensor.concat(scenes)
