"""``TrafficModelAdapter``: what the SDK needs from any traffic model (sampling with a replayable trace,
log-probabilities, its own training loss, trainable parameter groups, closed-loop planning, save/load)."""

from __future__ import annotations

import abc
import json
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import torch
from pydantic import BaseModel, ConfigDict, Field
from safetensors.torch import save_file

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.models.checkpoint import (
    CONFIG_FILE,
    WEIGHTS_FILE,
    build_checked,
    load_checked_weights,
    parse_architecture_config,
    read_checkpoint_config,
    sha256_file,
)
from trafficrlhf_sdk.models.random import SceneGenerators
from trafficrlhf_sdk.simulation.guidance import GuidanceSet, select_samples
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import Plan

__all__ = [
    "AdapterOptions",
    "PolicyTrace",
    "SampleOutput",
    "TrafficModelAdapter",
    "extend_constant_velocity",
    "read_adapter_config",
]


class AdapterOptions(BaseModel):
    """Options every adapter accepts (subclass it to add model-specific ones)."""

    model_config = ConfigDict(extra="forbid")

    guidance: str | None = Field(None, description="Guidance spec used by `plan`, e.g. 'no_collision:50,no_offroad'.")
    plan_samples: int = Field(5, ge=1, description="Samples drawn per agent at each replan (filtered by guidance).")
    checkpoint: str | None = Field(None, description="Weights directory; None loads the adapter's bundled checkpoint.")
    seed: int = Field(0, description="Seed of the sampling generator used by `plan`.")
    device: str = Field("cpu", description="Torch device of the model.")


@dataclass
class PolicyTrace:
    """What is needed to recompute the log-probability of exactly the sampled futures.

    tensors: model-specific, each with leading dims ``(B, S, A)`` (e.g. a denoising chain, a goal cell, a mode).
    agents: bool ``(B, A)``: the agents that were sampled (the controlled ones).
    now: the step the futures start after.
    """

    tensors: dict[str, torch.Tensor]
    agents: torch.Tensor
    now: int
    info: dict[str, Any] = field(default_factory=dict)

    def detach(self) -> PolicyTrace:
        """A copy whose tensors do not track gradients."""
        return PolicyTrace({k: v.detach() for k, v in self.tensors.items()}, self.agents, self.now, dict(self.info))


class SampleOutput(NamedTuple):
    """futures: float32 ``(B, S, A, H, 4)`` scene-frame states after ``now``; trace: :class:`PolicyTrace`;
    log_prob: the log-probability at sampling time, same shape as :meth:`TrafficModelAdapter.log_prob`."""

    futures: torch.Tensor
    trace: PolicyTrace
    log_prob: torch.Tensor


def read_adapter_config(directory: str, adapter_name: str, train_hint: str = "") -> dict[str, Any]:
    """The architecture config that :meth:`TrafficModelAdapter.save_pretrained` wrote to ``directory``.

    ``config.json`` is validated first (:func:`~trafficrlhf_sdk.models.checkpoint.read_checkpoint_config`): it
    raises ``DataNotFoundError`` (with ``train_hint``, e.g. the training command) when there is none and
    ``DataFormatError`` for invalid JSON, unknown keys, a missing weights SHA-256 or weights of another adapter.
    """
    return read_checkpoint_config(directory, adapter_name, train_hint).config


def extend_constant_velocity(futures: torch.Tensor, horizon: int, dt: float) -> torch.Tensor:
    """Extend ``(..., H, 4)`` futures to ``horizon`` steps by holding the last speed and heading."""
    h = futures.shape[-2]
    if h >= horizon:
        return futures[..., :horizon, :]
    last = futures[..., -1:, :]
    steps = torch.arange(1, horizon - h + 1, dtype=futures.dtype, device=futures.device)[:, None] * dt
    x = last[..., 0] + last[..., 2] * torch.cos(last[..., 3]) * steps[..., 0]
    y = last[..., 1] + last[..., 2] * torch.sin(last[..., 3]) * steps[..., 0]
    extra = torch.stack([x, y, last[..., 2].expand_as(x), last[..., 3].expand_as(x)], -1)
    return torch.cat([futures, extra], -2)


class TrafficModelAdapter(abc.ABC):
    """Base class of every traffic-model adapter; it is also a closed-loop policy (``reset`` + ``plan``).

    Subclasses set ``name``, ``Options``, ``horizon`` and ``history_steps``, and implement :meth:`build`,
    :meth:`get_config`, :attr:`module`, :meth:`sample`, :meth:`log_prob`, :meth:`imitation_loss` and
    :meth:`parameter_groups`.
    What must stay frozen (e.g. BITS's policy, TrafficGen's initializer) is simply not offered by
    :meth:`parameter_groups`. Run :func:`trafficrlhf_sdk.testing.check_adapter` on a new adapter.
    """

    name: ClassVar[str] = ""
    Options: ClassVar[type[AdapterOptions]] = AdapterOptions
    horizon: int = 20
    history_steps: int = 10  # history steps (before "now") the model reads; set from the model's config
    scene_generators: ClassVar[bool] = False
    """Whether :meth:`sample` accepts a :class:`~trafficrlhf_sdk.models.random.SceneGenerators` as its generator
    (one random stream per group of scenes), which lets :meth:`seed_scenes` batch independently seeded groups."""

    def __init__(self, config: dict[str, Any] | None = None, **options: Any) -> None:
        self.options = self.Options(**options)
        self.guidance = GuidanceSet.parse(self.options.guidance)
        self._generator: torch.Generator | SceneGenerators = torch.Generator(device="cpu").manual_seed(
            self.options.seed)
        self._scene_seeds: tuple[list[int], list[int]] | None = None
        self.build(config)
        self.module.to(self.options.device)

    # ------------------------------------------------------------ contract
    @abc.abstractmethod
    def build(self, config: dict[str, Any] | None) -> None:
        """Create the model from ``config`` (None: the default or bundled checkpoint's config) and load weights."""

    @abc.abstractmethod
    def get_config(self) -> dict[str, Any]:
        """JSON-serializable architecture config that :meth:`build` accepts."""

    @property
    @abc.abstractmethod
    def module(self) -> torch.nn.Module:
        """The wrapped model (all its parameters, frozen ones included)."""

    @abc.abstractmethod
    def sample(self, context: ScenarioTensor, num_samples: int, guidance: GuidanceSet | None = None,
               generator: torch.Generator | None = None) -> SampleOutput:
        """Draw ``num_samples`` futures ``(B, S, A, horizon, 4)`` for the controlled agents of ``context``."""

    @abc.abstractmethod
    def log_prob(self, context: ScenarioTensor, trace: PolicyTrace) -> torch.Tensor:
        """Log-probability of the traced samples under the current parameters: ``(B, S, A)`` or per step
        ``(B, S, A, K)`` (e.g. per denoising step); entries of agents not sampled are 0. Differentiable."""

    @abc.abstractmethod
    def imitation_loss(self, batch: ScenarioTensor) -> torch.Tensor:
        """The model's own training loss on logged scenes (scalar, differentiable): the paper's r."""

    @abc.abstractmethod
    def parameter_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """Trainable parameter groups by name (e.g. ``encoder``, ``decoder``); frozen parts are not offered."""

    def transition_kl(self, context: ScenarioTensor, trace: PolicyTrace,
                      reference: TrafficModelAdapter) -> torch.Tensor | None:
        """The KL from this model to ``reference`` (the same adapter class, frozen) on the traced samples, in
        closed form, shaped like :meth:`log_prob`'s output, with gradients into this model only. A diffusion
        model returns it per denoising step (its Gaussian transitions share their variances, so the KL is
        ``||mu - mu_ref||^2 / (2 sigma^2)``, finite and 0 at the start). None (the default): the fine-tuner uses
        a sample estimate from :meth:`log_prob` instead."""
        return None

    def choice_futures(self, context: ScenarioTensor) -> torch.Tensor | None:
        """For a policy that first picks one of ``C`` discrete choices per agent (a mixture's modes, a set of
        goals) and then draws the rest: ``(B, C, A, horizon, 4)``, every choice's most likely future (e.g. a mode's
        mean plan) for the agents :meth:`sample` draws, without gradient. The fine-tuner's ``choice_coef`` scores
        them all and trains :meth:`choice_log_prob` on the exact expected reward over the choices. None (the
        default): the model has no such choice."""
        return None

    def choice_log_prob(self, context: ScenarioTensor) -> torch.Tensor:
        """``(B, C, A)`` log-probability of each choice of :meth:`choice_futures` under the current parameters
        (0 for agents not sampled). Differentiable. Needed only where :meth:`choice_futures` is offered."""
        raise NotImplementedError(f"{type(self).__name__} implements choice_futures but not choice_log_prob; "
                                  "implement both, or return None from choice_futures.")

    # ------------------------------------------------------------ policy
    def reset(self, scenario: ScenarioTensor) -> None:
        """Fit the guidance heuristics on the logged scene at the rollout start and re-seed the sampler (one
        generator from ``options.seed``, or one per group of scenes after :meth:`seed_scenes`)."""
        if self.guidance is not None:
            self.guidance.fit(scenario)
        if self._scene_seeds is None:
            self._generator = torch.Generator(device="cpu").manual_seed(self.options.seed)
            return
        seeds, sizes = self._scene_seeds
        if sum(sizes) != scenario.num_scenes:
            raise ValueError(f"seed_scenes covers {sum(sizes)} scenes in groups {sizes}, but the rollout has "
                             f"{scenario.num_scenes}; seed the groups of this batch (or call seed_scenes(None)).")
        self._generator = SceneGenerators(seeds, sizes)

    def seed_scenes(self, seeds: Sequence[int] | None, sizes: Sequence[int] = ()) -> None:
        """From the next :meth:`reset` on, sample group g of ``sizes[g]`` consecutive scenes from its own
        generator seeded by ``seeds[g]``: a batch of groups then draws exactly what each group draws alone with
        its seed as ``options.seed`` (e.g. many feedback contexts, each seeded by its scene, in one rollout).
        ``None`` returns to one generator from ``options.seed``. Needs an adapter with ``scene_generators``."""
        if seeds is None:
            self._scene_seeds = None
            return
        if not self.scene_generators:
            raise TrafficRLHFError(f"the {self.name!r} adapter samples from one generator; run its seeded groups "
                                   "one by one (seed_policy per group) instead of seed_scenes.")
        if len(seeds) != len(sizes) or not seeds or any(int(n) < 1 for n in sizes):
            raise ValueError(f"seed_scenes: seeds {list(seeds)} and sizes {list(sizes)} must pair one seed with "
                             "each group of at least one scene.")
        self._scene_seeds = ([int(s) for s in seeds], [int(n) for n in sizes])

    @torch.no_grad()
    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """Sample ``plan_samples`` futures, keep the one with the lowest guidance loss (sample 0 without
        guidance), and extend it to ``horizon`` steps if the model plans fewer."""
        context = context.to(self.options.device)
        now = context.current_index
        if not (context.controlled & context.valid[:, :, now]).any():  # nobody to plan for: hold course
            return Plan(extend_constant_velocity(context.states[:, :, now: now + 1], horizon + 1, context.dt)[
                :, :, 1:].cpu())
        samples = 1 if self.guidance is None else self.options.plan_samples
        with torch.enable_grad() if self.guidance is not None else torch.no_grad():
            out = self.sample(context, samples, self.guidance, self._generator)
        futures = out.futures.detach()
        if self.guidance is not None and samples > 1:
            loss = self.guidance.loss(futures, context.current_index, context)
            choice = select_samples(loss, context.controlled, self.guidance.scene_level)  # (B, A)
            index = choice[:, None, :, None, None].expand(-1, 1, -1, futures.shape[-2], 4)
            futures = futures.gather(1, index)
        return Plan(extend_constant_velocity(futures[:, 0], horizon, context.dt).cpu())

    # ------------------------------------------------------------ weights
    def save_pretrained(self, directory: str) -> None:
        """Write ``config.json`` (adapter name, architecture config, the weights' SHA-256) and ``model.safetensors``.

        Each file is written to a temporary name and moved into place, so an interrupted save leaves the previous
        files (or none), never a half-written one."""
        os.makedirs(directory, exist_ok=True)
        state = {k: v.detach().cpu().contiguous() for k, v in self.module.state_dict().items()}
        weights = os.path.join(directory, WEIGHTS_FILE)
        handle, tmp = tempfile.mkstemp(prefix=".model-", suffix=".tmp", dir=directory)
        os.close(handle)
        try:
            save_file(state, tmp, metadata={"format": "pt", "adapter": self.name})
            saved = {"adapter": self.name, "config": self.get_config(),
                     "weights": {"file": WEIGHTS_FILE, "sha256": sha256_file(tmp), "bytes": os.path.getsize(tmp)}}
            os.replace(tmp, weights)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
        config_tmp = os.path.join(directory, f".{CONFIG_FILE}.tmp")
        with open(config_tmp, "w", encoding="utf-8") as out:
            json.dump(saved, out, indent=2)
        os.replace(config_tmp, os.path.join(directory, CONFIG_FILE))

    @classmethod
    def from_pretrained(cls, directory: str, **options: Any) -> TrafficModelAdapter:
        """Rebuild an adapter saved with :meth:`save_pretrained` (never unpickles anything)."""
        config = read_adapter_config(directory, cls.name)
        adapter = cls(config=config, **{**options, "checkpoint": None})
        adapter.load_weights(directory)
        return adapter

    def resolve_checkpoint(
        self, config: dict[str, Any] | None, default_directory: str, train_hint: str = ""
    ) -> tuple[dict[str, Any], str | None]:
        """For :meth:`build`: the architecture config and the weights directory to load (None: fresh weights).

        ``config`` None reads both from ``options.checkpoint`` or else ``default_directory`` (the bundled
        checkpoint); an explicit ``config`` loads weights only when ``options.checkpoint`` is set.
        """
        directory = self.options.checkpoint
        if config is None:
            directory = directory or default_directory
            config = read_adapter_config(directory, self.name, train_hint)
        return config, directory

    def load_architecture(self, config: dict[str, Any] | None, default_directory: str, train_hint: str,
                          config_type: Any, module_type: Any) -> tuple[Any, torch.nn.Module]:
        """For :meth:`build`: ``(cfg, module)`` with ``cfg = config_type.from_dict(...)`` and
        ``module = module_type(cfg)``, the config and weights chosen as in :meth:`resolve_checkpoint` (weights
        loaded when a checkpoint applies).

        The config is checked against ``config_type``'s fields and the module's size and tensors against the
        weights file before anything is allocated (:mod:`trafficrlhf_sdk.models.checkpoint`)."""
        raw, directory = self.resolve_checkpoint(config, default_directory, train_hint)
        label = f"checkpoint {directory!r}" if directory is not None else f"{self.name} config"
        cfg = parse_architecture_config(config_type, raw, label)
        module = build_checked(module_type, cfg, directory, self.name, label, self.options.device)
        return cfg, module

    def load_weights(self, directory: str) -> None:
        """Load ``model.safetensors`` from ``directory`` into :attr:`module` after checking ``config.json``, the
        weights' SHA-256, every tensor's name, shape and kind, and that all values are finite."""
        load_checked_weights(self.module, directory, self.name, self.options.device)
