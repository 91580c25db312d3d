"""A compact CTG (Controllable Traffic Generation, Zhong et al. 2023) in plain PyTorch.

This package knows nothing of the TrafficRLHF SDK: it takes per-agent tensors and returns per-agent tensors.
This module holds the diffusion model; its configuration is in :mod:`ctg_reference.config`, the networks in
:mod:`ctg_reference.networks` and the sampler's steering head in :mod:`ctg_reference.steering`.

* Context encoder: a small CNN over an agent-centric map crop, an MLP over the agent's recent history (and its
  box size), an MLP + max-pool over its nearest neighbours, fused into a conditioning vector.
* Denoiser: a 1-D temporal U-Net (Conv1d residual blocks, GroupNorm, Mish, one down/up level) whose blocks get the
  diffusion-time embedding concatenated with the conditioning vector as a per-channel bias. It predicts the clean
  sample x0 (not the noise) over ``horizon`` steps of normalized (acceleration, yaw rate).
* Diffusion: cosine beta schedule (s = 0.008) with ``diffusion_steps`` training steps. Training loss = MSE on
  normalized actions + MSE on normalized agent-frame states rebuilt from the actions by a unicycle rollout.
* Sampling: DDIM over ``sample_steps`` of the training steps with ``eta`` > 0, so every step is a Gaussian
  ``p(x_prev | x_k) = N(mu_theta(x_k) + delta_k, sigma_k^2)``. ``delta_k`` is the CTG guidance perturbation
  (one sign-gradient step of size ``guidance_step`` on the posterior mean, clipped to +-sigma_k, none at the
  last step); it is stored with the chain so :meth:`CTGModel.chain_log_prob` recomputes exactly the density the
  sample was drawn from.
* Scene-level denoising (``scene_denoising``): the agents of one scene are denoised together. At every step a
  :class:`CoDenoiseMixer` reads the current noisy samples of the neighbours being denoised with the agent (rows
  named by ``neighbour_row``) and shifts its conditioning; training draws one noise level per scene and step.
  Each step stays a Gaussian given every row's current sample, so the chain's density remains exact.
* Steering (``steer``): a :class:`SteerHead` adds ``sigma_k * tanh(g(cond, x0_k, k))`` to each step's mean. It
  starts at zero; fine-tuned alone it moves where the sampler goes through the frozen denoiser. With
  ``steer_road`` it also reads the drivable layer along ``x0_k``'s plan (:func:`road_profile`); with
  ``steer_neighbours``, how close the other agents come to that plan (:func:`neighbour_proximity`).
* Gap keeping (``follow``): a :class:`FollowHead` adds ``sigma_k * gate * tanh(g)`` to the acceleration channel
  only, reading the gap to the agent ahead in ``x0_k``'s path (:func:`lead_gaps`); the gate is the plan's
  largest headway hazard, 0 unless someone is ahead closer than the desired gap (with ``follow_ttc``: the largest
  time-to-collision hazard, 0 unless closing in on someone ahead; with ``follow_gate_steps``: read over the
  plan's first steps only).

Agent frame: origin at the agent's current position, x along its current heading. States are
``(x, y, speed, yaw)``; actions ``(acceleration m/s^2, yaw rate rad/s)``; one unicycle step of ``dt``::

    x' = x + dt cos(yaw) (v + a dt / 2),  y' = y + dt sin(yaw) (v + a dt / 2),  v' = v + a dt,  yaw' = yaw + w dt
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from trafficrlhf_sdk.models.random import draw_normal

from ctg_reference.config import CTGConfig
from ctg_reference.networks import CoDenoiseMixer, ContextEncoder, TemporalUNet
from ctg_reference.steering import (
    LEAD_GAP_CLIP,
    MAP_BEHIND_FRACTION,
    FollowHead,
    SteerHead,
    lead_gaps,
    neighbour_proximity,
    road_profile,
)

__all__ = ["MAP_BEHIND_FRACTION", "CTGConfig", "CTGModel", "CoDenoiseMixer", "ContextEncoder", "FollowHead",
           "SteerHead", "TemporalUNet", "cosine_alphas_bar", "lead_gaps", "neighbour_proximity", "road_profile",
           "unicycle_from_origin"]

LOG_2PI = math.log(2 * math.pi)
# a reading steering head's inputs, per row: drivable crop (N, 1, G, G) and speed v0 (N,); with steer_neighbours
# also the neighbours (N, K, 7) as in the features, their valid mask (N, K) and the row's own extent (N, 2)
SteerMap = tuple[torch.Tensor, ...]


# --------------------------------------------------------------------------------------------- utilities
def draw_device(generator: torch.Generator | None, device: torch.device | str) -> torch.device | str:
    """Where random draws for tensors on ``device`` are made: on the generator's own device (a CPU generator
    cannot draw on a GPU), then moved. A seeded CPU generator thus gives a GPU run the CPU run's noise."""
    return generator.device if generator is not None else device


def cosine_alphas_bar(steps: int, s: float = 0.008) -> torch.Tensor:
    """Cumulative products of (1 - beta) of the cosine schedule (Nichol & Dhariwal), ``(steps,)`` float64."""
    x = torch.linspace(0, steps, steps + 1, dtype=torch.float64)
    f = torch.cos(((x / steps) + s) / (1 + s) * math.pi / 2) ** 2
    f = f / f[0]
    betas = (1 - f[1:] / f[:-1]).clamp(0, 0.999)
    return torch.cumprod(1 - betas, 0)


def unicycle_from_origin(actions: torch.Tensor, v0: torch.Tensor, dt: float) -> torch.Tensor:
    """Unicycle rollout (no bounds) from ``(0, 0, v0, 0)``: actions ``(..., H, 2)``, ``v0 (...)`` ->
    states ``(..., H, 4)`` (yaw not wrapped; it stays small in the agent frame)."""
    acc, yaw_rate = actions.unbind(-1)
    v0 = v0[..., None]
    v = v0 + dt * torch.cumsum(acc, -1)
    yaw = dt * torch.cumsum(yaw_rate, -1)
    v_prev = torch.cat([v0, v[..., :-1]], -1)
    yaw_prev = torch.cat([torch.zeros_like(v0), yaw[..., :-1]], -1)
    travel = dt * (v_prev + 0.5 * dt * acc)
    x = torch.cumsum(travel * torch.cos(yaw_prev), -1)
    y = torch.cumsum(travel * torch.sin(yaw_prev), -1)
    return torch.stack([x, y, v, yaw], -1)



# --------------------------------------------------------------------------------------------- model
SceneRows = tuple[torch.Tensor, torch.Tensor]  # (neighbour_in (N, K, 8), neighbour_row (N, K)), see CoDenoiseMixer
GuidanceFn = Callable[[torch.Tensor, int], torch.Tensor]
CondFn = Callable[[int, torch.Tensor], torch.Tensor]

class CTGModel(nn.Module):
    """Encoder + denoiser + diffusion utilities. Actions are normalized with the config's mean/std."""

    def __init__(self, cfg: CTGConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or CTGConfig()
        self.encoder = ContextEncoder(self.cfg)
        self.denoiser = TemporalUNet(self.cfg)
        self.mixer = CoDenoiseMixer(self.cfg) if self.cfg.scene_denoising else None
        self.steer = SteerHead(self.cfg) if self.cfg.steer else None
        self.follow = FollowHead(self.cfg) if self.cfg.follow else None
        self.register_buffer("action_mean", torch.tensor(self.cfg.action_mean, dtype=torch.float32))
        self.register_buffer("action_std", torch.tensor(self.cfg.action_std, dtype=torch.float32))
        self.register_buffer("state_std", torch.tensor(self.cfg.state_std, dtype=torch.float32))
        self.register_buffer("alphas_bar", cosine_alphas_bar(self.cfg.diffusion_steps).float(), persistent=False)

    # ------------------------------------------------------------ schedule
    @property
    def sample_schedule(self) -> list[tuple[int, int]]:
        """DDIM transitions ``(k, k_prev)``: ``sample_steps`` evenly spaced steps from K-1 down to 0."""
        k = self.cfg.diffusion_steps
        points = [round((k - 1) * (1 - i / self.cfg.sample_steps)) for i in range(self.cfg.sample_steps + 1)]
        return list(zip(points[:-1], points[1:]))

    def set_normalization(self, action_mean: torch.Tensor, action_std: torch.Tensor, state_std: torch.Tensor) -> None:
        """Set the normalization statistics (buffers and config)."""
        self.action_mean.copy_(action_mean)
        self.action_std.copy_(action_std)
        self.state_std.copy_(state_std)
        self.cfg.action_mean = [float(v) for v in action_mean]
        self.cfg.action_std = [float(v) for v in action_std]
        self.cfg.state_std = [float(v) for v in state_std]

    def normalize(self, actions: torch.Tensor) -> torch.Tensor:
        """Physical actions -> normalized."""
        return (actions - self.action_mean) / self.action_std

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Normalized actions -> physical (m/s^2, rad/s)."""
        return x * self.action_std + self.action_mean

    def rollout(self, x: torch.Tensor, v0: torch.Tensor) -> torch.Tensor:
        """Agent-frame states ``(..., H, 4)`` of normalized actions ``x (..., H, 2)`` from speed ``v0 (...)``."""
        return unicycle_from_origin(self.unnormalize(x), v0, self.cfg.dt)

    # ------------------------------------------------------------ networks
    def encode(self, features: dict[str, torch.Tensor],
               own: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Conditioning ``(N, cond_dim)`` (``(N, S, cond_dim)`` for per-sample neighbour plans) from a feature
        dict (keys: map, history, history_valid, extent, neighbours, neighbour_valid, optionally neighbour_plan
        and neighbour_plan_valid); ``own`` reuses :meth:`ContextEncoder.own`'s output for the same rows."""
        if own is None:
            own = self.encoder.own(features["map"], features["history"], features["history_valid"],
                                   features["extent"])
        return self.encoder.combine(*own, features["neighbours"], features["neighbour_valid"],
                                    features.get("neighbour_plan"), features.get("neighbour_plan_valid"))

    def scene_rows(self, features: dict[str, torch.Tensor]) -> SceneRows | None:
        """The mixer's inputs from a feature dict with ``neighbour_row (N, K)`` (rows denoised together), or None
        for a model without scene-level denoising."""
        if self.mixer is None:
            return None
        if "neighbour_row" not in features:
            raise ValueError("this CTG checkpoint denoises agents jointly (scene_denoising=True); the features need "
                             "'neighbour_row' (N, K): the row index of each neighbour denoised with the row, or -1.")
        neighbour_in = self.encoder.neighbour_input(features["neighbours"], features["neighbour_valid"])
        return neighbour_in, features["neighbour_row"]

    def _mixed(self, cond: torch.Tensor, x: torch.Tensor, k: torch.Tensor | int, scene: SceneRows | None
               ) -> torch.Tensor:
        """Conditioning ``(N, S, cond_dim)`` for the rows' noisy samples ``x (N, S, H, 2)`` at step ``k``: ``cond``
        (``(N, D)`` or ``(N, S, D)``) plus the mixer's reading of the co-denoised neighbours."""
        n, s = x.shape[:2]
        c = cond if cond.dim() == 3 else cond[:, None].expand(n, s, cond.shape[-1])
        if scene is None or self.mixer is None:
            return c
        return c + self.mixer(x, k, *scene)

    def predict_x0(self, x: torch.Tensor, k: torch.Tensor | int, cond: torch.Tensor) -> torch.Tensor:
        """Denoiser output (clean normalized actions) for noisy ``x (N, H, 2)`` at step ``k``."""
        if not isinstance(k, torch.Tensor):
            k = torch.full((x.shape[0],), int(k), dtype=torch.long, device=x.device)
        return self.denoiser(x, k, cond)

    def _plan_states(self, x0: torch.Tensor, v0: torch.Tensor, n: int) -> torch.Tensor:
        """Agent-frame states ``(N, R, H, 4)`` of the clean plans ``x0 (M, H, 2)``, ``M = n * R`` rows ordered
        row-major by the ``n`` rows whose speeds are ``v0 (N,)``."""
        plans = x0.reshape(n, -1, *x0.shape[1:])  # (N, R, H, 2)
        return self.rollout(plans, v0[:, None].expand(plans.shape[:2]))

    def _steer_shift(self, cond: torch.Tensor, x0: torch.Tensor, k: torch.Tensor | int, steer_map: SteerMap | None,
                     n: int, states: torch.Tensor | None = None) -> torch.Tensor:
        """The steering head's shift ``(M, H, 2)`` for ``M = n * R`` rows ordered row-major by the ``n``
        conditioning rows (R samples, or samples x steps, each). ``states``: :meth:`_plan_states` of ``x0``, when
        already computed."""
        assert self.steer is not None
        cfg = self.cfg
        if not (cfg.steer_road or cfg.steer_neighbours):
            return self.steer(cond, x0, k)
        if steer_map is None or (cfg.steer_neighbours and len(steer_map) < 5):
            raise ValueError("this CTG model's steering head reads the plans' surroundings (steer_road / "
                             "steer_neighbours): pass steer_map=(drivable crop (N, 1, G, G), v0 (N,)) and, for "
                             "steer_neighbours, also neighbours (N, K, 7), neighbour_valid (N, K), extent (N, 2).")
        drivable = steer_map[0]
        states = self._plan_states(x0, steer_map[1], n) if states is None else states
        parts = []
        if cfg.steer_road:
            parts.append(road_profile(drivable, states, cfg.map_resolution, cfg.steer_road_offset))
        if cfg.steer_neighbours:
            parts.append(neighbour_proximity(*steer_map[2:5], states, cfg.dt, cfg.steer_road_offset,
                                             cfg.steer_neighbour_scale))
        surroundings = torch.cat(parts, -1)
        shift = self.steer(cond, x0, k, surroundings.reshape(*x0.shape[:2], surroundings.shape[-1]))
        if not cfg.steer_gate:
            return shift
        hazards = [parts[-1]] if cfg.steer_neighbours else []
        if cfg.steer_road:  # the off-road share, 0 past the crop's edge (a plan leaving the crop is no hazard)
            hazards.append(road_profile(1 - drivable, states, cfg.map_resolution, cfg.steer_road_offset))
        gate = torch.cat(hazards, -1).amax((-2, -1)).reshape(-1, 1, 1)  # (M, 1, 1) in [0, 1]
        return gate * shift

    def _follow_shift(self, x0: torch.Tensor, k: torch.Tensor | int, steer_map: SteerMap | None,
                      n: int, states: torch.Tensor | None = None) -> torch.Tensor:
        """The gap-keeping head's gated shift ``(M, H, 2)`` (yaw-rate channel 0) for ``M = n * R`` rows ordered
        row-major by the ``n`` conditioning rows; ``states`` as in :meth:`_steer_shift`."""
        head = self.follow
        assert head is not None
        cfg = self.cfg
        if steer_map is None or len(steer_map) < 5:
            raise ValueError("this CTG model's gap-keeping head reads the agents around: pass "
                             "steer_map=(drivable crop (N, 1, G, G), v0 (N,), neighbours (N, K, 7), "
                             "neighbour_valid (N, K), extent (N, 2)).")
        v0 = steer_map[1]
        states = self._plan_states(x0, v0, n) if states is None else states
        lead = lead_gaps(*steer_map[2:5], states, cfg.dt, cfg.follow_lane_margin, cfg.follow_standstill,
                         cfg.follow_headway, cfg.follow_ttc, cfg.follow_heading_cos)
        gate = lead[..., :cfg.follow_gate_steps, 2].amax(-1).reshape(-1, 1, 1)  # (M, 1, 1); lead (N, R, H, 3)
        features = torch.stack([lead[..., 0] / LEAD_GAP_CLIP, lead[..., 1] / 10.0, lead[..., 2]], -1)
        v_rows = v0[:, None].expand(states.shape[:2]).reshape(-1)
        return gate * head(x0, k, v_rows, features.reshape(*x0.shape[:2], 3))

    def _head_shifts(self, cond: torch.Tensor, x0: torch.Tensor, k: torch.Tensor | int,
                     steer_map: SteerMap | None, n: int) -> torch.Tensor | None:
        """The sum of the steering and gap-keeping heads' shifts ``(M, H, 2)``, or None for a model with neither."""
        shift, states = None, None
        if self.follow is not None and steer_map is not None:  # all read one rollout
            states = self._plan_states(x0, steer_map[1], n)
        if self.steer is not None:
            shift = self._steer_shift(cond, x0, k, steer_map, n, states)
        if self.follow is not None:
            extra = self._follow_shift(x0, k, steer_map, n, states)
            shift = extra if shift is None else shift + extra
        return shift

    # ------------------------------------------------------------ training
    def loss(self, cond: torch.Tensor, actions: torch.Tensor, v0: torch.Tensor,
             target_states: torch.Tensor | None = None, generator: torch.Generator | None = None,
             scene: SceneRows | None = None, group: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Diffusion loss on physical ``actions (N, H, 2)`` with agent-frame ``target_states (N, H, 4)``
        (default: the unicycle rollout of ``actions``) and current speeds ``v0 (N,)``. With ``scene`` (from
        :meth:`scene_rows`) each row also reads its co-denoised neighbours' noisy actions; ``group (N,)`` long in
        ``0..G-1`` gives the rows denoised together one shared noise level, as at sampling time.

        Returns ``(loss, parts)`` with ``parts = {"action": ..., "state": ...}`` (both normalized MSEs).
        """
        n = actions.shape[0]
        x0 = self.normalize(actions)
        at = draw_device(generator, actions.device)
        if group is None:
            k = torch.randint(0, self.cfg.diffusion_steps, (n,), generator=generator, device=at).to(actions.device)
        else:
            per_group = torch.randint(0, self.cfg.diffusion_steps, (int(group.max()) + 1 if n else 0,),
                                      generator=generator, device=at).to(actions.device)
            k = per_group[group]
        noise = torch.randn(x0.shape, generator=generator, device=at).to(actions.device)
        ab = self.alphas_bar[k][:, None, None]
        xk = ab.sqrt() * x0 + (1 - ab).sqrt() * noise
        if scene is not None:
            cond = self._mixed(cond, xk[:, None], k, scene)[:, 0]
        pred = self.predict_x0(xk, k, cond)
        action_loss = F.mse_loss(pred, x0)
        if target_states is None:
            target_states = unicycle_from_origin(actions, v0, self.cfg.dt)
        state_loss = self._state_loss(self.rollout(pred, v0), target_states)
        return action_loss + self.cfg.state_loss_weight * state_loss, {"action": action_loss.detach(),
                                                                        "state": state_loss.detach()}

    def _state_loss(self, states: torch.Tensor, target_states: torch.Tensor) -> torch.Tensor:
        """Mean squared error of agent-frame ``states (..., H, 4)`` against ``target_states`` (broadcast), each
        channel over its ``state_std``, the yaw difference wrapped to (-pi, pi]."""
        diff = states - target_states
        diff = torch.cat([diff[..., :3], torch.atan2(torch.sin(diff[..., 3:]), torch.cos(diff[..., 3:]))], -1)
        return ((diff / self.state_std) ** 2).mean()

    def head_loss(self, cond: torch.Tensor, actions: torch.Tensor, v0: torch.Tensor, steer_map: SteerMap | None,
                  target_states: torch.Tensor | None = None, generator: torch.Generator | None = None
                  ) -> torch.Tensor:
        """The training loss of the steered sampler on logged ``actions (N, H, 2)``: the heads' share of the model's
        own loss, 0 for a model without heads.

        The heads move each sampling step's mean by ``sigma_k * shift``, which is the step of a clean prediction
        moved by ``sigma_k * shift / c_k`` (``c_k``: the weight of the clean prediction in the DDIM mean). At every
        step ``(k, k_prev)`` of :attr:`sample_schedule` the logged actions are noised to ``x_k ~ q(x_k | x_0)``,
        and that steered clean prediction is scored against the log with :meth:`loss`'s action and state MSEs
        (averaged over the steps). Its gradient reaches the heads (and whatever the heads read), so a fine-tuned head
        pays for making the logged futures less likely where its gate opens on them. ``cond (N, cond_dim)``;
        ``steer_map`` as in :meth:`sample`, ``target_states`` and ``generator`` as in :meth:`loss`."""
        if self.steer is None and self.follow is None:
            return actions.new_zeros(())
        if self.mixer is not None:
            raise ValueError("head_loss: the heads of a scene-denoising model (scene_denoising=True) are steered "
                             "through the mixer's reading of the co-denoised rows, which this loss does not "
                             "rebuild; fine-tune such a model's heads with imitation_coef = 0.")
        n, h = actions.shape[0], self.cfg.horizon
        schedule = torch.tensor(self.sample_schedule, device=actions.device)  # (K, 2)
        steps = schedule.shape[0]
        k, k_prev = schedule[:, 0].repeat(n), schedule[:, 1].repeat(n)  # rows row-major by the n windows
        x0_log = self.normalize(actions)[:, None].expand(n, steps, h, 2).reshape(-1, h, 2)
        noise = draw_normal(generator, x0_log.shape, actions.device)
        ab, ab_prev = self.alphas_bar[k][:, None, None], self.alphas_bar[k_prev][:, None, None]
        xk = ab.sqrt() * x0_log + (1 - ab).sqrt() * noise
        c = cond[:, None].expand(n, steps, cond.shape[-1]).reshape(-1, cond.shape[-1])
        _, sigma, x0 = self._transition(xk, k, k_prev, c, with_x0=True)
        shift = self._head_shifts(c, x0, k, steer_map, n)
        assert shift is not None
        weight = ab_prev.sqrt() - (1 - ab_prev - sigma**2).clamp_min(0).sqrt() * ab.sqrt() / (1 - ab).sqrt()
        steered = x0 + sigma * shift / weight
        action_loss = F.mse_loss(steered, x0_log)
        if target_states is None:
            target_states = unicycle_from_origin(actions, v0, self.cfg.dt)
        states = self.rollout(steered.reshape(n, steps, h, 2), v0[:, None].expand(n, steps))
        return action_loss + self.cfg.state_loss_weight * self._state_loss(states, target_states[:, None])

    # ------------------------------------------------------------ sampling
    def _transition(self, x: torch.Tensor, k: torch.Tensor | int, k_prev: torch.Tensor | int, cond: torch.Tensor,
                    with_x0: bool = False) -> tuple[torch.Tensor, ...]:
        """DDIM mean ``mu_theta(x_k)`` ``(N, H, 2)`` and std (scalar, or ``(N, 1, 1)`` for per-row steps) of
        ``x_{k_prev}`` given ``x_k`` (and with ``with_x0`` the clipped clean prediction ``(N, H, 2)``)."""
        ab, ab_prev = self.alphas_bar[k], self.alphas_bar[k_prev]
        if ab.dim() == 1:
            ab, ab_prev = ab[:, None, None], ab_prev[:, None, None]
        x0 = self.predict_x0(x, k, cond).clamp(-self.cfg.x0_clip, self.cfg.x0_clip)
        eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
        sigma = self.cfg.eta * ((1 - ab_prev) / (1 - ab)).sqrt() * (1 - ab / ab_prev).clamp_min(0).sqrt()
        mean = ab_prev.sqrt() * x0 + (1 - ab_prev - sigma**2).clamp_min(0).sqrt() * eps
        return (mean, sigma, x0) if with_x0 else (mean, sigma)

    @staticmethod
    def _gaussian_log_prob(x: torch.Tensor, mean: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """Sum over (H, 2) of log N(x; mean, sigma^2)."""
        z = (x - mean) / sigma
        return (-0.5 * z**2 - torch.log(sigma) - 0.5 * LOG_2PI).sum((-1, -2))

    def sample(self, cond: torch.Tensor, num_samples: int, generator: torch.Generator | None = None,
               guidance_fn: GuidanceFn | None = None, cond_fn: CondFn | None = None, scene: SceneRows | None = None,
               steer_map: SteerMap | None = None, active: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw ``num_samples`` normalized action sequences per conditioning row.

        Args:
            cond: ``(N, cond_dim)``, or ``(N, S, cond_dim)`` for one conditioning per sample.
            num_samples: S.
            generator: source of all the randomness.
            guidance_fn: optional ``f(mean (N, S, H, 2) normalized, step index) -> scalar`` objective to lower;
                each non-final step's mean moves by ``-guidance_step * sign(grad)``, clipped to +-sigma.
            cond_fn: optional ``f(step index, x0 (N, S, H, 2) normalized) -> cond (N, S, cond_dim)`` called before
                every step after the first with the previous step's clean prediction: lockstep denoising, where the
                conditioning follows what the other rows are becoming (``cond`` is used for the first step).
            scene: for a scene-denoising model, :meth:`scene_rows` of the rows: every step of row i's sample s
                reads the current noisy samples s of the rows denoised as its neighbours.
            steer_map: for a ``steer_road`` head, the rows' drivable crop ``(N, 1, G, G)`` and speed ``v0 (N,)``;
                a ``steer_neighbours`` head or a ``follow`` head also needs the rows' neighbours ``(N, K, 7)``,
                their valid mask ``(N, K)`` and the rows' extent ``(N, 2)`` (see :data:`SteerMap`).
            active: optional bool ``(N,)``: the rows whose samples the caller uses. The denoiser runs on these
                only; the noise is still drawn for every row, so the active rows' samples equal those of a call
                without ``active``, and the other rows return their noise (a planner that holds those agents
                still). Ignored by scene-denoising models, whose rows read each other's samples.

        Returns:
            actions ``(N, S, H, 2)`` physical; chain ``(N, S, K+1, H, 2)`` normalized ``x_K .. x_0``;
            guide_delta ``(N, S, K, H, 2)`` the perturbation added to each step's mean; log_prob ``(N, S, K)``.
        """
        n, s = cond.shape[0], num_samples
        h = self.cfg.horizon
        c = (cond if cond.dim() == 3 else cond[:, None].expand(n, s, cond.shape[-1])).reshape(n * s, -1)
        x = draw_normal(generator, (n * s, h, 2), cond.device)
        schedule = self.sample_schedule
        rows = None
        if active is not None and scene is None and not bool(active.all()):
            rows = active.to(x.device)[:, None].expand(n, s).reshape(-1).nonzero().flatten()
        chain, deltas, log_probs = [x], [], []
        x0 = x
        for i, (k, k_prev) in enumerate(schedule):
            if cond_fn is not None and i > 0:
                c = cond_fn(i, x0.reshape(n, s, h, 2)).reshape(n * s, -1)
            c_step = c if scene is None else self._mixed(c.reshape(n, s, -1), x.reshape(n, s, h, 2), k,
                                                          scene).reshape(n * s, -1)
            if rows is None:
                mean, sigma, x0 = self._transition(x, k, k_prev, c_step, with_x0=True)
            else:  # the unused rows keep their noise as mean and a zero clean prediction
                part, sigma, x0_part = self._transition(x[rows], k, k_prev, c_step[rows], with_x0=True)
                mean, x0 = x.clone(), torch.zeros_like(x)
                mean[rows], x0[rows] = part, x0_part
            shift = self._head_shifts(c_step, x0, k, steer_map, n)
            if shift is not None:
                mean = mean + sigma * shift
            delta = torch.zeros_like(mean)
            if guidance_fn is not None and i < len(schedule) - 1:
                with torch.enable_grad():
                    m = mean.detach().reshape(n, s, h, 2).requires_grad_(True)
                    objective = guidance_fn(m, i)
                    grad = torch.autograd.grad(objective, m, allow_unused=True)[0] if objective.requires_grad else None
                if grad is not None:
                    step = self.cfg.guidance_step * torch.sign(grad.reshape(n * s, h, 2))
                    delta = torch.minimum(torch.maximum(-step, -sigma), sigma)
            mean = mean + delta
            noise = draw_normal(generator, mean.shape, cond.device)
            x = (mean + sigma * noise).detach()
            chain.append(x)
            deltas.append(delta.detach())
            log_probs.append(self._gaussian_log_prob(x, mean, sigma))
        chain_t = torch.stack(chain, 1).reshape(n, s, len(schedule) + 1, h, 2)
        delta_t = torch.stack(deltas, 1).reshape(n, s, len(schedule), h, 2)
        log_prob = torch.stack(log_probs, -1).reshape(n, s, len(schedule))
        return self.unnormalize(chain_t[:, :, -1]), chain_t, delta_t, log_prob

    def chain_log_prob(self, cond: torch.Tensor, chain: torch.Tensor, guide_delta: torch.Tensor | None = None,
                       scene: SceneRows | None = None, steer_map: SteerMap | None = None) -> torch.Tensor:
        """Per-step log-probabilities ``(N, S, K)`` of a stored chain ``(N, S, K+1, H, 2)`` under the current
        parameters: ``log N(x_{k_prev}; mu_theta(x_k) + delta_k, sigma_k^2)`` summed over H and action dims.
        ``cond`` is ``(N, cond_dim)``, ``(N, S, cond_dim)`` or per step ``(N, S, K, cond_dim)``; ``scene`` and
        ``steer_map`` as in :meth:`sample` (the co-denoised rows' states at each step are read from ``chain``
        itself)."""
        mean, sigma = self.chain_means(cond, chain, guide_delta, scene, steer_map)
        n, s, steps1, h, _ = chain.shape
        log_prob = self._gaussian_log_prob(chain[:, :, 1:].reshape(-1, h, 2), mean.reshape(-1, h, 2),
                                           sigma.reshape(-1, 1, 1))
        return log_prob.reshape(n, s, steps1 - 1)

    def chain_means(self, cond: torch.Tensor, chain: torch.Tensor, guide_delta: torch.Tensor | None = None,
                    scene: SceneRows | None = None, steer_map: SteerMap | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian transitions of a stored chain under the current parameters: means ``(N, S, K, H, 2)`` of
        each step's ``x_{k_prev}`` given the stored ``x_k``, and their standard deviations ``(N, S, K)``
        (arguments as :meth:`chain_log_prob`). Two models' transitions of the same chain share ``sigma``, so
        their KL per step is ``||mean_a - mean_b||^2 / (2 sigma^2)`` (the bound DPOK optimizes)."""
        n, s, steps1, h, _ = chain.shape
        k_steps = steps1 - 1
        schedule = torch.tensor(self.sample_schedule, device=chain.device)  # (K, 2)
        if scene is not None and self.mixer is not None:
            if cond.dim() == 4:
                raise ValueError("chain_log_prob: per-step conditioning and scene-level denoising cannot be combined.")
            cond = torch.stack([self._mixed(cond, chain[:, :, i], int(k), scene)
                                for i, (k, _) in enumerate(self.sample_schedule)], 2)  # (N, S, K, D)
        if cond.dim() == 4:
            c = cond.reshape(-1, cond.shape[-1])
        else:
            per_sample = cond if cond.dim() == 3 else cond[:, None].expand(n, s, cond.shape[-1])
            c = per_sample[:, :, None].expand(n, s, k_steps, cond.shape[-1]).reshape(-1, cond.shape[-1])
        k = schedule[:, 0].repeat(n * s)
        k_prev = schedule[:, 1].repeat(n * s)
        x = chain[:, :, :-1].reshape(-1, h, 2)
        mean, sigma, x0 = self._transition(x, k, k_prev, c, with_x0=True)  # one batched call for all steps
        shift = self._head_shifts(c, x0, k, steer_map, n)
        if shift is not None:
            mean = mean + sigma * shift
        if guide_delta is not None:
            mean = mean + guide_delta.reshape(-1, h, 2)
        sigma = torch.as_tensor(sigma, dtype=mean.dtype, device=mean.device).expand(mean.shape).reshape(
            n * s * k_steps, -1)[:, 0]
        return mean.reshape(n, s, k_steps, h, 2), sigma.reshape(n, s, k_steps)
