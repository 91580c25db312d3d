"""What the hostile-input cases share besides the harness: where the good inputs live, a one-scene copy of the
real data, and the check of an ``evaluate --json`` result that exits 0."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

from trafficrlhf_sdk.scenario import default_data_root

ROOT = Path(__file__).resolve().parents[2]
NUSCENES = Path(default_data_root()) / "nuscenes_pred"
SCENARIONET = Path(default_data_root()) / "nuscenes_mini_scenarionet"
SCENE = "scene-0002"


def one_scene_root(tmp_path: Path, nuscenes: Path = NUSCENES, scene: str = SCENE) -> Path:
    """A nuscenes_pred data root with one val scene (labels, map PNG, meta) copied from the real data."""
    root = tmp_path / "nuscenes_pred"
    (root / "label" / "val").mkdir(parents=True)
    (root / "maps").mkdir()
    shutil.copy(nuscenes / "label" / "val" / f"{scene}.txt", root / "label" / "val")
    for name in (f"{scene}.png", f"meta_{scene}.txt"):
        shutil.copy(nuscenes / "maps" / name, root / "maps")
    return root


def _rates(value: object) -> list[object]:
    """Every ``failure_rate`` in a JSON result (per-scene lists flattened, their NaN-as-None left out)."""
    if isinstance(value, dict):
        found: list[object] = []
        for key, item in value.items():
            if key != "failure_rate":
                found += _rates(item)
            elif isinstance(item, list):
                found += [x for x in item if x is not None]
            else:
                found.append(item)
        return found
    if isinstance(value, list):
        return [x for v in value for x in _rates(v)]
    return []


def check_evaluate(stdout: str, stderr: str) -> str | None:
    """``evaluate --json``: at least one scene and one controlled agent, finite failure rates in [0, 1]."""
    try:
        result = json.loads(stdout)
    except json.JSONDecodeError:
        return "stdout is not JSON"
    if result.get("num_scenes", 0) < 1 or result.get("num_controlled_agents", 0) < 1:
        return f"{result.get('num_scenes')} scenes, {result.get('num_controlled_agents')} controlled agents"
    rates = _rates(result)
    if not rates or not all(isinstance(r, float) and math.isfinite(r) and 0 <= r <= 1 for r in rates):
        return f"failure rates {rates[:4]!r}"
    return None
