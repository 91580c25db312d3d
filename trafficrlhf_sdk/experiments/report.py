"""Writing one experiment table: markdown, JSON and PNG, with the comparison against the paper's directions."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

from trafficrlhf_sdk.experiments.published import EXPECTED, SOURCE, compare_change, published_change

__all__ = ["COLUMNS", "clean_json", "direction_rows", "fmt", "markdown_table", "plot_bars", "write_result"]

COLUMNS: dict[str, str] = {
    "realism_ctg": "realism dev. (paper)",
    "realism_body": "realism dev. (body)",
    "realism_meta": "realism meta-metric",
    "failure_rate": "failure rate",
    "reward_cost": "reward cost",
}
"""Metric keys of the tables and their column headings."""


def fmt(value: Any, digits: int = 4) -> str:
    """A table cell: numbers with ``digits`` decimals, None and NaN as "n/a", anything else as text."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        return f"{value:.{digits}f}"
    return str(value)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table; cells go through :func:`fmt`. Every row must have one cell per header."""
    for row in rows:
        if len(row) != len(headers):
            raise ValueError(f"a row has {len(row)} cells for {len(headers)} headers: {list(row)}")
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def direction_rows(pairs: Sequence[tuple[str, dict[str, Any], dict[str, Any]]],
                   metrics: Sequence[str]) -> list[dict[str, Any]]:
    """For each ``(label, base, aligned)`` and metric: the change and whether it goes the paper's way
    (:func:`~trafficrlhf_sdk.experiments.published.compare_change`)."""
    rows = []
    for label, base, aligned in pairs:
        for metric in metrics:
            rows.append({"comparison": label, "metric": metric,
                         "base": base.get(metric), "aligned": aligned.get(metric),
                         **compare_change(metric, base.get(metric), aligned.get(metric)),
                         "paper_relative": published_change(label, metric)})
    return rows


def _direction_table(rows: Sequence[dict[str, Any]]) -> str:
    arrow = {-1: "lower", 1: "higher", 0: "no claim"}
    body = []
    for row in rows:
        relative = None if row["relative"] is None else f"{100 * row['relative']:+.1f} %"
        paper = row.get("paper_relative")
        agrees = {True: "yes", False: "**no**", None: "n/a"}[row["agrees"]]
        body.append([row["comparison"], COLUMNS.get(row["metric"], row["metric"]), row["base"], row["aligned"],
                     relative, None if paper is None else f"{100 * paper:+.1f} %", arrow[row["expected"]], agrees])
    return markdown_table(["comparison", "metric", "without RM", "with RM", "change", "the paper's change",
                           "paper's direction", "reproduced"], body)


def plot_bars(path: str, labels: Sequence[str], series: dict[str, Sequence[float | None]], title: str) -> str:
    """One panel per metric in ``series`` (values per label, None drawn as a gap); returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(series), figsize=(max(4.0, 0.55 * len(labels)) * len(series) ** 0.5 + 3,
                                                      3.6), squeeze=False)
    for ax, (metric, values) in zip(axes[0], series.items()):
        heights = [float("nan") if v is None else v for v in values]
        colours = ["tab:orange" if "+" in label else "tab:blue" for label in labels]
        ax.bar(range(len(labels)), heights, color=colours)
        ax.set_xticks(range(len(labels)))
        ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
        ax.set_title(COLUMNS.get(metric, metric), fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_result(folder: str, result: dict[str, Any], table_md: str, comparisons: Sequence[dict[str, Any]] = (),
                 notes: Sequence[str] = ()) -> list[str]:
    """Write ``result.json`` (``result`` plus the comparisons) and ``result.md`` (title, command, seeds, wall time,
    the table, the comparison with the paper's directions and ``notes``) into ``folder``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    result = {**result, "paper_source": SOURCE, "comparison": list(comparisons),
              "expected_directions": {k: {"direction": v.direction, "basis": v.basis} for k, v in EXPECTED.items()}}
    lines = [f"### {result['title']}", "", f"Command: `{result['command']}`; evaluation seed {result.get('seed')}, "
             f"{result.get('rollouts')} rollout(s) per scene on {result.get('scenes')} val scenes; wall time "
             f"{result['wall_time_s']:.0f} s ({result.get('threads')} torch threads).", "", table_md, ""]
    if comparisons:
        lines += ["Against the paper (its relative change beside ours, from its own tables: its models are the "
                  "full-size upstream ones, its base fails more, e.g. CTG 0.271 under no collision against about 0.10 "
                  "here, so a relative reduction is harder here; realism values are on another scale, compare "
                  "changes only):", "", _direction_table(comparisons), ""]
    lines += [f"- {note}" for note in notes]
    paths = [os.path.join(folder, "result.json"), os.path.join(folder, "result.md")]
    tmp = paths[0] + ".tmp"
    with open(paths[1], "w", encoding="utf-8") as handle:
        handle.write("\n".join(lines).rstrip() + "\n")
    with open(tmp, "w", encoding="utf-8") as handle:
        json.dump(clean_json(result), handle, indent=2, default=str)
    os.replace(tmp, paths[0])  # result.json last: its presence marks the table done
    return paths


def clean_json(value: Any) -> Any:
    """``value`` with every NaN or infinite float replaced by None (strict JSON), recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): clean_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean_json(v) for v in value]
    return value
