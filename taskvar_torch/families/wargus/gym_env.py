"""Gymnasium front end of the Wargus family (paper §3.5).

One environment, stepped through the same pure batched functions as :class:`WargusEnv` with a batch
of one, so that ``WargusGymEnv`` after ``reset(seed=s)`` and ``WargusEnv(num_envs=1, seed=s)``
produce bit-identical trajectories for the same actions.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from taskvar_torch import rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus import render as wargus_render
from taskvar_torch.families.wargus.dynamics import WargusConfig, WargusInstances

_OPTION_KEYS = ("instance", "start")


class WargusGymEnv(gym.Env):
    """Wargus resource gathering (paper §3.5) as a single Gymnasium environment.

    ## Description
    Collect items on a ``size x size`` grid while patrols walk at random, chase the agent once they
    see it (Chebyshev distance ``< sight``) and shoot it within ``shoot_range``. Step order and
    instance semantics: ``taskvar_torch/families/wargus/dynamics.py``.

    ## Action Space
    ``Discrete(8)``: 0 N, 1 NE, 2 E, 3 SE, 4 S, 5 SW, 6 W, 7 NW; ``Discrete(9)`` with ``noop``.

    ## Observation Space
    ``Box(24,)`` float32: own position / (size - 1); nearest item bearing one-hot (8), seen flag,
    offset / sight when seen; the same for the nearest patrol (layout in ``families/wargus/dynamics.py``).
    ``info`` carries the integer state the subtasks read, as :class:`WargusEnv` emits it:
    ``agent_pos``, ``item_seen``, ``patrol_seen``, ``picked`` and the event ``item_lost`` (the step
    lost sight of the item: seen before, not after, nothing picked; ``False`` after a reset).

    ## Starting State
    Agent at a uniform cell (or ``options["start"]``), items elsewhere, patrols out of sight.

    ## Reward
    +1 per item picked.

    ## Episode End
    Terminated when a shot destroys the agent; truncated after ``horizon`` steps.

    ## Arguments
    ``render_mode`` (``None``, ``"ansi"``, ``"rgb_array"``), the :class:`WargusConfig` fields
    (``size``, ``num_patrols``, ``num_items``, ``sight``, ``shoot_range``, ``hit_prob``,
    ``patrol_speed``, ``horizon``, ``noop``) and ``instances`` (``"train"``, ``"test"``,
    ``"nominal"``, a dict or a :class:`WargusInstances`).

    ## Task parameters
    The instance is an integer seed of the item-location and patrol processes. ``reset`` accepts
    ``options={"instance": {"seed": s}, "start": (row, col)}`` to pin the instance and the start
    cell for that episode. The instance is reported in ``info["instance"]`` (with the hidden
    patrol and item positions), never in the observation.

    Examples:
        >>> env = WargusGymEnv(render_mode="ansi")
        >>> obs, info = env.reset(seed=0, options={"instance": {"seed": 7}})
        >>> obs.shape, info["instance"]["seed"]
        ((24,), 7)
    """

    metadata = {"render_modes": list(wargus_render.RENDER_MODES), "render_fps": 8}

    def __init__(
        self,
        render_mode: str | None = None,
        size: int = 32,
        num_patrols: int = 1,
        num_items: int = 1,
        sight: int = 8,
        shoot_range: int = 5,
        hit_prob: float = 1.0,
        patrol_speed: float = 0.8,
        horizon: int = 500,
        noop: bool = False,
        instances: str | WargusInstances | dict = "train",
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}"
            )
        self.render_mode = render_mode
        settings = {
            "size": size,
            "num_patrols": num_patrols,
            "num_items": num_items,
            "sight": sight,
            "shoot_range": shoot_range,
            "hit_prob": hit_prob,
            "patrol_speed": patrol_speed,
            "horizon": horizon,
            "noop": noop,
        }
        gym_checks.check_as_config("wargus", settings, instances)
        self.config = WargusConfig(**settings)
        self.instances = wargus.wargus_instances(instances)
        self.model = wargus.WargusModel(self.config, "cpu")
        self.action_space = gym.spaces.Discrete(self.config.num_actions)
        self.observation_space = gym.spaces.Box(
            low=self.model.obs_low.numpy(),
            high=self.model.obs_high.numpy(),
            shape=(wargus.OBS_DIM,),
            dtype=np.float32,
        )
        self._index = torch.zeros(1, dtype=torch.int64)  # the gym env is sub-environment 0
        self._base_key: torch.Tensor | None = None
        self._episode = -1
        self._state: wargus.WargusState | None = None
        self._item_seen: torch.Tensor | None = None  # (1,) bool at the current state

    def _obs_info(
        self, picked: torch.Tensor, seen_before: torch.Tensor | None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Observation and info at the current state; ``seen_before``: ``item_seen`` before the
        step that led here (``None`` after a reset: no event)."""
        s = self._state
        obs, item_seen, patrol_seen = wargus.observe(self.model, s)
        lost = (
            False
            if seen_before is None
            else bool(wargus.item_lost(seen_before, item_seen, picked)[0])
        )
        self._item_seen = item_seen
        info = {
            "instance": {
                "seed": int(self._iseed[0]),
                "patrol_pos": s.patrols[0].numpy().copy(),
                "item_pos": s.items[0].numpy().copy(),
            },
            wargus.AGENT_POS: tuple(int(v) for v in s.agent[0]),
            wargus.ITEM_SEEN: bool(item_seen[0]),
            wargus.PATROL_SEEN: bool(patrol_seen[0]),
            wargus.PICKED: int(picked[0]),
            wargus.ITEM_LOST: lost,
            "t": int(s.t[0]),
        }
        return obs[0].numpy().copy(), info

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode: the next one of this env's seed stream, or pin it with ``options``.

        Every option is checked before anything changes: a refused reset leaves the env as it was.

        ``seed`` is an integer in ``[0, 2**32 - 1]`` (the keyed streams' 32-bit keys; a larger one
        is a ``ValueError``, never wrapped). Without ``seed`` the first reset draws one from
        Gymnasium's ``np_random`` (entropy), later ones continue that stream, as Gymnasium's own
        envs do: two unseeded envs, or ``gym.make_vec`` sub-envs, play different episodes.
        """
        options = gym_checks.check_reset_options(options, _OPTION_KEYS)
        iseed = None
        if options.get("instance") is not None:
            inst = gym_checks.check_fields(options["instance"], "instance", ("seed",))
            s = gym_checks.as_int(inst.get("seed"))
            if s is None or not 0 <= s <= rng.MASK32:
                raise ValueError(
                    f"instance seed must be an integer in [0, {rng.MASK32}], got {inst.get('seed')!r}"
                )
            iseed = torch.tensor([s], dtype=torch.int64)
        start = None
        if options.get("start") is not None:
            start = gym_checks.check_cell(options["start"], self.config.size, self.config.size)
        seed = None if seed is None else rng.check_seed(seed)
        # every input is valid: only now change the env's state
        super().reset(seed=seed)
        if seed is None and self._base_key is None:  # first reset unseeded: Gymnasium's entropy
            seed = int(self.np_random.integers(0, rng.MAX_SEED + 1))
        if seed is not None:
            self._base_key = rng.sub_env_key(seed, self._index)  # (1,)
            self._episode = 0
        else:
            self._episode += 1
        episode = torch.full((1,), self._episode, dtype=torch.int64)
        ekey = rng.episode_key(self._base_key, episode)  # (1,)
        if iseed is None:
            iseed = self.instances.sample(ekey, self._index, episode)
        self._iseed = iseed
        self._ikey = wargus.instance_key(iseed)
        self._state = wargus.reset(
            self.model,
            self._ikey,
            None if start is None else torch.tensor(start, dtype=torch.int64),
        )
        return self._obs_info(torch.zeros(1, dtype=torch.int64), None)

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One step; ``ValueError`` for an action outside ``[0, num_actions)``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = gym_checks.check_action(action, self.config.num_actions)
        act = torch.tensor([a], dtype=torch.int64)
        self._state, picked, destroyed = wargus.step(self.model, self._state, act, self._ikey)
        terminated = bool(destroyed[0])
        truncated = (not terminated) and int(self._state.t[0]) >= self.config.horizon
        obs, info = self._obs_info(picked, self._item_seen)
        return obs, float(info[wargus.PICKED]), terminated, truncated, info

    def render(self) -> str | np.ndarray | None:
        """Text (``ansi``) or a uint8 (H, W, 3) image (``rgb_array``) of the current state."""
        if self.render_mode is None:
            gym.logger.warn(
                "render() called with render_mode=None; pass render_mode to the constructor"
            )
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        s = self._state
        frame = wargus_render.Frame.from_tensors(
            self.config, s.agent[0], s.patrols[0], s.items[0], int(s.t[0]), int(self._iseed[0])
        )
        return wargus_render.render(frame, self.render_mode)
