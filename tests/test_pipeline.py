"""The pipeline's one cache and resume scheme (trafficrlhf_sdk.pipeline): a finished step is a no-op, a changed
setting is refused naming it, a step stopped midway runs again, and the RLHF loop resumes from its last finished
step. The stages' own functions are replaced by counting stand-ins, so these tests need no data."""

from __future__ import annotations

import json
import os
from typing import Any

import pytest

from trafficrlhf_sdk.pipeline import MANIFEST, StepConfigError, input_differences, read_manifest, run_step


def _counting(calls: list[str], outputs: dict[str, Any] | None = None):  # type: ignore[no-untyped-def]
    def work() -> dict[str, Any]:
        calls.append("ran")
        return outputs or {"value": len(calls)}

    return work


def test_a_finished_step_returns_its_outputs_without_running(tmp_path) -> None:
    calls: list[str] = []
    folder = str(tmp_path / "step")
    first = run_step("train", folder, {"lr": 0.1, "groups": ("a", "b")}, _counting(calls))
    again = run_step("train", folder, {"groups": ["a", "b"], "lr": 0.1}, _counting(calls))  # same inputs as JSON
    assert calls == ["ran"]
    assert not first.cached and again.cached and again.outputs == first.outputs == {"value": 1}
    assert again.digest == first.digest
    manifest = read_manifest(folder)
    assert manifest is not None and manifest["step"] == "train" and manifest["inputs"]["lr"] == 0.1
    assert manifest["completed"].endswith("+00:00") and manifest["outputs"] == {"value": 1}


def test_a_changed_setting_is_refused_naming_it_and_overwrite_runs_again(tmp_path) -> None:
    calls: list[str] = []
    folder = tmp_path / "step"
    run_step("align", str(folder), {"align": {"epochs": 20, "alpha": 3.0}, "seed": 0}, _counting(calls))
    (folder / "checkpoint.bin").write_bytes(b"old")
    with pytest.raises(StepConfigError) as refused:
        run_step("align", str(folder), {"align": {"epochs": 25, "alpha": 3.0}, "seed": 0}, _counting(calls))
    message = str(refused.value)
    assert "align.epochs: 20 -> 25" in message and "alpha" not in message and "overwrite" in message
    assert calls == ["ran"] and (folder / "checkpoint.bin").exists()  # nothing was touched
    redone = run_step("align", str(folder), {"align": {"epochs": 25, "alpha": 3.0}, "seed": 0}, _counting(calls),
                      overwrite=True)
    assert calls == ["ran", "ran"] and not redone.cached and redone.outputs == {"value": 2}
    assert not (folder / "checkpoint.bin").exists()  # the old step's files went with it
    assert read_manifest(str(folder))["inputs"]["align"]["epochs"] == 25  # type: ignore[index]


def test_a_step_stopped_midway_runs_again_and_keeps_what_it_left(tmp_path) -> None:
    folder = tmp_path / "step"
    calls: list[str] = []

    def interrupted() -> dict[str, Any]:
        (folder / "partial.txt").write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_step("label", str(folder), {"limit": 4}, interrupted)
    assert read_manifest(str(folder)) is None and (folder / "partial.txt").exists()

    def resumed() -> dict[str, Any]:
        calls.append((folder / "partial.txt").read_text())  # the step sees what the stopped run left
        return {"labelled": 4}

    done = run_step("label", str(folder), {"limit": 4}, resumed)
    assert calls == ["half"] and not done.cached and done["labelled"] == 4


def test_an_upstream_step_redone_makes_the_downstream_one_differ(tmp_path) -> None:
    calls: list[str] = []
    up = run_step("generate", str(tmp_path / "a"), {"seed": 0}, _counting(calls))
    run_step("label", str(tmp_path / "b"), {"limit": 2}, _counting(calls), after=[up])
    up2 = run_step("generate", str(tmp_path / "a"), {"seed": 1}, _counting(calls), overwrite=True)
    with pytest.raises(StepConfigError, match=r"after\[0\]: \"generate:"):
        run_step("label", str(tmp_path / "b"), {"limit": 2}, _counting(calls), after=[up2])


def test_a_broken_manifest_is_an_error_saying_how_to_fix_it(tmp_path) -> None:
    folder = tmp_path / "step"
    folder.mkdir()
    (folder / MANIFEST).write_text("{not json")
    with pytest.raises(Exception, match="delete it"):
        run_step("x", str(folder), {}, lambda: {})


def test_input_differences_names_nested_keys_and_absent_ones() -> None:
    old = {"config": {"max_epochs": 30, "seed": 0}, "campaigns": ["round0"]}
    new = {"config": {"max_epochs": 12, "seed": 0, "margin": 0.1}, "campaigns": ["round0", "round1"]}
    assert input_differences(old, new) == ['campaigns: ["round0"] -> ["round0", "round1"]',
                                           "config.margin: <absent> -> 0.1", "config.max_epochs: 30 -> 12"]
    assert input_differences(old, old) == []


# --------------------------------------------------------------------------------------- the loop over the steps
class _FakeStages:
    """Stand-ins for the stage functions the steps call, counting calls; ``fail_at`` raises in that stage."""

    def __init__(self, fail_at: str | None = None) -> None:
        self.calls: list[str] = []
        self.fail_at = fail_at

    def _call(self, name: str) -> None:
        self.calls.append(name)
        if name == self.fail_at:
            raise KeyboardInterrupt(name)

    def install(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import trafficrlhf_sdk.alignment.recipe as recipe
        import trafficrlhf_sdk.feedback.campaign as campaign
        import trafficrlhf_sdk.feedback.synthetic as synthetic
        import trafficrlhf_sdk.plugins as plugins
        import trafficrlhf_sdk.reward.card as card
        import trafficrlhf_sdk.reward.evaluation as evaluation
        from trafficrlhf_sdk.feedback.store import FeedbackStore

        fake = self

        class Source:
            def scene_ids(self, split: str) -> list[str]:
                return [f"scene-{i}" for i in range(20)]

        def create_campaign(store: FeedbackStore, config: Any, **_: Any) -> None:
            fake._call("generate")
            store.create_campaign(config.name, config.model, config.guidance, config.seed, config.num_candidates,
                                  config.model_dump(mode="json"), "test")

        class Annotator:
            def __init__(self, store: Any, name: str, settings: Any) -> None:
                known = {a.name: a for a in store.annotators()}
                self.annotator = known[name] if name in known else store.add_annotator(name)[0]

            def label(self, campaign: Any, limit: int | None = None) -> dict[str, int]:
                fake._call("label")
                return {"labeled": limit or 0, "none_realistic": 0, "ties": 0, "skipped": 0}

        class Trained:
            def __init__(self) -> None:
                self.card = {"metrics": {"val_accuracy": 0.75}, "data": {}}
                self.dataset_info = {"train_pairs": 8, "contrast_pairs": 0}
                self.probes = None

        def train_and_save(config: Any, dataset: Any, out_dir: str, **_: Any) -> Trained:
            fake._call("reward_model")
            os.makedirs(out_dir, exist_ok=True)
            return Trained()

        class Dataset:
            num_contexts = 2
            pairs = __import__("torch").zeros(8, 3)

        def run_recipe(recipe: Any, output_dir: str, **_: Any) -> dict[str, Any]:
            fake._call("align")
            return {"model": recipe.model, "epochs": 1, "wall_time_s": 0.0, "reward_first": 0.0, "reward_last": 0.1,
                    "heldout_realism_first": 0.0, "heldout_realism_last": 0.0}

        monkeypatch.setattr(plugins, "get_scenario_source", lambda name, **options: Source())
        monkeypatch.setattr(campaign, "create_campaign", create_campaign)
        monkeypatch.setattr(synthetic, "SyntheticAnnotator", Annotator)
        monkeypatch.setattr(card, "train_and_save", train_and_save)
        monkeypatch.setattr(evaluation, "load_preferences", lambda *a, **k: (Dataset(), None))
        monkeypatch.setattr(recipe, "run_recipe", run_recipe)


LOOP = {"model": "example_gru", "guidance": "no_collision", "rounds": 2, "contexts_per_round": 2, "candidate_pool": 1,
        "candidates": 3, "contrast_scenes": 0, "probe_scenes": 0, "annotators": ["attentive"]}


def test_the_loop_resumes_from_its_last_finished_step(tmp_path, monkeypatch) -> None:
    from trafficrlhf_sdk.loop import RLHFConfig, rlhf

    out = str(tmp_path / "run")
    stopped = _FakeStages(fail_at="align")
    stopped.install(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        rlhf(RLHFConfig(**LOOP), out, log=lambda line: None)
    # round 0: two campaigns (guided, unguided), each labelled, a reward model, then alignment stopped
    assert stopped.calls == ["generate", "generate", "label", "label", "reward_model", "align"]
    assert read_manifest(os.path.join(out, "round_0", "reward_model")) is not None
    assert read_manifest(os.path.join(out, "round_0", "aligned")) is None

    resumed = _FakeStages()
    resumed.install(monkeypatch)
    lines: list[str] = []
    result = rlhf(RLHFConfig(**LOOP), out, log=lines.append)
    assert resumed.calls == ["align", "generate", "generate", "label", "label", "reward_model", "align"]
    assert sum("skipped" in line for line in lines) == 5  # round 0's finished steps returned at once
    assert [r["aligned"] for r in result["rounds"]] == [os.path.join(out, f"round_{r}", "aligned") for r in (0, 1)]
    assert result["rounds"][1]["campaigns"] == ["round1", "round1_unguided"]
    # round 1's reward model reads both rounds' labels; its candidates come from round 0's aligned model
    inputs = read_manifest(os.path.join(out, "round_1", "reward_model"))["inputs"]  # type: ignore[index]
    assert inputs["campaigns"] == ["round0", "round0_unguided", "round1", "round1_unguided"]
    generated = read_manifest(os.path.join(out, "round_1", "campaigns", "round1"))["inputs"]  # type: ignore[index]
    assert generated["campaign"]["model_options"] == {"checkpoint": os.path.join(out, "round_0", "aligned")}

    again = _FakeStages()
    again.install(monkeypatch)
    assert rlhf(RLHFConfig(**LOOP), out, log=lambda line: None) == result and again.calls == []  # a no-op


def test_the_loop_refuses_a_changed_setting_naming_it(tmp_path, monkeypatch) -> None:
    from trafficrlhf_sdk.loop import RLHFConfig, rlhf

    out = str(tmp_path / "run")
    _FakeStages().install(monkeypatch)
    rlhf(RLHFConfig(**{**LOOP, "rounds": 1}), out, log=lambda line: None)
    changed = RLHFConfig(**{**LOOP, "rounds": 1, "reward": {"max_epochs": 7}})
    with pytest.raises(StepConfigError, match=r"config\.max_epochs: 30 -> 7"):
        rlhf(changed, out, log=lambda line: None)
    counting = _FakeStages()
    counting.install(monkeypatch)
    rlhf(changed, out, log=lambda line: None, overwrite=True)
    assert counting.calls == ["reward_model", "align"]  # the reward model and what reads it; nothing upstream
    with open(os.path.join(out, "round_0", "aligned", MANIFEST), encoding="utf-8") as handle:
        assert json.load(handle)["inputs"]["after"][0].startswith("reward_model:")


# --------------------------------------------------------------------------------------- weights among the inputs
def _checkpoint(folder: Any, digest: str) -> str:
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "config.json"), "w", encoding="utf-8") as handle:
        json.dump({"adapter": "example_gru", "weights": {"file": "model.safetensors", "sha256": digest}}, handle)
    return str(folder)


def test_new_weights_under_the_same_name_are_a_changed_setting(tmp_path, monkeypatch) -> None:
    """A step that read a checkpoint or reward-model folder records its weights' digest: new weights in the same
    folder make the finished step differ (refused naming the weights) instead of returning the old result."""
    import trafficrlhf_sdk.alignment.recipe as recipe_module
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.pipeline.stages import align_step

    calls: list[str] = []
    monkeypatch.setattr(recipe_module, "run_recipe", lambda recipe, folder, **_: calls.append("ran") or {"epochs": 1})
    start = _checkpoint(tmp_path / "start", "a" * 64)
    reward = _checkpoint(tmp_path / "rm", "b" * 64)
    recipe = AlignRecipe(model="example_gru", checkpoint=start, reward_model=reward)
    out = str(tmp_path / "aligned")
    first = align_step(out, recipe)
    recorded = read_manifest(out)["inputs"]["weights"]  # type: ignore[index]
    assert recorded == {"checkpoint": "a" * 64, "reward_model": "b" * 64}
    assert align_step(out, recipe).cached and calls == ["ran"]
    _checkpoint(tmp_path / "rm", "c" * 64)  # the reward model retrained in place
    with pytest.raises(StepConfigError, match=r"weights\.reward_model"):
        align_step(out, recipe)
    assert not first.cached and calls == ["ran"]


def test_the_weights_digest_of_bundled_names_folders_and_builtins(tmp_path) -> None:
    from trafficrlhf_sdk.pipeline.stages import _weights_digest

    assert _weights_digest(_checkpoint(tmp_path / "x", "d" * 64)) == "d" * 64
    assert _weights_digest("builtin:failure") is None and _weights_digest(None) is None
    assert _weights_digest(str(tmp_path)) is None  # a folder without config.json
    bundled = _weights_digest("ctg-4s")
    assert bundled is not None and len(bundled) == 64
