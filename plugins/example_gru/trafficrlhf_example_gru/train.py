"""Train ``example_gru`` by imitation on the nuScenes train split (seeded, time-boxed, CPU).

    python -m trafficrlhf_example_gru.train --out plugins/example_gru/trafficrlhf_example_gru/checkpoint --minutes 4

Scenes come from the SDK's ``nuscenes_pred`` source, loaded in fixed groups with
``load_batch("train", scene_ids=...)``. Each step takes one group and cuts, for every scene, a random window
(a random "now" on a 0.5 s keyframe where at least one vehicle moves on), then minimizes the adapter's own
:meth:`~trafficrlhf_example_gru.ExampleGRUAdapter.imitation_loss` (Gaussian NLL of the next 2 s of logged
actions) with Adam. Writes ``config.json`` + ``model.safetensors`` (``save_pretrained``), ``training_log.json``
and ``training_curve.png`` into ``--out``. The data, and so the checkpoint, are nuScenes: CC BY-NC-SA 4.0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import random
import time

import torch

from trafficrlhf_sdk import get_scenario_source
from trafficrlhf_sdk.scenario import AgentType, ScenarioTensor

from trafficrlhf_example_gru.adapter import ExampleGRUAdapter
from trafficrlhf_example_gru.model import GRUConfig

HISTORY = 30  # steps of history kept before "now" in a training window (3 s)
MIN_NOW = 5  # earliest "now" of a window (0.5 s into the scene)


def random_windows(group: ScenarioTensor, horizon: int, generator: torch.Generator, align: int = 1) -> ScenarioTensor:
    """One window per scene of ``group``: a random "now" (a multiple of ``align``) where a vehicle is valid at now
    and now+1, shifted so that ``current_index`` is ``HISTORY`` (steps outside the scene are invalid).

    Agents absent at "now" neither enter the features (neighbours must be valid now) nor the loss, so they are
    dropped and the others packed into the first slots: fewer padded rows per step.
    """
    b, a, t, _ = group.states.shape
    vehicle = group.agent_type == AgentType.VEHICLE
    moving_on = (group.valid[:, :, :-1] & group.valid[:, :, 1:] & vehicle[..., None]).any(1)  # (B, T-1)
    moving_on[:, :MIN_NOW] = False
    moving_on &= torch.arange(t - 1) % align == 0
    weights = moving_on.float() + 1e-12  # scenes without any eligible step get an (empty) arbitrary window
    now = torch.multinomial(weights, 1, generator=generator)[:, 0]  # (B,)
    present = group.valid.gather(2, now[:, None, None].expand(b, a, 1))[..., 0]  # (B, A)
    keep = int(present.sum(1).max().clamp_min(1))
    slots = torch.argsort((~present).to(torch.uint8), dim=1, stable=True)[:, :keep]  # present agents first
    steps = now[:, None] - HISTORY + torch.arange(HISTORY + 1 + horizon)  # (B, W)
    inside = (steps >= 0) & (steps < t)
    index = steps.clamp(0, t - 1)
    states = group.states.gather(1, slots[:, :, None, None].expand(b, keep, t, 4))
    states = states.gather(2, index[:, None, :, None].expand(b, keep, -1, 4))
    valid = group.valid.gather(1, slots[:, :, None].expand(b, keep, t))
    valid = valid.gather(2, index[:, None, :].expand(b, keep, -1)) & inside[:, None]
    pick = lambda x: x.gather(1, slots if x.dim() == 2 else slots[..., None].expand(b, keep, x.shape[-1]))  # noqa: E731
    return group.replace_unchecked(
        states=states * valid[..., None], valid=valid, extent=pick(group.extent), agent_type=pick(group.agent_type),
        controlled=pick(group.controlled) & valid[:, :, HISTORY], current_index=HISTORY, agent_ids=(),
    )


def plot_curve(log: dict, path: str) -> None:
    """Training loss (raw and smoothed) and validation loss against steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    steps = list(range(1, len(log["train_loss"]) + 1))
    ax.plot(steps, log["train_loss"], color="0.8", lw=0.6, label="train (per step)")
    ax.plot(steps, log["train_loss_ema"], color="C0", label="train (EMA 0.98)")
    if log["val"]:
        ax.plot([v["step"] for v in log["val"]], [v["loss"] for v in log["val"]], "o-", color="C3",
                label=f"val ({log['val_scenes']} scenes, now = 3 s)")
    losses = sorted(log["train_loss"])
    if losses:  # a few windows with annotation glitches spike the loss: keep the bulk of the curve readable
        val = [v["loss"] for v in log["val"]]
        low = min([losses[0], *val])
        high = max([losses[int(0.97 * (len(losses) - 1))], *val])
        ax.set_ylim(low - 0.3, high + 0.3)
    ax.set_xlabel("step")
    ax.set_ylabel("Gaussian NLL per (agent, 0.1 s step)")
    ax.set_title(f"example_gru imitation on nuScenes train ({log['wall_time_s']:.0f} s, seed {log['seed']})")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    """Run the training; returns the training log."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="Checkpoint directory to write.")
    parser.add_argument("--minutes", type=float, default=4.0,
                        help="Wall-clock training budget (data loading excluded).")
    parser.add_argument("--max-steps", type=int, default=None, help="Stop after this many steps (default: time only).")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--root", default=None, help="nuscenes_pred data directory (default: the SDK's data root).")
    parser.add_argument("--scenes", type=int, default=None, help="Use only the first N train scenes.")
    parser.add_argument("--group-size", type=int, default=32, help="Scenes per step.")
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machines are shared).")
    parser.add_argument("--val-scenes", type=int, default=20, help="First N val scenes for the validation loss.")
    parser.add_argument("--val-every", type=int, default=100)
    parser.add_argument("--align-s", type=float, default=0.5,
                        help="Windows start on multiples of this time (s): nuScenes keyframes are 2 Hz, the simulator "
                             "replans at 2 Hz from a keyframe; 0.1 allows any step.")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    random.seed(args.seed)
    torch.manual_seed(args.seed)
    generator = torch.Generator().manual_seed(args.seed)

    source = get_scenario_source("nuscenes_pred", **({"root": args.root} if args.root else {}))
    ids = source.scene_ids("train")[: args.scenes]
    order = torch.randperm(len(ids), generator=generator).tolist()
    shuffled = [ids[i] for i in order]
    tic = time.perf_counter()
    groups = [source.load_batch("train", scene_ids=shuffled[i : i + args.group_size])
              for i in range(0, len(shuffled), args.group_size)]
    val = source.load_batch("val", args.val_scenes) if args.val_scenes else None
    load_s = time.perf_counter() - tic
    print(f"loaded {len(ids)} train scenes in {len(groups)} groups (+{args.val_scenes} val) in {load_s:.1f} s")

    adapter = ExampleGRUAdapter(config=GRUConfig().model_dump(mode="json"), seed=args.seed)
    net = adapter.module
    params = [p for group in adapter.parameter_groups().values() for p in group]
    optimizer = torch.optim.Adam(params, lr=args.lr)
    budget = args.minutes * 60.0
    align = max(1, round(args.align_s / groups[0].dt))

    log: dict = {"seed": args.seed, "minutes": args.minutes, "lr": args.lr, "group_size": args.group_size,
                 "align_s": args.align_s,
                 "train_scenes": len(ids), "val_scenes": args.val_scenes, "data_load_s": load_s,
                 "parameters": {k: sum(p.numel() for p in v) for k, v in adapter.parameter_groups().items()},
                 "config": adapter.get_config(), "torch": torch.__version__, "threads": args.threads,
                 "machine": platform.machine(), "train_loss": [], "train_loss_ema": [], "val": [],
                 "data": "nuScenes prediction scenes (nuscenes_pred, train split); CC BY-NC-SA 4.0"}

    def validate(step: int) -> None:
        if val is None:
            return
        net.eval()
        with torch.no_grad():
            loss = float(adapter.imitation_loss(val))
        log["val"].append({"step": step, "loss": loss, "time_s": time.perf_counter() - began})
        print(f"step {step:5d}  val NLL {loss:+.4f}")

    began = time.perf_counter()
    validate(0)
    step, ema = 0, None
    while True:
        elapsed = time.perf_counter() - began
        if elapsed >= budget or (args.max_steps is not None and step >= args.max_steps):
            break
        progress = elapsed / budget if args.max_steps is None else max(elapsed / budget, step / args.max_steps)
        for group in optimizer.param_groups:  # cosine decay to 5% of the base rate over the budget
            group["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0))))
        scenes = groups[int(torch.randint(len(groups), (1,), generator=generator))]
        batch = random_windows(scenes, adapter.horizon, generator, align)
        net.train()
        loss = adapter.imitation_loss(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        step += 1
        value = float(loss.detach())
        ema = value if ema is None else 0.98 * ema + 0.02 * value
        log["train_loss"].append(value)
        log["train_loss_ema"].append(ema)
        if step % args.val_every == 0:
            print(f"step {step:5d}  train NLL (EMA) {ema:+.4f}  {time.perf_counter() - began:.0f} s")
            validate(step)
    if not log["val"] or log["val"][-1]["step"] != step:
        validate(step)
    log["steps"] = step
    log["wall_time_s"] = time.perf_counter() - began
    log["final_train_loss_ema"] = ema
    log["final_val_loss"] = log["val"][-1]["loss"] if log["val"] else None

    net.eval()
    adapter.save_pretrained(args.out)
    with open(os.path.join(args.out, "training_log.json"), "w", encoding="utf-8") as handle:
        json.dump(log, handle, indent=1)
    plot_curve(log, os.path.join(args.out, "training_curve.png"))
    print(f"{step} steps in {log['wall_time_s']:.0f} s; train NLL (EMA) {ema:+.4f}, val NLL "
          f"{log['final_val_loss']:+.4f}; wrote {args.out}")
    return log


if __name__ == "__main__":
    main()
