"""``BITSAdapter``: the compact BITS (:mod:`bits_reference`) behind the SDK's :class:`TrafficModelAdapter` contract.

* ``sample`` featurizes the sampled agents (controlled and valid now), runs the spatial goal network once,
  draws ``num_samples`` goal cells per agent from its categorical distribution masked to the drivable cells of
  the crop (unmasked when the crop has none), decodes each cell into an agent-frame goal with the predicted
  sub-cell offset and yaw, and lets the frozen goal-conditioned policy drive there (unicycle, 2 s). Other agent
  slots hold their current pose and get log-probability 0.
* Trace: ``cell (B, S, A)`` (the sampled cell index) and ``drivable (B, S, A, S_crop**2)`` (the mask used at
  sampling). Offsets, yaw and the policy are deterministic functions of the context, so
  :meth:`log_prob` = log p(cell) under the current goal network, masked as at sampling: ``(B, S, A)``.
* ``plan`` is BITS's selection (tbsim ``ego_sample_planning``): ``plan_samples`` goals per agent, each scored by
  ``0.01 progress - 15 collision - 1 drivable`` (collision against the other agents' most-likely-goal
  predictions, drivable = share of box centre and corners off the drivable layer), minus the guidance loss when
  a guidance is set; the best sample per agent (per scene for scene-level guidances) is executed.
* With ``train_on_selection``, ``sample`` runs that selection too: each of its samples is the executed choice
  among ``plan_samples`` goals, traced as the whole set (``cell (B, S, A, K)``), and ``log_prob`` sums the set's
  goal log-probabilities. The selection is a fixed function of the set (and of the other agents' sets for
  scene-level guidance), so this is the policy gradient of what ``plan`` executes; without it PPO trains single
  goals while the planner keeps picking the most progressive one.
* Only the goal network is offered for training (``goal_encoder``, ``goal_decoder``); the policy's parameters
  have ``requires_grad=False`` and are never offered.
* Stationary agents (|v| <= ``stationary_speed``) are held still, as the ``ctg`` adapter and upstream do, decided
  by ``stationary_rule`` (upstream's ``"rollout_start"``: once, from the speeds at ``reset``; a direct ``sample``
  call treats its context's current step as the start); their goal is still sampled and scored, so ``log_prob``
  stays exact.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import torch
from pydantic import Field

import bits_reference
from bits_reference.data import agent_features, future_targets, select_rows, window_mask
from bits_reference.model import BITSConfig, BITSModel, disk_collision, selection_score
from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.simulation.guidance import GuidanceSet, select_samples
from trafficrlhf_sdk.metrics.geometry import box_corners
from trafficrlhf_sdk.models.adapter import (
    AdapterOptions,
    PolicyTrace,
    SampleOutput,
    TrafficModelAdapter,
    extend_constant_velocity,
)
from trafficrlhf_sdk.models.features import from_agent_frame
from trafficrlhf_sdk.models.stationary import StationaryHold, StationaryRule
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan

__all__ = ["BITSAdapter", "BITSOptions", "default_checkpoint"]


def default_checkpoint() -> Path:
    """The checkpoint bundled with ``trafficrlhf-reference-bits`` (``reference_models/bits/checkpoints/bits_small``)."""
    return Path(bits_reference.__file__).resolve().parent.parent / "checkpoints" / "bits_small"


class BITSOptions(AdapterOptions):
    """Options of :class:`BITSAdapter` (``plan_samples`` is the number of goals BITS samples per replan;
    upstream uses 50 in tbsim and 5 in CTG's scene-editing config, the SDK default)."""

    stationary_speed: float = Field(0.5, ge=0, description="Agents at or below this speed (m/s) are held still.")
    stationary_rule: StationaryRule = Field(
        "rollout_start", description="When the speed is read: 'rollout_start' (upstream; once, at reset) or "
        "'every_replan' (the current speed at each replan, so an agent that stops stays stopped).")
    imitation_windows: int = Field(4, ge=1, description="Time steps per scene used by imitation_loss.")
    selection_weights: tuple[float, float, float] = Field(
        (0.01, 15.0, 1.0), description="BITS selection weights: progress, collision, drivable area (tbsim).")
    train_on_selection: bool = Field(
        False, description="sample() returns what plan() executes: each sample is BITS's choice among "
                           "`plan_samples` goals; the action is the whole goal set (log-probability: the sum over "
                           "its goals), so PPO optimizes the executed plan rather than single goals.")


class _Draw(NamedTuple):
    """What one goal-sampling pass produced, one row per agent it ran on."""

    index: torch.Tensor  # (N, S) sampled cells
    log_p: torch.Tensor  # (N, S) their masked log-probabilities
    mask: torch.Tensor  # (N, cells) drivable cells of the crop
    local: torch.Tensor  # (N, G, H, 4) agent-frame rollouts (G = S, or S + 1 with the most likely goal last)
    futures: torch.Tensor  # (N, G, H, 4) scene-frame rollouts (stationary agents held)
    state_now: torch.Tensor  # (N, 4) current scene-frame states
    held: torch.Tensor  # (N,) bool: held still (stationary)


class BITSAdapter(TrafficModelAdapter):
    """Compact BITS: spatial goal network (trainable) + goal-conditioned policy (frozen), 2 s horizon."""

    name = "bits"
    Options = BITSOptions
    horizon = 20

    # ------------------------------------------------------------ construction
    def build(self, config: dict[str, Any] | None) -> None:
        """``config`` None: architecture and weights from ``options.checkpoint`` or the bundled checkpoint.
        Otherwise build ``config`` and load weights only if ``options.checkpoint`` is set."""
        self.cfg, self.model = self.load_architecture(
            config, str(default_checkpoint()),
            "python -m bits_reference.train --out reference_models/bits/checkpoints/bits_small",
            BITSConfig, BITSModel,
        )
        self.horizon = self.cfg.horizon
        self.history_steps = self.cfg.history_steps
        self.model.policy.requires_grad_(False)  # frozen in TrafficRLHF: never offered, never differentiated
        self.model.eval()
        self._hold = StationaryHold(self.options.stationary_speed, self.options.stationary_rule)

    def get_config(self) -> dict[str, Any]:
        """The model's :class:`BITSConfig` as a dict (normalization statistics included)."""
        return self.model.cfg.to_dict()

    @property
    def module(self) -> torch.nn.Module:
        """The :class:`BITSModel` (goal network and policy)."""
        return self.model

    def parameter_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """The spatial goal network only: ``goal_encoder`` (agent/state encoders, U-Net encoder, FiLM) and
        ``goal_decoder`` (U-Net decoder, condition biases, output head). The policy is never offered."""
        net = self.model.goal_net
        encoder = [net.agent, net.state, net.enc0, net.enc1, net.enc2, net.enc3, net.film]
        decoder = [net.dec2, net.dec1, net.dec0, net.bias2, net.bias1, net.bias0, net.head]
        params = lambda modules: [p for m in modules for p in m.parameters()]  # noqa: E731
        return {"goal_encoder": params(encoder), "goal_decoder": params(decoder)}

    # ------------------------------------------------------------ helpers
    def _check_dt(self, context: ScenarioTensor) -> None:
        if abs(context.dt - self.cfg.dt) > 1e-9:
            raise ValueError(f"the BITS model runs at dt={self.cfg.dt} s; the scenario has dt={context.dt} s. Load "
                             "the scenes with dt=0.1.")

    def _to_scene(self, local: torch.Tensor, state_now: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
        """Agent-frame states ``(N, G, H, 4)`` -> scene frame from ``state_now (N, 4)``; the rows where ``held (N,)``
        is True stay still."""
        n, g, h, _ = local.shape
        pose = torch.stack([state_now[:, 0], state_now[:, 1], state_now[:, 3]], -1)
        xy = from_agent_frame(local[None, ..., :2], pose[None])[0]
        scene = torch.cat([xy, local[..., 2:3], wrap_angle(local[..., 3:4] + pose[:, None, None, 2:3])], -1)
        hold = torch.stack([state_now[:, 0], state_now[:, 1], torch.zeros_like(state_now[:, 0]), state_now[:, 3]], -1)
        return torch.where(held[:, None, None, None], hold[:, None, None].expand(n, g, h, 4), scene)

    @staticmethod
    def _scatter(rows: torch.Tensor, agents: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """Place per-row values ``(N, S, ...)`` into ``base (B, A, S, ...)`` at ``agents``; returns
        ``(B, S, A, ...)`` (differentiable w.r.t. ``rows``)."""
        full = base.clone()
        full[agents] = rows.to(full.dtype)
        return full.transpose(1, 2)

    def _draw(self, context: ScenarioTensor, agents: torch.Tensor, num_samples: int,
              generator: torch.Generator | None, modes: bool = False) -> _Draw:
        """Goal network on the ``agents (B, A)`` rows, ``num_samples`` sampled goals each (and the most likely
        goal when ``modes``), driven by the policy. Runs without gradients."""
        now = context.current_index
        with torch.no_grad():
            feats = select_rows(agent_features(context, self.cfg, agents), agents)
            state_now = context.states[:, :, now][agents]
            held = self._hold.mask(context)[agents]
            out = self.model.goal_net(feats)
            mask = feats["map"][:, 0].flatten(1) > 0
            if state_now.shape[0] == 0:
                empty = torch.zeros(0, num_samples, dtype=torch.long, device=context.device)
                index, log_p = empty, empty.float()
            else:
                index, log_p = self.model.sample_goals(out, mask, num_samples, generator)
            if modes:
                index = torch.cat([index, self.model.mode_goals(out, mask)], 1)
            local = self.model.policy.rollout(feats, self.model.goal_net.goal_at(out, index))
            futures = self._to_scene(local, state_now, held)
        return _Draw(index=index[:, :num_samples], log_p=log_p, mask=mask, local=local, futures=futures,
                     state_now=state_now, held=held)

    # ------------------------------------------------------------ contract
    def sample(self, context: ScenarioTensor, num_samples: int, guidance: GuidanceSet | None = None,
               generator: torch.Generator | None = None) -> SampleOutput:
        """Draw ``num_samples`` futures ``(B, S, A, 20, 4)`` for the controlled agents valid now.

        ``guidance`` is accepted for the interface: BITS does not steer its samples; :meth:`plan` filters them.
        All randomness comes from ``generator``.
        """
        self._check_dt(context)
        if self.options.train_on_selection:
            return self._sample_selected(context, num_samples, guidance, generator)
        agents = context.controlled & context.valid[:, :, context.current_index]
        draw = self._draw(context, agents, num_samples, generator)
        return self._output(context, agents, draw, num_samples, guidance)

    def _sample_selected(self, context: ScenarioTensor, groups: int, guidance: GuidanceSet | None,
                         generator: torch.Generator | None) -> SampleOutput:
        """``groups`` executed plans per agent, each chosen among ``plan_samples`` goals as :meth:`plan` does."""
        k = self.options.plan_samples
        out, choice = self._selection(context, groups, guidance, generator)  # choice (B, G, A) in 0..k-1
        b, _, a, h, _ = out.futures.shape
        futures = out.futures.reshape(b, groups, k, a, h, 4)
        futures = futures.gather(2, choice[:, :, None, :, None, None].expand(b, groups, 1, a, h, 4))[:, :, 0]
        cells = out.trace.tensors["cell"].reshape(b, groups, k, a).permute(0, 1, 3, 2)  # (B, G, A, K)
        drivable = out.trace.tensors["drivable"].reshape(b, groups, k, a, -1)[:, :, 0]
        trace = PolicyTrace(tensors={"cell": cells, "drivable": drivable}, agents=out.trace.agents,
                            now=out.trace.now, info={**out.trace.info, "selection": True})
        return SampleOutput(futures=futures, trace=trace,
                            log_prob=out.log_prob.reshape(b, groups, k, a).sum(2))

    def _output(self, context: ScenarioTensor, agents: torch.Tensor, draw: _Draw, s: int,
                guidance: GuidanceSet | None) -> SampleOutput:
        """Scatter the rows of ``draw`` into the contract's ``(B, S, A, ...)`` output (other slots hold still)."""
        b, a, h = context.num_scenes, context.num_agents, self.horizon
        now, dev = context.current_index, context.device
        current = context.states[:, :, now]
        hold = torch.stack([current[..., 0], current[..., 1], torch.zeros_like(current[..., 0]), current[..., 3]], -1)
        base = hold[:, :, None, None].expand(b, a, s, h, 4)
        cells = self.cfg.map_size**2
        mask = torch.zeros(b, a, cells, dtype=torch.bool, device=dev)
        mask[agents] = draw.mask
        trace = PolicyTrace(
            tensors={
                "cell": self._scatter(draw.index, agents, torch.zeros(b, a, s, dtype=torch.long, device=dev)),
                "drivable": mask[:, None].expand(b, s, a, cells),
            },
            agents=agents,
            now=now,
            info={"guidance": None if guidance is None else guidance.names},
        )
        return SampleOutput(
            futures=self._scatter(draw.futures[:, :s], agents, base),
            trace=trace,
            log_prob=self._scatter(draw.log_p, agents, torch.zeros(b, a, s, device=dev)),
        )

    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """``(B, S, A)`` log-probability of the traced goal cells under the current goal network, masked with the
        traced drivable mask (0 for agents not sampled). Differentiable w.r.t. the goal network."""
        if trace.now != context.current_index:
            raise ValueError(f"trace.now={trace.now} but context.current_index={context.current_index}; pass the "
                             "context the sample was drawn from.")
        agents = trace.agents.to(context.device)
        cell = trace.tensors["cell"]
        b, s, a = cell.shape[:3]
        k = cell.shape[3] if cell.dim() == 4 else 1  # goal sets (train_on_selection): K goals per sample
        rows = cell.reshape(b, s, a, k).transpose(1, 2)[agents].reshape(-1, s * k)  # (N, S*K)
        mask = trace.tensors["drivable"][:, 0][agents]  # (N, cells): the same for every sample
        feats = select_rows(agent_features(context, self.cfg, agents), agents)
        out = self.model.goal_net(feats)
        log_p = self.model.masked_log_probs(out.logits, mask).gather(1, rows).reshape(-1, s, k).sum(-1)
        return self._scatter(log_p, agents, torch.zeros(b, a, s, device=context.device))

    def imitation_loss(self, batch: ScenarioTensor) -> torch.Tensor:
        """The goal network's training loss (pixel CE + offset MSE + yaw MSE) on logged windows of ``batch``:
        every vehicle valid over the 2 s after up to ``imitation_windows`` evenly spaced steps (from the current
        index on, when the scene has that much future; else from the start). The policy is not involved."""
        self._check_dt(batch)
        h = self.horizon
        first = batch.current_index if batch.current_index + h < batch.num_steps else 0
        candidates = list(range(first, batch.num_steps - h, 5))
        if len(candidates) > self.options.imitation_windows:
            pick = torch.linspace(0, len(candidates) - 1, self.options.imitation_windows).round().long().tolist()
            candidates = [candidates[i] for i in pick]
        feats: dict[str, list[torch.Tensor]] = {}
        goals = []
        for t in candidates:
            mask = window_mask(batch, t, h)
            if not mask.any():
                continue
            rows = select_rows(agent_features(batch.replace_unchecked(current_index=t), self.cfg, mask), mask)
            _, states = future_targets(batch, t, h)
            final = states[mask][:, -1]
            goals.append(torch.stack([final[:, 0], final[:, 1], final[:, 3]], -1))
            for key, value in rows.items():
                feats.setdefault(key, []).append(value)
        if not goals:
            return sum(p.sum() * 0.0 for p in self.model.goal_net.parameters())  # type: ignore[return-value]
        data = {key: torch.cat(values) for key, values in feats.items()}
        loss, _ = self.model.goal_net.loss(self.model.goal_net(data), torch.cat(goals))
        return loss

    # ------------------------------------------------------------ BITS planning
    def selection_terms(self, context: ScenarioTensor, candidates: torch.Tensor, progress: torch.Tensor,
                        agents: torch.Tensor, others: torch.Tensor,
                        other_futures: torch.Tensor) -> dict[str, torch.Tensor]:
        """BITS's per-candidate terms ``(N, S)`` for the ``agents (B, A)`` rows with scene-frame ``candidates
        (N, S, H, 4)``: ``progress`` (m along the current heading at 2 s, given), collision (disk penetration
        against ``other_futures (B, A, H, 4)`` of the ``others (B, A)`` agents, self excluded) and drivable (share
        of box centre and corners off the drivable layer)."""
        n, s, h, _ = candidates.shape
        scene, slot = agents.nonzero(as_tuple=True)
        other_valid = others[scene].clone()  # (N, A)
        other_valid[torch.arange(n), slot] = False
        collision = disk_collision(candidates, other_futures[scene], context.extent[scene, slot],
                                   context.extent[scene], other_valid[..., None].expand(-1, -1, h))
        extent = context.extent[scene, slot][:, None, None].expand(n, s, h, 2)
        corners = box_corners(candidates[..., :2], candidates[..., 3], extent)  # (N, S, H, 4, 2)
        points = torch.cat([candidates[..., None, :2], corners], -2)  # (N, S, H, 5, 2)
        point_scene = scene[:, None, None, None].expand(n, s, h, 5).reshape(-1)
        on_road = context.map.lookup_points(point_scene, points.reshape(-1, 2))  # type: ignore[union-attr]
        drivable = 1.0 - on_road.reshape(n, s, h, 5).float().mean((-1, -2))
        return {"progress": progress, "collision": collision, "drivable": drivable}

    def _selection_cost(self, context: ScenarioTensor, agents: torch.Tensor, terms: dict[str, torch.Tensor],
                        futures: torch.Tensor, guidance: GuidanceSet | None) -> tuple[torch.Tensor, bool]:
        """``(cost (B, S, A), scene_level)``: minus BITS's score of the ``agents`` rows' candidates, plus the
        guidance loss of ``futures (B, S, A, H, 4)`` when a guidance is set (lower is executed first)."""
        score = selection_score(terms["progress"], terms["collision"], terms["drivable"],
                                tuple(self.options.selection_weights))  # (N, S)
        b, a, s = context.num_scenes, context.num_agents, score.shape[1]
        cost = self._scatter(-score, agents, torch.zeros(b, a, s, device=context.device))
        if guidance is None:
            return cost, False
        return cost + guidance.loss(futures, context.current_index, context), guidance.scene_level

    @torch.no_grad()
    def _selection(self, context: ScenarioTensor, groups: int, guidance: GuidanceSet | None,
                   generator: torch.Generator | None) -> tuple[SampleOutput, torch.Tensor]:
        """BITS's selection, ``groups`` times over: ``groups * plan_samples`` goals per controlled agent (group g
        holds samples ``g*K .. g*K+K-1``) and the index ``(B, G, A)`` in ``0..K-1`` of the chosen one per group.

        Scores ``0.01 progress - 15 collision - 1 drivable`` against the other agents' most-likely goals, minus the
        guidance loss when one is set (scene-level guidances choose one index per scene and group)."""
        now, k = context.current_index, self.options.plan_samples
        b, a, h = context.num_scenes, context.num_agents, self.horizon
        valid_now = context.valid[:, :, now]
        agents = context.controlled & valid_now
        # one goal-network pass over every agent present now: samples for the controlled ones, and the most
        # likely goal of each as the prediction the others are checked against (BITS's predictor role)
        draw = self._draw(context, valid_now, groups * k, generator, modes=True)
        modes = torch.zeros(b, a, h, 4, device=context.device)
        modes[valid_now] = draw.futures[:, -1]
        sub = agents[valid_now]  # which present agents are controlled
        draw_c = _Draw(*(t[sub] for t in draw))
        out = self._output(context, agents, draw_c, groups * k, guidance)
        progress = draw_c.local[:, : groups * k, -1, 0]
        progress = torch.where(draw_c.held[:, None], torch.zeros_like(progress), progress)
        terms = self.selection_terms(context, draw_c.futures[:, : groups * k], progress, agents, valid_now, modes)
        cost, scene_level = self._selection_cost(context, agents, terms, out.futures, guidance)
        # every (scene, group) pair is one selection among K: fold the groups into the batch
        choice = select_samples(cost.reshape(b * groups, k, a), agents.repeat_interleave(groups, 0), scene_level)
        return out, choice.reshape(b, groups, a)

    def reset(self, scenario: ScenarioTensor) -> None:
        """Fit the guidance and record which agents are stationary at the rollout start."""
        super().reset(scenario)
        self._hold.start(scenario)

    @torch.no_grad()
    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """BITS: sample ``plan_samples`` goals per agent, score each trajectory by
        ``0.01 progress - 15 collision - 1 drivable`` (minus the guidance loss when a guidance is set) and execute
        the best; extended at constant velocity beyond 2 s."""
        context = context.to(self.options.device)
        self._check_dt(context)
        with self._hold.planning():
            out, choice = self._selection(context, 1, self.guidance, self._generator)
        h = self.horizon
        chosen = out.futures.gather(1, choice[:, :, :, None, None].expand(-1, -1, -1, h, 4))[:, 0]
        return Plan(extend_constant_velocity(chosen, horizon, context.dt).cpu())
