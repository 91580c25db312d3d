"""Bad input never gives a valid-looking wrong result: one parametrized test per input class.

Each case edits a copy of a good input (a bundled checkpoint, the bundled reward model, one nuScenes scene, a
ScenarioNet pickle, a command line) the way a careless user or an attacker would, and asserts one clear error that
names the file, tensor, field or line, and that nothing was written or lost (the inputs are unchanged, no output
appeared). The memory cases run in a subprocess whose address space is capped (``RLIMIT_AS``), so a blow-up fails
the test instead of the machine, and assert a peak resident memory under 1 GB. The annotation server's HTTP bodies
are covered by ``plugins/annotation_web/tests``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError
from trafficrlhf_sdk.models.checkpoint import record_weights_digest, sha256_file
from trafficrlhf_sdk.scenario import default_data_root
from trafficrlhf_sdk.testing.images import png_declaring

ROOT = Path(__file__).resolve().parent.parent
CTG_SMALL = ROOT / "reference_models" / "ctg" / "checkpoints" / "ctg_small"
REWARD = ROOT / "reference_models" / "reward" / "ctg_no_collision"
NUSCENES = Path(default_data_root()) / "nuscenes_pred"
SCENE = "scene-0002"
PEAK_LIMIT_MB = 1024


def snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder``: comparing two snapshots shows that nothing was written or lost."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def copy_of(source: Path, tmp_path: Path, name: str = "ckpt") -> Path:
    folder = tmp_path / name
    folder.mkdir()
    for file in ("config.json", "model.safetensors"):
        shutil.copy(source / file, folder / file)
    return folder


def edit_config(folder: Path, change: Callable[[dict], object]) -> None:
    config = json.loads((folder / "config.json").read_text())
    result = change(config)
    (folder / "config.json").write_text(json.dumps(result if isinstance(result, list) else config))


def edit_weights(folder: Path, change: Callable[[dict[str, torch.Tensor]], None], record: bool = True) -> None:
    tensors = load_file(str(folder / "model.safetensors"))
    change(tensors)
    save_file(tensors, str(folder / "model.safetensors"))
    if record:
        record_weights_digest(str(folder))


def first_float(tensors: dict[str, torch.Tensor]) -> str:
    return next(k for k, v in sorted(tensors.items()) if v.is_floating_point() and v.dim() == 2)


def _as(dtype: torch.dtype) -> Callable[[dict[str, torch.Tensor]], None]:
    def change(t: dict[str, torch.Tensor]) -> None:
        name = first_float(t)
        t[name] = (t[name] * 100).to(dtype)
    return change


def _poison(value: float) -> Callable[[dict[str, torch.Tensor]], None]:
    def change(t: dict[str, torch.Tensor]) -> None:
        t[first_float(t)].view(-1)[3] = value
    return change


def _set(key: str, value: object) -> Callable[[dict], None]:
    return lambda c: c["config"].__setitem__(key, value)


# ------------------------------------------------------------------------------------------- checkpoints
CHECKPOINT_CASES = {
    # the weights
    "int32 layer": (lambda f: edit_weights(f, _as(torch.int32)), r"tensor '.+' is stored as I32 but .* needs "
                                                                  r"floating point"),
    "bool layer": (lambda f: edit_weights(f, _as(torch.bool)), r"is stored as BOOL"),
    "missing tensor": (lambda f: edit_weights(f, lambda t: t.pop(first_float(t))), r"missing tensors \['"),
    "extra tensor": (lambda f: edit_weights(f, lambda t: t.__setitem__("extra.weight", torch.zeros(2))),
                     r"unexpected tensors \['extra.weight'\]"),
    "wrong shape": (lambda f: edit_weights(f, lambda t: t.__setitem__(first_float(t), t[first_float(t)][:1])),
                    r"tensor '.+' has shape \(1, \d+\) but"),
    "NaN weight": (lambda f: edit_weights(f, _poison(float("nan"))), r"checkpoint '.+ckpt': tensor '.+' holds 1 NaN"),
    "inf weight": (lambda f: edit_weights(f, _poison(float("inf"))), r"holds 1 NaN or infinite"),
    "edited weights, old SHA-256": (lambda f: edit_weights(f, _poison(0.5), record=False),
                                    r"does not match the SHA-256 recorded in config.json"),
    "0-byte weights": (lambda f: ((f / "model.safetensors").write_bytes(b""), record_weights_digest(str(f))),
                       r"not a readable safetensors file"),
    "weights missing": (lambda f: (f / "model.safetensors").unlink(), r"has no weights file 'model.safetensors'"),
    # config.json
    "no SHA-256": (lambda f: edit_config(f, lambda c: c.pop("weights")), r"records no SHA-256 of the weights"),
    "config.json a list": (lambda f: edit_config(f, lambda c: [c]), r"expected a JSON object .* got a list"),
    "config.json not JSON": (lambda f: (f / "config.json").write_text("{oops"), r"invalid JSON"),
    "unknown top-level key": (lambda f: edit_config(f, lambda c: c.__setitem__("optimizer", {})),
                              r"`optimizer` extra inputs are not permitted"),
    "unknown config key": (lambda f: edit_config(f, _set("horizon_s", 2.0)), r"unknown architecture config key"),
    "horizon a string": (lambda f: edit_config(f, _set("horizon", "twenty")), r"`horizon` = 'twenty' is not"),
    "horizon 0": (lambda f: edit_config(f, _set("horizon", 0)), r"`horizon` = 0 must be at least 1"),
    "horizon -20": (lambda f: edit_config(f, _set("horizon", -20)), r"`horizon` = -20 must be at least 1"),
    "horizon 2.5": (lambda f: edit_config(f, _set("horizon", 2.5)), r"`horizon` = 2.5 is not a valid int"),
    "horizon 1e9": (lambda f: edit_config(f, _set("horizon", 10**9)), r"`horizon` = 1000000000 exceeds"),
    "dt NaN": (lambda f: (f / "config.json").write_text((f / "config.json").read_text().replace('"dt": 0.1',
                                                                                            '"dt": NaN')),
               r"`dt` = nan is not finite"),
    "layer sizes of 160 GB": (lambda f: edit_config(f, _set("unet_dims", [100000, 100000])),
                              r"asks for [\d,]+ parameters"),
    "weights file ../": (lambda f: edit_config(f, lambda c: c["weights"].__setitem__("file", "../other.safetensors")),
                         r"`weights.file` is '../other.safetensors', which lies outside the checkpoint folder"),
    "weights file absolute": (lambda f: edit_config(f, lambda c: c["weights"].__setitem__(
        "file", str(CTG_SMALL / "model.safetensors"))), r"lies outside the checkpoint folder"),
    "another adapter's checkpoint": (lambda f: edit_config(f, lambda c: c.__setitem__("adapter", "bits")),
                                     r"holds weights for adapter 'bits', not 'ctg'"),
}


@pytest.mark.parametrize("case", list(CHECKPOINT_CASES))
def test_bad_checkpoint_gets_one_clear_error_and_nothing_changes(case: str, tmp_path: Path) -> None:
    from trafficrlhf_ctg import CTGAdapter

    folder = copy_of(CTG_SMALL, tmp_path)
    edit, message = CHECKPOINT_CASES[case]
    edit(folder)
    before = snapshot(tmp_path)
    with pytest.raises((DataFormatError, DataNotFoundError), match=message) as error:
        CTGAdapter(checkpoint=str(folder))
    assert "\n" not in str(error.value)
    assert snapshot(tmp_path) == before, "loading wrote or removed a file"


def test_int32_checkpoint_on_the_command_line_exits_2_before_anything_is_written(tmp_path: Path, capsys) -> None:
    """The reproduction: an int32 layer used to load as zeros and evaluate with exit 0."""
    folder = copy_of(CTG_SMALL, tmp_path)
    edit_weights(folder, _as(torch.int32))
    out = tmp_path / "results"
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--checkpoint", str(folder), "--scenes", "1", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err[-1].startswith("Error: "), err
    assert "is stored as I32" in err[-1] and str(folder) in err[-1] and "Traceback" not in "".join(err)
    assert not out.exists()


def test_save_pretrained_records_a_digest_that_loading_checks(tmp_path: Path) -> None:
    from trafficrlhf_ctg import CTGAdapter

    CTGAdapter().save_pretrained(str(tmp_path / "saved"))
    saved = json.loads((tmp_path / "saved" / "config.json").read_text())
    assert saved["weights"]["sha256"] == sha256_file(str(tmp_path / "saved" / "model.safetensors"))
    assert sorted(os.listdir(tmp_path / "saved")) == ["config.json", "model.safetensors"]  # no temporary left
    CTGAdapter.from_pretrained(str(tmp_path / "saved"))


# ------------------------------------------------------------------------------------------- reward models
def _reward_sha(folder: Path) -> None:
    edit_config(folder, lambda c: c["weights"].update(sha256=sha256_file(str(folder / "model.safetensors")),
                                                      bytes=os.path.getsize(folder / "model.safetensors")))


REWARD_CASES = {
    "NaN weight": (lambda f: (edit_weights(f, _poison(float("nan")), record=False), _reward_sha(f)),
                   r"reward model '.+rm': tensor '.+' holds 1 NaN"),
    "inf weight": (lambda f: (edit_weights(f, _poison(float("-inf")), record=False), _reward_sha(f)),
                   r"holds 1 NaN or infinite"),
    "0-byte weights": (lambda f: ((f / "model.safetensors").write_bytes(b""), _reward_sha(f)),
                       r"not a readable safetensors file"),
    "no SHA-256": (lambda f: edit_config(f, lambda c: c["weights"].pop("sha256")), r"records no SHA-256"),
    "edited weights": (lambda f: edit_weights(f, _poison(0.25), record=False), r"does not match the SHA-256"),
    "weights file ../": (lambda f: edit_config(f, lambda c: c["weights"].__setitem__("file", "../x.safetensors")),
                         r"lies outside the model folder"),
    "int32 layer": (lambda f: (edit_weights(f, _as(torch.int32), record=False), _reward_sha(f)),
                    r"is not floating point"),
}


@pytest.mark.parametrize("case", list(REWARD_CASES))
def test_bad_reward_model_is_refused_by_load_and_by_rm_info(case: str, tmp_path: Path, capsys) -> None:
    from trafficrlhf_sdk.reward import RewardModel

    folder = copy_of(REWARD, tmp_path, "rm")
    edit, message = REWARD_CASES[case]
    edit(folder)
    before = snapshot(tmp_path)
    with pytest.raises(DataFormatError, match=message):
        RewardModel.from_pretrained(str(folder))
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "info", str(folder)])
    captured = capsys.readouterr()
    assert exit_info.value.code == 2 and "weights DO NOT LOAD" in captured.out and "weights ok" not in captured.out
    assert len(captured.err.strip().splitlines()) == 1
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------------- nuScenes scenes and maps
def scene_copy(tmp_path: Path) -> Path:
    """One val scene (labels, map PNG and meta) in a temporary data root; deleted with ``tmp_path``."""
    if not (NUSCENES / "label" / "val" / f"{SCENE}.txt").is_file():
        pytest.skip(f"real data not found under {NUSCENES}")
    root = tmp_path / "nuscenes_pred"
    (root / "label" / "val").mkdir(parents=True)
    (root / "maps").mkdir()
    shutil.copy(NUSCENES / "label" / "val" / f"{SCENE}.txt", root / "label" / "val")
    for name in (f"{SCENE}.png", f"meta_{SCENE}.txt"):
        shutil.copy(NUSCENES / "maps" / name, root / "maps")
    return root


def edit_row(index: int, column: int, value: str) -> Callable[[Path], None]:
    def edit(root: Path) -> None:
        path = root / "label" / "val" / f"{SCENE}.txt"
        lines = path.read_text().splitlines()
        parts = lines[index].split()
        parts[column] = value
        lines[index] = " ".join(parts)
        path.write_text("\n".join(lines) + "\n")
    return edit


def add_row(template: str) -> Callable[[Path], None]:
    """Append a row, ``{x}``/``{y}`` filled with a point 3 km east of the map's corner."""
    def edit(root: Path) -> None:
        x, y, _ = (float(v) for v in (root / "maps" / f"meta_{SCENE}.txt").read_text().split())
        path = root / "label" / "val" / f"{SCENE}.txt"
        path.write_text(path.read_text() + template.format(x=x + 3000.0, y=y) + "\n")
    return edit


def duplicate_row(root: Path) -> None:
    path = root / "label" / "val" / f"{SCENE}.txt"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines, lines[0]]) + "\n")


def blank_map(root: Path) -> None:
    from PIL import Image

    path = root / "maps" / f"{SCENE}.png"
    size = Image.open(path).size
    Image.new("RGB", size).save(path)


def meta(text: str) -> Callable[[Path], None]:
    return lambda root: (root / "maps" / f"meta_{SCENE}.txt").write_text(text)


def shifted_origin(dx: float) -> Callable[[Path], None]:
    def edit(root: Path) -> None:
        path = root / "maps" / f"meta_{SCENE}.txt"
        x, y, scale = (float(v) for v in path.read_text().split())
        path.write_text(f"{x + dx} {y} {scale}\n")
    return edit


SCENE_CASES = {
    # label files (columns: 0 frame, 1 track, 2 class, 10 width, 12 length, 13 x, 15 y)
    "frame 20000000": (edit_row(5, 0, "20000000"), r":6: frame must be an integer from 0 to 10,000, got '20000000'"),
    "fractional frame": (edit_row(5, 0, "2.5"), r":6: frame must be an integer"),
    "fractional track id": (edit_row(5, 1, "3.5"), r":6: track id must be an integer, got '3.5'"),
    "zero width": (edit_row(5, 10, "0"), r":6: box width 0 and length .* must be above 0"),
    "negative length": (edit_row(5, 12, "-4.2"), r":6: box width .* and length -4.2 must be above 0"),
    "unknown class": (edit_row(5, 2, "Spaceship"), r":6: unknown agent class 'Spaceship'"),
    "position 1e6 m": (edit_row(5, 13, "1000000"), r":6: position \(1000000, .*\) is more than 100,000 m"),
    "position 3 km off the map": (add_row("0 999 Car -1 -1 -1 -1 -1 -1 -1 1.8 1.5 4.5 {x} 0.7 {y} 0.0 0.0"),
                                  r":\d+: position .* lies more than 1000 m outside the map raster"),
    "teleporting track": (edit_row(5, 15, "-60"), r"moves [\d.]+ m/s since line \d+ \(more than 70 m/s\)"),
    "duplicate row": (duplicate_row, r"has a second row for frame \d+ \(the first is line 1\)"),
    "non-numeric value": (edit_row(5, 13, "east"), r":6: non-numeric value"),
    "NaN coordinate": (edit_row(5, 13, "nan"), r":6: NaN or inf"),
    # maps
    "blank map": (blank_map, r"scene-0002.png: the drivable layer is empty"),
    "scale 0": (meta("551 1459 0\n"), r"meta_scene-0002.txt: 'x_min y_min scale' = 551.0 1459.0 0.0"),
    "scale -3": (meta("551 1459 -3\n"), r"the scale \(pixels per metre\) above 0"),
    "origin NaN": (meta("nan 1459 3\n"), r"the origin must be finite"),
    "meta not numbers": (meta("x y z\n"), r"expected three numbers 'x_min y_min scale'"),
    "origin 5 km off": (shifted_origin(5000.0), r"lies more than 1000 m outside the map raster"),
    "origin 150 m off (no vehicle on the road)": (shifted_origin(-150.0), r"none of the scene's \d+ vehicle rows lies "
                                                                          r"on the drivable layer"),
    "PNG declaring 100000 x 100000": (lambda root: (root / "maps" / f"{SCENE}.png").write_bytes(
        png_declaring(100_000, 100_000)), r"cannot read the map image \(Image size \(10000000000 pixels\) exceeds"),
    "PNG declaring 8000 x 8000": (lambda root: (root / "maps" / f"{SCENE}.png").write_bytes(
        png_declaring(8_000, 8_000)), r"declares 8000 x 8000 pixels, more than 25,000,000"),
    "PNG truncated": (lambda root: (root / "maps" / f"{SCENE}.png").write_bytes(b"\x89PNG\r\n"),
                      r"cannot read the map image"),
}


@pytest.mark.parametrize("case", list(SCENE_CASES))
def test_bad_scene_files_get_an_error_naming_file_and_line(case: str, tmp_path: Path) -> None:
    from trafficrlhf_nuscenes_pred import NuScenesPredSource

    root = scene_copy(tmp_path)
    edit, message = SCENE_CASES[case]
    edit(root)
    before = snapshot(root)
    with pytest.raises(DataFormatError, match=message) as error:
        NuScenesPredSource(root=str(root)).load_scene("val", SCENE)
    assert "\n" not in str(error.value)
    assert snapshot(root) == before


def test_blank_map_on_the_command_line_exits_2_naming_the_map(tmp_path: Path, capsys) -> None:
    """The reproduction: an all-black raster used to give an exit-0 run with 0 controlled agents."""
    root = scene_copy(tmp_path)
    blank_map(root)
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "constant_velocity", "--root", str(root), "--scenes", "1", "--json"])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert exit_info.value.code == 2 and err[-1].startswith("Error: ") and "drivable layer is empty" in err[-1]
    assert f"{SCENE}.png" in err[-1] and captured.out == ""


def test_frame_20000000_on_the_command_line_exits_2_naming_file_and_line(tmp_path: Path, capsys) -> None:
    """The reproduction: one frame number of 20,000,000 used to take 8.9 GB."""
    root = scene_copy(tmp_path)
    edit_row(5, 0, "20000000")(root)
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "constant_velocity", "--root", str(root), "--scenes", "1", "--json"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and f"{SCENE}.txt:6: frame must be an integer" in err[-1]


# ------------------------------------------------------------------------------------------- ScenarioNet
def reference_bomb() -> bytes:
    """A pickle of a few kilobytes that expands to a billion values through shared references."""
    inner = [0.0] * 1000
    return pickle.dumps({"map_features": [[inner] * 1000] * 1000}, protocol=4)


SCENARIONET_CASES = {
    "reference bomb": (lambda: reference_bomb(), r"expands to more than 20,000,000 values"),
    "os.system global": (lambda: b"cos\nsystem\n(S'echo pwned'\ntR.", r"refusing|not allowed|forbidden"),
    "truncated": (lambda: pickle.dumps({"a": [1.0] * 100})[:-20], r"not a readable pickle"),
}


@pytest.mark.parametrize("case", list(SCENARIONET_CASES))
def test_bad_scenarionet_pickles_are_refused(case: str, tmp_path: Path) -> None:
    unpickler = pytest.importorskip("trafficrlhf_scenarionet.unpickler")
    make, message = SCENARIONET_CASES[case]
    path = tmp_path / "scenario.pkl"
    path.write_bytes(make())
    with pytest.raises(DataFormatError, match=message):
        unpickler.restricted_load(str(path))
    assert not (tmp_path / "pwned").exists()


def test_map_feature_with_a_point_at_1e9_m_is_refused() -> None:
    map_raster = pytest.importorskip("trafficrlhf_scenarionet.map_raster")
    features = {"lane1": {"type": "LANE_SURFACE_STREET", "polyline": [[0.0, 0.0], [10.0, 0.0], [1e9, 0.0]]}}
    with pytest.raises(DataFormatError, match=r"'lane1' has a segment of 999,999,990 m"):
        map_raster.parse_map_features(features, "scenario.pkl")


# ----------------------------------------------------------------------------------------------- memory
MEMORY_CHILD = textwrap.dedent("""
    import json, resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (CAP, CAP))
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_nuscenes_pred import NuScenesPredSource
    from trafficrlhf_scenarionet.map_raster import parse_map_features
    from trafficrlhf_scenarionet.unpickler import restricted_load
    outcomes = {}
    for case, root in json.loads(sys.argv[1]).items():
        try:
            if case == "reference-bomb pickle":
                restricted_load(root + "/bomb.pkl")
            elif case == "polyline point at 1e9 m":
                parse_map_features({"l": {"type": "LANE_SURFACE_STREET", "polyline": [[0.0, 0.0], [1e9, 0.0]]}},
                                   "x.pkl")
            else:
                NuScenesPredSource(root=root).load_scene("val", SCENE)
        except TrafficRLHFError as exc:
            outcomes[case] = "refused: " + str(exc).splitlines()[0][:300]
        except MemoryError:
            outcomes[case] = "MEMORY BLOW-UP"
        else:
            outcomes[case] = "ACCEPTED"
    peak = int(next(line for line in open('/proc/self/status') if line.startswith('VmHWM')).split()[1]) / 1024
    print(json.dumps({"outcomes": outcomes, "peak_mb": peak}))
""")
MEMORY_CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "frame 20000000": (edit_row(5, 0, "20000000"), r"frame must be an integer from 0 to 10,000"),
    "track at +1e6 m": (edit_row(5, 13, "1000000"), r"is more than 100,000 m from the map origin"),
    "PNG declaring 100000 x 100000": (lambda root: (root / "maps" / f"{SCENE}.png").write_bytes(
        png_declaring(100_000, 100_000)), r"cannot read the map image"),
    "reference-bomb pickle": (lambda root: (root / "bomb.pkl").write_bytes(reference_bomb()),
                              r"expands to more than 20,000,000 values"),
    "polyline point at 1e9 m": (lambda root: None, r"has a segment of 1,000,000,000 m"),
}


@pytest.fixture(scope="module")
def memory_run(tmp_path_factory) -> dict:  # type: ignore[no-untyped-def]
    """Every memory case in one subprocess (one import of torch) whose address space is capped at 6 GiB (torch
    maps about 2 GiB at import; the failures these cases caused asked for 9 to 21 GiB): per case the outcome,
    and the process's peak resident memory."""
    roots = {}
    for index, (case, (edit, _)) in enumerate(MEMORY_CASES.items()):
        root = scene_copy(tmp_path_factory.mktemp(f"memory{index}"))
        edit(root)
        roots[case] = str(root)
    code = MEMORY_CHILD.replace("CAP", str(6 * 2**30)).replace("SCENE", repr(SCENE))
    run = subprocess.run([sys.executable, "-c", code, json.dumps(roots)], capture_output=True, text=True,
                         timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout + run.stderr[-2000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", list(MEMORY_CASES))
def test_bad_data_is_refused_early_with_bounded_memory(case: str, memory_run: dict) -> None:
    outcome = memory_run["outcomes"][case]
    assert outcome.startswith("refused: ") and re.search(MEMORY_CASES[case][1], outcome), outcome
    assert memory_run["peak_mb"] < PEAK_LIMIT_MB, f"peak {memory_run['peak_mb']:.0f} MB"


# --------------------------------------------------------------------------------------------- CLI options
CLI_CASES = {
    "--out is a file": (["evaluate", "--model", "constant_velocity", "--scenes", "1", "--out", "{file}"],
                        r"--out '.+' is a file, not a folder"),
    "--checkpoint for a model that loads none": (["evaluate", "--model", "constant_velocity", "--checkpoint",
                                                  "{folder}", "--scenes", "1"], r"takes no option 'checkpoint'"),
    "--checkpoint unknown name": (["evaluate", "--checkpoint", "ctg-alinged", "--scenes", "1"],
                                  r"is neither a folder nor a bundled checkpoint"),
    "--seeds repeated": (["evaluate", "--model", "constant_velocity", "--seeds", "1,1", "--json"],
                         r"--seeds '1,1': give distinct comma-separated integers"),
    "--late-agents unknown": (["evaluate", "--model", "constant_velocity", "--late-agents", "keep"],
                              r"Invalid value for '--late-agents'"),
    "checkpoint-digest of no folder": (["checkpoint-digest", "{folder}/nothing"], r"checkpoint folder not found"),
}


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_bad_command_line_options_exit_2_before_any_work(case: str, tmp_path: Path, capsys) -> None:
    (tmp_path / "file").write_text("keep me")
    (tmp_path / "folder").mkdir()
    args, message = CLI_CASES[case]
    args = [a.replace("{file}", str(tmp_path / "file")).replace("{folder}", str(tmp_path / "folder")) for a in args]
    before = snapshot(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    captured = capsys.readouterr()
    assert exit_info.value.code == 2, captured.err
    assert re.search(message, captured.err), captured.err
    assert "simulating" not in captured.err and "Traceback" not in captured.err
    assert snapshot(tmp_path) == before


def test_more_scenes_than_the_split_has_says_how_many_ran(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    root = scene_copy(tmp_path)  # a split of one scene
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--model", "constant_velocity", "--root", str(root), "--scenes", "100", "--json"])
    captured = capsys.readouterr()
    assert exit_info.value.code == 0
    assert "--scenes 100 asked for more than the 1 long-enough scenes of nuscenes_pred/val" in captured.err
    assert json.loads(captured.out)["num_scenes"] == 1

# --------------------------------------------------------------------------------------- adapter contract
def _no_grad_log_prob(adapter) -> None:  # type: ignore[no-untyped-def]
    inner = adapter.log_prob

    def log_prob(context, trace):  # type: ignore[no-untyped-def]
        with torch.no_grad():
            return inner(context, trace)
    adapter.log_prob = log_prob


def _squeezed_trace(adapter) -> None:  # type: ignore[no-untyped-def]
    inner = adapter.sample

    def sample(context, num_samples, guidance=None, generator=None):  # type: ignore[no-untyped-def]
        out = inner(context, num_samples, guidance, generator)
        out.trace.tensors = {k: v.flatten(0, 1) for k, v in out.trace.tensors.items()}
        return out
    adapter.sample = sample


ADAPTER_CASES = {
    "log_prob without gradient": (_no_grad_log_prob, r"log_prob\(\) returns a tensor without gradient"),
    "trace of the wrong shape": (_squeezed_trace, r"trace tensor '.+' has shape .* expected leading dims"),
}


@pytest.mark.parametrize("case", list(ADAPTER_CASES))
def test_check_adapter_catches_what_breaks_alignment(case: str, val_scenes, make_gru_adapter) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.testing.check_adapter import AdapterCheckError, check_adapter

    adapter = make_gru_adapter()
    edit, message = ADAPTER_CASES[case]
    edit(adapter)
    with pytest.raises(AdapterCheckError, match=message):
        check_adapter(adapter, val_scenes[:2], check_save_load=False)


# ------------------------------------------------------------------------------------------- interrupts
FAST_ALIGN = dict(epochs=3, contexts_per_epoch=2, samples_per_context=2, minibatch_contexts=2, ppo_epochs=1,
                  progress_bar=False, save_every=10)


def _slow_down_reward():  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.testing.rewards import SlowDownReward

    return SlowDownReward()


def _interrupt(kind: str) -> Callable[[int, dict], None]:
    def callback(epoch: int, stats: dict) -> None:
        if epoch == 0:
            if kind == "SIGTERM":
                os.kill(os.getpid(), signal.SIGTERM)
            raise KeyboardInterrupt
    return callback


@pytest.mark.parametrize("kind", ["Ctrl-C", "SIGTERM"])
def test_interrupted_align_keeps_its_finished_epochs(kind: str, val_scenes, make_gru_adapter, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.alignment import align

    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        align(make_gru_adapter(), _slow_down_reward(), alpha=1.0, scenes=val_scenes[:2], output_dir=str(out),
              callback=_interrupt(kind), **FAST_ALIGN)
    assert sorted(os.listdir(out / "checkpoints")) == ["checkpoint-1"]  # save_every=10 would have kept nothing
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is put back


def test_resume_without_a_checkpoint_says_so(val_scenes, make_gru_adapter, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.alignment import align

    message = r"resume: no checkpoint in '.+checkpoints' \(no checkpoint-N .*drop --resume"
    with pytest.raises(TrafficRLHFError, match=message):
        align(make_gru_adapter(), _slow_down_reward(), alpha=1.0, scenes=val_scenes[:2],
              output_dir=str(tmp_path / "none"), resume=True, **FAST_ALIGN)
    assert not (tmp_path / "none" / "checkpoints").exists()


def test_resume_falls_back_to_an_intact_checkpoint_and_refuses_changed_settings(val_scenes, make_gru_adapter,  # type: ignore[no-untyped-def]
                                                                               tmp_path) -> None:
    from trafficrlhf_sdk.alignment import align

    out = tmp_path / "run"
    settings = {**FAST_ALIGN, "save_every": 1}
    align(make_gru_adapter(), _slow_down_reward(), alpha=1.0, scenes=val_scenes[:2], output_dir=str(out),
          callback=lambda epoch, stats: epoch < 1, **settings)  # stops after two epochs
    assert sorted(os.listdir(out / "checkpoints")) == ["checkpoint-1", "checkpoint-2"]
    (out / "checkpoints" / "checkpoint-2" / "model.safetensors").write_bytes(b"")  # the newest is broken
    before = snapshot(out / "checkpoints" / "checkpoint-1")
    with pytest.raises(TrafficRLHFError, match=r"changed hyper-parameter\(s\) .*learning_rate: 0.0001 -> 0.001"):
        align(make_gru_adapter(), _slow_down_reward(), alpha=1.0, scenes=val_scenes[:2], output_dir=str(out),
              resume=True, **{**settings, "learning_rate": 1e-3})
    assert snapshot(out / "checkpoints" / "checkpoint-1") == before
    with pytest.warns(UserWarning, match=r"checkpoint-2' is broken"):
        result = align(make_gru_adapter(), _slow_down_reward(), alpha=1.0, scenes=val_scenes[:2],
                       output_dir=str(out), resume=True, resume_allow_changes=True,
                       **{**settings, "learning_rate": 1e-3})
    assert len(result.history) == 3  # epoch 1 from the intact checkpoint, then epochs 2 and 3
    state = json.loads((out / "checkpoints" / "checkpoint-3" / "trainer_state.json").read_text())
    assert state["config_changes"] == [{"from_epoch": 2, "changes": {"learning_rate": [0.0001, 0.001]}}]


def test_an_adapter_plans_for_a_scene_with_nobody_left_to_drive(val_scenes, make_gru_adapter) -> None:  # type: ignore[no-untyped-def]
    """When no controlled agent is present at the replanning step (their logged tracks ended), the plan holds
    every agent's course instead of asking the model to sample zero agents."""
    adapter = make_gru_adapter()
    scene = val_scenes[:2]
    now = scene.current_index
    empty = scene.replace_unchecked(controlled=torch.zeros_like(scene.controlled))
    plan = adapter.plan(empty, 12)
    assert plan.states.shape == (2, scene.num_agents, 12, 4) and torch.isfinite(plan.states).all()
    speed = scene.states[:, :, now, 2]
    moved = (plan.states[:, :, 0, :2] - scene.states[:, :, now, :2]).norm(dim=-1)
    assert torch.allclose(moved, speed.abs() * scene.dt, atol=1e-4)
