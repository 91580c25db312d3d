"""Shared fixtures: the real-data root and a small batch of nuscenes_pred val scenes.

Tests that need ``../shared/data`` take ``data_root`` (or ``val_scenes``) and are skipped, not failed, when
the data is absent. Point ``TRAFFICRLHF_DATA`` at another copy to use it instead.
"""

from __future__ import annotations

import os

import pytest

from trafficrlhf_sdk.scenario import ScenarioTensor, default_data_root

NUM_VAL_SCENES = 8


@pytest.fixture(scope="session")
def data_root() -> str:
    """``default_data_root()`` when it holds ``nuscenes_pred/label``; skips the test otherwise."""
    root = default_data_root()
    if not os.path.isdir(os.path.join(root, "nuscenes_pred", "label")):
        pytest.skip(f"real data not found under {root!r} (set TRAFFICRLHF_DATA to the shared data folder)")
    return root


@pytest.fixture(scope="session")
def nuscenes_source(data_root: str):  # type: ignore[no-untyped-def]
    """A ``NuScenesPredSource`` reading ``<data_root>/nuscenes_pred`` (skips when the plugin is missing)."""
    plugin = pytest.importorskip("trafficrlhf_nuscenes_pred")
    return plugin.NuScenesPredSource(root=os.path.join(data_root, "nuscenes_pred"))


@pytest.fixture(scope="session")
def val_scenes(nuscenes_source) -> ScenarioTensor:  # type: ignore[no-untyped-def]
    """The first 8 long-enough val scenes of nuscenes_pred (sorted by name) as one batch."""
    return nuscenes_source.load_batch("val", NUM_VAL_SCENES)


@pytest.fixture(scope="session")
def train_scene_list(nuscenes_source) -> list[ScenarioTensor]:  # type: ignore[no-untyped-def]
    """The first 8 long-enough train scenes of nuscenes_pred, one single-scene tensor each (alignment tests)."""
    batch = nuscenes_source.load_batch("train", 8)
    return [batch[i] for i in range(batch.num_scenes)]


@pytest.fixture
def make_gru_adapter():  # type: ignore[no-untyped-def]
    """A factory of ``example_gru`` adapters with the same seeded random weights (skips without the plugin)."""
    gru = pytest.importorskip("trafficrlhf_example_gru")

    def make():  # type: ignore[no-untyped-def]
        import torch

        torch.manual_seed(0)
        return gru.ExampleGRUAdapter()

    return make


@pytest.fixture(scope="session")
def scored_futures() -> ScenarioTensor:
    """Four tiny model-free contexts, each with the history and one candidate future (faithful, off-road,
    collision, stall; T = 41, A = 3): inputs for reward models without real data."""
    from trafficrlhf_sdk.testing.feedback import tiny_context

    parts = []
    for i, variant in enumerate(["faithful", "offroad", "collision", "stall"]):
        scenario, candidates, valid, _, _ = tiny_context([variant], i)
        parts.append(scenario.with_future(candidates, valid))
    return ScenarioTensor.concat(parts)
