"""``RewardModel``: r_HF, a learned score of how realistic a traffic scenario is.

Contract (every architecture):

- :meth:`RewardModel.step_rewards` maps a scenario ``(B, A, T)`` to per-step rewards ``(B, T)`` in [-1, 1]
  (the :data:`~trafficrlhf_sdk.metrics.reward_cost.RewardFn` of the reward-cost metric);
- :meth:`RewardModel.forward` (= :meth:`score`) maps it to one reward per scene ``(B,)`` in [-1, 1]: the mean of
  the per-step rewards over the steps the architecture scores (for the built-in one: every ``step_dt`` after
  ``current_index``, so the history that two candidates share never counts);
- :meth:`prepare` / :meth:`score_prepared` split scoring into a no-grad part computed once and a trainable part,
  so :class:`~trafficrlhf_sdk.reward.trainer.RewardTrainer` featurizes a dataset once and not every epoch.
  The defaults keep the scenario and call :meth:`forward`, so an architecture only has to implement
  :meth:`step_rewards` and :meth:`forward`.

Architectures are registered by plugins (``register_reward_model_architectures``) under the name stored in
``config.json``; :meth:`RewardModel.from_pretrained` resolves the class from that registry, never from pickle.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any, ClassVar

import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from torch import nn

from trafficrlhf_sdk.errors import DataFormatError, InvalidOptionError, RewardModelError, UnknownComponentError
from trafficrlhf_sdk.reward.serialization import load_weights, read_config, read_weights, save_reward_model
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["RewardEnsemble", "RewardModel", "ScenarioInputs", "check_architecture_options", "check_outputs",
           "get_reward_model_architecture", "load_reward_model", "option_error_message", "probe_scene",
           "reward_model_architectures"]


def option_error_message(config_type: type[BaseModel], given: dict[str, Any], exc: ValidationError, owner: str,
                         flag: str) -> str:
    """One line for options ``given`` that ``config_type`` refused: each bad option with its value, what is wrong
    and what it accepts (the field's description), and how to set it (``flag KEY=VALUE``)."""
    problems: dict[str, str] = {}
    for err in exc.errors():
        loc = [str(part) for part in err.get("loc", ())]
        key = loc[0] if loc else "<options>"
        if key in problems:  # one line per option (a tuple's element error is followed by a length error)
            continue
        field = config_type.model_fields.get(key)
        shown = json.dumps(given[key], default=str)[:80] if key in given else "(not given)"
        accepted = f"; accepted: {field.description.rstrip('.')}" if field is not None and field.description else ""
        if err.get("type") == "extra_forbidden":
            accepted = f"; known options: {', '.join(config_type.model_fields)}"
        problems[key] = f"option `{key}` = {shown}: {'.'.join(loc)}: {err.get('msg', 'invalid value')}{accepted}"
    return (f"{owner}: " + " | ".join(problems.values()) + f". Fix it with `{flag} KEY=VALUE` (a JSON value), or "
            "drop it to use the default.")


class ScenarioInputs:
    """The default prepared input: the scenario itself (selectable by scene like :class:`StepInputs`)."""

    def __init__(self, scenario: ScenarioTensor) -> None:
        self.scenario = scenario

    @property
    def num_scenes(self) -> int:
        """B."""
        return self.scenario.num_scenes

    def select(self, scenes: torch.Tensor | Sequence[int]) -> ScenarioInputs:
        """The scenes at ``scenes`` (repeats allowed)."""
        return ScenarioInputs(self.scenario[torch.as_tensor(scenes, dtype=torch.long)])

    @staticmethod
    def concat(parts: Sequence[ScenarioInputs]) -> ScenarioInputs:
        """Scenes of all parts, in order."""
        return ScenarioInputs(ScenarioTensor.concat([p.scenario for p in parts]))

    def to(self, device: torch.device | str) -> ScenarioInputs:
        """The same inputs on ``device``."""
        return ScenarioInputs(self.scenario.to(device))

    @property
    def device(self) -> torch.device:
        """Where the inputs are."""
        return self.scenario.states.device


def prepared_device(prepared: Any) -> torch.device:
    """The device of a prepared input: its ``device`` attribute (:class:`ScenarioInputs`, ``StepInputs``); an
    architecture's own input type without one is taken to be on the CPU, where :meth:`RewardModel.prepare` runs."""
    return torch.device(getattr(prepared, "device", "cpu"))


class RewardModel(nn.Module):
    """Base class of reward-model architectures.

    Subclasses set :attr:`architecture` (the registry name) and :attr:`Config` (a pydantic model of their
    constructor options, written to ``config.json``), take ``config`` as their only constructor argument and
    implement :meth:`step_rewards` and :meth:`forward`.
    """

    architecture: ClassVar[str] = ""
    Config: ClassVar[type[BaseModel]]
    #: the interval every scene and per-step reward lies in (checked on a synthetic scene when loading)
    output_range: ClassVar[tuple[float, float]] = (-1.0, 1.0)

    def __init__(self, config: BaseModel | dict[str, Any] | None = None) -> None:
        super().__init__()
        if config is None:
            config = self.Config()
        elif isinstance(config, dict):
            try:
                config = self.Config(**config)
            except ValidationError as exc:
                raise InvalidOptionError(option_error_message(self.Config, config, exc,
                                                              f"reward-model architecture {self.architecture!r}",
                                                              "--architecture-option")) from None
        elif not isinstance(config, self.Config):
            raise TypeError(f"`config` must be a {self.Config.__name__} or a dict; got {type(config).__name__}.")
        self.config = config
        self.card_info: dict[str, Any] = {}  # provenance and metrics for the model card (set by the trainer)

    # ------------------------------------------------------------------ scoring
    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Per-step rewards ``(B, T)`` in [-1, 1]."""
        raise NotImplementedError

    def forward(self, scenario: ScenarioTensor) -> torch.Tensor:  # noqa: D102
        raise NotImplementedError

    def score(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Scenario rewards ``(B,)`` in [-1, 1]; the same as calling the model."""
        return self(scenario)

    def prepare(self, scenario: ScenarioTensor) -> Any:
        """The no-grad part of scoring (default: the scenario itself); selectable by scene and concatenable."""
        return ScenarioInputs(scenario)

    def score_prepared(self, prepared: Any) -> torch.Tensor:
        """Scenario rewards ``(B,)`` from the output of :meth:`prepare` (differentiable)."""
        return self(self.on_device(prepared).scenario)

    @property
    def device(self) -> torch.device:
        """Where the weights are (the CPU for a model without parameters)."""
        return next((p.device for p in self.parameters()), torch.device("cpu"))

    def on_device(self, prepared: Any) -> Any:
        """``prepared`` (the output of :meth:`prepare`, which runs where the scenario is) moved to :attr:`device`,
        so CPU-featurized inputs score on a GPU model."""
        device = self.device
        return prepared if prepared_device(prepared) == device else prepared.to(device)

    @property
    def num_parameters(self) -> int:
        """Number of trainable values."""
        return sum(p.numel() for p in self.parameters())

    # ----------------------------------------------------------------------- io
    def config_dict(self) -> dict[str, Any]:
        """The constructor options as JSON-ready values."""
        return self.config.model_dump(mode="json")

    def save_pretrained(self, directory: str | os.PathLike[str], card: dict[str, Any] | None = None,
                        dtype: torch.dtype | None = None) -> str:
        """Write ``config.json``, ``model.safetensors`` and a ``README.md`` model card into ``directory``.

        ``card`` adds to (and overrides) :attr:`card_info`: keys ``data``, ``training``, ``metrics``,
        ``commands``, ``notes`` (see :func:`~trafficrlhf_sdk.reward.serialization.render_model_card`).
        ``dtype=torch.float16`` stores the weights in half precision (they load back as float32).
        """
        return save_reward_model(self, directory, {**self.card_info, **(card or {})}, dtype)

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike[str], verify: bool = True,
                        device: str | torch.device = "cpu") -> RewardModel:
        """Load a model saved by :meth:`save_pretrained`; the class comes from the architecture registry.

        Args:
            directory: the folder with ``config.json`` and ``model.safetensors``.
            verify: check the weights file against the SHA-256 recorded in ``config.json`` (refuses edited or
                truncated files).
            device: where to put the weights.

        Raises:
            DataNotFoundError: the folder or a file is missing.
            DataFormatError: unreadable, tampered, truncated or mis-shaped files.
            UnknownComponentError: ``config.json`` names an architecture no installed plugin registers.
        """
        model = load_reward_model(directory, verify=verify, device=device)
        if not isinstance(model, cls):
            raise DataFormatError(f"{os.fspath(directory)!r} holds a {type(model).__name__} "
                                  f"({model.architecture!r}), not a {cls.__name__}; load it with "
                                  "RewardModel.from_pretrained.")
        return model


def reward_model_architectures() -> Any:
    """The registry of reward-model architectures (built from the plugins on each call)."""
    from trafficrlhf_sdk.plugins import registry

    return registry("reward_model_architectures")


def get_reward_model_architecture(name: str) -> type[RewardModel]:
    """The class registered as ``name``; unknown names raise ``UnknownComponentError`` listing the known ones."""
    cls = reward_model_architectures().get(name)
    if not (isinstance(cls, type) and issubclass(cls, RewardModel)):
        raise DataFormatError(f"reward-model architecture {name!r} is registered as {cls!r}, which is not a "
                              "RewardModel subclass; fix the plugin that registers it.")
    return cls


def check_architecture_options(name: str, options: dict[str, Any]) -> BaseModel:
    """The validated options of architecture ``name`` (before any data is read or any weight allocated); bad ones
    raise :class:`~trafficrlhf_sdk.errors.InvalidOptionError` naming each option and its value."""
    cls = get_reward_model_architecture(name)
    try:
        return cls.Config(**options)
    except ValidationError as exc:
        raise InvalidOptionError(option_error_message(cls.Config, options, exc, f"reward-model architecture "
                                                      f"{name!r}", "--architecture-option")) from None


def load_reward_model(directory: str | os.PathLike[str], verify: bool = True,
                      device: str | torch.device = "cpu") -> RewardModel:
    """Rebuild the model of a folder written by :meth:`RewardModel.save_pretrained` (see
    :meth:`RewardModel.from_pretrained`): the class from the architecture registry, never from pickle."""
    directory = os.fspath(directory)
    config = read_config(directory)
    name = config["architecture"]
    architectures = reward_model_architectures()
    if name not in architectures:
        raise UnknownComponentError(
            f"{directory!r} needs the reward-model architecture {name!r}, which no installed plugin registers "
            f"(registered: {architectures.names()}). Install the plugin that provides it (see `trafficrlhf plugins`)."
        )
    cls = architectures.get(name)
    if not (isinstance(cls, type) and issubclass(cls, RewardModel)):
        raise DataFormatError(f"architecture {name!r} is registered as {cls!r}, not a RewardModel subclass.")
    try:
        model = cls(config["config"])
    except (ValidationError, TypeError, ValueError) as exc:
        raise DataFormatError(f"{directory!r}: config.json's `config` does not fit architecture {name!r}: "
                              f"{' '.join(str(exc).split())}") from exc
    size = sum(t.numel() * max(t.element_size(), 4) for t in model.state_dict().values())  # stored in <= 32 bits
    tensors, weights = read_weights(directory, config, verify, expected_bytes=size)
    load_weights(model, tensors, weights, config, directory)
    model.card_info = {k: config[k] for k in ("data", "training", "metrics") if k in config}
    model.card_info.update(config.get("card") or {})
    check_outputs(model.eval(), f"reward model {directory!r}")
    return model.to(device)


def probe_scene() -> ScenarioTensor:
    """A tiny synthetic scene every architecture can score: two cars driving along a straight road for 3 s (1 s of
    history), on a 64 m x 64 m map at 1 px/m whose middle 12 m are drivable."""
    steps, dt, now = 31, 0.1, 10
    t = torch.arange(steps, dtype=torch.float32) * dt
    cars = []
    for x0, y0, speed in ((-10.0, -2.0, 8.0), (-4.0, 2.0, 9.0)):
        x = x0 + speed * t
        cars.append(torch.stack([x, torch.full_like(t, y0), torch.full_like(t, speed), torch.zeros_like(t)], -1))
    raster = torch.zeros(1, 3, 64, 64, dtype=torch.uint8)
    raster[0, 0, :, 26:38] = 1  # drivable: |y| < 6 m (the column index follows y)
    raster[0, 2, :, 32] = 1  # a lane divider at y = 0
    to_pixel = torch.tensor([[[1.0, 0.0, 32.0], [0.0, 1.0, 32.0], [0.0, 0.0, 1.0]]])
    from trafficrlhf_sdk.scenario.map import MapRaster

    return ScenarioTensor(states=torch.stack(cars)[None], valid=torch.ones(1, 2, steps, dtype=torch.bool),
                          extent=torch.tensor([[[4.5, 1.9], [4.6, 1.9]]]),
                          agent_type=torch.ones(1, 2, dtype=torch.long),
                          controlled=torch.ones(1, 2, dtype=torch.bool), dt=dt, current_index=now,
                          map=MapRaster(raster=raster, world_to_pixel=to_pixel), scene_ids=("probe",),
                          agent_ids=(("a", "b"),), source="probe")


def check_outputs(model: RewardModel, name: str) -> None:
    """The probe pass of loading: ``model`` scores :func:`probe_scene`; its scene and per-step rewards must be
    finite and inside the architecture's :attr:`RewardModel.output_range`, else
    :class:`~trafficrlhf_sdk.errors.RewardModelError` (weights that load but are unusable, e.g. scaled by 1e30)."""
    low, high = model.output_range
    scene = probe_scene().to(model.device)
    try:
        with torch.no_grad():
            outputs = {"scene score is": model(scene).float().cpu(),
                       "per-step rewards are": model.step_rewards(scene).float().cpu()}
    except (RuntimeError, ValueError, IndexError) as exc:
        raise RewardModelError(f"{name}: scoring a tiny synthetic scene fails ({type(exc).__name__}: "
                               f"{' '.join(str(exc).split())[:200]}); the weights or the architecture's plugin are "
                               "broken: re-train the model or update the plugin.") from None
    for what, values in outputs.items():
        bad = ~torch.isfinite(values) | (values < low - 1e-5) | (values > high + 1e-5)
        if bool(bad.any()):
            shown = ", ".join(f"{v:.4g}" for v in values[bad].flatten()[:3].tolist())
            raise RewardModelError(
                f"{name}: on a tiny synthetic scene its {what} {shown} ({int(bad.sum())} of {values.numel()} "
                f"values not finite or outside the architecture's range [{low:g}, {high:g}]); the weights load "
                "but are unusable (scaled, diverged or edited): restore the saved weights or re-train.")


class EnsembleConfig(BaseModel):
    """Options of :class:`RewardEnsemble`."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    member_architecture: str = Field("ctg_mlp", description="Registered architecture of every member.")
    member_config: dict[str, Any] = Field(default_factory=dict, description="Options of the member architecture.")
    num_members: int = Field(2, ge=1, description="Number of members.")


class RewardEnsemble(RewardModel):
    """Members of one architecture (bootstrap ensemble); rewards are the members' mean, the spread their std.

    ``uncertainty(scenario)`` gives the standard deviation across members of the scenario reward ``(B,)``.
    :meth:`conservative` switches what the rewards a fine-tuner reads aggregate to the worst member or to
    mean - k x std (Coste et al. 2023); training always uses the mean.
    """

    architecture = "ensemble"
    Config = EnsembleConfig

    def __init__(self, config: EnsembleConfig | dict[str, Any] | None = None,
                 members: Sequence[RewardModel] | None = None) -> None:
        if members is not None and config is None:
            first = members[0]
            config = EnsembleConfig(member_architecture=first.architecture, member_config=first.config_dict(),
                                    num_members=len(members))
        super().__init__(config)
        cfg: EnsembleConfig = self.config  # type: ignore[assignment]
        if members is None:
            member_cls = get_reward_model_architecture(cfg.member_architecture)
            members = [member_cls(cfg.member_config) for _ in range(cfg.num_members)]
        if len(members) != cfg.num_members:
            raise ValueError(f"`members` holds {len(members)} models but `num_members` is {cfg.num_members}.")
        self.members = nn.ModuleList(members)
        self.aggregation, self.pessimism = "mean", 0.0

    def conservative(self, aggregation: str = "lcb", pessimism: float = 1.0) -> RewardEnsemble:
        """Aggregate the members' rewards by ``"mean"``, ``"worst"`` (their minimum) or ``"lcb"`` (mean -
        ``pessimism`` x std) in :meth:`step_rewards`, :meth:`agent_scores` and the scenario score; returns self."""
        if aggregation not in ("mean", "worst", "lcb"):
            raise ValueError(f"`aggregation` is {aggregation!r}; use 'mean', 'worst' or 'lcb'.")
        if pessimism < 0:
            raise ValueError(f"`pessimism` is {pessimism}; give k >= 0 (mean - k x std).")
        self.aggregation, self.pessimism = aggregation, float(pessimism)
        return self

    def _combine(self, stacked: torch.Tensor) -> torch.Tensor:
        if self.aggregation == "worst":
            return stacked.min(0).values
        if self.aggregation == "lcb" and len(self.members) > 1:
            return stacked.mean(0) - self.pessimism * stacked.std(0)
        return stacked.mean(0)

    def member_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Scenario rewards of every member ``(M, B)``."""
        return torch.stack([m(scenario) for m in self.members])

    def agent_scores(self, scenario: ScenarioTensor) -> torch.Tensor:
        """The members' per-agent rewards ``(B, A)``, aggregated (the mean unless :meth:`conservative`)."""
        return self._combine(torch.stack([m.agent_scores(scenario) for m in self.members]))

    def step_rewards(self, scenario: ScenarioTensor) -> torch.Tensor:
        """The members' per-step rewards ``(B, T)``, aggregated (the mean unless :meth:`conservative`)."""
        return self._combine(torch.stack([m.step_rewards(scenario) for m in self.members]))

    def forward(self, scenario: ScenarioTensor) -> torch.Tensor:
        """The members' scenario rewards ``(B,)``, aggregated (the mean unless :meth:`conservative`)."""
        return self._combine(self.member_scores(scenario))

    def uncertainty(self, scenario: ScenarioTensor) -> torch.Tensor:
        """Standard deviation across members of the scenario rewards ``(B,)`` (0 for one member)."""
        scores = self.member_scores(scenario)
        return scores.std(0) if len(self.members) > 1 else torch.zeros_like(scores[0])

    def prepare(self, scenario: ScenarioTensor) -> Any:
        """The first member's prepared inputs (members share an architecture and so their inputs)."""
        return self.members[0].prepare(scenario)

    def score_prepared(self, prepared: Any) -> torch.Tensor:
        """Mean over members of :meth:`RewardModel.score_prepared`."""
        return torch.stack([m.score_prepared(prepared) for m in self.members]).mean(0)
