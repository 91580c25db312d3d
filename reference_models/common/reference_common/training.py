"""The training loop of the reference models' ``train.py`` scripts.

:func:`fit` runs ``loss_fn`` under a learning rate with a linear warm-up and a cosine decay to 5 %
(:func:`cosine_rate`) over either a fixed number of steps (bit-reproducible) or a wall-clock budget, clips the
gradient norm at 1, keeps running means of the losses and validates every ``val_every`` steps. What differs
between the models (how a batch is drawn, what the loss is, an EMA copy, what a validation prints) stays in
their scripts as the callbacks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable

import torch
from tqdm.auto import tqdm

__all__ = ["cosine_rate", "fit", "take_rows"]

FLOOR = 0.05  # the cosine decays to this share of the peak learning rate


def cosine_rate(lr: float, step: int, fraction: float, warmup: int) -> float:
    """The learning rate at ``step``: ``lr`` times a linear warm-up over ``warmup`` steps, times a cosine from 1
    down to :data:`FLOOR` over ``fraction`` (0 -> 1) of the run."""
    return lr * min(1.0, (step + 1) / warmup) * (FLOOR + (1 - FLOOR) * 0.5 * (1 + math.cos(math.pi * fraction)))


def fit(optimizer: torch.optim.Optimizer, params: Iterable[torch.nn.Parameter],
        loss_fn: Callable[[], tuple[torch.Tensor, dict[str, float]]], *, lr: float, warmup: int,
        steps: int | None = None, seconds: float = 0.0, log_every: int = 10, val_every: int = 200,
        after_step: Callable[[int], None] | None = None,
        on_log: Callable[[int, dict[str, float], float], None] | None = None,
        validate: Callable[[int, float], None] | None = None, desc: str | None = None,
        progress: bool = True) -> int:
    """Train until ``steps`` steps are done, or, when ``steps`` is None, until ``seconds`` have passed; returns the
    steps taken.

    Args:
        optimizer: its learning rate is set before every step (:func:`cosine_rate`).
        params: the parameters whose gradient norm is clipped at 1.
        loss_fn: draws a batch and returns ``(loss, parts)``; ``parts`` are floats averaged for ``on_log``
            (the loss itself is averaged as ``loss``).
        after_step: called with the step count after each optimizer step (e.g. an EMA update).
        on_log: every ``log_every`` steps, hears the step, the running means since the last call and the rate.
        validate: every ``val_every`` steps, hears the step and the rate.
        desc, progress: the progress bar's label, and whether it is shown.
    """
    params = list(params)
    running: dict[str, list[float]] = {}
    step = 0
    began = time.perf_counter()
    bar = tqdm(total=steps, desc=desc, unit="step", disable=not progress)
    while True:
        fraction = step / steps if steps else (time.perf_counter() - began) / max(seconds, 1.0)
        if fraction >= 1.0:
            break
        rate = cosine_rate(lr, step, fraction, warmup)
        for group in optimizer.param_groups:
            group["lr"] = rate
        loss, parts = loss_fn()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        step += 1
        if after_step is not None:
            after_step(step)
        for key, value in {"loss": float(loss.detach()), **parts}.items():
            running.setdefault(key, []).append(value)
        if step % log_every == 0:
            means = {key: sum(values) / len(values) for key, values in running.items()}
            running = {}
            bar.set_postfix(loss=f"{means['loss']:.3f}", lr=f"{rate:.1e}")
            if on_log is not None:
                on_log(step, means, rate)
        if validate is not None and step % val_every == 0:
            validate(step, rate)
        bar.update(1)
    bar.close()
    return step


def take_rows(data: dict[str, torch.Tensor], idx: torch.Tensor,
              crops: tuple[str, ...] = ("map", "crop")) -> dict[str, torch.Tensor]:
    """Rows ``idx`` of stored samples, the (uint8) map crops among ``crops`` as float."""
    out = {k: v[idx] for k, v in data.items()}
    for key in crops:
        if key in out:
            out[key] = out[key].float()
    return out
