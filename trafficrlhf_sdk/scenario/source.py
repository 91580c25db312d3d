"""``ScenarioSource``: the interface every dataset reader implements (registered through the plugin system)."""

from __future__ import annotations

import abc
import os
import warnings
from collections.abc import Iterator, Sequence
from typing import ClassVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from trafficrlhf_sdk.errors import TrafficRLHFError, UnknownComponentError
from trafficrlhf_sdk.scenario.checks import MAX_AGENTS, MIN_ON_MAP_SHARE
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["SOURCE_OPTIONS_ENV", "ScenarioSource", "SourceConfig", "default_data_root", "environment_options"]

SOURCE_OPTIONS_ENV = "TRAFFICRLHF_SOURCE_OPTIONS"


def default_data_root() -> str:
    """Where bundled data is looked for: ``$TRAFFICRLHF_DATA`` or ``../shared/data`` beside the project root."""
    env = os.environ.get("TRAFFICRLHF_DATA")
    if env:
        return env
    project_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return os.path.join(os.path.dirname(project_root), "shared", "data")


class SourceConfig(BaseModel):
    """Options common to every scenario source."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    root: str | None = Field(None, description="Directory holding the data; None uses the source's default.")
    dt: float = Field(0.1, gt=0, description="Time step of the produced ScenarioTensor (s).")
    history_s: float = Field(3.0, ge=0, description="History before 'now' in each scene window (s).")
    min_future_s: float = Field(10.0, ge=0, description="Scenes with less future than this are skipped (s).")
    max_future_s: float | None = Field(
        None, gt=0, description="Future kept after 'now' (s); None keeps everything up to the end of the scene."
    )
    min_on_map_share: float = Field(
        MIN_ON_MAP_SHARE, ge=0, le=1, description="A scene whose moving vehicles spend a smaller share of their "
        "logged positions on the drivable layer of its own map is refused (the map's origin or scale does not "
        "belong to the tracks), and so is one below 0.88 that a move of the map within 16 m would improve by 12 "
        "points (a misregistered map); 0 accepts every scene. Real nuScenes scenes measure 0.9 or more.")
    max_agents: int = Field(
        MAX_AGENTS, ge=1, description="Agents (tracks) one scene may hold, checked before any per-agent array is "
        "allocated; real scenes hold at most a few hundred.")

    @property
    def history_steps(self) -> int:
        """Number of steps before the current one."""
        return round(self.history_s / self.dt)


class ScenarioSource(abc.ABC):
    """Reads scenes of one dataset format into :class:`ScenarioTensor` windows.

    Subclasses set ``name`` and ``splits`` and implement :meth:`scene_ids` and :meth:`load_scene`. A scene
    window starts at the first logged step, holds ``history_s`` of history, then the future.
    """

    name: ClassVar[str] = ""
    Config: ClassVar[type[SourceConfig]] = SourceConfig

    def __init__(self, config: SourceConfig | None = None, **options: object) -> None:
        """``config``, or a ``Config`` built from ``options`` over those of ``$TRAFFICRLHF_SOURCE_OPTIONS``."""
        if config is None:
            fields, from_env = self.Config.model_fields, environment_options()
            ignored = sorted(set(from_env) - set(fields))
            if ignored:  # another source's option, or a typo: say so, never fail a source that does not take it
                warnings.warn(f"${SOURCE_OPTIONS_ENV}: source {self.name!r} takes no option {ignored}; ignored. Its "
                              f"options are {sorted(fields)}.", stacklevel=2)
            merged = {**{k: v for k, v in from_env.items() if k in fields}, **options}
            try:
                config = self.Config(**merged)
            except ValidationError as exc:
                if not set(merged) - set(options):
                    raise
                raise TrafficRLHFError(f"source {self.name!r}: the options {merged} (with those of "
                                       f"${SOURCE_OPTIONS_ENV}) are not valid: {_first_error(exc)}; fix "
                                       f"${SOURCE_OPTIONS_ENV} or the option.") from exc
        self.config = config

    @property
    @abc.abstractmethod
    def root(self) -> str:
        """The data directory actually used."""

    @abc.abstractmethod
    def splits(self) -> list[str]:
        """The splits present on disk (e.g. ``["train", "val"]``)."""

    @abc.abstractmethod
    def scene_ids(self, split: str) -> list[str]:
        """Ids of the scenes of ``split`` that are long enough for a window, sorted by name."""

    @abc.abstractmethod
    def load_scene(self, split: str, scene_id: str) -> ScenarioTensor:
        """One scene as a ScenarioTensor with B = 1."""

    def check_split(self, split: str) -> None:
        """Raise a clear error if ``split`` is not present."""
        available = self.splits()
        if split not in available:
            raise UnknownComponentError(
                f"split {split!r} not found in source {self.name!r} at {self.root!r}; available splits: {available}."
            )

    def iter_scenes(self, split: str, scene_ids: Sequence[str] | None = None) -> Iterator[ScenarioTensor]:
        """Yield one ScenarioTensor (B = 1) per scene of ``split`` (or of ``scene_ids``)."""
        for scene_id in scene_ids if scene_ids is not None else self.scene_ids(split):
            yield self.load_scene(split, scene_id)

    def load_batch(self, split: str, num_scenes: int | None = None, scene_ids: Sequence[str] | None = None,
                   progress: bool = False) -> ScenarioTensor:
        """The first ``num_scenes`` scenes of ``split`` (sorted by name), or ``scene_ids``, as one batch."""
        ids = list(scene_ids) if scene_ids is not None else self.scene_ids(split)[:num_scenes]
        if not ids:
            raise UnknownComponentError(f"source {self.name!r} has no scene long enough in split {split!r}.")
        scenes = self.iter_scenes(split, ids)
        if progress:
            from trafficrlhf_sdk.console import progress as progress_bar

            scenes = progress_bar(scenes, total=len(ids), desc=f"loading {self.name}/{split}", unit="scene")
        return ScenarioTensor.concat(list(scenes))


def environment_options() -> dict[str, str]:
    """Source options from ``$TRAFFICRLHF_SOURCE_OPTIONS``, comma-separated ``key=value`` pairs (e.g.
    ``min_on_map_share=0,max_agents=4096``): every command that opens a source gets those its source takes;
    options given in code or on the command line win; a key the source does not take is ignored with a warning."""
    text = os.environ.get(SOURCE_OPTIONS_ENV, "").strip()
    options: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise TrafficRLHFError(f"${SOURCE_OPTIONS_ENV}={text!r}: {item!r} is not key=value; write comma-separated"
                                   " pairs such as 'min_on_map_share=0,max_agents=4096'.")
        options[key.strip()] = value.strip()
    return options


def _first_error(exc: ValidationError) -> str:
    error = exc.errors()[0]
    return f"{'.'.join(str(p) for p in error['loc'])}: {error['msg']}"
