"""Metric cost: FailureMetric + RealismMetric("ctg") of the SDK against the slow reference implementation
(``trafficrlhf_sdk.testing.reference_metrics``: shapely boxes, per-point pixel lookups, numpy/scipy) on the first
100 long-enough nuscenes_pred val scenes x 10 s, for a constant-velocity and a log-replay rollout.

Asserts identical results (failure/collision/off-road rates exactly equal, realism within 1e-9) and prints the
speed-up. Target: >= 50x.

Run: .venv/bin/python benchmarks/bench_metrics.py  [--threads N]
"""

from __future__ import annotations

from _common import header, load_val, timed

from trafficrlhf_sdk.metrics import FailureMetric, RealismMetric
from trafficrlhf_sdk.simulation import ConstantVelocityPolicy, log_rollout, simulate
from trafficrlhf_sdk.testing.reference_metrics import reference_failure, reference_realism_ctg

RATES = ("failure_rate", "collision_rate", "offroad_rate")
REALISM = ("realism_ctg", "realism_ctg_lon_acc", "realism_ctg_lat_acc", "realism_ctg_jerk")


def sdk_metrics(rollout):  # type: ignore[no-untyped-def]
    values = dict(FailureMetric().compute(rollout).values)
    values.update(RealismMetric("ctg").compute(rollout).values)
    return values


def reference_metrics(rollout):  # type: ignore[no-untyped-def]
    failure = reference_failure(rollout)
    realism = reference_realism_ctg(rollout)
    return {**{k: failure[k] for k in RATES}, **{k: realism[k] for k in REALISM}}


def main() -> None:
    header("failure + realism(ctg) metrics: SDK vs slow reference, 100 val scenes x 10 s")
    batch, load_s = load_val(100)
    print(f"   loaded {batch.num_scenes} scenes in {load_s:.2f} s (not timed)")
    rollouts = {"constant_velocity": simulate(ConstantVelocityPolicy(), batch), "log_replay": log_rollout(batch)}
    for name, rollout in rollouts.items():
        sdk_median, sdk_min, sdk = timed(lambda: sdk_metrics(rollout), repeats=7)  # noqa: B023
        ref_median, ref_min, ref = timed(lambda: reference_metrics(rollout), repeats=3, warmup=0)  # noqa: B023
        for key in RATES:
            assert sdk[key] == ref[key], (name, key, sdk[key], ref[key])
        for key in REALISM:
            assert abs(sdk[key] - ref[key]) <= 1e-9, (name, key, sdk[key], ref[key])
        print(f"   {name}: {int(rollout.controlled.sum())} controlled agents; results identical "
              f"(rates exactly, realism max |diff| {max(abs(sdk[k] - ref[k]) for k in REALISM):.1e})")
        print("     " + ", ".join(f"{k} {sdk[k]:.4f}" for k in RATES + REALISM[:1]))
        print(f"     SDK {sdk_median * 1e3:8.1f} ms (min {sdk_min * 1e3:.1f})   reference {ref_median:6.2f} s "
              f"(min {ref_min:.2f})   speed-up {ref_median / sdk_median:5.0f}x (median/median), "
              f"{ref_min / sdk_min:.0f}x (min/min)")


if __name__ == "__main__":
    main()
