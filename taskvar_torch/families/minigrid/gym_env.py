"""One MiniGrid env of the port behind Gymnasium's API (``taskvar/MiniGrid-DoorKey-5x5-v0``, ...).

It steps the batched :class:`~taskvar_torch.families.minigrid.env.MiniGridEnv` with one
sub-environment, so with the same seed its episodes are the batched env's sub-environment 0's.
Its observation is the family's (``encode``: the direction and the view, ``obs_encoding``); the
``info`` dict holds MiniGrid's own ``image`` and ``direction``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from taskvar_torch import keys, rng
from taskvar_torch.families.minigrid import dynamics as D
from taskvar_torch.families.minigrid.env import MiniGridEnv, render_ansi

COLOURS = np.array(
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [112, 39, 195], [255, 255, 0], [100, 100, 100]],
    dtype=np.uint8,
)
"""MiniGrid's colours by index (``minigrid.core.constants.COLORS``)."""
TILE = 16


class MiniGridGymEnv(gym.Env):
    """MiniGrid DoorKey or LavaGap (the port) as a Gymnasium env.

    Args:
        task, size, max_steps, obs_encoding: as :class:`MiniGridEnv`.
        instances: the layouts it draws (default ``minigrid``: MiniGrid's own distribution).
        render_mode: ``ansi`` (MiniGrid's ``pprint_grid`` letters) or ``rgb_array`` (one flat
            tile a cell, the agent a red square).
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 10}

    def __init__(
        self,
        task: str = "doorkey",
        size: int = 5,
        max_steps: int | None = None,
        obs_encoding: str = "onehot",
        instances: str = "minigrid",
        render_mode: str | None = None,
    ):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        self.render_mode = render_mode
        self._env = MiniGridEnv(
            1,
            task=task,
            size=size,
            max_steps=max_steps,
            obs_encoding=obs_encoding,
            instances=instances,
        )
        spec = self._env.observation_spec[keys.OBSERVATION]
        high = float(spec.space.high.max())
        self.observation_space = spaces.Box(0.0, high, (spec.shape[-1],), dtype=np.float32)
        self.action_space = spaces.Discrete(D.NUM_ACTIONS)
        self._seeded = False

    def _obs(self, td: TensorDict) -> tuple[np.ndarray, dict[str, Any]]:
        info = {"image": self._env.image()[0].numpy(), "direction": int(self._env._dir[0])}
        return td[keys.OBSERVATION][0].numpy(), info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or not self._seeded:  # a seed restarts the stream at episode 0
            s = seed if seed is not None else int(self.np_random.integers(0, rng.MAX_SEED + 1))
            self._env.set_seed(rng.check_seed(s))
            self._seeded = True
        return self._obs(self._env.reset())

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action must be in [0, {D.NUM_ACTIONS - 1}], got {action!r}")
        td = TensorDict({keys.ACTION: torch.tensor([int(action)])}, [1])
        nxt = self._env._step(td)  # TorchRL's hook itself: one sub-env needs none of step's checks
        obs, info = self._obs(nxt)
        reward = float(nxt[keys.REWARD][0, 0])
        return obs, reward, bool(nxt[keys.TERMINATED][0]), bool(nxt[keys.TRUNCATED][0]), info

    def render(self):
        env = self._env
        grid, x, y, d = env._grid[0], int(env._x[0]), int(env._y[0]), int(env._dir[0])
        if self.render_mode == "ansi":
            return render_ansi(grid, env.size, x, y, d)
        if self.render_mode == "rgb_array":
            cells = grid.view(env.size, env.size, 3).numpy()
            img = COLOURS[cells[..., 1]] * (cells[..., :1] > D.OBJECT_TO_IDX["empty"])
            img[x, y] = (255, 0, 0)
            img = img.transpose(1, 0, 2).repeat(TILE, 0).repeat(TILE, 1)  # rows are y
            img[::TILE], img[:, ::TILE] = 100, 100  # grid lines
            return np.ascontiguousarray(img, dtype=np.uint8)
        return None
