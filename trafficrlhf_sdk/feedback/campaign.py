"""Feedback campaigns: K contexts (logged scenes), each with N candidate futures from one traffic model.

**How candidates are made.** For each context the scene is copied N times into one batch and the registered
traffic model drives every controlled agent in the SDK's closed-loop simulator
(:func:`~trafficrlhf_sdk.simulation.simulate`, replanning at 2 Hz, agents not controlled replay the log) for
``candidate_seconds`` (default 5 s) from the end of the logged history. Copy k of the batch is candidate k.
This is what the paper's annotators compare: N whole scenario futures of all agents from the same context, as
the model would produce them in simulation, rather than N open-loop 2 s samples of
:meth:`TrafficModelAdapter.sample`, which are too short to judge and never feel the consequences of their own
actions. It works for every registered traffic model (adapters and the built-in policies alike), and one
batched rollout per context keeps it cheap. The model is built with a seed derived from the campaign seed and
the scene (:func:`context_seed`), and ``reset`` re-seeds it, so a context's candidates depend only on (model,
guidance, campaign seed, scene): extending a campaign later regenerates nothing and changes nothing that
exists, and the same command reproduces the same candidates.

**Contexts the policy reaches itself.** With ``contexts="closed_loop"`` the model first drives the scene in
closed loop for up to ``drive_seconds``; the context is cut one second before the first collision or off-road
step of a driven agent (at a seeded random step of the drive when none fails), so its history is the model's own
driving and the candidates start where the model gets into trouble, the states a fine-tuner trains on
(iterated RLHF collects preferences where the policy drives).

The logged future over the same window is stored as the hidden reference ("none realistic" makes it the
winner). Maps are cropped to the agents' area plus a margin so the database stays small.

**Several models in one set.** ``candidate_models`` names the model of each of the N slots (e.g. two from one
model, three from another); each model rolls out its own copies of the scene (seeded per model and scene) and
the candidates are stored in slot order with their model recorded, so the export can tell which model each
winner and loser came from (``PreferenceDataset.context_keys[i]["models"]``). The annotators never see it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from trafficrlhf_sdk.errors import DataFormatError, TrafficRLHFError
from trafficrlhf_sdk.feedback.settings import AnnotationSettings
from trafficrlhf_sdk.feedback.store import Campaign, FeedbackStore, _shuffle_key
from trafficrlhf_sdk.parallel import ExecutionConfig, iter_tasks
from trafficrlhf_sdk.plugins import build_policy, get_scenario_source, list_plugins, registry
from trafficrlhf_sdk.scenario.map import crop_map
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.policies import seed_policy
from trafficrlhf_sdk.simulation.simulator import SimulationConfig, simulate
from trafficrlhf_sdk.version import __version__

__all__ = ["CampaignConfig", "CampaignReport", "campaign_candidates", "campaign_policy", "context_seed",
           "create_campaign", "crop_map", "extend_campaign", "generate_candidates",
           "generate_candidates_batch", "iter_candidates"]

MAX_CANDIDATES = 9  # keys 1..9 pick a candidate in the app
CONTEXTS_PER_ROLLOUT = 8  # contexts whose candidates one batched rollout makes (models with scene_generators)


class CampaignConfig(BaseModel):
    """Everything that defines a campaign; stored as JSON with it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(..., min_length=1, max_length=100, description="Campaign name, unique in the database.")
    model: str = Field(..., description="Registered traffic model or built-in policy (see `trafficrlhf plugins`).")
    guidance: str | None = Field(None, description="Guidance spec for models that accept one, e.g. 'no_collision'.")
    model_options: dict[str, Any] = Field(
        default_factory=dict, description="Extra options of the traffic model (e.g. {'checkpoint': 'dir'})."
    )
    source: str = Field("nuscenes_pred", description="Registered scenario source of the contexts.")
    split: str = Field("val", description="Split of the source.")
    root: str | None = Field(None, description="Data directory of the source; None uses the source's default.")
    scene_ids: list[str] | None = Field(None, description="Scenes to use; None takes the first `num_contexts`.")
    num_contexts: int = Field(10, ge=1, description="K: first K long-enough scenes of the split (sorted by name).")
    num_candidates: int = Field(5, ge=2, le=MAX_CANDIDATES, description="N candidate futures per context.")
    candidate_seconds: float = Field(5.0, gt=0, le=30, description="Length of each candidate future (s).")
    history_seconds: float = Field(3.0, ge=0.5, description="Logged history before the candidates start (s).")
    seed: int = Field(0, ge=0, description="Campaign seed: per-context model seeds and per-annotator shuffles.")
    labels_per_item: int | None = Field(
        None, ge=1, description="Annotators per item; None: every annotator labels every item."
    )
    map_margin_m: float = Field(25.0, ge=0, description="Map kept around the agents' positions (m).")
    contexts: Literal["log", "closed_loop"] = Field("log", description="'log': candidates start after the logged "
                                                    "history; 'closed_loop': after the model's own closed-loop "
                                                    "driving, cut shortly before its first failure (see the "
                                                    "module docstring).")
    drive_seconds: float = Field(6.0, gt=0, le=20, description="With contexts='closed_loop': the longest drive "
                                                                  "before a context is cut (s).")
    candidate_models: list[str] | None = Field(
        None, description="The traffic model of each of the N candidates, in slot order (several models in one "
                          "set, e.g. ['a', 'a', 'b', 'b', 'c']); None: all N from `model`. Guidance and "
                          "model_options apply to every model.")
    annotation: AnnotationSettings = Field(
        default_factory=AnnotationSettings, description="Playback, guidelines, gold items, qualification, leases "
                                                        "and ties (changeable later).")

    @model_validator(mode="after")
    def _check_models(self) -> CampaignConfig:
        if self.contexts == "closed_loop" and self.candidate_models is not None:
            raise ValueError("contexts='closed_loop' drives one model before the candidates; leave "
                             "`candidate_models` unset or use contexts='log'.")
        if self.candidate_models is not None and len(self.candidate_models) != self.num_candidates:
            raise ValueError(f"`candidate_models` must name one model per candidate ({self.num_candidates}); got "
                             f"{len(self.candidate_models)}: {self.candidate_models}. Repeat a model to give it "
                             "several slots.")
        return self


@dataclass(frozen=True)
class CampaignReport:
    """What a create/extend call did: the campaign, ids of the added contexts, scenes already present, and scenes
    left out because their context shows no vehicle to judge at its start (e.g. a later start of a scene whose
    vehicles have all left)."""

    campaign: Campaign
    added: list[int]
    skipped: list[str]
    empty: list[str] = field(default_factory=list)


def context_seed(campaign_seed: int, source: str, split: str, scene_id: str) -> int:
    """The model seed of one context (31 bits), a hash of the campaign seed and the scene."""
    return _shuffle_key(campaign_seed, source, split, scene_id) % (2**31 - 1)


def campaign_policy(model: str, guidance: str | None, seed: int, options: dict[str, Any] | None = None) -> Any:
    """Instantiate registered traffic model ``model`` for a campaign: ``guidance`` for a model that takes none is
    an error (silently dropping it would mislabel the campaign); ``seed`` is passed where accepted (deterministic
    policies have none); other ``options`` must be accepted."""
    return build_policy(model, {**(options or {}), "guidance": guidance, "seed": seed})


def generate_candidates(policy: Any, scene: ScenarioTensor, num_candidates: int, seconds: float,
                        map_margin_m: float) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                                      torch.Tensor]:
    """Roll ``policy`` out ``num_candidates`` times from one logged scene (B = 1).

    Returns:
        context: the logged scene over steps ``0 .. end`` (B = 1, ``current_index`` = start, ``controlled`` =
            the agents the policy drove, map cropped); candidates ``(N, A, H, 4)`` and their valid ``(N, A, H)``;
            the logged future ``(A, H, 4)`` and its valid ``(A, H)``, with H = ``seconds / dt`` steps.
    """
    rollout = simulate(policy, ScenarioTensor.concat([scene] * num_candidates), SimulationConfig(duration_s=seconds))
    return _context_candidates(rollout, scene, 0, num_candidates, map_margin_m)


def generate_candidates_batch(policy: Any, scenes: Sequence[ScenarioTensor], seeds: Sequence[int],
                              num_candidates: int, seconds: float, map_margin_m: float) -> list[tuple[Any, ...]]:
    """:func:`generate_candidates` for several contexts, context i with ``policy`` seeded by ``seeds[i]``.

    An adapter that offers ``scene_generators`` rolls all contexts out as one batch, each context's copies
    drawing from its own seed (:meth:`~trafficrlhf_sdk.models.adapter.TrafficModelAdapter.seed_scenes`), so each
    result equals the context's own run; other policies run the contexts one after the other. (Equal to the last
    bit where the context alone gives the model 16 rows or more per call, e.g. CTG with guidance: 5 samples x 5
    copies per agent; on CPU the matrix kernels of smaller calls may round the last bit differently.)"""
    if len(scenes) == 1 or not getattr(policy, "scene_generators", False):
        out = []
        for scene, seed in zip(scenes, seeds):
            seed_policy(policy, seed)
            out.append(generate_candidates(policy, scene, num_candidates, seconds, map_margin_m))
        return out
    batch = ScenarioTensor.concat([copy for scene in scenes for copy in [scene] * num_candidates])
    policy.seed_scenes(seeds, [num_candidates] * len(scenes))
    try:
        rollout = simulate(policy, batch, SimulationConfig(duration_s=seconds))
    finally:
        policy.seed_scenes(None)
    return [_context_candidates(rollout, scene, i, num_candidates, map_margin_m) for i, scene in enumerate(scenes)]


def _context_candidates(rollout: Any, scene: ScenarioTensor, index: int, num_candidates: int, map_margin_m: float
                        ) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Context ``index`` of a rollout over consecutive groups of ``num_candidates`` copies: its context, candidates
    and logged future (:func:`generate_candidates`), cut back to the scene's own agents and map."""
    start, end, a = rollout.start_index, rollout.end_index, scene.num_agents
    rows, future = slice(index * num_candidates, (index + 1) * num_candidates), slice(start + 1, end + 1)
    candidates = rollout.simulated.states[rows, :a, future].contiguous()
    candidate_valid = rollout.simulated.valid[rows, :a, future].contiguous()
    logged = rollout.logged[index * num_candidates]
    context = logged.replace_unchecked(
        states=logged.states[:, :a], valid=logged.valid[:, :a], extent=logged.extent[:, :a],
        agent_type=logged.agent_type[:, :a], controlled=rollout.controlled[rows][:1, :a].clone(), map=scene.map,
        agent_ids=tuple(ids[:a] for ids in logged.agent_ids))
    if context.map is not None:
        shown = torch.cat([scene.xy[0][scene.valid[0]], candidates[..., :2][candidate_valid]])
        context = context.replace_unchecked(map=crop_map(context.map, shown, map_margin_m))
    context = ScenarioTensor(**{f: getattr(context, f) for f in context.__dataclass_fields__})  # validate
    return (context, candidates, candidate_valid, logged.states[0, :a, future].clone(),
            logged.valid[0, :a, future].clone())


def closed_loop_context(policy: Any, scene: ScenarioTensor, drive_seconds: float, candidate_seconds: float,
                        seed: int, lead_seconds: float = 1.0) -> ScenarioTensor:
    """``scene`` (B = 1) after ``policy`` drove its controlled agents in closed loop, cut ``lead_seconds`` before
    the first collision or off-road step of a driven agent (at a random step of the drive, drawn from ``seed``,
    when none fails): the model's states up to the cut, the log after it, the same history length as ``scene``
    and ``current_index`` at the cut; ``controlled`` = the driven agents present and on the road there. ``scene``
    itself when no such agent is left."""
    from trafficrlhf_sdk.metrics.failure import collisions_per_step, offroad_per_step

    start, dt = scene.current_index, scene.dt
    drive = max(1, min(round(drive_seconds / dt), scene.num_steps - 1 - start - round(candidate_seconds / dt)))
    with torch.no_grad():
        rollout = simulate(policy, scene, SimulationConfig(duration_s=drive * dt))
    sim = rollout.simulated
    driven = rollout.controlled[0]
    failed = collisions_per_step(sim)[0]
    if sim.map is not None and "drivable" in sim.map.layers:
        failed = failed | offroad_per_step(sim)[0]
    failed = failed & sim.valid[0] & driven[:, None]
    steps = torch.arange(sim.num_steps)
    failed &= (steps > start) & (steps <= start + drive)
    if failed.any():
        cut = max(start, int(steps[failed.any(0)].min()) - round(lead_seconds / dt))
    else:
        gen = torch.Generator().manual_seed(seed)
        cut = start + int(torch.randint(0, drive + 1, (1,), generator=gen))
    t = min(cut + 1, sim.num_steps)
    states = torch.cat([sim.states[:, :, :t], scene.states[:, :, t:]], 2)
    valid = torch.cat([sim.valid[:, :, :t], scene.valid[:, :, t:]], 2)
    hybrid = scene.replace_unchecked(states=states * valid[..., None], valid=valid)
    window = hybrid.time_slice(cut - start, scene.num_steps)
    controlled = rollout.controlled & window.valid[:, :, start]
    if window.map is not None and "drivable" in window.map.layers:  # as the simulator keeps agents at a start
        controlled &= window.map.lookup(window.xy[:, :, start].double())
    if not controlled.any():  # nobody left to drive from the cut: the logged context
        return scene
    return window.replace_unchecked(current_index=start, controlled=controlled)


def _open_source(cfg: CampaignConfig) -> Any:
    future = cfg.candidate_seconds + (cfg.drive_seconds if cfg.contexts == "closed_loop" else 0.0)
    options: dict[str, Any] = {"history_s": cfg.history_seconds, "min_future_s": future,
                               "max_future_s": future + 1.0}
    if cfg.root is not None:
        options["root"] = cfg.root
    return get_scenario_source(cfg.source, **options)


def _provenance(model: str) -> dict[str, Any]:
    owner = registry("traffic_models").owner(model)
    versions = {p["name"]: p["version"] for p in list_plugins()}
    return {"model_plugin": owner, "model_plugin_version": versions.get(owner)}


def create_campaign(store: FeedbackStore, config: CampaignConfig, on_context: Callable[[str], None] | None = None,
                    execution: ExecutionConfig | None = None) -> CampaignReport:
    """Create campaign ``config.name`` in ``store`` and generate its contexts (one transaction per context).
    ``execution``: a :class:`~trafficrlhf_sdk.parallel.ExecutionConfig` to generate candidates on Ray workers."""
    source = _open_source(config)
    source.check_split(config.split)
    for model in dict.fromkeys(config.candidate_models or [config.model]):  # fail early
        campaign_policy(model, config.guidance, config.seed, config.model_options)
    stored = config.model_dump(mode="json")
    stored["provenance"] = _provenance(config.model)
    if config.candidate_models:
        stored["provenance"]["candidate_models"] = {m: _provenance(m) for m in dict.fromkeys(config.candidate_models)}
    campaign = store.create_campaign(config.name, config.model, config.guidance, config.seed, config.num_candidates,
                                     stored, __version__)
    return _fill(store, campaign, source, _scene_list(source, config), on_context, execution)


def extend_campaign(store: FeedbackStore, name: str, scene_ids: Sequence[str] | None = None,
                    num_contexts: int | None = None, root: str | None = None,
                    on_context: Callable[[str], None] | None = None,
                    execution: ExecutionConfig | None = None) -> CampaignReport:
    """Add contexts to campaign ``name`` with its stored model, guidance, seed and sizes (``execution``: as for
    :func:`create_campaign`).

    ``scene_ids`` adds those scenes; ``num_contexts`` grows the campaign to cover the first ``num_contexts``
    scenes of its split. Scenes already present are skipped, never regenerated.
    """
    campaign = store.campaign(name)
    stored = {k: v for k, v in campaign.config.items() if k != "provenance"}
    if root is not None:
        stored["root"] = root
    config = CampaignConfig(**{**stored, "scene_ids": list(scene_ids) if scene_ids else None,
                               "num_contexts": num_contexts or stored.get("num_contexts", 10)})
    source = _open_source(config)
    return _fill(store, campaign, source, _scene_list(source, config), on_context, execution)


def _scene_list(source: Any, config: CampaignConfig) -> list[str]:
    available = source.scene_ids(config.split)
    if config.scene_ids is None:
        return available[: config.num_contexts]
    missing = [s for s in config.scene_ids if s not in available]
    if missing:
        raise TrafficRLHFError(
            f"scenes {missing} are not long enough scenes of {config.source}/{config.split} (history "
            f"{config.history_seconds} s + {config.candidate_seconds} s); pick others (`trafficrlhf inspect`)."
        )
    return list(config.scene_ids)


def _fill(store: FeedbackStore, campaign: Campaign, source: Any, scene_ids: list[str],
          on_context: Callable[[str], None] | None, execution: ExecutionConfig | None = None) -> CampaignReport:
    cfg = campaign.config
    present = {(k["source"], k["split"], k["scene_id"]) for k in store.context_keys(campaign)}
    todo = [s for s in scene_ids if (cfg["source"], cfg["split"], s) not in present]
    skipped = [s for s in scene_ids if (cfg["source"], cfg["split"], s) in present]
    parts = iter_candidates(campaign, source, todo, execution)  # each stored as soon as it is made
    added, empty = [], []
    for scene_id, (context, cands, cand_valid, logged, logged_valid) in zip(todo, parts):
        seed = context_seed(campaign.seed, cfg["source"], cfg["split"], scene_id)
        if not bool(context.controlled.any()):  # its items would show nobody to judge: left out, reported
            empty.append(scene_id)
            continue
        added.append(store.add_context(campaign, cfg["source"], cfg["split"], scene_id, seed, context, cands,
                                       cand_valid, logged, logged_valid, __version__,
                                       candidate_models=cfg.get("candidate_models")))
        if on_context is not None:
            on_context(scene_id)
    if empty and not added:
        shown = ", ".join(f"{cfg['source']}/{cfg['split']}/{s}" for s in empty[:5]) + (" ..." if len(empty) > 5 else "")
        raise DataFormatError(
            f"{shown}: the context has no controlled agent (no vehicle is present at its start on the drivable layer "
            f"of its map), so its items would show nobody to judge; none of the {len(empty)} new contexts was "
            "stored. Pick other scenes or an earlier start (`history_seconds`), or fix the map."
        )
    return CampaignReport(store.campaign(campaign.id), added, skipped, empty)


def _mixed_candidates(campaign: Campaign, scene: ScenarioTensor, slots: list[str], cfg: dict[str, Any],
                      key: tuple[str, str, str]) -> tuple[ScenarioTensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                                           torch.Tensor]:
    """Candidates of several models in slot order: each model rolls out as many copies as it has slots."""
    parts: dict[str, tuple[Any, ...]] = {}
    for model in dict.fromkeys(slots):
        seed = context_seed(campaign.seed, *key) if model == slots[0] else \
            _shuffle_key(campaign.seed, model, *key) % (2**31 - 1)
        policy = campaign_policy(model, campaign.guidance, seed, cfg.get("model_options"))
        with torch.no_grad():
            parts[model] = generate_candidates(policy, scene, slots.count(model), cfg["candidate_seconds"],
                                               cfg["map_margin_m"])
    taken = dict.fromkeys(parts, 0)
    cands, valid = [], []
    for model in slots:
        cands.append(parts[model][1][taken[model]])
        valid.append(parts[model][2][taken[model]])
        taken[model] += 1
    context, _, _, logged, logged_valid = parts[slots[0]]
    candidates, candidate_valid = torch.stack(cands), torch.stack(valid)
    if scene.map is not None:
        shown = torch.cat([context.xy[0][context.valid[0]], candidates[..., :2][candidate_valid]])
        context = context.replace_unchecked(map=crop_map(scene.map, shown, cfg["map_margin_m"]))
        context = ScenarioTensor(**{f: getattr(context, f) for f in context.__dataclass_fields__})
    return context, candidates, candidate_valid, logged, logged_valid


def _shared_payload(campaign: Campaign, source: Any) -> dict[str, Any]:
    """What every context's task reads: the campaign, the source and the model, built once (None for a campaign
    that mixes models, which :func:`_mixed_candidates` builds per context)."""
    cfg = campaign.config
    policy = None if cfg.get("candidate_models") else \
        campaign_policy(campaign.model, campaign.guidance, campaign.seed, cfg.get("model_options"))
    return {"campaign": campaign, "source": source, "policy": policy}


def _candidates_task(shared: dict[str, Any], scene_ids: list[str]) -> list[tuple[Any, ...]]:
    """Candidates of a few campaign contexts (runs in-process or on a Ray worker): the scenes are read from the
    shipped source and the shipped model samples each context from the context's seed (what building it with
    that seed does), all of them in one rollout when the model offers ``scene_generators``
    (:func:`generate_candidates_batch`); for ``contexts="closed_loop"`` the model first drives each scene to its
    context (:func:`closed_loop_context`)."""
    campaign, cfg = shared["campaign"], shared["campaign"].config
    keys = [(cfg["source"], cfg["split"], scene_id) for scene_id in scene_ids]
    scenes = [shared["source"].load_scene(cfg["split"], scene_id) for scene_id in scene_ids]
    if cfg.get("candidate_models"):
        return [_mixed_candidates(campaign, scene, cfg["candidate_models"], cfg, key)
                for scene, key in zip(scenes, keys)]
    policy = shared["policy"]
    seeds = [context_seed(campaign.seed, *key) for key in keys]
    if cfg.get("contexts", "log") == "closed_loop":
        for i, seed in enumerate(seeds):
            seed_policy(policy, seed)
            scenes[i] = closed_loop_context(policy, scenes[i], cfg["drive_seconds"], cfg["candidate_seconds"], seed)
    with torch.no_grad():
        return generate_candidates_batch(policy, scenes, seeds, campaign.num_candidates, cfg["candidate_seconds"],
                                         cfg["map_margin_m"])


def _task_chunks(shared: dict[str, Any], scene_ids: Sequence[str]) -> list[list[str]]:
    """The contexts each task makes together: ``CONTEXTS_PER_ROLLOUT`` for a model that samples groups of scenes
    from their own seeds in one batch, one otherwise."""
    size = CONTEXTS_PER_ROLLOUT if getattr(shared["policy"], "scene_generators", False) else 1
    return [list(scene_ids[i : i + size]) for i in range(0, len(scene_ids), size)]


def campaign_candidates(campaign: Campaign, source: Any, scene_ids: Sequence[str],
                        execution: ExecutionConfig | None = None) -> dict[str, tuple[Any, ...]]:
    """Candidates of a feedback campaign's contexts ``{scene_id: (context, candidates, valid, logged,
    logged_valid)}``, as :func:`create_campaign` makes them, computed on ``execution`` (Ray workers; in-process
    without). The model is built once and shipped once with the source; each task re-seeds it with its context's
    seed. Storing stays with the caller (one writer to the database)."""
    return dict(zip(scene_ids, iter_candidates(campaign, source, scene_ids, execution)))


def iter_candidates(campaign: Campaign, source: Any, scene_ids: Sequence[str],
                    execution: ExecutionConfig | None = None) -> Iterator[tuple[Any, ...]]:
    """:func:`campaign_candidates` as an iterator over ``scene_ids``, in order: a few contexts per task,
    in-process or on Ray workers, each yielded as soon as its task is done while the workers make the next."""
    shared = _shared_payload(campaign, source)
    for chunk in iter_tasks(_candidates_task, shared, _task_chunks(shared, list(scene_ids)), execution):
        yield from chunk
