"""Summary statistics of a source's scenes (what ``trafficrlhf inspect`` prints): counts, durations, agent types,
speeds."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from typing import Any

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.source import ScenarioSource
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["inspect_source", "scene_statistics"]


def _summary(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"mean": None, "min": None, "max": None}
    return {"mean": round(sum(values) / len(values), 4), "min": round(min(values), 4), "max": round(max(values), 4)}


def scene_statistics(scenes: Iterable[ScenarioTensor]) -> dict[str, Any]:
    """Summary statistics over scenes (each a ScenarioTensor; every scene of every batch counts once).

    Returns ``scenes_loaded``, ``dt_s`` (the time steps met), ``agents`` and ``controlled_agents`` (totals and per
    scene), ``duration_s`` / ``history_s`` / ``future_s`` (mean, min, max), ``agent_types`` (count per type),
    ``mean_speed_mps`` (over valid agent steps) and ``scene_ids``.
    """
    agents: list[int] = []
    controlled: list[int] = []
    durations: list[float] = []
    history_s: list[float] = []
    future_s: list[float] = []
    dts: set[float] = set()
    types: Counter[str] = Counter()
    speed_sum, speed_count = 0.0, 0
    scene_ids: list[str] = []
    for batch in scenes:
        for b in range(batch.num_scenes):
            valid = batch.valid[b]
            present = valid.any(-1)
            agents.append(int(present.sum()))
            controlled.append(int((batch.controlled[b] & present).sum()))
            active = valid.any(0).nonzero().flatten()
            span = int(active[-1] - active[0] + 1) if len(active) else 0
            durations.append(span * batch.dt)
            history_s.append(batch.current_index * batch.dt)
            future_s.append((batch.num_steps - 1 - batch.current_index) * batch.dt)
            dts.add(batch.dt)
            for code in batch.agent_type[b][present].tolist():
                types[AgentType(code).name if code in AgentType._value2member_map_ else str(code)] += 1
            speeds = batch.speed[b][valid].abs()
            speed_sum += float(speeds.double().sum())
            speed_count += int(speeds.numel())
            scene_ids.append(batch.scene_ids[b] if batch.scene_ids else str(len(scene_ids)))
    return {
        "scenes_loaded": len(agents),
        "dt_s": sorted(dts),
        "agents": {"total": sum(agents), "per_scene_mean": sum(agents) / len(agents) if agents else None,
                   "per_scene_max": max(agents, default=None), "per_scene_min": min(agents, default=None)},
        "controlled_agents": {"total": sum(controlled),
                              "per_scene_mean": sum(controlled) / len(controlled) if controlled else None},
        "duration_s": _summary(durations),
        "history_s": _summary(history_s),
        "future_s": _summary(future_s),
        "agent_types": dict(sorted(types.items())),
        "mean_speed_mps": speed_sum / speed_count if speed_count else None,
        "scene_ids": scene_ids,
    }


def _total_scene_count(source: ScenarioSource, split: str) -> int | None:
    """Number of scenes in ``split`` before the length filter, when the source offers ``all_scene_ids``."""
    all_ids = getattr(source, "all_scene_ids", None)
    if not callable(all_ids):
        return None
    try:
        return len(all_ids(split))
    except Exception:  # optional information only
        return None


def inspect_source(source: ScenarioSource, split: str, num_scenes: int | None = None) -> dict[str, Any]:
    """:func:`scene_statistics` of the first ``num_scenes`` long-enough scenes of ``split`` (all when None), with
    ``source``, ``split``, ``root`` and ``scenes``: how many were ``loaded``, are ``long_enough`` and are in the
    split in all (``total``, None when the source cannot tell)."""
    from trafficrlhf_sdk.console import progress

    source.check_split(split)
    ids = source.scene_ids(split)
    if not ids:
        raise TrafficRLHFError(
            f"source {source.name!r} has no scene long enough in split {split!r} at {source.root!r} (needs "
            f"{source.config.history_s} s of history + {source.config.min_future_s} s of future)."
        )
    chosen = ids[:num_scenes]
    scenes = progress((source.load_scene(split, scene_id) for scene_id in chosen), total=len(chosen),
                      desc=f"loading {source.name}/{split}", unit="scene", leave=False)
    stats = scene_statistics(scenes)
    return {"source": source.name, "split": split, "root": str(source.root),
            "scenes": {"loaded": stats.pop("scenes_loaded"), "long_enough": len(ids),
                       "total": _total_scene_count(source, split)},
            **stats}
