"""``trafficrlhf_sdk.render``: map/agent alignment on synthetic scenes, options, errors and a real scene."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from PIL import Image

from trafficrlhf_sdk.errors import ScenarioValidationError
from trafficrlhf_sdk.render import (
    BACKGROUND_RGB,
    CONTROLLED_COLOUR,
    MAP_LAYER_RGB,
    render_scene,
    save_scene_png,
)
from trafficrlhf_sdk.scenario import AgentType, MapRaster, ScenarioTensor

# World regions painted on the synthetic map (x0, x1, y0, y1) in metres.
DRIVABLE_BOX = (10.0, 30.0, 5.0, 15.0)
LANE_DIVIDER_BOX = (40.0, 50.0, 5.0, 15.0)
WORLD = (-20.0, 80.0, -20.0, 50.0)  # area the raster covers


def _transform(kind: str) -> np.ndarray:
    """world -> pixel matrices of several shapes, all at 2 px/m."""
    if kind == "x_rows":
        return np.array([[2.0, 0, 40], [0, 2.0, 40], [0, 0, 1]])
    if kind == "y_rows":
        return np.array([[0, 2.0, 40], [2.0, 0, 40], [0, 0, 1]])
    if kind == "flipped":
        return np.array([[-2.0, 0, 160], [0, 2.0, 40], [0, 0, 1]])
    angle = math.radians(30)
    rot = 2.0 * np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    corners = np.array([[x, y] for x in WORLD[:2] for y in WORLD[2:]]) @ rot.T
    m = np.eye(3)
    m[:2, :2] = rot
    m[:2, 2] = -corners.min(0) + 1
    return m


def _raster(m: np.ndarray) -> torch.Tensor:
    """(1, 3, H, W) layers painted by testing each pixel centre's world position against the boxes."""
    corners = np.array([[x, y, 1.0] for x in WORLD[:2] for y in WORLD[2:]]) @ m.T
    h, w = (math.ceil(v) + 2 for v in corners[:, :2].max(0))
    ii, jj = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    world = np.stack([ii, jj, np.ones_like(ii)], -1) @ np.linalg.inv(m).T
    x, y = world[..., 0], world[..., 1]

    def inside(box: tuple[float, float, float, float]) -> np.ndarray:
        return (x >= box[0]) & (x < box[1]) & (y >= box[2]) & (y < box[3])

    layers = np.stack([inside(DRIVABLE_BOX), np.zeros_like(x, bool), inside(LANE_DIVIDER_BOX)])
    return torch.from_numpy(layers.astype(np.uint8))[None]


def synthetic_scene(kind: str = "x_rows", with_map: bool = True) -> ScenarioTensor:
    """Two agents: a car driving along y = 0 from x = 0 to 60, and a parked truck at (30, 30) facing +y."""
    t = 21
    states = torch.zeros(1, 3, t, 4)
    states[0, 0, :, 0] = torch.linspace(0, 60, t)
    states[0, 0, :, 2] = 30.0
    states[0, 1, :, 0], states[0, 1, :, 1], states[0, 1, :, 3] = 30.0, 30.0, math.pi / 2
    valid = torch.zeros(1, 3, t, dtype=torch.bool)
    valid[0, :2] = True  # agent 2 is padding
    scene_map = None
    if with_map:
        m = _transform(kind)
        scene_map = MapRaster(raster=_raster(m), world_to_pixel=torch.tensor(m, dtype=torch.float32)[None])
    return ScenarioTensor(
        states=states * valid[..., None],
        valid=valid,
        extent=torch.tensor([[[4.0, 2.0], [8.0, 2.0], [0.0, 0.0]]]),
        agent_type=torch.tensor([[AgentType.VEHICLE, AgentType.VEHICLE, AgentType.UNSET]]),
        controlled=torch.tensor([[True, True, False]]),
        dt=0.5,
        current_index=10,
        map=scene_map,
        scene_ids=("synthetic",),
        agent_ids=(("car", "truck", ""),),
        source="test",
    )


def pixel_colour(fig: Figure, x: float, y: float) -> np.ndarray:
    """RGB of the rendered figure at world point (x, y) of its first axes."""
    fig.canvas.draw()
    buffer = np.asarray(fig.canvas.buffer_rgba())
    col, row = fig.axes[0].transData.transform((x, y))
    return buffer[round(buffer.shape[0] - row), round(col), :3].astype(int)


def close_to(colour: np.ndarray, rgb: tuple[int, int, int] | str, tol: int = 12) -> bool:
    if isinstance(rgb, str):
        rgb = tuple(int(rgb[i: i + 2], 16) for i in (1, 3, 5))  # type: ignore[assignment]
    return bool(np.abs(colour - np.array(rgb)).max() <= tol)


@pytest.mark.parametrize("kind", ["x_rows", "y_rows", "flipped", "rotated"])
def test_map_is_drawn_where_world_to_pixel_puts_it(kind: str) -> None:
    scene = synthetic_scene(kind)
    # The raster itself is right: the SDK's own lookup agrees with where the boxes were painted.
    probe = torch.tensor([[[20.0, 10.0], [45.0, 10.0], [35.0, 25.0]]])
    assert scene.map.lookup(probe, "drivable").tolist() == [[True, False, False]]  # type: ignore[union-attr]
    fig = render_scene(scene, show_ids=False)
    assert close_to(pixel_colour(fig, 20.0, 10.0), MAP_LAYER_RGB["drivable"])
    assert close_to(pixel_colour(fig, 45.0, 10.0), MAP_LAYER_RGB["lane_divider"])
    assert close_to(pixel_colour(fig, 35.0, 25.0), BACKGROUND_RGB)


def test_boxes_are_oriented_along_yaw() -> None:
    fig = render_scene(synthetic_scene(), show_ids=False)
    # The truck (8 m x 2 m) faces +y at (30, 30): its rear half lies along y, not along x.
    assert close_to(pixel_colour(fig, 30.0, 27.0), CONTROLLED_COLOUR, tol=25)
    assert not close_to(pixel_colour(fig, 33.0, 30.0), CONTROLLED_COLOUR, tol=25)
    assert not close_to(pixel_colour(fig, 27.0, 30.0), CONTROLLED_COLOUR, tol=25)
    # Its front carries the white heading triangle.
    assert close_to(pixel_colour(fig, 30.0, 33.2), (255, 255, 255), tol=40)


def test_view_is_cropped_to_agents_plus_margin() -> None:
    fig = render_scene(synthetic_scene())
    ax = fig.axes[0]
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    assert x0 <= -15 + 1e-6 and x1 >= 75 - 1e-6 and y0 <= -15 + 1e-6 and y1 >= 45 - 1e-6
    assert x1 - x0 < 200 and y1 - y0 < 200  # not the whole map
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"


def test_default_step_title_labels_and_legend() -> None:
    fig = render_scene(synthetic_scene())
    ax = fig.axes[0]
    assert "synthetic" in ax.get_title() and "step 10/20" in ax.get_title()
    labels = {text.get_text() for text in ax.texts}
    assert labels == {"car", "truck"}
    legend = [text.get_text() for text in ax.get_legend().get_texts()]
    assert "controlled" in legend and "history" in legend and "simulated" not in legend
    assert not render_scene(synthetic_scene(), show_ids=False).axes[0].texts
    assert render_scene(synthetic_scene(), title="mine").axes[0].get_title() == "mine"


def test_step_moves_the_boxes() -> None:
    scene = synthetic_scene()
    late = render_scene(scene, step=20, show_ids=False)  # the car is at x = 60 at the last step
    assert close_to(pixel_colour(late, 59.0, 0.0), CONTROLLED_COLOUR, tol=25)
    now = render_scene(scene, show_ids=False)  # ... and at x = 30 now
    assert close_to(pixel_colour(now, 29.0, 0.0), CONTROLLED_COLOUR, tol=25)
    assert not close_to(pixel_colour(now, 59.0, 0.0), CONTROLLED_COLOUR, tol=25)


def test_sim_states_overlay() -> None:
    scene = synthetic_scene()
    sim = scene.states.clone()
    sim[..., 1] += 5.0 * scene.valid
    for value in (sim, sim[0], sim[0].numpy(), scene.with_future(sim[:, :, 11:])):
        fig = render_scene(scene, sim_states=value)
        assert "simulated" in [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    with pytest.raises(ScenarioValidationError, match="sim_states"):
        render_scene(scene, sim_states=torch.zeros(5, 21, 4))


def test_errors_and_no_map() -> None:
    scene = synthetic_scene()
    with pytest.raises(ScenarioValidationError, match="step"):
        render_scene(scene, step=21)
    with pytest.raises(ScenarioValidationError, match="index"):
        render_scene(scene, index=1)
    fig = render_scene(synthetic_scene(with_map=False))
    assert isinstance(fig, Figure)


def test_empty_scene_shows_the_map() -> None:
    scene = synthetic_scene()
    empty = ScenarioTensor(states=torch.zeros_like(scene.states), valid=torch.zeros_like(scene.valid),
                           extent=scene.extent, agent_type=scene.agent_type,
                           controlled=torch.zeros_like(scene.controlled), dt=scene.dt,
                           current_index=scene.current_index, map=scene.map)
    ax = render_scene(empty).axes[0]
    assert ax.get_xlim()[0] <= -19 and ax.get_xlim()[1] >= 79


def test_draws_into_given_axes_and_batches() -> None:
    batch = ScenarioTensor.concat([synthetic_scene(), synthetic_scene("rotated")])
    fig = Figure()
    ax = fig.add_subplot()
    assert render_scene(batch, index=1, ax=ax) is fig
    assert len(fig.axes) == 1 and ax.collections


def test_save_scene_png(tmp_path: Path) -> None:
    path = save_scene_png(synthetic_scene(), tmp_path / "nested" / "scene.png", dpi=60)
    assert Path(path).is_file()
    with Image.open(path) as image:
        assert image.format == "PNG" and image.size[0] >= 400


def test_real_scene_renders_fast(val_scenes: ScenarioTensor, tmp_path: Path) -> None:
    render_scene(val_scenes, index=0)  # warm-up (fonts, caches)
    start = time.perf_counter()
    path = save_scene_png(val_scenes, tmp_path / "real.png", index=1)
    elapsed = time.perf_counter() - start
    assert elapsed < 2.0, f"rendering one scene took {elapsed:.2f} s"
    assert Path(path).stat().st_size > 10_000
