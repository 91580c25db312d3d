"""The hostile-input harness: run one case in its own process, measure its peak memory, classify the outcome.

A *fork server* (one Python process that imports torch, the CLI and the plugins once) forks one child per
case. The child redirects its stdout and stderr to files, caps its address space, runs ``trafficrlhf ARGS``
in-process through :func:`trafficrlhf_sdk.cli.main` (the console-script entry point) and exits with its exit
code; the server reads the child's peak resident memory from ``wait4`` and kills it past a time limit. A case
costs a fork and the command's own work, not a Python start and a torch import, so the large form fits in a few
minutes on one core. A few cases run the real ``trafficrlhf`` executable instead (:func:`run_executable`), to
cover the console script itself.

Every case ends in one of these outcomes:

- ``clear error``: a nonzero exit whose stderr ends in one ``Error: ...`` paragraph, without a traceback and
  without "internal error";
- ``correct``: exit 0 and the case's own check of the output passes;
- ``silent wrong``: exit 0 but the check fails (empty or garbage output, 0 agents scored), or a hostile input
  that should have been refused was accepted;
- ``unclear error``: a nonzero exit without a one-paragraph ``Error:`` message;
- ``internal error``: a traceback, "internal error", a signal, a memory blow-up or a time-out.

Only ``clear error`` and ``correct`` pass, and only with a peak resident memory under :data:`PEAK_LIMIT_MB`.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from typing import Any
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

PEAK_LIMIT_MB = 1024  # inputs under 10 MB
ADDRESS_CAP_BYTES = 8 * 2**30  # torch maps about 2 GiB at import; a blow-up fails the case, not the machine
CASE_TIMEOUT_S = 90.0
RESULTS_ENV = "TRAFFICRLHF_HOSTILE_RESULTS"  # append every outcome to this JSON-lines file when set

OUTCOMES = ("clear error", "correct", "silent wrong", "unclear error", "internal error")
PASSING = ("clear error", "correct")

SERVER_CODE = textwrap.dedent("""
    import io, json, os, resource, signal, sys, time, traceback
    import torch
    torch.set_num_threads(1)
    from trafficrlhf_sdk.cli import get_cli, main
    get_cli()
    for module in ("trafficrlhf_nuscenes_pred", "trafficrlhf_scenarionet", "trafficrlhf_ctg"):
        try:
            __import__(module)
        except ImportError:
            pass

    def child(spec):
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
        for fd, path in ((1, spec["stdout"]), (2, spec["stderr"])):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
        sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8", line_buffering=True)
        sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8", line_buffering=True)
        resource.setrlimit(resource.RLIMIT_AS, (spec["cap"], spec["cap"]))
        os.chdir(spec["cwd"])
        os.environ.update(spec["env"])
        code = 0
        try:
            main(spec["args"])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            if isinstance(exc.code, str):
                print(exc.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
            code = 70
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        spec = json.loads(line)
        start = time.monotonic()
        pid = os.fork()
        if pid == 0:
            child(spec)
        timed_out = False
        while True:
            done, status, usage = os.wait4(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() - start > spec["timeout"]:
                os.kill(pid, signal.SIGKILL)
                done, status, usage = os.wait4(pid, 0)
                timed_out = True
                break
            time.sleep(0.005)
        code = os.waitstatus_to_exitcode(status)
        print(json.dumps({"code": code, "peak_mb": usage.ru_maxrss / 1024, "seconds": time.monotonic() - start,
                          "timed_out": timed_out}), flush=True)
""")


@dataclass
class Outcome:
    """What one case did: its exit code, output, peak memory and classified outcome."""

    category: str
    case: str
    command: str
    code: int | None
    stdout: str
    stderr: str
    peak_mb: float
    seconds: float
    kind: str = ""
    why: str = ""
    input_bytes: int = 0

    @property
    def passed(self) -> bool:
        """A clear error or a correct result, under the memory bound."""
        return self.kind in PASSING and self.peak_mb < PEAK_LIMIT_MB

    def explain(self) -> str:
        """A short account for an assertion message."""
        tail = "\n".join(self.stderr.strip().splitlines()[-6:])
        return (f"[{self.kind}] {self.why} | exit {self.code}, peak {self.peak_mb:.0f} MB, {self.seconds:.1f} s\n"
                f"  $ {self.command}\n  stderr: {tail[:1500]}\n  stdout: {self.stdout.strip()[:400]}")


Check = Callable[[str, str], "str | None"]  # (stdout, stderr) -> None when the output is right, else what is wrong


def error_message(stderr: str) -> str | None:
    """The final ``Error: ...`` paragraph of ``stderr``, or None when stderr does not end in one."""
    paragraphs = [p.strip() for p in re.split(r"\n\s*\n", stderr.strip()) if p.strip()]
    if not paragraphs:
        return None
    lines = paragraphs[-1].splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith("Error:")]
    if not starts:
        return None
    message = " ".join(line.strip() for line in lines[starts[-1]:])
    return message if len(message) > len("Error: ") + 8 else None


def classify(outcome: Outcome, check: Check | None, timed_out: bool = False) -> Outcome:
    """Fill ``kind`` and ``why`` of ``outcome`` (see the module docstring)."""
    text = outcome.stdout + outcome.stderr
    if timed_out:
        outcome.kind, outcome.why = "internal error", f"no answer within {CASE_TIMEOUT_S:.0f} s"
    elif outcome.code is not None and outcome.code < 0:
        outcome.kind, outcome.why = "internal error", f"killed by signal {-outcome.code}"
    elif "Traceback (most recent call last)" in text:
        outcome.kind, outcome.why = "internal error", "a traceback"
    elif re.search(r"internal error|MemoryError", text, re.IGNORECASE):
        outcome.kind, outcome.why = "internal error", "an internal error"
    elif outcome.code != 0:
        message = error_message(outcome.stderr)
        if message is None:
            outcome.kind, outcome.why = "unclear error", "a nonzero exit without one 'Error:' paragraph"
        else:
            outcome.kind, outcome.why = "clear error", message[:300]
    elif check is None:
        outcome.kind, outcome.why = "silent wrong", "exit 0 on an input that should have been refused"
    else:
        problem = check(outcome.stdout, outcome.stderr)
        outcome.kind, outcome.why = ("correct", "exit 0, output checked") if problem is None else \
            ("silent wrong", problem)
    if outcome.kind in PASSING and outcome.peak_mb >= PEAK_LIMIT_MB:
        outcome.why += f" (but peak {outcome.peak_mb:.0f} MB)"
    return outcome


def record(outcome: Outcome) -> None:
    """Append ``outcome`` to the results file named by ``TRAFFICRLHF_HOSTILE_RESULTS`` (when set)."""
    path = os.environ.get(RESULTS_ENV)
    if path:
        row = asdict(outcome)
        row["stdout"], row["stderr"] = row["stdout"][-500:], row["stderr"][-1000:]
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(row) + "\n")


def _stored(path: Path) -> int:
    stat = path.stat()
    return min(stat.st_size, stat.st_blocks * 512)  # a sparse file counts by the blocks it holds


def folder_bytes(paths: Sequence[Path]) -> int:
    """Total stored size of the regular files under ``paths`` (the input size the memory bound is stated for)."""
    total = 0
    for path in paths:
        if path.is_file():
            total += _stored(path)
        elif path.is_dir():
            total += sum(_stored(p) for p in path.rglob("*") if p.is_file())
    return total


@dataclass
class ForkServer:
    """The fork server process (see the module docstring); one per test session."""

    proc: subprocess.Popen[str] | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)
    scratch: str = field(default_factory=lambda: tempfile.mkdtemp(prefix="hostile-"))

    def start(self) -> ForkServer:
        """Start the server and wait until it has imported everything."""
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
        env.pop("TRAFFICRLHF_DEBUG", None)
        self.proc = subprocess.Popen([sys.executable, "-c", SERVER_CODE], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)
        ready = self.proc.stdout.readline()  # type: ignore[union-attr]
        if not ready.strip():
            raise RuntimeError("the hostile-input fork server did not start")
        return self

    def stop(self) -> None:
        """Close the server's input (it exits) and wait for it."""
        if self.proc is not None:
            self.proc.stdin.close()  # type: ignore[union-attr]
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc.stdout.close()  # type: ignore[union-attr]
            self.proc = None

    def run(self, category: str, case: str, args: Sequence[str], cwd: Path, check: Check | None = None,
            env: dict[str, str] | None = None, inputs: Sequence[Path] = (),
            timeout: float = CASE_TIMEOUT_S, keep: bool = True) -> Outcome:
        """Run ``trafficrlhf ARGS`` in a forked child in ``cwd``; classify (with ``check`` for exit 0) and
        record the outcome (unless ``keep`` is false: a reference run, not a case)."""
        assert self.proc is not None, "start() the server first"
        with self.lock:
            out, err = Path(self.scratch) / "stdout", Path(self.scratch) / "stderr"
            spec = {"args": [str(a) for a in args], "cwd": str(cwd), "env": env or {}, "stdout": str(out),
                    "stderr": str(err), "cap": ADDRESS_CAP_BYTES, "timeout": timeout}
            self.proc.stdin.write(json.dumps(spec) + "\n")  # type: ignore[union-attr]
            self.proc.stdin.flush()  # type: ignore[union-attr]
            reply = json.loads(self.proc.stdout.readline())  # type: ignore[union-attr]
            stdout = out.read_text(encoding="utf-8", errors="replace")
            stderr = err.read_text(encoding="utf-8", errors="replace")
        outcome = Outcome(category, case, "trafficrlhf " + " ".join(_quote(a) for a in args), reply["code"],
                          stdout, stderr, reply["peak_mb"], reply["seconds"], input_bytes=folder_bytes(inputs))
        classify(outcome, check, reply["timed_out"])
        if keep:
            record(outcome)
        return outcome


def run_executable(category: str, case: str, args: Sequence[str], cwd: Path, check: Check | None = None,
                   inputs: Sequence[Path] = (), timeout: float = CASE_TIMEOUT_S) -> Outcome:
    """Run the installed ``trafficrlhf`` console script in a fresh process; peak memory from ``wait4``."""
    exe = Path(sys.executable).with_name("trafficrlhf")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("TRAFFICRLHF_DEBUG", None)
    start = time.monotonic()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([str(exe), *map(str, args)], cwd=cwd, stdout=out, stderr=err,
                                stdin=subprocess.DEVNULL, env=env)
        timed_out = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() - start > timeout:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                timed_out = True
                break
            time.sleep(0.01)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    outcome = Outcome(category, case, "trafficrlhf " + " ".join(_quote(a) for a in args), proc.returncode, stdout,
                      stderr, usage.ru_maxrss / 1024, time.monotonic() - start, input_bytes=folder_bytes(inputs))
    classify(outcome, check, timed_out)
    record(outcome)
    return outcome


def _quote(arg: object) -> str:
    text = str(arg)
    if len(text) > 120:
        text = text[:60] + f"...<{len(text)} chars>"
    return text if re.fullmatch(r"[\w./:=,@+-]+", text) else repr(text)


def assert_handled(outcome: Outcome) -> None:
    """The assertion every case makes: a clear error or a correct result, under the memory bound."""
    assert outcome.passed, outcome.explain()


def draw(strategy: object, count: int, seed: int) -> list:
    """``count`` distinct examples of a hypothesis ``strategy``, the same on every run (a fixed seed, no
    database, no shrinking): generated cases become an ordinary, stable parametrized list."""
    from hypothesis import HealthCheck, Phase, given, seed as with_seed, settings

    examples: list = []
    seen: set[str] = set()

    @with_seed(seed)
    @settings(max_examples=count * 3, database=None, phases=[Phase.generate], deadline=None,
              suppress_health_check=list(HealthCheck))
    @given(strategy)
    def collect(example: object) -> None:
        key = repr(example)
        if len(examples) < count and key not in seen:
            seen.add(key)
            examples.append(example)

    collect()
    return examples


def case_param(*values: object, case_id: str, large: bool, known: dict[str, str]) -> Any:
    """One generated case as a pytest parameter: the large form's cases carry the ``hostile`` marker, and a known
    open failure (``known``: case id -> what happens) is a strict xfail, so a fix shows up as a pass to un-mark."""
    import pytest

    marks = [pytest.mark.hostile] if large else []
    if case_id in known:
        marks.append(pytest.mark.xfail(strict=True, reason=known[case_id]))
    return pytest.param(*values, id=case_id + ("-L" if large else ""), marks=marks)
