"""Automatic contrast from recorded driving: the logged future against the same future made unrealistic.

A reward model learns what its data contrasts. Candidates drawn from one traffic model rarely differ in pace, in
the gap kept to the lead or in lane keeping, so preferences over them say little about those, and a policy
optimized against the reward model is free to drift there (agents speed up). Perturbing logged futures gives
pairs where the answer is known (the log is preferred), in the spirit of using real samples as positives
(Adv-GRPO) and of ranking a model's samples by how well they match the log (DPA-OMF):

========== ===============================================================================================
kind       the controlled agents that drive (above 1 m/s now) ...
========== ===============================================================================================
faster     follow their own logged path ``1 + strength`` times as fast (time-warped; constant velocity past
           the end of the log)
slower     follow it ``1 - strength / 2`` times as fast
jerky      follow it with the clock oscillating by ``strength`` seconds over a 3 s period (stop-and-go)
off_lane   drift sideways, ``4 * strength`` metres after 1.5 s, off their lane
tailgate   close in on the agent ahead to a bumper gap of 1 m over 2 s (agents with a lead within 40 m only)
weave      swerve side to side within their lane, ``strength`` metres either way every 2.5 s
stall      brake along their path to a standstill within 1.5 s, starting ``(1 - strength) * 2`` s in, and stay
           stopped
========== ===============================================================================================

The same perturbations are the **probes** of :func:`probe_reward_model`: on held-out logs each perturbed future
must score below the log; the pass rate per kind (and per ensemble member) says what the reward model can see.
Contrast sets use the first six by default (:data:`CONTRAST_KINDS`); ``stall`` is a probe, and a contrast kind
only when asked for.
Contrast pairs are stored with the annotator name ``CONTRAST_ANNOTATOR`` and weighed by
``RewardConfig.contrast_weight``; they are never counted as human labels.

Shapes follow :class:`~trafficrlhf_sdk.scenario.ScenarioTensor`: scenes ``B``, agents ``A``, steps ``T``; futures
are the steps after ``current_index``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.metrics.geometry import following_gaps
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor
from trafficrlhf_sdk.simulation.dynamics import wrap_angle

__all__ = ["CONTRAST_ANNOTATOR", "CONTRAST_KINDS", "PERTURBATIONS", "contrast_dataset", "log_windows", "perturb_future",
           "probe_reward_model", "recorded_windows"]

CONTRAST_ANNOTATOR = "contrast:log"
CONTRAST_KINDS = ("faster", "slower", "jerky", "off_lane", "tailgate", "weave")
"""The perturbations of a contrast set by default (:func:`contrast_dataset`)."""
PERTURBATIONS = (*CONTRAST_KINDS, "stall")
"""Every perturbation, and the probes of :func:`probe_reward_model`."""
MOVING_SPEED = 1.0  # m/s at "now": only agents that drive are perturbed
DEFAULT_STRENGTH = 0.5
JERK_PERIOD_S = 3.0  # s, the period of the stop-and-go clock
WEAVE_PERIOD_S = 2.5  # s, the period of a weave within the lane
STALL_BRAKE_S = 1.5  # s, braking from the logged pace to a standstill


def _warp(states: torch.Tensor, valid: torch.Tensor, now: int, clock: torch.Tensor, dt: float) -> torch.Tensor:
    """States ``(B, A, T, 4)`` re-timed: future step ``now + k`` takes the logged state at (fractional) step
    ``now + clock[..., k]``; ``clock (B, A, H)`` in steps. Past the last valid step the agent goes on at its last
    velocity. Speed is the path speed times the clock's rate."""
    t = states.shape[2]
    h = t - 1 - now
    steps = torch.arange(t, device=states.device)
    last = torch.where(valid, steps, torch.full_like(steps, -1)).amax(-1).clamp_min(now)  # (B, A)
    pos = now + clock  # (B, A, H)
    lo = pos.floor().long().clamp(0, t - 1)
    hi = (lo + 1).clamp(max=t - 1)
    lo_c, hi_c = torch.minimum(lo, last[..., None]), torch.minimum(hi, last[..., None])
    frac = (pos - lo.to(pos.dtype)).clamp(0, 1)[..., None]
    take = lambda idx: states.gather(2, idx[..., None].expand(-1, -1, -1, 4))  # noqa: E731
    s_lo, s_hi = take(lo_c), take(hi_c)
    xy = s_lo[..., :2] + (s_hi[..., :2] - s_lo[..., :2]) * frac
    yaw = s_lo[..., 3] + wrap_angle(s_hi[..., 3] - s_lo[..., 3]) * frac[..., 0]
    # beyond the log: constant velocity from the last valid state
    end = states.gather(2, last[..., None, None].expand(-1, -1, 1, 4))[:, :, 0]  # (B, A, 4)
    beyond = (pos - last[..., None].to(pos.dtype)).clamp_min(0)  # steps past the end
    heading = torch.stack([torch.cos(end[..., 3]), torch.sin(end[..., 3])], -1)[:, :, None]
    xy = torch.where((beyond > 0)[..., None], end[:, :, None, :2] + heading * (end[:, :, None, 2:3] * beyond[..., None]
                                                                             * dt), xy)
    yaw = torch.where(beyond > 0, end[..., None, 3].expand_as(yaw), yaw)
    rate = torch.diff(clock, dim=-1, prepend=torch.zeros_like(clock[..., :1]))  # steps of log per step
    speed = (s_lo[..., 2] + (s_hi[..., 2] - s_lo[..., 2]) * frac[..., 0]) * rate
    speed = torch.where(beyond > 0, end[..., None, 2] * rate, speed)
    out = states.clone()
    out[:, :, now + 1:] = torch.cat([xy, speed[..., None], wrap_angle(yaw)[..., None]], -1)[:, :, :h]
    return out


def perturb_future(scenario: ScenarioTensor, kind: str,
                   strength: float = DEFAULT_STRENGTH) -> tuple[ScenarioTensor, torch.Tensor]:
    """``(perturbed, changed)``: ``scenario`` with the future (after ``current_index``) of its moving controlled
    agents made unrealistic as ``kind`` (one of :data:`PERTURBATIONS`) says, ``strength`` in (0, 1], and the bool
    ``(B, A)`` mask of the agents it changed. The history and every other agent keep the log.

    ``faster`` / ``slower``: re-timed at 1 + strength / 1 - strength / 2 times the pace; ``jerky``: a stop-and-go
    clock; ``off_lane``: drifting up to 4 x strength metres sideways; ``tailgate``: closing in on the lead;
    ``weave``: swerving side to side by strength metres every 2.5 s; ``stall``: braking to a standstill from
    (1 - strength) x 2 s on."""
    if kind not in PERTURBATIONS:
        raise TrafficRLHFError(f"unknown perturbation {kind!r}; use one of {', '.join(PERTURBATIONS)}.")
    if not 0 < strength <= 1:
        raise TrafficRLHFError(f"`strength` is {strength}; give a value in (0, 1], e.g. 0.5.")
    states, valid, now = scenario.states, scenario.valid, scenario.current_index
    b, a, t, _ = states.shape
    h = t - 1 - now
    if h < 2:
        raise TrafficRLHFError(f"the scenario has {h} future steps after current_index {now}; at least 2 are needed.")
    dt = scenario.dt
    k = torch.arange(1, h + 1, dtype=states.dtype, device=states.device).expand(b, a, h)
    moving = scenario.controlled & valid[:, :, now] & (states[:, :, now, 2] > MOVING_SPEED)
    new = states.clone()
    if kind in ("faster", "slower", "jerky", "stall"):
        if kind == "faster":
            clock = k * (1 + strength)
        elif kind == "slower":
            clock = k * (1 - strength / 2)
        elif kind == "stall":  # the clock's rate falls from 1 to 0 over STALL_BRAKE_S, then the agent stays put
            rate = (1 - (k * dt - (1 - strength) * 2.0) / STALL_BRAKE_S).clamp(0, 1)
            clock = torch.cumsum(rate, -1)
        else:
            amplitude = strength / dt  # steps
            clock = k + amplitude * torch.sin(2 * math.pi * k * dt / JERK_PERIOD_S)
        new = _warp(states, valid, now, clock, dt)
    elif kind in ("off_lane", "weave"):
        if kind == "off_lane":
            offset = (k * dt / 1.5).clamp(max=1.0) * 4 * strength  # metres to the left
        else:  # a side-to-side swerve of strength x 2 m peak to peak, starting smoothly
            offset = strength * torch.sin(2 * math.pi * k * dt / WEAVE_PERIOD_S)
        yaw = states[:, :, now + 1:, 3]
        normal = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)
        new[:, :, now + 1:, :2] = states[:, :, now + 1:, :2] + normal * offset[..., None]
        if kind == "weave":  # the heading follows the swerve
            drift = torch.diff(offset, dim=-1, prepend=torch.zeros_like(offset[..., :1])) / dt
            new[:, :, now + 1:, 3] = wrap_angle(yaw + torch.atan2(drift, states[:, :, now + 1:, 2].clamp_min(0.5)))
    else:  # tailgate
        gap = following_gaps(scenario.xy, scenario.yaw, states[..., 2], scenario.extent, valid)[:, :, now]  # (B, A)
        has_lead = torch.isfinite(gap) & (gap > 2.0) & (gap < 40.0)
        moving = moving & has_lead
        speed = states[:, :, now, 2].clamp_min(MOVING_SPEED)
        ahead_steps = (gap - 1.0).clamp_min(0) / (speed * dt)  # steps of the agent's own driving to close the gap
        ramp = (k * dt / 2.0).clamp(max=1.0) * ahead_steps[..., None] * strength * 2
        new = _warp(states, valid, now, k + ramp, dt)
    keep = moving[:, :, None, None] & valid[:, :, :, None]
    future = torch.zeros(t, dtype=torch.bool, device=states.device)
    future[now + 1:] = True
    states_out = torch.where(keep & future[None, None, :, None], new, states)
    return scenario.replace_unchecked(states=states_out * valid[..., None]), moving


def log_windows(scenes: ScenarioTensor, history_steps: int = 10, future_steps: int = 40,
                starts: Sequence[int] = (30, 60)) -> ScenarioTensor:
    """Windows ``[s - history_steps, s + future_steps]`` of every scene at each start step ``s`` (``current_index`` =
    ``history_steps``), the agents valid at ``s`` controlled; scenes too short for a start are skipped."""
    parts = []
    for start in starts:
        if start - history_steps < 0 or start + future_steps >= scenes.num_steps:
            continue
        window = scenes.time_slice(start - history_steps, start + future_steps + 1)
        window = window.replace_unchecked(current_index=history_steps,
                                          controlled=scenes.controlled & scenes.valid[:, :, start])
        parts.append(window)
    if not parts:
        raise TrafficRLHFError(f"the scenes ({scenes.num_steps} steps) hold no window of {history_steps} + "
                               f"{future_steps} steps at starts {list(starts)}.")
    return ScenarioTensor.concat(parts)


def recorded_windows(source: str = "nuscenes_pred", split: str = "val", num_scenes: int = 50,
                     root: str | None = None, from_end: bool = False, future_steps: int = 40) -> ScenarioTensor:
    """:func:`log_windows` of the first (``from_end``: last) ``num_scenes`` long-enough scenes of ``split``: held-out
    logs for probes (``val``) or contrast pairs (the end of ``train``, away from the scenes campaigns start with)."""
    from trafficrlhf_sdk.plugins import get_scenario_source

    reader = get_scenario_source(source, **({"root": root} if root else {}))
    ids = reader.scene_ids(split)
    ids = ids[-num_scenes:] if from_end else ids[:num_scenes]
    if not ids:
        raise TrafficRLHFError(f"split {split!r} of source {source!r} has no scene long enough.")
    return log_windows(reader.load_batch(split, scene_ids=ids), future_steps=future_steps)


def contrast_dataset(scenes: ScenarioTensor, kinds: Sequence[str] = CONTRAST_KINDS,
                     strength: float = DEFAULT_STRENGTH, split: str = "train",
                     annotators: Mapping[str, Any] | None = None) -> Any:
    """A :class:`~trafficrlhf_sdk.feedback.PreferenceDataset` of contrast items: every context of ``scenes``
    (``current_index`` = the start of the futures) with, as options, its logged future and that future perturbed
    as each of ``kinds`` that changes an agent; futures ``(K, len(kinds) + 1, A, H, 4)`` with the log last.

    ``annotators`` None: the pairs "log ≻ each perturbation", annotator :data:`CONTRAST_ANNOTATOR` (an assumption:
    the log is more realistic). ``annotators`` (name -> a
    :class:`~trafficrlhf_sdk.feedback.SyntheticAnnotatorConfig`, e.g. stand-in profiles): each annotator labels
    each item as a campaign item, from what the item shows, with its own noise (best of the options, or "none
    realistic": no pairs); its pick is preferred to every other option. A perturbation the judgment does not
    notice then gives no pair "log ≻ it", and one it finds more realistic is preferred to the log."""
    from trafficrlhf_sdk.feedback.preference import PreferenceDataset

    now = scenes.current_index
    futures, valids, changed, options = [], [], [], []
    for kind in kinds:
        moved, agents = perturb_future(scenes, kind, strength)
        futures.append(moved.states[:, :, now + 1:])
        valids.append(scenes.valid[:, :, now + 1:])
        changed.append(agents.any(-1))
        options.append(moved)
    futures.append(scenes.states[:, :, now + 1:])
    valids.append(scenes.valid[:, :, now + 1:])
    options.append(scenes)
    futures_t = torch.stack(futures, 1).float()
    valid_t = torch.stack(valids, 1)
    log_slot = len(kinds)
    shown = torch.stack([*changed, torch.ones_like(changed[0])], 1).cpu()  # (K, kinds + 1): the item's options
    ids = scenes.scene_ids or tuple(str(c) for c in range(scenes.num_scenes))
    if annotators is None:
        names: tuple[str, ...] = (CONTRAST_ANNOTATOR,)
        pairs = [(c, log_slot, j, 0) for c in range(scenes.num_scenes) for j in range(len(kinds)) if shown[c, j]]
    else:
        from trafficrlhf_sdk.feedback.judgment import judge_scenarios
        from trafficrlhf_sdk.feedback.synthetic import annotator_generator, noisy_choice

        names = tuple(annotators)
        pairs = []
        for n, (name, config) in enumerate(annotators.items()):
            judgment = config.judgment()
            realism = torch.stack([judge_scenarios(o, o.controlled, judgment).realism for o in options], 1).cpu()
            for c in range(scenes.num_scenes):
                slots = shown[c].nonzero().flatten().tolist()
                if len(slots) < 2:
                    continue
                generator = annotator_generator(config.seed, name, f"contrast/{ids[c]}/{now}")
                pick = noisy_choice(realism[c, slots], config, generator)
                if pick is not None:
                    pairs += [(c, slots[pick], j, n) for j in slots if j != slots[pick]]
    if not pairs:
        raise TrafficRLHFError("no perturbation changed any agent of these scenes (no controlled agent drives "
                               f"faster than {MOVING_SPEED} m/s at current_index), or no annotator found any "
                               "option realistic; pass scenes with moving traffic.")
    table = torch.tensor(pairs, dtype=torch.long)
    # one label per pair for the assumption; per (context, annotator) when annotators pick
    labels = torch.arange(len(pairs)) if annotators is None else table[:, 0] * len(names) + table[:, 3]
    keys = tuple({"campaign": "contrast", "source": scenes.source, "split": (scenes.extras or {}).get("split"),
                  "scene_id": ids[c], "context_id": f"contrast/{ids[c]}/{now}",
                  "models": [f"log:{kind}" for kind in kinds] + ["log"]}
                 for c in range(scenes.num_scenes))
    return PreferenceDataset(contexts=scenes, futures=futures_t, future_valid=valid_t, pairs=table[:, :3],
                             pair_annotator=table[:, 3], pair_label=labels,
                             context_split=tuple(split for _ in range(scenes.num_scenes)), context_keys=keys,
                             annotators=names,
                             metadata={"kinds": list(kinds), "strength": strength, "contrast": True,
                                       "judged_by": None if annotators is None else list(names)})


def _members(model: Any) -> list[Any]:
    members = getattr(model, "members", None)
    return list(members) if members is not None and len(members) > 1 else [model]


def probe_reward_model(model: Any, scenes: ScenarioTensor, kinds: Sequence[str] = PERTURBATIONS,
                       strength: float = DEFAULT_STRENGTH) -> dict[str, dict[str, Any]]:
    """Per kind: the share of the windows of ``scenes`` that the perturbation changes (the probes) where
    ``model`` scores the perturbed future strictly below the log, for the model and each ensemble member; and the
    mean score gap (log minus perturbed). A reward model that cannot see a kind passes about half of its probes,
    one that prefers it fewer. ``model``: anything with ``score(scenario) -> (B,)``.

    Each entry counts its ``windows`` (the probes) and the distinct ``scenes`` they come from:
    :func:`recorded_windows` cuts two windows from most scenes, and a kind changes only windows it applies to
    (tailgating needs a lead)."""
    def scores(m: Any, scenario: ScenarioTensor) -> torch.Tensor:
        with torch.no_grad():
            return m.score(scenario).detach().float().cpu()

    report: dict[str, dict[str, Any]] = {}
    models = _members(model)
    logged = {id(m): scores(m, scenes) for m in [model, *models]}
    for kind in kinds:
        moved, agents = perturb_future(scenes, kind, strength)
        changed = agents.any(-1).cpu()
        if not changed.any():
            report[kind] = {"windows": 0, "scenes": 0, "pass_rate": float("nan"), "members": [],
                            "mean_gap": float("nan")}
            continue
        ids = scenes.scene_ids or [str(b) for b in range(scenes.num_scenes)]
        entry: dict[str, Any] = {"windows": int(changed.sum()),
                                 "scenes": len({ids[b] for b in changed.nonzero().flatten().tolist()})}
        for m in [model, *models]:
            gap = (logged[id(m)] - scores(m, moved))[changed]
            rate = float((gap > 0).float().mean())
            if m is model:
                entry["pass_rate"], entry["mean_gap"] = rate, float(gap.mean())
            else:
                entry.setdefault("members", []).append(rate)
        entry.setdefault("members", [])
        report[kind] = entry
    return report
