"""``metrics.following_gaps`` and ``metrics.path_gaps``: the gap to the agent ahead in the path."""

from __future__ import annotations

import math

import pytest
import torch

from trafficrlhf_sdk.metrics import following_gaps, path_gaps


def loop_following_gaps(xy, yaw, extent, valid, margin):  # type: ignore[no-untyped-def]
    """One agent pair and step at a time, in plain Python: the nearest in-path bumper gap, inf if none."""
    b_n, a_n, t_n = valid.shape
    out = torch.full((b_n, a_n, t_n), math.inf, dtype=torch.float64)
    for b in range(b_n):
        for a in range(a_n):
            for t in range(t_n):
                if not valid[b, a, t]:
                    continue
                c, s = math.cos(float(yaw[b, a, t])), math.sin(float(yaw[b, a, t]))
                for o in range(a_n):
                    if o == a or not valid[b, o, t]:
                        continue
                    dx, dy = (float(v) for v in xy[b, o, t] - xy[b, a, t])
                    along, across = dx * c + dy * s, abs(dy * c - dx * s)
                    if along > 0 and across <= float(extent[b, a, 1] + extent[b, o, 1]) / 2 + margin:
                        gap = max(along - float(extent[b, a, 0] + extent[b, o, 0]) / 2, 0.0)
                        out[b, a, t] = min(out[b, a, t], gap)
    return out


def test_following_gaps_match_a_pairwise_loop(val_scenes) -> None:  # type: ignore[no-untyped-def]
    scene = val_scenes.time_slice(25, 40)  # around the current step: everyone's boxes, 1.5 s
    speed = scene.states[..., 2]
    got = following_gaps(scene.xy, scene.yaw, speed, scene.extent, scene.valid, 0.5)
    expected = loop_following_gaps(scene.xy.double(), scene.yaw.double(), scene.extent.double(), scene.valid, 0.5)
    assert torch.isfinite(got).sum() > 20, "the val scenes should have followers"
    assert torch.equal(torch.isinf(got), torch.isinf(expected))
    finite = torch.isfinite(expected)
    assert torch.allclose(got[finite].double(), expected[finite], atol=1e-4)


def test_a_follower_worked_by_hand() -> None:
    # agent 0 at the origin heading +x at 10 m/s; agent 1 12 m ahead, 0.8 m to the side at 6 m/s; agent 2 behind;
    # agent 3 ahead but 4 m to the side (another lane); every car 4.5 m x 1.8 m
    xy = torch.tensor([[[[0.0, 0.0]], [[12.0, 0.8]], [[-10.0, 0.0]], [[5.0, 4.0]]]])
    yaw, extent = torch.zeros(1, 4, 1), torch.tensor([[[4.5, 1.8]] * 4])
    speed, valid = torch.tensor([[[10.0], [6.0], [10.0], [10.0]]]), torch.ones(1, 4, 1, dtype=torch.bool)
    gap = following_gaps(xy, yaw, speed, extent, valid, 0.5)[0, :, 0]
    assert gap[0] == pytest.approx(12.0 - 4.5)
    assert gap[2] == pytest.approx(10.0 - 4.5)  # agent 0 is ahead of agent 2 (agent 1 is farther)
    assert math.isinf(gap[1]) and math.isinf(gap[3])
    _, closing, in_path = path_gaps(xy, yaw, speed, extent, valid, 0.5)
    assert bool(in_path[0, 0, 1]) and not bool(in_path[0, 0, 3]) and not bool(in_path[0, 0, 0])
    assert closing[0, 0, 1, 0] == pytest.approx(4.0)
    # an invalid leader does not count: agent 0 then has nobody in its path (agent 3 is 4 m to the side)
    valid[0, 1, 0] = False
    assert math.isinf(following_gaps(xy, yaw, speed, extent, valid, 0.5)[0, 0, 0])
