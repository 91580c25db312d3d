"""Weight averaging and extrapolation of aligned checkpoints (``average_checkpoints``, ``extrapolate_checkpoint``,
``trafficrlhf average`` / ``extrapolate``)."""

from __future__ import annotations

import json
import os

import pytest
import torch
from trafficrlhf_sdk.models.checkpoint import record_weights_digest
from safetensors.torch import load_file, save_file

from trafficrlhf_sdk.alignment import average_checkpoints, extrapolate_checkpoint
from trafficrlhf_sdk.cli import main
from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, TrafficRLHFError

gru = pytest.importorskip("trafficrlhf_example_gru")


def _save(tensors: dict, path: str) -> None:
    """Write edited weights and record their SHA-256, so the check under test is the one that fails."""
    save_file(tensors, path)
    record_weights_digest(os.path.dirname(path))


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
    field = next(iter(config["config"]))
    config["config"][field] = [config["config"][field], "changed"]
    (other / "config.json").write_text(json.dumps(config))
    _save(_weights(three[1]), str(other / "model.safetensors"))
    with pytest.raises(DataFormatError, match=f"different architecture configs \\({field}: "):
        average_checkpoints([three[0], str(other)], str(tmp_path / "x"))
    config["config"][field] = json.loads(open(os.path.join(three[1], "config.json")).read())["config"][field]
    config["adapter"] = "ctg"
    (other / "config.json").write_text(json.dumps(config))
    record_weights_digest(str(other))
    with pytest.raises(DataFormatError, match="adapter 'ctg'"):
        average_checkpoints([three[0], str(other)], str(tmp_path / "x"))
    broken = {k: v.clone() for k, v in _weights(three[1]).items()}
    first = next(k for k, v in broken.items() if v.is_floating_point())
    broken[first].view(-1)[0] = float("nan")
    _save(broken, os.path.join(three[2], "model.safetensors"))
    with pytest.raises(DataFormatError, match="non-finite"):
        average_checkpoints(three, str(tmp_path / "x"))
    assert not (tmp_path / "x").exists(), "nothing is written when the inputs are bad"


def test_a_config_field_only_one_checkpoint_records_is_kept(three: list[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    # a checkpoint saved before a config field existed (it loads with the field's default) combines with newer ones
    older = json.loads(open(os.path.join(three[0], "config.json")).read())
    dropped = next(iter(older["config"]))
    value = older["config"].pop(dropped)
    (tmp_path / "run0" / "config.json").write_text(json.dumps(older))
    out = average_checkpoints(three[:2], str(tmp_path / "soup"))
    assert json.loads(open(os.path.join(out, "config.json")).read())["config"][dropped] == value
    out = extrapolate_checkpoint(three[0], three[1], str(tmp_path / "x2"), 2.0)
    assert json.loads(open(os.path.join(out, "config.json")).read())["config"][dropped] == value
    gru.ExampleGRUAdapter.from_pretrained(out)


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


def test_extrapolation_is_base_plus_factor_times_the_step(three: list[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    base_dir, aligned_dir = three[0], three[1]
    base, aligned = _weights(base_dir), _weights(aligned_dir)
    frozen = next(k for k, v in base.items() if v.is_floating_point())
    aligned[frozen] = base[frozen].clone()  # a parameter group alignment did not train
    _save(aligned, os.path.join(aligned_dir, "model.safetensors"))
    for factor in (0.0, 0.5, 1.0, 2.0, 3.5):
        out = _weights(extrapolate_checkpoint(base_dir, aligned_dir, str(tmp_path / f"x{factor}"), factor))
        assert out.keys() == base.keys()
        for name, value in out.items():
            assert value.dtype == base[name].dtype
            expected = base[name].double() + factor * (aligned[name].double() - base[name].double())
            torch.testing.assert_close(value.double(), expected, atol=1e-6, rtol=0)
        assert torch.equal(out[frozen], base[frozen]), "an untrained tensor must stay bitwise equal to the base"
        if factor in (0.0, 1.0):
            source = base if factor == 0.0 else aligned
            assert all(torch.equal(out[k], source[k]) for k in out)
    record = json.loads((tmp_path / "x2.0" / "extrapolated_from.json").read_text())
    assert record == {"base": base_dir, "aligned": aligned_dir, "factor": 2.0}
    adapter = gru.ExampleGRUAdapter.from_pretrained(str(tmp_path / "x2.0"))
    assert torch.equal(adapter.module.state_dict()[frozen], base[frozen])


def test_extrapolation_rejects_bad_requests(three: list[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    for factor in (-1.0, float("nan"), float("inf")):
        with pytest.raises(TrafficRLHFError, match="factor"):
            extrapolate_checkpoint(three[0], three[1], str(tmp_path / "x"), factor)
    with pytest.raises(TrafficRLHFError, match="one of the inputs"):
        extrapolate_checkpoint(three[0], three[1], three[1], 2.0)
    with pytest.raises(DataNotFoundError, match=r"model\.safetensors|config\.json"):
        extrapolate_checkpoint(three[0], str(tmp_path / "missing"), str(tmp_path / "x"), 2.0)
    shrunk = tmp_path / "shrunk"
    shrunk.mkdir()
    (shrunk / "config.json").write_text(open(os.path.join(three[1], "config.json")).read())
    state = _weights(three[1])
    name = next(k for k, v in state.items() if v.is_floating_point() and v.dim() > 0)
    state[name] = state[name][:1].clone()
    _save(state, str(shrunk / "model.safetensors"))
    with pytest.raises(DataFormatError, match=name):
        extrapolate_checkpoint(three[0], str(shrunk), str(tmp_path / "x"), 2.0)
    assert not (tmp_path / "x").exists(), "nothing is written when the inputs are bad"


def test_cli_extrapolate(three: list[str], tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = str(tmp_path / "x2")
    with pytest.raises(SystemExit) as done:
        main(["extrapolate", three[1], "--base", three[0], "--factor", "2", "--out", out])
    assert done.value.code in (0, None)
    assert "base + 2 x (aligned - base)" in capsys.readouterr().out
    assert json.loads(open(os.path.join(out, "extrapolated_from.json")).read())["factor"] == 2.0
    with pytest.raises(SystemExit) as usage:
        main(["extrapolate", three[1], "--base", three[0], "--factor", "-1", "--out", str(tmp_path / "y")])
    assert usage.value.code == 2
    assert "--factor" in capsys.readouterr().err
    with pytest.raises(SystemExit) as failed:
        main(["extrapolate", str(tmp_path / "nope"), "--base", three[0], "--factor", "2", "--out", str(tmp_path / "z")])
    assert failed.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("Error:") and "Traceback" not in err


def test_further_directions_add_their_weighted_change(three: list[str], tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    base_dir, aligned_dir, stage2_dir = three
    base, aligned, stage2 = (_weights(d) for d in three)
    out = _weights(extrapolate_checkpoint(base_dir, aligned_dir, str(tmp_path / "c"), 2.0,
                                          [(aligned_dir, stage2_dir, 1.5), (base_dir, aligned_dir, -0.5)]))
    for name, value in out.items():
        b, a, s2 = base[name].double(), aligned[name].double(), stage2[name].double()
        expected = b + 2.0 * (a - b) + 1.5 * (s2 - a) - 0.5 * (a - b)
        torch.testing.assert_close(value.double(), expected, atol=1e-6, rtol=0)
    record = json.loads((tmp_path / "c" / "extrapolated_from.json").read_text())
    assert record["directions"] == [{"from": aligned_dir, "to": stage2_dir, "weight": 1.5},
                                    {"from": base_dir, "to": aligned_dir, "weight": -0.5}]
    # weight 1 on the second stage and factor 1 reproduce the second stage itself
    same = _weights(extrapolate_checkpoint(base_dir, aligned_dir, str(tmp_path / "s"), 1.0,
                                           [(aligned_dir, stage2_dir, 1.0)]))
    for name, value in same.items():
        torch.testing.assert_close(value, stage2[name], atol=1e-6, rtol=0)
    with pytest.raises(TrafficRLHFError, match="weight of direction"):
        extrapolate_checkpoint(base_dir, aligned_dir, str(tmp_path / "n"), 1.0,
                               [(aligned_dir, stage2_dir, float("nan"))])
    with pytest.raises(TrafficRLHFError, match="one of the inputs"):
        extrapolate_checkpoint(base_dir, aligned_dir, stage2_dir, 1.0, [(aligned_dir, stage2_dir, 1.0)])
    with pytest.raises(DataNotFoundError):
        extrapolate_checkpoint(base_dir, aligned_dir, str(tmp_path / "m"), 1.0,
                               [(aligned_dir, str(tmp_path / "no"), 1.0)])
    assert not (tmp_path / "n").exists() and not (tmp_path / "m").exists()
    with pytest.raises(SystemExit) as done:
        main(["extrapolate", aligned_dir, "--base", base_dir, "--factor", "2", "--add-direction", aligned_dir,
              stage2_dir, "0.5", "--out", str(tmp_path / "cli")])
    assert done.value.code in (0, None)
    assert "+ 0.5 x (" in capsys.readouterr().out
    assert json.loads((tmp_path / "cli" / "extrapolated_from.json").read_text())["directions"][0]["weight"] == 0.5

