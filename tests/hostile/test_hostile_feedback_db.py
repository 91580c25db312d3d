"""Hostile feedback databases: a small labelled campaign database (campaign ``tiny``, 3 items labelled by the
synthetic annotator) damaged the way a crash, a bad copy or an attacker would, generated with hypothesis: the file
truncated, overwritten in its header or its pages, replaced by an empty file, text, random bytes, a folder or a
link to ``/dev/zero``, left with a garbage write-ahead log, made read-only, or edited through SQLite (a table
dropped or renamed, a column renamed, rows of the wrong type, an unknown schema version, a broken campaign
config or candidate blob). A path that does not exist is offered to commands that only read.

Each case runs one feedback command on the copy (``status``, ``annotator list``, ``annotator add``, ``export``,
``rm train``); a run that exits 0 must print what it prints for the undamaged database, unless the edit was
legitimate content or SQLite's own integrity check finds nothing wrong with the damaged file (a changed byte
inside a stored value cannot be told from an edit).
"""

from __future__ import annotations

import os
import re
import shutil
import sqlite3
from pathlib import Path

import pytest
from hostile_harness import case_param, ForkServer, assert_handled, draw
from hypothesis import strategies as st

SQL_EDITS = [
    "DROP TABLE labels", "DROP TABLE campaigns", "DROP TABLE candidates", "ALTER TABLE labels RENAME TO labels_old",
    "ALTER TABLE campaigns RENAME COLUMN config_json TO config", "ALTER TABLE annotators RENAME COLUMN name TO who",
    "PRAGMA user_version = 999", "PRAGMA user_version = -1", "PRAGMA user_version = 0",
    "UPDATE campaigns SET config_json = '{oops'", "UPDATE campaigns SET config_json = '[]'",
    "UPDATE campaigns SET num_candidates = 1000000", "UPDATE candidates SET tensors = x'00ff00ff'",
    "UPDATE candidates SET tensors = zeroblob(0)", "UPDATE labels SET slot = 99", "UPDATE labels SET candidate = -7",
    "UPDATE labels SET permutation = 'not a permutation'", "UPDATE contexts SET start_index = -5",
    "UPDATE contexts SET scene_id = char(0) || id", "UPDATE annotators SET active = 'maybe'",
    "UPDATE campaigns SET seed = 'text'", "DELETE FROM contexts", "DELETE FROM campaigns",
    "INSERT INTO campaigns (name, created_at, model, seed, num_candidates, sdk_version, config_json) "
    "VALUES ('other', 'x', 'm', 0, 2, 'v', '{}')",
    "UPDATE campaigns SET name = '\u202eevil' || char(10) || 'line'",
    "CREATE TABLE extra (x)", "UPDATE labels SET context_id = 424242",
]
FILE_EDITS = ["empty", "text", "random", "folder", "/dev/zero", "missing", "garbage wal", "garbage journal",
              "read-only", "header magic", "header page size", "header zeroed"]
COMMANDS = ["status", "annotator list", "annotator add", "export", "rm train"]

EDITS = st.one_of(
    st.tuples(st.just("file"), st.sampled_from(FILE_EDITS)),
    st.tuples(st.just("truncate"), st.floats(0.0, 0.99)),
    st.tuples(st.just("overwrite"), st.tuples(st.integers(0, 400_000), st.binary(min_size=1, max_size=64))),
    st.tuples(st.just("sql"), st.sampled_from(SQL_EDITS)),
)
# Edits of legitimate content: the commands may show the change.
LEGITIMATE = ("INSERT INTO campaigns (name, created_at, model, seed, num_candidates, sdk_version, config_json) "
              "VALUES ('other', 'x', 'm', 0, 2, 'v', '{}')", "CREATE TABLE extra (x)", "PRAGMA user_version = 0",
              "garbage wal", "garbage journal")


def damage(path: Path, operation: str, argument: object) -> None:
    if operation == "file":
        if argument == "empty":
            path.write_bytes(b"")
        elif argument == "text":
            path.write_text("campaign,items\ntiny,3\n")
        elif argument == "random":
            path.write_bytes(os.urandom(8192))
        elif argument == "folder":
            path.unlink()
            path.mkdir()
        elif argument == "/dev/zero":
            path.unlink()
            path.symlink_to("/dev/zero")
        elif argument == "missing":
            path.unlink()
        elif argument == "garbage wal":
            Path(str(path) + "-wal").write_bytes(os.urandom(4096))
        elif argument == "garbage journal":
            Path(str(path) + "-journal").write_bytes(os.urandom(4096))
        elif argument == "read-only":
            path.chmod(0o444)
            path.parent.chmod(0o555)
        else:
            data = bytearray(path.read_bytes())
            if argument == "header magic":
                data[:16] = b"SQLite format 4\0"
            elif argument == "header page size":
                data[16:18] = b"\x00\x07"
            else:
                data[:100] = bytes(100)
            path.write_bytes(bytes(data))
    elif operation == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * float(argument))])  # type: ignore[arg-type]
    elif operation == "overwrite":
        where, patch = argument  # type: ignore[misc]
        data = bytearray(path.read_bytes())
        where = min(where, len(data) - len(patch))
        data[where:where + len(patch)] = patch
        path.write_bytes(bytes(data))
    else:
        connection = sqlite3.connect(path)
        connection.execute("PRAGMA ignore_check_constraints = ON")
        connection.execute(str(argument))
        connection.commit()
        connection.close()


GENERATED = [(("sql", "CREATE TABLE extra (x)"), "status")] + draw(
    st.tuples(EDITS, st.sampled_from(COMMANDS)), 90, 73)
GENERATED += [(("file", "missing"), "annotator add"), (("file", "text"), "status")]  # the reproductions

KNOWN: dict[str, str] = {}  # open failures (strict xfail); none at present


@pytest.fixture(scope="module")
def baselines(labelled_db: Path, fork_server: ForkServer, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Each command's normalized output on an undamaged copy."""
    found = {}
    for command in COMMANDS:
        folder = tmp_path_factory.mktemp("baseline")
        db, out = folder / "feedback.db", folder / "out"
        shutil.copy(labelled_db, db)
        outcome = fork_server.run("feedback databases", command, _command(command, db, out), folder, lambda o, e: None,
                                  keep=False)
        assert outcome.kind == "correct", outcome.explain()
        found[command] = normalized(outcome.stdout, db, out)
    return found


@pytest.fixture(scope="module")
def labelled_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Campaign ``tiny`` (3 items, N = 5), labelled once by the synthetic annotator."""
    from trafficrlhf_sdk.cli import main
    from trafficrlhf_sdk.feedback import FeedbackStore
    from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

    path = tmp_path_factory.mktemp("feedback") / "feedback.db"
    store = FeedbackStore(str(path))
    make_tiny_campaign(store, num_contexts=3)
    store.close()
    with pytest.raises(SystemExit) as done:
        main(["feedback", "label", "--db", str(path), "--campaign", "tiny", "--synthetic"])
    assert done.value.code == 0
    connection = sqlite3.connect(path)  # fold the write-ahead log into the file: copies take the file alone
    connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    connection.close()
    return path


def _command(name: str, db: Path, out: Path) -> list[str]:
    return {"status": ["feedback", "status", "--db", db, "--json"],
            "annotator list": ["feedback", "annotator", "list", "--db", db],
            "annotator add": ["feedback", "annotator", "add", "carol", "--db", db],
            "export": ["feedback", "export", "--db", db, "--campaign", "tiny", "--out", out],
            "rm train": ["rm", "train", "--db", db, "--campaign", "tiny", "--out", out, "--epochs", "1", "--quiet"],
            }[name]  # type: ignore[return-value]


def normalized(stdout: str, db: Path, out: Path) -> str:
    """``stdout`` with the case's own paths and a printed token replaced (what differs between two runs)."""
    text = stdout.replace(str(out), "OUT").replace(str(db), "DB")
    # a token may start or end with "-", where \b finds no word boundary
    return re.sub(r"(?<![A-Za-z0-9_-])[A-Za-z0-9_-]{32}(?![A-Za-z0-9_-])", "TOKEN", text)


def test_normalized_hides_any_printed_token() -> None:
    for token in ("YrhjrqKXqjVeGyOQbRyDTLAkTPW2S-QC", "-rhjrqKXqjVeGyOQbRyDTLAkTPW2S-QC",
                  "_rhjrqKXqjVeGyOQbRyDTLAkTPW2S-Q-"):
        assert normalized(f"token: {token}\n", Path("/db"), Path("/out")) == "token: TOKEN\n"


def integrity_ok(db: Path) -> bool:
    """SQLite's own ``PRAGMA integrity_check`` finds nothing wrong with ``db``."""
    try:
        connection = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        try:
            return connection.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        finally:
            connection.close()
    except sqlite3.Error:
        return False


def _check(baseline: str, db: Path, out: Path, legitimate: bool, detectable: bool):  # type: ignore[no-untyped-def]
    """Exit 0 is right when the output is that of the undamaged database (the command did not need the damaged
    part), or when the edit was legitimate content, or SQLite itself finds the damaged file intact."""
    def check(stdout: str, stderr: str) -> str | None:
        if normalized(stdout, db, out) == baseline or legitimate:
            return None if stdout.strip() else "no output"
        if not detectable:
            return None
        return "exit 0 with an output that differs from the undamaged database's"
    return check


def _params(large: bool) -> list:
    params, seen = [], set()
    for index, ((operation, argument), command) in enumerate(GENERATED):
        is_small = (operation, command) not in seen and command in ("status", "annotator add", "export") and \
            operation in ("file", "sql", "truncate")
        seen.add((operation, command))
        if not (large or is_small):
            continue
        case_id = f"db-{command}-{operation}-{index}"
        params.append(case_param(operation, argument, command, case_id=case_id, large=large, known=KNOWN))
    return params


@pytest.mark.parametrize(("operation", "argument", "command"), _params(False) + _params(True))
def test_hostile_feedback_database(operation: str, argument: object, command: str, labelled_db: Path,
                                   baselines: dict, fork_server: ForkServer, tmp_path: Path, workdir: Path) -> None:
    folder = tmp_path / "db"
    folder.mkdir()
    db = folder / "feedback.db"
    shutil.copy(labelled_db, db)
    damage(db, operation, argument)
    out = tmp_path / "out"
    legitimate = argument in LEGITIMATE
    detectable = operation in ("file", "sql") or not integrity_ok(db)
    try:
        outcome = fork_server.run("feedback databases", f"{command}: {operation} {argument!r}"[:200],
                                  _command(command, db, out), workdir,
                                  _check(baselines[command], db, out, legitimate, detectable),
                                  inputs=[folder] if folder.is_dir() else [])
    finally:
        folder.chmod(0o755)
    assert_handled(outcome)
