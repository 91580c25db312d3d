"""Scenes are checked against their own map and against the limits of their source, before memory is spent.

Every input here is synthetic and small (a 100 m map with one drivable band, a few tracks; a ScenarioNet pickle
built in the test), written to ``tmp_path``. The memory cases run in a subprocess whose address space is capped,
and assert a clear refusal and a peak resident memory under 1 GB (the child's ``VmHWM``: ``ru_maxrss``
would keep the RSS the child had as a fork of the test process before it exec'd).
"""

from __future__ import annotations

import json
import math
import os
import pickle
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.feedback.store import FeedbackStore
from trafficrlhf_sdk.errors import FileEncodingError, InputLimitError, MapMismatchError, TrafficRLHFError
from trafficrlhf_sdk.metrics import geometry
from trafficrlhf_sdk.scenario.checks import on_map_share

nuscenes_pred = pytest.importorskip("trafficrlhf_nuscenes_pred")
scenarionet = pytest.importorskip("trafficrlhf_scenarionet")

SCENE = "scene-0001"
ORIGIN = (1000.0, 2000.0)  # world position of the map's corner
PPM = 3  # pixels per metre
BAND = (40.0, 60.0)  # the drivable band: scene-frame y in [40, 60) m, every x
PEAK_LIMIT_MB = 1024


# ------------------------------------------------------------------------------------------ synthetic nuScenes
def label_rows(num_tracks: int = 3, frames: int = 41) -> list[str]:
    """Tracks driving along +x at 2.5 m/s inside the band (y = 48, 50, 52 m, repeated for more tracks)."""
    rows = []
    for track in range(num_tracks):
        y = ORIGIN[1] + 48.0 + 2.0 * (track % 3)
        for frame in range(frames):
            x = ORIGIN[0] + 10.0 + 1.25 * frame + 8.0 * (track // 3 % 5)
            rows.append(f"{frame} {track} Car -1 -1 -1 -1 -1 -1 -1 1.8 1.5 4.2 {x:.2f} 0.0 {y:.2f} 0.0 0")
    return rows


def write_scene(root: Path, rows: list[str] | None = None, origin_shift: tuple[float, float] = (0.0, 0.0),
                transpose: bool = False) -> Path:
    """A nuscenes_pred data root with one val scene; ``origin_shift`` (m) moves the map's origin in its meta file."""
    (root / "label" / "val").mkdir(parents=True, exist_ok=True)
    (root / "maps").mkdir(exist_ok=True)
    (root / "label" / "val" / f"{SCENE}.txt").write_text("\n".join(rows or label_rows()) + "\n")
    image = np.zeros((100 * PPM, 100 * PPM, 3), np.uint8)  # [x pixel, y pixel, (R, G, B)]; drivable is B
    image[:, int(BAND[0] * PPM):int(BAND[1] * PPM), 2] = 255
    if transpose:
        image = image.transpose(1, 0, 2).copy()
    Image.fromarray(image).save(root / "maps" / f"{SCENE}.png")
    x, y = ORIGIN[0] + origin_shift[0], ORIGIN[1] + origin_shift[1]
    (root / "maps" / f"meta_{SCENE}.txt").write_text(f"{x} {y} {PPM}\n")
    return root


def load(root: Path, **options: object):  # type: ignore[no-untyped-def]
    return nuscenes_pred.NuScenesPredSource(root=str(root), **options).load_scene("val", SCENE)


def test_the_true_map_loads_with_every_moving_position_on_it(tmp_path: Path) -> None:
    share, count = on_map_share(load(write_scene(tmp_path)))
    assert share == 1.0 and count > 100


def test_a_map_shifted_9_m_is_refused_with_the_share_and_the_move_that_fits(tmp_path: Path) -> None:
    root = write_scene(tmp_path, origin_shift=(0.0, 9.0))  # one track of three leaves the band
    with pytest.raises(MapMismatchError) as error:
        load(root)
    message = str(error.value)
    assert re.search(r"scene-0001.txt: only 67% of the \d+ logged positions of its moving vehicles lie on the "
                     r"drivable layer", message), message
    assert "moving the map's origin by about (+0, -" in message and f"meta_{SCENE}.txt" in message
    assert "min_on_map_share=0" in message and "TRAFFICRLHF_SOURCE_OPTIONS" in message and "\n" not in message


def test_a_map_that_passes_the_share_but_fits_much_better_moved_is_refused(tmp_path: Path) -> None:
    """Six tracks across the band, the map's origin 2 m off: five of six stay on the road (83 %, above the 80 %
    floor), yet every agent's road is wrong by 2 m and a move of 1 to 2 m puts all of them on it."""
    rows = [f"{frame} {track} Car -1 -1 -1 -1 -1 -1 -1 1.8 1.5 4.2 {ORIGIN[0] + 10.0 + 1.25 * frame:.2f} 0.0 "
            f"{ORIGIN[1] + 41.0 + 3.0 * track:.2f} 0.0 0" for track in range(6) for frame in range(41)]
    assert on_map_share(load(write_scene(tmp_path / "true", rows)))[0] == 1.0
    with pytest.raises(MapMismatchError) as error:
        load(write_scene(tmp_path / "shifted", rows, origin_shift=(0.0, 2.0)))
    message = str(error.value)
    assert re.search(r"scene-0001.txt: 83% of the [\d,]+ logged positions .* moving the map's origin by about "
                     r"\(\+0, -[12]\) m would put 100% on it .* the map is misregistered", message), message
    assert "min_on_map_share=0" in message and "\n" not in message
    assert on_map_share(load(tmp_path / "shifted", min_on_map_share=0.0))[0] == pytest.approx(5 / 6, abs=0.01)


def test_a_transposed_map_is_refused(tmp_path: Path) -> None:
    with pytest.raises(MapMismatchError, match=r"only \d+% of the"):
        load(write_scene(tmp_path, transpose=True))


def test_the_user_can_accept_an_off_map_scene_in_code_or_for_every_command(tmp_path: Path, monkeypatch) -> None:
    root = write_scene(tmp_path, origin_shift=(0.0, 9.0))
    assert on_map_share(load(root, min_on_map_share=0.0))[0] < 0.8
    monkeypatch.setenv("TRAFFICRLHF_SOURCE_OPTIONS", "min_on_map_share=0")
    assert on_map_share(load(root))[0] < 0.8
    monkeypatch.setenv("TRAFFICRLHF_SOURCE_OPTIONS", "min_on_map_shar=0,max_steps=50")  # a typo; a ScenarioNet option
    ignored = r"source 'nuscenes_pred' takes no option \['max_steps', 'min_on_map_shar'\]"
    with pytest.warns(UserWarning, match=ignored), pytest.raises(MapMismatchError):
        load(root)
    monkeypatch.setenv("TRAFFICRLHF_SOURCE_OPTIONS", "min_on_map_share=zero")
    with pytest.raises(TrafficRLHFError, match=r"TRAFFICRLHF_SOURCE_OPTIONS.*min_on_map_share: Input should be"):
        load(root)


def test_evaluate_on_a_shifted_map_exits_2_naming_the_share(tmp_path: Path, capsys) -> None:
    root = write_scene(tmp_path / "data", origin_shift=(0.0, 9.0))
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "constant_velocity", "--root", str(root), "--scenes", "1", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err[-1].startswith("Error: ") and "logged positions" in err[-1]
    assert not out.exists()


def test_a_scene_accepted_with_no_agent_to_drive_fails_evaluate_and_feedback_create(tmp_path: Path, capsys,
                                                                                    monkeypatch) -> None:
    """The reproduction: a map 50 m off gave an exit-0 evaluation of '1 scenes, 0 controlled agents'."""
    root = write_scene(tmp_path / "data", origin_shift=(0.0, 30.0))  # every track off the band
    monkeypatch.setenv("TRAFFICRLHF_SOURCE_OPTIONS", "min_on_map_share=0")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "constant_velocity", "--root", str(root), "--scenes", "1", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and "none of the 1 scenes (scene-0001)" in err[-1] and "nothing was written" \
        in err[-1]
    assert not out.exists()
    with pytest.raises(SystemExit) as exit_info:
        main(["feedback", "create", "--db", str(tmp_path / "f.db"), "--name", "c", "--model", "constant_velocity",
              "--root", str(root), "--scenes", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and "scene-0001: the context has no controlled agent" in err[-1]


def test_a_label_file_that_is_not_utf8_names_file_line_and_byte(tmp_path: Path) -> None:
    root = write_scene(tmp_path)
    path = root / "label" / "val" / f"{SCENE}.txt"
    lines = path.read_bytes().splitlines()
    lines[4] = lines[4].replace(b"Car", b"C\xe4r")
    path.write_bytes(b"\n".join(lines) + b"\n")
    with pytest.raises(FileEncodingError, match=r"scene-0001.txt:5: not UTF-8 text \(byte 0xe4 at column \d+\).*"
                                                r"Re-export it as UTF-8"):
        load(root)


def test_more_tracks_than_max_agents_are_refused_naming_the_option(tmp_path: Path) -> None:
    root = write_scene(tmp_path, rows=label_rows(num_tracks=40, frames=30))
    with pytest.raises(InputLimitError, match=r"40 agents \(tracks\), more than max_agents=30; .*max_agents="):
        load(root, max_agents=30)
    assert load(root, max_agents=40).num_agents == 40


# ------------------------------------------------------------------------------------------ synthetic ScenarioNet
def scenarionet_scenario(length: int = 130, num_tracks: int = 3) -> dict:
    """Tracks driving along +x at 5 m/s on one lane polygon (world y in [1990, 2010])."""
    t = np.arange(length) * 0.1
    tracks = {}
    for k in range(num_tracks):
        pos = np.stack([1000.0 + 5 * t + 8 * k, np.full(length, 2000.0 + (k % 3) - 1), np.zeros(length)], 1)
        tracks[f"car{k}"] = {"type": "VEHICLE", "state": {
            "position": pos, "heading": np.zeros(length), "velocity": np.tile([5.0, 0.0], (length, 1)),
            "valid": np.ones(length), "length": np.full((length, 1), 4.5), "width": np.full((length, 1), 1.9)}}
    lane = np.array([[900.0, 1990.0], [1200.0, 1990.0], [1200.0, 2010.0], [900.0, 2010.0]])
    return {"id": "s", "version": "test", "length": length, "tracks": tracks, "dynamic_map_states": {},
            "metadata": {"dataset": "synthetic", "sample_rate": 0.1, "sdc_id": "car0"},
            "map_features": {"lane": {"type": "LANE_SURFACE_STREET", "polyline": lane[:2], "polygon": lane}}}


def write_pickle(folder: Path, data: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sd_case.pkl").write_bytes(pickle.dumps(data, protocol=4))
    return folder


def load_pickle(folder: Path, **options: object):  # type: ignore[no-untyped-def]
    return scenarionet.ScenarioNetSource(root=str(folder), **options).load_scene("all", "sd_case")


def test_a_good_scenarionet_scene_loads_on_its_map(tmp_path: Path) -> None:
    assert on_map_share(load_pickle(write_pickle(tmp_path, scenarionet_scenario())))[0] == 1.0


def test_scenarionet_map_features_off_the_tracks_are_refused(tmp_path: Path) -> None:
    data = scenarionet_scenario()
    data["map_features"]["lane"]["polygon"] = data["map_features"]["lane"]["polygon"] + [0.0, 40.0]
    with pytest.raises(MapMismatchError, match=r"sd_case.pkl: only 0% .*'map_features'"):
        load_pickle(write_pickle(tmp_path, data))


def test_scenarionet_shared_track_objects_are_refused(tmp_path: Path) -> None:
    data = scenarionet_scenario()
    data["tracks"] = {"car0": data["tracks"]["car0"], **{f"copy{k}": data["tracks"]["car1"] for k in range(3)}}
    with pytest.raises(scenarionet.source.DataFormatError, match=r"tracks 'copy0' and 'copy1' are the same object"):
        load_pickle(write_pickle(tmp_path, data))


def test_scenarionet_limits_name_their_option_and_can_be_raised(tmp_path: Path) -> None:
    folder = write_pickle(tmp_path, scenarionet_scenario())
    with pytest.raises(InputLimitError, match=r"'length' is 130 logged steps, more than max_steps=100; .*max_steps="):
        load_pickle(folder, max_steps=100)
    with pytest.raises(InputLimitError, match=r"3 agents \(tracks\), more than max_agents=2"):
        load_pickle(folder, max_agents=2)
    with pytest.raises(InputLimitError, match=r"more than max_map_pixels=1,000; the farthest position"):
        load_pickle(folder, max_map_pixels=1000)
    assert load_pickle(folder, max_steps=130, max_agents=3).num_agents == 3


# ------------------------------------------------------------------------------------------------- memory
MEMORY_CHILD = textwrap.dedent("""
    import json, resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (CAP, CAP))
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_sdk.metrics.failure import collisions_per_step
    from trafficrlhf_nuscenes_pred import NuScenesPredSource
    from trafficrlhf_scenarionet import ScenarioNetSource
    outcomes = {}
    for case, (kind, root) in json.loads(sys.argv[1]).items():
        try:
            if kind == "nuscenes_pred":
                scene = NuScenesPredSource(root=root).load_scene("val", "scene-0001")
            else:
                scene = ScenarioNetSource(root=root).load_scene("all", "sd_case")
            collisions_per_step(scene)  # what evaluate computes first over every pair of agents
        except TrafficRLHFError as exc:
            outcomes[case] = "refused: " + str(exc)[:400]
        except MemoryError:
            outcomes[case] = "MEMORY BLOW-UP"
        else:
            outcomes[case] = "ACCEPTED"
    hwm = next(line for line in open("/proc/self/status") if line.startswith("VmHWM"))
    print(json.dumps({"outcomes": outcomes, "peak_mb": int(hwm.split()[1]) / 1024}))
""")


def shared_track_bomb() -> dict:
    data = scenarionet_scenario()
    data["tracks"] = {f"t{k}": data["tracks"]["car0"] for k in range(2000)}
    return data


def far_position() -> dict:
    data = scenarionet_scenario()
    data["tracks"]["car2"]["state"]["position"][60, 0] = 1e6
    return data


def huge_length() -> dict:
    data = scenarionet_scenario()
    data["length"] = 10**12
    return data


MEMORY_CASES = {
    "nuScenes label file of 1,500 tracks": ("nuscenes_pred", r"1,500 agents \(tracks\), more than max_agents=1,024"),
    "ScenarioNet position at 1e6 m": (far_position, r"more than max_map_pixels=25,000,000; the farthest position is "
                                                    r"track 'car2' at step \d+ \(1,000,000.0, "),
    "ScenarioNet 2,000 references to one track": (shared_track_bomb, r"2,000 agents \(tracks\), more than "
                                                                     r"max_agents=1,024"),
    "ScenarioNet length 1e12": (huge_length, r"'length' is 1,000,000,000,000 logged steps, more than "
                                             r"max_steps=100,000"),
}


@pytest.fixture(scope="module")
def memory_run(tmp_path_factory) -> dict:  # type: ignore[no-untyped-def]
    """Every memory case in one subprocess capped at 6 GiB of address space (torch maps about 2 GiB at import; the
    failures asked for 3.5 GB to 7 TiB): the outcome of each, and the child's peak resident memory."""
    roots = {}
    for index, (case, (make, _)) in enumerate(MEMORY_CASES.items()):
        folder = tmp_path_factory.mktemp(f"limits{index}")
        if make == "nuscenes_pred":
            roots[case] = ("nuscenes_pred", str(write_scene(folder, rows=label_rows(num_tracks=1500))))
        else:
            roots[case] = ("scenarionet", str(write_pickle(folder, make())))
    code = MEMORY_CHILD.replace("CAP", str(6 * 2**30))
    env = {k: v for k, v in os.environ.items() if k != "TRAFFICRLHF_SOURCE_OPTIONS"}
    run = subprocess.run([sys.executable, "-c", code, json.dumps(roots)], capture_output=True, text=True,
                         timeout=300, env={**env, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout + run.stderr[-2000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", list(MEMORY_CASES))
def test_oversized_scenes_are_refused_before_allocating(case: str, memory_run: dict) -> None:
    outcome = memory_run["outcomes"][case]
    assert outcome.startswith("refused: ") and re.search(MEMORY_CASES[case][1], outcome), outcome
    assert memory_run["peak_mb"] < PEAK_LIMIT_MB, f"peak {memory_run['peak_mb']:.0f} MB"


# ------------------------------------------------------------------------------------ collisions in chunks
def random_agents(b: int, a: int, t: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(seed)
    xy = torch.rand(b, a, t, 2, generator=gen) * 60
    yaw = torch.rand(b, a, t, generator=gen) * 2 * math.pi
    extent = torch.tensor([4.5, 1.9]).expand(b, a, 2).clone()
    valid = torch.rand(b, a, t, generator=gen) > 0.3
    return xy, yaw, extent, valid


def test_colliding_pairs_in_chunks_give_the_same_pairs_in_the_same_order(monkeypatch) -> None:
    args = random_agents(3, 40, 12)
    whole = geometry.colliding_pairs(*args)
    monkeypatch.setattr(geometry, "PAIR_CHUNK_CELLS", 100)  # 2 pairs x 3 scenes x 12 steps per chunk
    chunked = geometry.colliding_pairs(*args)
    assert len(whole[0]) > 50
    for a, b in zip(whole, chunked):
        assert torch.equal(a, b)


COLLISION_CHILD = textwrap.dedent("""
    import json, resource, torch
    from trafficrlhf_sdk.metrics.geometry import colliding_pairs
    a, t = 1000, 100  # 499,500 pairs x 100 steps: 1.2 GB of pair indices at once
    xy = torch.stack([torch.arange(a, dtype=torch.float32)[:, None].expand(a, t) * 10,
                      torch.arange(t, dtype=torch.float32)[None].expand(a, t)], -1)[None]
    before = next(line for line in open("/proc/self/status") if line.startswith("VmRSS"))
    pairs = colliding_pairs(xy, torch.zeros(1, a, t), torch.tensor([4.5, 1.9]).expand(1, a, 2), torch.ones(1, a, t,
                            dtype=torch.bool))
    hwm = next(line for line in open("/proc/self/status") if line.startswith("VmHWM"))
    print(json.dumps({"pairs": len(pairs[0]), "peak_mb": int(hwm.split()[1]) / 1024,
                      "start_mb": int(before.split()[1]) / 1024}))
""")


def test_collision_checks_of_a_large_scene_take_memory_for_one_chunk() -> None:
    run = subprocess.run([sys.executable, "-c", COLLISION_CHILD], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    # the check's own growth over the process's size before it (torch alone is a few hundred MB, and the allocator
    # moves the peak by tens of MB between runs); all pairs at once would add 1.2 GB
    assert result["pairs"] == 0 and result["peak_mb"] - result["start_mb"] < 650, result


def test_a_campaign_leaves_out_and_reports_a_scene_with_no_vehicle_to_judge(tmp_path: Path, capsys,
                                                                            monkeypatch) -> None:
    """A later start of a scene whose vehicles have all left shows nobody to judge: the campaign stores the other
    scenes and names the one it left out (every one empty: the error that
    test_a_scene_accepted_with_no_agent_to_drive_fails_evaluate_and_feedback_create checks)."""
    root = write_scene(tmp_path / "data")
    empty = "scene-0002"  # the same scene with its map moved off every track
    for folder, name in (("label/val", "{}.txt"), ("maps", "{}.png")):
        (root / folder / name.format(empty)).write_bytes((root / folder / name.format(SCENE)).read_bytes())
    (root / "maps" / f"meta_{empty}.txt").write_text(f"{ORIGIN[0]} {ORIGIN[1] + 30.0} {PPM}\n")
    monkeypatch.setenv("TRAFFICRLHF_SOURCE_OPTIONS", "min_on_map_share=0")
    db = tmp_path / "f.db"
    with pytest.raises(SystemExit) as exit_info:
        main(["feedback", "create", "--db", str(db), "--name", "c", "--model", "constant_velocity", "--root",
              str(root), "--scenes", "2"])
    out = capsys.readouterr().out
    assert exit_info.value.code == 0
    assert f"added 1 contexts, 1 left out with no vehicle to judge at their start ({empty})" in out
    store = FeedbackStore(str(db))
    assert [k["scene_id"] for k in store.context_keys(store.campaign("c"))] == [SCENE]
