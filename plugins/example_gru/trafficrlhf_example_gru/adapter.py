"""``ExampleGRUAdapter``: the :class:`~trafficrlhf_sdk.models.TrafficModelAdapter` of the GRU policy.

The contract in one paragraph: :meth:`sample` draws Gaussian actions step by step, rolls them through the
SDK's unicycle dynamics from each agent's current state, and returns the scene-frame states together with a
trace holding the sampled actions; :meth:`log_prob` replays the decoder teacher-forced on exactly those actions
and sums their Gaussian log-densities over the horizon; :meth:`imitation_loss` is the Gaussian negative
log-likelihood of the logged actions; :meth:`parameter_groups` offers ``encoder`` and ``decoder``. Closed-loop
planning, guidance filtering and save/load come from the base class.
"""

from __future__ import annotations

import os
import warnings
from typing import Any

import torch

from trafficrlhf_sdk.simulation.dynamics import action_bounds, wrap_angle
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.models import PolicyTrace, SampleOutput, TrafficModelAdapter
from trafficrlhf_sdk.models.adapter import read_adapter_config
from trafficrlhf_sdk.models.features import history_features, map_crops, neighbour_features
from trafficrlhf_sdk.scenario import AgentType, ScenarioTensor

from trafficrlhf_example_gru.model import GRUConfig, GRUPolicyNet

__all__ = ["BUNDLED_CHECKPOINT", "ExampleGRUAdapter"]

BUNDLED_CHECKPOINT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "checkpoint")

# Feature normalization: history x, y (m), speed (m/s), cos, sin.
_HISTORY_SCALE = (0.1, 0.1, 0.1, 1.0, 1.0)
# Neighbour x, y (m), cos, sin, speed (m/s), length, width (m).
_NEIGHBOUR_SCALE = (0.05, 0.05, 1.0, 1.0, 0.1, 0.2, 0.2)


class ExampleGRUAdapter(TrafficModelAdapter):
    """A GRU policy with a stochastic diagonal-Gaussian head over (acceleration, yaw rate), 2 s horizon.

    Options are the SDK's :class:`~trafficrlhf_sdk.models.AdapterOptions`; ``checkpoint=None`` loads the
    checkpoint bundled in the package (trained on the nuScenes train split, CC BY-NC-SA 4.0).
    """

    name = "example_gru"
    horizon = 20

    # ------------------------------------------------------------ build / config / module
    def build(self, config: dict[str, Any] | None) -> None:
        """Create the network; with ``config=None`` read config and weights from the checkpoint directory."""
        weights_dir = self.options.checkpoint
        if config is None:
            directory = self.options.checkpoint or BUNDLED_CHECKPOINT
            config_path = os.path.join(directory, "config.json")
            if os.path.isfile(config_path):
                config, weights_dir = read_adapter_config(directory, self.name), directory
            elif self.options.checkpoint:
                raise DataNotFoundError(f"no config.json in checkpoint {directory!r}; pass a save_pretrained folder.")
            else:
                warnings.warn("example_gru: no bundled checkpoint found; the model is randomly initialized. Train one "
                              "with `python -m trafficrlhf_example_gru.train`.", stacklevel=2)
        self.config = GRUConfig(**(config or {}))
        self.horizon = self.config.horizon
        self.history_steps = self.config.history_steps
        self.net = GRUPolicyNet(self.config)
        self.net.eval()
        if weights_dir is not None:
            self.load_weights(weights_dir)

    def get_config(self) -> dict[str, Any]:
        """The architecture config (JSON)."""
        return self.config.model_dump(mode="json")

    @property
    def module(self) -> torch.nn.Module:
        """The network (all its parameters)."""
        return self.net

    def parameter_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """``encoder`` (history, neighbours, map, fusion) and ``decoder`` (GRU cell and Gaussian head)."""
        params = lambda modules: [p for m in modules for p in m.parameters()]  # noqa: E731
        return {"encoder": params(self.net.encoder_modules()), "decoder": params(self.net.decoder_modules())}

    # ------------------------------------------------------------ features
    def _encode(self, context: ScenarioTensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Initial GRU state ``(B, A, hidden)``, current state ``(B, A, 4)`` and last executed action ``(B, A, 2)``."""
        cfg, device = self.config, context.device
        now = context.current_index
        hist, hist_valid = history_features(context, cfg.history_steps)
        keep = list(range(cfg.history_steps - 1, -1, -cfg.history_stride))[::-1]  # ends at now
        hist, hist_valid = hist[:, :, keep], hist_valid[:, :, keep]
        hist = hist * torch.tensor(_HISTORY_SCALE, device=device)
        history = torch.cat([hist, hist_valid[..., None].float()], -1)

        nb, nb_valid = neighbour_features(context, cfg.num_neighbours, cfg.neighbour_radius_m)
        nb = nb * torch.tensor(_NEIGHBOUR_SCALE, device=device)
        neighbours = torch.cat([nb, nb_valid[..., None].float()], -1)

        crops = self._crops(context) if cfg.use_map else None

        state0 = context.states[:, :, now]
        prev = torch.zeros_like(state0[..., :2])
        if now >= 1:  # the action that led to "now" (inverse dynamics), clipped like the simulator would
            before = context.states[:, :, now - 1]
            raw = torch.stack([(state0[..., 2] - before[..., 2]) / context.dt,
                               wrap_angle(state0[..., 3] - before[..., 3]) / context.dt], -1)
            lb, ub = action_bounds(before[..., 2])
            both = context.valid[:, :, now] & context.valid[:, :, now - 1]
            prev = torch.maximum(torch.minimum(raw, ub), lb) * both[..., None]
        current = torch.cat([state0[..., 2:3] / 10.0, prev / self.net.action_scale], -1)
        return self.net.encode(history, neighbours, crops, current), state0, prev

    def _crops(self, context: ScenarioTensor) -> torch.Tensor:
        """``(B, A, C, S, S)`` crops of the configured layers (a layer the map lacks, or no map: zeros)."""
        cfg = self.config
        b, a, s = context.num_scenes, context.num_agents, cfg.map_size_px
        out = torch.zeros(b, a, len(cfg.map_layers), s, s, device=context.device)
        if context.map is None:
            return out
        crops = map_crops(context, size_px=s, resolution_m=cfg.map_resolution_m)
        for i, layer in enumerate(cfg.map_layers):
            if layer in context.map.layers:
                out[:, :, i] = crops[:, :, context.map.layers.index(layer)]
        return out

    def _decode(self, context: ScenarioTensor, num_samples: int, noise: torch.Tensor | None = None,
                actions: torch.Tensor | None = None):  # type: ignore[no-untyped-def]
        """Decode ``num_samples`` futures per agent; noise/actions are ``(B, S, A, H, 2)``."""
        b, a, s, h = context.num_scenes, context.num_agents, num_samples, self.horizon
        h0, state0, prev = self._encode(context)
        flat = lambda t: t[:, None].expand(b, s, *t.shape[1:]).reshape(b * s * a, -1)  # noqa: E731
        return self.net.decode(
            flat(h0), flat(state0), flat(prev), context.dt,
            noise=None if noise is None else noise.reshape(-1, h, 2),
            actions=None if actions is None else actions.reshape(-1, h, 2),
        )

    # ------------------------------------------------------------ contract
    def sample(self, context: ScenarioTensor, num_samples: int, guidance: GuidanceSet | None = None,
               generator: torch.Generator | None = None) -> SampleOutput:
        """Draw ``num_samples`` futures ``(B, S, A, 20, 4)``; trace tensor ``actions (B, S, A, 20, 2)``.

        ``guidance`` is accepted for the interface; this model does not steer its samples (``plan`` picks the
        best of ``plan_samples`` under guidance). All randomness comes from ``generator``.
        """
        b, a, s, h = context.num_scenes, context.num_agents, num_samples, self.horizon
        now = context.current_index
        agents = context.controlled & context.valid[:, :, now]
        noise = torch.randn(b, s, a, h, 2, generator=generator).to(context.device)
        with torch.no_grad():
            out = self._decode(context, s, noise=noise)
        mask = agents[:, None].expand(b, s, a)
        actions = out.actions.reshape(b, s, a, h, 2) * mask[..., None, None]
        log_prob = out.log_prob.reshape(b, s, a, h).sum(-1) * mask
        futures = out.states.reshape(b, s, a, h, 4)
        trace = PolicyTrace({"actions": actions}, agents, now, {"model": self.name})
        return SampleOutput(futures, trace, log_prob)

    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """``(B, S, A)`` sum over the horizon of the Gaussian log-density of the traced actions (teacher forced)."""
        if trace.now != context.current_index:
            raise ValueError(f"trace was sampled at step {trace.now} but context.current_index is "
                             f"{context.current_index}; pass the context the samples were drawn from.")
        actions = trace.tensors["actions"]
        b, s, a, h, _ = actions.shape
        out = self._decode(context, s, actions=actions)
        return out.log_prob.reshape(b, s, a, h).sum(-1) * trace.agents[:, None]

    def imitation_loss(self, batch: ScenarioTensor) -> torch.Tensor:
        """Mean Gaussian NLL per (agent, step) of the logged actions of the ``horizon`` steps after
        ``batch.current_index``, over vehicles valid now, up to their first invalid step."""
        now, h = batch.current_index, self.horizon
        logged = batch.actions()[:, :, now : now + h]
        valid = batch.action_valid[:, :, now : now + h]
        if logged.shape[2] < h:
            pad = h - logged.shape[2]
            logged = torch.nn.functional.pad(logged, (0, 0, 0, pad))
            valid = torch.nn.functional.pad(valid, (0, pad))
        agents = batch.valid[:, :, now] & (batch.agent_type == AgentType.VEHICLE)
        mask = (valid.long().cumprod(-1) > 0) & agents[..., None]  # (B, A, H): valid prefix of each agent
        out = self._decode(batch, 1, actions=logged[:, None])
        log_prob = out.log_prob.reshape(mask.shape)
        return -(log_prob * mask).sum() / mask.sum().clamp_min(1)
