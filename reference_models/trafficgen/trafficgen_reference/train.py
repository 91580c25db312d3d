"""Train the compact TrafficGen on the nuScenes train split: initializer, then forecaster (one seeded command).

    .venv/bin/python -m trafficgen_reference.train \
        --out reference_models/trafficgen/checkpoints/trafficgen_small --minutes 10

Data (one pass over the train scenes):

* initializer snapshots: every ``--init-stride`` steps of a scene, the first vehicle valid then is the context
  agent; the map crop around it and every other vehicle valid then (its cell, offset, size, heading, speed) are
  one sample. Upstream trains on the scene's first frame only; several snapshots per scene give more samples.
* forecaster windows: (scene, vehicle, now) with ``now`` on a 0.5 s keyframe (the simulator replans there),
  the vehicle valid now and over the next ``--horizon`` steps (2 s by default); history (1 s) may be partial.

Validation uses val scenes that the standard 100-scene evaluation does *not* use. ``--minutes`` bounds the whole
run (data preparation included); ``--init-fraction`` of the training time goes to the initializer, the rest to
the forecaster, each with a cosine learning-rate schedule over its share. Writes ``config.json`` (loadable by
the ``trafficgen`` adapter), ``model.safetensors``, ``training_curve.png`` and ``training_log.json``.
nuScenes data: CC BY-NC-SA 4.0.
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
from safetensors.torch import load_file, save_file
from tqdm.auto import tqdm

from trafficrlhf_sdk.models.features import history_features, map_crops, neighbour_features, to_agent_frame
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

from trafficgen_reference.data import context_agent_inputs, context_slots, window_mask
from trafficgen_reference.model import TrafficGenConfig, TrafficGenModel

FORECAST_STORE = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "actions", "future_xy")
INIT_STORE = ("crop", "context", "agents", "agent_valid")


# --------------------------------------------------------------------------------------------- data
def forecast_windows(scene: ScenarioTensor, cfg: TrafficGenConfig, stride: int) -> dict[str, torch.Tensor] | None:
    """Every usable (now, vehicle) window of one scene (B = 1). History and neighbour features are computed with
    the candidate steps stacked along the batch axis (no map); the map crops of the selected rows are taken as
    the agents of one single-step scene, so the raster is never copied."""
    h, th = cfg.horizon, cfg.history_steps
    steps = [n for n in range(stride, scene.num_steps - h, stride)]
    if not steps:
        return None
    masks = torch.cat([window_mask(scene, n, h) for n in steps])  # (n, A)
    if not masks.any():
        return None
    a = scene.num_agents
    pad = th - 1
    states = torch.nn.functional.pad(scene.states[0], (0, 0, pad, 0))  # (A, pad + T, 4)
    valid = torch.nn.functional.pad(scene.valid[0], (pad, 0))
    idx = torch.tensor(steps)[:, None] + torch.arange(th)  # padded indices of now-th+1 .. now
    stacked = scene.replace_unchecked(
        states=states[:, idx].permute(1, 0, 2, 3).contiguous(), valid=valid[:, idx].permute(1, 0, 2).contiguous(),
        extent=scene.extent.expand(len(steps), a, 2), agent_type=scene.agent_type.expand(len(steps), a),
        controlled=scene.controlled.expand(len(steps), a), map=None, origin=None, current_index=th - 1,
    )
    history, history_valid = history_features(stacked, th)
    neighbours, neighbour_valid = neighbour_features(stacked, cfg.num_neighbours)
    rows = stacked.states[:, :, -1][masks]  # (N, 4)
    single = scene.replace_unchecked(
        states=rows[None, :, None], valid=torch.ones(1, len(rows), 1, dtype=torch.bool),
        extent=stacked.extent[masks][None], agent_type=stacked.agent_type[masks][None],
        controlled=torch.ones(1, len(rows), dtype=torch.bool), current_index=0,
    )
    crops = map_crops(single, size_px=cfg.map_size, resolution_m=1.0, behind_fraction=0.25)[0]
    fut = torch.tensor(steps)[:, None] + torch.arange(1, h + 1)  # (n, H)
    future = scene.states[0][:, fut].permute(1, 0, 2, 3)[masks]  # (N, H, 4)
    actions = scene.actions()[0][:, fut - 1].permute(1, 0, 2, 3)[masks]  # action t: step t -> t+1
    pose = torch.stack([rows[:, 0], rows[:, 1], rows[:, 3]], -1)[None]
    future_xy = to_agent_frame(future[None, :, :, :2], pose)[0]
    return {"map": crops.to(torch.uint8), "history": history[masks], "history_valid": history_valid[masks],
            "extent": stacked.extent[masks], "neighbours": neighbours[masks],
            "neighbour_valid": neighbour_valid[masks], "actions": actions, "future_xy": future_xy}


def init_snapshots(scene: ScenarioTensor, cfg: TrafficGenConfig, stride: int) -> dict[str, torch.Tensor] | None:
    """Initializer samples of one scene (B = 1) every ``stride`` steps."""
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in INIT_STORE}
    for n in range(0, scene.num_steps, stride):
        at = scene.replace_unchecked(current_index=n)
        slots = context_slots(at)
        if int(slots[0]) < 0:
            continue
        crop, context, agents, mask = context_agent_inputs(at, slots, cfg)
        for key, value in zip(INIT_STORE, (crop.to(torch.uint8), context, agents, mask)):
            parts[key].append(value)
    if not parts["crop"]:
        return None
    return {k: torch.cat(v) for k, v in parts.items()}


def build(source, split: str, scene_ids: list[str], cfg: TrafficGenConfig, stride: int, init_stride: int,
          desc: str) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Forecaster windows and initializer snapshots of ``scene_ids`` (agent lists padded to a common size)."""
    fparts: dict[str, list[torch.Tensor]] = {k: [] for k in FORECAST_STORE}
    iparts: dict[str, list[torch.Tensor]] = {k: [] for k in INIT_STORE}
    for scene in tqdm(source.iter_scenes(split, scene_ids), total=len(scene_ids), desc=desc, unit="scene"):
        windows = forecast_windows(scene, cfg, stride)
        if windows is not None:
            for k in FORECAST_STORE:
                fparts[k].append(windows[k])
        snaps = init_snapshots(scene, cfg, init_stride)
        if snaps is not None:
            for k in INIT_STORE:
                iparts[k].append(snaps[k])
    width = max(t.shape[1] for t in iparts["agents"])
    iparts["agents"] = [torch.nn.functional.pad(t, (0, 0, 0, width - t.shape[1])) for t in iparts["agents"]]
    iparts["agent_valid"] = [torch.nn.functional.pad(t, (0, width - t.shape[1])) for t in iparts["agent_valid"]]
    return {k: torch.cat(v) for k, v in fparts.items()}, {k: torch.cat(v) for k, v in iparts.items()}


# --------------------------------------------------------------------------------------------- training
@torch.no_grad()
def validate_forecaster(model: TrafficGenModel, data: dict[str, torch.Tensor]) -> dict[str, float]:
    """WTA loss parts, minADE and most-likely-mode ADE (m) over the horizon on ``data``."""
    model.eval()
    b = take_rows(data, torch.arange(data["actions"].shape[0]))
    loss, parts = model.forecaster.loss(b, b["actions"], b["future_xy"])
    model.train()
    return {"loss": float(loss), **parts}


@torch.no_grad()
def validate_initializer(model: TrafficGenModel, data: dict[str, torch.Tensor]) -> dict[str, float]:
    """Initializer loss parts on ``data``."""
    model.eval()
    b = take_rows(data, torch.arange(data["crop"].shape[0]))
    loss, parts = model.initializer.loss(b["crop"], b["context"], b["agents"], b["agent_valid"])
    model.train()
    return {"loss": float(loss), **parts}


INITIALIZER_FIELDS = ("init_crop_px", "init_crop_res_m", "init_cell_px", "init_width", "init_components")


def load_initializer(folder: str) -> tuple[dict, dict[str, torch.Tensor]] | None:
    """(config dict, initializer state dict) of a trafficgen checkpoint folder, or None when it is not one."""
    config_path, weights_path = os.path.join(folder, "config.json"), os.path.join(folder, "model.safetensors")
    if not (os.path.isfile(config_path) and os.path.isfile(weights_path)):
        return None
    with open(config_path, encoding="utf-8") as handle:
        config = json.load(handle).get("config", {})
    if not all(key in config for key in INITIALIZER_FIELDS):
        return None
    state = load_file(weights_path)
    prefix = "initializer."
    return config, {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def train_part(name: str, params: list[torch.nn.Parameter], step_fn, validate_fn, seconds: float,
               fixed_steps: int | None, lr: float, val_every: int, curve: dict[str, list]) -> int:
    """AdamW with warm-up and cosine decay over ``seconds`` (or ``fixed_steps``), the running train loss every
    10 steps and the validation loss every ``val_every`` steps in ``curve``; returns the steps taken."""

    def log(step: int, means: dict[str, float], rate: float) -> None:
        curve[f"{name}_step"].append(step)
        curve[f"{name}_train"].append(means["loss"])

    def validate(step: int, rate: float) -> None:
        v = validate_fn()
        curve[f"{name}_val_step"].append(step)
        curve[f"{name}_val"].append(v["loss"])
        tqdm.write(f"{name} step {step}: " + ", ".join(f"{k} {x:.4f}" for k, x in v.items()))

    optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    return fit(optimizer, params, lambda: (step_fn(), {}), lr=lr, warmup=50, steps=fixed_steps, seconds=seconds,
               val_every=val_every, on_log=log, validate=validate, desc=f"training {name}")


def main(argv: list[str] | None = None) -> None:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="Output directory.")
    parser.add_argument("--minutes", type=float, default=10.0, help="Wall-clock budget of the whole run.")
    parser.add_argument("--init-fraction", type=float, default=0.25, help="Share of training time for the initializer.")
    parser.add_argument("--init-steps", type=int, default=None, help="Fixed initializer steps (bit-reproducible).")
    parser.add_argument("--steps", type=int, default=None, help="Fixed forecaster steps (bit-reproducible).")
    parser.add_argument("--batch-size", type=int, default=128, help="Forecaster windows per step.")
    parser.add_argument("--init-batch-size", type=int, default=32, help="Initializer snapshots per step.")
    parser.add_argument("--lr", type=float, default=1.5e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stride", type=int, default=5, help="Steps between forecaster windows (5 = keyframes).")
    parser.add_argument("--init-stride", type=int, default=20, help="Steps between initializer snapshots.")
    parser.add_argument("--train-scenes", type=int, default=None, help="Use only the first N train scenes.")
    parser.add_argument("--val-every", type=int, default=200)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared).")
    parser.add_argument("--root", default=None, help="nuscenes_pred data directory (default: shared data).")
    parser.add_argument("--horizon", type=int, default=20,
                        help="Forecast steps at 0.1 s (20 = 2 s, the default model; 40 = 4 s).")
    parser.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                        help="Copy the initializer from this checkpoint folder and train the forecaster only "
                             "(the initializer is frozen in TrafficRLHF, so both models then place the same agents).")
    args = parser.parse_args(argv)
    if args.horizon < 2 or args.horizon % 2:
        parser.error(f"--horizon must be an even number of steps >= 2; got {args.horizon}.")
    donor = None
    if args.init_from is not None:
        donor = load_initializer(args.init_from)
        if donor is None:
            parser.error(f"--init-from {args.init_from!r}: no config.json + model.safetensors of a trafficgen "
                         "checkpoint there; pass a folder written by this script.")

    began = time.perf_counter()
    budget = args.minutes * 60.0
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    from trafficrlhf_sdk import get_scenario_source

    options = {"root": args.root} if args.root else {}
    # history_s=0: scenes start at their first logged step and we pick "now" ourselves; min_future_s = horizon
    cfg = TrafficGenConfig(horizon=args.horizon)
    if donor is not None:  # the initializer's architecture must match the copied weights
        for key in INITIALIZER_FIELDS:
            setattr(cfg, key, donor[0][key])
    source = get_scenario_source("nuscenes_pred", history_s=0.0, min_future_s=cfg.horizon * cfg.dt, **options)
    train_ids = source.scene_ids("train")[: args.train_scenes]
    ftrain, itrain = build(source, "train", train_ids, cfg, args.stride, args.init_stride, "featurizing train")
    held_out = set(get_scenario_source("nuscenes_pred", **options).scene_ids("val")[:100])  # the evaluation scenes
    val_ids = [s for s in source.scene_ids("val") if s not in held_out]
    fval, ival = build(source, "val", val_ids, cfg, 10, args.init_stride, "featurizing val")
    pick = torch.linspace(0, fval["actions"].shape[0] - 1, min(600, fval["actions"].shape[0])).long()
    fval = {k: v[pick] for k, v in fval.items()}
    pick = torch.linspace(0, ival["crop"].shape[0] - 1, min(240, ival["crop"].shape[0])).long()
    ival = {k: v[pick] for k, v in ival.items()}
    prep_time = time.perf_counter() - began
    n_f, n_i = ftrain["actions"].shape[0], itrain["crop"].shape[0]
    print(f"{n_f} forecaster windows and {n_i} initializer snapshots from {len(train_ids)} train scenes; "
          f"validation {fval['actions'].shape[0]} windows / {ival['crop'].shape[0]} snapshots from {len(val_ids)} "
          f"held-out val scenes; data ready in {prep_time:.0f} s")

    acts = ftrain["actions"].reshape(-1, 2)
    cfg.action_mean = [float(v) for v in acts.mean(0)]
    cfg.action_std = [float(v) for v in acts.std(0).clamp_min(1e-3)]
    model = TrafficGenModel(cfg)
    if donor is not None:
        model.initializer.load_state_dict(donor[1])
    counts = {"initializer": sum(p.numel() for p in model.initializer.parameters()),
              "forecaster": sum(p.numel() for p in model.forecaster.parameters())}
    print(f"parameters: {counts}")
    gen = torch.Generator().manual_seed(args.seed)
    curve: dict[str, list] = {k: [] for k in ("init_step", "init_train", "init_val_step", "init_val", "forecaster_step",
                                              "forecaster_train", "forecaster_val_step", "forecaster_val")}
    train_seconds = budget - prep_time - 30.0  # keep time for the final validation and writing

    def init_step() -> torch.Tensor:
        b = take_rows(itrain, torch.randint(0, n_i, (args.init_batch_size,), generator=gen))
        return model.initializer.loss(b["crop"], b["context"], b["agents"], b["agent_valid"])[0]

    def forecaster_step() -> torch.Tensor:
        b = take_rows(ftrain, torch.randint(0, n_f, (args.batch_size,), generator=gen))
        return model.forecaster.loss(b, b["actions"], b["future_xy"])[0]

    model.train()
    t0 = time.perf_counter()
    init_steps = 0
    if donor is None:
        init_steps = train_part("init", list(model.initializer.parameters()), init_step,
                                lambda: validate_initializer(model, ival), train_seconds * args.init_fraction,
                                args.init_steps, args.lr, args.val_every, curve)
    init_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    steps = train_part("forecaster", list(model.forecaster.parameters()), forecaster_step,
                       lambda: validate_forecaster(model, fval), train_seconds - init_time, args.steps, args.lr,
                       args.val_every, curve)
    forecaster_time = time.perf_counter() - t0
    final_init, final_forecaster = validate_initializer(model, ival), validate_forecaster(model, fval)
    train_pick = torch.linspace(0, n_f - 1, fval["actions"].shape[0]).long()
    final_train = validate_forecaster(model, {k: v[train_pick] for k, v in ftrain.items()})
    model.eval()

    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "config.json"), "w", encoding="utf-8") as handle:
        json.dump({"adapter": "trafficgen", "config": cfg.to_dict()}, handle, indent=2)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, os.path.join(args.out, "model.safetensors"), metadata={"format": "pt", "adapter": "trafficgen"})
    record_weights_digest(args.out)  # config.json records the weights' SHA-256, which loading requires
    plot_curve(curve, os.path.join(args.out, "training_curve.png"))
    log = {
        "command": "python -m trafficgen_reference.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed, "lr": args.lr, "batch_size": args.batch_size, "init_batch_size": args.init_batch_size,
        "init_steps": init_steps, "forecaster_steps": steps, "parameters": counts,
        "train_scenes": len(train_ids), "val_scenes": len(val_ids), "forecaster_windows": n_f,
        "initializer_snapshots": n_i, "stride": args.stride, "init_stride": args.init_stride,
        "data_prep_s": round(prep_time, 1), "initializer_train_s": round(init_time, 1),
        "forecaster_train_s": round(forecaster_time, 1), "wall_time_s": round(time.perf_counter() - began, 1),
        "horizon": cfg.horizon, "initializer_from": args.init_from,
        "threads": args.threads, "machine": f"{platform.machine()} {platform.processor()}".strip(),
        "torch": torch.__version__, "final_val_initializer": final_init, "final_val_forecaster": final_forecaster,
        "final_train_forecaster": final_train, "curve": curve, "data_licence": "nuScenes, CC BY-NC-SA 4.0",
    }
    with open(os.path.join(args.out, "training_log.json"), "w", encoding="utf-8") as handle:
        json.dump(log, handle, indent=1)
    print(json.dumps({k: log[k] for k in ("init_steps", "forecaster_steps", "wall_time_s", "final_val_initializer",
                                          "final_val_forecaster")}, indent=2))


def plot_curve(curve: dict[str, list], path: str) -> None:
    """Initializer and forecaster losses (train running mean, validation) against steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    for ax, name, label in ((axes[0], "init", "initializer: BCE + 0.2 mixture NLL"),
                            (axes[1], "forecaster", "forecaster: WTA loss")):
        ax.plot(curve[f"{name}_step"], curve[f"{name}_train"], label="train (running mean)")
        ax.plot(curve[f"{name}_val_step"], curve[f"{name}_val"], "o-", label="held-out val")
        ax.set_xlabel("step")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("compact TrafficGen on nuScenes train (CC BY-NC-SA 4.0)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
