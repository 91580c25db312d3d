"""Bad files and options get one clear error naming the argument, the value and the fix (never an internal
error): feedback databases that are not SQLite or do not exist, invalid architecture options."""

from __future__ import annotations

from pathlib import Path

import pytest

from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DatabaseFileError, InvalidOptionError
from trafficrlhf_sdk.feedback import FeedbackStore


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    captured = capsys.readouterr()
    return int(exit_info.value.code or 0), captured.out, captured.err


def not_sqlite(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / f"{kind}.db"
    if kind == "random":
        path.write_bytes(bytes(range(256)) * 20)
    elif kind == "text":
        path.write_text("campaign,label\nx,1\n", encoding="utf-8")
    else:  # a real database with its pages overwritten past the header
        store = FeedbackStore(path)
        store.add_annotator("alice")
        store.close()
        data = bytearray(path.read_bytes())
        data[100:4096] = b"\xff" * (4096 - 100)
        path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("kind", ["random", "text", "damaged"])
@pytest.mark.parametrize(("command", "names"), [(["feedback", "status"], []),
                                                (["feedback", "annotator", "add"], ["bob"]),
                                                (["feedback", "annotator", "list"], []),
                                                (["feedback", "admin"], ["owner"])])
def test_a_file_that_is_not_sqlite_as_db_is_a_clear_error(kind: str, command: list[str], names: list[str],
                                                          tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = not_sqlite(tmp_path, kind)
    before = path.read_bytes()
    code, _, err = run_cli([*command, "--db", str(path), *names], capsys)
    assert code == 2, err
    assert "internal error" not in err and "Traceback" not in err
    assert "--db" in err and str(path) in err and "feedback create" in err
    assert path.read_bytes() == before  # nothing was written into the file


def test_the_store_refuses_a_file_that_is_not_sqlite(tmp_path: Path) -> None:
    path = not_sqlite(tmp_path, "text")
    with pytest.raises(DatabaseFileError, match="not an SQLite database"):
        FeedbackStore(path)
    with pytest.raises(DatabaseFileError, match="is a directory"):
        FeedbackStore(tmp_path)


def test_annotator_add_refuses_a_missing_database(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "nonexistent.db"
    code, out, err = run_cli(["feedback", "annotator", "add", "--db", str(path), "alice"], capsys)
    assert code == 2 and out == ""  # no token printed
    assert not path.exists()
    assert "no such feedback database" in err and "trafficrlhf feedback create" in err


@pytest.mark.parametrize(("option", "key"), [
    ("hidden_sizes=[-5]", "hidden_sizes"),
    ("hidden_sizes=[0]", "hidden_sizes"),
    ("hidden_sizes=[100000]", "hidden_sizes"),
    ("map_channels=[4, -1]", "map_channels"),
    ("crop_size=100000", "crop_size"),
    ("bogus=1", "bogus"),
])
def test_invalid_architecture_options_name_the_option_and_value(option: str, key: str, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from trafficrlhf_sdk.cli.app import parse_key_values
    from trafficrlhf_sdk.reward.ctg_mlp import CTGMLPRewardModel

    options = parse_key_values([option], "--architecture-option")
    with pytest.raises(InvalidOptionError) as info:
        CTGMLPRewardModel(options)
    message = str(info.value)
    assert f"`{key}`" in message and "--architecture-option" in message and "ctg_mlp" in message
    assert f"= {option.partition('=')[2]}" in message
    # on the command line it is refused before any data is read (the --data folder does not even exist)
    code, _, err = run_cli(["rm", "train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "m"),
                            "--architecture-option", option], capsys)
    assert code == 2 and "internal error" not in err and f"option `{key}`" in err
    assert not (tmp_path / "m").exists()
