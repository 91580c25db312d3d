"""Hostile ScenarioNet pickles: a small synthetic scenario (a straight road, three vehicles, 12 s at 10 Hz) in
ScenarioNet's layout, edited the way a broken converter or an attacker would, generated with hypothesis: one
field (a track's positions, headings, sizes or valid flags, the scenario length, the sample rate, the SDC id, a
map polyline, a feature type) replaced by a hostile value (NaN, infinities, far positions, wrong shapes and
dtypes, wrong types, empty containers), a key removed, tracks multiplied or shared by reference, and the pickle
bytes truncated, overwritten or replaced by a pickle that names a forbidden global or expands by shared references.

Every case runs ``evaluate --source scenarionet --root DIR --scenes 1 --duration 1``; a run that exits 0 must
score at least one agent with finite rates.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest
from hostile_harness import case_param, ForkServer, assert_handled, draw
from hostile_inputs import check_evaluate
from hypothesis import strategies as st

ORIGIN = np.array([500.0, 800.0])
LENGTH = 120


def vehicle(x0: float, lane_y: float, speed: float) -> dict:
    """One vehicle track driving along +x at ``speed`` m/s."""
    t = np.arange(LENGTH) * 0.1
    xy = np.stack([ORIGIN[0] + x0 + speed * t, ORIGIN[1] + lane_y + 0 * t], 1)
    ones = np.ones(LENGTH)
    return {"type": "VEHICLE", "metadata": {"type": "vehicle"}, "state": {
        "position": np.concatenate([xy, np.zeros((LENGTH, 1))], 1), "heading": 0 * ones,
        "velocity": np.stack([speed * ones, 0 * ones], 1), "valid": ones,
        "length": np.full((LENGTH, 1), 4.5), "width": np.full((LENGTH, 1), 1.9), "height": np.full((LENGTH, 1), 1.5)}}


def scenario() -> dict:
    """The unedited scenario: three vehicles on a two-lane road."""
    def lane(y: float) -> np.ndarray:
        return np.array([[-100.0, y, 0.0], [300.0, y, 0.0]]) + [*ORIGIN, 0.0]

    def box(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) + ORIGIN

    return {"id": "hostile", "version": "test", "length": LENGTH, "dynamic_map_states": {},
            "metadata": {"dataset": "synthetic", "sample_rate": 0.1, "sdc_id": "ego", "ts": np.arange(LENGTH) * 0.1},
            "tracks": {"ego": vehicle(0.0, 0.0, 6.0), "lead": vehicle(25.0, 0.0, 5.0), "side": vehicle(5.0, 3.5, 7.0)},
            "map_features": {
                "lane_a": {"type": "LANE_SURFACE_STREET", "polyline": lane(0.0),
                           "polygon": box(-100, 300, -1.75, 1.75)},
                "lane_b": {"type": "LANE_SURFACE_STREET", "polyline": lane(3.5),
                           "polygon": box(-100, 300, 1.75, 5.25)},
                "edge": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": lane(-1.75)[:, :2]},
            }}


NUMBERS = [math.nan, math.inf, -math.inf, 1e6, -1e6, 1e12, 1e308, 0.0, -1.0]
VALUES = ["nan array", "inf array", "far array", "empty array", "1-D array", "3-D array", "string array",
          "object array", "complex array", "list", "None", "string", "dict", "int", "huge shape"]
TRACK_FIELDS = ["position", "heading", "velocity", "valid", "length", "width"]
FIELDS = [("length",), ("metadata", "sample_rate"), ("metadata", "sdc_id"), ("metadata", "ts"), ("tracks",),
          ("map_features",), ("map_features", "lane_a", "polyline"), ("map_features", "lane_a", "polygon"),
          ("map_features", "lane_a", "type"), ("tracks", "ego", "type"), ("tracks", "ego", "state")] + \
         [("tracks", "ego", "state", f) for f in TRACK_FIELDS] + [("tracks", "lead", "state", f) for f in TRACK_FIELDS]

EDITS = st.one_of(
    st.tuples(st.just("value"), st.tuples(st.sampled_from(FIELDS), st.sampled_from(VALUES))),
    st.tuples(st.just("number"), st.tuples(st.sampled_from(FIELDS[:3]), st.sampled_from(NUMBERS + [10**12, -5, 0]))),
    st.tuples(st.just("point"), st.tuples(st.sampled_from(["ego", "lead"]), st.integers(0, LENGTH - 1),
                                          st.sampled_from(NUMBERS))),
    st.tuples(st.just("drop"), st.sampled_from(FIELDS)),
    st.tuples(st.just("tracks"), st.tuples(st.sampled_from(["copies", "shared"]), st.sampled_from([50, 500, 2000]))),
    st.tuples(st.just("truncate"), st.floats(0.0, 0.99)),
    st.tuples(st.just("overwrite"), st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=8))),
    st.tuples(st.just("protocol"), st.integers(0, 5)),
    st.tuples(st.just("raw"), st.sampled_from(["os.system", "builtins.eval", "subprocess", "numpy frombuffer",
                                               "reference bomb", "not a pickle", "empty", "a list", "deep nesting"])),
)


def _hostile_value(name: str, like: object) -> object:
    shape = np.shape(like) if isinstance(like, np.ndarray) else (LENGTH, 2)
    return {"nan array": lambda: np.full(shape, np.nan), "inf array": lambda: np.full(shape, np.inf),
            "far array": lambda: np.full(shape, 1e9), "empty array": lambda: np.zeros((0,)),
            "1-D array": lambda: np.zeros(7), "3-D array": lambda: np.zeros((2, 3, 4)),
            "string array": lambda: np.array(["x"] * 4), "object array": lambda: np.array([None, {}, []], dtype=object),
            "complex array": lambda: np.ones(shape, dtype=np.complex128), "list": lambda: [1, [2, [3]]],
            "None": lambda: None, "string": lambda: "VEHICLE\x00", "dict": lambda: {"a": {"b": 1}}, "int": lambda: 7,
            "huge shape": lambda: np.zeros((500_000, 2))}[name]()  # 8 MB: inputs stay under 10 MB


def _at(data: dict, path: tuple) -> tuple[dict, object]:
    parent = data
    for key in path[:-1]:
        parent = parent[key]
    return parent, path[-1]


def _raw(kind: str) -> bytes:
    if kind == "os.system":
        return b"cos\nsystem\n(S'touch pwned'\ntR."
    if kind == "builtins.eval":
        return b"cbuiltins\neval\n(S'__import__(\"os\").system(\"touch pwned\")'\ntR."
    if kind == "subprocess":
        return b"csubprocess\ncheck_output\n((S'touch'\nS'pwned'\nltR."
    if kind == "numpy frombuffer":  # an allowed-looking global asked for a huge array
        return b"cnumpy\nzeros\n(I4000000000\ntR."
    if kind == "reference bomb":
        inner = [0.0] * 1000
        return pickle.dumps({"tracks": {}, "map_features": [[inner] * 1000] * 1000}, protocol=4)
    if kind == "not a pickle":
        return b"PK\x03\x04 this is a zip file"
    if kind == "empty":
        return b""
    if kind == "a list":
        return pickle.dumps([1, 2, 3])
    nested: list = []
    for _ in range(50_000):
        nested = [nested]
    return b"(" * 200_000 + b"l" * 200_000 + b"."


def build(operation: str, argument: object) -> bytes:
    data = scenario()
    protocol = 4
    if operation == "value":
        path, name = argument  # type: ignore[misc]
        parent, key = _at(data, path)
        parent[key] = _hostile_value(name, parent.get(key))
    elif operation == "number":
        path, number = argument  # type: ignore[misc]
        parent, key = _at(data, path)
        parent[key] = number
    elif operation == "point":
        track, step, number = argument  # type: ignore[misc]
        data["tracks"][track]["state"]["position"][step, 0] = number
    elif operation == "drop":
        parent, key = _at(data, argument)  # type: ignore[arg-type]
        del parent[key]
    elif operation == "tracks":
        how, count = argument  # type: ignore[misc]
        for i in range(count if how == "shared" else min(count, 900)):  # 900 copies: a 9 MB pickle
            data["tracks"][f"copy{i}"] = data["tracks"]["lead"] if how == "shared" else vehicle(30.0 + i, 0.0, 5.0)
    elif operation == "protocol":
        protocol = int(argument)  # type: ignore[call-overload]
    elif operation == "raw":
        return _raw(str(argument))
    blob = pickle.dumps(data, protocol=protocol)
    if operation == "truncate":
        blob = blob[: int(len(blob) * float(argument))]  # type: ignore[arg-type]
    elif operation == "overwrite":
        where, patch = argument  # type: ignore[misc]
        start = min(int(float(where) * len(blob)), len(blob) - len(patch))
        blob = blob[:start] + patch + blob[start + len(patch):]
    return blob


GENERATED = [("protocol", 4)] + draw(EDITS, 100, 73)
GENERATED += [("point", ("ego", 60, 1e6)), ("tracks", ("shared", 2000)), ("number", (("length",), 10**12))]

KNOWN: dict[str, str] = {}  # open failures, each with its command; strict: a fix turns them into passes to un-mark


def _params(large: bool) -> list:
    params, seen = [], set()
    for index, (operation, argument) in enumerate(GENERATED):
        is_small = operation not in seen and operation in ("protocol", "value", "tracks", "truncate", "raw", "point")
        seen.add(operation)
        if not (large or is_small):
            continue
        case_id = f"scenarionet-{operation}-{index}"
        params.append(case_param(operation, argument, case_id=case_id, large=large, known=KNOWN))
    return params


@pytest.mark.parametrize(("operation", "argument"), _params(False) + _params(True))
def test_hostile_scenarionet_pickle(operation: str, argument: object, fork_server: ForkServer, tmp_path: Path,
                                    workdir: Path) -> None:
    root = tmp_path / "scenarionet"
    root.mkdir()
    (root / "sd_hostile.pkl").write_bytes(build(operation, argument))
    args = ["evaluate", "--model", "constant_velocity", "--source", "scenarionet", "--root", root, "--split", "all",
            "--scenes", "1",
            "--duration", "1", "--json"]
    described = f"pickle: {operation} {argument!r}"[:200]
    outcome = fork_server.run("ScenarioNet pickles", described, args, workdir,
                              None if operation == "raw" else check_evaluate, inputs=[root])
    assert_handled(outcome)
    assert not (workdir / "pwned").exists()
    if (operation, argument) == GENERATED[0]:
        assert outcome.kind == "correct", "the unedited scenario must evaluate: " + outcome.explain()
