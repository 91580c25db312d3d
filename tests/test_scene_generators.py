"""One random stream per group of scenes: a batch of groups draws exactly what each group draws alone."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.models.random import RowGenerators, SceneGenerators, draw_normal


@settings(max_examples=40, deadline=None)
@given(sizes=st.lists(st.integers(1, 4), min_size=1, max_size=5), data=st.data())
def test_each_group_draws_what_it_draws_alone(sizes, data):
    seeds = data.draw(st.lists(st.integers(0, 2**31 - 2), min_size=len(sizes), max_size=len(sizes)), label="seeds")
    agents = data.draw(st.lists(st.integers(0, 3), min_size=sum(sizes), max_size=sum(sizes)), label="agents")
    scene_of_row = torch.repeat_interleave(torch.arange(sum(sizes)), torch.tensor(agents))
    per_row = data.draw(st.integers(1, 3), label="per_row")
    batched = SceneGenerators(seeds, sizes)
    draws = [draw_normal(batched.rows(scene_of_row, per_row), (len(scene_of_row) * per_row, 2, 3), "cpu")
             for _ in range(2)]  # two draws in a row, as a sampler's steps make them
    first = 0
    for g, (seed, size) in enumerate(zip(seeds, sizes)):
        rows = sum(agents[first : first + size]) * per_row
        first += size
        alone = torch.Generator().manual_seed(seed)
        offset = sum(sum(agents[sum(sizes[:h]) : sum(sizes[: h + 1])]) for h in range(g)) * per_row
        for draw in draws:
            if rows:  # a group without rows draws nothing, as alone it would not be asked to
                assert torch.equal(draw[offset : offset + rows], torch.randn((rows, 2, 3), generator=alone))


def test_rows_must_follow_the_scene_order_and_shapes_must_match() -> None:
    gens = SceneGenerators([1, 2], [1, 1])
    with pytest.raises(ValueError, match="sorted by scene"):
        gens.rows(torch.tensor([1, 0]))
    with pytest.raises(ValueError, match="first dimension must be 2"):
        gens.rows(torch.tensor([0, 1])).randn((3, 2))
    with pytest.raises(ValueError, match="one seed per group"):
        SceneGenerators([1], [1, 2])
    with pytest.raises(ValueError, match="one per block"):
        RowGenerators([torch.Generator()], [1, 2])


def test_a_plain_generator_draws_as_torch_does() -> None:
    assert torch.equal(draw_normal(torch.Generator().manual_seed(3), (4, 2), "cpu"),
                       torch.randn((4, 2), generator=torch.Generator().manual_seed(3)))
