"""``scripts/collision_partners.py``: first contacts of colliding agents, weighted like the collision rate."""

from __future__ import annotations

import math

import pytest

from trafficrlhf_sdk.metrics import FailureMetric, collisions_per_step
from trafficrlhf_sdk.simulation import ConstantVelocityPolicy, SimulationConfig, simulate
from trafficrlhf_sdk.testing.reference_metrics import box_polygon

pytest.importorskip("shapely")


@pytest.fixture(scope="module")
def rollout(val_scenes):  # type: ignore[no-untyped-def]
    """Constant-velocity driving over the 10 s protocol on the shared val scenes: about a quarter collide."""
    return simulate(ConstantVelocityPolicy(), val_scenes, SimulationConfig())


def test_weights_sum_to_the_collision_rate_and_contacts_are_first(rollout, load_script) -> None:  # type: ignore[no-untyped-def]
    script = load_script("collision_partners")
    records = script.first_contacts(rollout)
    metric = FailureMetric().compute(rollout)
    assert len(records) > 0, "constant velocity should collide somewhere"
    assert math.isclose(sum(r["weight"] for r in records), metric.values["collision_rate"], rel_tol=1e-9)
    window = rollout.simulated.time_slice(rollout.start_index + 1, rollout.end_index + 1)
    steps = collisions_per_step(window) & window.valid
    collided = metric.extras["collided"] & rollout.controlled
    assert {(r["scene"], r["agent"]) for r in records} == set(map(tuple, collided.nonzero().tolist()))
    for r in records:
        b, a, o, t = r["scene"], r["agent"], r["partner"], r["step"]
        assert int(steps[b, a].nonzero()[0]) == t  # the first colliding step
        assert math.isclose(r["time_s"], (t + 1) * rollout.simulated.dt)
        assert r["partner_controlled"] == bool(rollout.controlled[b, o])
        box_a = box_polygon(*window.xy[b, a, t].tolist(), float(window.yaw[b, a, t]), *window.extent[b, a].tolist())
        box_o = box_polygon(*window.xy[b, o, t].tolist(), float(window.yaw[b, o, t]), *window.extent[b, o].tolist())
        assert box_a.intersects(box_o)
    summary = script.summarize(records)
    for grouping in summary["groups"].values():
        assert math.isclose(sum(v["rate"] for v in grouping.values()), summary["collision_rate"], abs_tol=1e-3)
        assert sum(v["agents"] for v in grouping.values()) == len(records)


def test_where_the_partner_is_seen_from(load_script) -> None:  # type: ignore[no-untyped-def]
    group = load_script("collision_partners").group
    base = {"partner_controlled": False, "partner_type": "vehicle", "partner_speed": 0.0, "time_s": 1.0}
    assert group({**base, "bearing": 0.1})["where"] == "front"
    assert group({**base, "bearing": -3.0})["where"] == "rear"
    assert group({**base, "bearing": 1.5})["where"] == "side"
    assert group({**base, "bearing": 0.0})["partner_and_where"] == "replayed/front"
    assert group({**base, "bearing": 0.0, "partner_speed": 3.0})["partner_standing"] == "moving"


def test_onset_separates_the_first_plan_from_later_contacts(load_script) -> None:  # type: ignore[no-untyped-def]
    script = load_script("collision_partners")
    assert script.onset(0.1) == script.onset(0.5) == "first plan (<= 0.5 s)"
    assert script.onset(0.6) == script.onset(3.0) == "early (<= 3 s)"
    assert script.onset(3.1) == script.onset(10.0) == "late (> 3 s)"
