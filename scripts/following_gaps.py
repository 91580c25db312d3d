r"""How close do logged drivers follow? The bumper gap to the agent ahead in each controlled agent's path, against
its own speed, over a split's logged scenes (``trafficrlhf_sdk.metrics.following_gaps``; in the path = ahead along
the heading and within half of both widths plus 0.5 m to the side).

It calibrates a desired gap ``standstill + headway x speed`` (m, s), the form CTG's gap-keeping head
(``ctg_reference.lead_gaps``) and car-following models use: it prints which share of the logged following steps
lie inside each ``--desired`` pair, and the headway that puts ``--target-share`` of them inside for each
``--standstill``. A gate meant to act only where people rarely drive should hold few logged steps: on the 442
train scenes, the follow head's first defaults (2 m, 1.5 s) hold 41 % of them and (1.5 m, 0.5 s) 5 %
(docs/explanation/alignment-log.md, session 49). Only the logged window a closed loop drives (from the current
step on) counts, and only steps with someone in the path within ``--max-gap`` m.

It also calibrates the gates that read closing in (``follow_ttc``, ``follow_decel``): over every controlled
agent-step from the current step on, the share whose time to collision with an agent in its path is below each
``--ttc`` (s), and the share that would need more than each ``--decel`` (m/s²) to stop the closing at contact
(closing speed² / (2 gap)). On the train scenes: TTC < 3 s on 2.35 %, more than 1 m/s² on 2.63 % (session 51).

    python scripts/following_gaps.py --split train --plot out/following_gaps.png
"""

from __future__ import annotations

import argparse
import json
import math

import pydantic
import torch
from tqdm import tqdm

from trafficrlhf_sdk.cli import format_error
from trafficrlhf_sdk.errors import TrafficRLHFError
from trafficrlhf_sdk.metrics import following_gaps, path_gaps
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

SPEED_BANDS = ((0.0, 0.5), (0.5, 3.0), (3.0, 8.0), (8.0, math.inf))  # m/s
QUANTILES = (0.01, 0.02, 0.05, 0.1, 0.5)


def logged_following(scenario: ScenarioTensor, max_gap_m: float = 30.0, lane_margin_m: float = 0.5
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(gap m, speed m/s)``, each ``(F,)``: every controlled agent's valid logged step from the current step on
    with an agent in its path closer than ``max_gap_m``."""
    speed = scenario.states[..., 2]
    gap = following_gaps(scenario.xy, scenario.yaw, speed, scenario.extent, scenario.valid, lane_margin_m)
    keep = scenario.controlled[..., None] & scenario.valid & (gap < max_gap_m)
    keep[..., : scenario.current_index] = False
    return gap[keep], speed[keep]


def logged_closing(scenario: ScenarioTensor, lane_margin_m: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ttc s, needed deceleration m/s²)``, each ``(C,)``: every controlled agent's valid logged step from the
    current step on, with the smallest time to collision (gap / closing speed) and the largest deceleration that
    stops the closing at contact (closing speed² / (2 gap)) over the agents in its path it closes in on (``inf``
    and 0 where it closes in on none; ``inf`` deceleration at contact)."""
    speed = scenario.states[..., 2]
    gap, closing, in_path = path_gaps(scenario.xy, scenario.yaw, speed, scenario.extent, scenario.valid,
                                      lane_margin_m)
    closing_in = in_path & (closing > 0)
    ttc = torch.where(closing_in, gap / closing.clamp_min(1e-9), torch.full_like(gap, math.inf))
    needed = torch.where(closing_in, closing.clamp_min(0) ** 2 / (2 * gap), torch.zeros_like(gap))
    if gap.shape[2] == 0:
        ttc_min, needed_max = torch.full_like(speed, math.inf), torch.zeros_like(speed)
    else:
        ttc_min, needed_max = ttc.amin(2), needed.amax(2)
    keep = scenario.controlled[..., None] & scenario.valid
    keep[..., : scenario.current_index] = False
    return ttc_min[keep], needed_max[keep]


def share_inside(gap: torch.Tensor, speed: torch.Tensor, standstill_m: float, headway_s: float) -> float:
    """The share of following steps whose gap is below ``standstill_m + headway_s x speed``."""
    return float((gap < standstill_m + headway_s * speed.clamp_min(0)).double().mean()) if gap.numel() else math.nan


def headway_for_share(gap: torch.Tensor, speed: torch.Tensor, standstill_m: float, share: float) -> float:
    """The headway (s) that puts ``share`` of the following steps inside the desired gap, by bisection (the share
    grows with the headway); ``nan`` if the standstill gap alone already holds more."""
    low, high = 0.0, 10.0
    if share_inside(gap, speed, standstill_m, low) > share:
        return math.nan
    for _ in range(50):
        middle = (low + high) / 2
        low, high = (middle, high) if share_inside(gap, speed, standstill_m, middle) < share else (low, middle)
    return round((low + high) / 2, 3)


def summary(gap: torch.Tensor, speed: torch.Tensor, desired: list[tuple[float, float]], standstills: list[float],
            target_share: float) -> dict[str, object]:
    """The printed report: gap quantiles per speed band, shares inside each desired gap, calibrated headways."""
    bands = {}
    for low, high in SPEED_BANDS:
        mask = (speed >= low) & (speed < high)
        values = gap[mask].double()
        bands[f"{low}-{high} m/s"] = {
            "steps": int(mask.sum()),
            "gap_quantiles_m": {f"{q:g}": round(float(torch.quantile(values, q)), 2) for q in QUANTILES}
            if values.numel() else {}}
    return {
        "following_steps": int(gap.numel()),
        "speed_bands": bands,
        "share_inside": {f"{s:g} m + {h:g} s": round(share_inside(gap, speed, s, h), 4) for s, h in desired},
        f"headway_for_{target_share:g}": {f"{s:g} m": headway_for_share(gap, speed, s, target_share)
                                          for s in standstills},
    }


def plot(gap: torch.Tensor, speed: torch.Tensor, desired: list[tuple[float, float]], path: str) -> None:
    """Gap against speed as a 2-D histogram, each desired gap drawn as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    ax.hist2d(speed.numpy(), gap.numpy(), bins=(60, 60), range=((0, 20), (0, 30)), cmap="Greys", norm=LogNorm())
    v = torch.linspace(0, 20, 50)
    for s, h in desired:
        share = share_inside(gap, speed, s, h)
        ax.plot(v, s + h * v, label=f"{s:g} m + {h:g} s x speed ({share:.1%} of steps inside)")
    ax.set(xlabel="own speed (m/s)", ylabel="bumper gap to the agent ahead (m)", ylim=(0, 30),
           title="Logged following gaps")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def pair(text: str) -> tuple[float, float]:
    """``STANDSTILL,HEADWAY`` as two floats."""
    try:
        standstill, headway = (float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not STANDSTILL,HEADWAY (e.g. 1.5,0.5)") from None
    return standstill, headway


def main() -> None:
    """Command-line entry point."""
    from trafficrlhf_sdk import get_scenario_source

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--split", choices=("train", "val"), default="train")
    parser.add_argument("--scenes", type=int, default=None, help="Only the split's first N scenes.")
    parser.add_argument("--max-gap", type=float, default=30.0, help="m: farther leaders do not count (default 30).")
    parser.add_argument("--desired", type=pair, action="append", default=None, metavar="STANDSTILL,HEADWAY",
                        help="A desired gap to report (m, s; repeatable; default 2,1.5 and 1.5,0.5).")
    parser.add_argument("--standstill", type=float, action="append", default=None,
                        help="Standstill gaps (m) to calibrate a headway for (repeatable; default 1.0 1.5 2.0).")
    parser.add_argument("--target-share", type=float, default=0.05,
                        help="Share of logged following steps the calibrated desired gap holds (default 0.05).")
    parser.add_argument("--ttc", type=float, action="append", default=None,
                        help="Times to collision (s) to report the share of controlled steps below (repeatable; "
                             "default 2 and 3).")
    parser.add_argument("--decel", type=float, action="append", default=None,
                        help="Decelerations (m/s²) to report the share of controlled steps needing more than, to "
                             "stop the closing at contact (repeatable; default 1, 1.5 and 2).")
    parser.add_argument("--plot", default=None, metavar="PNG", help="Also draw gap against speed there.")
    args = parser.parse_args()
    if not 0 < args.target_share < 1:
        parser.error(f"--target-share is {args.target_share}; give a share between 0 and 1, e.g. 0.05.")
    desired = args.desired or [(2.0, 1.5), (1.5, 0.5)]
    try:
        source = get_scenario_source("nuscenes_pred")
        ids = source.scene_ids(args.split)[: args.scenes]
        gaps, speeds, ttcs, needs = [], [], [], []
        for start in tqdm(range(0, len(ids), 50), desc="scenes", unit="batch"):
            batch = source.load_batch(args.split, scene_ids=ids[start:start + 50])
            gap, speed = logged_following(batch, args.max_gap)
            gaps.append(gap)
            speeds.append(speed)
            ttc, needed = logged_closing(batch)
            ttcs.append(ttc)
            needs.append(needed)
    except (TrafficRLHFError, pydantic.ValidationError, OSError) as error:  # one line, as the CLI gives it
        parser.exit(2, f"Error: {format_error(error)}\n")
    gap, speed = torch.cat(gaps), torch.cat(speeds)
    report = summary(gap, speed, desired, args.standstill or [1.0, 1.5, 2.0], args.target_share)
    ttc, needed = torch.cat(ttcs), torch.cat(needs)
    report["controlled_steps"] = int(ttc.numel())
    report["share_ttc_below"] = {f"{t:g} s": round(float((ttc < t).double().mean()), 4) for t in args.ttc or [2.0, 3.0]}
    report["share_needing_more_than"] = {f"{d:g} m/s2": round(float((needed > d).double().mean()), 4)
                                         for d in args.decel or [1.0, 1.5, 2.0]}
    print(json.dumps({"split": args.split, "scenes": len(ids), **report}, indent=1))
    if args.plot:
        plot(gap, speed, desired, args.plot)


if __name__ == "__main__":
    main()
