"""Weight averaging of aligned checkpoints (``average_checkpoints``, ``trafficrlhf average``)."""

from __future__ import annotations

import json
import os

import pytest
import torch
from safetensors.torch import load_file, save_file

from trafficrlhf_sdk.align import average_checkpoints
from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError

gru = pytest.importorskip("trafficrlhf_example_gru")


def _saved(tmp_path, name: str, seed: int) -> str:  # type: ignore[no-untyped-def]
    torch.manual_seed(seed)
    adapter = gru.ExampleGRUAdapter()
    directory = str(tmp_path / name)
    adapter.save_pretrained(directory)
    return directory


@pytest.fixture
def three(tmp_path) -> list[str]:  # type: ignore[no-untyped-def]
    return [_saved(tmp_path, f"run{i}", seed=i) for i in range(3)]


def _weights(directory: str) -> dict[str, torch.Tensor]:
    return load_file(os.path.join(directory, "model.safetensors"))


def test_uniform_and_weighted_means_are_elementwise(three: list[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    states = [_weights(d) for d in three]
    out = average_checkpoints(three, str(tmp_path / "soup"))
    soup = _weights(out)
    assert soup.keys() == states[0].keys()
    for name, value in soup.items():
        expected = sum(s[name].double() for s in states) / 3
        assert value.dtype == states[0][name].dtype
        torch.testing.assert_close(value.double(), expected, atol=1e-6, rtol=0)
    weighted = _weights(average_checkpoints(three, str(tmp_path / "w"), weights=[1, 0, 3]))
    for name, value in weighted.items():
        torch.testing.assert_close(value.double(), (states[0][name].double() + 3 * states[2][name].double()) / 4,
                                   atol=1e-6, rtol=0)
    record = json.loads((tmp_path / "w" / "averaged_from.json").read_text())
    assert record == {"sources": three, "weights": [0.25, 0.0, 0.75]}


def test_the_average_loads_and_plans_like_any_checkpoint(three: list[str], tmp_path, nuscenes_source) -> None:  # type: ignore[no-untyped-def]
    out = average_checkpoints(three[:2], str(tmp_path / "soup"))
    adapter = gru.ExampleGRUAdapter.from_pretrained(out)
    for name, value in adapter.module.state_dict().items():
        torch.testing.assert_close(value, _weights(out)[name])
    scene = nuscenes_source.load_batch("train", 1)
    plan = adapter.plan(scene.replace_unchecked(current_index=10), 20)
    assert plan.states.shape[-2:] == (20, 4) and torch.isfinite(plan.states).all()


def test_mismatched_or_broken_inputs_get_one_clear_error(three: list[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(TrafficRLHFError, match="at least two"):
        average_checkpoints(three[:1], str(tmp_path / "x"))
    with pytest.raises(TrafficRLHFError, match="one of the inputs"):
        average_checkpoints(three, three[0])
    with pytest.raises(TrafficRLHFError, match="weights"):
        average_checkpoints(three, str(tmp_path / "x"), weights=[1, -1, 1])
    with pytest.raises(TrafficRLHFError, match="weights"):
        average_checkpoints(three, str(tmp_path / "x"), weights=[1, 1])
    with pytest.raises(DataNotFoundError, match=r"config\.json"):
        average_checkpoints([three[0], str(tmp_path / "missing")], str(tmp_path / "x"))
    other = tmp_path / "other"
    other.mkdir()
    config = json.loads(open(os.path.join(three[1], "config.json")).read())
    config["config"]["hidden"] = 2 * config["config"].get("hidden", 32)
    (other / "config.json").write_text(json.dumps(config))
    save_file(_weights(three[1]), str(other / "model.safetensors"))
    with pytest.raises(DataFormatError, match=r"another config\.json"):
        average_checkpoints([three[0], str(other)], str(tmp_path / "x"))
    broken = {k: v.clone() for k, v in _weights(three[1]).items()}
    first = next(k for k, v in broken.items() if v.is_floating_point())
    broken[first].view(-1)[0] = float("nan")
    save_file(broken, os.path.join(three[2], "model.safetensors"))
    with pytest.raises(DataFormatError, match="non-finite"):
        average_checkpoints(three, str(tmp_path / "x"))
    assert not (tmp_path / "x").exists(), "nothing is written when the inputs are bad"


def test_cli_average(three: list[str], tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = str(tmp_path / "soup")
    with pytest.raises(SystemExit) as done:
        main(["average", *three, "--out", out, "--weights", "1,1,2"])
    assert done.value.code in (0, None)
    assert "averaged 3 checkpoints" in capsys.readouterr().out
    assert json.loads(open(os.path.join(out, "averaged_from.json")).read())["weights"] == [0.25, 0.25, 0.5]
    with pytest.raises(SystemExit) as failed:
        main(["average", three[0], str(tmp_path / "nope"), "--out", str(tmp_path / "y")])
    assert failed.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("Error:") and "config.json" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as usage:
        main(["average", *three, "--out", str(tmp_path / "z"), "--weights", "1,a"])
    assert usage.value.code == 2
