"""Train the compact CTG on the nuScenes train split (one seeded command, a few minutes on 2 CPU cores).

    .venv/bin/python -m ctg_reference.train --out reference_models/ctg/checkpoints/ctg_small --minutes 14

Samples are (scene, vehicle, step t) with 1 s of valid history up to t and a fully valid 2 s future, t every
``--stride`` steps. Features come from the SDK's feature functions, targets from its inverse dynamics. The
validation set is taken from val scenes that the standard 100-scene evaluation does *not* use.
``--minutes`` bounds the whole run (data preparation included); the learning-rate schedule follows the elapsed
fraction of the budget unless ``--steps`` fixes the number of steps (bit-reproducible).

Writes ``config.json`` (loadable by the ``ctg`` adapter), ``model.safetensors`` (EMA weights),
``training_curve.png`` and ``training_log.json``. nuScenes data: CC BY-NC-SA 4.0.
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
from tqdm.auto import tqdm

from trafficrlhf_sdk.simulation.dynamics import wrap_angle
from trafficrlhf_sdk.models.features import history_features, map_crops, neighbour_features, to_agent_frame
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.transforms import mirror_scenario

from ctg_reference.data import PLAN_KEYS, co_denoised_rows, drop_neighbour_plans, neighbour_plan_features
from ctg_reference.model import CTGConfig, CTGModel

STORE_KEYS = ("map", "history", "history_valid", "extent", "neighbours", "neighbour_valid", "v0", "actions",
              "states")
SCENE_KEYS = ("neighbour_row", "window")


def scene_samples(scene, cfg: CTGConfig, stride: int) -> dict[str, torch.Tensor] | None:
    """All usable windows of one scene (B = 1), featurized at once: the candidate "now" steps are stacked along
    the batch axis (history window only, no map) for history/neighbour features, and the selected (t, agent)
    rows become the agents of a single-step, one-scene context for the map crops (no raster copies)."""
    h, th = cfg.horizon, cfg.history_steps
    steps = torch.arange(th, scene.num_steps - h, stride)
    if len(steps) == 0:
        return None
    a = scene.num_agents
    valid = scene.valid[0]  # (A, T)
    span = steps[:, None] + torch.arange(-th, h + 1)  # (n, th + h + 1)
    mask = valid[:, span].all(-1).T & (scene.agent_type[0] == int(AgentType.VEHICLE))  # (n, A)
    if not mask.any():
        return None
    hist_idx = steps[:, None] + torch.arange(-th + 1, 1)  # (n, th): steps now-th+1 .. now
    n = len(steps)
    stacked = scene.replace_unchecked(
        states=scene.states[0][:, hist_idx].permute(1, 0, 2, 3).contiguous(),
        valid=valid[:, hist_idx].permute(1, 0, 2).contiguous(),
        extent=scene.extent.expand(n, a, 2), agent_type=scene.agent_type.expand(n, a),
        controlled=scene.controlled.expand(n, a), map=None, origin=None, current_index=th - 1,
    )
    history, history_valid = history_features(stacked, th)
    neighbours, neighbour_valid, neighbour_index = neighbour_features(stacked, cfg.num_neighbours,
                                                                      return_index=True)
    now = stacked.states[:, :, -1]  # (n, A, 4)
    rows = now[mask]  # (N, 4)
    single = scene.replace_unchecked(
        states=rows[None, :, None], valid=torch.ones(1, len(rows), 1, dtype=torch.bool),
        extent=stacked.extent[mask][None], agent_type=stacked.agent_type[mask][None],
        controlled=torch.ones(1, len(rows), dtype=torch.bool), current_index=0,
    )
    crops = map_crops(single, size_px=cfg.map_size, resolution_m=cfg.map_resolution, behind_fraction=0.25)[0]
    fut_idx = steps[:, None] + torch.arange(1, h + 1)  # (n, H)
    future = scene.states[0][:, fut_idx].permute(1, 0, 2, 3)[mask]  # (N, H, 4)
    actions = scene.actions()[0][:, fut_idx - 1].permute(1, 0, 2, 3)[mask]  # action t: step t -> t+1
    pose = torch.stack([rows[:, 0], rows[:, 1], rows[:, 3]], -1)[None]  # (1, N, 3)
    local = to_agent_frame(future[None, :, :, :2], pose)[0]
    yaw = wrap_angle(future[..., 3] - rows[:, 3:4])
    out = {
        "map": crops.to(torch.uint8), "history": history[mask], "history_valid": history_valid[mask],
        "extent": stacked.extent[mask], "neighbours": neighbours[mask], "neighbour_valid": neighbour_valid[mask],
        "v0": rows[:, 2], "actions": actions, "states": torch.cat([local, future[..., 2:3], yaw[..., None]], -1),
    }
    if cfg.scene_denoising:  # which rows of the same step are each row's neighbours (denoised together)
        out["neighbour_row"] = co_denoised_rows(mask, neighbour_index, neighbour_valid)
        out["window"] = torch.arange(n)[:, None].expand(n, a)[mask]
    if cfg.neighbour_plan_steps:  # the neighbours' logged positions at the plan steps, as their "plans"
        plan_idx = (steps[:, None] + torch.tensor(cfg.neighbour_plan_steps)).clamp_max(scene.num_steps - 1)
        positions = scene.xy[0][:, plan_idx].permute(1, 0, 2, 3)[:, None]  # (n, 1, A, F, 2)
        known = scene.valid[0][:, plan_idx].permute(1, 0, 2)[:, None]  # (n, 1, A, F)
        plan, plan_valid = neighbour_plan_features(stacked, neighbours, neighbour_valid, neighbour_index,
                                                   positions, known)
        out["neighbour_plan"], out["neighbour_plan_valid"] = plan[:, 0][mask], plan_valid[:, 0][mask]
    return out


def build_samples(source, split: str, scene_ids: list[str], cfg: CTGConfig, stride: int,
                  desc: str = "", mirror: bool = False) -> dict[str, torch.Tensor]:
    """Featurize every usable (scene, vehicle, t) window of ``scene_ids``; map crops stored as uint8. With
    ``mirror``, each scene's mirror image (``y -> -y``, its map reflected alike) adds its windows too."""
    keys = STORE_KEYS + (PLAN_KEYS if cfg.neighbour_plan_steps else ()) + (SCENE_KEYS if cfg.scene_denoising else ())
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    rows = windows = 0  # offsets: scene-denoising rows and windows are indexed over all scenes
    scenes = source.iter_scenes(split, scene_ids)
    for scene in tqdm(scenes, total=len(scene_ids), desc=desc or f"featurizing {split}", unit="scene"):
        for variant in (scene, mirror_scenario(scene)) if mirror else (scene,):
            samples = scene_samples(variant, cfg, stride)
            if samples is None:
                continue
            if cfg.scene_denoising:
                row = samples["neighbour_row"]
                samples["neighbour_row"] = torch.where(row >= 0, row + rows, row)
                samples["window"] = samples["window"] + windows
                windows = int(samples["window"].max()) + 1
            rows += samples["v0"].shape[0]
            for k in keys:
                parts[k].append(samples[k])
    return {k: torch.cat(v) for k, v in parts.items()}


def scene_batch(data: dict[str, torch.Tensor], idx: torch.Tensor, dropout: float = 0.0,
                generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """Rows ``idx`` of scene-denoising samples with ``neighbour_row`` re-indexed into the batch (neighbours
    outside it, and a share ``dropout`` of the others, become -1) and ``group``: the batch's windows as
    ``0..G-1``, so each window's rows get one noise level."""
    out = subset_rows(data, idx)
    out["map"] = out["map"].float()
    local = out["neighbour_row"]
    if dropout > 0:
        local = torch.where(torch.rand(local.shape, generator=generator) < dropout, torch.full_like(local, -1), local)
    out["neighbour_row"] = local
    out["group"] = torch.unique(out.pop("window"), return_inverse=True)[1]
    return out


def subset_rows(data: dict[str, torch.Tensor], idx: torch.Tensor) -> dict[str, torch.Tensor]:
    """Rows ``idx`` of scene-denoising samples, ``neighbour_row`` re-indexed into them (-1 outside)."""
    out = {k: v[idx] for k, v in data.items()}
    position = torch.full((data["v0"].shape[0],), -1, dtype=torch.long)
    position[idx] = torch.arange(len(idx))
    row = out["neighbour_row"]
    out["neighbour_row"] = torch.where(row >= 0, position[row.clamp_min(0)], row)
    return out


def whole_windows(data: dict[str, torch.Tensor], seeds: torch.Tensor) -> torch.Tensor:
    """Every row of the windows (scene, step) that the rows ``seeds`` belong to (windows are contiguous)."""
    window = data["window"]
    chosen = torch.zeros(int(window[-1]) + 1, dtype=torch.bool)
    chosen[window[seeds]] = True
    return chosen[window].nonzero()[:, 0]


@torch.no_grad()
def validate(model: CTGModel, data: dict[str, torch.Tensor], num_samples: int = 5, seed: int = 123
             ) -> dict[str, float]:
    """Diffusion loss (fixed noise) and minADE/minFDE (m) of ``num_samples`` DDIM samples."""
    model.eval()
    gen = torch.Generator().manual_seed(seed)
    everything = torch.arange(data["v0"].shape[0])
    b = scene_batch(data, everything) if model.mixer is not None else take_rows(data, everything)
    cond, scene = model.encode(b), model.scene_rows(b)
    loss, parts = model.loss(cond, b["actions"], b["v0"], b["states"], generator=gen, scene=scene,
                             group=b.get("group"))
    actions, _, _, _ = model.sample(cond, num_samples, gen, scene=scene)
    pos = model.rollout(model.normalize(actions), b["v0"][:, None].expand(-1, num_samples))[..., :2]
    err = torch.linalg.vector_norm(pos - b["states"][:, None, :, :2], dim=-1)  # (N, S, H)
    model.train()
    return {"loss": float(loss), "action": float(parts["action"]), "state": float(parts["state"]),
            "min_ade": float(err.mean(-1).amin(-1).mean()), "min_fde": float(err[..., -1].amin(-1).mean())}


def main(argv: list[str] | None = None) -> None:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="Output directory.")
    parser.add_argument("--minutes", type=float, default=12.0, help="Wall-clock budget of the whole run.")
    parser.add_argument("--steps", type=int, default=None, help="Fixed number of steps (overrides the time budget).")
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--lr", type=float, default=1.5e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stride", type=int, default=2, help="Steps between training windows of one agent.")
    parser.add_argument("--train-scenes", type=int, default=None, help="Use only the first N train scenes.")
    parser.add_argument("--val-samples", type=int, default=400)
    parser.add_argument("--val-every", type=int, default=200)
    parser.add_argument("--ema", type=float, default=0.995)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--root", default=None, help="nuscenes_pred data directory (default: shared data).")
    parser.add_argument("--horizon", type=int, default=20,
                        help="Planned steps at 0.1 s (default 20 = 2 s; even, for the U-Net's one down level).")
    parser.add_argument("--map-size", type=int, default=48, help="Map crop side in cells (default 48).")
    parser.add_argument("--map-resolution", type=float, default=1.0,
                        help="Metres per map crop cell (default 1.0; the source raster has 3 px/m).")
    parser.add_argument("--unet-dims", type=int, nargs=2, default=(32, 64), metavar=("D1", "D2"),
                        help="Channels of the denoiser U-Net's two levels (default 32 64).")
    parser.add_argument("--cond-dim", type=int, default=128, help="Conditioning vector size (default 128).")
    parser.add_argument("--map-dim", type=int, default=128, help="Map feature size (default 128).")
    parser.add_argument("--cnn-width", type=int, default=8,
                        help="First map-CNN layer's channels, doubled per layer (default 8; a multiple of 8).")
    parser.add_argument("--mirror", action="store_true",
                        help="Also train on each train scene's mirror image (twice the windows; nuScenes has both "
                             "right-hand Boston and left-hand Singapore traffic).")
    parser.add_argument("--neighbour-plan-steps", type=int, nargs="*", default=[], metavar="STEP",
                        help="Interaction: condition on the neighbours' planned positions this many steps ahead "
                             "(e.g. 10 20 30 40); the adapter then samples a proposal pass and a conditioned "
                             "pass. Default: none (the bundled checkpoints' layout).")
    parser.add_argument("--plan-dropout-all", type=float, default=0.5,
                        help="With --neighbour-plan-steps: share of training windows that see no neighbour plan.")
    parser.add_argument("--plan-dropout-each", type=float, default=0.2,
                        help="With --neighbour-plan-steps: share of the other windows' neighbour plans hidden.")
    parser.add_argument("--scene-denoising", action="store_true",
                        help="Scene-level model: every denoising step of an agent reads the current noisy samples of "
                             "the neighbours denoised with it; training shares one noise level per scene and step.")
    parser.add_argument("--scene-dropout", type=float, default=0.3,
                        help="With --scene-denoising: share of co-denoised neighbours hidden in training (as for "
                             "log-replayed neighbours in simulation).")
    args = parser.parse_args(argv)

    began = time.perf_counter()
    budget = args.minutes * 60.0
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    from trafficrlhf_sdk import get_scenario_source

    options = {"root": args.root} if args.root else {}
    if args.horizon < 2 or args.horizon % 2:
        parser.error(f"--horizon must be an even number of steps >= 2; got {args.horizon}.")
    if args.map_size < 16 or args.map_resolution <= 0:
        parser.error(f"--map-size must be >= 16 and --map-resolution > 0; got {args.map_size}, {args.map_resolution}.")
    if min(args.unet_dims) < 8 or any(d % 8 for d in args.unet_dims) or args.cnn_width % 8:
        parser.error(f"--unet-dims and --cnn-width must be multiples of 8 (GroupNorm groups); got "
                     f"{args.unet_dims}, {args.cnn_width}.")
    cfg = CTGConfig(horizon=args.horizon, map_size=args.map_size, map_resolution=args.map_resolution,
                    unet_dims=tuple(args.unet_dims), cond_dim=args.cond_dim, map_dim=args.map_dim,
                    cnn_width=args.cnn_width, neighbour_plan_steps=list(args.neighbour_plan_steps),
                    plan_dropout_all=args.plan_dropout_all, plan_dropout_each=args.plan_dropout_each,
                    scene_denoising=args.scene_denoising, scene_dropout=args.scene_dropout)
    if cfg.scene_denoising and cfg.neighbour_plan_steps:
        parser.error("--scene-denoising and --neighbour-plan-steps are two kinds of interaction; choose one.")
    if not 0 <= cfg.scene_dropout < 1:
        parser.error(f"--scene-dropout is a share in [0, 1); got {cfg.scene_dropout}.")
    if not (0 <= cfg.plan_dropout_all <= 1 and 0 <= cfg.plan_dropout_each <= 1):
        parser.error(f"--plan-dropout-all and --plan-dropout-each are shares in [0, 1]; got "
                     f"{cfg.plan_dropout_all}, {cfg.plan_dropout_each}.")
    if any(step < 1 or step > args.horizon for step in cfg.neighbour_plan_steps):
        parser.error(f"--neighbour-plan-steps must lie in 1..--horizon ({args.horizon}); got "
                     f"{cfg.neighbour_plan_steps}.")
    # history_s=0: windows start at the first logged step; we pick "now" ourselves; every scene with one horizon
    source = get_scenario_source("nuscenes_pred", history_s=0.0, min_future_s=cfg.horizon * cfg.dt, **options)
    train_ids = source.scene_ids("train")[: args.train_scenes]
    train = build_samples(source, "train", train_ids, cfg, args.stride, mirror=args.mirror)
    # validation: val scenes outside the first 100 long-enough ones (those are the evaluation scenes)
    eval_source = get_scenario_source("nuscenes_pred", **options)
    held_out = set(eval_source.scene_ids("val")[:100])
    val_ids = [s for s in source.scene_ids("val") if s not in held_out]
    val = build_samples(source, "val", val_ids, cfg, stride=10, desc="featurizing val")
    pick = torch.linspace(0, val["v0"].shape[0] - 1, min(args.val_samples, val["v0"].shape[0])).long()
    if cfg.scene_denoising:  # the whole windows of a third as many rows, neighbours re-indexed into the subset
        val = subset_rows(val, whole_windows(val, pick[::3]))
    else:
        val = {k: v[pick] for k, v in val.items()}
    prep_time = time.perf_counter() - began
    n_train = train["v0"].shape[0]
    print(f"{n_train} training windows from {len(train_ids)} scenes, {val['v0'].shape[0]} validation windows "
          f"from {len(val_ids)} scenes; data ready in {prep_time:.0f} s")

    model = CTGModel(cfg)
    acts = train["actions"].reshape(-1, 2)
    states = train["states"].reshape(-1, 4)
    model.set_normalization(acts.mean(0), acts.std(0).clamp_min(1e-3), states.std(0).clamp_min(1e-3))
    ema = CTGModel(CTGConfig.from_dict(model.cfg.to_dict()))
    ema.load_state_dict(model.state_dict())
    ema.requires_grad_(False)
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    gen = torch.Generator().manual_seed(args.seed)
    num_params = sum(p.numel() for p in model.parameters())
    print(f"model: {num_params} parameters")

    if cfg.scene_denoising:  # seed rows per batch so that their whole windows hold about batch_size rows
        sizes = torch.bincount(train["window"]).float()
        biased = float((sizes**2).sum() / sizes.sum())  # a random row's window size
        scene_seeds = max(1, round(args.batch_size / biased))
        print(f"scene-level denoising: {scene_seeds} windows per batch (a row's window holds {biased:.1f} rows)")
    train_budget = budget - prep_time - 45.0  # keep time for the final validation and writing
    warmup = 100
    curve: dict[str, list] = {"step": [], "train_loss": [], "val_step": [], "val_loss": [], "val_min_ade": []}
    loop_began = time.perf_counter()

    def train_step() -> tuple[torch.Tensor, dict[str, float]]:
        if cfg.scene_denoising:  # whole windows, about batch_size rows
            idx = whole_windows(train, torch.randint(0, n_train, (scene_seeds,), generator=gen))
            b = scene_batch(train, idx, cfg.scene_dropout, gen)
        else:
            b = take_rows(train, torch.randint(0, n_train, (args.batch_size,), generator=gen))
        if cfg.neighbour_plan_steps:
            b["neighbour_plan_valid"] = drop_neighbour_plans(b["neighbour_plan_valid"], cfg, gen)
        loss, _ = model.loss(model.encode(b), b["actions"], b["v0"], b["states"], generator=gen,
                             scene=model.scene_rows(b), group=b.get("group"))
        return loss, {}

    @torch.no_grad()
    def update_ema(step: int) -> None:  # the EMA copy starts once the warm-up is over
        decay = 0.0 if step < warmup else args.ema
        for pe, pm in zip(ema.parameters(), model.parameters()):
            pe.mul_(decay).add_(pm.detach(), alpha=1 - decay)

    def log(step: int, means: dict[str, float], lr: float) -> None:
        curve["step"].append(step)
        curve["train_loss"].append(means["loss"])

    def validate_ema(step: int, lr: float) -> None:
        v = validate(ema, val)
        curve["val_step"].append(step)
        curve["val_loss"].append(v["loss"])
        curve["val_min_ade"].append(v["min_ade"])
        tqdm.write(f"step {step}: val loss {v['loss']:.4f} minADE@5 {v['min_ade']:.3f} m")

    step = fit(optimizer, model.parameters(), train_step, lr=args.lr, warmup=warmup, steps=args.steps,
               seconds=train_budget, val_every=args.val_every, after_step=update_ema, on_log=log,
               validate=validate_ema, desc="training")
    train_time = time.perf_counter() - loop_began
    final = validate(ema, val)
    curve["val_step"].append(step)
    curve["val_loss"].append(final["loss"])
    curve["val_min_ade"].append(final["min_ade"])
    spread = torch.linspace(0, n_train - 1, len(val["v0"])).long()
    final_train = validate(ema, subset_rows(train, whole_windows(train, spread[::3])) if cfg.scene_denoising
                           else {k: v[spread] for k, v in train.items()})

    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "config.json"), "w", encoding="utf-8") as handle:
        json.dump({"adapter": "ctg", "config": ema.cfg.to_dict()}, handle, indent=2)
    state = {k: v.detach().cpu().contiguous() for k, v in ema.state_dict().items()}
    save_file(state, os.path.join(args.out, "model.safetensors"), metadata={"format": "pt", "adapter": "ctg"})
    record_weights_digest(args.out)  # config.json records the weights' SHA-256, which loading requires
    plot_curve(curve, os.path.join(args.out, "training_curve.png"))
    log = {
        "command": "python -m ctg_reference.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": args.seed, "steps": step, "batch_size": args.batch_size, "lr": args.lr, "ema": args.ema,
        "parameters": num_params, "train_windows": n_train, "train_scenes": len(train_ids),
        "val_windows": int(val["v0"].shape[0]), "val_scenes": len(val_ids), "stride": args.stride,
        "data_prep_s": round(prep_time, 1), "train_loop_s": round(train_time, 1),
        "wall_time_s": round(time.perf_counter() - began, 1), "threads": args.threads,
        "machine": f"{platform.machine()} {platform.processor()}".strip(), "torch": torch.__version__,
        "final_val": final, "final_train_ema": final_train,
        "curve": curve,
        "data_licence": "nuScenes, CC BY-NC-SA 4.0",
    }
    with open(os.path.join(args.out, "training_log.json"), "w", encoding="utf-8") as handle:
        json.dump(log, handle, indent=2)
    print(json.dumps({k: log[k] for k in ("steps", "wall_time_s", "final_val", "final_train_ema")}, indent=2))


def plot_curve(curve: dict[str, list], path: str) -> None:
    """Train (running mean) and validation loss vs step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(curve["step"], curve["train_loss"], label="train (running mean)")
    ax[0].plot(curve["val_step"], curve["val_loss"], "o-", label="val (EMA weights)")
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("diffusion loss")
    ax[0].set_yscale("log")
    ax[0].legend()
    ax[1].plot(curve["val_step"], curve["val_min_ade"], "o-", color="tab:green")
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("val minADE@5 (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
