"""The reference models' shared training loop: the learning-rate schedule, a fixed-step run that matches a loop
written out by hand step for step, and the callbacks' timing."""

from __future__ import annotations

import math

import torch

from reference_common import cosine_rate, fit, mlp, take_rows


def test_cosine_rate_warms_up_then_decays_to_five_percent() -> None:
    assert cosine_rate(1.0, 0, 0.0, warmup=10) == 0.1
    assert cosine_rate(1.0, 9, 0.0, warmup=10) == 1.0
    assert math.isclose(cosine_rate(2.0, 500, 0.5, warmup=10), 2.0 * (0.05 + 0.95 * 0.5))
    assert math.isclose(cosine_rate(1.0, 999, 1.0, warmup=10), 0.05)


def _problem(seed: int):  # type: ignore[no-untyped-def]
    torch.manual_seed(seed)
    model = mlp([3, 8, 1])
    data = {"x": torch.randn(64, 3), "y": torch.randn(64, 1)}
    return model, data, torch.Generator().manual_seed(seed)


def test_a_fixed_step_run_equals_the_loop_written_out() -> None:
    model, data, gen = _problem(0)
    optimizer = torch.optim.Adam(model.parameters(), lr=0.01)
    logged: list[tuple[int, float]] = []

    def loss_fn():  # type: ignore[no-untyped-def]
        batch = take_rows(data, torch.randint(0, 64, (8,), generator=gen))
        return torch.nn.functional.mse_loss(model(batch["x"]), batch["y"]), {}

    steps = fit(optimizer, model.parameters(), loss_fn, lr=0.01, warmup=5, steps=20, log_every=5,
                on_log=lambda step, means, rate: logged.append((step, means["loss"])), progress=False)

    hand, hand_data, hand_gen = _problem(0)
    hand_optimizer = torch.optim.Adam(hand.parameters(), lr=0.01)
    losses = []
    for step in range(20):
        for group in hand_optimizer.param_groups:
            group["lr"] = 0.01 * min(1.0, (step + 1) / 5) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * step / 20)))
        idx = torch.randint(0, 64, (8,), generator=hand_gen)
        loss = torch.nn.functional.mse_loss(hand(hand_data["x"][idx]), hand_data["y"][idx])
        hand_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(list(hand.parameters()), 1.0)
        hand_optimizer.step()
        losses.append(float(loss.detach()))
    assert steps == 20
    assert logged == [(s, sum(losses[s - 5:s]) / 5) for s in (5, 10, 15, 20)]
    assert all(torch.equal(a, b) for a, b in zip(model.parameters(), hand.parameters()))


def test_callbacks_run_after_each_step_and_every_val_every_steps() -> None:
    model, data, _ = _problem(1)
    seen: list[str] = []
    fit(torch.optim.SGD(model.parameters(), lr=0.1), model.parameters(),
        lambda: (model(data["x"]).pow(2).mean(), {"extra": 1.0}), lr=0.1, warmup=1, steps=4, log_every=2,
        val_every=3, after_step=lambda step: seen.append(f"step {step}"),
        on_log=lambda step, means, rate: seen.append(f"log {step} {sorted(means)}"),
        validate=lambda step, rate: seen.append(f"validate {step}"), progress=False)
    assert seen == ["step 1", "step 2", "log 2 ['extra', 'loss']", "step 3", "validate 3", "step 4",
                    "log 4 ['extra', 'loss']"]
    assert take_rows({"map": torch.zeros(3, 2, dtype=torch.uint8)}, torch.tensor([0]))["map"].dtype == torch.float32
