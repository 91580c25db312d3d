"""PPO rollout collection in chunks of contexts, in-process or on Ray workers (:func:`distribute_rollouts`).

The trainer draws ``samples_per_context`` futures for an epoch's contexts in chunks (:func:`sample_in_chunks`);
each chunk is sampled with its own generator, seeded from the epoch's sampling generator and the chunk's first
context, so the outputs are the same whether the chunks run in this process or on Ray workers, and `--workers` is
a speed switch only. On Ray, the epoch's model (its current weights) and the contexts are put in the object store
once per epoch; each task carries only its chunk's bounds.
"""

from __future__ import annotations

from typing import Any

import torch

from trafficrlhf_sdk.models.adapter import PolicyTrace, SampleOutput
from trafficrlhf_sdk.parallel import ExecutionConfig, derive_seed, run_tasks
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["distribute_rollouts", "sample_in_chunks"]


def _sample_chunk(shared: dict[str, Any], bounds: tuple[int, int]) -> SampleOutput:
    """Sample one chunk of contexts with its own generator (runs in-process or on a Ray worker)."""
    start, stop = bounds
    contexts: ScenarioTensor = shared["contexts"][start:stop]
    model, guidance = shared["model"], shared["guidance"]
    generator = torch.Generator().manual_seed(derive_seed(shared["seed"], start + 1))
    if guidance is not None:
        guidance.fit(contexts)
        with torch.enable_grad():
            out = model.sample(contexts, shared["samples"], guidance, generator)
    else:
        with torch.no_grad():
            out = model.sample(contexts, shared["samples"], None, generator)
    trace = out.trace.detach()
    return SampleOutput(out.futures.detach(), trace, out.log_prob.detach())


def _concat(parts: list[SampleOutput]) -> SampleOutput:
    """Join chunk outputs along the context axis."""
    first = parts[0].trace
    trace = PolicyTrace({k: torch.cat([p.trace.tensors[k] for p in parts]) for k in first.tensors},
                        torch.cat([p.trace.agents for p in parts]), first.now, dict(first.info))
    return SampleOutput(torch.cat([p.futures for p in parts]), trace, torch.cat([p.log_prob for p in parts]))


def sample_in_chunks(model: Any, guidance: Any, contexts: ScenarioTensor, samples: int, seed: int,
                     execution: ExecutionConfig | None = None, chunk_size: int = 8) -> SampleOutput:
    """``model.sample(contexts, samples, guidance, ...)`` over chunks of ``chunk_size`` contexts, each with a
    generator seeded by ``(seed, chunk)``; in-process or on Ray per ``execution``, with equal results.

    Returns one :class:`~trafficrlhf_sdk.models.adapter.SampleOutput` for all contexts, detached (the PPO
    update recomputes log-probabilities from the trace)."""
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size!r}.")
    shared = {"model": model, "guidance": guidance, "contexts": contexts, "samples": samples, "seed": seed}
    bounds = [(i, min(i + chunk_size, contexts.num_scenes)) for i in range(0, contexts.num_scenes, chunk_size)]
    return _concat(run_tasks(_sample_chunk, shared, bounds, execution))


def distribute_rollouts(trainer: Any, execution: ExecutionConfig | None) -> Any:
    """Make ``trainer`` (an :class:`~trafficrlhf_sdk.alignment.AlignTrainer`) run each epoch's sample chunks on
    ``execution`` (None: in this process). The chunk seeds come from the epoch's own sampling generator, so a run
    repeats exactly, and in-process and Ray runs agree. Returns ``trainer``."""
    trainer.execution = execution
    return trainer
