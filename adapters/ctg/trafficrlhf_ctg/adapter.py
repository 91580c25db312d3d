"""``CTGAdapter``: the compact CTG (:mod:`ctg_reference`) behind the SDK's :class:`TrafficModelAdapter` contract.

* ``sample`` featurizes the sampled agents (controlled and valid now; other slots hold their current state and
  get log-probability 0), runs the DDIM sampler in each agent's frame, and rolls the actions out with the
  unicycle (no bounds, as in training) from each agent's current scene-frame state: futures ``(B, S, A, 20, 4)``.
* Guidance (CTG): at every non-final denoising step the posterior mean is moved by one sign-gradient step of
  the :class:`GuidanceSet` loss evaluated on the rolled-out scene-frame futures, clipped to +-sigma. The
  perturbation is stored in the trace (``guide_delta``) so :meth:`log_prob` recomputes the density the sample
  was actually drawn from.
* Trace: ``chain (B, S, A, K+1, 20, 2)`` (normalized x_K .. x_0) and ``guide_delta (B, S, A, K, 20, 2)``;
  log-probabilities are per denoising step, ``(B, S, A, K)`` with K = 5.
* Interaction (checkpoints trained with ``--neighbour-plan-steps``), ``plan_mode``: ``"proposal"`` (default)
  first draws an unguided proposal for every agent, then each agent's sample s conditioned on the proposals s of
  its sampled neighbours ahead; ``"joint"`` denoises all sampled agents in lockstep, each step of agent i's sample
  s conditioned on the positions its neighbours ahead reach in their current clean predictions of sample s (the
  first step sees no plans); ``"none"`` never shows plans. The neighbours' positions each step was conditioned
  on are stored in the trace (``plan_positions (B, S, A, K, F, 2)`` per denoising step, or ``(B, S, A, F, 2)``
  for the proposal), so ``log_prob`` recomputes exactly the density of the executed chain, the plans being part
  of its context.
* Scene-level denoising (checkpoints trained with ``--scene-denoising``): all sampled agents of a scene are
  denoised in lockstep, each step of agent i's sample s reading the current noisy samples s of its sampled
  neighbours; those are in the trace's ``chain``, so ``log_prob`` is exact without further state.
* Stationary agents (|v| <= ``stationary_speed``, upstream's 0.5 m/s) are held still (position and heading
  kept, speed 0), as upstream disables their control. ``stationary_rule="rollout_start"`` (upstream) decides from
  the speeds at the rollout start (``reset``), so an agent that stops later may drive off again; a direct
  ``sample`` call treats its context's current step as the start. Their chain is still sampled and scored
  normally, so ``log_prob`` stays exact; only their executed future ignores it (their guidance gradient is 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import Field

import ctg_reference
from ctg_reference.data import (
    agent_features,
    co_denoised_rows,
    drop_neighbour_plans,
    future_targets,
    logged_neighbour_plans,
    neighbour_plan_features,
    select_rows,
    window_mask,
)
from ctg_reference.model import CTGConfig, CTGModel, SceneRows, SteerMap
from trafficrlhf_sdk.simulation.dynamics import unicycle_rollout
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.models.adapter import AdapterOptions, PolicyTrace, SampleOutput, TrafficModelAdapter
from trafficrlhf_sdk.models.random import SceneGenerators
from trafficrlhf_sdk.models.stationary import StationaryHold, StationaryRule
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan

__all__ = ["CTGAdapter", "CTGOptions", "default_checkpoint"]


STEER_INIT_SEED = 0  # the draw of a fresh steering head's hidden layers (the same in every run)


def default_checkpoint() -> Path:
    """The checkpoint bundled with ``trafficrlhf-reference-ctg`` (``reference_models/ctg/checkpoints/ctg_small``)."""
    return Path(ctg_reference.__file__).resolve().parent.parent / "checkpoints" / "ctg_small"


class CTGOptions(AdapterOptions):
    """Options of :class:`CTGAdapter`."""

    stationary_speed: float = Field(0.5, ge=0, description="Agents at or below this speed (m/s) are held still.")
    stationary_rule: StationaryRule = Field(
        "rollout_start", description="When the speed is read: 'rollout_start' (upstream; once, at reset) or "
        "'every_replan' (the current speed at each replan, so an agent that stops stays stopped).")
    imitation_windows: int = Field(4, ge=1, description="Time steps per scene sampled by imitation_loss.")
    plan_mode: Literal["joint", "proposal", "none"] = Field(
        "proposal", description="For checkpoints with neighbour_plan_steps, what each agent sees of its "
        "neighbours' plans: 'proposal' (an unguided first pass), 'joint' (their clean predictions at every "
        "denoising step) or 'none' (no plans; an ablation).")
    steer: bool = Field(False, description="Add a zero-initialized steering head (ctg_reference.SteerHead) to a "
                        "checkpoint that has none, offered as the parameter group 'steer': fine-tuning only it "
                        "moves the sampler through the frozen encoder and denoiser. Checkpoints saved with a head "
                        "load it without this option.")
    steer_road: bool = Field(False, description="As `steer`, with a head that also reads the drivable layer along "
                             "each denoising step's clean plan (ctg_reference.road_profile): whether a plan leaves "
                             "the road becomes one of its inputs.")
    steer_neighbours: bool = Field(False, description="As `steer`, with a head that also reads how close the other "
                                   "agents (driven on at constant velocity) come to each denoising step's clean "
                                   "plan (ctg_reference.neighbour_proximity); combines with `steer_road`. On a "
                                   "saved road head it widens the head: the new inputs start with zero weights, so "
                                   "the head's output is unchanged until fine-tuned.")
    follow: bool = Field(False, description="Add a zero-initialized gap-keeping head (ctg_reference.FollowHead) to "
                         "a checkpoint that has none, offered as the parameter group 'follow'. It shifts only the "
                         "acceleration channel, reads the gap to the agent ahead in each denoising step's clean plan "
                         "(ctg_reference.lead_gaps) and acts only where that gap is below follow_standstill + "
                         "follow_headway x the planned speed; any steering head is kept. Checkpoints saved with one "
                         "load it without this option.")
    follow_standstill: float | None = Field(None, gt=0, description="The gap-keeping head's desired gap at "
                                            "standstill (m); None keeps the checkpoint's setting (a new head: "
                                            "1.5 m).")
    follow_headway: float | None = Field(None, ge=0, description="The gap-keeping head's desired time gap at the "
                                         "planned speed (s); None keeps the checkpoint's setting (a new head: "
                                         "0.5 s).")
    follow_ttc: float | None = Field(None, gt=0, description="Gate the gap-keeping head by the time to collision "
                                     "with the agent ahead instead of the desired gap: clamp(1 - TTC / follow_ttc, "
                                     "0, 1) while closing in, 0 otherwise (s). None keeps the checkpoint's "
                                     "setting (a new head: the desired-gap gate).")
    follow_heading_cos: float | None = Field(None, ge=-1, le=1, description="Only agents heading the plan's way "
                                             "lead the gap-keeping head: the cosine of the heading difference at "
                                             "least this (0.7: within about 45 degrees), so oncoming and crossing "
                                             "agents driven on at constant velocity do not open its gate. None "
                                             "keeps the checkpoint's setting (a new head: every agent in the path).")
    follow_gate_steps: int | None = Field(None, ge=1, description="The gap-keeping head's gate reads only the first "
                                          "this many plan steps (0.1 s each; 5 is what runs before the next 2 Hz "
                                          "replan), while the head still reads them all. None keeps the "
                                          "checkpoint's setting (a new head: the whole plan).")
    follow_brake: float | None = Field(None, description="Start a new gap-keeping head (follow=true) braking: "
                                       "its output layer's bias, so a plan inside the desired gap has its "
                                       "acceleration mean shifted by sigma_k x gate x tanh(follow_brake) per "
                                       "denoising step (negative brakes; -3 is nearly the head's full authority). "
                                       "None: a zero head, sampling as without one.")
    steer_gate: bool | None = Field(None, description="Scale a reading head's shift by its plan's hazard (the "
                                    "off-road share and neighbour proximity along it, largest value), so plans "
                                    "with a clear road and nobody near are not steered; None keeps the "
                                    "checkpoint's setting. Applies to a fresh head or a saved one.")


class CTGAdapter(TrafficModelAdapter):
    """Compact CTG diffusion traffic model; its plan horizon comes from the checkpoint (20 steps = 2 s at 0.1 s for
    the bundled ``ctg_small``, 40 for ``ctg_small_4s``)."""

    name = "ctg"
    Options = CTGOptions
    horizon = 20
    scene_generators = True

    # ------------------------------------------------------------ construction
    def build(self, config: dict[str, Any] | None) -> None:
        """``config`` None: architecture and weights from ``options.checkpoint`` or the bundled checkpoint.
        Otherwise build ``config`` and load weights only if ``options.checkpoint`` is set."""
        self.cfg, self.model = self.load_architecture(
            config, str(default_checkpoint()),
            "python -m ctg_reference.train --out reference_models/ctg/checkpoints/ctg_small",
            CTGConfig, CTGModel,
        )
        opts = self.options
        if (opts.steer or opts.steer_road or opts.steer_neighbours) and not self.cfg.steer:
            self._add_steer_head(opts.steer_road, opts.steer_neighbours)
        elif opts.steer_neighbours and not self.cfg.steer_neighbours:
            self._widen_steer_head()
        if opts.follow and not self.cfg.follow:
            self._add_gap_head("follow", opts.follow_brake)
        elif opts.follow_brake is not None:
            raise TrafficRLHFError(f"follow_brake={opts.follow_brake} sets a new gap-keeping head's start; add "
                                   "follow=true to a checkpoint without one (a saved head keeps its weights).")
        gaps = {"follow_standstill": opts.follow_standstill, "follow_headway": opts.follow_headway,
                "follow_ttc": opts.follow_ttc, "follow_heading_cos": opts.follow_heading_cos,
                "follow_gate_steps": opts.follow_gate_steps}
        gaps = {key: value for key, value in gaps.items() if value is not None}
        if gaps and not self.cfg.follow:
            raise TrafficRLHFError(f"{', '.join(f'{k}={v}' for k, v in gaps.items())} sets the gap-keeping head's "
                                   "desired gap or gate; add follow=true (or load a checkpoint saved with that head).")
        if gaps:
            self.cfg = self.model.cfg = dataclasses.replace(self.cfg, **gaps)
        if opts.steer_gate is not None:
            self.cfg = self.model.cfg = dataclasses.replace(self.cfg, steer_gate=opts.steer_gate)
            if self.cfg.steer_gate and not (self.cfg.steer and (self.cfg.steer_road or self.cfg.steer_neighbours)):
                raise TrafficRLHFError("steer_gate=true needs a steering head that reads the road or the traffic; "
                                       "add steer_road=true or steer_neighbours=true (or load a checkpoint with one).")
        self.horizon = self.cfg.horizon
        self.history_steps = self.cfg.history_steps
        self.model.eval()
        self._hold = StationaryHold(self.options.stationary_speed, self.options.stationary_rule)

    def _add_steer_head(self, road: bool, neighbours: bool = False) -> None:
        """Rebuild the model with a fresh (zero) steering head (reading the road with ``road``, the other agents
        with ``neighbours``), keeping every trained weight (:meth:`_add_head`)."""
        self._add_head(dataclasses.replace(self.cfg, steer=True, steer_road=road, steer_neighbours=neighbours),
                       "steer.")

    def _add_gap_head(self, name: str, bias: float | None = None) -> None:
        """Rebuild the model with a fresh gap-keeping head ``name`` (``follow``: the agent ahead), keeping every
        trained weight, the other heads' too (:meth:`_add_head`); the head is zero, or with ``bias`` its output bias
        (weights still zero)."""
        self._add_head(dataclasses.replace(self.cfg, **{name: True}), f"{name}.")
        if bias is not None:
            last = getattr(self.model, name).net[-1]
            assert isinstance(last, torch.nn.Linear)
            with torch.no_grad():
                last.bias.fill_(bias)

    def _add_head(self, cfg: CTGConfig, prefix: str) -> None:
        """Rebuild the model as ``cfg``, whose only new tensors are those under ``prefix``, copying every other
        weight. The new head's hidden layers are one fixed draw (seed 0), so every run starts from the same
        weights: runs with different seeds can be averaged, and a run repeats exactly."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(STEER_INIT_SEED)
            model = CTGModel(cfg).to(self.options.device)
        missing, unexpected = model.load_state_dict(self.model.state_dict(), strict=False)
        assert not unexpected and all(key.startswith(prefix) for key in missing), (missing, unexpected)
        self.cfg, self.model = cfg, model

    def _widen_steer_head(self) -> None:
        """Give a saved road-reading head the neighbour inputs of :func:`ctg_reference.neighbour_proximity`: the
        first layer gains ``3 * horizon`` columns with zero weights (interleaved per step after the road profile, as
        the head concatenates them), so the head's output is unchanged until fine-tuned."""
        if not self.cfg.steer_road:
            raise TrafficRLHFError("steer_neighbours=true on a saved head widens a road-reading head only; this "
                                   "checkpoint's head reads neither road nor traffic. Start from a checkpoint "
                                   "without a head, or one saved with steer_road=true.")
        cfg = dataclasses.replace(self.cfg, steer_neighbours=True)
        model = CTGModel(cfg).to(self.options.device)
        state = self.model.state_dict()
        old = state.pop("steer.net.0.weight")
        missing, unexpected = model.load_state_dict(state, strict=False)
        assert not unexpected and missing == ["steer.net.0.weight"], (missing, unexpected)
        base = old.shape[1] - 3 * cfg.horizon  # conditioning, plan and step embedding come first
        weight = old.new_zeros(old.shape[0], base + 6 * cfg.horizon)
        weight[:, :base] = old[:, :base]
        weight[:, base:].view(old.shape[0], cfg.horizon, 6)[..., :3] = old[:, base:].view(old.shape[0], -1, 3)
        assert model.steer is not None
        with torch.no_grad():
            model.steer.net[0].weight.copy_(weight)
        self.cfg, self.model = cfg, model

    def get_config(self) -> dict[str, Any]:
        """The model's :class:`CTGConfig` as a dict (normalization statistics included)."""
        return self.model.cfg.to_dict()

    @property
    def module(self) -> torch.nn.Module:
        """The :class:`CTGModel`."""
        return self.model

    def parameter_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """``encoder`` (map CNN, history and neighbour MLPs, fusion), ``decoder`` (the temporal U-Net, and the
        co-denoising mixer of scene-denoising models) and, with a steering head, ``steer``; with a gap-keeping
        head, ``follow``."""
        decoder = list(self.model.denoiser.parameters())
        if self.model.mixer is not None:
            decoder += list(self.model.mixer.parameters())
        groups = {"encoder": list(self.model.encoder.parameters()), "decoder": decoder}
        if self.model.steer is not None:
            groups["steer"] = list(self.model.steer.parameters())
        if self.model.follow is not None:
            groups["follow"] = list(self.model.follow.parameters())
        return groups

    # ------------------------------------------------------------ helpers
    def _check_dt(self, context: ScenarioTensor) -> None:
        if abs(context.dt - self.cfg.dt) > 1e-9:
            raise ValueError(f"the CTG model runs at dt={self.cfg.dt} s; the scenario has dt={context.dt} s. Load "
                             "the scenes with dt=0.1.")

    def _plan_encoder(self, context: ScenarioTensor, agents: torch.Tensor
                      ) -> tuple[Callable[[torch.Tensor | None], torch.Tensor], SceneRows | None, SteerMap | None]:
        """``f(plan_positions (B, S, A, F, 2) or None) -> cond`` for the ``agents`` rows, featurizing the context
        and encoding map and history once (the plans change between denoising steps, the rest does not); for a
        scene-denoising model, the rows' co-denoised neighbours (the other ``agents`` rows); and for a steering
        head that reads the road or the traffic, the rows' drivable crop (the first map layer) and speed (and
        their neighbours and extent)."""
        features = agent_features(context, self.cfg, crop_agents=agents)
        rows = select_rows(features, agents)
        if self.model.mixer is not None:
            rows["neighbour_row"] = co_denoised_rows(agents, features["neighbour_index"], features["neighbour_valid"])
        own = self.model.encoder.own(rows["map"], rows["history"], rows["history_valid"], rows["extent"])

        def encode(plan_positions: torch.Tensor | None) -> torch.Tensor:
            if plan_positions is None:
                return self.model.encode(rows, own)
            b, s, a, f, _ = plan_positions.shape
            known = agents[:, None, :, None].expand(b, s, a, f)
            plan, valid = neighbour_plan_features(context, features["neighbours"], features["neighbour_valid"],
                                                  features["neighbour_index"], plan_positions, known)
            with_plans = {**rows, "neighbour_plan": plan.transpose(1, 2)[agents],  # (N, S, K, F, 2)
                          "neighbour_plan_valid": valid.transpose(1, 2)[agents]}
            return self.model.encode(with_plans, own)

        steer_map: SteerMap | None = None
        if self.cfg.steer_road or self.cfg.steer_neighbours or self.cfg.follow:
            steer_map = (rows["map"][:, :1], rows["v0"])
            if self.cfg.steer_neighbours or self.cfg.follow:
                steer_map += (rows["neighbours"], rows["neighbour_valid"], rows["extent"])
        return encode, self.model.scene_rows(rows), steer_map

    def _plan_positions(self, futures: torch.Tensor) -> torch.Tensor:
        """Positions ``(B, S, A, F, 2)`` of scene-frame ``futures (B, S, A, H, 4)`` at the plan steps."""
        steps = torch.tensor(self.cfg.neighbour_plan_steps, device=futures.device) - 1
        return futures[..., steps, :2]

    def _rollout(self, x: torch.Tensor, state_now: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
        """Scene-frame futures ``(N, S, H, 4)`` of normalized actions ``x (N, S, H, 2)`` from ``state_now (N, 4)``;
        the rows where ``held (N,)`` is True stay still."""
        n, s, h, _ = x.shape
        start = state_now[:, None].expand(n, s, 4)
        states = unicycle_rollout(start, self.model.unnormalize(x), dt=self.cfg.dt, bounds=None)
        hold = torch.stack([state_now[:, 0], state_now[:, 1], torch.zeros_like(state_now[:, 0]), state_now[:, 3]], -1)
        still = held[:, None, None, None]
        return torch.where(still, hold[:, None, None].expand(n, s, h, 4), states)

    @staticmethod
    def _scatter(rows: torch.Tensor, agents: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """Place per-row values ``(N, S, ...)`` into ``base (B, A, S, ...)`` at ``agents``; returns
        ``(B, S, A, ...)`` (differentiable w.r.t. ``rows``)."""
        full = base.clone()
        full[agents] = rows.to(full.dtype)
        return full.transpose(1, 2)

    # ------------------------------------------------------------ contract
    def sample(self, context: ScenarioTensor, num_samples: int, guidance: GuidanceSet | None = None,
               generator: torch.Generator | SceneGenerators | None = None) -> SampleOutput:
        """Draw ``num_samples`` futures ``(B, S, A, H, 4)``, H = ``self.horizon``, for the controlled agents valid
        now."""
        self._check_dt(context)
        now = context.current_index
        b, a, s, h = context.num_scenes, context.num_agents, num_samples, self.horizon
        k = self.cfg.sample_steps
        agents = context.controlled & context.valid[:, :, now]
        if isinstance(generator, SceneGenerators):  # one stream per group of scenes, over this call's rows
            generator = generator.rows(agents.nonzero(as_tuple=True)[0], per_row=s)
        current = context.states[:, :, now]  # (B, A, 4)
        hold = torch.stack([current[..., 0], current[..., 1], torch.zeros_like(current[..., 0]), current[..., 3]], -1)
        base_futures = hold[:, :, None, None].expand(b, a, s, h, 4)
        mode = self.options.plan_mode if self.cfg.neighbour_plan_steps else "none"
        plan_positions, cond_fn = None, None
        with torch.no_grad():
            encode, scene, steer_map = self._plan_encoder(context, agents)
            cond, state_now = encode(None), context.states[:, :, now][agents]
            held = self._hold.mask(context)[agents]
            # inside plan() the held agents' samples are never executed and no trace is kept: skip their denoising
            active = ~held if self._hold.in_plan else None
            if mode == "proposal" and cond.shape[0] > 0:  # an unguided proposal, then the plans
                proposal, _, _, _ = self.model.sample(cond, s, generator, steer_map=steer_map, active=active)
                plan_positions = self._plan_positions(self._scatter(
                    self._rollout(self.model.normalize(proposal), state_now, held), agents, base_futures))
                cond = encode(plan_positions)
            elif mode == "joint" and cond.shape[0] > 0:
                step_plans = [self._plan_positions(base_futures.transpose(1, 2))]  # first step: unused

                def cond_fn(step: int, x0: torch.Tensor) -> torch.Tensor:
                    step_plans.append(self._plan_positions(self._scatter(self._rollout(x0, state_now, held), agents,
                                                                         base_futures)))
                    return encode(step_plans[-1])

            guidance_fn = None
            if guidance is not None and cond.shape[0] > 0:
                def guidance_fn(mean: torch.Tensor, step: int) -> torch.Tensor:
                    futures = self._scatter(self._rollout(mean, state_now, held), agents, base_futures)
                    loss = guidance.loss(futures, now, context)  # (B, S, A)
                    return (loss * agents[:, None]).sum()

            actions, chain, delta, log_prob = self.model.sample(cond, s, generator, guidance_fn, cond_fn, scene,
                                                                steer_map, active)
            if cond_fn is not None:
                plan_positions = torch.stack(step_plans, 3)  # (B, S, A, K, F, 2)
            futures = self._rollout(self.model.normalize(actions), state_now, held)
        dev = context.device
        tensors = {
            "chain": self._scatter(chain, agents, torch.zeros(b, a, s, k + 1, h, 2, device=dev)),
            "guide_delta": self._scatter(delta, agents, torch.zeros(b, a, s, k, h, 2, device=dev)),
        }
        if plan_positions is not None:
            tensors["plan_positions"] = plan_positions
        trace = PolicyTrace(
            tensors=tensors,
            agents=agents,
            now=now,
            info={"guidance": None if guidance is None else guidance.names},
        )
        return SampleOutput(
            futures=self._scatter(futures, agents, base_futures),
            trace=trace,
            log_prob=self._scatter(log_prob, agents, torch.zeros(b, a, s, k, device=dev)),
        )

    def reset(self, scenario: ScenarioTensor) -> None:
        """Fit the guidance and record which agents are stationary at the rollout start."""
        super().reset(scenario)
        self._hold.start(scenario)

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """The base planner (guided samples, the lowest guidance loss executed), holding the agents that
        ``stationary_rule`` marks as stationary."""
        with self._hold.planning():
            return super().plan(context, horizon)

    def _chain_inputs(self, context: ScenarioTensor, trace: PolicyTrace) -> tuple[Any, ...]:
        """What :meth:`log_prob` and :meth:`transition_kl` hand the model for the traced chains."""
        if trace.now != context.current_index:
            raise ValueError(f"trace.now={trace.now} but context.current_index={context.current_index}; pass the "
                             "context the sample was drawn from.")
        agents = trace.agents.to(context.device)
        chain = trace.tensors["chain"].transpose(1, 2)[agents]  # (N, S, K+1, H, 2)
        delta = trace.tensors["guide_delta"].transpose(1, 2)[agents]
        k = chain.shape[2] - 1
        s = chain.shape[1]
        plans = trace.tensors.get("plan_positions")
        encode, scene, steer_map = self._plan_encoder(context, agents)
        if plans is None or plans.dim() == 5:  # no plans, or one proposal for every step
            cond = encode(plans)
        else:  # per denoising step; the first saw no plans
            cond = torch.stack([encode(None)[:, None].expand(-1, s, -1)]
                               + [encode(plans[:, :, :, i]) for i in range(1, k)], 2)  # (N, S, K, D)
        return agents, cond, chain, delta, scene, steer_map

    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """Per-denoising-step log-probabilities ``(B, S, A, K)`` of the traced chains (0 for other agents)."""
        agents, cond, chain, delta, scene, steer_map = self._chain_inputs(context, trace)
        b, s, a = trace.tensors["chain"].shape[:3]
        log_prob = self.model.chain_log_prob(cond, chain, delta, scene, steer_map)  # (N, S, K)
        return self._scatter(log_prob, agents, torch.zeros(b, a, s, chain.shape[2] - 1, device=context.device))

    def transition_kl(self, context: ScenarioTensor, trace: PolicyTrace, reference: CTGAdapter) -> torch.Tensor:
        """Per-denoising-step KL ``(B, S, A, K)`` from this model's Gaussian transitions of the traced chains to
        ``reference``'s, in closed form: ``||mu - mu_ref||^2 / (2 sigma^2)`` summed over the plan (the bound DPOK
        optimizes); finite by construction, exactly 0 while the two models are equal. Gradients flow into this
        model only."""
        agents, cond, chain, delta, scene, steer_map = self._chain_inputs(context, trace)
        b, s, a = trace.tensors["chain"].shape[:3]
        mean, sigma = self.model.chain_means(cond, chain, delta, scene, steer_map)
        with torch.no_grad():
            ref = reference._chain_inputs(context, trace)
            ref_mean, _ = reference.model.chain_means(*ref[1:])
        kl = ((mean - ref_mean) ** 2).sum((-1, -2)) / (2 * sigma**2)  # (N, S, K)
        return self._scatter(kl, agents, torch.zeros(b, a, s, chain.shape[2] - 1, device=context.device))

    def imitation_loss(self, batch: ScenarioTensor) -> torch.Tensor:
        """The diffusion training loss on logged windows of ``batch``: every vehicle with 1 s of valid history
        and a valid future of the model's horizon at up to ``imitation_windows`` evenly spaced steps; for a model
        with a steering or gap-keeping head, plus :meth:`CTGModel.head_loss` (the steered sampler's loss on the
        same windows), so the heads are held to the log too. Noise levels and noise are drawn from torch's global
        generator."""
        self._check_dt(batch)
        th, h = self.cfg.history_steps, self.horizon
        candidates = list(range(th, batch.num_steps - h, 5))
        if len(candidates) > self.options.imitation_windows:
            pick = torch.linspace(0, len(candidates) - 1, self.options.imitation_windows).round().long().tolist()
            candidates = [candidates[i] for i in pick]
        actions_all = batch.actions()
        parts: dict[str, list[torch.Tensor]] = {}
        offset = 0  # scene-denoising models: rows of one window (scene, t) are denoised together, at one noise level
        for t in candidates:  # a few time windows; agents are batched
            mask = window_mask(batch, t, h, th)
            if not mask.any():
                continue
            at_t = batch.replace_unchecked(current_index=t)
            features = agent_features(at_t, self.cfg, crop_agents=mask)
            rows = select_rows(features, mask)
            if self.model.mixer is not None:
                row = co_denoised_rows(mask, features["neighbour_index"], features["neighbour_valid"])
                rows["neighbour_row"] = torch.where(row >= 0, row + offset, row)
                scene = torch.arange(batch.num_scenes, device=mask.device)[:, None].expand_as(mask)[mask]
                rows["group"] = scene + len(parts.get("v0", [])) * batch.num_scenes
                offset += int(mask.sum())
            if self.cfg.neighbour_plan_steps:  # as in training: logged plans, randomly hidden
                plan, valid = logged_neighbour_plans(at_t, self.cfg, features)
                rows["neighbour_plan"] = plan[mask]
                rows["neighbour_plan_valid"] = drop_neighbour_plans(valid[mask], self.cfg)
            acts, states = future_targets(batch, t, h, actions_all)
            rows["actions"], rows["states"] = acts[mask], states[mask]
            for key, value in rows.items():
                parts.setdefault(key, []).append(value)
        if not parts:
            return sum(p.sum() * 0.0 for p in self.model.parameters())  # type: ignore[return-value]
        data = {key: torch.cat(values) for key, values in parts.items()}
        group = torch.unique(data["group"], return_inverse=True)[1] if "group" in data else None
        cond = self.model.encode(data)
        loss, _ = self.model.loss(cond, data["actions"], data["v0"], data["states"],
                                  scene=self.model.scene_rows(data), group=group)
        if self.model.steer is None and self.model.follow is None:
            return loss
        steer_map = (data["map"][:, :1], data["v0"], data["neighbours"], data["neighbour_valid"], data["extent"])
        return loss + self.model.head_loss(cond, data["actions"], data["v0"], steer_map, data["states"])
