"""Collect ``results.json`` of the BITS evaluation runs into the markdown table of ``adapters/bits/EVALUATION.md``.

    .venv/bin/python adapters/bits/scripts/evaluation_table.py out   # prints the table (runs under out/bits_eval)
"""

from __future__ import annotations

import json
import os
import sys

RUNS = [("log_replay", "bits_eval/log_replay"), ("constant_velocity", "bits_eval/constant_velocity"),
        ("ctg (no guidance)", "ctg_none"), ("**bits** (no guidance)", "bits_eval/bits"),
        ("bits + no_collision", "bits_eval/bits_no_collision"), ("bits + speed_limit", "bits_eval/bits_speed_limit"),
        ("bits + target_speed", "bits_eval/bits_target_speed"), ("bits + no_offroad", "bits_eval/bits_no_offroad"),
        ("bits + goal_waypoint", "bits_eval/bits_goal_waypoint"),
        ("bits, selection without progress", "bits_eval/bits_no_progress")]
ROWS = [("failure_rate", "failure rate"), ("collision_rate", "collision rate"), ("offroad_rate", "off-road rate"),
        ("failure_rate_corners", "failure rate (box corners)"), ("realism_ctg", "realism dev. (ctg)"),
        ("realism_body", "realism dev. (body)"), ("guidance_speed_limit", "speed-limit violation (m/s)"),
        ("guidance_target_speed", "target-speed error (m/s)"), ("guidance_goal_waypoint", "goal distance (m)")]


def main(root: str) -> None:
    """Print the markdown table of the runs found under ``root``."""
    found = []
    for label, folder in RUNS:
        path = os.path.join(root, folder, "results.json")
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as handle:
                found.append((label, json.load(handle)))
    print("| metric | " + " | ".join(label for label, _ in found) + " |")
    print("|---" * (len(found) + 1) + "|")
    for key, name in ROWS:
        cells = []
        for _, result in found:
            value = result["metrics"].get(key)
            cells.append("n/a" if value is None else f"{value:.4f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("| evaluate wall time (s) | " + " | ".join(f"{r['wall_time_s']:.1f}" for _, r in found) + " |")
    print("| closed-loop time (s) | " + " | ".join(f"{r['simulation_time_s']:.1f}" for _, r in found) + " |")
    print("| controlled agents | " + " | ".join(str(r["num_controlled_agents"]) for _, r in found) + " |")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "out")
