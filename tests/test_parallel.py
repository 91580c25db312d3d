"""In-process and Ray runs give the same numbers: closed-loop evaluation (scenes x rollouts), feedback-campaign
candidates and PPO rollout sampling. The Ray path runs against a local head on 127.0.0.1 (skipped without Ray)."""

from __future__ import annotations

import pytest
import torch

from trafficrlhf_sdk.evaluation.protocol import EvaluationConfig, evaluate_policy
from trafficrlhf_sdk.parallel import ExecutionConfig, derive_seed, run_tasks
from trafficrlhf_sdk.simulation.policies import NoisyLogPolicy

RAY = ExecutionConfig(workers=2)


@pytest.fixture(scope="module")
def ray_head():  # type: ignore[no-untyped-def]
    """One local Ray head on 127.0.0.1 with 2 CPUs for the module; run_tasks reuses it."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def _square_plus(shared: dict, task: int) -> int:
    return shared["offset"] + task * task


def test_run_tasks_in_process_keeps_order_and_derive_seed_keeps_base() -> None:
    assert run_tasks(_square_plus, {"offset": 1}, [3, 1, 2]) == [10, 2, 5]
    assert derive_seed(7) == 7 and derive_seed(7, 0, 0) == 7
    assert len({derive_seed(7, k, c) for k in range(4) for c in range(4)}) == 16


def test_missing_ray_names_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_ray(name: str, *args, **kwargs):  # type: ignore[no-untyped-def]
        if name == "ray":
            raise ImportError("no ray")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(Exception, match=r"trafficrlhf-sdk\[ray\]"):
        run_tasks(_square_plus, {"offset": 0}, [1], ExecutionConfig(workers=1))


def test_ray_hands_a_free_worker_the_next_task_while_an_earlier_one_runs(ray_head, tmp_path) -> None:  # type: ignore[no-untyped-def]
    def block_or_pass(shared: dict, task: tuple[str, int]) -> tuple[str, int]:  # shipped by value: workers cannot
        import os  # import this test module
        import time

        kind, index = task
        flag = os.path.join(shared["folder"], "fast_done")
        if kind == "slow":  # holds its worker until every short task has run (60 s at most)
            deadline = time.monotonic() + 60.0
            while not os.path.exists(flag) and time.monotonic() < deadline:
                time.sleep(0.02)
            return ("slow" if os.path.exists(flag) else "timed out"), os.getpid()
        if index == 4:
            open(flag, "w").close()
        return kind, os.getpid()

    # task 0 holds one worker until the short tasks are done: the other worker must run them all meanwhile, not
    # wait for task 0's result to be read first (that would time task 0 out); no timing, so load cannot flake it
    tasks = [("slow", 0), ("fast", 1), ("fast", 2), ("fast", 3), ("fast", 4)]
    results = run_tasks(block_or_pass, {"folder": str(tmp_path)}, tasks, RAY)
    assert [r[0] for r in results] == ["slow", "fast", "fast", "fast", "fast"]  # in task order, nobody timed out
    slow, fast = results[0][1], {r[1] for r in results[1:]}
    assert len(fast) == 1 and slow not in fast


def test_ray_workers_serve_the_next_call_and_let_go_on_other_threads(ray_head) -> None:  # type: ignore[no-untyped-def]
    def _pid_and_threads(shared: dict, task: int) -> tuple[int, int, int]:  # shipped by value (see above)
        import os

        import torch

        return os.getpid(), torch.get_num_threads(), shared["offset"] + task

    first = run_tasks(_pid_and_threads, {"offset": 0}, list(range(6)), RAY)
    second = run_tasks(_pid_and_threads, {"offset": 100}, list(range(6)), RAY)
    assert [r[2] for r in first] == list(range(6)) and [r[2] for r in second] == list(range(100, 106))
    assert {r[0] for r in second} == {r[0] for r in first}  # the same two workers, each with its new payload
    assert len({r[0] for r in first}) == 2 and {r[1] for r in first} == {1}
    # two threads each: the idle one-thread workers must free the 2 CPUs, or the new worker could never start
    wide = run_tasks(_pid_and_threads, {"offset": 0}, [1, 2], ExecutionConfig(workers=1, threads_per_worker=2))
    assert {r[1] for r in wide} == {2} and not {r[0] for r in wide} & {r[0] for r in first}
    again = run_tasks(_pid_and_threads, {"offset": 0}, [1, 2], RAY)  # and back: new one-thread workers
    assert {r[1] for r in again} == {1} and [r[2] for r in again] == [1, 2]
    one = run_tasks(_pid_and_threads, {"offset": 0}, [5], RAY)  # one task takes one of them; the other waits
    last = run_tasks(_pid_and_threads, {"offset": 0}, [1, 2, 3, 4], RAY)
    assert {one[0][0]} < {r[0] for r in last} == {r[0] for r in again}


def test_a_call_that_fails_lets_its_ray_workers_go(ray_head) -> None:  # type: ignore[no-untyped-def]
    import trafficrlhf_sdk.parallel as parallel

    def fail_on_two(shared: dict, task: int) -> int:
        if task == 2:
            raise ValueError("task 2")
        return task

    with pytest.raises(Exception, match="task 2"):
        run_tasks(fail_on_two, {}, [1, 2, 3], RAY)
    assert not any(parallel._IDLE.values())  # nothing half-used goes back to the session
    assert run_tasks(lambda shared, task: shared["offset"] + task, {"offset": 1}, [3, 1, 2], RAY) == [4, 2, 3]


@pytest.mark.data
def test_evaluation_on_ray_equals_in_process(ray_head, val_scenes) -> None:  # type: ignore[no-untyped-def]
    scenes = val_scenes[:3]
    config = EvaluationConfig(rollouts=2, batch_size=2, seed=5, metrics=("failure", "realism_ctg"))
    policy = NoisyLogPolicy(position_noise_m=2.0, seed=5)
    local = evaluate_policy(policy, scenes, config)
    remote = evaluate_policy(NoisyLogPolicy(position_noise_m=2.0, seed=5), scenes, config, execution=RAY)
    assert local.values == remote.values and local.per_scene == remote.per_scene
    assert torch.equal(local.rollout.simulated.states, remote.rollout.simulated.states)
    assert "realism_meta" in local.values and 0 < local.values["realism_meta"] < 1
    b = scenes.num_scenes  # the two rollouts of a scene differ: each has its own seed
    assert not torch.equal(local.rollout.simulated.states[:b], local.rollout.simulated.states[b:])
    assert policy.seed == 5  # the caller's policy keeps its seed


@pytest.mark.data
def test_several_seeds_on_ray_equal_in_process(ray_head, val_scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation.runs import evaluate_seeds

    scenes = val_scenes[:3]
    config = EvaluationConfig(batch_size=2, metrics=("failure", "realism_ctg"))

    def build(seed: int) -> NoisyLogPolicy:
        return NoisyLogPolicy(position_noise_m=2.0, seed=seed)

    local = evaluate_seeds(build, scenes, (3, 4), config)
    remote = evaluate_seeds(build, scenes, (3, 4), config, execution=RAY)
    assert [r.values for r in local.reports] == [r.values for r in remote.reports]
    assert local.reports[0].values != local.reports[1].values  # the seeds differ


@pytest.mark.data
@pytest.mark.parametrize("contexts", ["log", "closed_loop"])
def test_campaign_candidates_on_ray_equal_in_process(ray_head, tmp_path, nuscenes_source, contexts) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    config = CampaignConfig(name="c", model="noisy_log", num_contexts=3, num_candidates=3, candidate_seconds=2.0,
                            root=nuscenes_source.root, model_options={"position_noise_m": 2.0}, seed=4,
                            contexts=contexts, drive_seconds=2.0)
    local_store, ray_store = FeedbackStore(tmp_path / "a.db"), FeedbackStore(tmp_path / "b.db")
    local = create_campaign(local_store, config)
    remote = create_campaign(ray_store, config, execution=RAY)
    assert len(local.added) == len(remote.added) == 3
    for a, b in zip(local.added, remote.added):
        left, right = local_store.load_context(a), ray_store.load_context(b)
        assert torch.equal(left.candidates, right.candidates)
        assert torch.equal(left.scenario.states, right.scenario.states)


@pytest.mark.data
def test_ppo_rollout_sampling_on_ray_equals_in_process(ray_head, make_gru_adapter, val_scenes) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.alignment.distributed import sample_in_chunks

    model = make_gru_adapter()
    contexts = val_scenes[:4]
    local = sample_in_chunks(model, None, contexts, 3, seed=11, chunk_size=2)
    remote = sample_in_chunks(model, None, contexts, 3, seed=11, execution=RAY, chunk_size=2)
    assert torch.equal(local.futures, remote.futures) and torch.equal(local.log_prob, remote.log_prob)
    assert local.futures.shape[:2] == (4, 3)
    assert not torch.equal(local.futures[:, 0], local.futures[:, 1])  # samples differ


class _NoCollision:
    """Reward: minus the share of steps in collision (cheap and deterministic)."""

    def step_rewards(self, scenario):  # type: ignore[no-untyped-def]
        from trafficrlhf_sdk.metrics.geometry import pairwise_collisions

        hit = pairwise_collisions(scenario.xy, scenario.yaw, scenario.extent, scenario.valid).any(1)
        return -hit.float()


@pytest.mark.data
def test_ppo_training_with_distributed_rollouts_repeats_on_ray(ray_head, make_gru_adapter,  # type: ignore[no-untyped-def]
                                                               nuscenes_source) -> None:
    from trafficrlhf_sdk.alignment import AlignConfig, AlignTrainer
    from trafficrlhf_sdk.alignment.distributed import distribute_rollouts

    scenes = nuscenes_source.load_batch("train", 4)
    config = AlignConfig(epochs=2, contexts_per_epoch=10, samples_per_context=3, minibatch_contexts=5, ppo_epochs=1,
                         progress_bar=False)  # 10 contexts: two sample chunks (8 + 2)
    histories = []
    for execution in (None, RAY):
        trainer = distribute_rollouts(AlignTrainer(make_gru_adapter(), _NoCollision(), config, scenes=scenes),
                                      execution)
        histories.append(trainer.train())
    import math

    def comparable(history: list[dict]) -> list[dict]:  # wall time differs; NaN (no reference KL) != NaN
        return [{k: ("nan" if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()
                 if not k.startswith("time")} for row in history]

    assert comparable(histories[0]) == comparable(histories[1]) and len(histories[0]) == 2
    assert histories[0][0]["loss"] != histories[0][1]["loss"]  # the model did train


@pytest.mark.data
def test_align_command_samples_on_ray_and_trains_like_in_process(ray_head, data_root: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`trafficrlhf align --ray-address` draws each epoch's samples on the cluster in seeded chunks; the aligned
    weights equal those of the same recipe run plainly in this process (`--workers` is a speed switch only)."""
    import os

    from click.testing import CliRunner
    from safetensors.torch import load_file

    from trafficrlhf_sdk.alignment.recipe import AlignRecipe, run_recipe
    from trafficrlhf_sdk.cli import get_cli

    local = str(tmp_path / "local")
    run_recipe(AlignRecipe(model="example_gru", reward_model="builtin:collision", threads=1), local,
               epochs=1, num_scenes=3, progress_bar=False)
    remote = str(tmp_path / "ray")
    result = CliRunner().invoke(get_cli(), ["align", "--model", "example_gru", "--reward-model", "builtin:collision",
                                            "--epochs", "1", "--scenes", "3", "--threads", "1", "--quiet",
                                            "--ray-address", "auto", "--out", remote], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    a, b = (load_file(os.path.join(folder, "model.safetensors")) for folder in (local, remote))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.data
def test_alignments_side_by_side_on_ray_equal_those_in_process(ray_head, data_root: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`align_steps` runs independent alignments one per Ray worker (the ladder's rows, a paper table's
    variants): each one's weights equal the same recipe aligned in this process with one thread."""
    import os

    from safetensors.torch import load_file

    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.pipeline import AlignJob, align_steps

    recipes = [AlignRecipe(model="example_gru", reward_model=reward, threads=1,
                           align={"epochs": 1, "num_scenes": 3, "progress_bar": False, "seed": seed})
               for reward, seed in (("builtin:collision", 0), ("builtin:failure", 1))]
    local = align_steps([AlignJob(str(tmp_path / f"local{k}"), r) for k, r in enumerate(recipes)])
    logged: list[str] = []
    remote = align_steps([AlignJob(str(tmp_path / f"ray{k}"), r) for k, r in enumerate(recipes)], log=logged.append,
                         execution=ExecutionConfig(ray_address="auto", workers=2))
    assert any("side by side" in line for line in logged)
    for a, b in zip(local, remote, strict=True):
        left, right = (load_file(os.path.join(step["folder"], "model.safetensors")) for step in (a, b))
        assert left.keys() == right.keys() and all(torch.equal(left[k], right[k]) for k in left)
    first, second = (load_file(os.path.join(step["folder"], "model.safetensors")) for step in remote)
    assert any(not torch.equal(first[k], second[k]) for k in first)  # two different jobs, not one run twice
