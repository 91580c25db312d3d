"""Simulator overhead: closed-loop throughput with a zero-cost policy (a preallocated plan), 10 s at 2 Hz.

Reports controlled agent-steps per second (the steps the policy actually drives) and all-agent-slot steps per second
(B x A x 100, padding included), for the first 100 long-enough nuscenes_pred val scenes and for that batch tiled
k times along B. Target: >= 2 M agent-steps/s.

Run: .venv/bin/python benchmarks/bench_simulator.py  [--threads N]
"""

from __future__ import annotations


from _common import header, load_val, peak_rss_mb, timed

from trafficrlhf_sdk.scenario import ScenarioTensor
from trafficrlhf_sdk.simulation import Plan, SimulationConfig, simulate


class ZeroCostPolicy:
    """Returns the same preallocated plan (every agent stays where it is at the start) at every replan."""

    def __init__(self) -> None:
        self._plan: Plan | None = None

    def reset(self, scenario: ScenarioTensor) -> None:
        """Hold every agent at its current state."""
        now = scenario.states[:, :, scenario.current_index]
        self._plan = Plan(now[:, :, None].expand(-1, -1, 5, -1).contiguous())

    def plan(self, context: ScenarioTensor, horizon: int) -> Plan:
        """The same precomputed plan every time (the benchmark times the simulator, not a policy)."""
        assert self._plan is not None
        return self._plan


def main() -> None:
    header("simulator overhead, zero-cost policy, 10 s closed loop, replan every 0.5 s")
    batch, load_s = load_val(100)
    print(f"   loaded {batch.num_scenes} val scenes in {load_s:.2f} s (not timed below); A = {batch.num_agents} slots")
    config = SimulationConfig()
    # Tiles drop the map rasters (only read at reset, to skip off-road starters) and instead mark exactly the agents
    # the untiled run controlled, so every tile simulates the same agents without copying ~430 MB of rasters.
    controlled = simulate(ZeroCostPolicy(), batch, config).controlled
    untiled = batch.replace_unchecked(map=None, controlled=controlled)
    rows = []
    for k in (1, 4, 16, 64):
        scenario = batch if k == 1 else ScenarioTensor.concat([untiled] * k)
        policy = ZeroCostPolicy()
        runs = [simulate(policy, scenario, config)]  # warm-up
        median, _, _ = timed(lambda: runs.append(simulate(policy, scenario, config)), repeats=5, warmup=0)  # noqa: B023
        loop = sorted(r.wall_time_s for r in runs[1:])[2]
        steps = runs[-1].num_steps
        driven = int(runs[-1].controlled.sum()) * steps
        slots = scenario.num_scenes * scenario.num_agents * steps
        rows.append((k, scenario.num_scenes, driven, slots, median, loop))
    print(f"   {'tile':>4} {'scenes':>6} {'ctrl agent-steps':>16} {'slot-steps':>10} {'simulate() s':>12} "
          f"{'ctrl steps/s':>12} {'slot steps/s':>12} {'loop-only ctrl/s':>16}")
    for k, scenes, driven, slots, median, loop in rows:
        rates = f"{driven / median / 1e6:>10.2f} M {slots / median / 1e6:>10.2f} M {driven / loop / 1e6:>14.2f} M"
        print(f"   {k:>4} {scenes:>6} {driven:>16,} {slots:>10,} {median:>12.4f} {rates}")
    print("   (median of 5 runs after a warm-up; 'loop-only' is Rollout.wall_time_s, the replanning loop without the")
    print("    setup: window padding, controlled-agent selection with the off-road check, final validity/NaN pass)")
    print(f"   peak RSS {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
