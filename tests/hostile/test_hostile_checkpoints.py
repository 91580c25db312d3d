"""Hostile checkpoints: a traffic-model checkpoint (``ctg_small``) and a reward-model folder
(``ctg_no_collision``) edited the way an attacker would, generated with hypothesis: safetensors files truncated,
with bytes overwritten, with a forged header length or header (dtype, shape, offsets, metadata), weights scaled to
huge or tiny finite values, ``config.json`` with a value replaced, a key removed or added, or the file replaced
by raw bytes (empty, not UTF-8, a nesting bomb, a 5,000-digit number), and files swapped for a folder, a FIFO or a
link to ``/dev/zero``. The digest recorded in ``config.json`` is recomputed after most edits, as an attacker
would, so the checks behind it are reached.

Traffic checkpoints run ``evaluate --checkpoint DIR`` on one scene; reward models run ``rm info DIR`` and, for
the weight edits, ``evaluate --reward-model DIR``.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import pytest
from hostile_harness import case_param, ForkServer, assert_handled, draw, record
from hostile_inputs import ROOT, check_evaluate, one_scene_root
from hypothesis import strategies as st

from trafficrlhf_sdk.models.checkpoint import sha256_file

CTG_SMALL = ROOT / "reference_models" / "ctg" / "checkpoints" / "ctg_small"
REWARD = ROOT / "reference_models" / "reward" / "ctg_no_collision"

JSON_VALUES = [None, True, -1, 0, 1, 2**31, 2**63, -(2**63), 1e308, -1e308, 1e-308, 0.5, "", "x", "NaN", [], [0],
               [-5], [1e9, 1e9], {}, {"a": 1}, "../../etc/passwd", "/dev/zero", "\u202e", "a" * 10000]
DTYPES = ["F16", "BF16", "F64", "I64", "I8", "U8", "BOOL", "F8_E4M3", "C64", "XX", "", 7]
SHAPES = [[], [0], [-1], [2**40, 2**40], [1, 1, 1, 1, 1, 1, 1, 1, 1], [3]]
RAW_CONFIGS = [b"", b"\xff\xfe\x00{", b"\xef\xbb\xbf{}", b"[" * 100000 + b"]" * 100000, b'{"a": ' + b"1" * 5000 + b"}",
               b"null", b'"text"', b"{\"adapter\": \"ctg\", \"adapter\": \"bits\"}", b"{} {}", b"\x00" * 64]

# (operation, argument): hypothesis draws the argument for each operation
OPERATIONS = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 0.999)),
    st.tuples(st.just("overwrite"), st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=16))),
    st.tuples(st.just("overwrite header"), st.tuples(st.integers(8, 400), st.binary(min_size=1, max_size=8))),
    st.tuples(st.just("header length"), st.sampled_from([0, 1, 7, 2**63 - 1, 2**32, 10**8, -1, "size", "size+1"])),
    st.tuples(st.just("dtype"), st.sampled_from(DTYPES)),
    st.tuples(st.just("shape"), st.sampled_from(SHAPES)),
    st.tuples(st.just("offsets"), st.sampled_from([[0, 0], [10, 0], [0, 2**62], [-8, 8], "overlap", ["a", 1]])),
    st.tuples(st.just("metadata"), st.sampled_from([{"format": "np"}, {"format": 1}, {"x": "y" * 100000}, []])),
    st.tuples(st.just("scale"), st.sampled_from([1e30, -1e30, 1e38, 1e-30, 0.0, 1e4])),
    st.tuples(st.just("config value"), st.tuples(st.integers(0, 10**6), st.sampled_from(JSON_VALUES))),
    st.tuples(st.just("config drop"), st.integers(0, 10**6)),
    st.tuples(st.just("config add"), st.tuples(st.sampled_from(["config", "top"]), st.sampled_from(JSON_VALUES))),
    st.tuples(st.just("raw config"), st.sampled_from(RAW_CONFIGS)),
    st.tuples(st.just("swap"), st.sampled_from(["weights folder", "weights fifo", "weights /dev/zero",
                                                "config folder", "config /dev/zero", "config missing"])),
)


def _copy(source: Path, dest: Path) -> Path:
    dest.mkdir()
    for name in ("config.json", "model.safetensors"):
        (dest / name).write_bytes((source / name).read_bytes())
    return dest


def _header(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    (length,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + length]), data[8 + length:]


def _write_header(path: Path, header: dict, body: bytes) -> None:
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + body)


def _config_paths(config: object, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a JSON object (nested objects included)."""
    paths = []
    if isinstance(config, dict):
        for key, value in config.items():
            paths.append((*prefix, key))
            paths += _config_paths(value, (*prefix, key))
    return paths


def apply(folder: Path, operation: str, argument: object) -> bool:
    """Edit ``folder`` in place; returns whether the weights digest in config.json should be recomputed."""
    weights, config_path = folder / "model.safetensors", folder / "config.json"
    size = weights.stat().st_size
    if operation == "truncate":
        weights.write_bytes(weights.read_bytes()[: int(size * float(argument))])
    elif operation in ("overwrite", "overwrite header"):
        where, patch = argument
        data = bytearray(weights.read_bytes())
        start = int(where) if operation == "overwrite header" else min(int(float(where) * size), size - len(patch))
        data[start:start + len(patch)] = patch
        weights.write_bytes(bytes(data))
    elif operation == "header length":
        data = weights.read_bytes()
        value = {"size": size, "size+1": size + 1}.get(argument, argument)  # type: ignore[arg-type]
        weights.write_bytes(struct.pack("<q" if value == -1 else "<Q", value) + data[8:])
    elif operation in ("dtype", "shape", "offsets", "metadata"):
        header, body = _header(weights)
        name = sorted(k for k in header if k != "__metadata__")[0]
        if operation == "dtype":
            header[name]["dtype"] = argument
        elif operation == "shape":
            header[name]["shape"] = argument
        elif operation == "offsets":
            second = sorted(k for k in header if k != "__metadata__")[1]
            header[name]["data_offsets"] = header[second]["data_offsets"] if argument == "overlap" else argument
        else:
            header["__metadata__"] = argument
        _write_header(weights, header, body)
    elif operation == "scale":
        from safetensors.torch import load_file, save_file

        tensors = load_file(str(weights))
        save_file({k: (v * float(argument)).to(v.dtype) if v.is_floating_point() else v for k, v in tensors.items()},
                  str(weights), metadata={"format": "pt"})
    elif operation in ("config value", "config drop", "config add"):
        config = json.loads(config_path.read_text())
        if operation == "config add":
            where, value = argument
            (config.get("config", config) if where == "config" else config)["unexpected_key"] = value
        else:
            paths = [p for p in _config_paths(config) if p[0] != "weights"] or _config_paths(config)
            path = paths[(argument[0] if operation == "config value" else argument) % len(paths)]
            parent = config
            for key in path[:-1]:
                parent = parent[key]
            if operation == "config value":
                parent[path[-1]] = argument[1]
            else:
                del parent[path[-1]]
        config_path.write_text(json.dumps(config))
        return False
    elif operation == "raw config":
        config_path.write_bytes(argument)  # type: ignore[arg-type]
        return False
    elif operation == "sparse":  # a header declaring one huge tensor, over a sparse file of that size
        header, _ = _header(weights)
        name = sorted(k for k in header if k != "__metadata__")[0]
        count = int(argument) // 4  # type: ignore[call-overload]
        header = {name: {"dtype": "F32", "shape": [count], "data_offsets": [0, count * 4]}}
        _write_header(weights, header, b"")
        with open(weights, "r+b") as f:
            f.truncate(f.seek(0, 2) + count * 4)
        config = json.loads(config_path.read_text())  # hashing 22 GiB takes minutes: a made-up digest
        config.setdefault("weights", {}).update(sha256="0" * 64, bytes=weights.stat().st_size)
        config_path.write_text(json.dumps(config))
        return False
    elif operation == "swap":
        target = weights if argument.startswith("weights") else config_path
        target.unlink()
        if argument.endswith("folder"):
            target.mkdir()
        elif argument.endswith("fifo"):
            os.mkfifo(target)
        elif argument.endswith("/dev/zero"):
            target.symlink_to("/dev/zero")
        return False
    return True


def record_digest(folder: Path) -> None:
    """Recompute the weights' SHA-256 and size in config.json (what an attacker who edits the weights does)."""
    config = json.loads((folder / "config.json").read_text())
    weights = folder / "model.safetensors"
    config.setdefault("weights", {}).update(sha256=sha256_file(str(weights)), bytes=weights.stat().st_size)
    (folder / "config.json").write_text(json.dumps(config))


def check_rm_info(stdout: str, stderr: str) -> str | None:
    """``rm info`` of a loadable model says its weights are ok and gives a size."""
    return None if "weights ok" in stdout and "parameters" in stdout else "no 'weights ok' line"


GENERATED = draw(st.tuples(st.sampled_from(["checkpoint", "reward model"]), OPERATIONS), 150, 73)
GENERATED += [(target, operation) for target in ("checkpoint", "reward model")  # the reproductions
              for operation in (("scale", 1e30), ("sparse", 22 * 2**30))]

# Results that an edit can leave correct: a valid checkpoint after the edit (evaluated and checked).
KNOWN: dict[str, str] = {}


def _params(large: bool) -> list:
    params, small_ops = [], set()
    for index, (target, (operation, argument)) in enumerate(GENERATED):
        key = (target, operation)
        is_small = key not in small_ops and operation in ("truncate", "dtype", "raw config", "header length", "sparse")
        small_ops.add(key)
        if not (large or is_small):
            continue
        case_id = f"{target}-{operation}-{index}"
        params.append(case_param(target, operation, argument, case_id=case_id, large=large, known=KNOWN))
    return params


@pytest.mark.parametrize(("target", "operation", "argument"), _params(False) + _params(True))
def test_hostile_checkpoint(target: str, operation: str, argument: object, fork_server: ForkServer,
                            nuscenes_root: Path, tmp_path: Path, workdir: Path) -> None:
    folder = _copy(CTG_SMALL if target == "checkpoint" else REWARD, tmp_path / "model")
    if apply(folder, operation, argument):
        record_digest(folder)
    root = one_scene_root(tmp_path, nuscenes_root)
    described = f"{target}: {operation} {argument!r}"[:200]
    if target == "checkpoint":
        args = ["evaluate", "--checkpoint", folder, "--root", root, "--scenes", "1", "--duration", "1", "--json"]
        outcome = fork_server.run("checkpoints", described, args, workdir, check_evaluate, inputs=[folder])
    else:
        outcome = fork_server.run("reward models", described, ["rm", "info", folder], workdir, check_rm_info,
                                  inputs=[folder], keep=False)
        if outcome.kind == "correct" and operation in ("scale", "overwrite", "truncate", "sparse"):
            # weights that load must also score: the case's outcome is that of the evaluation
            args = ["evaluate", "--model", "constant_velocity", "--reward-model", folder, "--root", root,
                    "--scenes", "1", "--duration", "1", "--json"]
            outcome = fork_server.run("reward models", described + " (evaluate)", args, workdir, check_evaluate,
                                      inputs=[folder], keep=False)
        record(outcome)
    assert_handled(outcome)
