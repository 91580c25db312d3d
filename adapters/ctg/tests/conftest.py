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


@pytest.fixture(autouse=True)
def one_thread():  # type: ignore[no-untyped-def]
    """One torch thread per test: the bit-for-bit comparisons of runs with different batch compositions hold for
    a fixed thread count (with several threads, torch splits an elementwise op where the sizes put the split), and
    the tests' outcome must not depend on what set the thread count before them."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
