"""Shared fixtures of the ``ctg`` adapter's tests."""

from __future__ import annotations

import os

import pytest

from trafficrlhf_sdk.scenario import default_data_root


@pytest.fixture(scope="module")
def scenes():  # type: ignore[no-untyped-def]
    """The first 3 long-enough val scenes (skips without the nuscenes_pred data)."""
    root = os.path.join(default_data_root(), "nuscenes_pred")
    if not os.path.isdir(os.path.join(root, "label")):
        pytest.skip("no data")
    from trafficrlhf_nuscenes_pred import NuScenesPredSource

    return NuScenesPredSource(root=root).load_batch("val", 3)
