"""The alignment ladder: rows that differ only in their reward, written as a table, a plot and JSON."""

from __future__ import annotations

import json
import math

import pytest
from pydantic import ValidationError

from trafficrlhf_sdk.experiments.ladder import LADDER_ROWS, LadderConfig, run_ladder
from trafficrlhf_sdk.pipeline.step import StepResult

TINY_RECIPE = """
model = "ctg"
checkpoint = "ctg-4s"
reward_model = "builtin:failure"
model_options = { steer_road = true, steer_gate = true }

[align]
guidance = "no_collision"
epochs = 1
contexts_per_epoch = 2
samples_per_context = 2
ppo_epochs = 1
minibatch_contexts = 2
failure_fraction = 0.5
failure_scenes = 2
num_scenes = 4
credit = "agent"
groups = ["steer"]
learning_rate = 0.001
"""


def _fake_steps(monkeypatch, aligned: dict[str, object], failure=lambda name: 0.05) -> None:  # type: ignore[no-untyped-def]
    """Replace the ladder's alignment and evaluation steps: each alignment is recorded in ``aligned`` (folder name
    -> recipe), each evaluation reports ``failure(folder name)`` (the base: 0.1)."""
    import trafficrlhf_sdk.pipeline as pipeline

    def fake_align(folder, row, **_):  # type: ignore[no-untyped-def]
        aligned[folder.rsplit("/", 1)[-1]] = row
        return StepResult("align", folder, "x", {"folder": folder, "epochs": 1})

    def fake_evaluate(folder, request, **_):  # type: ignore[no-untyped-def]
        name = folder.rsplit("/", 1)[-1]
        value = 0.1 if name == "base" else failure(name)
        return StepResult("evaluate", folder, "x", {"metrics": {"failure_rate": value, "speed_ratio": 1.0}})

    monkeypatch.setattr(pipeline, "align_step", fake_align)
    monkeypatch.setattr(pipeline.stages, "align_step", fake_align)  # what align_steps calls
    monkeypatch.setattr(pipeline, "evaluate_step", fake_evaluate)


def test_rows_share_every_fine_tuning_setting_but_the_reward(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE)
    aligned: dict[str, object] = {}
    _fake_steps(monkeypatch, aligned)
    (tmp_path / "rm").mkdir()
    config = LadderConfig(recipe=str(recipe), reward_model=str(tmp_path / "rm"), agreement_contexts=0, draws=1)
    rows = run_ladder(config, str(tmp_path / "out"), log=lambda _: None)
    assert sorted(aligned) == sorted(LADDER_ROWS) and set(rows) == {"base", *LADDER_ROWS}
    base = aligned["a"].model_dump()  # type: ignore[attr-defined]
    for key, row in aligned.items():
        dumped = row.model_dump()  # type: ignore[attr-defined]
        assert dumped["reward_model"] == (LADDER_ROWS[key][1] or str(tmp_path / "rm"))
        expected_align = {**base["align"], "alpha": 0.0} if key == "d" else base["align"]
        assert dumped["align"] == expected_align, key
        assert {k: v for k, v in dumped.items() if k not in ("reward_model", "align")} == \
            {k: v for k, v in base.items() if k not in ("reward_model", "align")}
    table = (tmp_path / "out" / "ladder.md").read_text()
    assert "(a) built-in failure reward | 0.0500 (-50.0 %) | -50.0 % |" in table
    assert "- the reward model, (b) to (c): +0.0" in table
    assert (tmp_path / "out" / "ladder.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_every_row_runs_in_each_draw_with_its_own_training_seed(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.experiments.steps import read_recipe

    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE + "seed = 5\n")
    aligned: dict[str, object] = {}
    failures = {"a": (0.04, 0.05, 0.06), "b": (0.06, 0.07, 0.05), "c": (0.05, 0.05, 0.05), "d": (0.1, 0.1, 0.1)}

    def failure(name: str) -> float:
        key, _, seed = name.removeprefix("row_").partition("_seed")
        return failures[key][int(seed) - 5 if seed else 0]

    _fake_steps(monkeypatch, aligned, failure)
    (tmp_path / "rm").mkdir()
    config = LadderConfig(recipe=str(recipe), reward_model=str(tmp_path / "rm"), agreement_contexts=0)
    assert config.draws == 3
    rows = run_ladder(config, str(tmp_path / "out"), log=lambda _: None)
    assert sorted(aligned) == sorted(f"{k}{s}" for k in LADDER_ROWS for s in ("", "_seed6", "_seed7"))
    written = read_recipe(str(recipe)).align.model_dump(exclude_unset=True)
    for key in LADDER_ROWS:
        first = aligned[key].align  # type: ignore[attr-defined]
        # draw 0 is the recipe as written: the same set fields, so the digest of the recipe as written
        assert first.model_dump(exclude_unset=True) == {**written, **({"alpha": 0.0} if key == "d" else {})}
        for seed in (6, 7):
            other = aligned[f"{key}_seed{seed}"].align  # type: ignore[attr-defined]
            assert other.model_dump() == {**first.model_dump(), "seed": seed}
        assert [d["seed"] for d in rows[key]["draws"]] == [5, 6, 7]
    table = (tmp_path / "out" / "ladder.md").read_text()
    # row (a): -60 / -50 / -40 %, mean -50 %; t(0.975, 2) = 4.303, s = 10 -> half-width 24.8 points
    assert "(a) built-in failure reward | 0.0500 (-50.0 %) | -60.0 / -50.0 / -40.0 % | -74.8 % to -25.2 % |" in table
    assert "95 % interval over draws (t)" in table and "mean of 3 training draws (seeds 5, 6, 7)" in table
    # the annotator's link, paired by seed: (b) - (a) = +20, +20, -10 points -> mean +10.0
    assert "- the annotator, (a) to (b): +10.0 (-33.0 to +53.0)" in table
    saved = json.loads((tmp_path / "out" / "ladder.json").read_text())
    assert [d["evaluation"]["metrics"]["failure_rate"] for d in saved["a"]["draws"]] == [0.04, 0.05, 0.06]


def test_control_row_of_a_recipe_without_imitation_term_is_the_start(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE + "imitation_coef = 0.0\n")
    aligned: dict[str, object] = {}
    _fake_steps(monkeypatch, aligned)
    (tmp_path / "rm").mkdir()
    config = LadderConfig(recipe=str(recipe), reward_model=str(tmp_path / "rm"), agreement_contexts=0, draws=2)
    rows = run_ladder(config, str(tmp_path / "out"), log=lambda _: None)
    # alpha = 0 leaves only terms that hold the policy to its start: (d) is not trained, it is the base
    assert sorted(aligned) == ["a", "a_seed1", "b", "b_seed1", "c", "c_seed1"]
    assert rows["d"]["evaluation"] is rows["base"]["evaluation"] and len(rows["d"]["draws"]) == 2
    table = (tmp_path / "out" / "ladder.md").read_text()
    assert "(d) learned reward model, alpha = 0: the start | 0.1000 (+0.0 %) | +0.0 / +0.0 % |" in table
    assert "Row (d) is the starting model itself, not trained" in table


def test_alignments_on_workers_run_the_control_row_last(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk.parallel as parallel
    from trafficrlhf_sdk.errors import TrafficRLHFError
    from trafficrlhf_sdk.experiments import ladder
    from trafficrlhf_sdk.parallel import ExecutionConfig

    seen: list[str] = []
    failing: set[str] = set()

    def fake_tasks(fn, shared, tasks, execution):  # type: ignore[no-untyped-def]
        # a worker runs in the driver's folder, with its data root and the worker's threads
        assert execution.workers == 2 and shared["cwd"] == str(tmp_path) and shared["threads"] == 1
        assert shared["env"] == {"TRAFFICRLHF_DATA": "/data/here"}
        for job in tasks:
            seen.append(job.folder)
            if job.folder in failing:
                yield TrafficRLHFError(f"{job.folder} finished with other settings"), []
            else:
                yield StepResult("align", job.folder, "x", {"folder": job.folder}), [f"logged by {job.folder}"]

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TRAFFICRLHF_DATA", "/data/here")
    monkeypatch.setattr(parallel, "iter_tasks", fake_tasks)
    jobs = [ladder._AlignJob(key, draw, draw, f"{key}{draw}", None, []) for draw in range(2) for key in "abcd"]
    logged: list[str] = []
    done = ladder._align_rows(jobs, False, logged.append, ExecutionConfig(workers=2))
    assert seen == ["a0", "b0", "c0", "a1", "b1", "c1", "d0", "d1"] and set(done) == {j.folder for j in jobs}
    assert "logged by c1" in logged  # what a worker logged reaches the driver's log
    failing.add("b1")  # an SDK error on a worker is raised in the driver as itself
    with pytest.raises(TrafficRLHFError, match="b1 finished with other settings"):
        ladder._align_rows(jobs, False, logged.append, ExecutionConfig(workers=2))


def test_t_quantile_matches_scipy() -> None:
    from scipy.stats import t

    from trafficrlhf_sdk.experiments.ladder import _t_quantile

    for df in (1, 2, 3, 5, 9, 40):
        assert _t_quantile(0.975, df) == pytest.approx(t.ppf(0.975, df), abs=1e-4)
    with pytest.raises(ValueError, match=r"0\.5 < p < 1"):
        _t_quantile(0.2, 3)


def test_later_rounds_label_the_previous_policys_closed_loop_contexts(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk.pipeline as pipeline

    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE)
    calls: list[tuple[str, object]] = []

    def fake_generate(folder, db, campaign, **_):  # type: ignore[no-untyped-def]
        calls.append(("generate", campaign))
        return StepResult("generate", folder, "x", {"campaign": campaign.name, "contexts": campaign.num_contexts})

    def fake_label(folder, db, campaign, annotators, **_):  # type: ignore[no-untyped-def]
        return StepResult("label", folder, "x", {"campaign": campaign})

    def fake_reward(folder, config, db, campaigns, **kw):  # type: ignore[no-untyped-def]
        calls.append(("reward", list(campaigns)))
        calls.append(("contrast", (kw["contrast_scenes"], tuple(kw["contrast_annotators"]))))
        return StepResult("reward_model", folder, "x", {"folder": folder})

    def fake_align(folder, row, after=(), **_):  # type: ignore[no-untyped-def]
        calls.append(("align", (folder, row.reward_model)))
        calls.append(("after", (folder, [step.name for step in after])))
        return StepResult("align", folder, "x", {"folder": folder, "epochs": 1})

    def fake_evaluate(folder, request, **_):  # type: ignore[no-untyped-def]
        return StepResult("evaluate", folder, "x", {"metrics": {"failure_rate": 0.1, "speed_ratio": 1.0}})

    for name, fake in (("generate_step", fake_generate), ("label_step", fake_label),
                       ("reward_model_step", fake_reward), ("align_step", fake_align),
                       ("evaluate_step", fake_evaluate)):
        monkeypatch.setattr(pipeline, name, fake)
    monkeypatch.setattr(pipeline.stages, "align_step", fake_align)  # what align_steps calls
    out = tmp_path / "out"
    config = LadderConfig(recipe=str(recipe), campaigns=((5, 1),), rounds=2, round_contexts=3, agreement_contexts=0)
    run_ladder(config, str(out), log=lambda _: None)
    campaigns = [c for kind, c in calls if kind == "generate"]
    first, second = campaigns  # type: ignore[misc]
    round_0 = str(out / "reward_model")
    policy = str(out / "rounds" / "round_0" / "aligned")
    assert first.contexts == "log" and first.model_options["checkpoint"] == "ctg-4s"  # type: ignore[attr-defined]
    assert (second.contexts, second.num_contexts, second.seed) == ("closed_loop", 3, 11)  # type: ignore[attr-defined]
    assert second.model_options["checkpoint"] == policy  # type: ignore[attr-defined]
    assert [c for kind, c in calls if kind == "reward"] == [["ladder-train-0"], ["ladder-train-0", "ladder-round-1"]]
    aligned = dict(c for kind, c in calls if kind == "align")  # type: ignore[misc]
    last = str(out / "rounds" / "round_1" / "reward_model")
    assert aligned[policy] == round_0 and aligned[str(out / "rows" / "c")] == last
    assert aligned[str(out / "rows" / "d")] == last
    assert "round 1's" in (out / "ladder.md").read_text()
    # the built-in rows read no learned reward, so retraining it leaves them done; the learned rows wait for it
    after = dict(c for kind, c in calls if kind == "after")  # type: ignore[misc]
    assert after[str(out / "rows" / "a")] == after[str(out / "rows" / "b")] == []
    assert after[str(out / "rows" / "c")] == after[str(out / "rows" / "d")] == ["reward_model"]
    assert {c for kind, c in calls if kind == "contrast"} == {(0, ())}  # no contrast items by default
    calls.clear()
    run_ladder(config.model_copy(update={"contrast_scenes": 7}), str(tmp_path / "o2"), log=lambda _: None)
    assert {c for kind, c in calls if kind == "contrast"} == {(7, ("attentive", "safety", "flow"))}
    calls.clear()
    with pytest.raises(ValidationError, match=r"rounds=2 trains the reward model here.*--reward-model"):
        LadderConfig(recipe=str(recipe), rounds=2, reward_model=str(tmp_path / "rm"))
    # the campaign seed of round r is the largest of the campaigns' + 10 r, so it never repeats one of theirs
    config3 = config.model_copy(update={"campaigns": ((4, 21), (4, 1)), "rounds": 3})
    run_ladder(config3, str(tmp_path / "o3"), log=lambda _: None)
    seeds = [c.seed for kind, c in calls if kind == "generate"]  # type: ignore[attr-defined]
    assert seeds == [21, 1, 31, 41]
    aligned3 = dict(c for kind, c in calls if kind == "align")  # type: ignore[misc]
    assert aligned3[str(tmp_path / "o3" / "rounds" / "round_1" / "aligned")] == \
        str(tmp_path / "o3" / "rounds" / "round_1" / "reward_model")


def test_config_rejects_unknown_keys(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import main

    config = tmp_path / "ladder.toml"
    config.write_text('campaigns = [[4, 0]]\n[reward]\nmax_epoch = 2\n')
    with pytest.raises(SystemExit) as exit_info:
        main(["experiment", "ladder", "--config", str(config), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2 and "reward.max_epoch" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_config_recipe_is_run_and_model_cannot_contradict_it(tmp_path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import main
    from trafficrlhf_sdk.experiments import ladder

    seen: list[str] = []
    monkeypatch.setattr(ladder, "run_ladder", lambda config, out, **kw: seen.append(config.recipe) or {"base": {}})
    config = tmp_path / "ladder.toml"
    config.write_text('recipe = "my-recipe.toml"\n')
    with pytest.raises(SystemExit) as exit_info:
        main(["experiment", "ladder", "--config", str(config), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 0 and seen == ["my-recipe.toml"]
    with pytest.raises(SystemExit) as exit_info:
        main(["experiment", "ladder", "--model", "bits", "--config", str(config), "--out", str(tmp_path / "o2")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--model bits" in err and "my-recipe.toml" in err
    (tmp_path / "plain.toml").write_text("scenes = 3\n")
    with pytest.raises(SystemExit) as exit_info:
        main(["experiment", "ladder", "--model", "bits", "--config", str(tmp_path / "plain.toml"), "--out",
              str(tmp_path / "o3")])
    assert exit_info.value.code == 0 and seen[-1] == "docs/recipes/bits-ladder.toml"


@pytest.mark.slow
@pytest.mark.data
def test_tiny_ladder_end_to_end_and_resumed(data_root: str, tmp_path) -> None:
    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE)
    config = LadderConfig(recipe=str(recipe), campaigns=((3, 0), (2, 1)), scenes=2, seeds=(0,), agreement_contexts=2,
                          contrast_scenes=2, probe_scenes=2, draws=2,
                          reward={"max_epochs": 1, "batch_size": 2, "ensemble_size": 1, "progress": False})
    out = tmp_path / "ladder"
    rows = run_ladder(config, str(out), log=lambda _: None)
    saved = json.loads((out / "ladder.json").read_text())
    assert set(saved) == {"base", *LADDER_ROWS, "agreement"}
    for key in ("base", *LADDER_ROWS):
        failure = saved[key]["evaluation"]["metrics"]["failure_rate"]
        assert 0 <= failure <= 1 and math.isfinite(failure)
    assert 0 <= saved["agreement"]["start"]["agreement"] <= 1 or saved["agreement"]["start"]["pairs"] == 0
    # every evaluation names its scenes, so the rows can be compared scene by scene (the table's interval)
    named = json.loads((out / "evaluations" / "row_c" / "seed_0" / "results.json").read_text())["metadata"]
    assert len(named["scene_ids"]) == 2 and named["model"] == "ctg" and named["seed"] == 0
    assert "| 95 % interval over draws (t) |" in (out / "ladder.md").read_text()
    end = saved["agreement"]["end"]
    assert sum(v["pairs"] for v in end["by_term"].values()) == end["pairs"]
    assert ("by the judgment term that decides a pair" in (out / "ladder.md").read_text()) == bool(end["pairs"])
    assert set(end["by_gap"]) == {"0.02", "0.05"}
    assert ("whose realism differs by more than a gap" in (out / "ladder.md").read_text()) == bool(end["pairs"])
    # the second draw is its own training run: another seed in its own folder
    second = json.loads((out / "rows" / "a_seed1" / "step.json").read_text())
    assert second["inputs"]["align"]["seed"] == 1 and "seed" not in \
        json.loads((out / "rows" / "a" / "step.json").read_text())["inputs"]["align"]
    assert [d["seed"] for d in saved["c"]["draws"]] == [0, 1]
    again = run_ladder(config, str(out), log=lambda _: None)
    assert all(d["evaluation"].cached for k in LADDER_ROWS for d in again[k]["draws"])
    assert again["base"]["evaluation"].cached
    assert rows["c"]["reward"] == again["c"]["reward"]


def test_agreement_is_redone_when_the_reward_models_weights_or_the_policy_change(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk.reward.loading as loading
    import trafficrlhf_sdk.reward.oracle as oracle
    from trafficrlhf_sdk.experiments import ladder
    from trafficrlhf_sdk.experiments.steps import read_recipe

    recipe_file = tmp_path / "recipe.toml"
    recipe_file.write_text(TINY_RECIPE)
    recipe = read_recipe(str(recipe_file))
    generated: list[list[str]] = []

    def fake_generate(folder, db, campaign, after=(), **_):  # type: ignore[no-untyped-def]
        generated.append([step.digest for step in after])
        return StepResult("generate", folder, "g" + "".join(step.digest for step in after), {})

    runs: list[str] = []
    monkeypatch.setattr(loading, "load_reward", lambda path: path)
    monkeypatch.setattr(oracle, "judgment_agreement", lambda model, store, name: runs.append(name) or {"pairs": 1})
    rm = tmp_path / "rm"
    rm.mkdir()
    (rm / "model.safetensors").write_bytes(b"first")
    config = LadderConfig(recipe=str(recipe_file), agreement_contexts=2)
    steps = {"overwrite": True, "log": lambda _: None}
    db = str(tmp_path / "feedback.sqlite")

    def agreement(policy: list[StepResult]) -> None:
        ladder._agreement(config, recipe, "ckpt", str(rm), db, str(tmp_path), "end", steps, fake_generate, policy,
                         None)

    policy = [StepResult("align", "row_c", "p1", {})]
    agreement(policy)
    agreement(policy)
    assert len(runs) == 1 and generated[-1] == ["p1"]  # the same inputs: done before
    (rm / "model.safetensors").write_bytes(b"retrained")  # same folder, other weights
    agreement(policy)
    assert len(runs) == 2
    agreement([StepResult("align", "row_c", "p2", {})])  # another policy: its candidates and the agreement again
    assert len(runs) == 3 and generated[-1] == ["p2"]


def test_rows_c_and_d_follow_the_weights_of_a_given_reward_model(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk.pipeline as pipeline

    recipe = tmp_path / "recipe.toml"
    recipe.write_text(TINY_RECIPE)
    seen: dict[str, list[str]] = {}

    def fake_align(folder, row, after=(), **_):  # type: ignore[no-untyped-def]
        seen[folder] = [f"{step.name}:{step.digest}" for step in after]
        return StepResult("align", folder, "x", {"folder": folder, "epochs": 1})

    def fake_evaluate(folder, request, **_):  # type: ignore[no-untyped-def]
        return StepResult("evaluate", folder, "x", {"metrics": {"failure_rate": 0.1, "speed_ratio": 1.0}})

    monkeypatch.setattr(pipeline, "align_step", fake_align)
    monkeypatch.setattr(pipeline.stages, "align_step", fake_align)  # what align_steps calls
    monkeypatch.setattr(pipeline, "evaluate_step", fake_evaluate)
    rm = tmp_path / "rm"
    rm.mkdir()
    (rm / "model.safetensors").write_bytes(b"first")
    config = LadderConfig(recipe=str(recipe), reward_model=str(rm), agreement_contexts=0)
    out = tmp_path / "out"
    run_ladder(config, str(out), log=lambda _: None)
    first = dict(seen)
    (rm / "model.safetensors").write_bytes(b"retrained")
    run_ladder(config, str(out), log=lambda _: None)
    for key in ("a", "b"):
        assert first[str(out / "rows" / key)] == seen[str(out / "rows" / key)] == []
    for key in ("c", "d"):
        assert first[str(out / "rows" / key)] != seen[str(out / "rows" / key)]  # other weights: run again
