"""Independent random streams for groups of scenes batched together.

A feedback campaign seeds each context by itself (its candidates depend only on the campaign seed and the scene),
and so does each rollout of an evaluation. To run many such groups through a traffic model as one batch and still
draw exactly the numbers each would draw alone, every group keeps its own ``torch.Generator``:

* :class:`SceneGenerators`: one generator per group of consecutive scenes of a batch (what a policy holds);
* :class:`RowGenerators`: the same generators over the rows of one draw, whose first dimension lists the groups'
  rows in order (what a model's sampler receives); ``randn(shape)`` draws each group's block from its own
  generator and concatenates them.

A group that has no rows in a draw draws nothing, as it would alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["RowGenerators", "SceneGenerators", "draw_normal"]


class RowGenerators:
    """Draws whose first dimension is split into consecutive blocks of ``counts`` rows, block g from
    ``generators[g]``."""

    def __init__(self, generators: Sequence[torch.Generator], counts: Sequence[int]) -> None:
        if len(generators) != len(counts):
            raise ValueError(f"{len(generators)} generators for {len(counts)} row blocks; give one per block.")
        self.generators, self.counts = list(generators), [int(c) for c in counts]
        self.device = self.generators[0].device if self.generators else torch.device("cpu")

    @property
    def num_rows(self) -> int:
        """Rows of a draw (the sum of the blocks)."""
        return sum(self.counts)

    def randn(self, shape: Sequence[int]) -> torch.Tensor:
        """Standard normal ``shape`` on the generators' device; ``shape[0]`` must equal :attr:`num_rows`."""
        shape = tuple(int(d) for d in shape)
        if not shape or shape[0] != self.num_rows:
            raise ValueError(f"a draw of shape {shape} over row blocks {self.counts}: its first dimension must be "
                             f"{self.num_rows}.")
        parts = [torch.randn((c, *shape[1:]), generator=g, device=self.device)
                 for g, c in zip(self.generators, self.counts) if c > 0]
        return torch.cat(parts) if parts else torch.empty(shape, device=self.device)


class SceneGenerators:
    """One generator per group of consecutive scenes: group g covers ``sizes[g]`` scenes and is seeded by
    ``seeds[g]``; :meth:`rows` hands a sampler the generators over the rows of a draw."""

    def __init__(self, seeds: Sequence[int], sizes: Sequence[int], device: torch.device | str = "cpu") -> None:
        if len(seeds) != len(sizes) or not seeds or any(int(s) < 1 for s in sizes):
            raise ValueError(f"seeds {list(seeds)} and group sizes {list(sizes)}: give one seed per group and "
                             "groups of at least one scene.")
        self.seeds, self.sizes = [int(s) for s in seeds], [int(s) for s in sizes]
        self.generators = [torch.Generator(device=device).manual_seed(s) for s in self.seeds]
        self.device = self.generators[0].device

    @property
    def num_scenes(self) -> int:
        """Scenes the groups cover."""
        return sum(self.sizes)

    def group_of_scene(self) -> torch.Tensor:
        """long ``(B,)``: the group of each scene."""
        return torch.repeat_interleave(torch.arange(len(self.sizes)), torch.tensor(self.sizes))

    def rows(self, scene_of_row: torch.Tensor, per_row: int = 1) -> RowGenerators:
        """The generators over a draw whose rows belong to scenes ``scene_of_row (N,)`` (sorted by scene, as
        ``mask.nonzero()`` lists them), each row repeated ``per_row`` times in a row (e.g. samples per agent)."""
        group = self.group_of_scene()[scene_of_row.cpu()]
        if len(group) > 1 and bool((group[1:] < group[:-1]).any()):
            raise ValueError("rows must be sorted by scene so that each group's rows are consecutive.")
        counts = torch.bincount(group, minlength=len(self.sizes)) * per_row
        return RowGenerators(self.generators, counts.tolist())


def draw_normal(generator: torch.Generator | RowGenerators | None, shape: Sequence[int],
                device: torch.device | str) -> torch.Tensor:
    """Standard normal ``shape`` for tensors on ``device``, drawn from ``generator`` on its own device (a CPU
    generator gives a GPU run the CPU run's numbers) or block by block from :class:`RowGenerators`."""
    if isinstance(generator, RowGenerators):
        return generator.randn(shape).to(device)
    at = generator.device if generator is not None else device
    return torch.randn(tuple(shape), generator=generator, device=at).to(device)
