"""Train the compact BITS on the nuScenes train split (one seeded command, about 10 minutes on shared CPUs).

    .venv/bin/python -m bits_reference.train --out reference_models/bits/checkpoints/bits_small --minutes 10

Samples are (scene, vehicle, now) windows with a fully valid 2 s future, now every ``--stride`` steps (history
may be partly missing, as in closed loop). The spatial goal network (pixel CE + offset MSE + yaw MSE on the
logged position at the horizon) and the goal-conditioned policy (trajectory loss on ground-truth goals) are
trained together with one Adam optimizer; their parameters are disjoint. Validation windows come from val
scenes that the standard 100-scene evaluation does *not* use. ``--minutes`` bounds the whole run (data
preparation included); the learning rate follows a cosine over the elapsed fraction of the budget unless
``--steps`` fixes the number of steps (then the run is bit-reproducible).

Writes ``config.json`` (loadable by the ``bits`` adapter), ``model.safetensors``, ``training_curve.png`` and
``training_log.json``. nuScenes data: CC BY-NC-SA 4.0.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import torch
from reference_common.training import fit, take_rows
from trafficrlhf_sdk.models.checkpoint import record_weights_digest
from safetensors.torch import save_file

from bits_reference.data import scene_windows
from bits_reference.model import BITSConfig, BITSModel

STORE_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "v0", "actions",
              "states")


def build_windows(source, split: str, scene_ids: list[str], cfg: BITSConfig, stride: int) -> dict[str, torch.Tensor]:
    """All usable windows of ``scene_ids``, concatenated (map crops as uint8)."""
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in STORE_KEYS}
    for scene in source.iter_scenes(split, scene_ids):
        windows = scene_windows(scene, cfg, stride)
        if windows is not None:
            for k in STORE_KEYS:
                parts[k].append(windows[k])
    return {k: torch.cat(v) for k, v in parts.items()}


def losses(model: BITSModel, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
    """Goal-network loss + policy loss on one batch, and their parts."""
    goal = torch.stack([batch["states"][:, -1, 0], batch["states"][:, -1, 1], batch["states"][:, -1, 3]], -1)
    goal_loss, goal_parts = model.goal_net.loss(model.goal_net(batch), goal)
    policy_loss, policy_parts = model.policy.loss(batch, batch["actions"], batch["states"])
    parts = {"goal": float(goal_loss.detach()), "policy": float(policy_loss.detach())}
    parts.update({f"goal_{k}": float(v) for k, v in goal_parts.items()})
    parts.update({f"policy_{k}": float(v) for k, v in policy_parts.items()})
    return goal_loss + policy_loss, parts


@torch.no_grad()
def validate(model: BITSModel, data: dict[str, torch.Tensor], num_samples: int = 5, seed: int = 123
             ) -> dict[str, float]:
    """Losses, plus min/mean final displacement (m) of the policy driven to ``num_samples`` goals sampled from
    the drivable-masked goal distribution, and the final displacement with the most likely goal."""
    model.eval()
    batch = take_rows(data, torch.arange(data["v0"].shape[0]))
    _, parts = losses(model, batch)
    out = model.goal_net(batch)
    mask = batch["map"][:, 0].flatten(1) > 0
    index, _ = model.sample_goals(out, mask, num_samples, torch.Generator().manual_seed(seed))
    goals = model.goal_net.goal_at(out, torch.cat([index, model.mode_goals(out, mask)], 1))
    final = model.policy.rollout(batch, goals)[:, :, -1, :2]
    err = torch.linalg.vector_norm(final - batch["states"][:, None, -1, :2], dim=-1)  # (N, S+1)
    model.train()
    parts.update({"min_fde": float(err[:, :-1].amin(1).mean()), "mean_fde": float(err[:, :-1].mean()),
                  "mode_fde": float(err[:, -1].mean())})
    return parts


def plot_curve(curve: dict[str, list], path: str) -> None:
    """Training and validation losses of both parts, and the validation final displacement errors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 3.6))
    ax[0].plot(curve["step"], curve["train_goal"], label="train (running mean)")
    ax[0].plot(curve["val_step"], curve["val_goal"], "o-", label="val")
    ax[0].set_title("goal network: CE + offset + yaw")
    ax[1].plot(curve["step"], curve["train_policy"], label="train (running mean)")
    ax[1].plot(curve["val_step"], curve["val_policy"], "o-", label="val")
    ax[1].set_yscale("log")
    ax[1].set_title("goal-conditioned policy: trajectory loss")
    for key, label in (("val_min_fde", "min of 5 sampled goals"), ("val_mode_fde", "most likely goal"),
                       ("val_mean_fde", "mean of 5 sampled goals")):
        ax[2].plot(curve["val_step"], curve[key], "o-", label=label)
    ax[2].set_title("val final displacement at 2 s (m)")
    for a in ax:
        a.set_xlabel("step")
        a.legend()
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    """Command-line entry point; returns the training log."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="Output directory.")
    parser.add_argument("--minutes", type=float, default=10.0, help="Wall-clock budget of the whole run.")
    parser.add_argument("--steps", type=int, default=None, help="Fixed number of steps (overrides the time budget).")
    parser.add_argument("--batch-size", type=int, default=96)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stride", type=int, default=4, help="Steps between windows of one agent.")
    parser.add_argument("--train-scenes", type=int, default=None, help="Use only the first N train scenes.")
    parser.add_argument("--val-windows", type=int, default=500)
    parser.add_argument("--val-every", type=int, default=200)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machines are shared).")
    parser.add_argument("--root", default=None, help="nuscenes_pred data directory (default: shared data).")
    args = parser.parse_args(argv)

    began = time.perf_counter()
    budget = args.minutes * 60.0
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    from trafficrlhf_sdk import get_scenario_source

    options = {"root": args.root} if args.root else {}
    # history_s=0: windows start at the first logged step and we pick "now" ourselves; min_future_s=2: all scenes
    source = get_scenario_source("nuscenes_pred", history_s=0.0, min_future_s=2.0, **options)
    cfg = BITSConfig()
    train_ids = source.scene_ids("train")[: args.train_scenes]
    train = build_windows(source, "train", train_ids, cfg, args.stride)
    held_out = set(get_scenario_source("nuscenes_pred", **options).scene_ids("val")[:100])  # evaluation scenes
    val_ids = [s for s in source.scene_ids("val") if s not in held_out]
    val = build_windows(source, "val", val_ids, cfg, stride=10)
    pick = torch.linspace(0, val["v0"].shape[0] - 1, min(args.val_windows, val["v0"].shape[0])).long()
    val = {k: v[pick] for k, v in val.items()}
    prep_time = time.perf_counter() - began
    n_train = train["v0"].shape[0]
    print(f"{n_train} training windows from {len(train_ids)} scenes, {val['v0'].shape[0]} validation windows "
          f"from {len(val_ids)} scenes; data ready in {prep_time:.0f} s", flush=True)

    model = BITSModel(cfg)
    acts = train["actions"].reshape(-1, 2)
    states = train["states"].reshape(-1, 4)
    model.set_normalization(acts.std(0).clamp_min(1e-3), states.std(0).clamp_min(1e-3))
    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
    gen = torch.Generator().manual_seed(args.seed)
    counts = {"goal_net": sum(p.numel() for p in model.goal_net.parameters()),
              "policy": sum(p.numel() for p in model.policy.parameters())}
    print(f"parameters: {counts}", flush=True)

    train_budget = budget - prep_time - 30.0  # keep time for the final validation and writing
    curve: dict[str, list] = {k: [] for k in ("step", "train_goal", "train_policy", "val_step", "val_goal",
                                              "val_policy", "val_min_fde", "val_mean_fde", "val_mode_fde")}
    loop_began = time.perf_counter()

    def train_step() -> tuple[torch.Tensor, dict[str, float]]:
        loss, parts = losses(model, take_rows(train, torch.randint(0, n_train, (args.batch_size,), generator=gen)))
        return loss, {"goal": parts["goal"], "policy": parts["policy"]}

    def log(step: int, means: dict[str, float], lr: float) -> None:
        curve["step"].append(step)
        curve["train_goal"].append(means["goal"])
        curve["train_policy"].append(means["policy"])

    def validate_now(step: int, lr: float) -> None:
        v = validate(model, val)
        for key in ("goal", "policy", "min_fde", "mean_fde", "mode_fde"):
            curve[f"val_{key}"].append(v[key])
        curve["val_step"].append(step)
        print(f"step {step} ({time.perf_counter() - loop_began:.0f} s, lr {lr:.1e}): val goal {v['goal']:.3f} "
              f"(CE {v['goal_pixel']:.3f}), policy {v['policy']:.4f} (ADE {v['policy_ade']:.3f} m), "
              f"FDE min/mode {v['min_fde']:.2f}/{v['mode_fde']:.2f} m", flush=True)

    step = fit(optimizer, model.parameters(), train_step, lr=args.lr, warmup=50, steps=args.steps,
               seconds=train_budget, log_every=20, val_every=args.val_every, on_log=log, validate=validate_now,
               progress=False)
    train_time = time.perf_counter() - loop_began
    model.eval()
    final = validate(model, val)
    for key in ("goal", "policy", "min_fde", "mean_fde", "mode_fde"):
        curve[f"val_{key}"].append(final[key])
    curve["val_step"].append(step)
    final_train = validate(model, {k: v[torch.linspace(0, n_train - 1, len(val["v0"])).long()]
                                   for k, v in train.items()})

    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "config.json"), "w", encoding="utf-8") as handle:
        json.dump({"adapter": "bits", "config": model.cfg.to_dict()}, handle, indent=2)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, os.path.join(args.out, "model.safetensors"), metadata={"format": "pt", "adapter": "bits"})
    record_weights_digest(args.out)  # config.json records the weights' SHA-256, which loading requires
    plot_curve(curve, os.path.join(args.out, "training_curve.png"))
    log = {
        "command": "python -m bits_reference.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed, "steps": step, "batch_size": args.batch_size, "lr": args.lr, "parameters": counts,
        "train_windows": n_train, "train_scenes": len(train_ids), "val_windows": int(val["v0"].shape[0]),
        "val_scenes": len(val_ids), "stride": args.stride, "data_prep_s": round(prep_time, 1),
        "train_loop_s": round(train_time, 1), "wall_time_s": round(time.perf_counter() - began, 1),
        "threads": args.threads, "machine": f"{platform.machine()} {platform.processor()}".strip(),
        "torch": torch.__version__, "final_val": final, "final_train_sample": final_train, "curve": curve,
        "data_licence": "nuScenes, CC BY-NC-SA 4.0",
    }
    with open(os.path.join(args.out, "training_log.json"), "w", encoding="utf-8") as handle:
        json.dump(log, handle, indent=2)
    print(json.dumps({k: log[k] for k in ("steps", "wall_time_s", "final_val")}, indent=2))
    return log


if __name__ == "__main__":
    main()
