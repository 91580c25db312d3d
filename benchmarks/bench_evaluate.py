"""End-to-end evaluation: constant velocity on the first 100 long-enough nuscenes_pred val scenes, 10 s closed
loop at 2 Hz, every registered default metric for the policy and for the logged data (``evaluate_policy``).

Loading is timed separately; the evaluation is repeated and the median wall time reported. With ``--rollouts K``
every scene is simulated K times and the realism meta-metric is added (for the policy and, as its ceiling, for
the log against K copies of itself): constant velocity costs next to nothing, so the time is the metrics'.

Run: .venv/bin/python benchmarks/bench_evaluate.py  [--threads N] [--rollouts K]
"""

from __future__ import annotations

import argparse
import math

from _common import header, load_val, peak_rss_mb, timed

from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
from trafficrlhf_sdk.simulation import ConstantVelocityPolicy


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--threads", type=int, default=None, help="torch threads (see _common.configure_threads)")
    parser.add_argument("--rollouts", type=int, default=1, help="rollouts per scene (K >= 2 adds the meta-metric)")
    args = parser.parse_args()
    header(f"evaluate_policy(constant_velocity) on 100 val scenes, {args.rollouts} rollout(s) each")
    batch, load_s = load_val(100)
    print(f"   load   {load_s:.2f} s for {batch.num_scenes} scenes (separate from the evaluation)")
    config = EvaluationConfig(rollouts=args.rollouts)
    median, best, report = timed(lambda: evaluate_policy(ConstantVelocityPolicy(), batch, config), repeats=3)
    print(f"   evaluate_policy wall time {median:.2f} s median of 3 (min {best:.2f}); closed loop "
          f"{report.simulation_time_s:.3f} s; batch_size {config.batch_size}; metrics {', '.join(config.metrics)}")
    print(f"   {report.num_scenes} scenes, {report.num_controlled_agents} controlled agents")
    fmt = lambda v: "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4f}"  # noqa: E731
    width = max(len(k) for k in report.values)
    print(f"   {'metric':<{width}}  {'constant_velocity':>17}  {'logged data':>11}")
    for key, value in report.values.items():
        print(f"   {key:<{width}}  {fmt(value):>17}  {fmt(report.logged_values.get(key)):>11}")
    print(f"   peak RSS {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
