"""What shared raster rows save: 16 nuScenes train contexts, each repeated for 8 samples (an alignment epoch's 128
futures), their maps held as shared rows (``MapRaster.rows``, what ``repeat_scenes`` gives) against one copied row
per scene (``MapRaster.dense()``).

Prints, for each layout: the seconds to repeat the contexts, the raster megabytes held, and the seconds of the
map reads every epoch makes on the repeated batch (``map_crops`` of every agent at 48 px, the off-road lookup of
every agent-step). Asserts that both layouts read the same values. Data: nuScenes (CC BY-NC-SA 4.0).

Run: .venv/bin/python benchmarks/bench_map_rows.py  [--threads N]
"""

from __future__ import annotations

import torch
from _common import header, timed

from trafficrlhf_sdk import get_scenario_source
from trafficrlhf_sdk.models.features import map_crops
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

CONTEXTS, SAMPLES = 16, 8


def main() -> None:
    header(f"{CONTEXTS} train contexts x {SAMPLES} samples: shared raster rows against copied rows")
    source = get_scenario_source("nuscenes_pred")
    ids = source.scene_ids("train")
    picks = [ids[i] for i in torch.randperm(len(ids), generator=torch.Generator().manual_seed(0))[:CONTEXTS]]
    contexts = ScenarioTensor.concat([source.load_scene("train", i).time_slice(0, 71) for i in picks])
    contexts = contexts.replace_unchecked(current_index=30)
    assert contexts.map is not None
    results = {}
    for name, repeat in (("shared rows", lambda: contexts.repeat_scenes(SAMPLES)),
                         ("copied rows", lambda: contexts.repeat_scenes(SAMPLES).replace_unchecked(
                             map=contexts.repeat_scenes(SAMPLES).map.dense()))):  # type: ignore[union-attr]
        t_repeat, _, batch = timed(repeat, repeats=5)
        held = batch.map.pixels.numel() / 2**20  # type: ignore[union-attr]
        t_crops, _, crops = timed(lambda b=batch: map_crops(b, size_px=48), repeats=3)
        xy = batch.xy.double()
        t_lookup, _, on = timed(lambda b=batch, p=xy: b.map.lookup(p), repeats=3)
        results[name] = (crops, on)
        print(f"   {name:12s} repeat {1e3 * t_repeat:7.1f} ms   rasters held {held:7.0f} MB   "
              f"map_crops {1e3 * t_crops:6.1f} ms   lookup {1e3 * t_lookup:6.1f} ms")
    (a_crops, a_on), (b_crops, b_on) = results.values()
    assert torch.equal(a_crops, b_crops) and torch.equal(a_on, b_on), "the two layouts read different values"
    print("   both layouts read identical crops and lookups")


if __name__ == "__main__":
    main()
