"""The iterative RLHF loop (trafficrlhf_sdk.loop): rounds, active selection, resume after an interruption."""

from __future__ import annotations

import json
import os

import pytest

from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.loop import RLHFConfig, rlhf

pytest.importorskip("trafficrlhf_example_gru")
pytestmark = pytest.mark.data

SMALL = dict(model="example_gru", guidance=None, rounds=2, contexts_per_round=2, candidate_pool=2, candidates=3,
             seconds=2.0, annotators=["attentive", "hurried"], contrast_scenes=3, probe_scenes=2,
             reward={"ensemble_size": 2, "max_epochs": 1, "batch_size": 2,
                     "architecture_config": {"hidden_sizes": [16, 8], "crop_size": 8}},
             align={"epochs": 1, "contexts_per_epoch": 2, "samples_per_context": 2, "num_scenes": 4})


def test_two_rounds_then_an_interrupted_run_resumes_where_it_stopped(data_root: str, tmp_path, monkeypatch) -> None:
    import trafficrlhf_sdk.loop as loop

    config = RLHFConfig(**SMALL)
    out = str(tmp_path / "run")
    calls: list[int] = []
    real_align = loop._align

    def failing_align(cfg, folder, r, state, out_dir, log):  # type: ignore[no-untyped-def]
        calls.append(r)
        if r == 1:
            raise KeyboardInterrupt  # stopped between round 0 and round 1's alignment
        return real_align(cfg, folder, r, state, out_dir, log)

    monkeypatch.setattr(loop, "_align", failing_align)
    with pytest.raises(KeyboardInterrupt):
        rlhf(config, out, log=lambda line: None)
    state = json.load(open(os.path.join(out, "state.json")))
    assert "round_0/align" in state["done"] and "round_1/reward_model" in state["done"]
    assert "round_1/align" not in state["done"]
    monkeypatch.setattr(loop, "_align", real_align)
    lines: list[str] = []
    state = rlhf(config, out, log=lines.append)
    assert state["done"][-1] == "round_1/align" and len(state["done"]) == 9  # 2 x (generate, label, rm, align) + select
    assert all(line.startswith("round 1: aligned") for line in lines)  # nothing else was redone
    for r in (0, 1):
        assert os.path.isfile(os.path.join(out, f"round_{r}", "reward_model", "model.safetensors"))
        assert os.path.isfile(os.path.join(out, f"round_{r}", "aligned", "model.safetensors"))
        assert set(state[f"probes_{r}"]) == {"faster", "slower", "jerky", "off_lane", "tailgate"}
    # round 1's candidates come from round 0's aligned model, and its reward model saw both rounds' labels
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    store = FeedbackStore(os.path.join(out, "feedback.sqlite"))
    assert state["campaigns_1"] == ["round1"]  # no guidance: one campaign per round
    assert len(store.context_keys(store.campaign("round1"))) == 4  # the pool: 2 x contexts_per_round
    assert len({lab.context_id for lab in store.labels(store.campaign("round1"))}) == 2  # the chosen ones
    card = json.load(open(os.path.join(out, "round_1", "reward_model", "config.json")))
    assert card["data"]["campaigns"] == state["campaigns_0"] + state["campaigns_1"]
    store.close()
    with pytest.raises(TrafficRLHFError, match="another configuration"):
        rlhf(RLHFConfig(**{**SMALL, "contexts_per_round": 3}), out, log=lambda line: None)
