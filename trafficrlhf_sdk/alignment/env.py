"""``TrafficRLHFEnv``: the closed-loop simulator as a Gymnasium environment, with a reward model as reward.

One episode drives one "ego" agent of a logged scene for ``episode_s`` seconds from ``start_index`` (3 s by
default); every other agent replays the log. An action in [-1, 1]^2 is scaled to (acceleration in m/s^2,
yaw rate in rad/s) by ``ACTION_SCALE`` (5 m/s^2, 1 rad/s), held for
``action_repeat`` simulator steps of 0.1 s (0.5 s by default, the simulator's replanning period) and passed
through the SDK's unicycle dynamics (which clip it to the speed-dependent bounds). The reward of a step is the
reward model's per-step reward at the step reached, with the ego as the only controlled agent.

Observation (float32, clipped to +-``OBS_LIMIT``), in the ego's frame:
``[speed/10, last action (2, unit-scaled), elapsed fraction]``, then for the ``num_neighbours``
nearest agents ``[x/20, y/20, cos dyaw, sin dyaw, speed/10, present]``, then the drivable layer of a
``map_size_px`` x ``map_size_px`` crop (cells of ``map_resolution_m``) flattened.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch

from trafficrlhf_sdk.reward.builtin import FailureReward
from trafficrlhf_sdk.simulation.dynamics import unicycle_step
from trafficrlhf_sdk.errors import DataNotFoundError
from trafficrlhf_sdk.models.features import map_crops, neighbour_features
from trafficrlhf_sdk.scenario.agents import AgentType
from trafficrlhf_sdk.scenario.tensor import ScenarioTensor

__all__ = ["ACTION_SCALE", "OBS_LIMIT", "TrafficRLHFEnv"]

OBS_LIMIT = 10.0
ACTION_SCALE = (5.0, 1.0)  # acceleration (m/s^2) and yaw rate (rad/s) of a unit action


class TrafficRLHFEnv(gym.Env):
    """Gymnasium environment over logged scenes (see the module docstring).

    Args:
        scenes: logged scenes (a batch is split into single scenes); None loads ``num_scenes`` scenes of
            ``split`` from ``source``.
        reward_model: anything with ``step_rewards(scenario) -> (B, T)`` in [-1, 1] (a reward model);
            None: :class:`~trafficrlhf_sdk.reward.builtin.FailureReward` (minus collision / off-road).
        start_index: step the episode starts after (3 s of history at 0.1 s).
        episode_s: simulated seconds per episode (10 s); shorter if the log ends first.
        action_repeat: simulator steps per action.
        num_neighbours, map_size_px, map_resolution_m: observation layout.
        reward_history_steps: logged/simulated steps the reward model sees before the scored step.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, scenes: ScenarioTensor | None = None, reward_model: Any = None, *,
                 source: str = "nuscenes_pred", split: str = "train", root: str | None = None, num_scenes: int = 20,
                 start_index: int = 30, episode_s: float = 10.0, action_repeat: int = 5, num_neighbours: int = 4,
                 map_size_px: int = 8, map_resolution_m: float = 2.0, reward_history_steps: int = 10) -> None:
        super().__init__()
        if scenes is None:
            from trafficrlhf_sdk.plugins import get_scenario_source

            src = get_scenario_source(source, **({"root": root} if root else {}))
            scenes = src.load_batch(split, num_scenes)
        self.scenes = [scenes[i] for i in range(scenes.num_scenes)]
        self.reward_model = reward_model if reward_model is not None else FailureReward()
        self.start_index = start_index
        self.action_repeat = action_repeat
        self.num_neighbours = num_neighbours
        self.map_size_px = map_size_px
        self.map_resolution_m = map_resolution_m
        self.reward_history_steps = reward_history_steps
        self.episode_steps = max(1, round(episode_s / scenes.dt))
        self.candidates = [(i, self._egos(s)) for i, s in enumerate(self.scenes)]
        self.candidates = [(i, e) for i, e in self.candidates if e]
        if not self.candidates:
            raise DataNotFoundError(f"no scene has a vehicle valid at step {start_index} to drive.")
        dim = 4 + 6 * num_neighbours + map_size_px * map_size_px
        self.observation_space = gym.spaces.Box(-OBS_LIMIT, OBS_LIMIT, (dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._scenario: ScenarioTensor | None = None

    def _egos(self, scene: ScenarioTensor) -> list[int]:
        if scene.num_steps <= self.start_index + self.action_repeat:
            return []
        now = scene.valid[0, :, self.start_index]
        vehicle = scene.agent_type[0] == AgentType.VEHICLE
        preferred = (scene.controlled[0] & now & vehicle).nonzero().flatten().tolist()
        return preferred or (now & vehicle).nonzero().flatten().tolist()

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Pick a scene and an ego vehicle (from ``np_random``); returns the first observation and info."""
        super().reset(seed=seed)
        scene_index, egos = self.candidates[int(self.np_random.integers(len(self.candidates)))]
        scene = self.scenes[scene_index]
        self.ego = egos[int(self.np_random.integers(len(egos)))]
        controlled = torch.zeros_like(scene.controlled)
        controlled[0, self.ego] = True
        self._states = scene.states.clone()
        self._valid = scene.valid.clone()
        self._scenario = scene.replace_unchecked(states=self._states, valid=self._valid, controlled=controlled)
        self.t = self.start_index
        self.end = min(self.start_index + self.episode_steps, scene.num_steps - 1)
        self.last_action = np.zeros(2, np.float32)
        return self._observation(), {"scene_id": scene.scene_ids[0] if scene.scene_ids else str(scene_index),
                                     "ego": self.ego}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply ``action`` for ``action_repeat`` steps; reward = the reward model's step reward reached."""
        if self._scenario is None:
            raise RuntimeError("call reset() before step().")
        action = np.clip(np.asarray(action, np.float32), self.action_space.low, self.action_space.high)
        act = torch.as_tensor(action) * torch.tensor(ACTION_SCALE)
        for _ in range(self.action_repeat):
            if self.t >= self.end:
                break
            state = unicycle_step(self._states[0, self.ego, self.t], act, self._scenario.dt)
            self.t += 1
            self._states[0, self.ego, self.t] = state
            self._valid[0, self.ego, self.t] = True
        self.last_action = action  # in [-1, 1] units
        window = self._scenario.time_slice(max(0, self.t - self.reward_history_steps), self.t + 1)
        with torch.no_grad():
            reward = float(self.reward_model.step_rewards(window)[0, -1])
        truncated = self.t >= self.end
        return self._observation(), reward, False, truncated, {"step": self.t}

    # ------------------------------------------------------------------ features
    def _observation(self) -> np.ndarray:
        assert self._scenario is not None
        now = self._scenario.time_slice(self.t, self.t + 1)
        state = self._states[0, self.ego, self.t]
        ego = [float(state[2]) / 10.0, float(self.last_action[0]), float(self.last_action[1]),
               (self.t - self.start_index) / self.episode_steps]
        nb, nb_valid = neighbour_features(now, self.num_neighbours, 40.0)
        nb, nb_valid = nb[0, self.ego], nb_valid[0, self.ego]  # (K, 7), (K,)
        neighbours = torch.stack([nb[:, 0] / 20.0, nb[:, 1] / 20.0, nb[:, 2], nb[:, 3], nb[:, 4] / 10.0,
                                  nb_valid.float()], -1) * nb_valid[:, None]
        size = self.map_size_px
        patch = torch.zeros(size * size)
        if now.map is not None and "drivable" in now.map.layers:
            crops = map_crops(now, size_px=size, resolution_m=self.map_resolution_m)
            patch = crops[0, self.ego, now.map.layers.index("drivable")].flatten()
        obs = np.concatenate([np.asarray(ego, np.float32), neighbours.flatten().numpy(), patch.numpy()])
        return np.clip(np.nan_to_num(obs), -OBS_LIMIT, OBS_LIMIT).astype(np.float32)
