"""``trafficrlhf rm train | eval | info`` and ``evaluate --reward-model`` through click's runner."""

from __future__ import annotations

import json
import re
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from trafficrlhf_sdk.cli import get_cli, main
from trafficrlhf_sdk.feedback import FeedbackStore, SyntheticAnnotator, SyntheticAnnotatorConfig
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

ROOT = Path(__file__).resolve().parent.parent
COMMITTED = ROOT / "reference_models" / "reward" / "ctg_no_collision"
SMALL = ["--architecture-option", "hidden_sizes=[32,16]", "--architecture-option", "map_channels=[4,8]",
         "--architecture-option", "map_embedding=8"]


def invoke(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(get_cli(), list(args), catch_exceptions=False)
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def tiny_db(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A tiny campaign (10 contexts) labeled by a noisy and a noise-free synthetic annotator."""
    path = str(tmp_path_factory.mktemp("rmcli") / "feedback.db")
    store = FeedbackStore(path)
    make_tiny_campaign(store, num_contexts=10)
    SyntheticAnnotator(store, "noisy", SyntheticAnnotatorConfig(epsilon=0.1)).label("tiny")
    SyntheticAnnotator(store, "oracle", SyntheticAnnotatorConfig(beta=None)).label("tiny")
    store.close()
    return path


@pytest.fixture(scope="module")
def trained(tiny_db: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rmcli") / "model"
    code, output = invoke("rm", "train", "--db", tiny_db, "--campaign", "tiny", "--annotator", "noisy", "--out",
                          str(out), "--epochs", "2", "--batch-size", "4", "--val-fraction", "0.2", "--quiet",
                          "--test-campaign", "tiny", "--test-annotator", "oracle", "--note", "unit test", *SMALL)
    assert code == 0, output
    assert "trained in" in output and "test_strict_accuracy" in output
    return out


def test_rm_train_writes_a_model_folder(trained: Path) -> None:
    assert {"config.json", "model.safetensors", "README.md", "training_log.json"} <= set(os.listdir(trained))
    config = json.loads((trained / "config.json").read_text())
    assert config["architecture"] == "ctg_mlp" and config["config"]["hidden_sizes"] == [32, 16]
    assert config["data"]["campaign"] == "tiny" and config["data"]["annotators"] == ["noisy"]
    assert config["metrics"]["test_pairs"] == 40
    card = (trained / "README.md").read_text()
    assert "unit test" in card and "CC BY-NC-SA 4.0" in card and "## Intended use" in card


def test_rm_eval_on_a_campaign(trained: Path, tiny_db: str) -> None:
    code, output = invoke("rm", "eval", "--model", str(trained), "--db", tiny_db, "--campaign", "tiny",
                          "--annotator", "oracle", "--json")
    assert code == 0, output
    metrics = json.loads(output)
    assert metrics["pairs"] == 40 and metrics["contexts"] == 10
    assert 0 <= metrics["accuracy"] <= 1 and metrics["strict_pairs"] <= 40
    code, output = invoke("rm", "eval", "--model", str(trained), "--db", tiny_db, "--campaign", "tiny")
    assert code == 0 and "accuracy" in output


def test_rm_info_lists_architectures_and_describes_a_model(trained: Path) -> None:
    code, output = invoke("rm", "info")
    assert code == 0 and "ctg_mlp" in output and "ensemble" in output
    code, output = invoke("rm", "info", str(trained), "--json")
    summary = json.loads(output)
    assert summary["weights_sha256_ok"] and summary["registered"] and summary["num_parameters"] > 0


@pytest.mark.parametrize(("extra", "message"), [
    (["--contrast-annotator", "attentive"], "add --contrast-scenes N"),
    (["--contrast-scenes", "4", "--contrast-annotator", "nobody"], "not stand-in profiles"),
])
def test_rm_train_refuses_contrast_annotators_it_cannot_use(tiny_db: str, tmp_path: Path, extra: list[str],
                                                            message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "train", "--db", tiny_db, "--campaign", "tiny", "--out", str(tmp_path / "m"), "--quiet", *extra])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m" / "model.safetensors").exists()


@pytest.mark.skipif(not COMMITTED.is_dir(), reason="the committed reward model is not in this checkout")
def test_rm_info_on_the_committed_model() -> None:
    code, output = invoke("rm", "info", str(COMMITTED))
    assert code == 0, output
    assert "ctg_mlp" in output and "weights ok" in output and "test_strict_accuracy" in output


def test_broken_model_folder_is_a_one_line_error(trained: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(trained, broken)
    config = json.loads((broken / "config.json").read_text())
    config["architecture"] = "not_installed"
    (broken / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "eval", "--model", str(broken), "--data", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1
    assert "'not_installed'" in err and "ctg_mlp" in err
    weights = broken / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    config["architecture"] = "ctg_mlp"
    (broken / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "info", str(broken)])  # info still describes it, flagging the weights, and exits 2
    captured = capsys.readouterr()
    assert exit_info.value.code == 2 and "DO NOT LOAD" in captured.out
    assert "does not load" in captured.err and "SHA-256" in captured.err


def test_rm_train_needs_one_data_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["rm", "train", "--out", str(tmp_path / "m")])
    assert exit_info.value.code == 2
    assert "either a feedback database" in capsys.readouterr().err


@pytest.mark.skipif(not COMMITTED.is_dir(), reason="the committed reward model is not in this checkout")
def test_evaluate_with_reward_model(data_root: str) -> None:
    code, output = invoke("evaluate", "--model", "constant_velocity", "--scenes", "2", "--reward-model",
                          str(COMMITTED), "--json")
    assert code == 0, output
    report = json.loads(output[output.index("{"):])
    assert 0 <= report["metrics"]["reward_cost"] <= 20 and 0 <= report["logged"]["reward_cost"] <= 20


def test_rm_train_pools_repeated_campaigns(tiny_db: str, tmp_path: Path) -> None:
    """`--campaign` repeated (one campaign per RLHF round) trains on the pairs of all of them."""
    store = FeedbackStore(tiny_db)
    make_tiny_campaign(store, name="round2", num_contexts=4, seed=7)
    SyntheticAnnotator(store, "noisy", SyntheticAnnotatorConfig(epsilon=0.1)).label("round2")
    store.close()
    out = tmp_path / "pooled"
    code, output = invoke("rm", "train", "--db", tiny_db, "--campaign", "tiny", "--campaign", "round2",
                          "--annotator", "noisy", "--out", str(out), "--epochs", "1", "--batch-size", "4",
                          "--val-fraction", "0.2", "--quiet", *SMALL)
    assert code == 0, output
    counts = [int(n) for n in re.findall(r"(\d+) (?:pairs|contexts)", output.splitlines()[0])]
    assert counts[0] + counts[2] == 40 + 16 and counts[1] + counts[3] == 10 + 4  # (train, val) pairs and contexts
    config = json.loads((out / "config.json").read_text())
    assert config["data"]["campaign"] == ["tiny", "round2"]


def test_rm_eval_on_the_held_out_side_of_a_campaign(trained: Path, tiny_db: str) -> None:
    """`--val-fraction F --subset val` scores only the contexts `rm train --val-fraction F` held out."""
    code, output = invoke("rm", "eval", "--model", str(trained), "--db", tiny_db, "--campaign", "tiny",
                          "--annotator", "oracle", "--val-fraction", "0.2", "--subset", "val", "--json")
    assert code == 0, output
    metrics = json.loads(output)
    assert metrics["contexts"] == 2 and 2 * 4 <= metrics["pairs"] <= 2 * 5  # N-1 pairs per choice, N for 'none'
