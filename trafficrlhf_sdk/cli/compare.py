"""``trafficrlhf compare``: one markdown table from several ``trafficrlhf evaluate --out`` folders."""

from __future__ import annotations

import json
import os

import click

from trafficrlhf_sdk.cli import cli
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError

__all__ = ["comparison_table"]

ROWS = (
    ("failure_rate", "failure rate"),
    ("collision_rate", "collision rate"),
    ("offroad_rate", "off-road rate"),
    ("failure_rate_corners", "failure rate (box corners)"),
    ("realism_ctg", "realism dev. (ctg)"),
    ("realism_body", "realism dev. (body)"),
    ("guidance_speed_limit", "speed-limit violation (m/s)"),
    ("guidance_target_speed", "target-speed error (m/s)"),
    ("guidance_goal_waypoint", "goal distance (m)"),
    ("reward_cost", "reward cost"),
)


def _label(result: dict, folder: str) -> str:
    meta = result.get("metadata", {})
    model = meta.get("model") or os.path.basename(os.path.normpath(folder))
    label = f"{model} + {meta['guidance']}" if meta.get("guidance") else str(model)
    if meta.get("checkpoint"):  # aligned or retrained weights: say which
        label += f" ({os.path.basename(os.path.normpath(str(meta['checkpoint'])))})"
    return label


def comparison_table(folders: list[str]) -> str:
    """Markdown table (metrics as rows, runs as columns) of the ``results.json`` in each folder."""
    runs = []
    for folder in folders:
        path = os.path.join(folder, "results.json")
        if not os.path.isfile(path):
            raise DataNotFoundError(f"no results.json in {folder!r}; pass folders written by "
                                    "`trafficrlhf evaluate --out`.")
        try:
            with open(path, encoding="utf-8") as handle:
                runs.append((_label(result := json.load(handle), folder), result))
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{path}: invalid JSON ({exc}).") from exc
    lines = ["| metric | " + " | ".join(label for label, _ in runs) + " |", "|---" * (len(runs) + 1) + "|"]
    for key, name in ROWS:
        values = [result["metrics"].get(key) for _, result in runs]
        if all(v is None for v in values):
            continue
        lines.append(f"| {name} | " + " | ".join("n/a" if v is None else f"{v:.4f}" for v in values) + " |")
    lines.append("| closed-loop time (s) | " + " | ".join(f"{r['simulation_time_s']:.1f}" for _, r in runs) + " |")
    lines.append("| scenes / controlled agents | " + " | ".join(
        f"{r['num_scenes']} / {r['num_controlled_agents']}" for _, r in runs) + " |")
    return "\n".join(lines)


@cli.command("compare")
@click.argument("folders", nargs=-1, required=True)
def compare_command(folders: tuple[str, ...]) -> None:
    """Print a markdown table comparing the evaluation runs in FOLDERS (each holds a results.json)."""
    click.echo(comparison_table(list(folders)))
