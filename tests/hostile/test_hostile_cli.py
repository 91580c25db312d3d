"""Hostile command lines: one option (or argument) of a working ``trafficrlhf`` command replaced by a hostile
value, generated with hypothesis from a pool of values that break parsers (empty, signs, NaN, huge numbers,
long strings, control and bidirectional characters, device files, path traversal, JSON where text is expected).

A value the command accepts must give a correct result: ``evaluate`` prints JSON with at least one scene and one
controlled agent and finite rates, ``inspect`` counts the scene, ``render scene`` writes a PNG. ``--workers`` and
``--ray-address`` are left out (a valid value starts a Ray cluster).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
from hostile_harness import ForkServer, case_param, assert_handled, draw, run_executable
from hostile_inputs import SCENE, check_evaluate, one_scene_root
from hypothesis import strategies as st

CATEGORY = "CLI arguments"

VALUES = ["", " ", "-1", "0", "-0", "1", "2.5", "1e309", "-1e309", "nan", "NaN", "inf", "-inf", "1e-320",
          "99999999999999999999999", "0x10", "\uff11", "1,1", "1,,2", ",", "a" * 5000, "../../../../etc/passwd",
          "/dev/zero", "/dev/null", "/proc/self/mem", "-", "--json", "'; rm -rf ~", "%s%n%x", "{}", "[]", "null",
          "true", "\u202eevil", "sc\u00e8ne", "\U0001f697", "\x7f\x1b[2J", "\t", "{file}", "{dir}", "{missing}",
          "{root}", "=", "k=", "=v", "k=v", "plan_samples=1e9", "plan_samples=-3", "stationary_rule=[1]"]

Check = "Callable[[str, str], str | None]"


def check_architectures(stdout: str, stderr: str) -> str | None:
    """``rm info`` without a folder: the registered architectures."""
    try:
        listed = json.loads(stdout)
    except json.JSONDecodeError:
        return "stdout is not JSON" if stdout.lstrip().startswith(("[", "{")) else \
            (None if "ctg_mlp" in stdout else "no architecture listed")
    ok = isinstance(listed, list) and any(row.get("architecture") == "ctg_mlp" for row in listed)
    return None if ok else "not the list of architectures"


def check_inspect(stdout: str, stderr: str) -> str | None:
    """``inspect --json``: the one scene."""
    try:
        result = json.loads(stdout)
    except json.JSONDecodeError:
        return "stdout is not JSON"
    text = json.dumps(result)
    return None if SCENE in text or '"num_scenes": 1' in text else "the scene is not listed"


@dataclass(frozen=True)
class Command:
    """A working command line and the options a case may replace."""

    base: tuple[str, ...]
    options: tuple[str, ...]
    check: str | None


COMMANDS = {
    "evaluate": Command(("evaluate", "--model", "constant_velocity", "--root", "{root}", "--scenes", "1", "--json"),
                        ("--model", "--source", "--split", "--root", "--scenes", "--scene-id", "--guidance",
                         "--checkpoint", "--seed", "--seeds", "--batch-size", "--out", "--reward-model",
                         "--worst-scenes", "--model-option", "--late-agents", "--after-log-end", "--rollouts",
                         "--duration"), "evaluate"),
    "inspect": Command(("inspect", "nuscenes_pred", "--root", "{root}", "--json"),
                       ("--split", "--root", "--scenes", "SOURCE"), "inspect"),
    "render scene": Command(("render", "scene", "nuscenes_pred", SCENE, "--root", "{root}", "-o", "{out}.png"),
                            ("--split", "--step", "--dpi", "-o", "SCENE"), "png"),
    "render compare": Command(("render", "compare", "--model", "constant_velocity", "--model", "constant_velocity",
                               "--root", "{root}", "--scenes", "1", "--out", "{out}"),
                              ("--scenes", "--scene-id", "--worst", "--seed", "--batch-size", "--duration",
                               "--frame-hz", "--speed", "--dpi", "--out", "--guidance", "--model-option"), "compare"),
    "rm info": Command(("rm", "info"), ("MODEL_DIR",), "architectures"),
    "compare": Command(("compare",), ("FOLDERS",), None),
    "checkpoint-digest": Command(("checkpoint-digest",), ("FOLDERS",), None),
    "feedback status": Command(("feedback", "status", "--db", "{missing}.db"), ("--db", "--campaign"), None),
}


def _build(command: str, option: str, value: str) -> tuple[str, ...]:
    spec = COMMANDS[command]
    args = list(spec.base)
    if option.isupper():  # a positional argument
        if option in ("SOURCE", "SCENE"):
            args[args.index("nuscenes_pred" if option == "SOURCE" else SCENE)] = value
        else:
            args.append(value)
    elif option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    return tuple(args)


GENERATED = draw(st.sampled_from(sorted(COMMANDS)).flatmap(
    lambda c: st.tuples(st.just(c), st.sampled_from(COMMANDS[c].options), st.sampled_from(VALUES))), 130, 73)

HAND = [  # the cases of the issue, and command lines no single replacement produces
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--root", "{root}", "--rollouts", "1000000",
                  "--scenes", "1", "--json"), "evaluate"),
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--root", "{root}", "--duration", "0.6", "--json"),
     None),  # the realism metrics need three samples 0.5 s apart
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--root", "{root}", "--scene-id", SCENE,
                  "--scene-id", SCENE, "--json"), "evaluate"),
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--root", "{root}", "--seeds", "0,1", "--out",
                  "{file}", "--json"), None),
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--root", "{root}", "--duration", "1e6", "--json"),
     None),
    ("evaluate", ("evaluate", "--model", "constant_velocity", "--model", "ctg", "--root", "{root}", "--json"),
     "evaluate"),  # the last --model wins, as with every single-valued option
    ("rm train", ("rm", "train", "--db", "{missing}.db", "--campaign", "c", "--out", "{out}",
                  "--architecture-option", "hidden_sizes=[-5]"), None),
    ("rm train", ("rm", "train", "--data", "{dir}", "--out", "{out}", "--epochs", "0"), None),
    ("align", ("align", "--checkpoint", "ctg-small", "--reward-model", "{missing}", "--out", "{out}",
               "--epochs", "1", "--scenes", "1"), None),
    ("align", ("align", "--config", "{file}", "--out", "{out}"), None),
    ("align", ("align", "--config", "{file}", "--checkpoint", "ctg", "--reward-model", "{missing}", "--out", "{out}"),
     None),  # a recipe of only an [align] table: the reward model of the command line still counts
    ("average", ("average", "{dir}", "{dir}", "--out", "{out}", "--weights", "nan,1"), None),
    ("extrapolate", ("extrapolate", "{dir}", "--base", "{dir}", "--factor", "1e309", "--out", "{out}"), None),
    ("report", ("report", "{missing}"), None),
    ("feedback annotator add", ("feedback", "annotator", "add", "alice", "--db", "{missing}.db"), None),
    ("sources", ("sources", "--json", "--json", "extra"), None),
    ("top level", ("--no-such-option",), None),
    ("top level", ("no-such-command",), None),
]

KNOWN: dict[str, str] = {}

SMALL = {"evaluate", "inspect", "render scene", "render compare", "rm info", "feedback status"}


def _params(large: bool) -> list:
    params, seen_small = [], set()
    for index, (command, option, value) in enumerate(GENERATED):
        is_small = command in SMALL and command not in seen_small and option not in ("--out", "-o", "--scenes")
        if is_small:
            seen_small.add(command)
        if large or is_small:
            case_id = f"{command}-{option}-{index}"
            params.append(case_param(command, _build(command, option, value), COMMANDS[command].check,
                                     case_id=case_id, large=large, known=KNOWN))
    for index, (command, args, check) in enumerate(HAND):
        case_id = f"{command}-hand-{index}"
        if large or index in (0, 1, 6, 13):
            params.append(case_param(command, args, check, case_id=case_id, large=large, known=KNOWN))
    return params


def _fill(args: tuple[str, ...], places: dict[str, Path]) -> list[str]:
    out = []
    for arg in args:
        for key, path in places.items():
            arg = arg.replace("{" + key + "}", str(path))
        out.append(arg)
    return out


@pytest.mark.parametrize(("command", "args", "check"), _params(False) + _params(True))
def test_hostile_command_line(command: str, args: tuple[str, ...], check: str | None, fork_server: ForkServer,
                              nuscenes_root: Path, tmp_path: Path, workdir: Path) -> None:
    root = one_scene_root(tmp_path, nuscenes_root)
    places = {"root": root, "file": tmp_path / "notes.txt", "dir": tmp_path / "empty", "missing": tmp_path / "nope",
              "out": tmp_path / "out"}
    places["file"].write_text("[align]\nepochs = 1\n")
    places["dir"].mkdir()
    filled = _fill(args, places)
    png = Path(filled[filled.index("-o") + 1]) if "-o" in filled[:-1] else None

    def check_png(stdout: str, stderr: str) -> str | None:
        if png is not None and str(png) == "/dev/null":
            return None
        target = png if png is not None and png.is_absolute() else workdir / (png or f"{SCENE}.png")
        if str(png) in ("", "."):
            target = workdir / f"{SCENE}.png"
        if not target.is_file() or target.read_bytes()[:8] != b"\x89PNG\r\n\x1a\n":
            return f"no PNG at {target}"
        return None

    def check_compare(stdout: str, stderr: str) -> str | None:
        out = Path(filled[filled.index("--out") + 1])
        summary = (out if out.is_absolute() else workdir / out) / "side_by_side.json"
        if not summary.is_file():
            return f"no {summary}"
        return None if "failure rate" in stdout else "no failure rates printed"

    checks = {"evaluate": check_evaluate, "inspect": check_inspect, "png": check_png, "compare": check_compare,
              "architectures": check_architectures, None: None}
    outcome = fork_server.run(CATEGORY, f"{command}: {' '.join(args)[:160]}", filled, workdir, checks[check],
                              inputs=[root])
    assert_handled(outcome)


def test_the_console_script_itself_reports_a_bad_option_in_one_line(tmp_path: Path) -> None:
    """The installed executable (not the in-process entry point) on a hostile option."""
    outcome = run_executable(CATEGORY, "console script: evaluate --seeds nan", ["evaluate", "--model",
                             "constant_velocity", "--scenes", "1", "--seeds", "nan", "--json"], tmp_path)
    assert_handled(outcome)
    assert outcome.kind == "clear error"


def test_rollouts_are_capped_before_any_simulation() -> None:
    """K rollouts are all held in memory: a K above 64 is refused by the configuration, not by an allocation."""
    from pydantic import ValidationError

    from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig

    assert EvaluationConfig(rollouts=64).rollouts == 64
    with pytest.raises(ValidationError, match="less than or equal to 64"):
        EvaluationConfig(rollouts=65)
