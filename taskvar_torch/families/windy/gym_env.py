"""Gymnasium ``Env`` for one windy gridworld (for people who live in Gymnasium).

It steps the same lookup tables and keyed random stream as :class:`WindyGridEnv`, so with the same
seed it produces bit-identical trajectories to sub-environment 0 of the TorchRL env.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from taskvar_torch import rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.gym_episodes import EpisodeKeys
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy import render
from taskvar_torch.families.windy.env import _C_START, observation_table, resolve_layout
from taskvar_torch.families.windy.instances import WindyInstances, windy_instances

_OPTION_KEYS = ("instance", "start")


class WindyGridGymEnv(gym.Env):
    """The windy gridworld family (paper §3.3.1) as a single Gymnasium environment.

    ## Description
    Reach any goal cell (``G``) through one of the exits in the wall; wind blows in the cells just
    west of the exits with an unknown direction and strength that are fixed for an episode.

    ## Action Space
    ``Discrete(4)``: 0 north, 1 south, 2 east, 3 west.

    ## Observation Space
    ``Box(0, 1, (D,), float32)``: the one-hot cell (``onehot``) or coordinates and a local patch
    (``coords_patch``). The instance is never in the observation.

    ## Starting State
    A uniformly random start cell ``S`` (or ``options={"start": (row, col)}``).

    ## Reward
    -1 per step.

    ## Episode End
    ``terminated`` on reaching a goal cell, ``truncated`` after ``horizon`` steps.

    ## Arguments
    ``layout`` (name or map string), ``instances`` (``train``/``test``/``south``/``north`` or a
    :class:`WindyInstances`), ``horizon``, ``obs_encoding``, ``patch_radius``, ``render_mode``
    (``ansi`` or ``rgb_array``).

    ## Task parameters
    ``reset(options={"instance": {"p": 0.7, "direction": "north"}})`` pins an instance; ``info``
    reports it as ``info["instance"]``.
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(
        self,
        layout: str | windy.WindyLayout = "default",
        instances: str | WindyInstances | dict = "train",
        horizon: int | None = None,
        obs_encoding: str = "onehot",
        patch_radius: int = 2,
        render_mode: str | None = None,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}"
            )
        gym_checks.check_as_config(
            "windy",
            {
                "layout": "\n".join(layout.rows)
                if isinstance(layout, windy.WindyLayout)
                else layout,
                "horizon": horizon,
                "obs_encoding": obs_encoding,
                "patch_radius": patch_radius,
            },
            instances,
        )
        self.layout = resolve_layout(layout)
        self.model = windy.WindyModel(self.layout, "cpu")
        self.instances = windy_instances(instances)
        self.horizon = int(horizon) if horizon is not None else windy.default_horizon(self.layout)
        self.render_mode = render_mode
        self._obs = observation_table(self.layout, obs_encoding, patch_radius)
        self.observation_space = gym.spaces.Box(0.0, 1.0, (self._obs.shape[1],), np.float32)
        self.action_space = gym.spaces.Discrete(4)
        self._move, self._push = self.model.np_move.tolist(), self.model.np_push.tolist()
        self._goal = self.model.np_is_goal.tolist()
        self._keys = EpisodeKeys()  # seeded at the first reset
        self._cell = int(self.model.np_start_cells[0])
        self._t, self._p, self._dir = 0, np.float32(0.0), 0
        self._key = 0
        self._started = False  # step() before the first reset() is an error

    def _info(self) -> dict[str, Any]:
        return {
            "instance": {"p": float(self._p), "direction": windy.DIRECTIONS[self._dir]},
            "cell": divmod(self._cell, self.layout.width),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``options`` may hold ``instance`` (``p``, ``direction``) and ``start``.

        Every option is checked before anything changes: a refused reset leaves the env (episode
        counter, instance, position, seed) exactly as it was.

        ``seed`` is an integer in ``[0, 2**32 - 1]`` (the keyed streams' 32-bit keys; a larger one
        is a ``ValueError``, never wrapped). Without ``seed`` the first reset draws one from
        Gymnasium's ``np_random`` (entropy), later ones continue that stream, as Gymnasium's own
        envs do: two unseeded envs, or ``gym.make_vec`` sub-envs, play different episodes.
        """
        options = gym_checks.check_reset_options(options, _OPTION_KEYS)
        pinned: dict[str, Any] = {}
        if options.get("instance") is not None:
            inst = gym_checks.check_fields(options["instance"], "instance", ("p", "direction"))
            if "p" in inst:
                pinned["p"] = np.float32(gym_checks.check_probability(inst["p"], "instance p"))
            if "direction" in inst:
                pinned["direction"] = windy.direction_index(inst["direction"])
        start = None
        if options.get("start") is not None:
            H, W = self.layout.height, self.layout.width
            r, c = gym_checks.check_cell(options["start"], H, W)
            if self.layout.rows[r][c] in "#G":
                raise ValueError(
                    f"start must be a free (row, col) cell (not a wall or goal), got {options['start']!r}"
                )
            start = r * W + c
        seed = None if seed is None else rng.check_seed(seed)
        super().reset(seed=seed)
        key = self._keys.next(seed, self.np_random)  # (1,)
        p, d = self.instances.sample(key)
        self._p, self._dir = np.float32(p[0].item()), int(d[0])
        self._p = pinned.get("p", self._p)
        self._dir = pinned.get("direction", self._dir)
        starts = self.model.np_start_cells
        self._cell = int(starts[int(rng.draw_index(key.numpy(), _C_START, len(starts))[0])])
        if start is not None:
            self._cell = start
        self._key = int(key[0])  # python-int hashing is the fastest for a single env
        self._t = 0
        self._started = True
        return self._obs[self._cell].copy(), self._info()

    def step(self, action):
        """Move, then at most one gust; reward -1."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = gym_checks.check_action(action, 4)
        moved = int(self._move[self._cell][a])
        if rng.draw_uniform(self._key, self._t) < self._p:
            moved = int(self._push[moved][self._dir])
        self._cell = moved
        self._t += 1
        terminated = self._goal[moved]
        truncated = self._t >= self.horizon and not terminated
        return self._obs[moved].copy(), -1.0, terminated, truncated, self._info()

    def render(self):
        direction = windy.DIRECTIONS[self._dir]
        if self.render_mode == "ansi":
            return render.windy_ansi(self.layout, self._cell, float(self._p), direction)
        if self.render_mode == "rgb_array":
            return render.windy_rgb(self.layout, self._cell, direction)
        return None
