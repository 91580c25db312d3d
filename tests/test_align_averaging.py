"""Weight averaging and extrapolation of aligned checkpoints (``average_checkpoints``, ``extrapolate_checkpoint``,
``trafficrlhf average`` / ``extrapolate``, ``scripts/extrapolation_sweep.py``)."""

from __future__ import annotations

import argparse
import json
import os
import shutil

import pytest
import torch
from safetensors.torch import load_file, save_file

from trafficrlhf_sdk.alignment import average_checkpoints, extrapolate_checkpoint
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
    field = next(iter(config["config"]))
    config["config"][field] = [config["config"][field], "changed"]
    (other / "config.json").write_text(json.dumps(config))
    save_file(_weights(three[1]), str(other / "model.safetensors"))
    with pytest.raises(DataFormatError, match=f"different architecture configs \\({field}: "):
        average_checkpoints([three[0], str(other)], str(tmp_path / "x"))
    config["config"][field] = json.loads(open(os.path.join(three[1], "config.json")).read())["config"][field]
    config["adapter"] = "ctg"
    (other / "config.json").write_text(json.dumps(config))
    with pytest.raises(DataFormatError, match="adapter 'ctg'"):
        average_checkpoints([three[0], str(other)], str(tmp_path / "x"))
    broken = {k: v.clone() for k, v in _weights(three[1]).items()}
    first = next(k for k, v in broken.items() if v.is_floating_point())
    broken[first].view(-1)[0] = float("nan")
    save_file(broken, os.path.join(three[2], "model.safetensors"))
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
    save_file(aligned, os.path.join(aligned_dir, "model.safetensors"))
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
    save_file(state, str(shrunk / "model.safetensors"))
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


@pytest.mark.parametrize("split", ["train", "val"])
def test_sweep_evaluates_every_factor_and_names_the_lowest_failure(three: list[str], tmp_path, data_root, capsys,
                                                                   load_script,
                                                                   split: str) -> None:  # type: ignore[no-untyped-def]
    sweep = load_script("extrapolation_sweep")
    pytest.importorskip("trafficrlhf_nuscenes_pred")
    out = tmp_path / "sweep"
    code = sweep.main(["--model", "example_gru", "--base", three[0], "--aligned", three[1],
                                 "--factors", "0,1,2", "--seeds", "0", "--max-scenes", "2", "--split", split,
                                 "--out", str(out)])
    assert code == 0
    result = json.loads((out / "sweep.json").read_text())
    assert result["split"] == split and result["scenes"] == 2 and result["factors"] == [0.0, 1.0, 2.0]
    failures = {f: result["mean"][f]["failure_rate"] for f in ("0", "1", "2")}
    assert all(0.0 <= v <= 1.0 for v in failures.values())
    assert result["best_factor"] == float(min(failures, key=failures.__getitem__))
    keeping = [f for f in failures if all(result["mean"][f][k] <= result["mean"]["0"][k]
                                          for k in ("realism_ctg", "realism_body"))]
    assert "0" in keeping and result["best_factor_keeping_realism"] == float(min(keeping, key=failures.__getitem__))
    assert (out / "sweep.png").stat().st_size > 1000
    assert all(torch.equal(v, _weights(three[0])[k]) for k, v in _weights(str(out / "x0")).items())
    printed = capsys.readouterr().out
    assert "| factor |" in printed and f"factor {result['best_factor']:g}" in printed
    slow = sweep.sweep("example_gru", three[0], three[1], [0.0, 2.0], [0], str(tmp_path / "s2"), None, 10,
                                 max_scenes=2, min_speed_ratio=1e6)
    assert slow["best_factor"] is None and slow["best_factor_keeping_realism"] is None
    capsys.readouterr()
    assert sweep.main(["--model", "example_gru", "--base", three[0], "--aligned", str(tmp_path / "no"),
                                 "--factors", "2", "--seeds", "0", "--max-scenes", "1", "--out", str(out)]) == 2
    assert capsys.readouterr().err.startswith("Error:")


def test_val_development_scenes_are_the_tail_the_reported_evaluation_never_drives(data_root, load_script) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("trafficrlhf_nuscenes_pred")
    from trafficrlhf_sdk import get_scenario_source

    dev = load_script("align_dev_eval")
    every_val = get_scenario_source("nuscenes_pred").scene_ids("val")
    ids, batch = dev.held_out_scenes(None, None, "val")
    reported = set(every_val[:100])  # what `trafficrlhf evaluate --scenes 100` drives
    assert ids == every_val[100:] and ids and not reported & set(ids)
    assert batch.num_scenes == len(ids)
    with pytest.raises(ValueError, match="holdout_every"):
        dev.held_out_scenes(10, None, "val")
    with pytest.raises(ValueError, match="split"):
        dev.held_out_scenes(None, None, "test")


def test_mirrored_development_scenes_are_the_held_out_scenes_reflected(data_root, load_script) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("trafficrlhf_nuscenes_pred")
    dev = load_script("align_dev_eval")
    ids, plain = dev.held_out_scenes(40, None, "train")
    mirrored_ids, mirrored = dev.held_out_scenes(40, None, "train", mirror=True)
    assert mirrored_ids == ids and mirrored.num_scenes == plain.num_scenes
    valid = plain.valid
    assert torch.equal(mirrored.valid, valid)
    assert torch.equal(mirrored.xy[..., 0][valid], plain.xy[..., 0][valid])
    assert torch.equal(mirrored.xy[..., 1][valid], -plain.xy[..., 1][valid])
    # the map is read where the original point read it: the logged positions stay on the same pixels
    scene, agent, step = valid.nonzero(as_tuple=True)
    assert torch.equal(mirrored.map.lookup_points(scene, mirrored.xy[scene, agent, step].double()),
                       plain.map.lookup_points(scene, plain.xy[scene, agent, step].double()))


def test_development_evaluation_passes_model_options_and_refuses_malformed_ones(load_script, monkeypatch,
                                                                                capsys) -> None:  # type: ignore[no-untyped-def]
    dev = load_script("align_dev_eval")
    seen: list[dict] = []

    class Stop(Exception):
        pass

    def fake_build(model: str, options: dict) -> None:
        seen.append(options)
        raise Stop

    monkeypatch.setattr(dev, "build_policy", fake_build)
    with pytest.raises(Stop):
        dev.held_out_report("ctg", "CKPT", "no_collision", None, 3, {"steer_gate_offset": 2, "seed": 99})
    assert seen == [{"steer_gate_offset": 2, "seed": 3, "guidance": "no_collision", "checkpoint": "CKPT"}]
    monkeypatch.setattr("sys.argv", ["align_dev_eval.py", "--model", "ctg", "--model-option", "oops"])
    with pytest.raises(SystemExit) as exit_info:
        dev.main()
    assert exit_info.value.code == 2
    assert "--model-option: expected KEY=VALUE, got 'oops'" in capsys.readouterr().err

    def refuse(model: str, options: dict) -> None:
        raise TrafficRLHFError("`nosuch` is not an option of ctg")

    monkeypatch.setattr(dev, "build_policy", refuse)
    monkeypatch.setattr(dev, "held_out_scenes", lambda *args: (["scene-0001"], None))
    monkeypatch.setattr("sys.argv", ["align_dev_eval.py", "--model", "ctg", "--model-option", "nosuch=1"])
    with pytest.raises(SystemExit) as exit_info:
        dev.main()
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == "Error: `nosuch` is not an option of ctg\n"


def test_sweep_over_a_second_direction_evaluates_the_grid(three: list[str], tmp_path, data_root, capsys,
                                                          load_script) -> None:  # type: ignore[no-untyped-def]
    sweep = load_script("extrapolation_sweep")
    pytest.importorskip("trafficrlhf_nuscenes_pred")
    out = tmp_path / "grid"
    code = sweep.main(["--model", "example_gru", "--base", three[0], "--aligned", three[1], "--factors", "0,2",
                       "--direction", three[1], three[2], "--direction-weights", "0,1", "--seeds", "0",
                       "--max-scenes", "1", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "sweep.json").read_text())
    assert sorted(result["mean"]) == ["0+0", "0+1", "2+0", "2+1"]
    assert result["direction"] == {"from": three[1], "to": three[2], "weights": [0.0, 1.0]}
    failures = {k: v["failure_rate"] for k, v in result["mean"].items()}
    best = min(failures, key=failures.__getitem__)
    assert result["best_factor"] == [float(x) for x in best.split("+")]
    assert isinstance(result["best_factor_keeping_realism"], list)  # "0+0" (the base) always qualifies
    base, aligned, stage2 = (_weights(d) for d in three)
    for name, value in _weights(str(out / "x2_d1")).items():
        expected = base[name].double() + 2 * (aligned[name].double() - base[name].double()) + (
            stage2[name].double() - aligned[name].double())
        torch.testing.assert_close(value.double(), expected, atol=1e-6, rtol=0)
    assert all(torch.equal(v, base[k]) for k, v in _weights(str(out / "x0_d0")).items())
    assert (out / "sweep.png").stat().st_size > 1000
    assert "direction weight" in capsys.readouterr().out


def test_held_out_soup_averages_the_runs_with_the_lowest_held_out_failure(three: list[str], tmp_path, data_root,
                                                                          capsys, load_script) -> None:  # type: ignore[no-untyped-def]
    soup = load_script("held_out_soup")
    pytest.importorskip("trafficrlhf_nuscenes_pred")
    out = tmp_path / "best2"
    code = soup.main(["--model", "example_gru", "--runs", *three, "--keep", "2", "--seeds", "0,1",
                      "--max-scenes", "2", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "selection.json").read_text())
    assert result["scenes"] == 2 and result["seeds"] == [0, 1] and sorted(result["ranking"]) == sorted(three)
    for run in three:  # the mean is over the seeds' reports
        reports = result["per_seed"][run]
        assert len(reports) == 2
        assert result["mean"][run]["failure_rate"] == pytest.approx(sum(r["failure_rate"] for r in reports) / 2)
    failures = [result["mean"][run]["failure_rate"] for run in result["ranking"]]
    assert failures == sorted(failures) and result["kept"] == result["ranking"][:2]
    kept = [_weights(d) for d in result["kept"]]
    for name, value in _weights(str(out)).items():
        torch.testing.assert_close(value.double(), (kept[0][name].double() + kept[1][name].double()) / 2,
                                   atol=1e-6, rtol=0)
    assert json.loads((out / "averaged_from.json").read_text())["sources"] == result["kept"]
    assert "| rank | run |" in capsys.readouterr().out


def test_held_out_soup_speed_guard_and_bad_requests_refused_before_driving(three: list[str], tmp_path, capsys,
                                                                            load_script) -> None:  # type: ignore[no-untyped-def]
    soup = load_script("held_out_soup")
    # the speed guard, on canned held-out figures: the run that avoids failures by crawling is ranked last and
    # never kept; with none fast enough nothing is written
    # (failure, speed / log); three[1] and three[3] tie, so the given order decides between them
    three = [*three, shutil.copytree(three[1], three[1] + "_copy")]
    figures = {three[0]: (0.01, 0.5), three[1]: (0.05, 1.0), three[2]: (0.03, 0.95), three[3]: (0.05, 1.0)}

    def canned(model, checkpoints, guidance, scenario, seeds, desc):  # type: ignore[no-untyped-def]
        return {key: [{k: 0.0 for k in soup.KEYS} | {"failure_rate": figures[run][0] + 0.001 * seed,
                                                     "speed_ratio": figures[run][1]} for seed in seeds]
                for key, run in checkpoints.items()}

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(soup, "held_out_scenes", lambda every, first, split: (["s"], None))
        patch.setattr(soup, "held_out_reports", canned)
        plain = soup.select_and_average("example_gru", three, 2, [0, 1], str(tmp_path / "plain"), None, 10)
        guarded = soup.select_and_average("example_gru", three, 2, [0, 1], str(tmp_path / "guarded"), None, 10,
                                          min_speed_ratio=0.9)
        with pytest.raises(TrafficRLHFError, match="min_speed_ratio"):
            soup.select_and_average("example_gru", three, 2, [0], str(tmp_path / "none"), None, 10,
                                    min_speed_ratio=1.01)
    assert plain["ranking"] == [three[0], three[2], three[1], three[3]] and plain["kept"] == [three[0], three[2]]
    assert plain["mean"][three[0]]["failure_rate"] == pytest.approx(0.0105)
    assert guarded["ranking"] == [three[2], three[1], three[3], three[0]] and guarded["kept"] == [three[2], three[1]]
    three = three[:3]
    assert not (tmp_path / "none").exists()
    for runs, keep, message in ((three, 4, "keep between 2 and 3"), (three, 1, "keep between 2 and 3"),
                                ([three[0], three[0], three[1]], 2, "twice"),
                                ([three[0], str(tmp_path / "missing")], 2, "does not exist")):
        code = soup.main(["--model", "example_gru", "--runs", *runs, "--keep", str(keep), "--out",
                          str(tmp_path / "never")])
        assert code == 2
        err = capsys.readouterr().err
        assert err.startswith("Error:") and message in err
    assert not (tmp_path / "never").exists()


def test_greedy_soup_adds_a_run_only_when_the_held_out_failure_does_not_rise(three: list[str], tmp_path,
                                                                             capsys, load_script) -> None:  # type: ignore[no-untyped-def]
    soup = load_script("held_out_soup")
    runs = [*three, _saved(tmp_path, "run3", seed=3)]
    a, b, c, d = runs[2], runs[0], runs[3], runs[1]  # the held-out ranking the canned figures below give
    single = {a: 0.02, b: 0.03, c: 0.04, d: 0.05}
    # held-out failure of each trial soup: {a,b} improves, adding c would not, adding d does
    soups = {frozenset({a, b}): 0.015, frozenset({a, b, c}): 0.018, frozenset({a, b, d}): 0.012}
    driven = []

    def canned(model, checkpoints, guidance, scenario, seeds, desc):  # type: ignore[no-untyped-def]
        figures = {}
        for key, folder in checkpoints.items():
            if folder in single:
                failure = single[folder]
            else:
                with open(os.path.join(folder, "averaged_from.json"), encoding="utf-8") as handle:
                    failure = soups.get(frozenset(json.load(handle)["sources"]), 0.5)  # others: worse
            driven.append(folder)
            figures[key] = [{k: 0.0 for k in soup.KEYS} | {"failure_rate": failure, "speed_ratio": 1.0}
                            for _ in seeds]
        return figures

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(soup, "held_out_scenes", lambda every, first, split: (["s"], None))
        patch.setattr(soup, "held_out_reports", canned)
        result = soup.select_and_average("example_gru", runs, None, [0, 1], str(tmp_path / "greedy"), None, 10)
        # when no trial improves on the best run, the soup is that run, copied
        single[a] = 0.001
        alone = soup.select_and_average("example_gru", runs, None, [0], str(tmp_path / "alone"), None, 10)
    assert result["ranking"] == [a, b, c, d] and result["kept"] == [a, b, d]
    assert [(t["run"], t["soup_size"], t["accepted"]) for t in result["greedy"]] == [
        (b, 2, True), (c, 3, False), (d, 3, True)]
    assert [t["mean"]["failure_rate"] for t in result["greedy"]] == pytest.approx([0.015, 0.018, 0.012])
    assert len(driven) == 4 + 3 + 4 + 3  # every run once, then one drive per trial (both calls)
    kept = [_weights(folder) for folder in (a, b, d)]
    for name, value in _weights(str(tmp_path / "greedy")).items():
        torch.testing.assert_close(value.double(), sum(w[name].double() for w in kept) / 3, atol=1e-6, rtol=0)
    assert alone["kept"] == [a] and not any(t["accepted"] for t in alone["greedy"])
    assert all(torch.equal(v, _weights(a)[k]) for k, v in _weights(str(tmp_path / "alone")).items())
    # --greedy and --keep exclude each other; one of them is required
    for extra in ([], ["--greedy", "--keep", "2"]):
        with pytest.raises(SystemExit):
            soup.main(["--model", "example_gru", "--runs", *runs, *extra, "--out", str(tmp_path / "never")])
    assert "--keep" in capsys.readouterr().err and not (tmp_path / "never").exists()


def test_graft_takes_the_prefixed_tensors_from_the_part_and_the_rest_from_the_body(three: list[str], tmp_path,
                                                                                 capsys) -> None:  # type: ignore[no-untyped-def]
    """Bitwise: every ``history.`` tensor is the part's, every other the body's, the config the part's; a body
    without the prefixed module (a model saved before a head was added) gets it; the result loads."""
    from trafficrlhf_sdk.alignment import graft_checkpoint

    body, part = three[0], three[1]
    out = graft_checkpoint(body, part, str(tmp_path / "grafted"), prefixes=("history.",))
    got, b, p = _weights(out), _weights(body), _weights(part)
    assert got.keys() == b.keys() and any(k.startswith("history.") for k in got)
    for name, tensor in got.items():
        assert torch.equal(tensor, (p if name.startswith("history.") else b)[name]), name
    assert json.load(open(os.path.join(out, "grafted_from.json")))["prefixes"] == ["history."]
    assert gru.ExampleGRUAdapter.from_pretrained(out) is not None

    headless = str(tmp_path / "headless")
    shutil.copytree(body, headless)
    save_file({k: v for k, v in b.items() if not k.startswith("history.")},
              os.path.join(headless, "model.safetensors"))
    again = _weights(graft_checkpoint(headless, part, str(tmp_path / "grafted2"), prefixes=("history.",)))
    assert again.keys() == got.keys() and all(torch.equal(again[k], got[k]) for k in got)

    with pytest.raises(SystemExit) as done:
        main(["graft", part, "--body", body, "--prefix", "history.", "--out", str(tmp_path / "cli")])
    assert done.value.code in (0, None) and "history." in capsys.readouterr().out
    assert all(torch.equal(v, got[k]) for k, v in _weights(str(tmp_path / "cli")).items())


def test_graft_refuses_a_prefix_that_matches_nothing_other_architectures_and_overwriting_an_input(
        three: list[str], tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.alignment import graft_checkpoint

    with pytest.raises(DataFormatError, match="no tensor whose name starts with"):
        graft_checkpoint(three[0], three[1], str(tmp_path / "a"), prefixes=("nothing.",))
    with pytest.raises(TrafficRLHFError, match="one of the inputs"):
        graft_checkpoint(three[0], three[1], three[0], prefixes=("history.",))
    small = gru.ExampleGRUAdapter()
    small.build({"hidden": 32})
    small.save_pretrained(str(tmp_path / "small"))
    with pytest.raises(DataFormatError, match=r"tensor .* is .* in"):
        graft_checkpoint(str(tmp_path / "small"), three[1], str(tmp_path / "b"), prefixes=("history.",))
    with pytest.raises(SystemExit) as failed:
        main(["graft", three[1], "--body", str(tmp_path / "nope"), "--out", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert failed.value.code == 2 and err.startswith("Error:") and "Traceback" not in err


def test_development_evaluation_over_several_seeds_prints_each_then_their_mean(load_script, monkeypatch,
                                                                               capsys) -> None:  # type: ignore[no-untyped-def]
    dev = load_script("align_dev_eval")
    assert dev.seed_list("0-3,8") == [0, 1, 2, 3, 8]
    assert dev.seed_list("2, 1") == [2, 1]
    for bad in ("", "a", "3-1", "1-x", "0-2,1"):
        with pytest.raises(argparse.ArgumentTypeError, match="--seeds"):
            dev.seed_list(bad)

    def fake_report(model, checkpoint, guidance, scenario, seed, options=None, **saving):  # type: ignore[no-untyped-def]
        return {"wall_s": 1.0, "failure_rate": 0.01 * (seed + 1), "collision_rate": 0.0}

    monkeypatch.setattr(dev, "held_out_report", fake_report)
    monkeypatch.setattr(dev, "held_out_scenes", lambda *args: (["scene-0001", "scene-0002"], None))
    monkeypatch.setattr("sys.argv", ["align_dev_eval.py", "--model", "ctg", "--seeds", "0-2"])
    dev.main()
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["seed"] for line in lines[:3]] == [0, 1, 2] and lines[1]["failure_rate"] == 0.02
    assert lines[3]["seeds"] == [0, 1, 2] and lines[3]["scenes"] == 2
    assert lines[3]["mean"] == {"wall_s": 3.0, "failure_rate": 0.02, "collision_rate": 0.0}
    monkeypatch.setattr("sys.argv", ["align_dev_eval.py", "--model", "ctg", "--seed", "1", "--seeds", "0-2"])
    with pytest.raises(SystemExit) as exit_info:
        dev.main()
    assert exit_info.value.code == 2


def test_development_reports_saved_with_out_pair_up_in_compare(load_script, monkeypatch, val_scenes,
                                                                tmp_path) -> None:  # type: ignore[no-untyped-def]
    from click.testing import CliRunner

    from trafficrlhf_sdk.cli import get_cli
    from trafficrlhf_sdk.plugins import build_policy

    dev = load_script("align_dev_eval")
    monkeypatch.setattr(dev, "build_policy", lambda model, options: build_policy(model, {}))
    ids = [f"scene-{i}" for i in range(val_scenes.num_scenes)]
    for model in ("constant_velocity", "log_replay"):
        report = dev.held_out_report(model, None, None, val_scenes, 0, out_dir=str(tmp_path / model / "seed_0"),
                                     metadata={"scene_ids": ids, "mirror": False})
        saved = json.loads((tmp_path / model / "seed_0" / "results.json").read_text())
        assert saved["metadata"]["scene_ids"] == ids and saved["metadata"]["model"] == model
        assert saved["metrics"]["failure_rate"] == pytest.approx(report["failure_rate"], abs=5e-5)
        assert len(saved["per_scene"]["failure_rate"]) == len(ids)
    out = CliRunner().invoke(get_cli(), ["compare", str(tmp_path / "constant_velocity" / "seed_0"),
                                         str(tmp_path / "log_replay" / "seed_0"), "--interval"])
    assert out.exit_code == 0, out.output
    assert "constant_velocity -> log_replay (1 / 1 seed(s))" in out.output
