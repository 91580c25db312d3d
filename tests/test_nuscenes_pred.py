"""The ``nuscenes_pred`` source on the real data in ../shared/data (skipped when it is absent).

nuScenes data: CC BY-NC-SA 4.0 (non-commercial); it is read in place and never copied into the repository
(the malformed-file test copies one scene into a temporary directory that is deleted afterwards).
"""

from __future__ import annotations

import math
import os
import shutil

import numpy as np
import pytest
import torch

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError
from trafficrlhf_sdk.scenario import AgentType, ScenarioTensor

pytestmark = pytest.mark.data
plugin = pytest.importorskip("trafficrlhf_nuscenes_pred")
from trafficrlhf_nuscenes_pred.source import KEYFRAME_DT, NuScenesPredSource, parse_label_file  # noqa: E402

FACTOR = round(KEYFRAME_DT / 0.1)  # 10 Hz steps per 2 Hz keyframe


def label_dir(data_root: str, split: str) -> str:
    return os.path.join(data_root, "nuscenes_pred", "label", split)


@pytest.mark.parametrize(("split", "files", "long_enough"), [("val", 185, 160), ("train", 475, 442)])
def test_scene_counts(data_root, nuscenes_source, split, files, long_enough):
    names = [n for n in sorted(os.listdir(label_dir(data_root, split))) if n.endswith(".txt")]
    assert len(names) == files
    assert list(nuscenes_source._num_keyframes(split)) == [n[:-4] for n in names]
    ids = nuscenes_source.scene_ids(split)
    assert len(ids) == long_enough and ids == sorted(ids)
    needed = 3.0 + 10.0  # history_s + min_future_s
    counts = nuscenes_source._num_keyframes(split)
    assert all((counts[i] - 1) * KEYFRAME_DT >= needed for i in ids)
    assert all((n - 1) * KEYFRAME_DT < needed for i, n in counts.items() if i not in set(ids))


def test_splits(nuscenes_source):
    assert nuscenes_source.splits() == ["train", "val"]
    with pytest.raises(KeyError, match="test"):
        nuscenes_source.scene_ids("test")


def test_val_batch_fixture(val_scenes, nuscenes_source):
    s = val_scenes
    assert isinstance(s, ScenarioTensor) and s.num_scenes == 8
    assert s.scene_ids == tuple(nuscenes_source.scene_ids("val")[:8])
    assert s.source == "nuscenes_pred" and s.dt == pytest.approx(0.1) and s.current_index == 30
    assert s.num_steps >= 131  # 3 s history + 10 s future at 10 Hz
    assert s.origin.dtype == torch.float64 and s.map.layers == ("drivable", "road_divider", "lane_divider")
    assert (s.yaw[s.valid] >= -math.pi).all() and (s.yaw[s.valid] < math.pi).all()
    assert (s.states[~s.valid] == 0).all()
    assert s.controlled.any() and not (s.controlled & ~s.valid[:, :, s.current_index]).any()
    assert (s.agent_type[s.controlled] == AgentType.VEHICLE).all()
    present = s.valid.any(-1)
    assert (s.extent[present] > 0.5).all() and (s.extent[present][:, 0] >= s.extent[present][:, 1]).float().mean() > 0.9
    for b in range(s.num_scenes):
        ids = [i for i in s.agent_ids[b] if i]
        assert len(ids) == int(present[b].sum()) and len(set(ids)) == len(ids)


def test_logged_positions_on_drivable(nuscenes_source):
    """At least 99% of valid logged positions of the first 40 val scenes lie on drivable pixels."""
    on = total = 0
    for scene_id in nuscenes_source.scene_ids("val")[:40]:
        s = nuscenes_source.load_scene("val", scene_id)
        drivable = s.map.lookup(s.xy)
        on += int((drivable & s.valid).sum())
        total += int(s.valid.sum())
    assert total > 10_000
    assert on / total >= 0.99, f"only {on / total:.2%} of logged positions are on drivable pixels"


@pytest.mark.parametrize("index", [0, 3, 7])
def test_resampling_reproduces_keyframes_and_interpolates(data_root, nuscenes_source, val_scenes, index):
    scene_id = val_scenes.scene_ids[index]
    s = nuscenes_source.load_scene("val", scene_id)
    table = parse_label_file(os.path.join(label_dir(data_root, "val"), f"{scene_id}.txt"))
    x_min, y_min = s.origin[0].tolist()
    agent_of = {track: a for a, track in enumerate(s.agent_ids[0])}
    frames = int(table.frame.max()) + 1
    present = np.zeros((s.num_agents, frames), bool)
    for row in range(len(table.frame)):
        a, step = agent_of[str(table.track[row])], FACTOR * int(table.frame[row])
        present[a, table.frame[row]] = True
        assert s.valid[0, a, step]
        expected_xy = torch.tensor([table.x[row] - x_min, table.y[row] - y_min], dtype=torch.float64).float()
        assert torch.equal(s.xy[0, a, step], expected_xy), (scene_id, row)  # exact at keyframes
        assert abs(wrap_angle(s.yaw[0, a, step].double() - table.yaw[row]).item()) < 1e-6
    assert s.num_steps == (frames - 1) * FACTOR + 1
    assert torch.equal(s.valid[0, :, ::FACTOR], torch.from_numpy(present))
    for a in range(s.num_agents):
        for f in range(frames - 1):
            block = s.states[0, a, FACTOR * f : FACTOR * (f + 1) + 1].double()
            inner_valid = s.valid[0, a, FACTOR * f + 1 : FACTOR * (f + 1)]
            if not (present[a, f] and present[a, f + 1]):
                assert not inner_valid.any()
                continue
            assert inner_valid.all()
            start, end = block[0], block[-1]
            for k in range(1, FACTOR):
                w = k / FACTOR
                lo, hi = torch.minimum(start[:3], end[:3]), torch.maximum(start[:3], end[:3])
                assert ((block[k, :3] >= lo - 1e-4) & (block[k, :3] <= hi + 1e-4)).all()
                assert torch.allclose(block[k, :3], (1 - w) * start[:3] + w * end[:3], atol=1e-3)
                # yaw moves the short way round from start to end
                expected_yaw = start[3] + w * wrap_angle(end[3] - start[3])
                assert abs(wrap_angle(block[k, 3] - expected_yaw).item()) < 1e-4


def test_yaw_continuous_and_speed_consistent(val_scenes):
    """Consecutive valid 10 Hz steps turn by at most pi/5 (a 2 Hz keyframe step of at most pi split in 5; no 2 pi
    jumps), and the speed matches the motion along the heading (median error < 0.25 m/s, 95% < 1.5 m/s)."""
    s = val_scenes
    st = s.states.double()
    both = s.action_valid
    turn = wrap_angle(st[:, :, 1:, 3] - st[:, :, :-1, 3])[both].abs()
    assert turn.max() <= math.pi / FACTOR + 1e-4
    assert turn.quantile(0.99) < 0.1  # vehicles turn slowly
    d = st[:, :, 1:, :2] - st[:, :, :-1, :2]
    heading = st[:, :, :-1, 3]
    along = (d[..., 0] * torch.cos(heading) + d[..., 1] * torch.sin(heading)) / s.dt
    mean_speed = 0.5 * (st[:, :, 1:, 2] + st[:, :, :-1, 2])
    err = (along - mean_speed)[both].abs()
    assert err.median() < 0.25 and err.quantile(0.95) < 1.5
    speeds = s.speed[s.valid]
    assert 1.0 < speeds.mean() < 15.0 and speeds.abs().max() < 40.0


def _write_scene_copy(data_root: str, dest, scene_id: str, lines: list[str]) -> None:
    (dest / "label" / "val").mkdir(parents=True)
    (dest / "label" / "val" / f"{scene_id}.txt").write_text("".join(lines))
    (dest / "maps").mkdir()
    for name in (f"{scene_id}.png", f"meta_{scene_id}.txt"):
        shutil.copy(os.path.join(data_root, "nuscenes_pred", "maps", name), dest / "maps" / name)


def test_malformed_label_row_names_file_and_line(data_root, tmp_path):
    scene_id = "scene-0001"
    with open(os.path.join(label_dir(data_root, "val"), f"{scene_id}.txt"), encoding="utf-8") as handle:
        lines = handle.readlines()
    _write_scene_copy(data_root, tmp_path, scene_id, lines)
    good = NuScenesPredSource(root=str(tmp_path), min_future_s=0.0)
    assert good.load_scene("val", scene_id).num_agents > 0

    lines[2] = " ".join(lines[2].split()[:17]) + "\n"  # line 3 loses its last column
    broken_root = tmp_path / "broken"
    _write_scene_copy(data_root, broken_root, scene_id, lines)
    broken = NuScenesPredSource(root=str(broken_root), min_future_s=0.0)
    label = str(broken_root / "label" / "val" / f"{scene_id}.txt")
    with pytest.raises(DataFormatError, match="found 17") as info:
        broken.load_scene("val", scene_id)
    assert f"{label}:3:" in str(info.value)
    with pytest.raises(DataFormatError, match=":3:"):
        broken.scene_ids("val")

    lines[2] = lines[2].rstrip("\n") + " nan\n"  # 18 columns again, one of them not a number
    lines[4] = lines[4].replace(lines[4].split()[13], "abc", 1)
    bad_values = tmp_path / "bad_values"
    _write_scene_copy(data_root, bad_values, scene_id, lines)
    with pytest.raises(DataFormatError, match=":5: non-numeric"):
        NuScenesPredSource(root=str(bad_values)).load_scene("val", scene_id)


def test_missing_root_names_path_and_option(tmp_path):
    missing = tmp_path / "not-here"
    source = NuScenesPredSource(root=str(missing))
    with pytest.raises(DataNotFoundError, match="--root") as info:
        source.splits()
    assert str(missing) in str(info.value) and isinstance(info.value, FileNotFoundError)
    with pytest.raises(DataNotFoundError, match="--root"):
        source.scene_ids("val")
    with pytest.raises(DataNotFoundError, match="--root"):
        source.load_scene("val", "scene-0001")


def test_default_root_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("TRAFFICRLHF_DATA", str(tmp_path))
    assert NuScenesPredSource().root == os.path.join(str(tmp_path), "nuscenes_pred")


def test_states_up_to_now_read_only_the_past(data_root, tmp_path):
    """Moving every keyframe after 'now' changes no state up to 'now' (the speed at a keyframe is the backward
    difference, never the average with the next keyframe), and the speed at 'now' is that backward difference."""
    split, scene = "val", sorted(os.listdir(label_dir(data_root, "val")))[0][:-4]
    copies = {}
    for shift in (0.0, 3.0):
        root = tmp_path / f"shift{shift}"
        (root / "label" / split).mkdir(parents=True)
        shutil.copytree(os.path.join(data_root, "nuscenes_pred", "maps"), root / "maps",
                        ignore=lambda _, names: [n for n in names if scene not in n])
        rows = []
        for line in open(os.path.join(label_dir(data_root, split), f"{scene}.txt"), encoding="utf-8"):
            parts = line.split()
            if parts and float(parts[0]) > 6:  # keyframe 6 is 'now' after the default 3 s of history
                parts[13] = f"{float(parts[13]) + shift:.4f}"
            rows.append(" ".join(parts))
        (root / "label" / split / f"{scene}.txt").write_text("\n".join(rows) + "\n")
        copies[shift] = NuScenesPredSource(root=str(root)).load_scene(split, scene)
    now = copies[0.0].current_index
    assert torch.equal(copies[0.0].states[:, :, : now + 1], copies[3.0].states[:, :, : now + 1])
    assert not torch.equal(copies[0.0].states[:, :, now + 1 :], copies[3.0].states[:, :, now + 1 :])
    scene_tensor = copies[0.0]
    both = scene_tensor.valid[0, :, now] & scene_tensor.valid[0, :, now - FACTOR]
    step = scene_tensor.xy[0, both, now] - scene_tensor.xy[0, both, now - FACTOR]
    heading = torch.stack([torch.cos(scene_tensor.yaw[0, both, now]), torch.sin(scene_tensor.yaw[0, both, now])], -1)
    assert both.any()
    torch.testing.assert_close(scene_tensor.speed[0, both, now], (step * heading).sum(-1) / KEYFRAME_DT,
                               atol=1e-3, rtol=1e-4)


def test_history_ending_between_keyframes_is_refused(nuscenes_source):
    source = NuScenesPredSource(root=nuscenes_source.root, history_s=2.8)
    with pytest.raises(DataFormatError, match=r"history_s=2.8 puts 'now' between two 0.5 s keyframes"):
        source.load_scene("val", source.scene_ids("val")[0])


def test_the_map_check_reads_the_whole_log_not_the_window_loaded(data_root):
    """A short window of a real scene can hold few moving positions, some off the drivable layer (train
    scene-0765: 79 % over 3 s + 5 s); the check against the map reads the whole logged track, so no real scene is
    refused for the window a campaign loads."""
    source = NuScenesPredSource(root=os.path.join(data_root, "nuscenes_pred"), history_s=3.0, min_future_s=4.0,
                                max_future_s=5.0)
    scene = source.load_scene("train", "scene-0765")
    assert scene.num_steps == 81 and bool(scene.controlled.any())
