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


def test_feedback_serve_refuses_a_file_that_is_not_sqlite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("trafficrlhf_annotation_web")
    path = not_sqlite(tmp_path, "random")
    code, out, err = run_cli(["feedback", "serve", "--db", str(path), "--port", "1"], capsys)
    assert code == 2 and "not an SQLite database" in err and "annotation app on" not in out


def test_an_empty_file_or_a_database_missing_a_table_is_refused(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    import sqlite3

    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    code, out, err = run_cli(["feedback", "status", "--db", str(empty)], capsys)
    assert code == 2 and "empty file" in err and out == "" and empty.read_bytes() == b""
    damaged = tmp_path / "damaged.db"
    FeedbackStore(damaged).close()
    with sqlite3.connect(damaged) as conn:
        conn.execute("DROP TABLE labels")
    for command in (["feedback", "status"], ["feedback", "annotator", "list"]):
        code, _, err = run_cli([*command, "--db", str(damaged)], capsys)
        assert code == 2 and "table(s) labels are missing" in err and "backup" in err
    with sqlite3.connect(damaged) as conn:  # nothing was recreated
        assert conn.execute("SELECT count(*) FROM sqlite_master WHERE name = 'labels'").fetchone() == (0,)


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


# ------------------------------------------------------------------------------------ reward models at load
SMALL_ARCH = {"hidden_sizes": [16, 8], "map_channels": [2, 4], "map_embedding": 4}


def saved_model(tmp_path: Path, scale: float, name: str = "model") -> Path:
    import torch

    from trafficrlhf_sdk.reward.ctg_mlp import CTGMLPRewardModel

    torch.manual_seed(0)
    model = CTGMLPRewardModel(SMALL_ARCH)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.mul_(scale)
    out = tmp_path / name
    model.save_pretrained(out)
    return out


@pytest.mark.parametrize("scale", [1e30, 1e20])
def test_finite_but_huge_weights_are_refused_at_load(scale: float, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from trafficrlhf_sdk.errors import RewardModelError
    from trafficrlhf_sdk.reward import RewardModel

    folder = saved_model(tmp_path, scale)
    with pytest.raises(RewardModelError, match="synthetic scene") as info:
        RewardModel.from_pretrained(folder)
    assert str(folder) in str(info.value) and "re-train" in str(info.value)
    code, _, err = run_cli(["rm", "info", str(folder)], capsys)
    assert code == 2 and "synthetic scene" in err and "internal error" not in err


def test_a_sound_model_passes_the_probe(tmp_path: Path) -> None:
    from trafficrlhf_sdk.reward import RewardModel
    from trafficrlhf_sdk.reward.model import check_outputs

    model = RewardModel.from_pretrained(saved_model(tmp_path, 1.0))
    check_outputs(model, "fresh model")


# ------------------------------------------------------------------------------------------ safetensors files
def write_safetensors(path: Path, data_bytes: int, declared: int | None = None) -> Path:
    """A safetensors file of one float32 tensor of ``data_bytes``, its header declaring ``declared`` bytes; the
    data is a hole (sparse), so a 22 GiB file costs no disk."""
    import json
    import struct

    declared = data_bytes if declared is None else declared
    header = {"__metadata__": {"format": "pt"}, "w": {"dtype": "F32", "shape": [declared // 4],
                                                      "data_offsets": [0, declared]}}
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    with open(path, "wb") as handle:
        handle.write(struct.pack("<Q", len(raw)) + raw)
        handle.truncate(8 + len(raw) + data_bytes)
    return path


@pytest.mark.parametrize(("case", "match"), [("truncated", "should be"), ("padded", "should be"),
                                             ("short", "too short"), ("header", "bytes of JSON")])
def test_malformed_safetensors_are_refused_from_the_header(case: str, match: str, tmp_path: Path) -> None:
    from trafficrlhf_sdk.errors import SafetensorsFileError
    from trafficrlhf_sdk.safetensors_files import check_safetensors_file

    path = tmp_path / "w.safetensors"
    if case == "truncated":
        write_safetensors(path, 64, declared=128)
    elif case == "padded":
        write_safetensors(path, 128, declared=64)
    elif case == "short":
        path.write_bytes(b"\x01\x02")
    else:
        path.write_bytes((10**12).to_bytes(8, "little") + b"{}")
    with pytest.raises(SafetensorsFileError, match=match) as info:
        check_safetensors_file(path)
    assert str(path) in str(info.value)


def test_a_sparse_22_gib_reward_model_is_refused_before_reading(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    folder = saved_model(tmp_path, 1.0)
    write_safetensors(folder / "model.safetensors", 22 * 1024**3)
    code, _, err = run_cli(["rm", "info", str(folder)], capsys)  # refused in well under a second, nothing hashed
    assert code == 2 and "22.0 GiB" in err and "internal error" not in err


def test_a_sparse_22_gib_file_under_a_4_gb_address_limit_is_a_clear_error(tmp_path: Path) -> None:
    import resource
    import subprocess
    import sys

    path = write_safetensors(tmp_path / "big.safetensors", 22 * 1024**3)
    code = ("from trafficrlhf_sdk.feedback.preference import PreferenceDataset\n"
            "from trafficrlhf_sdk.errors import SafetensorsFileError\n"
            "try:\n"
            f"    PreferenceDataset.load({str(tmp_path)!r})\n"
            "except SafetensorsFileError as exc:\n"
            "    print(exc)\n")
    (tmp_path / "preferences.safetensors").symlink_to(path)

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (4_000_000 * 1024, resource.RLIM_INFINITY))

    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            preexec_fn=limit)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "22.0 GiB" in result.stdout and "nothing was read" in result.stdout


# -------------------------------------------------------------------------------------------- text encodings
@pytest.mark.parametrize("command", [["align", "--config", "{file}", "--model", "ctg", "--out", "{out}"],
                                     ["rlhf", "--config", "{file}", "--out", "{out}"],
                                     ["feedback", "prioritize", "--db", "{db}", "--campaign", "tiny", "--ranking",
                                      "{file}"],
                                     ["feedback", "settings", "--db", "{db}", "--campaign", "tiny", "--guidelines",
                                      "{file}"]])
def test_a_text_file_that_is_not_utf8_is_a_clear_error(command: list[str], tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

    db = tmp_path / "fb.db"
    store = FeedbackStore(db)
    make_tiny_campaign(store, num_contexts=2)
    store.close()
    bad = tmp_path / "latin1.txt"
    bad.write_bytes("vitesse = 'élevée'\n".encode("latin-1"))
    args = [a.format(file=bad, out=tmp_path / "out", db=db) for a in command]
    code, _, err = run_cli(args, capsys)
    option = command[command.index("{file}") - 1]
    assert code == 2 and "internal error" not in err
    assert f"{option} {str(bad)!r} is not UTF-8" in err and "save it as UTF-8" in err
