"""Comparison tables over several evaluation folders (what ``trafficrlhf compare`` prints)."""

from __future__ import annotations

import json
import os
import re

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError

__all__ = ["change_interval_table", "compare_report", "comparison_table", "interval_table", "meta_metric_table",
           "read_results", "run_folders", "run_label", "scene_change_table", "tradeoff_plot", "tradeoff_points"]

SHARED_ROWS = (
    ("guidance_speed_limit", "speed-limit violation (m/s)"),
    ("guidance_target_speed", "target-speed error (m/s)"),
    ("guidance_goal_waypoint", "goal distance (m)"),
    ("speed_ratio", "speed / logged speed"),
    ("speed_ratio_turning", "  agents turning in the log"),
    ("speed_ratio_straight", "  agents driving straight"),
    ("stopped_share", "stopped at the end (share)"),
    ("stopped_share_logged", "  stopped in the log"),
    ("reward_cost", "reward cost"),
    ("realism_meta", "realism meta-metric (higher is better)"),
    ("realism_meta_linear_speed", "  linear speed"),
    ("realism_meta_linear_acceleration", "  linear acceleration"),
    ("realism_meta_angular_speed", "  angular speed"),
    ("realism_meta_angular_acceleration", "  angular acceleration"),
    ("realism_meta_distance_to_nearest_object", "  distance to nearest object"),
    ("realism_meta_collision_indication", "  collision"),
    ("realism_meta_time_to_collision", "  time to collision"),
    ("realism_meta_distance_to_road_edge", "  distance to road edge"),
    ("realism_meta_offroad_indication", "  off-road"),
)
"""The rows after the failure and realism rows, shared with ``trafficrlhf evaluate``'s table."""

ROWS = (
    ("failure_rate", "failure rate"),
    ("collision_rate", "collision rate"),
    ("collision_rate_own", "  with an agent it drives"),
    ("collision_rate_replayed", "  with a replayed agent"),
    ("offroad_rate", "off-road rate"),
    ("failure_rate_turning", "failure rate, agents turning in the log"),
    ("failure_rate_straight", "  agents driving straight"),
    ("failure_rate_corners", "failure rate (box corners)"),
    ("realism_ctg", "realism dev. (ctg)"),
    ("realism_body", "realism dev. (body)"),
    ("realism_body_speed", "speed-histogram dev. (body, m/s)"),
) + SHARED_ROWS


def run_label(metadata: dict, folder: str = "") -> str:
    """The name of a run in tables: the model, its guidance and, when one was given, the checkpoint (a bundled
    checkpoint's name, or a folder's last two parts), so a base and its aligned checkpoint never share a column."""
    model = metadata.get("model") or os.path.basename(os.path.normpath(folder)) or "model"
    label = f"{model} + {metadata['guidance']}" if metadata.get("guidance") else str(model)
    checkpoint = metadata.get("checkpoint")
    if checkpoint:  # aligned or retrained weights: say which
        parts = os.path.normpath(str(checkpoint)).split(os.sep)
        label += f" ({'/'.join(parts[-2:]) if len(parts) > 1 else parts[0]})"
    return label


def _label(result: dict, folder: str) -> str:
    return run_label(result.get("metadata", {}), folder)


def read_results(folder: str) -> dict:
    """The ``results.json`` of an evaluation folder (``trafficrlhf evaluate --out``), with ``_folder`` set."""
    path = os.path.join(folder, "results.json")
    if not os.path.isfile(path):
        raise DataNotFoundError(f"no results.json in {folder!r}; pass folders written by "
                                "`trafficrlhf evaluate --out`.")
    try:
        with open(path, encoding="utf-8") as handle:
            result = json.load(handle)
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: invalid JSON ({exc}).") from exc
    result["_folder"] = folder  # where scene_histograms.npz lies, read only by --interval
    return result


def run_folders(folder: str) -> list[str]:
    """The results folders of one evaluation folder: its ``seed_<S>`` folders in seed order (``trafficrlhf evaluate
    --seeds``), or the folder itself."""
    seeds = [name for name in os.listdir(folder) if name.startswith("seed_") and name[5:].isdigit()
             and os.path.isfile(os.path.join(folder, name, "results.json"))] if os.path.isdir(folder) else []
    return [os.path.join(folder, name) for name in sorted(seeds, key=lambda n: int(n[5:]))] or [folder]


def _scene_counts(runs: list[dict]) -> list[dict] | None:
    """Each run's per-scene realism counts ``{preset: ...}``, each archive read once (None if any run lacks
    them: results written without per-scene histograms)."""
    from trafficrlhf_sdk.evaluation.protocol import SCENE_HISTOGRAMS, load_scene_histograms

    paths = [os.path.join(run["_folder"], SCENE_HISTOGRAMS) for run in runs]
    if not all(os.path.isfile(path) for path in paths):
        return None
    return [load_scene_histograms(path) for path in paths]


def _pool_seeds(runs: list[tuple[str, dict]]) -> list[tuple[str, list[dict]]]:
    """Group runs of one policy (same label and scenes) that differ only in their seed, keeping order."""
    groups: list[tuple[str, list[dict]]] = []
    for label, result in runs:
        meta = result.get("metadata", {})
        for name, members in groups:
            first = members[0].get("metadata", {})
            seeds = {m.get("metadata", {}).get("seed") for m in members}
            if (name == label and first.get("scene_ids") == meta.get("scene_ids")
                    and meta.get("seed") is not None and meta.get("seed") not in seeds):
                members.append(result)
                break
        else:
            groups.append((label, [result]))
    # within a policy, in seed order (a shell glob lists seed_10 before seed_9)
    return [(label, sorted(members, key=lambda m: m.get("metadata", {}).get("seed") or 0))
            for label, members in groups]


def comparison_table(folders: list[str]) -> str:
    """Markdown table (metrics as rows, runs as columns) of the ``results.json`` in each folder.

    Runs of the same policy on the same scenes with different seeds share a column: the mean, then the value
    of each seed (evaluation noise is often as large as the effects compared).
    """
    groups = _pool_seeds([(_label(result := read_results(folder), folder), result) for folder in folders])
    header = []
    for label, members in groups:
        seeds = [str(m.get("metadata", {}).get("seed")) for m in members]
        header.append(label if len(members) == 1 else f"{label}, seeds {' / '.join(seeds)}")
    lines = ["| metric | " + " | ".join(header) + " |", "|---" * (len(groups) + 1) + "|"]

    def cell(values: list[float | None]) -> str:
        if any(v is None for v in values):
            return "n/a"
        mean = sum(values) / len(values)  # type: ignore[arg-type]
        return f"{mean:.4f}" if len(values) == 1 else f"{mean:.4f} ({' / '.join(f'{v:.4f}' for v in values)})"

    for key, name in ROWS:
        values = [[m["metrics"].get(key) for m in members] for _, members in groups]
        if all(v is None for vs in values for v in vs):
            continue
        lines.append(f"| {name} | " + " | ".join(cell(vs) for vs in values) + " |")
    lines.append("| closed-loop time (s) | " + " | ".join(
        " / ".join(f"{m['simulation_time_s']:.1f}" for m in members) for _, members in groups) + " |")
    lines.append("| scenes / controlled agents | " + " | ".join(
        f"{members[0]['num_scenes']} / {members[0]['num_controlled_agents']}" for _, members in groups) + " |")
    return "\n".join(lines)


def scene_change_table(folders: list[str], top: int, key: str = "failure_rate") -> str:
    """Markdown table of the ``top`` scenes whose ``key`` changed most from the first policy's runs to the last
    policy's (each pooled over its seeds, as in :func:`comparison_table`), plus how many scenes rose or fell."""
    from trafficrlhf_sdk.evaluation.breakdown import pooled_per_scene, scene_changes

    (first, before_runs), (last, after_runs) = _first_and_last(folders, "--scene-changes")
    before, after = pooled_per_scene(before_runs, key), pooled_per_scene(after_runs, key)
    changes = scene_changes(before, after)
    rose = sum(1 for row in changes if row.change > 0)
    fell = sum(1 for row in changes if row.change < 0)
    lines = [f"{key} per scene, {first} -> {last}: {fell} scenes lower, {rose} higher, "
             f"{len(changes) - rose - fell} unchanged", "",
             f"| scene | agents | {first} | {last} | change |", "|---|---|---|---|---|"]
    lines += [f"| {row.scene_id} | {row.controlled_agents} | {row.before:.4f} | {row.after:.4f} | {row.change:+.4f} |"
              for row in changes[:top]]
    return "\n".join(lines)


INTERVAL_KEYS = (("failure_rate", "failure rate"), ("collision_rate", "collision rate"),
                 ("collision_rate_own", "collision with an agent it drives"),
                 ("collision_rate_replayed", "collision with a replayed agent"), ("offroad_rate", "off-road rate"))
REALISM_INTERVAL_KEYS = (("ctg", "realism dev. (ctg)"), ("body", "realism dev. (body)"))


def _first_and_last(folders: list[str], option: str) -> tuple[tuple[str, list[dict]], tuple[str, list[dict]]]:
    groups = _pool_seeds([(_label(result := read_results(folder), folder), result) for folder in folders])
    if len(groups) < 2:
        raise DataFormatError(f"{option} needs runs of two policies; got one ({groups[0][0]!r}). Pass the "
                              "folders of a first and a second model.")
    return groups[0], groups[-1]


def change_interval_table(folders: list[str], level: float = 0.95, resamples: int = 10_000,
                          target: float | None = None) -> str:
    """Markdown table of the relative change from the first policy's runs to the last policy's (each pooled over
    its seeds) in the failure, collision and off-road rates, each with a paired bootstrap interval over scenes
    (:func:`~trafficrlhf_sdk.evaluation.breakdown.paired_change_interval`), and in the two realism deviations where
    every run's folder has ``scene_histograms.npz``
    (:func:`~trafficrlhf_sdk.evaluation.breakdown.paired_realism_interval`).
    ``target``: a relative change such as -0.7; adds the share of the failure-rate draws at or below it."""
    (first, before_runs), (last, after_runs) = _first_and_last(folders, "--interval")
    return interval_table(first, before_runs, last, after_runs, level, resamples, target)


def interval_table(first: str, before_runs: list[dict], last: str, after_runs: list[dict], level: float = 0.95,
                   resamples: int = 10_000, target: float | None = None) -> str:
    """:func:`change_interval_table` of two policies already grouped: ``before_runs`` and ``after_runs`` are
    :func:`read_results` dicts of the same scenes (each policy's seeds), ``first`` and ``last`` their names."""
    from trafficrlhf_sdk.evaluation.breakdown import paired_change_interval, paired_realism_interval, pooled_per_scene

    seeds = f"{len(before_runs)} / {len(after_runs)} seed(s)"
    extra = "" if target is None else f" share of draws <= {100 * target:+.0f} % |"
    lines = [f"{first} -> {last} ({seeds}); {100 * level:.0f} % paired bootstrap interval over scenes", "",
             f"| metric | {first} | {last} | change | interval |{extra}",
             "|---|---|---|---|---|" + ("---|" if target is not None else "")]
    scenes = draws = None
    for key, name in INTERVAL_KEYS:
        if not all(key in (r.get("per_scene") or {}) for r in before_runs + after_runs):
            continue
        before, after = pooled_per_scene(before_runs, key), pooled_per_scene(after_runs, key)
        if not any(value > 0 for _, value in before.values()):
            after_mean = sum(value for _, value in after.values()) / max(len(after), 1)
            lines.append(f"| {name} | 0.0000 | {after_mean:.4f} | n/a: 0 before | |" + (" |" if extra else ""))
            continue
        ci = paired_change_interval(before, after, level=level, resamples=resamples, target=target)
        row = (f"| {name} | {ci.before:.4f} | {ci.after:.4f} | {100 * ci.change:+.1f} % | "
               f"{100 * ci.low:+.1f} % to {100 * ci.high:+.1f} % |")
        if ci.share_meeting_target is not None:
            row += f" {ci.share_meeting_target:.2f} |"
        lines.append(row)
        scenes, draws = ci.scenes, ci.resamples
    if len(lines) == 4:
        raise DataFormatError("no per-scene failure, collision or off-road rates in these results; re-run "
                              "`trafficrlhf evaluate --out` with this version to write them.")
    same_scenes = (before_runs[0].get("metadata", {}).get("scene_ids")
                   == after_runs[0].get("metadata", {}).get("scene_ids"))
    before_counts = _scene_counts(before_runs) if same_scenes else None
    after_counts = _scene_counts(after_runs) if before_counts is not None else None
    for preset, name in REALISM_INTERVAL_KEYS:
        if before_counts is None or after_counts is None:
            break
        if any(preset not in run for run in before_counts + after_counts):
            continue
        ci = paired_realism_interval([run[preset] for run in before_counts], [run[preset] for run in after_counts],
                                     level=level, resamples=resamples)
        lines.append(f"| {name} | {ci.before:.4f} | {ci.after:.4f} | {100 * ci.change:+.1f} % | "
                     f"{100 * ci.low:+.1f} % to {100 * ci.high:+.1f} % |" + (" |" if extra else ""))
    if scenes is not None:
        lines += ["", f"{scenes} scenes, {draws} draws. The interval covers drawing another {scenes} scenes like "
                      "these (and the seeds' noise inside each scene's mean), not a change of data set."]
    return "\n".join(lines)


def meta_metric_table(folders: list[str], level: float = 0.95, resamples: int = 10_000) -> str | None:
    """Markdown table of the realism meta-metric of every run against the first (each pooled over its seeds):
    the difference with a paired bootstrap interval over scenes, and the head-to-head share (scenes where the run
    beats the first; ties count half). None unless every run holds per-scene meta-metric values at the same K."""
    from trafficrlhf_sdk.evaluation.breakdown import paired_difference_interval, pooled_per_scene

    groups = _pool_seeds([(_label(result := read_results(folder), folder), result) for folder in folders])
    runs = [members for _, members in groups]
    if len(groups) < 2 or not all("realism_meta" in (r.get("per_scene") or {}) for rs in runs for r in rs):
        return None
    ks = {r.get("metadata", {}).get("rollouts") for rs in runs for r in rs}
    if len(ks) != 1:
        raise DataFormatError(f"the runs used different rollouts per scene ({sorted(map(str, ks))}); the "
                              "meta-metric depends on K, so compare runs of equal --rollouts.")
    base_label, base = groups[0][0], pooled_per_scene(groups[0][1], "realism_meta")
    lines = [f"realism meta-metric (K = {ks.pop()}) against {base_label}; {100 * level:.0f} % paired bootstrap "
             "interval of the difference over scenes", "",
             f"| run | meta-metric | {base_label} | difference | interval | scenes won |", "|---|---|---|---|---|---|"]
    for label, members in groups[1:]:
        other = pooled_per_scene(members, "realism_meta")
        ci = paired_difference_interval(base, other, level=level, resamples=resamples)
        lines.append(f"| {label} | {ci.after:.4f} | {ci.before:.4f} | {ci.difference:+.4f} | {ci.low:+.4f} to "
                     f"{ci.high:+.4f} | {100 * ci.win_share:.0f} % of {ci.scenes} |")
    return "\n".join(lines)


SEED_SUFFIX = re.compile(r"[_-]?s(?:eed)?\d+$")
"""A trailing training-seed suffix of a folder name (``_s3``, ``-seed3``): folders that differ only in it are
draws of one recipe and share a colour in :func:`tradeoff_plot`."""


def _mean_metric(folder: str, key: str) -> float:
    """``key`` averaged over the seed runs of an evaluation folder."""
    values = [read_results(run)["metrics"].get(key) for run in run_folders(folder)]
    if any(v is None for v in values):
        raise DataFormatError(f"{folder!r} has no {key!r} in its results.json; evaluate with the default metrics.")
    return sum(values) / len(values)


def tradeoff_points(folders: list[str]) -> list[tuple[str, float, float]]:
    """``(name, failure change, speed change)`` of each folder after the first, both relative to the first
    folder's (the base's) seed-averaged ``failure_rate`` and ``speed_ratio`` (speed / logged speed); ``name`` is the
    folder's own name."""
    if len(folders) < 2:
        raise TrafficRLHFError(f"tradeoff_points needs a base folder and at least one other; got {folders!r}.")
    base_failure, base_speed = (_mean_metric(folders[0], k) for k in ("failure_rate", "speed_ratio"))
    if base_failure <= 0 or base_speed <= 0:
        raise DataFormatError(f"the base folder {folders[0]!r} has failure rate {base_failure:g} and speed ratio "
                              f"{base_speed:g}; relative changes need both above 0. Pass another base first.")
    return [(os.path.basename(os.path.normpath(folder)),
             _mean_metric(folder, "failure_rate") / base_failure - 1.0,
             _mean_metric(folder, "speed_ratio") / base_speed - 1.0) for folder in folders[1:]]


def tradeoff_plot(folders: list[str], path: str, failure_target: float | None = None,
                  speed_band: float | None = None) -> str:
    """A PNG at ``path``: each folder after the first as a point, its failure-rate change against its change in
    speed / logged speed, both relative to the first folder. Folders whose names differ only in a seed suffix
    (:data:`SEED_SUFFIX`) share a colour and a legend entry, with their mean as a larger marker. Optional guides:
    ``failure_target`` (e.g. -0.6) and ``speed_band`` (e.g. 0.05, drawn at -band and +band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list[tuple[float, float]]] = {}
    for name, failure, speed in tradeoff_points(folders):
        groups.setdefault(SEED_SUFFIX.sub("", name) or name, []).append((100 * speed, 100 * failure))
    fig, ax = plt.subplots(figsize=(7, 4.6))
    for i, (group, points) in enumerate(groups.items()):
        colour = f"C{i % 10}"
        ax.scatter([p[0] for p in points], [p[1] for p in points], color=colour, alpha=0.6, s=28,
                   label=f"{group} ({len(points)})")
        if len(points) > 1:
            ax.scatter([sum(p[0] for p in points) / len(points)], [sum(p[1] for p in points) / len(points)],
                       color=colour, marker="D", s=80, edgecolor="black")
    if failure_target is not None:
        ax.axhline(100 * failure_target, color="grey", linestyle="--", linewidth=1)
    if speed_band is not None:
        for edge in (-speed_band, speed_band):
            ax.axvline(100 * edge, color="grey", linestyle="--", linewidth=1)
    ax.set(xlabel="speed / logged speed, change from the base (%)", ylabel="failure rate, change from the base (%)",
           title=f"against {os.path.basename(os.path.normpath(folders[0]))}; diamonds: mean of a group's draws")
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def compare_report(folders: list[str], scene_changes: int = 0, interval: bool = False, level: float = 0.95,
                   target: float | None = None) -> str:
    """What ``trafficrlhf compare`` prints: :func:`comparison_table` of the runs in ``folders`` (an ``evaluate
    --seeds`` folder stands for its ``seed_<S>`` runs), then, where they apply, :func:`meta_metric_table`, the
    ``scene_changes`` scenes that moved most (:func:`scene_change_table`) and with ``interval`` the changes with
    their paired intervals (:func:`change_interval_table`; ``target`` a relative change such as -0.7)."""
    runs = [run for folder in folders for run in run_folders(folder)]
    parts = [comparison_table(runs)]
    meta = meta_metric_table(runs, level=level)
    if meta is not None:  # runs with --rollouts K >= 2: the meta-metric against the first run, per scene
        parts.append(meta)
    if scene_changes:
        parts.append(scene_change_table(runs, scene_changes))
    if interval:
        parts.append(change_interval_table(runs, level=level, target=target))
    return "\n\n".join(parts)
