"""Tests of the compact CTG's sampler heads through the ``ctg`` adapter: the steering head (road and traffic
readings, gate, lateral-only, widening a saved head) and the gap-keeping follow head with its lead readings.

Data-dependent tests are skipped when ``trafficrlhf_sdk.scenario.default_data_root()`` lacks nuscenes_pred.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import pytest
import torch

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.simulation.guidance import GuidanceSet
from trafficrlhf_sdk.scenario import default_data_root

HAS_DATA = os.path.isdir(os.path.join(default_data_root(), "nuscenes_pred", "label"))
needs_data = pytest.mark.skipif(not HAS_DATA, reason="nuscenes_pred data not found")
REPO = Path(__file__).resolve().parents[3]
ALIGNED = REPO / "reference_models/baselines/ctg"
ROAD_ONLY_KEYS = ("steer_gate", "steer_neighbours", "steer_neighbour_scale")


def _steered_checkpoint(folder: Path, gated: bool) -> str:
    """The committed aligned CTG without its gap-keeping head (config fields of ``follow`` left to
    their defaults, ``follow.*`` tensors dropped): a saved steering head alone, with its gate (``gated``) or
    without (a plain road head, the gate fields left to their defaults)."""
    import json

    from safetensors.torch import load_file, save_file

    from trafficrlhf_sdk.models.checkpoint import record_weights_digest

    folder.mkdir(parents=True)
    saved = json.loads((ALIGNED / "config.json").read_text())
    drop = [k for k in saved["config"] if k.startswith("follow")]
    if not gated:
        drop += ROAD_ONLY_KEYS
    saved["config"] = {k: v for k, v in saved["config"].items() if k not in drop}
    (folder / "config.json").write_text(json.dumps(saved))
    tensors = load_file(str(ALIGNED / "model.safetensors"))
    save_file({k: v for k, v in tensors.items() if not k.startswith("follow.")}, str(folder / "model.safetensors"))
    record_weights_digest(str(folder))
    return str(folder)


@pytest.fixture(scope="module")
def gated_head(tmp_path_factory) -> str:  # type: ignore[no-untyped-def]
    """A saved, gated road-and-traffic steering head on the 4 s base (no gap-keeping head)."""
    return _steered_checkpoint(tmp_path_factory.mktemp("ctg") / "gated", gated=True)


@pytest.fixture(scope="module")
def road_head(tmp_path_factory) -> str:  # type: ignore[no-untyped-def]
    """A saved road steering head on the 4 s base without a gate."""
    return _steered_checkpoint(tmp_path_factory.mktemp("ctg") / "road", gated=False)


@needs_data
@pytest.mark.parametrize("options", [("steer",), ("steer_road",), ("steer_road", "steer_neighbours")])
def test_a_fresh_steering_head_samples_as_the_base_and_trains_alone(scenes, tmp_path, options) -> None:  # type: ignore[no-untyped-def]
    """``steer=True`` (or ``steer_road=True``, a head that also reads the road, with ``steer_neighbours`` the
    traffic too) adds a zero head: same guided
    futures and log-probabilities as the base under one generator; it is the ``steer`` group and gets the only
    gradient of a log-probability once its output layer is non-zero; the head then changes the sampled futures
    and the guided log-probability stays exact; it survives save_pretrained/from_pretrained without the option."""
    from trafficrlhf_ctg import CTGAdapter

    path = str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s")
    flags = dict.fromkeys(options, True)
    base, steered = CTGAdapter(checkpoint=path, seed=0), CTGAdapter(checkpoint=path, seed=0, **flags)
    assert steered.cfg.steer_road == ("steer_road" in options)
    assert steered.cfg.steer_neighbours == ("steer_neighbours" in options)
    torch.manual_seed(123)  # whatever the global generator holds, a fresh head is the same draw
    again = CTGAdapter(checkpoint=path, seed=1, **flags)
    for name, tensor in steered.model.steer.state_dict().items():
        assert torch.equal(tensor, again.model.steer.state_dict()[name]), name
    assert "steer" not in base.parameter_groups() and set(steered.parameter_groups()) == {"encoder", "decoder", "steer"}
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    a = base.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    b = steered.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.futures, b.futures)
    torch.testing.assert_close(a.log_prob, b.log_prob)

    with torch.no_grad():
        steered.model.steer.net[-1].weight.normal_(0, 0.05)
    out = steered.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    agents = out.trace.agents
    moved = (out.futures - a.futures)[:, :, :, :, :2].norm(dim=-1).amax(-1)  # (B, S, A)
    assert moved.masked_select(agents[:, None]).min() > 0
    recomputed = steered.log_prob(scenes, out.trace.detach())
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-3, rtol=1e-4)
    for group in steered.parameter_groups().values():
        for p in group:
            p.grad = None
    recomputed.sum().backward()
    head = steered.parameter_groups()["steer"]
    assert all(p.grad is not None for p in head[-2:]) and head[-2].grad.abs().sum() > 0

    steered.save_pretrained(str(tmp_path))
    loaded = CTGAdapter.from_pretrained(str(tmp_path), seed=0)
    assert loaded.cfg.steer and loaded.cfg.steer_road == ("steer_road" in options)
    assert loaded.cfg.steer_neighbours == ("steer_neighbours" in options)
    again = loaded.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(again.futures, out.futures)


def test_neighbour_proximity_matches_a_per_point_loop_and_ignores_missing_neighbours() -> None:
    """Against a plain Python loop over rows, samples, steps, probes and neighbours: each neighbour driven on at
    its current velocity, clearance = centre distance less both mean half-extents, proximity exp(-clearance /
    scale) (1 when the footprints overlap), the largest over valid neighbours; 0 with none."""
    from ctg_reference.model import neighbour_proximity

    gen = torch.Generator().manual_seed(0)
    n, k, s, h, dt, offset, scale = 3, 4, 2, 5, 0.1, 1.0, 2.0
    yaw_n = torch.rand(n, k, generator=gen) * 6.28
    neighbours = torch.cat([torch.randn(n, k, 2, generator=gen) * 6, torch.cos(yaw_n)[..., None],
                            torch.sin(yaw_n)[..., None], torch.rand(n, k, 1, generator=gen) * 10,
                            3 + torch.rand(n, k, 1, generator=gen) * 2, 1.5 + torch.rand(n, k, 1, generator=gen)], -1)
    valid = torch.rand(n, k, generator=gen) > 0.3
    valid[2] = False  # a row without neighbours
    extent = torch.tensor([[4.5, 1.9], [4.0, 1.8], [5.0, 2.0]])
    states = torch.randn(n, s, h, 4, generator=gen) * 5
    got = neighbour_proximity(neighbours, valid, extent, states, dt, offset, scale)
    assert got.shape == (n, s, h, 3)
    expected = torch.zeros(n, s, h, 3)
    for i in range(n):
        for j in range(s):
            for t in range(h):
                x, y, _, yaw = states[i, j, t].tolist()
                probes = [(x, y), (x - math.sin(yaw) * offset, y + math.cos(yaw) * offset),
                          (x + math.sin(yaw) * offset, y - math.cos(yaw) * offset)]
                for p, (px, py) in enumerate(probes):
                    for m in range(k):
                        if not valid[i, m]:
                            continue
                        nx, ny, c, sn, v, length, width = neighbours[i, m].tolist()
                        cx, cy = nx + v * c * (t + 1) * dt, ny + v * sn * (t + 1) * dt
                        reach = (extent[i].sum().item() + length + width) / 4
                        clearance = max(math.hypot(px - cx, py - cy) - reach, 0.0)
                        expected[i, j, t, p] = max(expected[i, j, t, p].item(), math.exp(-clearance / scale))
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)
    assert torch.all(got[2] == 0)
    assert neighbour_proximity(neighbours[:, :0], valid[:, :0], extent, states, dt, offset, scale).abs().sum() == 0


def test_the_steering_gate_leaves_plans_on_a_clear_road_alone_and_scales_others_by_their_hazard() -> None:
    """``steer_gate``: the head's shift is multiplied by the plan's largest hazard (off-road share inside the
    crop, neighbour proximity): all road and nobody near gives no shift at all; no road gives the ungated shift;
    a neighbour on the plan gives it too; past the crop's edge the missing map is no hazard."""
    from ctg_reference.model import CTGConfig, CTGModel

    torch.manual_seed(0)
    model = CTGModel(CTGConfig(horizon=8, steer=True, steer_road=True, steer_neighbours=True, steer_gate=True))
    with torch.no_grad():
        model.steer.net[-1].weight.normal_(0, 0.1)
    n, r, g = 2, 3, model.cfg.map_size
    cond = torch.randn(n * r, model.cfg.cond_dim)
    x0 = torch.randn(n * r, 8, 2) * 0.3
    v0 = torch.full((n,), 2.0)
    neighbours = torch.zeros(n, 1, 7)
    neighbours[..., 2], neighbours[..., 5], neighbours[..., 6] = 1.0, 4.5, 1.9
    far = torch.zeros(n, 1, dtype=torch.bool)
    extent = torch.tensor([[4.5, 1.9]] * n)

    def shift(drivable: torch.Tensor, valid: torch.Tensor, gate: bool) -> torch.Tensor:
        model.cfg.steer_gate = gate
        return model._steer_shift(cond, x0, 2, (drivable, v0, neighbours, valid, extent), n)

    road, no_road = torch.ones(n, 1, g, g), torch.zeros(n, 1, g, g)
    assert torch.all(shift(road, far, gate=True) == 0)
    assert shift(road, far, gate=False).abs().amin() > 0
    torch.testing.assert_close(shift(no_road, far, gate=True), shift(no_road, far, gate=False))
    near = torch.ones(n, 1, dtype=torch.bool)  # a neighbour standing where every plan starts
    torch.testing.assert_close(shift(road, near, gate=True), shift(road, near, gate=False))
    v0.fill_(80.0)  # plans that leave the 48 m crop within 0.5 s: the unmapped rest is not off-road
    assert torch.all(shift(road, far, gate=True) == 0)


def test_the_road_profile_reads_the_crop_cells_the_plan_passes_and_their_side_neighbours() -> None:
    """At agent-frame points on crop-cell centres (``map_crops``' convention: rows ahead, columns to the left,
    a quarter of the rows behind) the bilinear profile equals those cells' values; the offsets one cell across a
    plan heading along +x read the cells to its left and right, and a plan heading along +y swaps the axes."""
    from ctg_reference.model import MAP_BEHIND_FRACTION, road_profile

    g, res = 16, 0.5
    crop = (torch.rand(2, 1, g, g, generator=torch.Generator().manual_seed(0)) > 0.5).float()
    u = torch.tensor([[5, 6, 7, 9], [12, 3, 4, 8]])  # rows (ahead)
    v = torch.tensor([[3, 4, 10, 12], [1, 7, 8, 14]])  # columns (left)
    x = (u - MAP_BEHIND_FRACTION * g + 0.5) * res
    y = (v - g / 2 + 0.5) * res
    heading_x = torch.stack([x, y, torch.zeros_like(x), torch.zeros_like(x)], -1)[:, None]  # (N, S=1, H=4, 4)
    got = road_profile(crop, heading_x, res, offset=res)[:, 0]  # (N, H, 3)
    rows = torch.arange(2)[:, None]
    torch.testing.assert_close(got[..., 0], crop[rows, 0, u, v])
    torch.testing.assert_close(got[..., 1], crop[rows, 0, u, v + 1])
    torch.testing.assert_close(got[..., 2], crop[rows, 0, u, v - 1])
    heading_y = heading_x.clone()
    heading_y[..., 3] = math.pi / 2  # left of a plan heading along +y is -x: the row behind
    got = road_profile(crop, heading_y, res, offset=res)[:, 0]
    torch.testing.assert_close(got[..., 1], crop[rows, 0, u - 1, v], atol=1e-5, rtol=0)
    torch.testing.assert_close(got[..., 2], crop[rows, 0, u + 1, v], atol=1e-5, rtol=0)
    far = heading_x.clone()
    far[..., 0] = 100.0  # beyond the crop
    assert torch.all(road_profile(crop, far, res, offset=res) == 0)


def test_the_gate_options_apply_to_a_saved_head_and_are_refused_where_they_cannot_act(road_head: str,
                                                                                       gated_head: str) -> None:
    from trafficrlhf_ctg import CTGAdapter

    road = road_head
    gated = CTGAdapter(checkpoint=road, steer_gate=True)
    assert gated.cfg.steer_gate and gated.model.cfg.steer_gate
    assert not CTGAdapter(checkpoint=road).cfg.steer_gate
    committed = gated_head
    assert CTGAdapter(checkpoint=committed).cfg.steer_gate
    assert not CTGAdapter(checkpoint=committed, steer_gate=False).cfg.steer_gate
    with pytest.raises(TrafficRLHFError, match="needs a steering head"):
        CTGAdapter(checkpoint=str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s"), steer_gate=True)


def test_widening_a_saved_road_head_to_read_the_traffic_keeps_its_output_until_fine_tuned(tmp_path: Path,
                                                                                         gated_head: str) -> None:
    """``steer_neighbours=true`` on a saved road head: the new neighbour inputs get zero weights and every other
    weight is kept, so where the road opens the gate the shift equals the saved head's; a neighbour on the plan
    opens the gate where the road left it shut."""
    from trafficrlhf_ctg import CTGAdapter

    committed = gated_head
    saved = CTGAdapter(checkpoint=committed).model
    widened = CTGAdapter(checkpoint=committed, steer_neighbours=True).model
    assert widened.cfg.steer_neighbours and widened.cfg.steer_gate
    old_state, new_state = saved.state_dict(), widened.state_dict()
    assert all(torch.equal(old_state[key], new_state[key]) for key in old_state if key != "steer.net.0.weight")
    torch.manual_seed(0)
    n, r, h, g = 3, 4, saved.cfg.horizon, saved.cfg.map_size
    cond = torch.randn(n * r, saved.cfg.cond_dim)
    x0 = torch.randn(n * r, h, 2) * 0.5
    drivable = (torch.rand(n, 1, g, g) > 0.3).float()
    v0 = torch.tensor([3.0, 6.0, 9.0])
    neighbours = torch.zeros(n, 2, 7)
    neighbours[..., 0] = torch.tensor([6.0, 15.0])
    neighbours[..., 2], neighbours[..., 5], neighbours[..., 6] = 1.0, 4.5, 1.9
    valid, extent = torch.ones(n, 2, dtype=torch.bool), torch.tensor([[4.5, 1.9]] * n)
    nobody = (drivable, v0, neighbours, torch.zeros_like(valid), extent)
    with torch.no_grad():
        expected = saved._steer_shift(cond, x0, 2, (drivable, v0), n)
        torch.testing.assert_close(widened._steer_shift(cond, x0, 2, nobody, n), expected, atol=1e-6, rtol=1e-5)
        clear = torch.ones_like(drivable)
        assert torch.all(saved._steer_shift(cond, x0, 2, (clear, v0), n) == 0)
        assert widened._steer_shift(cond, x0, 2, (clear, v0, neighbours, valid, extent), n).abs().amax() > 0
    blind = tmp_path / "blind_head"
    CTGAdapter(checkpoint=str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s"), steer=True).save_pretrained(
        str(blind))
    with pytest.raises(TrafficRLHFError, match="widens a road-reading head only"):
        CTGAdapter(checkpoint=str(blind), steer_neighbours=True)


def test_lead_gaps_match_a_per_step_loop_and_a_hand_computed_follower() -> None:
    """:func:`lead_gaps` against a plain Python loop (neighbours at constant velocity; in the path = ahead along the
    planned heading and within half of both widths plus the margin to the side; gap bumper to bumper, clipped;
    closing speed against the lead's speed along the heading; hazard against the desired gap), and one case by
    hand: a car 20 m ahead at 5 m/s, the plan at a steady 10 m/s straight on."""
    from ctg_reference.steering import LEAD_GAP_CLIP, lead_gaps

    gen = torch.Generator().manual_seed(1)
    n, k, s, h, dt, margin, s0, headway = 3, 5, 2, 6, 0.1, 0.5, 2.0, 1.5
    yaw_n = torch.rand(n, k, generator=gen) * 0.6 - 0.3
    neighbours = torch.cat([torch.rand(n, k, 1, generator=gen) * 40 - 5, torch.randn(n, k, 1, generator=gen) * 2,
                            torch.cos(yaw_n)[..., None], torch.sin(yaw_n)[..., None],
                            torch.rand(n, k, 1, generator=gen) * 12, 3 + torch.rand(n, k, 1, generator=gen) * 2,
                            1.5 + torch.rand(n, k, 1, generator=gen)], -1)
    valid = torch.rand(n, k, generator=gen) > 0.2
    valid[2] = False
    extent = torch.tensor([[4.5, 1.9], [4.0, 1.8], [5.0, 2.0]])
    states = torch.cat([torch.rand(n, s, h, 1, generator=gen) * 10, torch.randn(n, s, h, 1, generator=gen),
                        torch.rand(n, s, h, 1, generator=gen) * 12, torch.randn(n, s, h, 1, generator=gen) * 0.2], -1)
    got = lead_gaps(neighbours, valid, extent, states, dt, margin, s0, headway)
    ttc = 2.5
    by_ttc = lead_gaps(neighbours, valid, extent, states, dt, margin, s0, headway, ttc)
    assert got.shape == by_ttc.shape == (n, s, h, 3)
    alike = lead_gaps(neighbours, valid, extent, states, dt, margin, s0, headway, None, 0.9)
    for i in range(n):
        for j in range(s):
            for t in range(h):
                x, y, v, yaw = states[i, j, t].tolist()
                best, lead_speed, best_alike = LEAD_GAP_CLIP, v, LEAD_GAP_CLIP
                for m in range(k):
                    nx, ny, c, sn, speed, length, width = neighbours[i, m].tolist()
                    cx, cy = nx + speed * c * (t + 1) * dt, ny + speed * sn * (t + 1) * dt
                    along = (cx - x) * math.cos(yaw) + (cy - y) * math.sin(yaw)
                    across = abs(-(cx - x) * math.sin(yaw) + (cy - y) * math.cos(yaw))
                    if not valid[i, m] or along <= 0 or across > (extent[i, 1].item() + width) / 2 + margin:
                        continue
                    if c * math.cos(yaw) + sn * math.sin(yaw) >= 0.9:
                        best_alike = min(best_alike, min(max(along - (extent[i, 0].item() + length) / 2, 0.0),
                                                         LEAD_GAP_CLIP))
                    gap = min(max(along - (extent[i, 0].item() + length) / 2, 0.0), LEAD_GAP_CLIP)
                    if gap < best:
                        best = gap
                        lead_speed = speed * (c * math.cos(yaw) + sn * math.sin(yaw))
                expected = [best, v - lead_speed, min(max(1 - best / (s0 + headway * v), 0.0), 1.0)]
                torch.testing.assert_close(got[i, j, t], torch.tensor(expected), atol=1e-4, rtol=1e-4)
                closing = v - lead_speed
                ttc_hazard = min(max(1 - best / (ttc * closing), 0.0), 1.0) if closing > 0 else 0.0
                torch.testing.assert_close(by_ttc[i, j, t], torch.tensor([best, closing, ttc_hazard]), atol=1e-4,
                                           rtol=1e-4)
                assert abs(alike[i, j, t, 0].item() - best_alike) < 1e-4
    assert torch.all(got[2, ..., 0] == LEAD_GAP_CLIP) and torch.all(got[2, ..., 2] == 0)

    ahead = torch.tensor([[[20.0, 0.0, 1.0, 0.0, 5.0, 4.5, 1.9], [20.0, 3.5, 1.0, 0.0, 5.0, 4.5, 1.9],
                           [-8.0, 0.0, 1.0, 0.0, 5.0, 4.5, 1.9]]])  # in the lane, one lane over, behind
    t = torch.arange(1, 4) * dt
    plan = torch.stack([10 * t, torch.zeros(3), torch.full((3,), 10.0), torch.zeros(3)], -1)[None, None]
    one = lead_gaps(ahead, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), plan, dt, margin, s0,
                    headway)[0, 0]
    gap = 20 + 5 * t - 10 * t - 4.5
    torch.testing.assert_close(one, torch.stack([gap, torch.full((3,), 5.0), 1 - gap / 17.0], -1))
    # closing in at 5 m/s from about 15 m: TTC about 3 s, hazard 1 - TTC / 4 s; slower than the lead: none
    by_ttc = lead_gaps(ahead, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), plan, dt, margin, s0,
                       headway, 4.0)[0, 0]
    torch.testing.assert_close(by_ttc[:, 2], 1 - (gap / 5.0) / 4.0)
    oncoming = ahead.clone()
    oncoming[0, 0, 2:5] = torch.tensor([-1.0, 0.0, 5.0])  # the car in the lane drives towards the plan
    kept = lead_gaps(oncoming, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), plan, dt, margin, s0,
                     headway)[0, 0]
    assert torch.all(kept[:, 0] < LEAD_GAP_CLIP)
    assert torch.all(lead_gaps(oncoming, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), plan, dt,
                               margin, s0, headway, None, 0.7)[..., 0] == LEAD_GAP_CLIP)
    slow = plan.clone()
    slow[..., 2] = 4.0
    assert torch.all(lead_gaps(ahead, torch.ones(1, 3, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), slow, dt,
                               margin, s0, headway, 4.0)[..., 2] == 0)
    # a plan braking at 2 m/s² from 10 m/s to a stop just behind a car stopped 25 m ahead (bumper gap)
    stopped = torch.tensor([[[25.0 + 4.5, 0.0, 1.0, 0.0, 0.0, 4.5, 1.9]]])
    tb = torch.arange(1, 41) * dt
    braking = torch.stack([10 * tb - tb ** 2, torch.zeros(40), 10 - 2 * tb, torch.zeros(40)], -1)[None, None]
    assert lead_gaps(stopped, torch.ones(1, 1, dtype=torch.bool), torch.tensor([[4.5, 1.9]]), braking, dt, margin,
                     s0, headway, 4.0)[0, 0, -5:, 2].min() > 0.5  # while its time to collision goes to 0 at the end



@needs_data
def test_a_fresh_follow_head_samples_as_its_checkpoint_acts_only_behind_a_lead_and_saves(
        scenes, tmp_path, gated_head) -> None:  # type: ignore[no-untyped-def]
    """``follow=True`` on a saved gated steering head adds a zero gap-keeping head next to its steering head: same
    guided futures and log-probabilities under one generator, every saved tensor kept; it is the ``follow`` group.
    With a non-zero output layer its shift is exactly 0 for rows with nobody ahead (the gate), non-zero behind a
    close lead and on the acceleration channel only; the guided log-probability stays exact, a log-probability's
    gradient reaches the head, and the head survives save_pretrained/from_pretrained without the option."""
    from ctg_reference.model import CTGConfig, CTGModel
    from trafficrlhf_ctg import CTGAdapter

    path = gated_head
    base, follow = CTGAdapter(checkpoint=path, seed=0), CTGAdapter(checkpoint=path, seed=0, follow=True)
    assert follow.cfg.follow and follow.cfg.steer_gate and "follow" not in base.parameter_groups()
    assert set(follow.parameter_groups()) == {"encoder", "decoder", "steer", "follow"}
    for name, tensor in base.model.state_dict().items():
        assert torch.equal(tensor, follow.model.state_dict()[name]), name
    guidance = GuidanceSet.parse("no_collision").fit(scenes)
    a = base.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    b = follow.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.futures, b.futures)
    torch.testing.assert_close(a.log_prob, b.log_prob)

    model = CTGModel(CTGConfig(horizon=8, follow=True))
    with torch.no_grad():
        model.follow.net[-1].weight.normal_(0, 0.5)
        model.follow.net[-1].bias.fill_(0.5)
    x0 = torch.zeros(2, 8, 2)  # two rows, one sample each: about 0.1 m/s^2 (the normalization's mean)
    lead = torch.tensor([[[8.0, 0.0, 1.0, 0.0, 2.0, 4.5, 1.9]], [[8.0, 0.0, 1.0, 0.0, 2.0, 4.5, 1.9]]])
    steer_map = (torch.ones(2, 1, 48, 48), torch.full((2,), 8.0), lead, torch.tensor([[True], [False]]),
                 torch.tensor([[4.5, 1.9], [4.5, 1.9]]))
    shift = model._follow_shift(x0, 3, steer_map, 2)
    assert shift[0, :, 0].abs().min() > 0 and torch.all(shift[1] == 0) and torch.all(shift[..., 1] == 0)
    far = lead.clone()
    far[..., 0] = 14.0  # 8.9 m ahead after 0.1 s, inside the 5.5 m desired gap only from the 7th step
    far_map = (*steer_map[:2], far, *steer_map[3:])
    assert model._follow_shift(x0, 3, far_map, 2)[0, :, 0].abs().min() > 0
    model.cfg = dataclasses.replace(model.cfg, follow_gate_steps=5)  # the gate reads the first 0.5 s only
    assert torch.all(model._follow_shift(x0, 3, far_map, 2) == 0)
    assert model._follow_shift(x0, 3, steer_map, 2)[0, :, 0].abs().min() > 0

    with torch.no_grad():
        follow.model.follow.net[-1].weight.normal_(0, 0.05)
        follow.model.follow.net[-1].bias.fill_(-0.5)  # brake wherever the gate opens
    out = follow.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    assert not torch.equal(out.futures, a.futures)
    recomputed = follow.log_prob(scenes, out.trace.detach())
    torch.testing.assert_close(recomputed.detach(), out.log_prob, atol=1e-3, rtol=1e-4)
    recomputed.sum().backward()
    head = follow.parameter_groups()["follow"]
    assert head[-2].grad is not None and head[-2].grad.abs().sum() > 0
    follow.save_pretrained(str(tmp_path))
    loaded = CTGAdapter.from_pretrained(str(tmp_path), seed=0)
    assert loaded.cfg.follow and loaded.cfg.steer_gate
    again = loaded.sample(scenes, 2, guidance, torch.Generator().manual_seed(3))
    torch.testing.assert_close(again.futures, out.futures)


def test_follow_options_start_the_head_braking_and_set_its_desired_gap(gated_head: str) -> None:
    """``follow_brake`` sets a new head's output bias (weights stay zero); ``follow_standstill`` / ``follow_headway``
    override the desired gap (a new head: 1.5 m + 0.5 s); each refuses to act without
    the head it configures, naming the option."""
    from trafficrlhf_ctg import CTGAdapter

    path = gated_head
    plain = CTGAdapter(checkpoint=path, seed=0, follow=True)
    assert (plain.cfg.follow_standstill, plain.cfg.follow_headway) == (1.5, 0.5)
    braking = CTGAdapter(checkpoint=path, seed=0, follow=True, follow_brake=-3.0, follow_standstill=2.0,
                         follow_headway=1.0)
    last = braking.model.follow.net[-1]
    assert torch.all(last.bias == -3.0) and torch.all(last.weight == 0)
    assert (braking.cfg.follow_standstill, braking.cfg.follow_headway) == (2.0, 1.0)
    assert braking.model.cfg is braking.cfg
    for name, tensor in plain.model.state_dict().items():
        if not name.startswith("follow.net.6"):
            assert torch.equal(tensor, braking.model.state_dict()[name]), name
    with pytest.raises(TrafficRLHFError, match=r"follow_brake=-3\.0"):
        CTGAdapter(checkpoint=path, seed=0, follow_brake=-3.0)
    with pytest.raises(TrafficRLHFError, match=r"follow_headway=1\.0"):
        CTGAdapter(checkpoint=path, seed=0, follow_headway=1.0)
    with pytest.raises(TrafficRLHFError, match=r"follow_ttc=2\.0"):
        CTGAdapter(checkpoint=path, seed=0, follow_ttc=2.0)
    assert plain.cfg.follow_ttc is None
    assert CTGAdapter(checkpoint=path, seed=0, follow=True, follow_ttc=2.0).cfg.follow_ttc == 2.0
    assert CTGAdapter(checkpoint=path, seed=0, follow=True, follow_heading_cos=0.7).cfg.follow_heading_cos == 0.7
    with pytest.raises(TrafficRLHFError, match=r"follow_heading_cos=0\.7"):
        CTGAdapter(checkpoint=path, seed=0, follow_heading_cos=0.7)
    assert CTGAdapter(checkpoint=path, seed=0, follow=True, follow_gate_steps=5).cfg.follow_gate_steps == 5
    assert plain.cfg.follow_gate_steps is None
    with pytest.raises(TrafficRLHFError, match=r"follow_gate_steps=5"):
        CTGAdapter(checkpoint=path, seed=0, follow_gate_steps=5)


@needs_data
def test_the_imitation_loss_holds_a_head_to_the_log_through_the_clean_prediction_its_step_implies(scenes) -> None:  # type: ignore[no-untyped-def]
    """A model with a head adds :meth:`CTGModel.head_loss` to its imitation loss. Rebuilt step by step from the same
    noise: each sampling step's steered mean ``mu + sigma * shift`` is the DDIM mean of one clean prediction, found
    here by inverting the mean's affine map, and the loss scores that prediction against the log with the
    training loss's action and state MSEs. A fresh (zero) head's loss is the base denoiser's loss at the sampling
    steps; a non-zero head gets the gradient; a model without heads adds nothing."""
    from ctg_reference.data import agent_features, future_targets, select_rows, window_mask
    from trafficrlhf_ctg import CTGAdapter

    from trafficrlhf_sdk.models.random import draw_normal

    path = str(REPO / "reference_models/ctg/checkpoints/ctg_small_4s")
    adapter = CTGAdapter(checkpoint=path, seed=0, steer_road=True)
    model, cfg = adapter.model, adapter.cfg
    t = cfg.history_steps
    mask = window_mask(scenes, t, cfg.horizon, cfg.history_steps)
    rows = select_rows(agent_features(scenes.replace_unchecked(current_index=t), cfg, crop_agents=mask), mask)
    actions, states = (x[mask] for x in future_targets(scenes, t, cfg.horizon))
    steer_map = (rows["map"][:, :1], rows["v0"])
    with torch.no_grad():
        cond = model.encode(rows)

    def by_steps(seed: int) -> torch.Tensor:
        n, schedule = actions.shape[0], model.sample_schedule
        noise = draw_normal(torch.Generator().manual_seed(seed), (n * len(schedule), cfg.horizon, 2), "cpu")
        noise = noise.reshape(n, len(schedule), cfg.horizon, 2)
        x0_log, total = model.normalize(actions), 0.0
        for j, (k, k_prev) in enumerate(schedule):
            ab, ab_prev = model.alphas_bar[k], model.alphas_bar[k_prev]
            x = ab.sqrt() * x0_log + (1 - ab).sqrt() * noise[:, j]
            mean, sigma, x0 = model._transition(x, k, k_prev, cond, with_x0=True)
            mean = mean + sigma * model._head_shifts(cond, x0, k, steer_map, n)
            along_x = (1 - ab_prev - sigma**2).clamp_min(0).sqrt() / (1 - ab).sqrt()
            clean = (mean - along_x * x) / (ab_prev.sqrt() - along_x * ab.sqrt())
            diff = model.rollout(clean, rows["v0"]) - states
            diff = torch.cat([diff[..., :3], torch.atan2(diff[..., 3:].sin(), diff[..., 3:].cos())], -1)
            state = ((diff / model.state_std) ** 2).mean()
            total = total + torch.nn.functional.mse_loss(clean, x0_log) + cfg.state_loss_weight * state
        return total / len(schedule)

    with torch.no_grad():
        fresh = model.head_loss(cond, actions, rows["v0"], steer_map, states, torch.Generator().manual_seed(4))
        torch.testing.assert_close(fresh, by_steps(4), rtol=1e-4, atol=1e-6)
        model.steer.net[-1].weight.normal_(0, 0.1)
        steered = model.head_loss(cond, actions, rows["v0"], steer_map, states, torch.Generator().manual_seed(4))
        torch.testing.assert_close(steered, by_steps(4), rtol=1e-4, atol=1e-6)
    assert not torch.isclose(fresh, steered)

    base = CTGAdapter(checkpoint=path, seed=0)
    torch.manual_seed(5)
    plain = base.imitation_loss(scenes)
    torch.manual_seed(5)
    with_head = adapter.imitation_loss(scenes)
    assert with_head > plain
    with_head.backward()
    head = adapter.parameter_groups()["steer"]
    assert head[-2].grad is not None and head[-2].grad.abs().sum() > 0
    assert base.model.head_loss(cond, actions, rows["v0"], steer_map) == 0
