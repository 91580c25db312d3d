"""The configuration of :class:`~ctg_reference.model.CTGModel`: architecture, diffusion and normalization."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = ["CTGConfig"]


@dataclass
class CTGConfig:
    """Architecture, diffusion and normalization settings (JSON-serializable via :meth:`to_dict`)."""

    horizon: int = 20
    dt: float = 0.1
    map_channels: int = 3
    map_size: int = 48
    map_resolution: float = 1.0  # metres per crop cell (the crop spans map_size * map_resolution m)
    history_steps: int = 10
    num_neighbours: int = 8
    cond_dim: int = 128
    map_dim: int = 128
    cnn_width: int = 8  # channels of the map CNN's first layer; each of its 4 layers doubles them
    unet_dims: tuple[int, int] = (32, 64)
    kernel_size: int = 3
    groups: int = 8
    time_dim: int = 32
    diffusion_steps: int = 100
    sample_steps: int = 5
    eta: float = 1.0
    guidance_step: float = 0.3
    x0_clip: float = 6.0
    state_loss_weight: float = 1.0
    # interaction: steps after now at which the neighbours' planned positions are an input (empty: none). Where
    # those plans come from at sampling time is the caller's choice (the ctg adapter's ``plan_mode``: a proposal
    # pass, or the neighbours' clean predictions at every denoising step through ``sample(cond_fn=...)``).
    neighbour_plan_steps: list[int] = field(default_factory=list)
    plan_dropout_all: float = 0.5  # training: share of windows that see no neighbour plan (the proposal pass)
    plan_dropout_each: float = 0.2  # training: share of the other windows' neighbour plans hidden one by one
    # scene-level (joint) denoising: each denoising step of an agent also reads the current noisy samples of the
    # neighbours denoised with it (CoDenoiseMixer); training shares one noise level per scene and step
    scene_denoising: bool = False
    scene_dropout: float = 0.3  # training: share of co-denoised neighbours shown as not co-denoised (log replay)
    # steering head (SteerHead): a learned shift of each sampling step's mean, zero until fine-tuned; the
    # encoder and denoiser stay as trained, so only how the sampler moves through them changes
    steer: bool = False
    steer_hidden: int = 128
    # the head also reads the drivable layer of the agent's map crop along each step's clean plan (on it, and
    # steer_road_offset m to either side of it), so whether a plan leaves the road is an input, not a pattern
    # the head would have to find in the encoder's summary of the whole crop
    steer_road: bool = False
    steer_road_offset: float = 1.0
    # the head also reads how close the other agents come to each step's clean plan (on it and
    # steer_road_offset m to either side), with each neighbour driven on at its current velocity: the road
    # profile tells the head where the road ends, this where the traffic is
    steer_neighbours: bool = False
    steer_neighbour_scale: float = 2.0  # m: proximity exp(-clearance / scale) of a neighbour's footprint
    # gate the head's shift by the plan's hazard, the largest over its steps and probes of the off-road share
    # (inside the crop) and the neighbour proximity: a plan with the road clear around it and nobody near is
    # left as the frozen model draws it, so steering cannot change driving that needed no change
    steer_gate: bool = False
    # gap keeping (FollowHead): a second head, acceleration channel only, reading the gap to the agent ahead in
    # each step's clean plan (lead_gaps: neighbours at constant velocity) and gated by the headway hazard
    # clamp(1 - gap / (follow_standstill + follow_headway * speed), 0, 1); zero until fine-tuned, and exactly
    # zero for plans with nobody ahead closer than that desired gap
    follow: bool = False
    follow_hidden: int = 64
    follow_lane_margin: float = 0.5  # m beyond half of both widths to the side that still counts as in the path
    # desired gap: follow_standstill + follow_headway x speed, short enough that ordinary following is left alone
    follow_standstill: float = 1.5  # m: desired bumper-to-bumper gap at standstill
    follow_headway: float = 0.5  # s: desired time gap at the planned speed
    # s: if set, the gate reads the time to collision with the agent ahead instead of the desired gap,
    # clamp(1 - TTC / follow_ttc, 0, 1) while closing in, so steady following at a short gap is left alone
    follow_ttc: float | None = None
    # if set, only agents heading the plan's way lead (cosine of the heading difference at least this)
    follow_heading_cos: float | None = None
    # if set, the gate reads only the first this many plan steps (5 at 0.1 s: what runs before the next 2 Hz replan);
    # the head still reads them all. Plans that stop in time read a short time to collision at their end, which a
    # gate over the whole plan would brake too
    follow_gate_steps: int | None = None
    # normalization (filled from data by the training script)
    action_mean: list[float] = field(default_factory=lambda: [0.0, 0.0])
    action_std: list[float] = field(default_factory=lambda: [1.0, 0.1])
    state_std: list[float] = field(default_factory=lambda: [10.0, 1.0, 3.0, 0.1])

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (tuples as lists)."""
        d = asdict(self)
        d["unet_dims"] = list(self.unet_dims)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CTGConfig:
        """Inverse of :meth:`to_dict` (unknown keys are an error)."""
        d = dict(d)
        if "unet_dims" in d:
            d["unet_dims"] = tuple(d["unet_dims"])
        return cls(**d)
