"""Loading cost: every nuscenes_pred label file (train + val, 660 scenes, short ones included) read into one
ScenarioTensor per scene (no batching), maps included.

Reports total seconds, scenes/s and peak resident memory. Each repeat uses a fresh source object (so the label
listing, which parses every file once to count keyframes, is timed too) and drops the previous repeat's scenes.
The first repeat may read from a cold OS file cache; the median is over all repeats.

Run: .venv/bin/python benchmarks/bench_load.py  [--threads N]
"""

from __future__ import annotations

import gc
import time

from _common import header, peak_rss_mb

from trafficrlhf_sdk import get_scenario_source

REPEATS = 3


def load_everything() -> tuple[list, float, float]:  # type: ignore[type-arg]
    """(scenes, seconds to list the scenes, seconds in total)."""
    tic = time.perf_counter()
    source = get_scenario_source("nuscenes_pred", min_future_s=0.0)  # every scene with >= 3 s of history
    list_all = getattr(source, "all_scene_ids", None) or source._num_keyframes  # every label file of the split
    ids = [(split, scene) for split in ("train", "val") for scene in list_all(split)]
    listed = time.perf_counter() - tic
    scenes = [source.load_scene(split, scene) for split, scene in ids]
    return scenes, listed, time.perf_counter() - tic


def main() -> None:
    header("load all nuscenes_pred scenes into per-scene ScenarioTensors")
    rss_before = peak_rss_mb()
    totals, listings = [], []
    scenes: list = []  # type: ignore[type-arg]
    for repeat in range(REPEATS):
        scenes = []
        gc.collect()
        scenes, listed, total = load_everything()
        totals.append(total)
        listings.append(listed)
        if repeat == 0:
            rss_one = peak_rss_mb()
    totals.sort()
    median = totals[len(totals) // 2]
    steps = sum(s.num_steps for s in scenes)
    agents = sum(s.num_agents for s in scenes)
    state_mb = sum(s.states.numel() * 4 + s.valid.numel() for s in scenes) / 2**20
    raster_mb = sum(s.map.pixels.numel() for s in scenes if s.map is not None) / 2**20
    print(f"   scenes {len(scenes)} ({agents} agent tracks, {steps} steps at 0.1 s in all)")
    print(f"   total  {median:.2f} s median of {REPEATS} (min {totals[0]:.2f}, max {totals[-1]:.2f}); "
          f"listing/parsing for keyframe counts {sorted(listings)[len(listings) // 2]:.2f} s of it")
    print(f"   rate   {len(scenes) / median:.0f} scenes/s")
    print(f"   memory peak RSS {rss_one:.0f} MB after the first load ({rss_before:.0f} MB before), "
          f"{peak_rss_mb():.0f} MB at the end; held tensors: states+valid {state_mb:.1f} MB, map rasters "
          f"{raster_mb:.0f} MB")


if __name__ == "__main__":
    main()
